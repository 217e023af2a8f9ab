"""One sequence of a split, start to end: what a worker executes (:func:`run_sequence`).

The work itself is the single-sequence commands' own: ``benchmark`` runs
:func:`~sfm_ttr_ros.tools.one_sequence.benchmark_sequence` (all modes of the sequence in one
task: they share the opened sequence and the network), ``run`` runs
:func:`~sfm_ttr_ros.tools.one_sequence.run_whole_sequence`. Both write into a scratch folder on
the worker; the files come back in the :class:`SequenceOutcome` and the driver alone writes the
output folder (a worker that dies leaves nothing half-written there, and the output folder need
not be shared between the nodes).

A sequence that fails on its data (unreadable, no ground truth, a listed frame missing, ...:
:class:`~sfm_ttr_ros.core.frames.InputError`) or on an error of the method comes back as
``failed`` with its reason; it is not retried (the same data fails the same way). Only a worker
that dies is retried (:mod:`.engine`).
"""

from __future__ import annotations

import argparse
import os
import socket
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.evaluation import METRICS
from sfm_ttr_ros.tools.split.spec import SequenceSpec

COMMANDS = ("benchmark", "run")
#: Per mode, what a sequence's row keeps from the single-sequence results.
MODE_KEYS = (*METRICS, "frames", "refined_frames", "processed_frames", "seconds",
             "seconds_per_frame", "windows", "windows_refined")


@dataclass
class SplitJob:
    """What every task of one split shares: the command, the parameter values (the schema's
    names), the parameter file they came from, the command's own options (``benchmark``: modes,
    rate, offline chunks, figure frames, depth files, evaluation; ``run``: the Eigen crop), the
    threads of one task and the command line (recorded in each sequence's results)."""

    command: str
    values: dict[str, Any]
    params_path: str
    options: dict[str, Any]
    threads: int = 1
    command_line: str = ""

    def __post_init__(self) -> None:
        if self.command not in COMMANDS:
            raise InputError(f"unknown split command {self.command!r}")
        if self.threads < 1:
            raise InputError(f"threads per task must be >= 1, got {self.threads}")


#: Why a sequence failed, as the key beside its ``reason`` text: its data was refused (an
#: InputError), the method raised on it, the task raised past :func:`run_sequence`, or every
#: worker it ran on was lost.
INPUT_ERROR, METHOD_ERROR, TASK_ERROR, WORKER_LOST = (
    "input_error", "method_error", "task_error", "worker_lost")


@dataclass
class SequenceOutcome:
    """A task's answer: ``status`` ``done`` (``row``: the sequence's numbers; ``files``: its
    output files, path relative to its folder -> bytes) or ``failed`` (``reason`` and its key,
    ``reason_key``)."""

    id: str
    status: str
    reason: str = ""
    reason_key: str = ""
    row: dict[str, Any] = field(default_factory=dict)
    files: dict[str, bytes] = field(default_factory=dict)
    seconds: float = 0.0
    host: str = ""
    detail: str = ""


def _mode_row(r: dict[str, Any]) -> dict[str, Any]:
    out = {k: r.get(k) for k in MODE_KEYS if k in r}
    out["timings"] = {k: float(v) for k, v in (r.get("timings") or {}).items()}
    return out


def benchmark_row(results: dict[str, Any]) -> dict[str, Any]:
    """A sequence's row from its benchmark ``results.json``."""
    return {"frames_total": results["frames_total"],
            "frames_with_gt": results["frames_with_gt"],
            "first_frame": results.get("first_frame", 0),
            "modes": {m: _mode_row(results[m]) for m in results["modes"]}}


def run_row(summary: dict[str, Any]) -> dict[str, Any]:
    """A sequence's row from ``run``'s ``summary.json`` (methods ``no_ttr`` = before,
    ``sfm_ttr`` = after the one window)."""
    from sfm_ttr_ros.tools.one_sequence import METHODS

    metrics = summary.get("metrics") or {}
    n = summary["frames_total"]
    modes = {}
    for key, method in METHODS.items():
        m = dict(metrics.get(key) or {"frames": 0})
        refined = n if key == "after" and summary.get("refined") else 0
        modes[method] = {**{k: m.get(k) for k in (*METRICS, "frames")},
                         "refined_frames": refined, "processed_frames": n}
    modes["sfm_ttr"]["seconds"] = summary["seconds"]
    modes["sfm_ttr"]["timings"] = {k: float(v) for k, v in summary.get("timings", {}).items()}
    return {"frames_total": n, "frames_with_gt": modes["no_ttr"]["frames"],
            "first_frame": summary.get("first_frame", 0), "modes": modes,
            "refined": bool(summary.get("refined")), "reason": summary.get("reason", ""),
            "reason_key": summary.get("reason_key")}


def _collect(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _apply_threads(threads: int) -> None:
    import cv2
    import torch

    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)


def run_sequence(spec: SequenceSpec, job: SplitJob) -> SequenceOutcome:
    """Run ``job``'s command over ``spec`` (module docstring); never raises for a sequence's
    own failure (only for an interrupt)."""
    from sfm_ttr_ros.core.params import build
    from sfm_ttr_ros.tools.split.sources import open_spec

    t0 = time.perf_counter()
    host = f"{socket.gethostname()}:{os.getpid()}"
    try:
        settings = build(job.values)
        _apply_threads(job.threads)
        with tempfile.TemporaryDirectory(prefix=f"sfm_ttr_{spec.id}_") as tmp:
            t_open = time.perf_counter()
            opened = open_spec(spec, Path(tmp) / "source")
            open_s = time.perf_counter() - t_open
            out = Path(tmp) / "out"
            args = argparse.Namespace(**job.options)
            if job.command == "benchmark":
                from sfm_ttr_ros.tools.one_sequence import benchmark_sequence

                results = benchmark_sequence(
                    opened.seq, settings, args, out, start=opened.start,
                    max_frames=opened.max_frames, params_path=job.params_path,
                    command=job.command_line, quiet=True)
                row = benchmark_row(results)
            else:
                from sfm_ttr_ros.tools.one_sequence import run_whole_sequence

                summary = run_whole_sequence(opened.seq, settings, out, start=opened.start,
                                             max_frames=opened.max_frames,
                                             eigen_crop=bool(job.options.get("eigen_crop")))
                row = run_row(summary)
            files = _collect(out)
        row["notes"] = dict(opened.notes)
        row["open_seconds"] = open_s
        seconds = time.perf_counter() - t0
        row["task_seconds"] = seconds
        return SequenceOutcome(spec.id, "done", row=row, files=files, seconds=seconds,
                               host=host)
    except InputError as exc:
        return SequenceOutcome(spec.id, "failed", reason=str(exc), reason_key=INPUT_ERROR,
                               seconds=time.perf_counter() - t0, host=host)
    except Exception as exc:  # the method failed on this sequence: reported, the others go on
        return SequenceOutcome(spec.id, "failed", reason=f"{type(exc).__name__}: {exc}",
                               reason_key=METHOD_ERROR, seconds=time.perf_counter() - t0, host=host,
                               detail=traceback.format_exc())
