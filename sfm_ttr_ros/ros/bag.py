"""rosbag2 files without ROS: the type store, writing (:class:`BagRecorder`), reading
(:func:`read_bag`, :func:`bag_topics`), Image messages for bags, a text progress bar.

Everything here uses only `rosbags <https://gitlab.com/ternaris/rosbags>`_ (pure Python), numpy,
the core and msg_adapters (which builds and reads every message; the rosbags classes come from
:func:`message_classes`), so it runs on machines without a ROS install. Playing a bag into a
ROS graph is :mod:`sfm_ttr_ros.ros.player` (rclpy); a KITTI drive becomes a bag in
:mod:`sfm_ttr_ros.ros.kitti_bag`; a bag of predicted depth is scored in
:mod:`sfm_ttr_ros.ros.bag_evaluation`.

Bags are written as rosbag2 version 9 (what Jazzy writes) with the ``ROS2_JAZZY`` type store of
rosbags: every connection carries its message definition, its RIHS01 type hash (equal to the one
of the Jazzy message packages) and serialization format ``cdr``, so ``ros2 bag play`` /
``ros2 bag info`` on a Jazzy install read them. No offered-QoS metadata is written (an empty
list): ``ros2 bag play`` then publishes with its default profile (reliable, volatile). Both
storage plugins work with rosbags 0.11.9: ``mcap`` (Jazzy's default, the default here) and
``sqlite3``.
"""

from __future__ import annotations

import functools
import shutil
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msg_adapters.classes import MessageClasses, make_header, typestore_classes
from msg_adapters.image import depth_to_image, numpy_to_image
from msg_adapters.stamp import NS_PER_S, stamp_to_ns
from sfm_ttr_ros.core.errors import InputError

IMAGE_MSGTYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_MSGTYPE = "sensor_msgs/msg/CameraInfo"
STORAGES = ("mcap", "sqlite3")
BAG_VERSION = 9  # rosbag2 metadata version written by Jazzy


@functools.cache
def typestore():
    """The rosbags type store of ROS 2 Jazzy (created once)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


@functools.cache
def message_classes() -> MessageClasses:
    """The message classes of :func:`typestore`, for the builders of msg_adapters."""
    return typestore_classes(typestore())


def storage_plugin(storage: str):
    """The rosbags StoragePlugin of ``storage`` (one of :data:`STORAGES`; else InputError)."""
    from rosbags.rosbag2 import StoragePlugin

    s = str(storage).lower()
    if s not in STORAGES:
        raise InputError(f"unknown bag storage {storage!r}: use one of {', '.join(STORAGES)}")
    return StoragePlugin.MCAP if s == "mcap" else StoragePlugin.SQLITE3




# ---------------------------------------------------------------------------------------------
# Messages for bags
# ---------------------------------------------------------------------------------------------


def bag_rgb(msg) -> np.ndarray:
    """The RGB pixels of a bag's Image or CompressedImage message."""
    from msg_adapters.compressed import compressed_to_rgb8
    from msg_adapters.image import image_to_rgb8

    return compressed_to_rgb8(msg) if hasattr(msg, "format") else image_to_rgb8(msg)


def stamp_str(ns: int) -> str:
    """Nanoseconds -> ``sec.nanosec`` (9 digits), used as the frame name of a stamp."""
    return f"{ns // NS_PER_S}.{ns % NS_PER_S:09d}"


def make_image_msg(array: np.ndarray, encoding: str, stamp_ns: int, frame_id: str):
    """A rosbags sensor_msgs/Image (unpadded, little-endian) from an array
    (:func:`msg_adapters.image.numpy_to_image`): e.g. ``rgb8`` / ``bgr8`` need H x W x 3 uint8,
    ``mono8`` H x W uint8, ``32FC1`` H x W float (sent as float32)."""
    c = message_classes()
    return numpy_to_image(array, encoding, make_header(stamp_ns, frame_id, c), classes=c)


def depth_msg(depth_m: np.ndarray, stamp_ns: int, frame_id: str):
    """A rosbags REP 118 depth Image (:func:`msg_adapters.image.depth_to_image`): 32FC1 metres,
    NaN where the depth is not finite or <= 0."""
    c = message_classes()
    return depth_to_image(depth_m, make_header(stamp_ns, frame_id, c), classes=c)


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
        plugin = storage_plugin(storage)
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

# Reading
# ---------------------------------------------------------------------------------------------


@dataclass
class BagTopic:
    topic: str
    msgtype: str
    count: int


def open_reader(path: str | Path):
    """An opened rosbags AnyReader of the bag folder ``path`` (close it); InputError when the
    folder is missing, unfinished (no metadata.yaml) or unreadable."""
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
    reader = open_reader(path)
    try:
        return {t: BagTopic(t, info.msgtype or "", int(info.msgcount))
                for t, info in reader.topics.items()}
    finally:
        reader.close()


def select_connections(reader, path, topics: Iterable[str] | None) -> list:
    """The connections of ``reader`` on ``topics`` (all when None); InputError naming the bag's
    topics when one is missing."""
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
    reader = open_reader(path)
    try:
        conns = select_connections(reader, path, topics)
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


__all__ = [
    "BAG_VERSION", "CAMERA_INFO_MSGTYPE", "IMAGE_MSGTYPE", "STORAGES", "BagRecorder", "BagTopic",
    "ProgressBar", "bag_topics", "depth_msg", "header_stamp_ns", "make_image_msg",
    "message_classes", "open_reader", "read_bag", "select_connections", "serialize", "stamp_str",
    "storage_plugin", "typestore",
]
