"""A recorded rosbag2 as a sequence to benchmark or refine offline: :func:`bag_sequence`.

The bag holds what the refiner node subscribes to: an image topic (sensor_msgs/Image, or
CompressedImage on ``<image>/compressed``) and its CameraInfo, optionally a depth ground-truth
topic (32FC1 metres, REP 118; ``sfm-ttr kitti-to-bag`` writes one). The frames are decoded once
into a folder (lossless PNG, the ground truth as KITTI's uint16 PNG, metres x 256) and returned
as an :class:`~sfm_ttr_ros.data.sequence.ImageSequence` with the bag's header stamps, so every
offline tool reads a bag as it reads an image folder.

Default topics, when none is given: the node's own ``/image`` (or ``/image/compressed``), else
the KITTI bag's ``/kitti/camera_color_left/image_raw`` (or its ``/compressed``), else the only
colour image topic of the bag; the CameraInfo beside the image (``<namespace>/camera_info``); the
ground truth ``<namespace>/depth_gt`` when the bag has it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from msg_adapters.camera_info import camera_info_to_intrinsics
from msg_adapters.compressed import compressed_to_rgb8
from msg_adapters.image import image_to_depth, image_to_rgb8
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.data.kitti import KITTI_DEPTH_SCALE, write_depth_png
from sfm_ttr_ros.data.sequence import ImageSequence
from sfm_ttr_ros.ros import names
from sfm_ttr_ros.ros.bag import CAMERA_INFO_MSGTYPE, IMAGE_MSGTYPE, bag_topics, read_bag
from sfm_ttr_ros.ros.kitti_bag import COMPRESSED_IMAGE_MSGTYPE, IMAGE_TOPIC

IMAGE_TYPES = (IMAGE_MSGTYPE, COMPRESSED_IMAGE_MSGTYPE)


def _namespace(image_topic: str) -> str:
    base = image_topic[:-len(names.COMPRESSED_SUFFIX)] if image_topic.endswith(
        names.COMPRESSED_SUFFIX) else image_topic
    return base.rpartition("/")[0]


def default_topics(topics: dict, image: str | None = None, camera_info: str | None = None,
                   gt: str | None = None) -> tuple[str, str, str | None]:
    """(image, camera_info, ground truth or None) of a bag with ``topics`` (topic ->
    :class:`~sfm_ttr_ros.ros.bag.BagTopic`), the given ones kept (module docstring)."""
    have = sorted(topics)
    if image is None:
        node_image = names.resolve(names.IMAGE_TOPIC)
        candidates = [t for base in (node_image, IMAGE_TOPIC)
                      for t in (base, names.compressed_topic(base))]
        image = next((t for t in candidates if t in topics), None)
        if image is None:
            colour = [t for t in have if topics[t].msgtype in IMAGE_TYPES and "depth" not in t]
            if len(colour) != 1:
                raise InputError(f"cannot tell the image topic of the bag (give image=TOPIC): "
                                 f"its image topics are {', '.join(colour) or 'none'}")
            image = colour[0]
    if image not in topics:
        raise InputError(f"image topic {image} not in the bag; it has: {', '.join(have)}")
    if topics[image].msgtype not in IMAGE_TYPES:
        raise InputError(f"topic {image} is {topics[image].msgtype}, not an image")
    ns = _namespace(image)
    if camera_info is None:
        camera_info = f"{ns}/camera_info"
    if camera_info not in topics or topics[camera_info].msgtype != CAMERA_INFO_MSGTYPE:
        raise InputError(f"no CameraInfo topic {camera_info} in the bag (give camera_info="
                         f"TOPIC); it has: {', '.join(have)}")
    if gt is None:
        gt = f"{ns}/depth_gt" if f"{ns}/depth_gt" in topics else None
    elif gt not in topics:
        raise InputError(f"ground-truth topic {gt} not in the bag; it has: {', '.join(have)}")
    return image, camera_info, gt


def bag_sequence(bag: str | Path, folder: str | Path, image_topic: str | None = None,
                 camera_info_topic: str | None = None, gt_topic: str | None = None,
                 name: str | None = None) -> tuple[ImageSequence, dict[str, int]]:
    """(sequence, counts): the frames of ``bag`` decoded into ``folder`` (``images/``,
    ``gt/``) as an :class:`ImageSequence` named ``name`` (default: the bag's folder name),
    frames in log-time order named by their index, stamps the images' header stamps; ground
    truth matched to an image by exact stamp. Repeated image stamps keep the first image;
    ``counts`` says how many images were so skipped and how many ground-truth messages had no
    image. :class:`InputError` for an unreadable bag, missing topics, a CameraInfo that
    changes or does not fit the images, or a bag without images."""
    bag = Path(bag)
    topics = bag_topics(bag)
    image_topic, camera_info_topic, gt_topic = default_topics(
        topics, image_topic, camera_info_topic, gt_topic)
    folder = Path(folder)
    img_dir, gt_dir = folder / "images", folder / "gt"
    img_dir.mkdir(parents=True, exist_ok=True)
    wanted = [image_topic, camera_info_topic] + ([gt_topic] if gt_topic else [])
    intrinsics = None
    paths: list[Path] = []
    stamps: list[int] = []
    by_stamp: dict[int, str] = {}
    gt_pending: dict[int, np.ndarray] = {}
    duplicates = 0
    for topic, msgtype, stamp, msg in read_bag(bag, wanted):
        if topic == camera_info_topic:
            k = camera_info_to_intrinsics(msg)
            if intrinsics is None:
                intrinsics = k
            elif k != intrinsics:
                raise InputError(f"{bag}: the CameraInfo on {topic} changes within the bag "
                                 f"({intrinsics} then {k}): one camera per sequence")
        elif topic == image_topic:
            if stamp in by_stamp:
                duplicates += 1
                continue
            rgb = compressed_to_rgb8(msg) if msgtype == COMPRESSED_IMAGE_MSGTYPE \
                else image_to_rgb8(msg)
            frame = f"{len(paths):010d}"
            path = img_dir / f"{frame}.png"
            if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
                raise InputError(f"cannot write {path}")
            paths.append(path)
            stamps.append(stamp)
            by_stamp[stamp] = frame
        else:
            gt_pending.setdefault(stamp, image_to_depth(msg))
    if not paths:
        raise InputError(f"{bag}: no message on the image topic {image_topic}")
    if intrinsics is None:
        raise InputError(f"{bag}: no message on the CameraInfo topic {camera_info_topic}")
    first = cv2.imread(str(paths[0]), cv2.IMREAD_UNCHANGED)
    if (first.shape[1], first.shape[0]) != (intrinsics.width, intrinsics.height):
        raise InputError(f"{bag}: images are {first.shape[1]}x{first.shape[0]}, the CameraInfo "
                         f"says {intrinsics.width}x{intrinsics.height}")
    gt_paths: dict[str, Path] = {}
    for stamp, depth in gt_pending.items():
        frame = by_stamp.get(stamp)
        if frame is not None:
            gt_paths[frame] = gt_dir / f"{frame}.png"
            write_depth_png(gt_paths[frame], depth, KITTI_DEPTH_SCALE)
    seq = ImageSequence(name or bag.name, paths, intrinsics, [s * 1e-9 for s in stamps],
                        gt_paths, KITTI_DEPTH_SCALE)
    return seq, {"duplicate_image_stamps": duplicates,
                 "gt_without_image": len(gt_pending) - len(gt_paths)}


__all__ = ["bag_sequence", "default_topics"]
