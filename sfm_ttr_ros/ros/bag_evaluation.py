"""KITTI metrics of a bag of predicted depth against a ground-truth depth topic, matched by
header stamp: :func:`evaluate_bag` (``sfm-ttr evaluate --bag``).

The refiner publishes depth in metres on its metric topics and depth not (yet) in metres on
their relative twins (REP 118, :mod:`sfm_ttr_ros.ros.units`): a refiner output topic is read
together with its twin (:func:`pred_topics`), each frame from whichever carries it; median-scaled
metrics take either, metres-only metrics should be read with ``--no-median-scaling`` knowing
how many frames came relative (``pred_relative_frames``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from msg_adapters.image import image_to_depth
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.evaluation import EvalConfig, Evaluator
from sfm_ttr_ros.ros import names
from sfm_ttr_ros.ros.bag import (
    IMAGE_MSGTYPE,
    ProgressBar,
    bag_topics,
    header_stamp_ns,
    open_reader,
    read_bag,
    select_connections,
    stamp_str,
)
from sfm_ttr_ros.ros.kitti_bag import DEPTH_GT_TOPIC

DEFAULT_PRED_TOPIC = names.DEPTH_TOPIC_RESOLVED  # the refiner's live depth: /refiner/depth/image


def pred_topics(path: Path, topic: str) -> list[str]:
    """``topic`` and its relative twin (:func:`~sfm_ttr_ros.ros.names.relative_twin_of`), those
    of them in the bag at ``path``; ``[topic]`` when neither is (the check names it)."""
    have = bag_topics(path)
    twin = names.relative_twin_of(topic)
    found = [t for t in (topic, twin) if t is not None and t in have]
    return found or [topic]


def _stamp_index(path: Path, topics: list[str]) -> tuple[dict[int, int], int]:
    """header stamp -> log time of the first message with it; number of repeated stamps."""
    index: dict[int, int] = {}
    dupes = 0
    reader = open_reader(path)
    try:
        conns = select_connections(reader, path, topics)
        for conn, t, raw in reader.messages(connections=conns):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:
                raise InputError(f"cannot decode a message on {conn.topic} in {path}: "
                                 f"{exc}") from exc
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
    (exact nanoseconds); with the relative twin of ``pred_topic`` when the bag has it
    (:func:`pred_topics`: ``pred_topic`` in the result lists what was read,
    ``pred_relative_frames`` counts the frames from the twin).

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
    topics = pred_topics(pred_bag, pred_topic)
    for topic in topics:
        _check_image_topic(pred_bag, topic)
    _check_image_topic(gt_bag, gt_topic)
    gt_index, dup_gt = _stamp_index(gt_bag, [gt_topic])
    pred_index, dup_pred = _stamp_index(pred_bag, topics)
    matched = sorted(set(gt_index) & set(pred_index))

    evaluator = Evaluator(config or EvalConfig())
    bar = ProgressBar(len(matched), "evaluate", enabled=progress)
    gt_reader = open_reader(gt_bag)
    seen: set[int] = set()
    relative = 0
    try:
        gt_conns = select_connections(gt_reader, gt_bag, [gt_topic])
        for topic, _, st, msg in read_bag(pred_bag, topics):
            if st not in gt_index or st in seen:
                continue
            seen.add(st)
            relative += topic != pred_topic
            pred = image_to_depth(msg)
            t = gt_index[st]
            gt = None
            for conn, _t, raw in gt_reader.messages(connections=gt_conns, start=t, stop=t + 1):
                gmsg = gt_reader.deserialize(raw, conn.msgtype)
                if header_stamp_ns(gmsg, _t) == st:
                    gt = image_to_depth(gmsg)
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
        "pred_topic": " + ".join(topics), "gt_topic": gt_topic,
        "pred_relative_frames": relative,
        "pred_frames": len(pred_index), "gt_frames": len(gt_index), "matched": len(matched),
        "missing_gt": len(missing_gt), "missing_pred": len(missing_pred),
        "missing_gt_stamps": [stamp_str(s) for s in missing_gt],
        "missing_pred_stamps": [stamp_str(s) for s in missing_pred],
        "duplicate_pred": dup_pred, "duplicate_gt": dup_gt,
    })
    return out


__all__ = ["DEFAULT_PRED_TOPIC", "evaluate_bag", "pred_topics"]
