"""Faulted test inputs from a real (synthetic) dataset: the one feature path, re-rendered strokes, the cache."""

import numpy as np
import pytest

from models.offline.datasets.build import build
from models.offline.tradeoffs.cli import parse_runs
from models.offline.tradeoffs.faulted import CLEAN, SEGMENT_WINDOWS, faulted_inputs, variant
from models.tactile.config import STAT_NAMES


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return build("synthetic", tmp_path_factory.mktemp("ds") / "synthetic", n_textures=3, duration_s=13, image_size=256)


def test_touch_variants_through_the_feature_path_and_cached(dataset, tmp_path):
    textures = ["synth_000", "synth_001", "synth_002"]
    inputs = faulted_inputs(dataset, textures, tmp_path, visual=False, workers=1)
    assert inputs.visual is None
    speed_mean = STAT_NAMES.index("speed_mean") - len(STAT_NAMES)
    for i in range(3):
        clean = inputs.tactile[CLEAN][i]
        assert clean.shape == (SEGMENT_WINDOWS, 526)
        fast = inputs.tactile[variant("speed_fast", 2)][i]
        np.testing.assert_allclose(fast[:, speed_mean], 2 * clean[:, speed_mean], rtol=0.02)
        assert len(inputs.tactile[variant("gap", 200)][i]) < SEGMENT_WINDOWS  # 20 % of the time lost
        # the 20 Hz high-pass removes a constant bias: features unchanged
        np.testing.assert_allclose(inputs.tactile[variant("bias", 5)][i], clean, atol=1e-3)
        assert not np.allclose(inputs.tactile[variant("noise", 10)][i], clean)
    files = list(tmp_path.glob("faulted-tactile-*.npz"))
    assert len(files) == 1
    again = faulted_inputs(dataset, textures, tmp_path, visual=False, workers=1)
    np.testing.assert_array_equal(again.tactile[variant("noise", 0)][1], inputs.tactile[variant("noise", 0)][1])


def test_run_specs_are_parsed_or_refused():
    assert parse_runs(["ann:0,1:cal+aug", "mean:0", "svr-both:0:sub"]) == [
        ("ann", [0, 1], True, True, False),
        ("mean", [0], False, False, False),
        ("svr-both", [0], False, False, True),
    ]
    for bad in ("ann", "ann:x", "ann:0:fast", ":0", "ann:0:cal+sub"):
        with pytest.raises(ValueError):
            parse_runs([bad])
