"""Helpers only the tests use: one-shot calls and baselines the package itself does not need.

Each was once in the package beside the code it wraps; the package keeps only what it runs.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from sfm_ttr_ros.core import params
from sfm_ttr_ros.core.alignment.scale import _check, _valid
from sfm_ttr_ros.core.frames import Frame, Intrinsics, load_rgb
from sfm_ttr_ros.core.models.base import DepthModel
from sfm_ttr_ros.core.refinement import trainable
from sfm_ttr_ros.core.sfm.reconstruction import SfmReconstructor
from sfm_ttr_ros.core.sfm.result import SfmResult
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig
from sfm_ttr_ros.core.window_io import TTRConfig

#: The paper's method as a parameter file (Izquierdo & Civera, CVPR 2023, Sec. 3).
PAPER_PARAMS = Path(__file__).resolve().parents[1] / "params" / "paper.yaml"


def paper_settings() -> params.Settings:
    """Everything ``params/paper.yaml`` configures, read by the one reader of parameter files:
    windows of 10 every 5, batch SfM from the upsampled octave, 200 whole-encoder steps of
    Eq. (5), ``reset``, no unsupported-change check, the default memory format. For tests whose
    assertions are about those settings rather than the defaults (the real-footage ones)."""
    return params.build(params.read_params_file(PAPER_PARAMS, "refiner"))


def paper_config() -> TTRConfig:
    """The core's configuration of :func:`paper_settings` (a fresh copy each call)."""
    return paper_settings().ttr


def load_frames(paths: Iterable[str | Path], stamps: Sequence[float] | None = None) -> list[Frame]:
    """Image files as frames (index = position, name = file stem, stamp = index unless given)."""
    frames = []
    for i, p in enumerate(paths):
        p = Path(p)
        stamp = float(stamps[i]) if stamps is not None else float(i)
        frames.append(Frame(index=i, image=load_rgb(p), stamp=stamp, name=p.stem))
    return frames


def reconstruct_window(frames: Sequence[Frame], intrinsics: Intrinsics,
                       config: SfmConfig | None = None) -> SfmResult:
    """One-shot reconstruction of a window in a temporary workspace."""
    with SfmReconstructor(config) as rec:
        return rec.reconstruct(frames, intrinsics)


def median_scale(d_sfm: np.ndarray, d_nn: np.ndarray) -> float:
    """Ablation baseline of Sec. 3.2: s = median(D_nn / D_sfm) over valid pairs."""
    d_sfm, d_nn = _check(d_sfm, d_nn)
    v = _valid(d_sfm, d_nn)
    return float(np.median(d_nn[v] / d_sfm[v])) if v.any() else float("nan")


def least_squares_scale(d_sfm: np.ndarray, d_nn: np.ndarray) -> float:
    """Ablation baseline of Sec. 3.2: unweighted argmin_s Σ (s·D_sfm − D_nn)² over all valid
    pairs."""
    d_sfm, d_nn = _check(d_sfm, d_nn)
    v = _valid(d_sfm, d_nn)
    den = float(np.sum(d_sfm[v] ** 2))
    return float(np.sum(d_sfm[v] * d_nn[v]) / den) if den > 0 else float("nan")


def reset_lora(model: DepthModel) -> int:
    """Re-initialise every LoRA adapter (B = 0: the network is the original again); returns
    the number of adapted layers."""
    layers = trainable._lora_layers(model.encoder)
    for _, layer in layers:
        layer.reset_lora_parameters(trainable.LORA_ADAPTER, True)
    return len(layers)


def remove_lora(model: DepthModel) -> int:
    """Put the plain layers back, discarding the adapters (the original network)."""
    return trainable._unwrap(model.encoder, merge=False)


def wait_for(pred: Callable[[], object], timeout: float, what: str, period: float = 0.02):
    """Poll ``pred`` until it gives a true value (returned) or ``timeout`` seconds passed (an
    AssertionError naming ``what``)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(period)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")


def stop_spun(refiner, executor, thread, *nodes) -> None:
    """Stop a refiner node spun by ``executor`` in ``thread`` beside ``nodes``: its worker,
    the executor, the thread, then every node."""
    refiner.stop_worker()
    executor.shutdown(timeout_sec=2.0)
    thread.join(5)
    for node in (refiner, *nodes):
        node.destroy_node()
