"""KITTI monocular-depth evaluation, exactly the protocol of Monodepth2 (used by SfM-TTR).

Per frame (``evaluate_frame``; steps 1-4 are :func:`scaled_prediction`, the prediction as the
evaluation sees it, which anything that breaks the metrics down must use too):

1. the prediction is resized to the ground-truth size (``cv2.resize``, bilinear) if they differ,
   NaN-safely (a finite copy and the invalid mask are resized);
2. valid pixels: ``min_depth < gt < max_depth`` (1e-3 < gt < 80 m), optionally intersected
   with the Eigen (Garg) crop, whose bounds are ``int32(fraction * H or W)`` as in Monodepth2
   (rows ``crop[0]:crop[1]``, columns ``crop[2]:crop[3]``);
3. per-image median scaling ``ratio = median(gt) / median(pred)`` over the valid pixels, for
   scale-less networks (on by default);
4. the (scaled) prediction is clamped to ``[min_depth, max_depth]``;
5. Abs Rel, Sq Rel, RMSE, RMSE log and delta < 1.25**k are computed over those pixels.

The reported numbers are the means over frames of the per-frame metrics (not per pixel).

Bad predictions at valid ground-truth pixels are handled explicitly:

* zero or negative (finite) depths are kept and, like Monodepth2, end up clamped to
  ``min_depth`` after scaling;
* non-finite values (NaN, +-inf: "no prediction") are excluded from the median and from the
  metrics and counted in ``FrameResult.invalid_pred`` (``Evaluator.summary()['invalid_pred']``);
* a frame with no valid ground-truth pixel, with no finite prediction at them, or whose median
  prediction is not positive (so median scaling is undefined) is not evaluated: it is skipped and
  counted, with the reason, by ``Evaluator``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from sfm_ttr_ros.core.errors import InputError

EIGEN_CROP = (0.40810811, 0.99189189, 0.03594771, 0.96405229)  # fractions of H, H, W, W
MIN_DEPTH = 1e-3
MAX_DEPTH = 80.0

METRICS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")
ERROR_METRICS = ("abs_rel", "sq_rel", "rmse", "rmse_log")  # lower is better
ACCURACY_METRICS = ("a1", "a2", "a3")  # higher is better

SKIP_NO_VALID_GT = "no_valid_gt"
SKIP_NO_FINITE_PRED = "no_finite_pred"
SKIP_NONPOSITIVE_MEDIAN = "nonpositive_median_pred"
SKIP_NO_AFFINE_FIT = "no_affine_fit"


PREDICTION_KINDS = ("depth", "relative_inverse_depth")


@dataclass
class EvalConfig:
    """Evaluation options. Defaults: depth range (1e-3, 80) m, no crop, median scaling.

    ``prediction``: what a predicted map holds. ``"depth"`` (depth, up to scale with
    ``median_scaling``); ``"relative_inverse_depth"`` (affine-invariant inverse depth, the
    MiDaS / DPT / Depth Anything relative heads): per frame the least-squares (a, b) with
    a·p + b ≈ 1/GT over the valid pixels (the MiDaS protocol, Ranftl et al. 2020), then
    depth = 1 / max(a·p + b, 1/max_depth); median scaling does not apply (the fit has the scale).
    """

    min_depth: float = MIN_DEPTH
    max_depth: float = MAX_DEPTH
    eigen_crop: bool = False
    median_scaling: bool = True
    prediction: str = "depth"

    def __post_init__(self) -> None:
        if self.prediction not in PREDICTION_KINDS:
            raise InputError(f"prediction must be one of {PREDICTION_KINDS}, got "
                             f"{self.prediction!r}")
        lo, hi = float(self.min_depth), float(self.max_depth)
        if not (math.isfinite(lo) and math.isfinite(hi)) or lo < 0 or hi <= lo:
            raise InputError(
                f"need 0 <= min_depth < max_depth (finite), got {self.min_depth}, {self.max_depth}"
            )


@dataclass
class FrameResult:
    """Metrics of one frame. ``ratio``: median GT / median prediction over the evaluated
    pixels (the median-scaling factor, applied or not; None for an affine fit)."""

    metrics: dict[str, float]
    ratio: float | None
    num_pixels: int  # pixels the metrics were computed over
    invalid_pred: int = 0  # valid-GT pixels dropped because the prediction was not finite
    name: str = ""


def eigen_crop_bounds(height: int, width: int) -> tuple[int, int, int, int]:
    """Monodepth2's crop ``(row0, row1, col0, col1)`` for an image of ``height`` x ``width``."""
    crop = np.array(
        [
            EIGEN_CROP[0] * height,
            EIGEN_CROP[1] * height,
            EIGEN_CROP[2] * width,
            EIGEN_CROP[3] * width,
        ]
    ).astype(np.int32)
    return int(crop[0]), int(crop[1]), int(crop[2]), int(crop[3])


def _as_depth_map(depth: np.ndarray, what: str) -> np.ndarray:
    arr = np.asarray(depth)
    if arr.ndim == 3 and 1 in (arr.shape[0], arr.shape[-1]):
        arr = arr.reshape(arr.shape[1:] if arr.shape[0] == 1 else arr.shape[:-1])
    if arr.ndim != 2 or arr.size == 0:
        raise InputError(f"{what} must be a non-empty H x W depth map, got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"{what} must hold numbers, got dtype {arr.dtype}")
    return arr.astype(np.float64, copy=False)


def valid_mask(gt: np.ndarray, config: EvalConfig | None = None) -> np.ndarray:
    """Boolean mask of the ground-truth pixels the protocol evaluates."""
    config = config or EvalConfig()
    gt = _as_depth_map(gt, "ground truth")
    with np.errstate(invalid="ignore"):
        mask = (gt > config.min_depth) & (gt < config.max_depth)
    if config.eigen_crop:
        r0, r1, c0, c1 = eigen_crop_bounds(*gt.shape)
        crop = np.zeros_like(mask)
        crop[r0:r1, c0:c1] = True
        mask &= crop
    return mask


def compute_errors(gt: np.ndarray, pred: np.ndarray) -> dict[str, float]:
    """Monodepth2's ``compute_errors`` on matching 1-D arrays of positive depths."""
    gt = np.asarray(gt, dtype=np.float64).ravel()
    pred = np.asarray(pred, dtype=np.float64).ravel()
    if gt.size == 0 or gt.shape != pred.shape:
        raise InputError(f"need equal, non-empty gt/pred arrays, got {gt.shape} and {pred.shape}")
    if not (np.all(np.isfinite(gt)) and np.all(np.isfinite(pred))):
        raise InputError("gt and pred must be finite")
    if np.any(gt <= 0) or np.any(pred <= 0):
        raise InputError("gt and pred depths must be positive")
    thresh = np.maximum(gt / pred, pred / gt)
    diff = gt - pred
    return {
        "abs_rel": float(np.mean(np.abs(diff) / gt)),
        "sq_rel": float(np.mean(diff**2 / gt)),
        "rmse": float(np.sqrt(np.mean(diff**2))),
        "rmse_log": float(np.sqrt(np.mean((np.log(gt) - np.log(pred)) ** 2))),
        "a1": float(np.mean(thresh < 1.25)),
        "a2": float(np.mean(thresh < 1.25**2)),
        "a3": float(np.mean(thresh < 1.25**3)),
    }


@dataclass
class ScaledPrediction:
    """A prediction as the evaluation sees it (:func:`scaled_prediction`): what the metrics of
    a frame, and anything that breaks them down (the benchmark's depth bands, its figures), are
    computed from, so that they cannot disagree."""

    gt: np.ndarray  # H x W ground truth, metres (float64)
    depth: np.ndarray  # H x W prediction at the GT size, scaled and clamped; NaN = no prediction
    pixels: np.ndarray  # H x W bool: valid GT and a finite prediction, the pixels evaluated
    ratio: float | None  # median GT / median prediction (applied with median scaling); None
    #                      for an affine fit or a non-positive median
    invalid_pred: int  # valid-GT pixels whose prediction is not finite (left out)
    skip: str | None = None  # why the frame is not evaluated (SKIP_*), None when it is

    def values(self) -> tuple[np.ndarray, np.ndarray]:
        """(GT, prediction) at the evaluated pixels, 1-D, in row-major order."""
        return self.gt[self.pixels], self.depth[self.pixels]


def _resize_nan_safe(pred: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``pred`` resized bilinearly to ``shape`` (H, W). cv2 cannot resize through NaN/inf
    safely: resize a finite copy and the invalid mask; a pixel touched by an invalid one is NaN."""
    if pred.shape == shape:
        return pred
    bad = ~np.isfinite(pred)
    h, w = shape
    out = cv2.resize(np.where(bad, 0.0, pred), (w, h), interpolation=cv2.INTER_LINEAR)
    if bad.any():
        bad_r = cv2.resize(bad.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
        out[bad_r > 0] = np.nan
    return out


def scaled_prediction(pred_depth: np.ndarray, gt_depth: np.ndarray,
                      config: EvalConfig | None = None) -> ScaledPrediction:
    """Steps 1-4 of the protocol (module docstring) on one frame: the prediction resized to the
    GT (NaN-safely), the valid pixels (valid GT and a finite prediction), per-image median
    scaling over them (or, for ``relative_inverse_depth``, the per-frame affine fit to 1/GT:
    :func:`inverse_affine_to_depth`, NaN outside the fitted pixels), clamped to
    ``[min_depth, max_depth]``. Non-finite predictions stay NaN (never clamped into range).
    A frame that cannot be evaluated has ``skip`` set (and its depth unscaled)."""
    config = config or EvalConfig()
    gt = _as_depth_map(gt_depth, "ground truth")
    pred = _resize_nan_safe(_as_depth_map(pred_depth, "prediction"), gt.shape)
    mask = valid_mask(gt, config)
    finite = np.isfinite(pred)
    pixels = mask & finite
    invalid = int(np.count_nonzero(mask & ~finite))
    pred = np.where(finite, pred, np.nan)
    skip = (SKIP_NO_VALID_GT if not mask.any() else
            SKIP_NO_FINITE_PRED if not pixels.any() else None)
    ratio = None
    if config.prediction == "relative_inverse_depth":
        fitted = None if skip else inverse_affine_to_depth(pred[pixels], gt[pixels],
                                                           config.max_depth)
        pred = np.full_like(pred, np.nan)
        if fitted is None:
            skip = skip or SKIP_NO_AFFINE_FIT
        else:
            pred[pixels] = fitted
    elif skip is None:
        med_pred = float(np.median(pred[pixels]))
        if med_pred > 0:  # measured without median scaling too: the scale's frame-to-frame spread
            ratio = float(np.median(gt[pixels])) / med_pred
        if config.median_scaling:
            if ratio is None:
                skip = SKIP_NONPOSITIVE_MEDIAN
            else:
                pred = pred * ratio
    depth = np.clip(pred, config.min_depth, config.max_depth)
    return ScaledPrediction(gt, depth, pixels, ratio, invalid, skip)


def _evaluate(
    pred_depth: np.ndarray, gt_depth: np.ndarray, config: EvalConfig
) -> tuple[FrameResult | None, str | None, int]:
    """(result, skip reason, invalid-prediction count)."""
    scaled = scaled_prediction(pred_depth, gt_depth, config)
    if scaled.skip is not None:
        return None, scaled.skip, scaled.invalid_pred
    gt_v, pred_v = scaled.values()
    metrics = compute_errors(gt_v, pred_v)
    result = FrameResult(metrics, scaled.ratio, int(gt_v.size), scaled.invalid_pred)
    return result, None, scaled.invalid_pred


def inverse_affine_to_depth(pred: np.ndarray, gt: np.ndarray, max_depth: float
                            ) -> np.ndarray | None:
    """Depth from affine-invariant inverse depth ``pred`` (1-D, at the valid GT pixels ``gt``):
    argmin_(a,b) Σ (a·p + b − 1/GT)², then 1 / max(a·p + b, 1/max_depth). None when the fit is
    degenerate (constant prediction) or not finite."""
    A = np.stack([pred, np.ones_like(pred)], 1)
    try:
        (a, b), *_ = np.linalg.lstsq(A, 1.0 / gt, rcond=None)
    except np.linalg.LinAlgError:
        return None
    if not (np.isfinite(a) and np.isfinite(b)) or float(np.ptp(pred)) == 0.0:
        return None
    return 1.0 / np.maximum(a * pred + b, 1.0 / max_depth)


def evaluate_frame(
    pred_depth: np.ndarray, gt_depth: np.ndarray, config: EvalConfig | None = None
) -> FrameResult | None:
    """Metrics of one predicted depth map against its ground truth (metres, 0 = no GT).

    Returns None when the frame cannot be evaluated (no valid GT pixel, no finite prediction at
    them, or a non-positive median prediction with median scaling); the caller counts it.
    """
    result, _, _ = _evaluate(pred_depth, gt_depth, config or EvalConfig())
    return result


def mean_over_frames(rows: Sequence[Mapping[str, float]]) -> dict:
    """The KITTI summary of per-frame metrics: each metric's mean over the frames (NaN for
    none) and ``frames``; ``rows`` are per-frame metric dicts (e.g. a ``per_frame`` subset)."""
    out: dict = {m: float(np.mean([r[m] for r in rows])) if rows else math.nan
                 for m in METRICS}
    out["frames"] = len(rows)
    return out


def means_by_part(rows: Sequence[Mapping[str, float]], parts: int = 3) -> list[dict]:
    """:func:`mean_over_frames` of ``rows`` cut, in their order, into ``parts`` consecutive
    parts of (nearly) equal size, e.g. the first, middle and last third of a drive: how an
    online output changes as its weights learn. Fewer rows than parts: one part per row."""
    if parts < 1:
        raise ValueError(f"parts must be >= 1, got {parts}")
    n, k = len(rows), min(parts, max(len(rows), 1))
    return [mean_over_frames(rows[i * n // k:(i + 1) * n // k]) for i in range(k)]


@dataclass
class Evaluator:
    """Accumulates frames and reports the protocol's means over frames."""

    config: EvalConfig = field(default_factory=EvalConfig)
    results: list[FrameResult] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)  # name -> reason
    invalid_pred: int = 0

    def add(self, name: str, pred: np.ndarray, gt: np.ndarray) -> FrameResult | None:
        result, reason, invalid = _evaluate(pred, gt, self.config)
        self.invalid_pred += invalid
        if result is None:
            key, k = str(name), 1
            while key in self.skipped:  # never lose a skip to a repeated name
                k += 1
                key = f"{name}#{k}"
            self.skipped[key] = str(reason)
            return None
        result.name = str(name)
        self.results.append(result)
        return result

    def summary(self) -> dict:
        """Mean metrics over frames plus counts, scaling-ratio statistics and per-frame rows."""
        out = mean_over_frames([r.metrics for r in self.results])
        out["skipped"] = len(self.skipped)
        out["skipped_frames"] = dict(self.skipped)
        out["invalid_pred"] = self.invalid_pred
        ratios = np.array([r.ratio for r in self.results if r.ratio is not None], dtype=np.float64)
        if ratios.size:
            med = float(np.median(ratios))
            out["ratio_median"] = med
            out["ratio_std"] = float(np.std(ratios / med))  # Monodepth2's "std" of ratios / med
        else:
            out["ratio_median"] = None
            out["ratio_std"] = None
        out["per_frame"] = [
            {
                "name": r.name,
                **r.metrics,
                "ratio": r.ratio,
                "pixels": r.num_pixels,
                "invalid_pred": r.invalid_pred,
            }
            for r in self.results
        ]
        return out


def format_table(results: dict[str, dict], decimals: int = 3) -> str:
    """Markdown table, one row per method (e.g. ``no_ttr``, ``sfm_ttr``).

    Monodepth2 prints every metric with 3 decimals; pass ``decimals=4`` for finer comparisons.
    """
    cols = (*METRICS, "frames")
    lines = [
        "| method | " + " | ".join(cols) + " |",
        "|---|" + "---:|" * len(cols),
    ]
    for method, res in results.items():
        cells = []
        for m in METRICS:
            v = res.get(m)
            ok = v is not None and math.isfinite(float(v))
            cells.append(f"{float(v):.{decimals}f}" if ok else "n/a")
        frames = res.get("frames")
        cells.append(str(int(frames)) if frames is not None else "n/a")
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def relative_gain(before: dict, after: dict) -> dict[str, float]:
    """Relative improvement per metric (positive = better after than before).

    Error metrics: ``(before - after) / before`` (relative reduction, e.g. 0.071 -> 0.056 gives
    0.211); accuracies: ``(after - before) / before``. NaN when ``before`` is 0 or missing.
    """
    out: dict[str, float] = {}
    for m in METRICS:
        if m not in before or m not in after:
            continue
        b, a = float(before[m]), float(after[m])
        if b == 0 or not (math.isfinite(a) and math.isfinite(b)):
            out[m] = math.nan
        elif m in ERROR_METRICS:
            out[m] = (b - a) / b
        else:
            out[m] = (a - b) / b
    return out


def _read_png16(path: Path, what: str) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"cannot read {what} PNG {path}")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise InputError(
            f"{what} PNG {path} must be single-channel uint16, got {img.dtype} {img.shape}"
        )
    return img


def evaluate_folders(
    pred_dir: str | Path,
    gt_dir: str | Path,
    gt_scale: float = 256.0,
    pred_format: str = "npy",
    config: EvalConfig | None = None,
    pred_scale: float | None = None,
) -> dict:
    """Evaluate every ``gt_dir/NAME.png`` against ``pred_dir/NAME.npy`` (or ``NAME.png``).

    Ground truth: uint16 PNG, depth = value / ``gt_scale``, 0 = no measurement. Predictions:
    ``npy`` float depth in metres, or ``png`` uint16 depth = value / ``pred_scale`` (default
    ``gt_scale``), where 0 means "no prediction" (treated as non-finite: excluded and counted).
    Returns ``Evaluator.summary()`` plus ``missing_pred`` / ``missing_gt`` counts and the names in
    ``missing_pred_names`` / ``missing_gt_names``.
    """
    pred_dir, gt_dir = Path(pred_dir), Path(gt_dir)
    for d, what in ((pred_dir, "prediction"), (gt_dir, "ground-truth")):
        if not d.is_dir():
            raise InputError(f"{what} folder {d} does not exist")
    if pred_format not in ("npy", "png"):
        raise InputError(f"pred_format must be 'npy' or 'png', got {pred_format!r}")
    pred_scale = gt_scale if pred_scale is None else pred_scale
    for s, what in ((gt_scale, "gt_scale"), (pred_scale, "pred_scale")):
        if not (math.isfinite(float(s)) and s > 0):
            raise InputError(f"{what} must be positive, got {s}")
    gt_files = {p.stem: p for p in sorted(gt_dir.glob("*.png")) if p.is_file()}
    if not gt_files:
        raise InputError(f"no ground-truth PNG in {gt_dir}")
    pred_files = {p.stem: p for p in sorted(pred_dir.glob(f"*.{pred_format}")) if p.is_file()}

    evaluator = Evaluator(config or EvalConfig())
    missing_pred = sorted(set(gt_files) - set(pred_files))
    missing_gt = sorted(set(pred_files) - set(gt_files))
    for name in sorted(set(gt_files) & set(pred_files)):
        gt = _read_png16(gt_files[name], "ground-truth").astype(np.float64) / gt_scale
        if pred_format == "npy":
            try:
                pred = np.load(pred_files[name], allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise InputError(f"cannot read prediction {pred_files[name]}: {exc}") from exc
        else:
            raw = _read_png16(pred_files[name], "prediction")
            pred = raw.astype(np.float64) / pred_scale
            pred[raw == 0] = np.nan
        evaluator.add(name, pred, gt)
    out = evaluator.summary()
    out["missing_pred"] = len(missing_pred)
    out["missing_gt"] = len(missing_gt)
    out["missing_pred_names"] = missing_pred
    out["missing_gt_names"] = missing_gt
    return out
