"""The synthetic world's known mapping is recovered where the paper's tactile features can see it.

Documented threshold (README, reports/synthetic): leave-one-texture-out, tactile-only ridge on
the 526 MFCC features, error against the noise-free ratings of the documented mapping:
rough–smooth and hard–soft at most 0.7 × predict-the-mean's error. The features cannot
resolve the cues of flat–bumpy (a resonance below the 40 Hz resolution of 25 ms MFCC frames)
or sticky–slippery (no friction channel among the 526 features); those are not asserted.
"""

import numpy as np
import pytest

from models.offline.datasets.build import build
from models.offline.evaluation.data import load_texture_data
from models.offline.evaluation.estimator_registry import EstimatorSpec
from models.offline.evaluation.loocv import loocv
from models.offline.evaluation.metrics import error_table

THRESHOLD = 0.7


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = build(
        "synthetic", tmp_path_factory.mktemp("world") / "ds", n_textures=32, duration_s=6, seed=1, image_size=256
    )
    return load_texture_data(root, visual=False)


def test_touch_recovers_roughness_and_hardness(world):
    truth = world.meta["true_ratings"]
    model = error_table(
        loocv(world, EstimatorSpec("ridge-tactile"), backend="serial", progress=False).predictions, truth
    )
    mean = error_table(loocv(world, EstimatorSpec("mean"), backend="serial", progress=False).predictions, truth)
    for attr in ("rough_smooth", "hard_soft"):
        assert model["mae"][attr] <= THRESHOLD * mean["mae"][attr], (attr, model["mae"][attr], mean["mae"][attr])
    assert np.isfinite(model["mae"]["mean"])
