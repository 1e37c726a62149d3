"""Building the HaTT–TexNet dataset from ../shared (read in place, never copied)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from models.offline.datasets.check import check_dataset
from models.offline.datasets.format import Dataset
from models.offline.datasets.hatt_texnet import build_hatt

PICK = ["abs_plastic", "blanket", "wood"]  # rated, withheld, rated (with attention-check repeats)


@pytest.fixture(scope="module")
def hatt_built(hatt_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("hatt") / "ds"
    return build_hatt(hatt_dir, out, textures=PICK, duration_s=6.0, workers=1), hatt_dir


def raw_means(src, texture):
    sums: dict[str, list[float]] = {}
    with open(src / "ratings.csv", newline="") as fh:
        for r in csv.DictReader(fh):
            if r["texture"] == texture and r["presentation"] == "1":
                sums.setdefault(r["attribute"], []).append(float(r["rating"]))
    return {a: np.mean(v) for a, v in sums.items()}


@pytest.mark.shared
def test_built_subset_is_clean(hatt_built):
    out, _ = hatt_built
    assert check_dataset(out) == []
    ds = Dataset(out)
    assert ds.header["source"] == "hatt-texnet" and ds.header["build"]["crop_s"] == 2.5
    assert [(t.texture, t.rated) for t in ds.textures()] == [
        ("abs_plastic", "yes"),
        ("blanket", "withheld"),
        ("wood", "yes"),
    ]


@pytest.mark.shared
def test_ratings_are_bipolar_and_follow_the_texnet_conversion(hatt_built):
    out, src = hatt_built
    ds = Dataset(out)
    rows = ds.rating_rows()
    assert {r.attribute for r in rows} == {"rough_smooth", "flat_bumpy", "sticky_slippery", "hard_soft"}
    values = np.array([r.rating for r in rows])
    assert values.min() >= -100 and values.max() <= 100 and values.min() < 0 < values.max()
    assert any(r.presentation == 2 for r in rows if r.texture == "wood")
    raw = raw_means(src, "wood")
    mean = ds.mean_ratings()["wood"]
    np.testing.assert_allclose(
        mean,
        [
            100 - 2 * raw["roughness"],
            2 * raw["bumpiness"] - 100,
            100 - 2 * raw["stickiness"],
            100 - 2 * raw["hardness"],
        ],
    )


@pytest.mark.shared
def test_withheld_textures_have_recordings_but_no_ratings(hatt_built):
    out, _ = hatt_built
    ds = Dataset(out)
    assert not [r for r in ds.rating_rows() if r.texture == "blanket"]
    (rec,) = ds.recordings("blanket")
    assert rec.duration_s == pytest.approx(6.0) and rec.accel.data.shape == (6000, 3)
    assert np.isfinite(rec.accel.data).all() and rec.accel.data.std() > 0.01


@pytest.mark.shared
def test_images_are_referenced_in_place_not_copied(hatt_built):
    out, src = hatt_built
    ds = Dataset(out)
    for tid in PICK:
        (path,) = ds.image_paths(tid)
        assert path.is_absolute() and path == src / "images" / f"{tid}.png"
    assert not list(out.rglob("*.png")) and not list(out.rglob("*.xml"))


@pytest.mark.shared
def test_the_vibration_model_and_the_recording_agree(hatt_built):
    """The recording's speed and force stay inside the model's grid; its friction is the model's μ."""
    out, _ = hatt_built
    from texture_library.vibration import VibrationModel

    ds = Dataset(out)
    model = VibrationModel.load(ds.vibration_model_path("wood"))
    (rec,) = ds.recordings("wood")
    assert rec.speed.data.max() <= model.max_speed and rec.force.data[:, 2].max() <= model.max_force + 0.1
    ratio = -rec.force.data[:, 0] / rec.force.data[:, 2]
    assert np.median(np.abs(ratio)) == pytest.approx(model.mu, rel=0.05)


@pytest.mark.shared
def test_limit_keeps_the_first_textures_and_unknown_ids_are_named(hatt_dir, tmp_path):
    out = build_hatt(hatt_dir, tmp_path / "ds", limit=3, duration_s=1.0, workers=1)
    with open(hatt_dir / "textures.csv", newline="") as fh:
        first = [r["texture"] for r in csv.DictReader(fh)][:3]
    assert Dataset(out).texture_ids() == first
    with pytest.raises(ValueError, match=r"no texture\(s\) \['unobtainium'\]"):
        build_hatt(hatt_dir, tmp_path / "x", textures=["wood", "unobtainium"])


def test_a_folder_that_is_not_hatt_is_refused(tmp_path):
    with pytest.raises(ValueError, match="does not look like hatt-texnet: missing textures.csv"):
        build_hatt(tmp_path, tmp_path / "out")
