"""The affine path end to end: a network whose output is affine-invariant inverse
depth, refined through SfmTTR, ends as accurate as the paper's scale-only path on the same
network's depth.

:class:`AffineInverse` wraps test_pipeline's biased street network (its encoder and decoder,
shared) and outputs p = a_j / D + b_j with a scale a_j and shift b_j drawn at random PER FRAME
(sfm_ttr_ros/tools/affine_wrap.py): what a MiDaS / Depth Anything relative head promises and no
more. The scale-only path runs on the plain network; both runs use the same SfM result, so the
comparison is the alignment and the loss space only."""

from __future__ import annotations

import numpy as np
import pytest
import test_pipeline
import torch

from sfm_ttr_ros.core.alignment.affine import (
    FrameAffineAlignment,
    affine_to_depth,
    is_affine_output,
)
from sfm_ttr_ros.core.alignment.scale import AlignmentResult
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.pipeline import SfmTTR
from sfm_ttr_ros.tools.affine_wrap import AffineInverse

abs_rel, config, street_model = test_pipeline.abs_rel, test_pipeline.config, \
    test_pipeline.street_model
scene, biased_state = test_pipeline.scene, test_pipeline.biased_state  # fixtures shared


@pytest.fixture(scope="module")
def runs(scene, biased_state):
    plain = SfmTTR(street_model(biased_state), config())
    scale_only = plain.process_window(scene.frames, scene.seq.intrinsics)
    plain.close()
    wrapped = AffineInverse(street_model(biased_state), scene.seq.images)
    ttr = SfmTTR(wrapped, config())
    ttr.sfm.reconstructor.reconstruct = lambda *a, **k: scale_only.sfm  # the same SfM result
    affine = ttr.process_window(scene.frames, scene.seq.intrinsics)
    ttr.close()
    # The affine path's depth: the refined raw output through each frame's own fit (SfM units)
    registered = [n for n in (f.name for f in scene.frames) if n in affine.sfm.frames]
    refined_depth = {n: affine_to_depth(affine.alignment.frame(k), affine.depths[n])
                     for k, n in enumerate(registered)}
    return scale_only, affine, wrapped, refined_depth


def test_the_wrapper_is_a_different_affine_map_per_frame(scene):
    model = AffineInverse(street_model(), scene.seq.images)
    assert is_affine_output(model) and not is_affine_output(model.inner)
    a, b = model.frame_affine(model.preprocess([f.image for f in scene.frames[:4]]))
    alone = [model.frame_affine(model.preprocess(f.image)) for f in scene.frames[:4]]
    assert torch.equal(torch.cat([p[0] for p in alone]), a)  # a frame alone keeps its pair
    assert len(set(np.round(a.flatten().tolist(), 6))) == 4
    assert len(set(np.round(b.flatten().tolist(), 6))) == 4


def test_affine_path_refines_as_well_as_the_scale_only_path(scene, runs):
    scale_only, affine, _, refined_depth = runs
    assert scale_only.refined and affine.refined, (scale_only.reason, affine.reason)
    assert type(scale_only.alignment) is AlignmentResult  # the paper's path for depth
    assert isinstance(affine.alignment, FrameAffineAlignment)
    assert affine.alignment.stats["frames_fitted"] == len(scene.frames)
    before = abs_rel(scale_only.depths_before, scene.gt)
    after_scale = abs_rel(scale_only.depths, scene.gt)
    after_affine = abs_rel(refined_depth, scene.gt)
    print(f"abs rel before {before:.4f}, scale-only {after_scale:.4f}, affine "
          f"{after_affine:.4f}")
    assert after_scale < 0.8 * before
    # Measured (80 steps, lr 1e-3), 10 runs on 2026-11-25: before 0.279, scale-only
    # 0.149-0.160, affine 0.144-0.159; the affine path's paired gap -5.7 % to +5.2 % (mean
    # -3.2 %): COLMAP's multi-threaded mapper makes each run's SfM (shared by both paths within
    # a run) differ, and the gap with it. An earlier stop measured 3-8 % behind. On the default
    # network and a generated KITTI-size drive see the affine-equivalence study (docs/decisions.md)
    # (BENCHMARKS.md §10). The affine path must stay a real refinement and near the paper's.
    assert after_affine < 0.7 * before
    assert abs(after_affine - after_scale) <= 0.10 * after_scale


def test_affine_targets_live_in_the_networks_output_space(runs):
    _, affine, _, _ = runs
    # the published depths are the network's raw output: p = a / D + b, small and positive
    p = np.concatenate([d.ravel() for d in affine.depths.values()])
    assert affine.loss_after < affine.loss_before
    assert np.all(p > 0) and np.median(p) < 5
    # the cloud stays in SfM units (an affine fit has no depth unit of its own)
    assert affine.cloud_xyz.shape[0] > 0


def test_photometric_loss_is_refused_for_affine_outputs(scene):
    ttr = SfmTTR(AffineInverse(street_model(), scene.seq.images), config())
    cfg = config()
    cfg.refinement.loss = "hybrid"
    with pytest.raises(InputError, match="affine-invariant inverse depth"):
        ttr.set_config(cfg)
    ttr.close()
