"""The minimum versions of the dependencies, stated once, each with the reason it is that one.

``setup.py`` runs this file by path (``runpy.run_path``: nothing of the package is imported, so
it builds before its dependencies are installed) for ``install_requires``; ``requirements.txt``
(the pip dependencies without a rosdep key) and ``package.xml`` (``version_gte``) repeat them,
and ``tests/test_package.py`` checks that they agree. At start-up the ``refiner`` node and the
``sfm-ttr`` commands that run SfM call :func:`check_sfm_dependencies`: a pycolmap or torch older
than its floor, or a pycolmap without an API the code calls, is one clear error there
(:class:`~sfm_ttr_ros.core.errors.InputError`) instead of every window failing later; so is a
torch without a name of :data:`TORCH_API` (what the CUDA path calls).

How each floor was found: the releases were installed side by side (``pip download NAME==V
--no-deps``) and the package's own tests run against them: pycolmap 4.2.0 passes
``tests/test_sfm.py`` and ``tests/test_features_torch.py``, 4.1.1 fails at the first window
(no ``CancellationToken``); rosbags 0.11.6 passes ``tests/test_bag.py``, 0.11.5 and earlier
fail ``evaluate_bag``.
"""

from __future__ import annotations

import re

#: name -> (minimum version, upper bound or "", why that minimum)
FLOORS: dict[str, tuple[str, str, str]] = {
    "pycolmap": ("4.2.0", "5", "pycolmap.CancellationToken and the cancellation_token argument of "
                 "extract_features, match_sequential, geometric_verification and "
                 "incremental_mapping (SfM stops at shutdown) are new in 4.2.0: with 4.0.x or "
                 "4.1.x every window failed"),
    "torch": ("2.3", "", "the first torch whose wheels are built against NumPy 2 (pip installs "
              "NumPy 2 for the unpinned numpy; torch 2.2 and older cannot exchange arrays "
              "with it: torch.from_numpy, Tensor.numpy); the torch API the code calls "
              "(inference_mode, meshgrid(indexing=), torch.load(weights_only=), linalg) is "
              "older"),
    "rosbags": ("0.11.6", "", "reading an mcap bag's messages between two log times "
                "(AnyReader.messages(start=, stop=): sfm-ttr evaluate --bag, the demo) returns "
                "them from 0.11.6 on; Writer(version=9, storage_plugin=) needs 0.10.9, the "
                "ROS2_JAZZY type store 0.10.8"),
    "cmeel-mimalloc": ("3.4", "4", "the node preloads the wheel's libmimalloc.so.3 "
                       "(ros/allocator.py); 3.4 is the mimalloc measured to give freed pages "
                       "back (docs/node.md, Memory)"),
}
#: PEP 508 markers of a requirement (the node's malloc is a Linux shared library)
MARKERS = {"cmeel-mimalloc": "sys_platform == 'linux'"}
#: Every pycolmap name the code calls (dotted: attributes of attributes); a pycolmap missing
#: one is refused at start-up by :func:`check_pycolmap`.
PYCOLMAP_API = (
    "CancellationToken", "CameraMode.SINGLE", "Database.open", "Device.cpu",
    "FeatureDescriptors", "FeatureExtractionOptions", "FeatureExtractorType.SIFT",
    "FeatureMatchingOptions", "GeometricVerifierOptions", "ImageReaderOptions",
    "IncrementalPipelineOptions", "SequentialPairingOptions", "extract_features",
    "geometric_verification", "import_images", "incremental_mapping", "logging",
    "match_sequential", "pair_id_to_image_pair",
    # the streaming SfM (core/sfm/frontend.py, map_cache.py, streaming_map.py)
    "Camera", "DatabaseCache", "FeatureExtractor.create", "FeatureMatcher", "Frame", "Image",
    "IncrementalMapper", "IncrementalPipeline", "Reconstruction", "ReconstructionManager",
    "Rig", "SensorType.CAMERA", "TwoViewGeometryOptions", "data_t", "estimate_two_view_geometry",
    "keypoints_to_matrix", "sensor_t", "set_random_seed",
)

#: Every torch name the CUDA path calls (core/refinement/graph_step.py, graph_cache.py,
#: core/stream/serving.py), all in the floor's release (2.3: ``torch.cuda.graph`` with
#: ``stream=`` and ``capture_error_mode=``, ``Adam(capturable=, foreach=)``, stream priorities);
#: ``torch.autograd.graph.increment_version`` is newer (2.5) and guarded: older releases use
#: ``torch._C._increment_version`` one tensor at a time (graph_step.bump_versions). A torch
#: missing one is refused at start-up by :func:`check_torch`.
TORCH_API = (
    "cuda.CUDAGraph", "cuda.Event", "cuda.Stream", "cuda.current_stream", "cuda.graph",
    "cuda.stream", "cuda.synchronize", "optim.Adam", "optim.Optimizer", "_C._increment_version",
)


def requirement(name: str) -> str:
    """The pip requirement of ``name`` (``pycolmap>=4.2.0,<5``, with its marker)."""
    low, high, _ = FLOORS[name]
    text = f"{name}>={low}" + (f",<{high}" if high else "")
    marker = MARKERS.get(name)
    return f"{text}; {marker}" if marker else text


def version_tuple(text: str) -> tuple[int, ...]:
    """``"4.2.1"`` -> (4, 2, 1); the leading numbers of a version (``2.13.0+cpu``, ``4.3.0.dev1``
    -> (2, 13, 0), (4, 3, 0)); () when it has none."""
    m = re.match(r"\s*v?(\d+(?:\.\d+)*)", str(text))
    return tuple(int(p) for p in m.group(1).split(".")) if m else ()


def too_old(version: str, minimum: str) -> bool:
    """Whether ``version`` is below ``minimum`` (an unreadable version counts as too old)."""
    have, want = version_tuple(version), version_tuple(minimum)
    width = max(len(have), len(want))
    return not have or have + (0,) * (width - len(have)) < want + (0,) * (width - len(want))


def _missing(module, names) -> list[str]:
    out = []
    for dotted in names:
        obj = module
        for part in dotted.split("."):
            obj = getattr(obj, part, None)
            if obj is None:
                out.append(dotted)
                break
    return out


def check_pycolmap(module=None) -> None:
    """:class:`InputError` unless ``module`` (default: ``import pycolmap``) is at least the
    floor of :data:`FLOORS` and has every name of :data:`PYCOLMAP_API`."""
    from sfm_ttr_ros.core.errors import InputError

    if module is None:
        try:
            import pycolmap as module
        except ImportError as exc:
            raise InputError(f"pycolmap is not installed ({exc}): pip install "
                             f"'{requirement('pycolmap')}'") from None
    version = str(getattr(module, "__version__", "?"))
    low, _, why = FLOORS["pycolmap"]
    if too_old(version, low):
        raise InputError(f"pycolmap {version} is too old: SfM needs {requirement('pycolmap')} "
                         f"({why}); pip install '{requirement('pycolmap')}'")
    missing = _missing(module, PYCOLMAP_API)
    if missing:
        raise InputError(f"pycolmap {version} lacks {', '.join(missing)}, which SfM calls: "
                         f"install a release of '{requirement('pycolmap')}' that has them")


def check_torch(module=None) -> None:
    """:class:`InputError` unless ``module`` (default: ``import torch``) is at least the floor."""
    from sfm_ttr_ros.core.errors import InputError

    if module is None:
        import torch as module
    version = str(getattr(module, "__version__", "?"))
    low, _, why = FLOORS["torch"]
    if too_old(version, low):
        raise InputError(f"torch {version} is too old: the package needs "
                         f"{requirement('torch')} ({why})")
    missing = _missing(module, TORCH_API)
    if missing:
        raise InputError(f"torch {version} lacks {', '.join(missing)}, which the CUDA path "
                         f"calls: install a release of '{requirement('torch')}' that has them")


def check_sfm_dependencies() -> None:
    """What the node and the ``sfm-ttr`` commands that run SfM check at start-up."""
    check_torch()
    check_pycolmap()
