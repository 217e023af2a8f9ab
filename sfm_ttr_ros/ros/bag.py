"""rosbag2 files without ROS: KITTI drive -> bag, reading bags, recording, evaluating a bag.

Everything here uses only `rosbags <https://gitlab.com/ternaris/rosbags>`_ (pure Python), numpy
and the core, so it runs on machines without a ROS install. Playing a bag into a ROS graph is
:mod:`sfm_ttr_ros.ros.player` (rclpy).

Bags are written as rosbag2 version 9 (what Jazzy writes) with the ``ROS2_JAZZY`` type store of
rosbags: every connection carries its message definition, its RIHS01 type hash (equal to the one
of the Jazzy message packages) and serialization format ``cdr``, so ``ros2 bag play`` /
``ros2 bag info`` on a Jazzy install read them. No offered-QoS metadata is written (an empty
list): ``ros2 bag play`` then publishes with its default profile (reliable, volatile). Both
storage plugins work with rosbags 0.11.9: ``mcap`` (Jazzy's default, the default here) and
``sqlite3``.

KITTI topics (kitti2bag's names, camera 02 = left colour camera):

* ``/kitti/camera_color_left/image_raw``: sensor_msgs/Image ``rgb8``, one per frame, stamped
  with ``image_02/timestamps.txt`` (nanoseconds exactly as written in the file);
* ``/kitti/camera_color_left/camera_info``: sensor_msgs/CameraInfo with the image's stamp,
  from ``P_rect_02`` / ``S_rect_02`` of ``calib_cam_to_cam.txt``
  (see :func:`camera_info_from_calib`);
* ``/kitti/camera_color_left/depth_gt`` (with ground truth): the improved ground truth as REP 118
  ``32FC1`` metres, NaN = no measurement, with the image's stamp, only for the frames that have
  a ground-truth PNG (frames without one are still written as image + camera_info).

All three share frame_id ``camera_color_left``. In the bag, each message's log time is its
header stamp, and per frame camera_info is written first, then the image, then the GT.
"""

from __future__ import annotations

import calendar
import shutil
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

from sfm_ttr_ros.core.evaluation import EvalConfig, Evaluator
from sfm_ttr_ros.core.frames import InputError

IMAGE_MSGTYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_MSGTYPE = "sensor_msgs/msg/CameraInfo"

# kitti2bag's frame ids / topic namespaces per KITTI camera.
KITTI_CAMERA_NAMES = {"02": "camera_color_left", "03": "camera_color_right"}
KITTI_NAMESPACE = "/kitti"
IMAGE_TOPIC = "/kitti/camera_color_left/image_raw"
CAMERA_INFO_TOPIC = "/kitti/camera_color_left/camera_info"
DEPTH_GT_TOPIC = "/kitti/camera_color_left/depth_gt"
DEFAULT_PRED_TOPIC = "/refiner/depth"  # the refiner node's ~/depth
STORAGES = ("mcap", "sqlite3")
BAG_VERSION = 9  # rosbag2 metadata version written by Jazzy

_typestore = None


def typestore():
    """The rosbags type store of ROS 2 Jazzy (created once)."""
    global _typestore
    if _typestore is None:
        from rosbags.typesys import Stores, get_typestore

        _typestore = get_typestore(Stores.ROS2_JAZZY)
    return _typestore


def _storage_plugin(storage: str):
    from rosbags.rosbag2 import StoragePlugin

    s = str(storage).lower()
    if s not in STORAGES:
        raise InputError(f"unknown bag storage {storage!r}: use one of {', '.join(STORAGES)}")
    return StoragePlugin.MCAP if s == "mcap" else StoragePlugin.SQLITE3


# ---------------------------------------------------------------------------------------------
# Small helpers
# ---------------------------------------------------------------------------------------------


def kitti_timestamp_ns(text: str) -> int:
    """``YYYY-MM-DD HH:MM:SS.fffffffff`` (UTC) -> integer nanoseconds since the epoch, exactly
    (a float of seconds since 1970 cannot hold nanoseconds)."""
    from sfm_ttr_ros.data.kitti import parse_kitti_timestamp

    parse_kitti_timestamp(text)  # validates, with the reader's error message
    text = text.strip()
    head, _, frac = text.partition(".")
    secs = calendar.timegm(datetime.strptime(head, "%Y-%m-%d %H:%M:%S").timetuple())
    return secs * 1_000_000_000 + int(frac.ljust(9, "0") if frac else 0)


def stamp_to_ns(stamp) -> int:
    """A builtin_interfaces/Time (anything with ``sec`` and ``nanosec``) -> nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamp_str(ns: int) -> str:
    """Nanoseconds -> ``sec.nanosec`` (9 digits), used as the frame name of a stamp."""
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def _header(ns: int, frame_id: str):
    if ns < 0:
        raise InputError(f"negative stamp {ns} ns cannot be a ROS time")
    T = typestore().types
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000,
                                               nanosec=ns % 1_000_000_000),
        frame_id=str(frame_id),
    )


def make_image_msg(array: np.ndarray, encoding: str, stamp_ns: int, frame_id: str):
    """A rosbags sensor_msgs/Image (unpadded, little-endian) from an array: ``rgb8`` /
    ``bgr8`` need H x W x 3 uint8, ``mono8`` H x W uint8, ``32FC1`` H x W float (sent as
    float32)."""
    a = np.asarray(array)
    layouts = {"rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "mono8": (np.uint8, 1),
               "32FC1": (np.float32, 1)}
    if encoding not in layouts:
        raise InputError(f"cannot write encoding {encoding!r}: use one of {', '.join(layouts)}")
    dtype, ch = layouts[encoding]
    if (a.ndim != (3 if ch > 1 else 2) or (ch > 1 and a.shape[2] != ch)
            or a.shape[0] == 0 or a.shape[1] == 0):
        raise InputError(f"{encoding} needs an H x W{' x 3' if ch > 1 else ''} array, "
                         f"got {a.shape}")
    if dtype is np.uint8 and a.dtype != np.uint8:
        raise InputError(f"{encoding} needs uint8, got {a.dtype}")
    if dtype is np.float32 and not np.issubdtype(a.dtype, np.floating):
        raise InputError(f"{encoding} needs a floating array, got {a.dtype}")
    le = np.ascontiguousarray(a, dtype=np.dtype(dtype).newbyteorder("<"))
    h, w = int(a.shape[0]), int(a.shape[1])
    return typestore().types[IMAGE_MSGTYPE](
        header=_header(stamp_ns, frame_id), height=h, width=w, encoding=encoding,
        is_bigendian=0, step=w * ch * np.dtype(dtype).itemsize,
        data=le.view(np.uint8).reshape(-1))


def depth_msg(depth_m: np.ndarray, stamp_ns: int, frame_id: str):
    """REP 118 depth: 32FC1 metres, NaN where the depth is not finite or <= 0."""
    d = np.asarray(depth_m, dtype=np.float32).copy()
    if d.ndim != 2:
        raise InputError(f"depth must be H x W, got shape {d.shape}")
    with np.errstate(invalid="ignore"):
        d[~(np.isfinite(d) & (d > 0))] = np.nan
    return make_image_msg(d, "32FC1", stamp_ns, frame_id)


def camera_info_from_calib(calib: dict, cam: str, stamp_ns: int, frame_id: str):
    """A rosbags sensor_msgs/CameraInfo for the rectified images of KITTI camera ``cam``.

    The ``_sync`` images are already rectified, so the message describes a distortion-free
    pinhole camera: width x height = ``S_rect_<cam>``; P = ``P_rect_<cam>`` as it is (including
    its 4th column, the offset ``fx * tx`` to camera 00, as kitti2bag writes it); K = the left
    3x3 block of P, i.e. fx, fy, cx, cy of P_rect; D = five zeros with ``plumb_bob``; R = identity
    (not ``R_rect_00``: R is the rotation that rectifies the *raw* image, and applying R_rect to
    an already rectified image would rotate it a second time; image_geometry with D = 0, R = I,
    K = P[:3, :3] leaves the image as it is).
    """
    from sfm_ttr_ros.data.kitti import kitti_intrinsics

    intr = kitti_intrinsics(calib, cam)  # validates P_rect and S_rect
    P = np.asarray(calib[f"P_rect_{cam}"], dtype=np.float64).reshape(3, 4)
    K = P[:, :3].copy()
    K[0, 1] = 0.0  # P_rect has no skew; keep K a clean pinhole matrix
    return typestore().types[CAMERA_INFO_MSGTYPE](
        header=_header(stamp_ns, frame_id),
        height=intr.height, width=intr.width, distortion_model="plumb_bob",
        d=np.zeros(5, np.float64), k=K.reshape(-1), r=np.eye(3).reshape(-1), p=P.reshape(-1),
        binning_x=0, binning_y=0,
        roi=typestore().types["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def serialize(msg, msgtype: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, msgtype))


class ProgressBar:
    """A text progress bar on stderr (no dependency): redrawn in place on a terminal at most
    every 0.2 s; one line per 10 % otherwise (logs, CI)."""

    def __init__(self, total: int, label: str = "", enabled: bool = True, stream=None,
                 width: int = 30) -> None:
        self.total = max(0, int(total))
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = bool(enabled)
        self.width = width
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.done = 0
        self.extra = ""
        self._last_draw = 0.0
        self._last_decile = -1
        self._drawn: tuple[int, str] | None = None

    def update(self, done: int, extra: str = "", force: bool = False) -> None:
        self.done, self.extra = int(done), extra
        if not self.enabled:
            return
        frac = min(1.0, self.done / self.total) if self.total else 1.0
        if self.tty:
            now = time.monotonic()
            if not force and now - self._last_draw < 0.2:
                return
            self._last_draw = now
            bar = "#" * int(round(frac * self.width))
            self.stream.write(f"\r{self.label} [{bar:<{self.width}}] {self.done}/{self.total} "
                              f"{extra}\x1b[K")
        else:
            decile = int(frac * 10)
            if (decile == self._last_decile and not force) or self._drawn == (self.done, extra):
                return
            self._last_decile = decile
            self.stream.write(f"{self.label} {self.done}/{self.total} ({100 * frac:.0f}%) "
                              f"{extra}\n")
        self._drawn = (self.done, extra)
        self.stream.flush()

    def close(self) -> None:
        """Draw the final state (and end the terminal line)."""
        if not self.enabled:
            return
        self.update(self.done, self.extra, force=True)
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------


class BagRecorder:
    """A rosbag2 writer for serialized (CDR) messages.

    Use it from one thread: the sqlite3 storage refuses calls from any thread but the one that
    created it (:class:`sfm_ttr_ros.ros.player.TopicRecorder` opens, writes and closes it in its
    spinning thread). Writes after :meth:`close` are ignored.

    Topics are added with their message type (``sensor_msgs/msg/Image``); messages are written
    as raw CDR bytes (:meth:`write_raw`, what an rclpy subscription with ``raw=True`` receives,
    see :class:`sfm_ttr_ros.ros.player.TopicRecorder`) or as rosbags message objects
    (:meth:`write`). The output folder must not exist. Use as a context manager, or call
    :meth:`close` (which writes ``metadata.yaml``; a bag without it cannot be read).
    """

    def __init__(self, path: str | Path, storage: str = "mcap") -> None:
        from rosbags.rosbag2 import Writer, WriterError

        self.path = Path(path)
        plugin = _storage_plugin(storage)
        self.storage = str(storage).lower()
        if self.path.exists():
            raise InputError(f"bag output {self.path} exists already: choose another --out or "
                             "delete it")
        try:
            self._writer = Writer(self.path, version=BAG_VERSION, storage_plugin=plugin)
            self._writer.open()
        except (WriterError, OSError) as exc:
            raise InputError(f"cannot create bag {self.path}: {exc}") from exc
        self._connections: dict[str, object] = {}
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.closed = False

    def add_topic(self, topic: str, msgtype: str) -> None:
        """Declare ``topic`` with ``msgtype`` (must be a ROS 2 Jazzy type known to rosbags)."""
        with self._lock:
            if topic in self._connections:
                if self._connections[topic].msgtype != msgtype:
                    raise InputError(f"topic {topic} already recorded as "
                                     f"{self._connections[topic].msgtype}, not {msgtype}")
                return
            if msgtype not in typestore().types:
                raise InputError(f"unknown message type {msgtype!r} for {topic} (not in the "
                                 "ROS 2 Jazzy type store)")
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=typestore())
            self.counts[topic] += 0

    @property
    def topics(self) -> dict[str, str]:
        return {t: c.msgtype for t, c in self._connections.items()}

    def write_raw(self, topic: str, data: bytes | memoryview, log_time_ns: int) -> None:
        """Write one serialized message (CDR bytes) with log time ``log_time_ns``."""
        with self._lock:
            if self.closed:
                return  # late callbacks after close are dropped (the bag is final)
            conn = self._connections.get(topic)
            if conn is None:
                raise InputError(f"topic {topic} was not added to the recorder")
            self._writer.write(conn, int(log_time_ns), data)
            self.counts[topic] += 1

    def write(self, topic: str, msg, log_time_ns: int | None = None) -> None:
        """Write a rosbags message object; log time = its header stamp unless given."""
        conn = self._connections.get(topic)
        if conn is None:
            raise InputError(f"topic {topic} was not added to the recorder")
        if log_time_ns is None:
            log_time_ns = stamp_to_ns(msg.header.stamp)
        self.write_raw(topic, serialize(msg, conn.msgtype), log_time_ns)

    def close(self) -> None:
        with self._lock:
            if not self.closed:
                self.closed = True
                self._writer.close()

    def abort(self) -> None:
        """Close and delete the (partial) bag."""
        with self._lock:
            if not self.closed:
                self.closed = True
                try:
                    self._writer.close()
                except Exception:  # noqa: BLE001 - the folder is removed anyway
                    pass
        shutil.rmtree(self.path, ignore_errors=True)

    def __enter__(self) -> BagRecorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


@dataclass
class ConvertResult:
    path: Path
    storage: str
    drive: str
    frames: int
    gt_frames: int
    counts: dict[str, int]
    width: int
    height: int
    start_ns: int
    end_ns: int
    seconds: float


def _drive_stamps_ns(drive) -> list[int]:
    """Per frame of a :class:`~sfm_ttr_ros.data.kitti.KittiDrive`, its stamp in integer ns: read
    from ``timestamps.txt`` (line = frame number) as KittiDrive does, or its 10 Hz fallback."""
    if not drive.stamps_from_file:
        return [round(s * 1e9) for s in drive.stamps]
    ts_path = drive.drive_dir / f"image_{drive.camera}" / "timestamps.txt"
    lines = [ln for ln in ts_path.read_text().splitlines() if ln.strip()]
    out = []
    for name in drive.frame_names:  # KittiDrive already checked every frame has a line
        out.append(kitti_timestamp_ns(lines[int(name)]))
    return out


def kitti_to_bag(
    raw_root: str | Path,
    drive: str,
    out: str | Path,
    gt_root: str | Path | None = None,
    storage: str = "mcap",
    *,
    camera: str = "02",
    start: int = 0,
    max_frames: int = 0,
    progress: bool = False,
) -> ConvertResult:
    """Convert a KITTI raw drive (``raw_root/<date>/<drive>``) into the rosbag2 folder ``out``.

    Topics and conventions: see the module docstring. ``gt_root`` (the depth benchmark root,
    ``{train,val}/<drive>/proj_depth/groundtruth``) adds the improved ground truth; it is an
    error when that root has no ground truth for the drive. ``start`` / ``max_frames`` (0 = all)
    select a range of frames. Frames are read and written one at a time. Raises
    :class:`InputError` for a missing drive / calibration / GT, an image whose size is not
    ``S_rect``, or an existing ``out``; a failed conversion leaves no partial bag behind.
    """
    from sfm_ttr_ros.data.kitti import KittiDrive

    if camera not in KITTI_CAMERA_NAMES:
        raise InputError(f"camera must be one of {', '.join(KITTI_CAMERA_NAMES)} (colour), "
                         f"got {camera!r}")
    _storage_plugin(storage)
    if start < 0 or max_frames < 0:
        raise InputError(f"start and max_frames must be >= 0, got {start}, {max_frames}")
    kd = KittiDrive(raw_root, drive, gt_root=gt_root, camera=camera)
    if gt_root is not None and kd.gt_dir is None:
        raise InputError(f"no ground truth for {drive} under {gt_root}: expected "
                         f"{gt_root}/{{train,val}}/{drive}/proj_depth/groundtruth/image_{camera}")
    stop = len(kd) if max_frames == 0 else min(len(kd), start + max_frames)
    if start >= stop:
        raise InputError(f"no frames selected: start={start}, drive has {len(kd)} frames")
    stamps = _drive_stamps_ns(kd)
    name = KITTI_CAMERA_NAMES[camera]
    frame_id = name
    ns = f"{KITTI_NAMESPACE}/{name}"
    topics = {"image": f"{ns}/image_raw", "info": f"{ns}/camera_info", "gt": f"{ns}/depth_gt"}
    intr = kd.intrinsics

    t0 = time.perf_counter()
    gt_frames = 0
    bar = ProgressBar(stop - start, f"kitti-to-bag {drive}", enabled=progress)
    rec = BagRecorder(out, storage)
    try:
        rec.add_topic(topics["image"], IMAGE_MSGTYPE)
        rec.add_topic(topics["info"], CAMERA_INFO_MSGTYPE)
        if kd.gt_dir is not None:
            rec.add_topic(topics["gt"], IMAGE_MSGTYPE)
        for k, i in enumerate(range(start, stop)):
            st = stamps[i]
            rgb = kd.load_image(i)
            if rgb.shape[:2] != (intr.height, intr.width):
                raise InputError(
                    f"{kd.image_path(i)} is {rgb.shape[1]}x{rgb.shape[0]} but S_rect_{camera} "
                    f"of {kd.calib_path} says {intr.width}x{intr.height}")
            rec.write(topics["info"], camera_info_from_calib(kd.calib, camera, st, frame_id))
            rec.write(topics["image"], make_image_msg(rgb, "rgb8", st, frame_id))
            gt = kd.load_gt(i)
            if gt is not None:
                if gt.shape != rgb.shape[:2]:
                    raise InputError(f"ground truth {kd.gt_path(i)} is {gt.shape[1]}x"
                                     f"{gt.shape[0]}, its image {rgb.shape[1]}x{rgb.shape[0]}")
                rec.write(topics["gt"], depth_msg(gt, st, frame_id))
                gt_frames += 1
            bar.update(k + 1, f"GT {gt_frames}")
    except BaseException:
        rec.abort()
        bar.close()
        raise
    rec.close()
    bar.close()
    return ConvertResult(
        path=Path(out), storage=rec.storage, drive=drive, frames=stop - start,
        gt_frames=gt_frames, counts=dict(rec.counts), width=intr.width, height=intr.height,
        start_ns=stamps[start], end_ns=stamps[stop - 1], seconds=time.perf_counter() - t0)


# ---------------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------------


@dataclass
class BagTopic:
    topic: str
    msgtype: str
    count: int


def _open_reader(path: str | Path):
    from rosbags.highlevel import AnyReader

    path = Path(path)
    if not path.exists():
        raise InputError(f"bag not found: {path}")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise InputError(f"{path} is not a rosbag2 folder (no metadata.yaml): an unfinished "
                         "recording, or not a bag")
    try:
        reader = AnyReader([path], default_typestore=typestore())
        reader.open()
    except Exception as exc:  # rosbags raises several error types for unreadable bags
        raise InputError(f"cannot read bag {path}: {type(exc).__name__}: {exc}") from exc
    return reader


def bag_topics(path: str | Path) -> dict[str, BagTopic]:
    """Topic -> (msgtype, message count) of a bag."""
    reader = _open_reader(path)
    try:
        return {t: BagTopic(t, info.msgtype or "", int(info.msgcount))
                for t, info in reader.topics.items()}
    finally:
        reader.close()


def _select(reader, path, topics: Iterable[str] | None) -> list:
    if topics is None:
        return list(reader.connections)
    topics = list(topics)
    have = {c.topic for c in reader.connections}
    missing = [t for t in topics if t not in have]
    if missing:
        raise InputError(f"topic(s) {', '.join(missing)} not in bag {path}; it has: "
                         f"{', '.join(sorted(have)) or 'no topics'}")
    return [c for c in reader.connections if c.topic in set(topics)]


def header_stamp_ns(msg, default: int) -> int:
    """The header stamp of ``msg`` in ns when it has one, else ``default``."""
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None or not hasattr(stamp, "sec"):
        return int(default)
    return stamp_to_ns(stamp)


def read_bag(path: str | Path, topics: Iterable[str] | None = None,
             start_ns: int | None = None, stop_ns: int | None = None
             ) -> Iterator[tuple[str, str, int, object]]:
    """Messages of a bag in log-time order: ``(topic, msgtype, stamp_ns, msg)``.

    ``stamp_ns`` is the message's header stamp when it has a header, else its log time; ``msg``
    is the deserialized rosbags message (attributes as in ROS: ``msg.header.stamp.sec``,
    ``msg.data`` a numpy uint8 array, ...). ``topics`` restricts to those topics (an unknown one
    is an :class:`InputError`); ``start_ns`` / ``stop_ns`` restrict the log time.
    """
    reader = _open_reader(path)
    try:
        conns = _select(reader, path, topics)
        if not conns:
            return
        for conn, t, raw in reader.messages(connections=conns, start=start_ns, stop=stop_ns):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:
                raise InputError(f"cannot decode a {conn.msgtype} message on {conn.topic} in "
                                 f"{path} (log time {t}): {exc}") from exc
            yield conn.topic, conn.msgtype, header_stamp_ns(msg, t), msg
    finally:
        reader.close()


def image_msg_to_array(msg) -> np.ndarray:
    """Decode a sensor_msgs/Image read from a bag (uses :func:`msg_adapters.image_to_numpy`,
    which reads any object with height/width/encoding/step/is_bigendian/data; importing
    msg_adapters needs the ROS 2 message packages)."""
    try:
        from msg_adapters.image import image_to_numpy
    except ImportError as exc:  # pragma: no cover - ROS message packages missing
        raise InputError(f"decoding images needs the ROS 2 message packages "
                         f"(pip install ros-jazzy-common-interfaces): {exc}") from exc
    return image_to_numpy(msg)


def image_msg_to_depth(msg) -> np.ndarray:
    """A depth Image -> float32 metres (NaN / 0 = none): ``32FC1`` (metres, REP 118) or
    ``16UC1`` / ``mono16`` (millimetres, REP 118; 0 becomes NaN)."""
    enc = str(msg.encoding)
    a = image_msg_to_array(msg)
    if enc.upper() == "32FC1":
        return a.astype(np.float32, copy=False)
    if enc.upper() == "16UC1" or enc == "mono16":
        d = a.astype(np.float32) / 1000.0
        d[a == 0] = np.nan
        return d
    raise InputError(f"a depth image must be 32FC1 (metres) or 16UC1 (millimetres), got "
                     f"encoding {enc!r}")


# ---------------------------------------------------------------------------------------------
# Evaluation
# ---------------------------------------------------------------------------------------------


def _stamp_index(path: Path, topic: str) -> tuple[dict[int, int], int]:
    """header stamp -> log time of the first message with it; number of repeated stamps."""
    index: dict[int, int] = {}
    dupes = 0
    reader = _open_reader(path)
    try:
        conns = _select(reader, path, [topic])
        for conn, t, raw in reader.messages(connections=conns):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:
                raise InputError(f"cannot decode a message on {topic} in {path}: {exc}") from exc
            st = header_stamp_ns(msg, t)
            if st in index:
                dupes += 1
            else:
                index[st] = t
    finally:
        reader.close()
    return index, dupes


def _check_image_topic(path: Path, topic: str) -> None:
    topics = bag_topics(path)
    if topic not in topics:
        raise InputError(f"topic {topic} not in bag {path}; it has: "
                         f"{', '.join(sorted(topics)) or 'no topics'}")
    if topics[topic].msgtype != IMAGE_MSGTYPE:
        raise InputError(f"topic {topic} in {path} is {topics[topic].msgtype}, not "
                         f"{IMAGE_MSGTYPE}")


def evaluate_bag(
    pred_bag: str | Path,
    gt_bag: str | Path | None = None,
    pred_topic: str = DEFAULT_PRED_TOPIC,
    gt_topic: str = DEPTH_GT_TOPIC,
    config: EvalConfig | None = None,
    progress: bool = False,
) -> dict:
    """KITTI metrics of the depth images on ``pred_topic`` of ``pred_bag`` against the ground
    truth on ``gt_topic`` of ``gt_bag`` (default: the same bag), matched by header stamp
    (exact nanoseconds).

    Both topics hold depth Images (32FC1 metres, NaN = none; 16UC1 millimetres also read). The
    ground truth is read one frame at a time (indexed by stamp first), so memory stays at one
    frame per side. Returns :meth:`Evaluator.summary` (frame names are ``sec.nanosec``) plus
    ``pred_frames`` / ``gt_frames`` (distinct stamps), ``missing_gt`` (predictions without GT),
    ``missing_pred`` (GT frames without a prediction), the stamps of both in
    ``missing_gt_stamps`` / ``missing_pred_stamps``, and ``duplicate_pred`` / ``duplicate_gt``
    (messages repeating a stamp: only the first one counts).
    """
    pred_bag = Path(pred_bag)
    gt_bag = pred_bag if gt_bag is None else Path(gt_bag)
    _check_image_topic(pred_bag, pred_topic)
    _check_image_topic(gt_bag, gt_topic)
    gt_index, dup_gt = _stamp_index(gt_bag, gt_topic)
    pred_index, dup_pred = _stamp_index(pred_bag, pred_topic)
    matched = sorted(set(gt_index) & set(pred_index))

    evaluator = Evaluator(config or EvalConfig())
    bar = ProgressBar(len(matched), "evaluate", enabled=progress)
    gt_reader = _open_reader(gt_bag)
    seen: set[int] = set()
    try:
        gt_conns = _select(gt_reader, gt_bag, [gt_topic])
        for topic, _, st, msg in read_bag(pred_bag, [pred_topic]):
            del topic
            if st not in gt_index or st in seen:
                continue
            seen.add(st)
            pred = image_msg_to_depth(msg)
            t = gt_index[st]
            gt = None
            for conn, _t, raw in gt_reader.messages(connections=gt_conns, start=t, stop=t + 1):
                gmsg = gt_reader.deserialize(raw, conn.msgtype)
                if header_stamp_ns(gmsg, _t) == st:
                    gt = image_msg_to_depth(gmsg)
                    break
            if gt is None:  # pragma: no cover - the index was built from this very bag
                raise InputError(f"ground truth for stamp {stamp_str(st)} vanished from {gt_bag}")
            evaluator.add(stamp_str(st), pred, np.where(np.isfinite(gt), gt, 0.0))
            bar.update(len(seen))
    finally:
        gt_reader.close()
        bar.close()
    out = evaluator.summary()
    missing_gt = sorted(set(pred_index) - set(gt_index))
    missing_pred = sorted(set(gt_index) - set(pred_index))
    out.update({
        "pred_bag": str(pred_bag), "gt_bag": str(gt_bag),
        "pred_topic": pred_topic, "gt_topic": gt_topic,
        "pred_frames": len(pred_index), "gt_frames": len(gt_index), "matched": len(matched),
        "missing_gt": len(missing_gt), "missing_pred": len(missing_pred),
        "missing_gt_stamps": [stamp_str(s) for s in missing_gt],
        "missing_pred_stamps": [stamp_str(s) for s in missing_pred],
        "duplicate_pred": dup_pred, "duplicate_gt": dup_gt,
    })
    return out


__all__ = [
    "CAMERA_INFO_TOPIC", "DEFAULT_PRED_TOPIC", "DEPTH_GT_TOPIC", "IMAGE_TOPIC", "STORAGES",
    "BagRecorder", "ConvertResult", "ProgressBar", "bag_topics", "camera_info_from_calib",
    "depth_msg", "evaluate_bag", "image_msg_to_array", "image_msg_to_depth", "kitti_to_bag",
    "kitti_timestamp_ns", "make_image_msg", "read_bag", "stamp_str", "stamp_to_ns",
]

