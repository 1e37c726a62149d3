"""Texture libraries on disk: entries, their models and images; the synthetic and HaTT builders."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from PIL import Image

from texture_library.attributes import ATTRIBUTES
from texture_library.library import Library, LibraryEntry, add_entry
from texture_library.synthetic_library import build_synthetic_library

FIELDS = dict(name="Test", group="plastic", ratings_source="human", provenance="test", licence="CC0")


def entry(entry_id: str = "a", ratings=(0.0, 10.0, -20.0, 30.0), **kw) -> LibraryEntry:
    return LibraryEntry(id=entry_id, ratings=np.array(ratings), model_path=f"models/{entry_id}.npz", **{**FIELDS, **kw})


@pytest.fixture
def library(tmp_path, make_model) -> Library:
    root = tmp_path / "lib"
    entries = [
        add_entry(
            root, "a", make_model(name="a"), ratings=np.array([-50.0, 0.0, 0.0, 0.0]), spread=np.full(4, 5.0), **FIELDS
        ),
        add_entry(root, "b", make_model(name="b", with_taps=True), ratings=np.array([50.0, 0.0, 0.0, 0.0]), **FIELDS),
    ]
    lib = Library(root, "test", entries)
    lib.save()
    return lib


def test_save_load_round_trip(library, make_model):
    loaded = Library.load(library.root)
    assert loaded.name == "test" and loaded.ids == ["a", "b"]
    np.testing.assert_array_equal(loaded.ratings, library.ratings)
    np.testing.assert_array_equal(loaded.entry("a").spread, np.full(4, 5.0))
    assert loaded.entry("b").spread is None
    for a, b in zip(loaded.entries, library.entries):
        assert a.to_json() == b.to_json()
    assert loaded.validate() == []
    np.testing.assert_array_equal(loaded.model("a").ar_lsf, make_model().ar_lsf)
    assert loaded.model("b").taps is not None
    assert loaded.model("a") is loaded.model("a")  # loaded once


def test_library_json_is_the_documented_layout(library):
    doc = json.loads((library.root / "library.json").read_text())
    assert (doc["format"], doc["version"], doc["name"]) == ("hapticlink-library", 1, "test")
    first = doc["entries"][0]
    assert first["ratings"] == dict(zip(ATTRIBUTES, [-50.0, 0.0, 0.0, 0.0]))
    assert first["model"] == "models/a.npz" and (library.root / "models" / "a.npz").is_file()


def test_validate_names_a_missing_model(library):
    (library.root / "models" / "b.npz").unlink()
    problems = Library.load(library.root).validate()
    assert len(problems) == 1 and problems[0].startswith("entry 'b': ") and "not found" in problems[0]


@pytest.mark.parametrize("bad_id", ["", "../x", "a b", ".hidden", "é"])
def test_entry_ids_must_be_plain_names(bad_id):
    with pytest.raises(ValueError, match="is not a valid name"):
        entry(bad_id)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"ratings": (0.0, 0.0, 0.0, 150.0)}, r"values must lie in \[-100, 100\], got \[0, 150\]"),
        ({"ratings": (0.0, 0.0, 0.0)}, "last axis must have 4 attributes"),
        ({"ratings": (0.0, np.nan, 0.0, 0.0)}, "NaN or Inf"),
        ({"ratings_source": "guessed"}, "ratings_source must be one of"),
        ({"spread": np.array([1.0, -1.0, 0.0, 0.0])}, "spread must be 4 finite values ≥ 0"),
    ],
)
def test_entry_validation(kwargs, message):
    with pytest.raises(ValueError, match=message):
        entry(**kwargs)


def test_add_entry_refuses_a_bad_id_before_writing(tmp_path, make_model):
    with pytest.raises(ValueError, match="is not a valid name"):
        add_entry(tmp_path / "lib", "../escape", make_model(), ratings=np.zeros(4), **FIELDS)
    assert not list(tmp_path.rglob("*.npz"))


def test_duplicate_ids_and_empty_libraries_are_refused(tmp_path):
    with pytest.raises(ValueError, match=r"duplicate entry ids \['a'\]"):
        Library(tmp_path, "dup", [entry("a"), entry("b"), entry("a")])
    with pytest.raises(ValueError, match="has no entries"):
        Library(tmp_path, "empty", [])


def _write_doc(root, entries, **header):
    root.mkdir(parents=True, exist_ok=True)
    doc = {"format": "hapticlink-library", "version": 1, "name": "x", "entries": entries, **header}
    (root / "library.json").write_text(json.dumps(doc))
    return root


@pytest.mark.parametrize(
    "change, message",
    [
        ({"drop": "model"}, r"missing key\(s\) \['model'\]"),
        ({"drop": "ratings"}, r"missing key\(s\) \['ratings'\]"),
        ({"ratings": {"rough_smooth": 0.0}}, "ratings must have exactly"),
        ({"ratings": {**dict.fromkeys(ATTRIBUTES, 0.0), "warmness": 1.0}}, "ratings must have exactly"),
        ({"ratings": dict.fromkeys(ATTRIBUTES, 101.0)}, "values must lie in"),
        ({"spread": {"rough_smooth": 1.0}}, "spread must be null or have exactly"),
        ({"id": "no/slash"}, "is not a valid name"),
    ],
)
def test_load_names_bad_entries(tmp_path, change, message):
    raw = entry("a").to_json()
    if "drop" in change:
        del raw[change.pop("drop")]
    raw.update(change)
    with pytest.raises(ValueError, match=message):
        Library.load(_write_doc(tmp_path / "lib", [raw]))


def test_load_names_bad_files(tmp_path):
    with pytest.raises(ValueError, match="not a texture library"):
        Library.load(tmp_path)
    (tmp_path / "library.json").write_text("{")
    with pytest.raises(ValueError, match="invalid JSON"):
        Library.load(tmp_path)
    with pytest.raises(ValueError, match="is not hapticlink-library v1"):
        Library.load(_write_doc(tmp_path / "v2", [entry().to_json()], version=2))
    with pytest.raises(ValueError, match="duplicate entry ids"):
        Library.load(_write_doc(tmp_path / "dup", [entry().to_json(), entry().to_json()]))


def test_unknown_entry_is_named(library):
    with pytest.raises(ValueError, match="no entry 'zzz' in library 'test'"):
        library.entry("zzz")


def test_synthetic_library_with_images(tmp_path):
    lib = build_synthetic_library(tmp_path / "syn", n_textures=3, seed=1, image_size=64)
    loaded = Library.load(tmp_path / "syn")
    assert loaded.ids == ["synth_000", "synth_001", "synth_002"] and loaded.validate() == []
    assert all(e.ratings_source == "ground-truth" and e.spread is not None for e in loaded.entries)
    png = loaded.image("synth_001")
    with Image.open(io.BytesIO(png)) as im:
        assert im.size == (64, 64) and im.mode == "L"
    np.testing.assert_allclose(loaded.ratings, lib.ratings)


def test_an_entry_without_an_image_has_none(tmp_path):
    assert Library(tmp_path, "x", [entry("a")]).image("a") is None


@pytest.mark.shared
def test_import_hatt_keeps_human_rated_textures_and_names_the_rest(hatt_dir, tmp_path):
    from texture_library.hatt_library import import_hatt

    pred = tmp_path / "pred.csv"
    pred.write_text("texture," + ",".join(ATTRIBUTES) + "\nblanket,10,20,30,40\n")
    lib, skipped = import_hatt(hatt_dir, tmp_path / "hatt", predictions=pred)
    assert len(lib.entries) == 80 and len(skipped) == 20 and "blanket" not in skipped and "candle" in skipped
    assert lib.entry("blanket").ratings_source == "predicted"
    np.testing.assert_array_equal(lib.entry("blanket").ratings, [10, 20, 30, 40])
    assert lib.entry("wood").ratings_source == "human" and lib.entry("wood").spread is not None
    assert Library.load(tmp_path / "hatt").model("wood").taps is not None


def test_a_library_validates_its_models_against_the_served_size_bound(library, monkeypatch):
    from texture_library import render_model

    assert library.validate() == []
    monkeypatch.setattr(render_model, "MAX_RENDER_MODEL_BYTES", 100)
    problems = library.validate()
    assert len(problems) == len(library.ids) and "at most 100 are served" in problems[0]
