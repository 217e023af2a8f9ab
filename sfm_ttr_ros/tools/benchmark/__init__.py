"""``sfm-ttr benchmark``: the same frames, the same network, three ways.

* ``no_ttr``: the network's plain prediction (the original weights).
* ``sfm_ttr_online``: every frame pushed through
  :class:`~sfm_ttr_ros.core.stream.window_runner.WindowRunner` exactly as the ROS node feeds it
  (same windows, keyframes, overlap and accounting; no ROS transport), then
  :meth:`~sfm_ttr_ros.core.stream.window_runner.WindowRunner.flush` at the end of the stream (the
  node's idle flush). The depth of each frame is the one the node would publish.
* ``sfm_ttr_offline``: one :meth:`~sfm_ttr_ros.core.pipeline.SfmTTR.process_window` over the whole
  sequence, the paper's setting (or consecutive chunks of ``offline_max_frames`` frames, each
  from the original weights, when the sequence is too long for one reconstruction).
* ``ph_ttr_online`` / ``ph_ttr_offline`` and ``hybrid_online`` / ``hybrid_offline`` (on
  request with ``--modes``): the same windows with ``refinement.loss`` ``photometric``
  (Ph-TTR: Monodepth2's loss with the window's SfM poses) and ``hybrid`` (Eq. 5 + λ·photometric);
  the ``sfm_ttr_online`` / ``_offline`` modes always run ``sfm`` (:func:`.runners.mode_config`);
  ``sfm_ttr_live`` runs the parameter file's loss, as the node does (its ``loss`` key).

Each mode starts from a fresh copy of the original weights (``model_factory()``). Every frame
that has ground truth is evaluated (KITTI protocol, :mod:`sfm_ttr_ros.core.evaluation`); frames that
SfM could not use count with the prediction the mode published for them (unrefined), as in the
paper. The online and offline windows read their settings from the node's parameter file
(``params/kitti.yaml`` by default, see :func:`default_params_file`), so the benchmark measures
what the node does.

Outputs in ``out_dir``: ``results.json`` (per mode: the metrics, ``frames``,
``seconds_per_frame``, ``refined_frames``, per-stage timings; the relative gains against
``no_ttr``; ``bands``: abs rel, RMSE and pixels per GT depth band 0-10, 10-20, 20-40, 40-80 m,
pooled over pixels, and ``error_by_depth`` in finer bins; the settings, the model, the command
line), ``results.md`` (the same as tables), ``error_by_depth.png`` (abs rel against GT depth,
one line per mode: the paper's Fig. 4),
``per_frame.csv`` (abs rel and RMSE of every GT frame in every mode) and ``figure.png`` (for a
few frames: image, depth of each mode on one colour scale, abs-rel error maps at the GT pixels
and predicted-vs-GT density plots, drawn with OpenCV).

Modules: :mod:`.settings` (the parameter file), :mod:`.runners` (the windowed modes),
:mod:`.live` (``sfm_ttr_live``: the node's live serving fed in real time at ``--rate``),
:mod:`.run` (:func:`run_benchmark`, :class:`BenchmarkOptions`), :mod:`.report` (markdown / csv,
through the shared :mod:`sfm_ttr_ros.tools.report_files`), :mod:`.figure`, :mod:`.bands` (the depth
bands and the error-against-depth figure).
"""

from sfm_ttr_ros.tools.benchmark.benchmark_report import describe_model, results_markdown
from sfm_ttr_ros.tools.benchmark.figure import qualitative_figure, scatter_panel
from sfm_ttr_ros.tools.benchmark.run import BenchmarkOptions, run_benchmark
from sfm_ttr_ros.tools.benchmark.runners import DEFAULT_MODES, MODES, STAGES
from sfm_ttr_ros.tools.benchmark.settings import (
    PARAMS_FILE,
    default_params_file,
    read_params_file,
    settings_from_params,
)
from sfm_ttr_ros.tools.report_files import json_safe

__all__ = [
    "BenchmarkOptions",
    "DEFAULT_MODES",
    "MODES",
    "PARAMS_FILE",
    "STAGES",
    "default_params_file",
    "describe_model",
    "json_safe",
    "qualitative_figure",
    "read_params_file",
    "results_markdown",
    "run_benchmark",
    "scatter_panel",
    "settings_from_params",
]
