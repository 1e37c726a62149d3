"""Writing and reading the dataset format: tables, ratings, meta, the synthetic builder's content."""

from __future__ import annotations

import json

import numpy as np
import pytest

from models.offline.datasets.format import Dataset, DatasetWriter, RatingRow, TextureInfo, TextureMeta
from texture_library.attributes import ATTRIBUTES
from texture_library.vibration import VibrationModel


@pytest.fixture
def small(tmp_path) -> Dataset:
    """Two rated textures; rater r2 saw 'a' twice (presentation 2 says −100, to be ignored); r2 never rated 'b'."""
    w = DatasetWriter(
        tmp_path / "ds", name="small", source="test", licence="CC0", provenance="test", build={"crop_s": 0.25}
    )
    rows_a = [RatingRow("a", "r1", 1, attr, 10.0 * (i + 1)) for i, attr in enumerate(ATTRIBUTES)]
    rows_a += [RatingRow("a", "r2", 1, attr, -10.0 * (i + 1)) for i, attr in enumerate(ATTRIBUTES)]
    rows_a += [RatingRow("a", "r2", 2, attr, -100.0) for attr in ATTRIBUTES]
    rows_b = [RatingRow("b", "r1", 1, "rough_smooth", 50.0), RatingRow("b", "r3", 1, "rough_smooth", 70.0)]
    w.add_texture(TextureInfo("a", "A", "wood", "yes"), TextureMeta(["/abs/photo.png"], ["recording_000.npz"]), rows_a)
    w.add_texture(TextureInfo("b", "B", "foam", "yes"), TextureMeta(), rows_b)
    w.add_texture(TextureInfo("c", "C", "foam", "withheld"), TextureMeta(extra={"k": 1}))
    w.close()
    return Dataset(tmp_path / "ds")


def test_rating_table_shape_and_missing_values(small):
    textures, raters, table = small.rating_table()
    assert textures == ["a", "b"] and raters == ["r1", "r2", "r3"]
    assert table.shape == (2, 3, 4)
    np.testing.assert_array_equal(table[0, 0], [10, 20, 30, 40])
    np.testing.assert_array_equal(table[0, 1], [-10, -20, -30, -40])  # presentation 1, not the repeat
    assert np.isnan(table[0, 2]).all() and np.isnan(table[1, 1]).all()
    np.testing.assert_array_equal(table[1, :, 0], [50, np.nan, 70])


def test_mean_ratings_use_presentation_one_only(small):
    means = small.mean_ratings()
    assert set(means) == {"a", "b"}
    np.testing.assert_array_equal(means["a"], [0, 0, 0, 0])  # r2's −100 repeat would pull this down
    assert means["b"][0] == 60.0 and np.isnan(means["b"][1:]).all()


def test_tables_and_meta_read_back(small):
    assert small.name == "small" and small.header["build"] == {"crop_s": 0.25}
    assert [t.texture for t in small.textures()] == ["a", "b", "c"]
    assert small.texture_ids(rated="withheld") == ["c"] and small.texture_ids(rated="yes") == ["a", "b"]
    assert len(small.rating_rows()) == 14
    meta = small.meta("a")
    assert meta.images == ["/abs/photo.png"] and meta.vibration_model is None
    assert small.meta("c").extra == {"k": 1}
    # absolute paths stay absolute, relative ones live in the texture's folder
    assert str(small.image_paths("a")[0]) == "/abs/photo.png"
    assert small.resolve("a", "recording_000.npz") == small.root / "textures" / "a" / "recording_000.npz"
    assert small.vibration_model_path("a") is None
    assert small.features_dir == small.root / "features"


def test_reader_refuses_what_it_cannot_read(small, tmp_path):
    with pytest.raises(ValueError, match="not a hapticlink dataset"):
        Dataset(tmp_path)
    path = small.root / "dataset.json"
    path.write_text(json.dumps({**small.header, "version": 9}))
    with pytest.raises(ValueError, match="unsupported version 9"):
        Dataset(small.root)
    path.write_text("{")
    with pytest.raises(ValueError, match="invalid JSON"):
        Dataset(small.root)
    with pytest.raises(ValueError, match="texture 'zz': missing"):
        small.meta("zz")


def test_writer_refuses_an_unknown_rated_value(tmp_path):
    w = DatasetWriter(tmp_path / "ds", name="x", source="x", licence="x", provenance="x")
    with pytest.raises(ValueError, match="rated must be one of"):
        w.add_texture(TextureInfo("a", "A", "g", "perhaps"), TextureMeta())


def test_synthetic_build_content(synthetic_dataset):
    ds = Dataset(synthetic_dataset)
    assert ds.header["source"] == "synthetic" and ds.header["build"]["crop_s"] == 0.5
    assert [(t.texture, t.rated) for t in ds.textures()] == [
        ("synth_000", "yes"),
        ("synth_001", "yes"),
        ("synth_002", "withheld"),
    ]
    textures, raters, table = ds.rating_table()
    assert textures == ["synth_000", "synth_001"] and len(raters) == 4 and not np.isnan(table).any()
    (rec,) = ds.recordings("synth_000")
    assert (
        rec.duration_s == pytest.approx(2.0) and rec.accel.data.shape == (2000, 3) and rec.force.data.shape == (2000, 3)
    )
    model = VibrationModel.load(ds.vibration_model_path("synth_000"))
    meta = ds.meta("synth_000")
    assert model.extra["physical"] == meta.extra["physical"]
    # the raters are noisy around the documented truth
    truth = np.array(meta.extra["true_ratings"])
    assert np.all(np.abs(ds.mean_ratings()["synth_000"] - truth) < 40)


def test_synthetic_build_is_reproducible(synthetic_dataset, tmp_path):
    from models.offline.datasets.synthetic import build_synthetic

    again = build_synthetic(
        tmp_path / "again", n_textures=3, seed=0, duration_s=2.0, n_raters=4, image_size=224, withheld=1
    )
    a, b = Dataset(synthetic_dataset), Dataset(again)
    np.testing.assert_array_equal(a.recordings("synth_001")[0].accel.data, b.recordings("synth_001")[0].accel.data)
    assert (synthetic_dataset / "ratings.csv").read_text() == (again / "ratings.csv").read_text()


def test_synthetic_withheld_must_leave_a_rated_texture(tmp_path):
    from models.offline.datasets.synthetic import build_synthetic

    with pytest.raises(ValueError, match=r"withheld must lie in \[0, n_textures\)"):
        build_synthetic(tmp_path / "x", n_textures=2, withheld=2)
