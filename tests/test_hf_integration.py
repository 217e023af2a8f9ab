"""A tiny transformers model through the rest of the system: LoRA-refined weights
handed to the serving copy, and ``sfm-ttr benchmark --model hf --model-path DIR``.

The tiny randomly initialised Depth Anything of test_hf_model is saved to a temporary directory
and loaded back offline: nothing is downloaded."""

from __future__ import annotations

import json
import os

os.environ["HF_HUB_OFFLINE"] = "1"

import numpy as np  # noqa: E402
import pytest  # noqa: E402

pytest.importorskip("transformers", reason="extra 'hf' not installed")
pytest.importorskip("peft", reason="extra 'hf' not installed")

import test_benchmark  # noqa: E402
import test_hf_model  # noqa: E402

from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig  # noqa: E402
from sfm_ttr_ros.core.refinement import trainable  # noqa: E402
from sfm_ttr_ros.core.refinement.encoder import refine_encoder  # noqa: E402
from sfm_ttr_ros.core.refinement.refinement_config import RefinementConfig
from sfm_ttr_ros.core.refinement.supervision import FrameSupervision  # noqa: E402
from sfm_ttr_ros.core.stream.serving import ServingModel  # noqa: E402

model_dirs, data = test_hf_model.model_dirs, test_benchmark.data  # fixtures shared
FRAME = test_hf_model.FRAME


def supervision(model) -> list[FrameSupervision]:
    before = model.predict(FRAME)[0]
    rng = np.random.default_rng(1)
    pixels = np.stack([rng.uniform(0, 129, 60), rng.uniform(0, 39, 60)], axis=1)
    target = 1.2 * before[pixels[:, 1].astype(int), pixels[:, 0].astype(int)] + 0.05
    return [FrameSupervision("f0", FRAME, pixels, target, np.ones(60))]


@pytest.mark.parametrize("blocks", [0, 1])
def test_lora_refinement_merges_and_serves_the_refined_weights(model_dirs, blocks):
    model = test_hf_model.load(model_dirs, "da")
    keys = set(model.encoder.state_dict())
    serving = ServingModel(model)
    whole = RefinementConfig(frozen_encoder_levels=0)  # the tiny model has 2 feature maps
    ttr = SfmTTR(model, TTRConfig(refinement=whole))  # checks the mode, keeps the snapshot
    before = model.predict(FRAME)[0]
    cfg = RefinementConfig(steps=8, lr=1e-3, trainable="lora", lora_rank=4,
                           trainable_blocks=blocks, frozen_encoder_levels=0)
    result = refine_encoder(model, supervision(model), cfg)
    assert result.steps_done == 8
    assert np.mean(result.loss_history[-2:]) < np.mean(result.loss_history[:2])
    # merged: the encoder is back to its own module tree and keys, with the refined output
    assert not trainable.has_lora(model) and set(model.encoder.state_dict()) == keys
    refined = model.predict(FRAME)[0]
    assert not np.allclose(refined, before)
    assert ttr.predictor.predict([FRAME])[0] is not None
    np.testing.assert_allclose(ttr.predictor.predict([FRAME])[0], refined)  # cache saw the merge
    serving.update(model.encoder.state_dict(), 1)
    np.testing.assert_allclose(serving.predict(FRAME)[0], refined, rtol=1e-5, atol=1e-6)
    ttr.weights.reset()  # the reset policy: back to the start-up weights
    np.testing.assert_array_equal(model.predict(FRAME)[0], before)
    ttr.close()


def test_lora_on_a_convolutional_model_is_refused_at_configuration():
    from sfm_ttr_ros.core.errors import InputError
    from sfm_ttr_ros.core.models.mobilenet import MobileDepthNet

    cfg = TTRConfig()
    cfg.refinement.trainable = "lora"
    with pytest.raises(InputError, match="attention projections"):
        SfmTTR(MobileDepthNet(), cfg)


def test_benchmark_runs_a_transformers_model(model_dirs, data):
    out = data / "out_hf"
    argv = ["benchmark", "--kitti-raw", str(data / "raw"), "--kitti-gt", str(data / "gt"),
            "--drive", test_benchmark.DRIVE, "--out", str(out), "--params-file",
            str(data / "small.yaml"), "--model", "hf", "--model-path", model_dirs["da"],
            "--steps", "3", "--lr", "1e-3", "--set", "refinement.trainable=lora",
            "--set", "refinement.lora_rank=2", "--set", "min_supervision_points=5",
            # Depth Anything predicts relative inverse depth: no metric source turns it into
            # metres (the KITTI profile's camera_height is refused for it)
            "--set", "metric.source=none"]
    assert test_benchmark.cli(argv) == 0
    res = json.loads((out / "results.json").read_text())
    text = json.dumps(res)
    assert "no_ttr" in text and "sfm_ttr" in text
