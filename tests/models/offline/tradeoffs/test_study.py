"""The robustness and interval machinery end to end on a small linear world: fits, faulted predictions, curves,
breaking points, augmentation, intervals and their coverage."""

import json

import numpy as np
import pytest

from models.offline.evaluation.bootstrap import per_texture_error
from models.offline.tradeoffs import analysis
from models.offline.tradeoffs.detection import calibration_distances, fold_checks, shift_checks
from models.offline.tradeoffs.faulted import CLEAN
from models.offline.tradeoffs.folds import partition
from models.offline.tradeoffs.robustness import summarise
from models.offline.tradeoffs.study import augment, expand_for_texture_models, run_study


@pytest.fixture(scope="module")
def summary(world):
    data, inputs = world
    part = partition(len(data), 4, seed=0)
    tables = {
        "folds": fold_checks(data, inputs, with_visual=True),
        "calibration": calibration_distances(data, inputs, part, with_visual=True),
        "shift": shift_checks(data, inputs, with_visual=True),
    }
    runs = {
        "mean": [run_study(data, inputs, part, "mean", seed=0, shift=False)],
        "ridge-both": [run_study(data, inputs, part, "ridge-both", seed=0, calibration=True, augmentation=True)],
    }
    return data, runs, summarise(data, runs, tables, part)


def test_loocv_clean_prediction_is_the_ordinary_loocv(world, summary):
    from models.offline.evaluation.estimator_registry import EstimatorSpec
    from models.offline.evaluation.loocv import loocv

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
    # on this world ridge degrades (4 MAE at 0 dB) but stays far from predict-the-mean (about 16): never broken
    assert maes[-1] < s["reference_mean_mae"]
    assert not bp["reached"] and bp["breaking_point"] is None
    assert bp["worst_mae"] == pytest.approx(max(maes))
    flat = [r["mae"] for r in s["robustness"] if r["model"] == "mean" and r["fault"] == "noise"]
    assert max(flat) - min(flat) < 1e-9  # predict-the-mean ignores its input


def test_breaking_point_is_where_the_curve_first_reaches_the_reference():
    from models.offline.tradeoffs.analysis import breaking_point

    curve = [{"strength": float("inf"), "mae": 2.0}, {"strength": 30.0, "mae": 4.0}, {"strength": 10.0, "mae": 12.0}]
    assert breaking_point(curve, 8.0) == pytest.approx(20.0)  # half way from 4 to 12, half way from 30 to 10
    assert breaking_point(curve, 3.0) == 30.0  # from clean to the first strength: the first strength
    assert breaking_point(curve, 1.0) == float("inf")  # broken when clean
    assert breaking_point(curve, 13.0) is None


def test_a_model_run_on_a_subset_of_folds_is_judged_on_those_textures(world, summary):
    data, runs, full = summary
    inputs = world[1]
    part = partition(len(data), 4, seed=0)
    held = np.array([0, 2, 5])
    sub = run_study(data, inputs, part, "ridge-both", seed=0, shift=False, held_out=held)
    assert sub.held_out == [0, 2, 5]
    assert [p is not None for p in sub.loocv[CLEAN]] == [i in (0, 2, 5) for i in range(len(data))]
    for i in held:  # the same fold fits the same model: the same prediction as the full run
        np.testing.assert_allclose(sub.loocv[CLEAN][i].texture, runs["ridge-both"][0].loocv[CLEAN][i].texture)
    tables = {"folds": fold_checks(data, inputs, with_visual=True), "calibration": {}, "shift": {}}
    s = summarise(data, {"mean": runs["mean"], "ridge-sub": [sub]}, tables, part)
    truth = data.targets.astype(float)
    mean_pred = np.stack([runs["mean"][0].loocv[CLEAN][i].texture for i in held])
    assert s["clean"]["ridge-sub"]["n_textures"] == 3 and s["clean"]["ridge-sub"]["subset"]
    assert s["clean"]["ridge-sub"]["reference_mean_mae"] == pytest.approx(
        per_texture_error(mean_pred, truth[held]).mean()
    )
    assert s["spread"]["ridge-sub"]["n_textures"] == 3
    assert all(r["n_textures"] <= 3 for r in s["robustness"] if r["model"] == "ridge-sub")
    with pytest.raises(ValueError, match="held_out"):
        run_study(data, inputs, part, "ridge-both", held_out=np.array([len(data)]))


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
        lo, hi = r["empirical_ci"]  # over textures: the mean lies inside, and textures disagree somewhere
        assert 0 <= lo <= r["empirical"] <= hi <= 1
    assert any(r["empirical_ci"][1] - r["empirical_ci"][0] > 0.01 for r in rows)
    clean = [r for r in rows if r["condition"] == CLEAN and r["target"] == "texture" and r["scale"] == "none"]
    for r in clean:  # 24 textures: loose, but an interval that means nothing would miss it
        assert abs(r["empirical"] - r["nominal"]) < 0.2
    # under 0 dB noise the detector flags the windows, and the widened interval still covers
    severe = next(
        r
        for r in rows
        if r["condition"] == "noise@0" and r["target"] == "window" and r["scale"] == "none" and r["nominal"] == 0.9
    )
    assert severe["flagged"] > 0.8 and severe["empirical"] >= 0.8
    assert s["recommended_intervals"]["ridge-both"]["target"] in ("window", "ema")
    # the rule run inside the folds: one pick per held-out texture, and what the picks cover clean
    nested = s["nested_intervals"]["ridge-both"]
    n_clean = next(r["n_textures"] for r in rows if r["condition"] == CLEAN)
    assert sum(nested["picks"].values()) == n_clean
    assert {name.split("/")[0] for name in nested["picks"]} <= {"window", "ema"}
    assert [c["nominal"] for c in nested["clean"]] == [0.8, 0.9]
    for c in nested["clean"]:
        assert c["n_textures"] == n_clean and abs(c["empirical"] - c["nominal"]) < 0.2


def test_spread_and_shift_are_numbers(summary):
    data, runs, s = summary
    sp = s["spread"]["ridge-both"]
    assert sp["fold_std"] > 0 and sp["fold_iqr"][0] <= sp["fold_iqr"][1] <= sp["fold_worst"]
    assert s["shift"]["ridge-both"]["mae"] > 0 and set(s["shift"]["ridge-both"]["per_group"]) == set(data.groups)
    err = per_texture_error(analysis.seed_mean(runs["ridge-both"], CLEAN)[0], data.targets)
    assert s["clean"]["ridge-both"]["mae"] == pytest.approx(float(err.mean()))


def _frontier_rows():
    """Rendering input for the report test (hand-made rows; the frontier's own numbers come from its run)."""
    rows = []
    for label, ms, mae, pareto in (
        ("effnet-lite0 7×7 @ native + GLCM", 480.0, 5.7, True),
        ("effnet-lite0 1×1 @ 448", 40.0, 5.9, True),
        ("effnet-lite0 3×3 @ 640", 120.0, 6.1, False),
    ):
        ci = {"mean": mae, "lo": mae - 0.5, "hi": mae + 0.5}
        rows.append(
            {
                "config": label + " · 1 thread",
                "label": label,
                "backbone": "efficientnet_lite0",
                "weights": "ImageNet weights",
                "grid": 7,
                "resize": None,
                "glcm": "GLCM" in label,
                "threads": 1,
                "frame_ms": ms,
                "prep_ms": 1.0,
                "embed_ms": ms - 2,
                "glcm_ms": 1.0,
                "mae": mae,
                "mae_ci": ci,
                "window_us": 300.0,
                "model_us": 20.0,
                "vs_best": {"mean": mae - 5.7, "lo": -0.2, "hi": 0.6},
                "pareto": pareto,
            }
        )
    rows.append(
        {
            **rows[0],
            "backbone": "resnet50",
            "label": "resnet50 7×7 @ native + GLCM",
            "mae": None,
            "pareto": False,
            "window_us": None,
            "frame_ms": 1900.0,
        }
    )
    return {
        "model": "ridge-both",
        "seeds": [0],
        "views_per_image": 1,
        "n_textures": 24,
        "tactile_window_us": 280.0,
        "timing_repeats": 3,
        "timing_image": {"texture": "t00", "shape": [1024, 1024]},
        "frontier": rows,
        "recommendation": {
            "config": rows[1]["label"],
            "mae": 5.9,
            "mae_ci": rows[1]["mae_ci"],
            "frame_ms_1thread": 40.0,
            "best_config": rows[0]["label"],
            "best_mae": 5.7,
            "target_met": True,
            "rule": "the rule",
            "nested": {"folds": 5, "mae": {"mean": 6.0, "lo": 5.5, "hi": 6.5}, "picked": {rows[1]["label"]: 24}},
        },
        "load_before": {"loadavg_1_5_15": [1, 1, 1]},
        "load_after": {"loadavg_1_5_15": [1, 1, 1]},
        "note": "under load",
    }


def test_report_page_charts_and_results_in_the_issue_shape(summary, tmp_path):
    from models.offline.tradeoffs.common import write_json
    from models.offline.tradeoffs.report import build_tradeoffs_report

    _, _, s = summary
    write_json(tmp_path / "robustness.json", s)
    write_json(tmp_path / "frontier-ridge-both.json", _frontier_rows())
    page = build_tradeoffs_report(tmp_path).read_text()
    for heading in ("## 1. The frontier", "## 2. Stability", "## 3. Intervals", "## 4. Adaptive serving", "*Pending*"):
        assert heading in page
    assert "Run inside the folds" in page and "predates the rule's nested run" not in page
    assert s["augmentation"] and "older than the fix" not in page
    write_json(tmp_path / "robustness.json", {k: v for k, v in s.items() if k != "augmentation_loo"})
    assert "older than the fix" in build_tradeoffs_report(tmp_path).read_text()  # a run from before it says so
    write_json(tmp_path / "robustness.json", s)
    for png in (
        "frontier-ridge-both.png",
        "robustness-touch.png",
        "robustness-camera.png",
        "augmentation.png",
        "coverage-vs-windows.png",
        "coverage-ridge-both.png",
    ):
        assert (tmp_path / png).stat().st_size > 5000 and png in page
    text = (tmp_path / "results.json").read_text()
    assert "Infinity" not in text and "NaN" not in text  # strict JSON
    results = json.loads(text)
    assert set(results) >= {"frontier", "robustness", "coverage", "adaptive"}
    assert {"config", "mae", "window_us", "frame_ms", "pareto"} <= set(results["frontier"][0])
    assert {"model", "fault", "strength", "mae"} <= set(results["robustness"][0])
    assert {"model", "condition", "nominal", "empirical"} <= set(results["coverage"][0])
    assert results["adaptive"]["pending"]
    write_json(
        tmp_path / "adaptive.json",
        {"compute_ratio": 6.0, "mae_full": 5.2, "mae_adaptive": 5.3, "choice_agreement": 0.97},
    )
    page = build_tradeoffs_report(tmp_path).read_text()
    assert "compute ratio 6.00×" in page and "*Pending*" not in page
    assert json.loads((tmp_path / "results.json").read_text())["adaptive"]["compute_ratio"] == 6.0


def test_two_runs_of_one_model_get_their_own_charts_and_the_served_pick_is_marked(tmp_path):
    from models.offline.featurize import SERVED_VISUAL
    from models.offline.tradeoffs.common import write_json
    from models.offline.tradeoffs.report import build_tradeoffs_report

    fp32 = {**_frontier_rows(), "model": "selected"}
    served = {**_frontier_rows(), "model": "selected"}
    served["frontier"] = [
        {**r, "label": r["label"].replace("effnet-lite0", "effnet-lite0-int8")} for r in fp32["frontier"]
    ]
    served["recommendation"] = {
        **fp32["recommendation"],
        "config": served["frontier"][1]["label"],
        "backbone": SERVED_VISUAL.backbone,
        "visual_config": SERVED_VISUAL.model_dump(exclude={"backbone", "resnet50_weights"}),
    }
    # the fp32 run's pick names the served grid too, on another backbone: not the served configuration
    fp32["recommendation"] = {**served["recommendation"], "backbone": "efficientnet_lite0"}
    write_json(tmp_path / "frontier-selected.json", fp32)
    write_json(tmp_path / "frontier-quant.json", served)
    page = build_tradeoffs_report(tmp_path).read_text()
    for name in ("selected", "quant"):
        assert (tmp_path / f"frontier-{name}.png").stat().st_size > 5000 and f"(frontier-{name}.png)" in page
        assert f"(`frontier-{name}.json`)" in page
    assert page.count("The served models read this configuration") == 1
    quant = page.index("(`frontier-quant.json`)")
    assert quant < page.index("The served models read this configuration") < page.index("(`frontier-selected.json`)")
    assert "- **Frontier** (selected; effnet-lite0-int8; served)" in page
    assert "- **Frontier** (selected; effnet-lite0):" in page
    runs = {r["run"] for r in json.loads((tmp_path / "results.json").read_text())["frontier"]}
    assert runs == {"selected", "quant"}


def test_detector_tables_in_worker_processes_equal_the_serial_ones(world):
    data, inputs = world
    part = partition(len(data), 4, seed=0)
    for fn, args in ((fold_checks, ()), (calibration_distances, (part,)), (shift_checks, ())):
        serial, forked = fn(data, inputs, *args, with_visual=True), fn(data, inputs, *args, with_visual=True, workers=2)
        assert serial.keys() == forked.keys()
        for k in serial:
            a, b = serial[k], forked[k]
            pairs = zip(a, b) if isinstance(a, list) else ((a[j], b[j]) for j in a) if isinstance(a, dict) else [(a, b)]
            for x, y in pairs:
                np.testing.assert_array_equal(getattr(x, "distance", x), getattr(y, "distance", y))


def test_a_pick_made_inside_the_folds_is_reported_with_the_procedures_mae(tmp_path):
    from models.offline.tradeoffs.common import write_json
    from models.offline.tradeoffs.report import build_tradeoffs_report

    legacy = _frontier_rows()
    inside = _frontier_rows()
    a, b = inside["frontier"][0]["label"], inside["frontier"][1]["label"]
    inside["recommendation"] = {
        **legacy["recommendation"],
        "chosen_by": "inner 5-fold CV over all 24 rated textures (seed 0)",
        "inner_mae": {a: 5.8, b: 6.0},
        "pick_inner_mae": 6.0,
        "best_config": a,
        "best_mae": 5.8,
        "mae": 6.1,
        "mae_ci": {"mean": 6.1, "lo": 5.6, "hi": 6.7},
        "loocv_mae": 5.9,
        "loocv_mae_ci": {"mean": 5.9, "lo": 5.4, "hi": 6.4},
        "nested": {"folds": 5, "mae": {"mean": 6.1, "lo": 5.6, "hi": 6.7}, "picked": {b: 20, a: 4}},
    }
    write_json(tmp_path / "frontier-quant.json", inside)
    write_json(tmp_path / "frontier-ridge-both.json", legacy)
    page = build_tradeoffs_report(tmp_path).read_text()
    new = page[page.index("(`frontier-quant.json`)") :]
    new = new[: new.index("| configuration |")]
    assert f"chosen inside the folds: `{b}`" in new
    assert f"`{a}` 5.80, `{b}` 6.00 — never the LOOCV numbers" in new
    assert "scores **MAE 6.10 [5.60, 6.70]**" in new and f"`{b}` ×20, `{a}` ×4" in new
    assert "The picked row's own LOOCV MAE, 5.90 [5.40, 6.40]" in new
    old = page[page.index("(`frontier-ridge-both.json`)") :]
    assert "picked on the LOOCV table it reports" in old[: old.index("| configuration |")]
    assert "picked inside the folds (inner-CV MAE 6.00 vs best 5.80); the procedure scores MAE 6.10" in page
    assert "at MAE 5.90 vs best 5.70 (picked on its own LOOCV folds)" in page
