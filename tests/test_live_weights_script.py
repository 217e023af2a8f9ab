"""scripts/studies/live_weights.py (docs/decisions.md, "Live serving"): the shrunk weights it
serves and the shares of the windowed gain it reports."""

import importlib.util
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "studies" / "live_weights.py"


@pytest.fixture(scope="module")
def study():
    spec = importlib.util.spec_from_file_location("live_weights", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_blended_weights_move_floats_by_alpha_and_keep_counters(study):
    theta0 = {"w": torch.tensor([0.0, 2.0]), "n": torch.tensor(3)}
    theta = {"w": torch.tensor([1.0, 4.0]), "n": torch.tensor(7)}
    half = study.blended(theta0, theta, 0.5)
    assert torch.equal(half["w"], torch.tensor([0.5, 3.0]))
    assert int(half["n"]) == 7  # BatchNorm's num_batches_tracked is not interpolated
    assert torch.equal(study.blended(theta0, theta, 1.0)["w"], theta["w"])
    assert torch.equal(study.blended(theta0, theta, 1.5)["w"], torch.tensor([1.5, 5.0]))


def test_gain_shares_are_against_no_ttr_and_the_windowed_output(study):
    shares = study.gain_shares({"no_ttr": [0.3, 1.0], "carried": [0.2, 0.9],
                                "windowed": [0.1, 0.5]})
    assert shares["no_ttr"] == [0.0, 0.0]
    assert shares["windowed"] == [1.0, 1.0]
    assert shares["carried"] == pytest.approx([0.5, 0.2])
