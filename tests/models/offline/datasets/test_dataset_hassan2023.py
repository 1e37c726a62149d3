"""The hassan2023 source: an image-only dataset (photos referenced in place, touch ratings × 2, no recordings)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from models.offline.datasets.build import build
from models.offline.datasets.check import check_dataset
from models.offline.datasets.format import Dataset
from models.offline.evaluation.data import TextureData
from models.offline.evaluation.estimator_registry import EstimatorSpec, for_dataset
from models.offline.evaluation.loocv import loocv
from texture_library.attributes import ATTRIBUTES

PROJECT_ROOT = Path(__file__).resolve().parents[4]
HASSAN_DIR = (PROJECT_ROOT / ".." / "shared" / "data" / "hassan2023").resolve()
HEADER = ["texture", *ATTRIBUTES]


def write_table(path: Path, rows: list[list]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(HEADER)
        w.writerows(rows)


@pytest.fixture
def tiny_source(tmp_path) -> Path:
    """Five textures in the hassan2023 layout: t1–t3 rated, t4 withheld, t5 without a photo."""
    src = tmp_path / "src"
    (src / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for t in ("t1", "t2", "t3", "t4"):
        Image.fromarray(rng.integers(0, 256, (256, 256, 3), dtype=np.uint8)).save(src / "images" / f"{t}.jpg")
    with open(src / "textures.csv", "w", newline="") as fh:
        fh.write("texture,image,ratings\nt1,yes,yes\nt2,yes,yes\nt3,yes,yes\nt4,yes,withheld\nt5,missing,unused\n")
    write_table(src / "ratings.csv", [["t1", -10, 20, 0.5, 50], ["t2", 1, 2, 3, 4], ["t3", -50, 0, 10, -25]])
    write_table(src / "published_predictions.csv", [["t1", -8, 18, 1, 40], ["t2", 0, 0, 0, 0], ["t3", -40, 5, 9, -20]])
    return src


def test_builds_an_image_only_dataset_the_validator_accepts(tiny_source, tmp_path):
    out = build("hassan2023", tmp_path / "ds", path=tiny_source)
    assert check_dataset(out) == []
    ds = Dataset(out)
    assert ds.modalities == ("images",) and not ds.has_recordings
    assert [(t.texture, t.rated) for t in ds.textures()] == [
        ("t1", "yes"),
        ("t2", "yes"),
        ("t3", "yes"),
        ("t4", "withheld"),
    ]
    assert ds.header["build"]["without_photo"] == ["t5"]
    # published −50…+50 → bipolar −100…+100: × 2
    np.testing.assert_allclose(ds.mean_ratings()["t1"], [-20, 40, 1, 100])
    np.testing.assert_allclose(ds.mean_ratings()["t3"], [-100, 0, 20, -50])
    assert "t4" not in ds.mean_ratings()  # withheld: built without its ratings
    # the photos and the published predictions stay where they are: referenced, not copied
    assert ds.image_paths("t4") == [tiny_source.resolve() / "images" / "t4.jpg"]
    ref = ds.reference_predictions
    assert ref["path"] == str(tiny_source.resolve() / "published_predictions.csv")
    assert not list(Path(out).rglob("*.jpg")) and not list(Path(out).rglob("published_predictions.csv"))


def test_validator_refuses_recordings_in_an_image_only_dataset(tiny_source, tmp_path):
    out = build("hassan2023", tmp_path / "ds", path=tiny_source)
    meta = Path(out) / "textures" / "t1" / "meta.json"
    meta.write_text(json.dumps({**json.loads(meta.read_text()), "recordings": ["recording_000.npz"]}))
    problems = check_dataset(out)
    assert "t1" in problems[0] and "image-only" in problems[0]


def test_validator_refuses_an_unknown_modality(tiny_source, tmp_path):
    out = build("hassan2023", tmp_path / "ds", path=tiny_source)
    header = Path(out) / "dataset.json"
    header.write_text(json.dumps({**json.loads(header.read_text()), "modalities": ["smell"]}))
    assert any("modalities" in p and "smell" in p for p in check_dataset(out))


def test_bad_rating_names_the_line(tiny_source, tmp_path):
    write_table(tiny_source / "ratings.csv", [["t1", -10, 20, 0.5, 51], ["t2", 1, 2, 3, 4], ["t3", 0, 0, 0, 0]])
    with pytest.raises(ValueError, match=r"ratings.csv line 2: hard_soft = 51 outside ±50"):
        build("hassan2023", tmp_path / "ds", path=tiny_source)


def test_not_a_hassan_folder(tmp_path):
    with pytest.raises(ValueError, match="does not look like hassan2023: missing textures.csv"):
        build("hassan2023", tmp_path / "ds", path=tmp_path)


BLOCKS = {
    "backbone": [0, 4],
    **{b: [4 + i, 5 + i] for i, b in enumerate(("glcm", "lbp", "spectrum", "colour", "grids", "scattering"))},
}


def image_only_data(n: int = 12) -> TextureData:
    """n textures with 2 image views of every visual block and ratings that follow the backbone block."""
    rng = np.random.default_rng(1)
    visual = rng.normal(size=(n, 2, 10)).astype(np.float32)
    visual[:, 1] = visual[:, 0] + 0.1 * visual[:, 1]  # the second view: the first, slightly noisy
    targets = (40 * np.tanh(visual[:, 0, :4])).astype(np.float32)
    return TextureData(
        [f"t{i}" for i in range(n)],
        ["g"] * n,
        [np.zeros((0, 0), np.float32)] * n,
        visual,
        targets,
        {"dataset": "tiny", "image_only": True, "visual_blocks": BLOCKS},
    )


def test_touch_models_are_refused_with_the_model_and_the_modality_named():
    for name in ("ridge-both", "svr-tactile-windows", "vtnet-compact"):
        with pytest.raises(ValueError, match=rf"model '{name}' needs touch .* dataset 'tiny' is image-only"):
            for_dataset(EstimatorSpec(name), True, "dataset 'tiny'")
    with pytest.raises(ValueError, match="'ridge-both' needs touch"):
        loocv(image_only_data(), EstimatorSpec("ridge-both"), workers=1, progress=False)


def test_image_models_run_on_an_image_only_dataset():
    data = image_only_data()
    mean = loocv(data, EstimatorSpec("mean"), workers=1, progress=False).predictions
    err_mean = np.abs(mean - data.targets).mean()
    for spec in (
        EstimatorSpec("ridge-visual"),
        for_dataset(EstimatorSpec("krr-pooled"), True),  # becomes its image-only variant
        for_dataset(EstimatorSpec("selected"), True),
        EstimatorSpec("krr-backbone-image"),
    ):
        pred = loocv(data, spec, workers=1, progress=False).predictions
        assert pred.shape == (12, 4) and np.all(np.isfinite(pred)), spec
        assert np.abs(pred - data.targets).mean() < err_mean, spec  # the ratings follow the image


def test_selected_image_picks_blocks_inside_the_fit():
    from models.offline.evaluation.estimator_registry import build_estimator

    data = image_only_data(20)
    est = build_estimator("selected-image").fit(data, 0)
    info = est.fit_info()
    assert set(info["chosen"]) == set(ATTRIBUTES)
    # the ratings follow the backbone block only: every attribute picks a candidate that reads it
    assert all(c.split("-")[1] in ("backbone", "all") for c in info["chosen"].values()), info["chosen"]


@pytest.mark.shared
def test_real_folder_builds_73_rated_18_withheld(tmp_path):
    if not (HASSAN_DIR / "images").is_dir():
        pytest.skip(f"{HASSAN_DIR} is absent")
    out = build("hassan2023", tmp_path / "ds", path=HASSAN_DIR)
    assert check_dataset(out, deep=False) == []
    ds = Dataset(out)
    assert len(ds.texture_ids("yes")) == 73 and len(ds.texture_ids("withheld")) == 18
    with open(HASSAN_DIR / "ratings.csv", newline="") as fh:
        first = next(csv.DictReader(fh))
    np.testing.assert_allclose(ds.mean_ratings()[first["texture"]], [2 * float(first[a]) for a in ATTRIBUTES])


def test_export_refuses_an_image_only_dataset(tiny_source, tmp_path):
    from models.offline.train import train_and_export

    out = build("hassan2023", tmp_path / "ds", path=tiny_source)
    with pytest.raises(
        ValueError, match="'hassan2023' is image-only .* exporting a model trained on it is not supported"
    ):
        train_and_export(out, "ridge-visual", tmp_path / "m.onnx")
