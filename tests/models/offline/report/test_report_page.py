"""The report page: tables from results.json files, targets, the speed–accuracy chart and its Pareto frontier."""

import json
import re

import numpy as np
import pytest

from models.offline.datasets.build import build
from models.offline.evaluation.data import load_texture_data
from models.offline.evaluation.estimator_registry import EstimatorSpec
from models.offline.evaluation.evaluate import evaluate
from models.offline.report.evaluation_figures import results_figures
from models.offline.report.markdown import _ablation_label, build_report
from models.offline.report.speed_accuracy import pareto_front


def test_pareto_front_known_answer():
    latency = np.array([10, 20, 30, 15, 40])
    error = np.array([5.0, 4.0, 4.5, 6.0, 3.0])
    # (30, 4.5) is beaten by (20, 4.0); (15, 6.0) by (10, 5.0)
    assert pareto_front(latency, error).tolist() == [True, True, False, False, True]
    with pytest.raises(ValueError, match="equal length"):
        pareto_front(latency, error[:2])


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    root = tmp_path_factory.mktemp("report")
    dataset = build("synthetic", root / "ds", n_textures=8, duration_s=3, image_size=256)
    data = load_texture_data(dataset, visual=False)
    for name in ("mean", "ridge-tactile", "knn-tactile"):
        out = root / "reports" / name
        res = evaluate(data, EstimatorSpec(name), out, seeds=(0,), workers=1, backend="serial", progress=False)
        results_figures(res, data.textures, data.targets, out)  # as `hapticlink evaluate` does
    return dataset, root / "reports"


def test_ablation_label_names_the_features_of_every_modality_a_model_reads():
    assert _ablation_label({"modality": "visual", "features": {"visual_part": "glcm"}}) == "visual glcm"
    assert _ablation_label({"modality": "tactile", "features": {"tactile_features": "dwt"}}) == "tactile dwt"
    both = {"modality": "both", "features": {"visual_part": "backbone", "tactile_features": "dft"}}
    assert _ablation_label(both) == "visual backbone + tactile dft"


def test_evaluate_writes_results_and_results_figures_draws_them(reports):
    _, folder = reports
    res = json.loads((folder / "ridge-tactile" / "results.json").read_text())
    assert set(res["mae"]) == {"rough_smooth", "flat_bumpy", "sticky_slippery", "hard_soft", "mean"}
    assert len(res["predictions"]) == res["n_textures"] == 8
    assert "truth" not in res  # committed results carry no human ratings
    assert list(res["predictions_per_seed"]) == ["0"] and len(res["predictions_per_seed"]["0"]) == 8
    assert res["latency_us"]["runtime"] == "onnxruntime" and res["latency_us"]["p50_us"] > 0
    assert res["vs_true_mapping"]["mae"]["mean"] > 0  # the synthetic world knows its noise-free ratings
    # what it was made from: the commit (None outside a git checkout) and the inputs it was handed (none here)
    commit = res["provenance"]["commit"]
    assert res["provenance"]["inputs"] == [] and (commit is None or len(commit) == 40)
    for fig in ("actual_vs_predicted.png", "group_mae.png", "perceptual_space.png"):
        assert (folder / "ridge-tactile" / fig).stat().st_size > 10_000


def test_report_page_lists_every_model_with_the_ceiling_and_the_chart(reports):
    dataset, folder = reports
    page = build_report(dataset, folder, regenerate="bash reports/regenerate.sh", reference="ridge-tactile").read_text()
    for name in (
        "| mean |",
        "| ridge-tactile |",
        "| knn-tactile |",
        "*human split-half*",
        "bash reports/regenerate.sh",
    ):
        assert name in page
    assert "speed_accuracy.png" in page and (folder / "speed_accuracy.png").is_file()
    assert "## Against the targets" in page
    # tables are sorted by mean MAE: the first data row is the best model
    first_row = page.split("## MAE")[1].split("\n")[4]
    maes = {
        n: json.loads((folder / n / "results.json").read_text())["mae"]["mean"]
        for n in ("mean", "ridge-tactile", "knn-tactile")
    }
    assert first_row.startswith(f"| {min(maes, key=maes.get)} |")


def test_every_mae_on_the_page_has_its_interval_and_a_paired_comparison(reports):
    dataset, folder = reports
    page = build_report(dataset, folder, reference="ridge-tactile").read_text()
    mean_row = next(line for line in page.split("## MAE")[1].split("\n") if line.startswith("| mean "))
    cells = [c.strip() for c in mean_row.strip("|").split("|")]
    res = json.loads((folder / "mean" / "results.json").read_text())
    # each attribute cell: value [lo, hi], the interval around the value
    for cell, key in zip(cells[4:8], ("rough_smooth", "flat_bumpy", "sticky_slippery", "hard_soft")):
        value, lo, hi = (float(x) for x in re.match(r"([\d.]+) \[([\d.]+), ([\d.]+)\]", cell).groups())
        assert value == pytest.approx(res["mae"][key], abs=0.005) and lo <= value <= hi
    assert "## Paired comparison against ridge-tactile" in page and "Δ mean vs ridge-tactile" in page
    assert re.search(r"\| mean [^|]*\|( [+-][\d.]+ \[[+-]?[\d.]+, [+-]?[\d.]+\] \|){5}", page)


def test_the_views_section_plots_error_against_views_pooled(reports, tmp_path):
    dataset, folder = reports
    res = json.loads((folder / "mean" / "results.json").read_text())
    work = tmp_path / "reports"
    (work / "mean").mkdir(parents=True)
    (work / "mean" / "results.json").write_text(json.dumps({**res, "views": 8}))  # the main run pooled 8 views
    for k in (1, 2, 4):
        (work / "views" / f"mean-v{k}").mkdir(parents=True)
        (work / "views" / f"mean-v{k}" / "results.json").write_text(json.dumps({**res, "views": k}))
    (work / "views" / "other-v8").mkdir(parents=True)
    (work / "views" / "other-v8" / "results.json").write_text(json.dumps({**res, "model": "other", "views": 8}))
    (work / "views" / "mean-shown1").mkdir(parents=True)
    (work / "views" / "mean-shown1" / "results.json").write_text(json.dumps({**res, "views": 4, "test_views": 1}))
    page = build_report(dataset, work).read_text()
    assert "## Views pooled" in page and "| model | k = 1 | k = 2 | k = 4 | k = 8 |" in page
    assert "| mean, fit on 4, shown k | " in page
    # views/ has no mean-v8: the main table's run, which pooled 8 views, stands in (marked *); "other" has only k = 8
    section = page.split("## Views pooled")[1].split("\n## ")[0]
    mean_row = next(line for line in section.split("\n") if line.startswith("| mean | "))
    assert mean_row.endswith(" * |") and mean_row.count(" * ") == 1 and mean_row.count("[") == 4
    other_row = next(line for line in section.split("\n") if line.startswith("| other | "))
    assert other_row.startswith("| other | — | — | — | ") and " * " not in other_row
    assert (work / "views_curve.png").stat().st_size > 10_000


def test_the_report_reads_ratings_from_the_dataset_and_says_when_they_are_missing(reports, tmp_path):
    dataset, folder = reports
    res = json.loads((folder / "mean" / "results.json").read_text())
    res["predictions"]["not_in_dataset"] = res["predictions"]["synth_000"]
    (tmp_path / "mean").mkdir()
    (tmp_path / "mean" / "results.json").write_text(
        json.dumps({k: v for k, v in res.items() if k != "predictions_per_seed"})
    )
    with pytest.raises(ValueError, match=r"no ratings for \['not_in_dataset'\]; pass the dataset the run used"):
        build_report(dataset, tmp_path)


def test_report_without_results_says_what_to_run(tmp_path, reports):
    dataset, _ = reports
    with pytest.raises(ValueError, match="run `hapticlink evaluate"):
        build_report(dataset, tmp_path)


def test_no_committed_results_carry_human_ratings():
    from pathlib import Path

    reports = Path(__file__).resolve().parents[4] / "reports"
    files = sorted(reports.rglob("results.json"))
    assert files, "the repository's reports/ holds results"
    carrying = [str(p.relative_to(reports)) for p in files if "truth" in json.loads(p.read_text())]
    assert carrying == []


def _copy_runs(folder, work, names):
    for src, dst in names.items():
        (work / dst).mkdir(parents=True)
        (work / dst / "results.json").write_text((folder / src / "results.json").read_text())


def test_the_readme_table_is_written_from_the_results_between_its_markers(reports, tmp_path):
    from models.offline.report.markdown import README_BEGIN, README_END, TARGET_MEAN_MAE

    dataset, folder = reports
    work = tmp_path / "reports"
    _copy_runs(folder, work, {"mean": "mean", "ridge-tactile": "ridge-tactile", "knn-tactile": "selected"})
    readme = tmp_path / "README.md"
    readme.write_text(f"# title\n\nbefore\n{README_BEGIN}\n| stale | row |\n{README_END}\nafter\n")
    rows = {"selected": "the pick", "ridge-tactile": "ridge, touch", "mean": "predict the mean"}
    build_report(dataset, work, reference="ridge-tactile", readme=readme, readme_rows=rows)
    text = readme.read_text()
    assert text.startswith("# title\n\nbefore\n") and text.endswith(f"{README_END}\nafter\n") and "stale" not in text
    table = [line for line in text.split("\n") if line.startswith("| ") and not line.startswith("| model")]
    assert [line.split(" | ")[0] for line in table] == [
        "| selected",
        "| ridge-tactile",
        "| mean",
        "| *human split-half*",
    ]
    res = {d: json.loads((work / d / "results.json").read_text()) for d in rows}
    for line, d in zip(table, rows):
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[1] == rows[d]
        assert [float(c) for c in cells[2:6]] == pytest.approx(
            [res[d]["mae"][k] for k in ("rough_smooth", "flat_bumpy", "sticky_slippery", "hard_soft")], abs=0.005
        )
        value, lo, hi = (float(x) for x in re.search(r"([\d.]+) \[([\d.]+), ([\d.]+)\]", cells[6]).groups())
        assert value == pytest.approx(res[d]["mae"]["mean"], abs=0.005) and lo <= value <= hi
        if d == "ridge-tactile":
            assert cells[7] == "—"
        else:  # the paired difference's point value is the difference of the two MAEs
            delta = float(re.match(r"([+-][\d.]+) \[", cells[7]).group(1))
            assert delta == pytest.approx(res[d]["mae"]["mean"] - res["ridge-tactile"]["mae"]["mean"], abs=0.006)
        assert re.fullmatch(r"\d+ µs|\d+\.\d ms", cells[8])  # the run's per-window latency
    sentence = next(line for line in text.split("\n") if line.startswith("`selected` against the targets"))
    m = res["selected"]["mae"]["mean"]
    assert (
        f"misses ≤ {TARGET_MEAN_MAE} by {m - TARGET_MEAN_MAE:.2f}"
        if m > TARGET_MEAN_MAE
        else f"meets ≤ {TARGET_MEAN_MAE}"
    ) in sentence


def test_the_readme_table_names_what_is_missing(reports, tmp_path):
    dataset, folder = reports
    readme = tmp_path / "README.md"
    readme.write_text("# no markers\n")
    with pytest.raises(ValueError, match="needs one line"):
        build_report(dataset, folder, reference="ridge-tactile", readme=readme, readme_rows={"mean": "m"})
    with pytest.raises(ValueError, match=r"needs results for \['ann'\]"):
        build_report(dataset, folder, reference="ridge-tactile", readme=readme, readme_rows={"mean": "m", "ann": "a"})


def test_the_families_section_sets_each_run_beside_its_leave_one_texture_out_twin(reports, tmp_path):
    dataset, folder = reports
    work = tmp_path / "reports"
    _copy_runs(folder, work, {"mean": "mean", "ridge-tactile": "ridge-tactile", "knn-tactile": "families/knn-tactile"})
    twin = json.loads((folder / "ridge-tactile" / "results.json").read_text())
    (work / "families" / "ridge-tactile").mkdir(parents=True)
    (work / "families" / "ridge-tactile" / "results.json").write_text(json.dumps({**twin, "leave_out": "family"}))
    far = {s: {t: [v + 150.0 for v in p] for t, p in per.items()} for s, per in twin["predictions_per_seed"].items()}
    (work / "families" / "ridge-far").mkdir(parents=True)
    (work / "families" / "ridge-far" / "results.json").write_text(
        json.dumps({**twin, "predictions_per_seed": far, "leave_out": "family"})
    )
    page = build_report(dataset, work).read_text()
    section = page.split("## A new material, not a new sample: families left out")[1].split("\n## ")[0]
    rows = {line.split(" | ")[0] + " | " + line.split(" | ")[1]: line for line in section.split("\n") if "| " in line}
    # the same predictions as its twin: the same MAE, a difference of exactly 0 (synthetic names: one family, 8)
    same = rows["| families/ridge-tactile | all (8)"].split(" | ")
    assert same[2] == same[3] and same[4].startswith("+0.00 [0.00, 0.00]")
    assert "| families/ridge-tactile | with a sibling (8)" in rows
    assert float(rows["| families/ridge-far | all (8)"].split(" | ")[4].split()[0]) > 10  # far worse
    # a run whose model the main table lacks says so rather than comparing it with another model
    assert "| families/knn-tactile | — | no main-table run of the same model" in section
    assert "families" not in page.split("## MAE")[1].split("## RMSE")[0]  # never a row of the main table


def test_the_headline_says_how_the_served_image_features_were_picked(reports, tmp_path):
    from models.offline.featurize import SERVED_VISUAL

    dataset, folder = reports
    work = tmp_path / "reports"
    _copy_runs(folder, work, {"mean": "mean", "knn-tactile": "selected"})
    page = build_report(dataset, work).read_text()
    headline = page.split("## Headline")[1].split("\n## ")[0]
    assert "no selection bias in the model" in headline and "frontier's fixed rule" not in headline
    run = json.loads((work / "selected" / "results.json").read_text())
    served = {"grid": SERVED_VISUAL.grid, "glcm": SERVED_VISUAL.glcm, "patch_size": 224}
    run["features"] = {**run["features"], "backbone": SERVED_VISUAL.backbone, "visual_config": served}
    (work / "selected" / "results.json").write_text(json.dumps(run))
    headline = build_report(dataset, work).read_text().split("## Headline")[1].split("\n## ")[0]
    assert "picked by the frontier's fixed rule on inner cross-validation over these textures" in headline


def test_the_speed_section_names_the_hosts_its_latencies_were_timed_on():
    from models.offline.report.markdown import _hosts_line

    epyc = {"hardware": {"host": {"model": "AMD EPYC", "isa": ["avx2", "avx512_vnni"]}}}
    old = {"hardware": {"platform": "Linux"}}
    assert _hosts_line([epyc, epyc]) == "Timed on AMD EPYC (avx2, avx512_vnni)."
    line = _hosts_line([epyc, old])
    assert line.startswith("Timed on AMD EPYC") and "1 of 2 runs predate the record of their CPU" in line
