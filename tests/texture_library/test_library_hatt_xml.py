"""Reading HaTT model and tap XML, and TexNet ratings → bipolar attributes."""

from __future__ import annotations

import csv
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from texture_library.hatt_xml import read_model, read_taps
from texture_library.lsf import lsf_to_poly
from texture_library.synthesis import render
from texture_library.texnet import read_texnet_ratings, to_bipolar

# A 4-point grid, two triangles written 1-based as HaTT does: (1, 2, 3) and (2, 4, 3).
GRID = [(0.0, 0.0), (100.0, 0.0), (0.0, 2.0), (100.0, 2.0)]


def values(xs) -> str:
    return "".join(f"<value>{x}</value>" for x in xs)


def model_xml(drop: str | None = None, replace: tuple[str, str] | None = None) -> str:
    models = "".join(
        f"<model><modNum>{k + 1}</modNum><ARlsf>{values([0.3 + 0.1 * k, 1.2, 2.0])}</ARlsf>"
        f"<MAlsf>{values([0.8, 2.2])}</MAlsf><var>{0.5 * k}</var><gain>{1.0 + k}</gain></model>"
        for k in range(len(GRID))
    )
    parts = {
        "material": "<material>Test Plastic</material>",
        "SampleRate": "<SampleRate>1000</SampleRate>",
        "mu": "<mu>0.25</mu>",
        "maxSpeed": "<maxSpeed>100</maxSpeed>",
        "maxForce": "<maxForce>2</maxForce>",
        "speedList": f'<speedList type="array">{values(s for s, _ in GRID)}</speedList>',
        "forceList": f'<forceList type="array">{values(f for _, f in GRID)}</forceList>',
        "tri": f'<tri type="array">{values([1, 2, 3])}</tri><tri type="array">{values([2, 4, 3])}</tri>',
        "model": models,
    }
    if drop:
        del parts[drop]
    text = '<?xml version="1.0" encoding="utf-8"?><modelSet texture="0">' + "".join(parts.values()) + "</modelSet>"
    if replace:
        assert replace[0] in text
        text = text.replace(replace[0], replace[1], 1)
    return text


def taps_xml(n_taps: int = 3, length: int = 100) -> str:
    taps = "".join(
        f"<tap><tapSpeed>{10.0 * (k + 1)}</tapSpeed><tapAccel>{values(np.arange(length) * (k + 1))}</tapAccel></tap>"
        for k in range(n_taps)
    )
    return f'<?xml version="1.0"?><tapSet><numTap>{n_taps}</numTap>{taps}</tapSet>'


@pytest.fixture
def hatt_files(tmp_path):
    (tmp_path / "m.xml").write_text(model_xml())
    (tmp_path / "t.xml").write_text(taps_xml())
    return tmp_path / "m.xml", tmp_path / "t.xml"


def test_read_model_parses_grid_models_and_taps(hatt_files):
    model = read_model(*hatt_files, name="test_plastic")
    assert model.name == "test_plastic"
    np.testing.assert_array_equal(model.speeds, [s for s, _ in GRID])
    np.testing.assert_array_equal(model.forces, [f for _, f in GRID])
    np.testing.assert_array_equal(model.triangles, [[0, 1, 2], [1, 3, 2]])  # 1-based → 0-based
    assert model.triangles.dtype.kind == "i"
    np.testing.assert_allclose(model.ar_lsf[2], [0.5, 1.2, 2.0])
    np.testing.assert_allclose(model.ma_lsf, np.tile([0.8, 2.2], (4, 1)))
    np.testing.assert_allclose(model.variance, [0.0, 0.5, 1.0, 1.5])
    np.testing.assert_allclose(model.gain, [1.0, 2.0, 3.0, 4.0])
    assert (model.mu, model.max_speed, model.max_force, model.rate_hz) == (0.25, 100.0, 2.0, 1000.0)
    assert "Test Plastic" in model.provenance and "non-profit" in model.provenance
    np.testing.assert_array_equal(model.taps.speeds, [10.0, 20.0, 30.0])
    np.testing.assert_array_equal(model.taps.accel[1], np.arange(100) * 2)


def test_name_defaults_to_the_file_stem_and_taps_are_optional(hatt_files):
    model = read_model(hatt_files[0])
    assert model.name == "m" and model.taps is None


@pytest.mark.parametrize("tag", ["mu", "maxSpeed", "maxForce", "SampleRate", "speedList", "forceList", "tri"])
def test_missing_element_is_named(tmp_path, tag):
    (tmp_path / "m.xml").write_text(model_xml(drop=tag))
    with pytest.raises(ValueError, match=f"missing <{tag}>"):
        read_model(tmp_path / "m.xml")


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("<mu>0.25</mu>", "<mu>slippery</mu>", r"<mu> is not a number: 'slippery'"),
        ("<var>0.0</var>", "<var>x</var>", r"<var> is not a number"),
        ("<var>0.0</var>", "", r"missing <var>"),
        ("<gain>1.0</gain>", "", r"missing <gain>"),
        ("<ARlsf><value>0.3</value>", "<ARlsf><value>abc</value>", r"<ARlsf> holds a value that is not a number"),
        ("<ARlsf><value>0.3</value><value>1.2</value><value>2.0</value></ARlsf>", "", r"missing <ARlsf>"),
        ("<MAlsf><value>0.8</value><value>2.2</value></MAlsf>", "", r"missing <MAlsf>"),
        (
            "<value>1</value><value>2</value><value>3</value></tri>",
            "<value>1</value><value>2</value></tri>",
            r"<tri> must hold 3",
        ),
        (
            "<value>1</value><value>2</value><value>3</value></tri>",
            "<value>1.5</value><value>2</value><value>3</value></tri>",
            r"<tri> holds a vertex index that is not an integer",
        ),
        (
            "<value>1</value><value>2</value><value>3</value></tri>",
            "<value>1</value><value>2</value><value>7</value></tri>",
            r"triangle indices must lie in \[0, 3\]",
        ),
        ('<speedList type="array"><value>0.0</value>', '<speedList type="array">', r"3 grid points"),
        ("<ARlsf><value>0.3</value>", "<ARlsf>", r"ARlsf orders differ between grid points: \[2, 3\]"),
    ],
)
def test_garbled_model_is_named(tmp_path, old, new, message):
    (tmp_path / "m.xml").write_text(model_xml(replace=(old, new)))
    with pytest.raises(ValueError, match=message):
        read_model(tmp_path / "m.xml")


def test_unreadable_files_are_named(tmp_path):
    (tmp_path / "bad.xml").write_text("<modelSet><mu>")
    with pytest.raises(ValueError, match="cannot read model XML"):
        read_model(tmp_path / "bad.xml")
    with pytest.raises(ValueError, match="cannot read model XML"):
        read_model(tmp_path / "absent.xml")
    (tmp_path / "t.xml").write_text("<tapSet></tapSet>")
    with pytest.raises(ValueError, match="no <tap> elements"):
        read_taps(tmp_path / "t.xml")
    (tmp_path / "t.xml").write_text("<tapSet><tap><tapAccel><value>1</value></tapAccel></tap></tapSet>")
    with pytest.raises(ValueError, match="missing <tapSpeed>"):
        read_taps(tmp_path / "t.xml")
    (tmp_path / "t.xml").write_text("<tapSet><tap><tapSpeed>3</tapSpeed></tap></tapSet>")
    with pytest.raises(ValueError, match="missing <tapAccel>"):
        read_taps(tmp_path / "t.xml")


# ---- TexNet ratings ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    "attribute, rating, expected",
    [
        ("roughness", 100, ("rough_smooth", -100.0)),  # very rough → the "rough" pole
        ("roughness", 0, ("rough_smooth", 100.0)),
        ("roughness", 30, ("rough_smooth", 40.0)),  # 100 − 2·30
        ("bumpiness", 100, ("flat_bumpy", 100.0)),  # very bumpy → the "bumpy" pole
        ("bumpiness", 30, ("flat_bumpy", -40.0)),  # 2·30 − 100
        ("stickiness", 100, ("sticky_slippery", -100.0)),  # very sticky → the "sticky" pole
        ("stickiness", 25, ("sticky_slippery", 50.0)),
        ("hardness", 100, ("hard_soft", -100.0)),  # very hard → the "hard" pole
        ("hardness", 50, ("hard_soft", 0.0)),
    ],
)
def test_texnet_poles_map_to_bipolar_attributes(attribute, rating, expected):
    assert to_bipolar(attribute, rating) == expected


@pytest.mark.parametrize(
    "attribute, rating, message",
    [
        ("warmness", 50, "unknown TexNet attribute"),
        ("roughness", 101, r"\[0, 100\]"),
        ("hardness", -1, r"\[0, 100\]"),
        ("hardness", float("nan"), r"\[0, 100\]"),
    ],
)
def test_texnet_rejects_bad_ratings(attribute, rating, message):
    with pytest.raises(ValueError, match=message):
        to_bipolar(attribute, rating)


def test_read_texnet_ratings_drops_warmness_and_keeps_presentations(tmp_path):
    path = tmp_path / "ratings.csv"
    path.write_text(
        "texture,rater,presentation,attribute,rating\n"
        "wood,r1,1,roughness,20\nwood,r1,1,warmness,90\nwood,r1,2,roughness,40\nwood,r2,1,hardness,75\n"
    )
    assert read_texnet_ratings(path) == {
        "wood": {"rough_smooth": [("r1", 1, 60.0), ("r1", 2, 20.0)], "hard_soft": [("r2", 1, -50.0)]}
    }


def test_read_texnet_ratings_names_bad_rows(tmp_path):
    path = tmp_path / "ratings.csv"
    path.write_text("texture,rater,attribute,rating\nwood,r1,roughness,20\n")
    with pytest.raises(ValueError, match=r"missing column\(s\) \['presentation'\]"):
        read_texnet_ratings(path)
    path.write_text("texture,rater,presentation,attribute,rating\nwood,r1,1,roughness,20\nwood,r1,1,roughness,120\n")
    with pytest.raises(ValueError, match=r"ratings.csv line 3: TexNet rating must lie in \[0, 100\], got 120"):
        read_texnet_ratings(path)


# ---- the real HaTT–TexNet data (../shared) -----------------------------------------------------
def _xml_rows(node, tag):
    return np.array([float(v.text) for v in node.find(tag).findall("value")])


@pytest.mark.shared
def test_every_hatt_model_parses_and_its_lsfs_give_its_coefficients(hatt_dir):
    files = sorted((hatt_dir / "models").glob("*.xml"))
    assert len(files) == 100
    for path in files:
        model = read_model(path, hatt_dir / "taps" / path.name, name=path.stem)
        assert model.rate_hz == 1000.0 and model.taps is not None and model.taps.accel.shape[1] == 100
        xml_models = ET.parse(path).getroot().findall("model")
        assert len(xml_models) == model.speeds.size
        ar_xml = np.stack([_xml_rows(node, "ARcoeff") for node in xml_models])
        ma_xml = np.stack([_xml_rows(node, "MAcoeff") for node in xml_models])
        np.testing.assert_allclose(lsf_to_poly(model.ar_lsf), ar_xml, atol=1e-4, err_msg=f"{path.name}: AR")
        np.testing.assert_allclose(lsf_to_poly(model.ma_lsf), ma_xml, atol=1e-4, err_msg=f"{path.name}: MA")


@pytest.mark.shared
def test_a_hatt_model_renders_finite_bounded_vibration(hatt_dir):
    model = read_model(hatt_dir / "models" / "wood.xml")
    n = 3000
    out = render(model, np.full(n, 0.5 * model.max_speed), np.full(n, 0.5 * model.max_force), np.random.default_rng(0))
    assert np.all(np.isfinite(out)) and 0.01 < out.std() < 100.0  # m/s²


@pytest.mark.shared
def test_texnet_conversion_of_a_real_texture(hatt_dir):
    """A texture with mean roughness r (presentation 1) has mean rough_smooth 100 − 2r, and so on."""
    raw: dict[str, list[float]] = {}
    with open(hatt_dir / "ratings.csv", newline="") as fh:
        for r in csv.DictReader(fh):
            if r["texture"] == "wood" and r["presentation"] == "1":
                raw.setdefault(r["attribute"], []).append(float(r["rating"]))
    converted = read_texnet_ratings(hatt_dir / "ratings.csv")["wood"]
    mean = {a: np.mean([v for _, p, v in rows if p == 1]) for a, rows in converted.items()}
    assert set(converted) == {"rough_smooth", "flat_bumpy", "sticky_slippery", "hard_soft"}
    assert mean["rough_smooth"] == pytest.approx(100 - 2 * np.mean(raw["roughness"]))
    assert mean["flat_bumpy"] == pytest.approx(2 * np.mean(raw["bumpiness"]) - 100)
    assert mean["sticky_slippery"] == pytest.approx(100 - 2 * np.mean(raw["stickiness"]))
    assert mean["hard_soft"] == pytest.approx(100 - 2 * np.mean(raw["hardness"]))
    assert any(p == 2 for _, p, _ in converted["rough_smooth"])  # wood is an attention-check repeat
