"""The report page: tables from results.json files, targets, the speed–accuracy chart and its Pareto frontier."""

import json

import numpy as np
import pytest

from models.datasets.build import build
from models.evaluation.evaluate import evaluate
from models.evaluation.data import load_texture_data
from models.evaluation.registry import EstimatorSpec
from models.report.markdown import _ablation_label, build_report
from models.report.speed_accuracy import pareto_front


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
        evaluate(data, EstimatorSpec(name), root / "reports" / name, seeds=(0,), workers=1, backend="serial", progress=False)
    return dataset, root / "reports"


def test_ablation_label_names_the_features_of_every_modality_a_model_reads():
    assert _ablation_label({"modality": "visual", "features": {"visual_part": "glcm"}}) == "visual glcm"
    assert _ablation_label({"modality": "tactile", "features": {"tactile_features": "dwt"}}) == "tactile dwt"
    both = {"modality": "both", "features": {"visual_part": "backbone", "tactile_features": "dft"}}
    assert _ablation_label(both) == "visual backbone + tactile dft"


def test_evaluate_writes_results_and_figures(reports):
    _, folder = reports
    res = json.loads((folder / "ridge-tactile" / "results.json").read_text())
    assert set(res["mae"]) == {"rough_smooth", "flat_bumpy", "sticky_slippery", "hard_soft", "mean"}
    assert len(res["predictions"]) == res["n_textures"] == 8
    assert res["latency_us"]["runtime"] == "onnxruntime" and res["latency_us"]["p50_us"] > 0
    assert res["vs_true_mapping"]["mae"]["mean"] > 0  # the synthetic world knows its noise-free ratings
    for fig in ("actual_vs_predicted.png", "group_mae.png", "perceptual_space.png"):
        assert (folder / "ridge-tactile" / fig).stat().st_size > 10_000


def test_report_page_lists_every_model_with_the_ceiling_and_the_chart(reports):
    dataset, folder = reports
    page = build_report(dataset, folder, regenerate="bash reports/regenerate.sh").read_text()
    for name in ("| mean |", "| ridge-tactile |", "| knn-tactile |", "*human split-half*", "bash reports/regenerate.sh"):
        assert name in page
    assert "speed_accuracy.png" in page and (folder / "speed_accuracy.png").is_file()
    assert "## Against the targets" in page
    # tables are sorted by mean MAE: the first data row is the best model
    first_row = page.split("## MAE")[1].split("\n")[4]
    maes = {n: json.loads((folder / n / "results.json").read_text())["mae"]["mean"] for n in ("mean", "ridge-tactile", "knn-tactile")}
    assert first_row.startswith(f"| {min(maes, key=maes.get)} |")


def test_report_without_results_says_what_to_run(tmp_path, reports):
    dataset, _ = reports
    with pytest.raises(ValueError, match="run `hapticlink evaluate"):
        build_report(dataset, tmp_path)
