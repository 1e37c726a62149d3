"""The frontier's pieces: the sweep, interleaved timing, the pick rule, chosen inside the folds, and its nested run."""

import numpy as np
import pytest

from models.offline.tradeoffs.frontier import (
    Patching,
    backbone_paths,
    config_label,
    inner_cv_mae,
    nested_rule_predictions,
    pick,
    served_pick,
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
    _, in_workers = nested_rule_predictions(datas, preds, cost, "ridge-both", {}, folds=3, workers=2)
    assert in_workers == picked  # outer folds in worker processes: the same picks
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
    # no inner folds, no pick: the table alone (the rule never reads these LOOCV rows)
    assert recommendation(frontier, scored, targets, model="ridge-both", options={}, nested_folds=0, seed=0) is None
    assert recommendation([], scored, targets, model="ridge-both", options={}, nested_folds=5, seed=0) is None


def test_inner_cv_reads_nothing_outside_its_training_textures(linear_world_pair):
    from dataclasses import replace

    from models.offline.evaluation.estimator_registry import EstimatorSpec

    datas, _ = linear_world_pair
    train = np.arange(1, 20)  # texture 0 held out
    spec = EstimatorSpec("ridge-both")
    before = inner_cv_mae(datas, train, spec, folds=3)
    rng = np.random.default_rng(1)
    spoiled = {}
    for k, d in datas.items():  # the held-out texture's ratings, windows and image features replaced by noise
        targets, visual = d.targets.copy(), d.visual.copy()
        targets[0] = rng.uniform(-1, 1, 4)
        visual[0] = rng.normal(size=visual[0].shape) * 100
        tactile = [rng.normal(size=d.tactile[0].shape).astype(np.float32) * 100, *d.tactile[1:]]
        spoiled[k] = replace(d, targets=targets, visual=visual, tactile=tactile)
    assert inner_cv_mae(spoiled, train, spec, folds=3) == before
    assert before["good"] < before["noisy"]
    with pytest.raises(ValueError, match="2 ≤ folds"):
        inner_cv_mae(datas, train, spec, folds=1)
    other = {**datas, "noisy": datas["noisy"].take(np.arange(1, 20))}
    with pytest.raises(ValueError, match="other textures"):
        inner_cv_mae(other, train[:5], spec, folds=3)


def test_the_served_pick_cannot_read_the_outer_folds(linear_world_pair):
    """The pick comes from inner CV over the training textures: outer LOOCV predictions that would flip a rule
    reading them (the cheap configuration perfect, the good one far off) leave the pick where it was."""
    from models.offline.tradeoffs.frontier import Sweep, frontier_rows, recommendation

    datas, preds = linear_world_pair
    good = config_label("efficientnet_lite0", Patching(2, None), False)
    cheap = config_label("efficientnet_lite0_int8", Patching(2, None), False)
    data = {good: datas["good"], cheap: datas["noisy"]}
    targets = datas["good"].targets
    rows = [{"label": k, "grid": 2, "resize": None, "glcm": False, "model_us": 10.0} for k in data]
    timing = [
        {"backbone": b, "threads": 1, "grid": 2, "resize": None, "prep_ms": 0.1, "embed_ms": ms, "glcm_ms": 5.0}
        for b, ms in (("efficientnet_lite0", 17.0), ("efficientnet_lite0_int8", 8.0))
    ]

    def recommend(outer: dict[str, np.ndarray]) -> tuple[dict, str]:
        """The recommendation, and what the rule would pick on these outer LOOCV rows."""
        scored = Sweep(rows, data, outer)
        frontier = frontier_rows(timing, 100.0, scored, targets, glcm=(False,), threads=(1,))
        rec = recommendation(frontier, scored, targets, model="ridge-both", options={}, nested_folds=3, seed=0)
        assert rec is not None
        return rec, pick({r["label"]: r["mae"] for r in frontier}, {r["label"]: r["frame_ms"] for r in frontier})

    honest, on_outer = recommend({good: preds["good"], cheap: preds["noisy"]})
    assert on_outer == good
    rec, on_outer = recommend({good: np.clip(targets + 0.5, -1, 1), cheap: targets.copy()})
    # a rule on these LOOCV rows would serve the cheap configuration; the pick inside the folds does not move
    assert on_outer == cheap
    assert honest["config"] == rec["config"] == good
    assert honest["inner_mae"] == rec["inner_mae"] and rec["inner_mae"][good] < rec["inner_mae"][cheap]
    assert rec["nested"]["picked"] == {good: len(targets)}
    # the headline is the procedure's own score on the outer predictions it made: it moves with them
    assert honest["mae"] == pytest.approx(honest["loocv_mae"]) and rec["mae"] == pytest.approx(rec["loocv_mae"])
    assert rec["mae"] > honest["mae"] and rec["mae_ci"]["lo"] <= rec["mae"] <= rec["mae_ci"]["hi"]
    assert rec["backbone"] == "efficientnet_lite0" and rec["visual_config"]["grid"] == 2


def test_served_pick_is_the_rule_on_every_rated_texture(linear_world_pair):
    from models.offline.evaluation.estimator_registry import EstimatorSpec

    datas, _ = linear_world_pair
    cost = {"good": 100.0, "noisy": 1.0}
    choice, inner = served_pick(datas, cost, "ridge-both", {}, folds=3)
    assert inner == inner_cv_mae(datas, np.arange(20), EstimatorSpec("ridge-both"), folds=3)
    assert choice == pick(inner, cost) == "good"
    # within the margin the cheaper one wins: the same inner numbers, the cost turned around
    assert pick({"good": 5.0, "noisy": 5.2}, cost) == "noisy"
