"""The §2/§3 machinery end to end on a small linear world: fits, faulted predictions, curves,
breaking points, augmentation, intervals and their coverage."""

import numpy as np
import pytest

from models.evaluation.bootstrap import per_texture_error
from models.tradeoffs import analysis
from models.tradeoffs.detection import calibration_distances, fold_checks, shift_checks
from models.tradeoffs.faulted import CLEAN
from models.tradeoffs.folds import partition
from models.tradeoffs.robustness import summarise
from models.tradeoffs.study import augment, expand_for_texture_models, run_study


@pytest.fixture(scope="module")
def summary(world):
    data, inputs = world
    part = partition(len(data), 4, seed=0)
    tables = {"folds": fold_checks(data, inputs, with_visual=True),
              "calibration": calibration_distances(data, inputs, part, with_visual=True),
              "shift": shift_checks(data, inputs, with_visual=True)}
    runs = {"mean": [run_study(data, inputs, part, "mean", seed=0, shift=False)],
            "ridge-both": [run_study(data, inputs, part, "ridge-both", seed=0, calibration=True, augmentation=True)]}
    return data, runs, summarise(data, runs, tables, part)


def test_loocv_clean_prediction_is_the_ordinary_loocv(world, summary):
    from models.evaluation.loocv import loocv
    from models.evaluation.registry import EstimatorSpec

    data, runs, _ = summary
    ordinary = loocv(data, EstimatorSpec("ridge-both"), backend="serial", progress=False).predictions
    ours = np.stack([p.texture for p in runs["ridge-both"][0].loocv[CLEAN]])
    np.testing.assert_allclose(ours, ordinary, atol=1e-6)


def test_noise_curve_rises_and_breaks_where_the_mean_is_reached(summary):
    data, runs, s = summary
    curve = [r for r in s["robustness"] if r["model"] == "ridge-both" and r["fault"] == "noise"]
    maes = [r["mae"] for r in curve]
    assert maes[-1] > 2 * maes[0]  # 0 dB noise three times the signal: far worse than clean
    bp = next(b for b in s["breaking_points"] if b["model"] == "ridge-both" and b["fault"] == "noise")
    ref = s["reference_mean_mae"]
    if maes[-1] >= ref:
        assert bp["reached"] and 0 <= bp["breaking_point"] <= 40
    else:
        assert not bp["reached"]
    flat = [r["mae"] for r in s["robustness"] if r["model"] == "mean" and r["fault"] == "noise"]
    assert max(flat) - min(flat) < 1e-9  # predict-the-mean ignores its input


def test_augmentation_is_reported_before_and_after(summary):
    _, _, s = summary
    blocks = {(a["model"], a["fault"]) for a in s["augmentation"]}
    assert ("ridge-both", "noise") in blocks and ("ridge-both", "blur") in blocks
    noise = next(a for a in s["augmentation"] if a["fault"] == "noise")
    # trained on noisy copies, ridge loses less under strong noise
    assert noise["after"][-1]["mae"] < noise["before"][-1]["mae"]


def test_augmented_training_set_holds_copies_of_training_textures_only(world):
    data, inputs = world
    train_idx = np.arange(1, len(data))
    expanded = expand_for_texture_models(augment(data.take(train_idx), inputs, train_idx))
    assert data.textures[0] not in expanded.textures
    assert len(expanded) == len(train_idx) * (1 + 4 + 3)  # clean + 4 noisy + 3 blurred copies


def test_coverage_rows_for_every_condition_target_and_level(summary):
    _, _, s = summary
    rows = [r for r in s["coverage"] if r["model"] == "ridge-both"]
    conditions = {r["condition"] for r in rows}
    assert {CLEAN, "noise@0", "blur@16", "no_frame@1", "shift"} <= conditions
    assert {(r["target"], r["nominal"]) for r in rows} >= {("window", 0.8), ("ema", 0.9), ("texture", 0.9)}
    for r in rows:
        assert 0 <= r["empirical"] <= 1 and 0 <= r["flagged"] <= 1 and r["width"] > 0
    clean = [r for r in rows if r["condition"] == CLEAN and r["target"] == "texture" and r["scale"] == "none"]
    for r in clean:  # 24 textures: loose, but an interval that means nothing would miss it
        assert abs(r["empirical"] - r["nominal"]) < 0.2
    # under 0 dB noise the detector flags the windows, and the widened interval still covers
    severe = next(r for r in rows if r["condition"] == "noise@0" and r["target"] == "window"
                  and r["scale"] == "none" and r["nominal"] == 0.9)
    assert severe["flagged"] > 0.8 and severe["empirical"] >= 0.8
    assert s["recommended_intervals"]["ridge-both"]["target"] in ("window", "ema")


def test_spread_and_shift_are_numbers(summary):
    data, runs, s = summary
    sp = s["spread"]["ridge-both"]
    assert sp["fold_std"] > 0 and sp["fold_iqr"][0] <= sp["fold_iqr"][1] <= sp["fold_worst"]
    assert s["shift"]["ridge-both"]["mae"] > 0 and set(s["shift"]["ridge-both"]["per_group"]) == set(data.groups)
    err = per_texture_error(analysis.seed_mean(runs["ridge-both"], CLEAN)[0], data.targets)
    assert s["clean"]["ridge-both"]["mae"] == pytest.approx(float(err.mean()))
