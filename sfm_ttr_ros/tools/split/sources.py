"""A :class:`~.spec.SequenceSpec` opened on the worker: the sequence, the frames to run and
the frames to evaluate.

* ``kitti``: :func:`~sfm_ttr_ros.data.sequence.open_kitti` (camera 02, or 03 for an Eigen ``r``
  line); ``images``: :func:`~sfm_ttr_ros.data.sequence.open_image_folder`; ``bag``:
  :func:`~sfm_ttr_ros.ros.bag_sequence.bag_sequence` (decoded into the task's scratch folder).
* Frames run: ``start`` .. ``start + frames`` (0 = to the end). An Eigen drive runs from
  ``context`` frames before its first listed frame to ``context`` frames after its last (clamped
  to the drive), every frame in between included: the online windows and the offline
  reconstruction see the drive's frames around the listed ones, as the node would.
* Frames evaluated: every frame run that has ground truth; for an Eigen drive only the listed
  frames that have (improved) ground truth; listed frames without it are counted
  (``listed_without_gt``), never evaluated with another frame's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.data.sequence import ImageSequence, open_image_folder, open_kitti
from sfm_ttr_ros.tools.split.spec import SequenceSpec


@dataclass
class OpenedSequence:
    """What a task runs: ``seq`` from ``start``, ``max_frames`` frames (0 = to the end), and
    counts worth reporting (``notes``)."""

    seq: ImageSequence
    start: int
    max_frames: int
    notes: dict[str, int] = field(default_factory=dict)


def open_spec(spec: SequenceSpec, scratch: str | Path) -> OpenedSequence:
    """Open ``spec`` (a bag is decoded into ``scratch``); :class:`InputError` when its data
    cannot be read or an Eigen frame is not in the drive."""
    opts = spec.options
    notes: dict[str, int] = {}
    if spec.kind == "kitti":
        seq = open_kitti(opts["raw"], spec.path, opts.get("gt"), camera=spec.camera)
    elif spec.kind == "images":
        try:
            gt_scale = float(opts.get("gt_scale", 256.0))
        except ValueError:
            raise InputError(f"gt_scale={opts['gt_scale']!r} is not a number") from None
        seq = open_image_folder(spec.path, opts["K"], opts.get("gt"), gt_scale)
        seq.name = spec.id
    elif spec.kind == "bag":
        from sfm_ttr_ros.ros.bag_sequence import bag_sequence

        seq, counts = bag_sequence(spec.path, Path(scratch) / "bag", opts.get("image"),
                                   opts.get("camera_info"), opts.get("gt"), name=spec.id)
        notes.update({k: v for k, v in counts.items() if v})
    else:  # pragma: no cover - read_split accepts no other kind
        raise InputError(f"unknown sequence kind {spec.kind!r}")
    if spec.eval_frames is None:
        return OpenedSequence(seq, spec.start, spec.frames, notes)
    index = {name: i for i, name in enumerate(seq.names)}
    missing = [f for f in spec.eval_frames if f not in index]
    if missing:
        raise InputError(f"{spec.path}: listed frame(s) {', '.join(missing[:5])}"
                         f"{' ...' if len(missing) > 5 else ''} not in the drive's "
                         f"{len(seq)} images")
    listed = sorted(index[f] for f in spec.eval_frames)
    start = max(0, listed[0] - spec.context)
    stop = min(len(seq), listed[-1] + spec.context + 1)
    gt = {f: p for f, p in seq.gt_paths.items() if f in set(spec.eval_frames)}
    notes["listed_frames"] = len(listed)
    notes["listed_without_gt"] = len(listed) - len(gt)
    seq.gt_paths = gt
    return OpenedSequence(seq, start, stop - start, notes)
