"""The frontier's pieces: the sweep, interleaved timing, the pick rule and its nested check."""

import numpy as np
import pytest

from models.offline.tradeoffs.frontier import (
    Patching,
    backbone_paths,
    config_label,
    nested_rule_predictions,
    pick,
    sweep,
    time_frames,
)
from models.visual.config import VisualConfig


class FakeEmbedder:
    """Cost proportional to the number of patches, as a backbone's is."""

    name, dim, fingerprint = "fake", 3, "0" * 16

    def __init__(self):
        self.patches = 0

    def embed(self, patches):
        self.patches += len(patches)
        return np.stack([patches.mean(axis=(1, 2))] * 3, axis=1).astype(np.float32)


def test_sweep_covers_grids_and_sizes_and_adds_the_whole_frame():
    configs = sweep((7, 3, 1), (None, 448))
    assert Patching(7, None) in configs and Patching(3, 448) in configs and Patching(1, 224) in configs
    assert len(configs) == 7
    assert Patching(2, 448).visual_config() == VisualConfig(grid=2, resize=448, backbone="efficientnet_lite0")
    assert Patching(7, None).visual_config().hash() == VisualConfig().hash()  # today's default, today's hash


def test_the_int8_backbone_is_a_row_of_its_own():
    # Its own label, so its LOOCV predictions and timing never overwrite the fp32 row's.
    fp32 = config_label("efficientnet_lite0", Patching(2, None), glcm=False)
    int8 = config_label("efficientnet_lite0_int8", Patching(2, None), glcm=False)
    assert (fp32, int8) == ("effnet-lite0 2×2 @ native", "effnet-lite0-int8 2×2 @ native")
    assert Patching(2, None).visual_config("efficientnet_lite0_int8").backbone == "efficientnet_lite0_int8"
    with pytest.raises(ValueError, match="unknown backbone"):
        backbone_paths(("mobilenet",))


def test_timing_interleaves_every_configuration_and_reports_each_step():
    emb = FakeEmbedder()
    img = np.random.default_rng(0).random((600, 600)).astype(np.float32)
    configs = [Patching(3, None), Patching(1, 224)]
    rows = time_frames(img, configs, {("fake", 1): emb}, repeats=2)
    assert len(rows) == 2 and all(r["repeats"] == 2 for r in rows)
    assert emb.patches == 2 * (9 + 1) + 4  # two repeats of both, plus the warm-up's 2×2
    for r in rows:
        assert r["prep_ms"] >= 0 and r["embed_ms"] > 0 and r["glcm_ms"] > 0
    with pytest.raises(ValueError):
        time_frames(img, configs, {("fake", 1): emb}, repeats=0)


def test_descriptor_sets_multiply_the_sweep_and_are_timed_as_their_own_step():
    configs = sweep((2,), (None,), ((), ("spectrum", "grids")))
    assert configs == [Patching(2, None), Patching(2, None, ("spectrum", "grids"))]
    assert configs[1].label == "2×2 @ native + spectrum + grids"
    assert configs[1].visual_config(glcm=False) == VisualConfig(
        grid=2, backbone="efficientnet_lite0", glcm=False, descriptors=("spectrum", "grids")
    )
    img = np.random.default_rng(0).random((400, 400)).astype(np.float32)
    rows = time_frames(img, configs, {("fake", 1): FakeEmbedder()}, repeats=1)
    by = {tuple(r["descriptors"]): r for r in rows}
    assert by[()]["desc_ms"] < by[("spectrum", "grids")]["desc_ms"]  # without descriptors: the clock's overhead


def test_descriptor_sets_parse_from_the_command_line():
    from models.offline.tradeoffs.cli import descriptor_set

    assert descriptor_set("none") == () and descriptor_set("spectrum,grids") == ("spectrum", "grids")
    with pytest.raises(ValueError, match="descriptor set 'sift'"):
        descriptor_set("sift")


def test_pick_takes_the_cheapest_within_the_margin():
    mae = {"big": 5.0, "mid": 5.25, "small": 5.4, "tiny": 6.0}
    cost = {"big": 500.0, "mid": 100.0, "small": 40.0, "tiny": 5.0}
    assert pick(mae, cost) == "mid"
    assert pick(mae, cost, margin=0.5) == "small"


def test_nested_rule_uses_training_textures_only(linear_world_pair):
    datas, preds = linear_world_pair
    cost = {"good": 100.0, "noisy": 1.0}
    nested, picked = nested_rule_predictions(datas, preds, cost, "ridge-both", {}, folds=3)
    assert nested.shape == preds["good"].shape and len(picked) == len(preds["good"])
    # the noisy configuration is far worse inside every fold: the rule keeps the good one
    assert set(picked) == {"good"}
    np.testing.assert_allclose(nested, preds["good"])


@pytest.fixture(scope="module")
def linear_world_pair():
    from dataclasses import replace

    from models.offline.evaluation.estimator_registry import EstimatorSpec
    from models.offline.evaluation.loocv import loocv

    from .conftest import make_linear_world

    good = make_linear_world(n_textures=20)
    rng = np.random.default_rng(5)
    noisy = replace(
        good,
        visual=rng.normal(size=good.visual.shape).astype(np.float32),
        tactile=[rng.normal(size=w.shape).astype(np.float32) for w in good.tactile],
    )
    datas = {"good": good, "noisy": noisy}
    preds = {
        k: loocv(d, EstimatorSpec("ridge-both"), backend="serial", progress=False).predictions for k, d in datas.items()
    }
    return datas, preds


def test_frontier_rows_join_timing_and_accuracy_and_the_rule_picks_among_them():
    from models.offline.tradeoffs.frontier import Sweep, config_label, frontier_rows, recommendation

    targets = np.zeros((6, 4))
    big, small = Patching(3, None), Patching(1, 224)
    preds = {
        config_label("efficientnet_lite0", big, False): np.full((6, 4), 10.0),  # MAE 5 on the 0–100 scale
        config_label("efficientnet_lite0", small, False): np.full((6, 4), 10.4),  # MAE 5.2: within the margin
    }
    rows = [
        {"label": label, "grid": p.grid, "resize": p.resize, "glcm": False, "model_us": 10.0}
        for label, p in zip(preds, (big, small))
    ]
    timing = [
        {"backbone": "efficientnet_lite0", "threads": 1, "grid": p.grid, "resize": p.resize, **ms}
        for p, ms in (
            (big, {"prep_ms": 1.0, "embed_ms": 90.0, "glcm_ms": 9.0}),
            (small, {"prep_ms": 1.0, "embed_ms": 9.0, "glcm_ms": 1.0}),
        )
    ]
    scored = Sweep(rows, {}, preds)
    frontier = frontier_rows(timing, 100.0, scored, targets, glcm=(False,), threads=(1,))
    by_label = {r["label"]: r for r in frontier}
    assert len(frontier) == 2
    assert by_label[config_label("efficientnet_lite0", big, False)]["frame_ms"] == 91.0  # no GLCM: prep + embed
    assert by_label[config_label("efficientnet_lite0", small, False)]["mae"] == pytest.approx(5.2)
    assert by_label[config_label("efficientnet_lite0", small, False)]["window_us"] == 110.0
    assert all(r["pareto"] for r in frontier)  # one is cheaper, the other more accurate
    rec = recommendation(frontier, scored, targets, model="ridge-both", options={}, nested_folds=0, seed=0)
    assert rec is not None and rec["config"] == config_label("efficientnet_lite0", small, False)
    assert rec["best_mae"] == pytest.approx(5.0) and "nested" not in rec
    assert recommendation([], scored, targets, model="ridge-both", options={}, nested_folds=0, seed=0) is None
