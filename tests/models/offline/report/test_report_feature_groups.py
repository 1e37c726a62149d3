"""The report's feature-group section: runs with and without extra groups, intervals
(models.offline.evaluation.bootstrap), ratings read from the dataset (results.json carry none)."""

import json

import numpy as np
import pytest

from models.offline.datasets.build import build
from models.offline.evaluation.data import load_texture_data
from models.offline.evaluation.estimator_registry import EstimatorSpec
from models.offline.evaluation.evaluate import evaluate
from models.offline.report.feature_groups import group_label, group_rows
from models.offline.report.markdown import build_report
from models.tactile.config import TactileConfig


@pytest.fixture(scope="module")
def group_reports(tmp_path_factory):
    root = tmp_path_factory.mktemp("groups")
    dataset = build("synthetic", root / "ds", n_textures=10, duration_s=3, image_size=64)
    reports = root / "reports"
    plain = load_texture_data(dataset, visual=False)
    for name in ("mean", "ridge-tactile"):
        evaluate(
            plain,
            EstimatorSpec(name),
            reports / name,
            seeds=(0,),
            workers=1,
            backend="serial",
            progress=False,
            latency=False,
        )
    evaluate(
        plain,
        EstimatorSpec("mean"),
        reports / "feature-groups" / "mean",
        seeds=(0,),
        workers=1,
        backend="serial",
        progress=False,
        latency=False,
    )
    for groups in ((), ("friction",), ("friction", "spatial", "taps")):
        data = load_texture_data(dataset, tactile_config=TactileConfig(extra_groups=groups), visual=False)
        evaluate(
            data,
            EstimatorSpec("ridge-tactile"),
            reports / "feature-groups" / "ridge-tactile" / ("+".join(groups) or "mfcc"),
            seeds=(0, 1),
            workers=1,
            backend="serial",
            progress=False,
            latency=False,
        )
    return dataset, reports


def test_results_carry_no_ratings(group_reports):
    _, reports = group_reports
    res = json.loads((reports / "feature-groups" / "ridge-tactile" / "friction" / "results.json").read_text())
    assert "truth" not in res and len(res["predictions"]) == 10
    assert res["features"]["extra_groups"] == ["friction"]


def test_rows_have_intervals_ratios_and_paired_deltas(group_reports):
    dataset, reports = group_reports
    rows = group_rows(dataset, reports)
    assert [group_label(r["groups"]) for r in rows] == ["MFCC", "MFCC + friction", "MFCC + friction + spatial + taps"]
    for r in rows:
        assert np.all(r["ci"][0] <= r["mae"] + 1e-9) and np.all(r["mae"] <= r["ci"][1] + 1e-9)
        assert np.all(r["ratio_ci"][0] <= r["ratio"] + 1e-9) and np.all(r["ratio"] <= r["ratio_ci"][1] + 1e-9)
    assert "delta" not in rows[0] and "delta" in rows[1]
    # friction is the stickiness cue: the paired change on sticky–slippery is negative beyond noise
    assert rows[1]["delta_ci"][1, 2] < 0


def test_report_page_has_the_section_and_figure(group_reports):
    dataset, reports = group_reports
    page = build_report(dataset, reports).read_text()
    assert "## Feature groups" in page and "### ridge-tactile" in page and "× mean [" in page
    assert "one model and group set meeting it on every attribute: " in page
    assert (reports / "feature_groups.png").stat().st_size > 10_000
    assert "feature-groups/" not in page.split("## Feature groups")[0]  # not mixed into the main table


def test_a_folder_of_feature_groups_alone_gets_its_own_page(group_reports, tmp_path):
    import shutil

    dataset, reports = group_reports
    only = tmp_path / "only"
    shutil.copytree(reports / "feature-groups", only / "feature-groups")
    page = build_report(dataset, only).read_text()
    assert page.startswith("# ") and "feature groups" in page.splitlines()[0] and "### ridge-tactile" in page
    with pytest.raises(ValueError, match="no results.json"):
        build_report(dataset, tmp_path / "empty")
