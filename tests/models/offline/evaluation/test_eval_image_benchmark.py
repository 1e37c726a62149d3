"""The image-only benchmark's pieces: leave-one-out recalibration, the report table, the reference line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from models.offline.evaluation.image_benchmark import loo_mean, loo_recalibrate, report, table
from texture_library.attributes import ATTRIBUTES


def test_recalibration_undoes_an_affine_distortion_without_seeing_the_texture():
    rng = np.random.default_rng(0)
    truth = rng.uniform(-40, 40, size=(10, 4))
    np.testing.assert_allclose(loo_recalibrate(0.5 * truth - 7, truth), truth, atol=1e-9)
    # leave-one-out: an outlier's own rating does not pull its map toward it
    pred = truth.copy()
    truth_out = truth.copy()
    truth_out[0, 0] = 90.0
    assert abs(loo_recalibrate(pred, truth_out)[0, 0] - truth[0, 0]) < abs(90.0 - truth[0, 0]) / 2


def test_loo_mean_leaves_the_texture_out():
    truth = np.array([[0.0] * 4, [3.0] * 4, [6.0] * 4])
    np.testing.assert_allclose(loo_mean(truth)[:, 0], [4.5, 3.0, 1.5])


def test_report_scores_each_run_and_the_reference(tmp_path):
    from PIL import Image

    from models.offline.datasets.build import build

    src = tmp_path / "src"
    (src / "images").mkdir(parents=True)
    rows = [f"t{i}" for i in range(6)]
    rng = np.random.default_rng(0)
    for t in rows:
        Image.fromarray(rng.integers(0, 256, (240, 240, 3), dtype=np.uint8)).save(src / "images" / f"{t}.jpg")
    (src / "textures.csv").write_text("texture,image,ratings\n" + "".join(f"{t},yes,yes\n" for t in rows))
    truth = rng.uniform(-40, 40, size=(6, 4))
    head = "texture," + ",".join(ATTRIBUTES) + "\n"
    (src / "ratings.csv").write_text(
        head + "".join(f"{t}," + ",".join(map(str, r)) + "\n" for t, r in zip(rows, truth))
    )
    # the published table on its −50…+50 scale: exactly the ratings, so the reference line scores 0
    (src / "published_predictions.csv").write_text((src / "ratings.csv").read_text())
    ds = build("hassan2023", tmp_path / "ds", path=src)
    bipolar = 2 * truth

    def write(name, pred):
        (tmp_path / "res" / name).mkdir(parents=True)
        per = {t: list(map(float, p)) for t, p in zip(rows, pred)}
        (tmp_path / "res" / name / "results.json").write_text(
            json.dumps({"predictions_per_seed": {"0": per}, "seeds": [0], "predictions": per})
        )

    write("mean", loo_mean(bipolar))
    write("half-way", (loo_mean(bipolar) + bipolar) / 2)
    summary = report(ds, tmp_path / "res")
    assert summary["rows"]["mean"]["ratio_to_mean"]["value"]["mean"] == pytest.approx(1.0)
    assert summary["rows"]["half-way"]["ratio_to_mean"]["value"]["mean"] == pytest.approx(0.5)
    assert summary["reference"]["mae"]["value"]["mean"] == pytest.approx(0.0, abs=1e-9)
    assert "published (published-1dcnn)" in table(summary)
