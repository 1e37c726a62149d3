"""Importing a user's own recordings (CSV folders, .npz, HDF5), images and ratings."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from models.offline.datasets.build import build
from models.offline.datasets.check import check_dataset
from models.offline.datasets.format import Dataset
from models.offline.datasets.recordings import build_recordings, read_csv_recording
from service.cli import main as hapticlink
from texture_library.recording import Recording, make_channel, save_recording

G = 9.80665
N = 1500  # samples per channel at 500 Hz: 3 s


def write_csv(path: Path, t: np.ndarray, *columns: np.ndarray, header: str) -> None:
    np.savetxt(path, np.column_stack([t, *columns]), delimiter=",", header=header, comments="")


def csv_recording(folder: Path, seed: int = 0, dt: float = 0.002) -> dict[str, np.ndarray]:
    """accel in g, force (t, fz) in N, speed in m/s; channels.json says so. Returns the raw arrays."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True)
    t = np.arange(N) * dt
    raw = {
        "accel": rng.standard_normal((N, 3)) * 0.1 + [0, 0, 1],
        "force": 1.5 + 0.1 * rng.random(N),
        "speed": 0.05 + 0.01 * rng.random(N),
    }
    write_csv(folder / "accel.csv", t, raw["accel"], header="t,x,y,z")
    write_csv(folder / "force.csv", t, raw["force"], header="t,fz")
    write_csv(folder / "speed.csv", t, raw["speed"], header="t,speed")
    (folder / "channels.json").write_text(json.dumps({"accel": {"units": "g"}, "speed": {"units": "m/s"}}))
    return raw


def npz_recording(path: Path) -> Recording:
    rec = Recording(
        make_channel("accel", np.ones((2000, 3)), 1000.0),
        make_channel("force", np.ones((2000, 3)), 1000.0),
        speed=make_channel("speed", np.full(200, 80.0), 100.0),
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    save_recording(path, rec)
    return rec


def image(path: Path, size: int = 256, value: int = 0) -> None:
    Image.fromarray(np.full((size, size), value, np.uint8)).save(path)


@pytest.fixture
def source(tmp_path) -> dict:
    """SRC with textures wood (CSV folder + npz), wood_2 (npz; an image whose name starts with 'wood'),
    foam (withheld, though ratings.csv has a rating for it). Ratings on the 0–100 scale."""
    src = tmp_path / "src"
    (src / "images").mkdir(parents=True)
    (src / "textures.csv").write_text(
        "texture,name,group,rated\nwood,Wood,wood,yes\nwood_2,Wood 2,wood,yes\nfoam,Foam,foam,withheld\n"
    )
    (src / "ratings.csv").write_text(
        "texture,rater,attribute,rating\n"
        "wood,alice,rough_smooth,25\nwood,bob,rough_smooth,75\nwood,alice,hard_soft,0\n"
        "wood_2,alice,flat_bumpy,100\nfoam,alice,hard_soft,90\n"
    )
    raw = csv_recording(src / "recordings" / "wood" / "rec1")
    npz_recording(src / "recordings" / "wood" / "rec2.npz")
    npz_recording(src / "recordings" / "wood_2" / "only.npz")
    npz_recording(src / "recordings" / "foam" / "only.npz")
    image(src / "images" / "wood.png", value=10)
    image(src / "images" / "wood_2.png", value=20)
    image(src / "images" / "wood_2b.jpg", value=30)
    image(src / "images" / "foam.png", value=40)
    (src / "images" / "notes.txt").write_text("not an image")
    return {"src": src, "raw": raw}


def test_cli_imports_csv_and_npz_with_units_converted(source, tmp_path):
    out = tmp_path / "out"
    assert (
        hapticlink(
            [
                "dataset",
                "build",
                "--source",
                "recordings",
                "--path",
                str(source["src"]),
                "--out",
                str(out),
                "--rating-scale",
                "0-100",
                "--no-features",
            ]
        )
        == 0
    )
    assert check_dataset(out) == []
    ds = Dataset(out)
    assert ds.header["source"] == "recordings" and ds.header["build"]["crop_s"] == 0.0
    assert [(t.texture, t.rated) for t in ds.textures()] == [("wood", "yes"), ("wood_2", "yes"), ("foam", "withheld")]
    csv_rec, npz_rec = ds.recordings("wood")
    raw = source["raw"]
    assert csv_rec.accel.rate_hz == pytest.approx(500.0) and csv_rec.force.data.shape == (N,)
    np.testing.assert_allclose(csv_rec.accel.data, raw["accel"] * G, rtol=1e-5)  # g → m/s²
    np.testing.assert_allclose(csv_rec.speed.data, raw["speed"] * 1000.0, rtol=1e-5)  # m/s → mm/s
    np.testing.assert_allclose(csv_rec.force.data, raw["force"], rtol=1e-5)
    assert npz_rec.speed.rate_hz == 100.0 and npz_rec.force.data.shape == (2000, 3)


def test_images_go_to_the_texture_whose_id_is_their_name(source, tmp_path):
    out = build_recordings(source["src"], tmp_path / "out")
    ds = Dataset(out)
    pixel = {t: [np.asarray(Image.open(p))[0, 0] for p in ds.image_paths(t)] for t in ("wood", "wood_2", "foam")}
    assert pixel == {"wood": [10], "wood_2": [20, 30], "foam": [40]}  # wood_2*.png are not wood's
    assert [p.name for p in ds.image_paths("wood_2")] == ["image_000.png", "image_001.jpg"]


def test_ratings_are_converted_and_withheld_ones_stay_out(source, tmp_path):
    ds = Dataset(build_recordings(source["src"], tmp_path / "out", rating_scale="0-100"))
    rows = {(r.texture, r.rater, r.attribute): r.rating for r in ds.rating_rows()}
    assert rows == {
        ("wood", "alice", "rough_smooth"): -50.0,
        ("wood", "bob", "rough_smooth"): 50.0,
        ("wood", "alice", "hard_soft"): -100.0,
        ("wood_2", "alice", "flat_bumpy"): 100.0,
    }
    assert all(r.presentation == 1 for r in ds.rating_rows())


def test_bipolar_is_the_default_scale(source, tmp_path):
    (source["src"] / "ratings.csv").write_text(
        "texture,rater,attribute,rating,presentation\nwood,a,rough_smooth,-30,1\nwood,a,rough_smooth,150,2\n"
    )
    with pytest.raises(
        ValueError, match=r"ratings.csv line 3: rating 150 is outside −100…100 \(bipolar; use --rating-scale 0-100"
    ):
        build_recordings(source["src"], tmp_path / "bad")
    (source["src"] / "ratings.csv").write_text(
        "texture,rater,attribute,rating,presentation\nwood,a,rough_smooth,-30,1\nwood,a,rough_smooth,-10,2\n"
    )
    ds = Dataset(build_recordings(source["src"], tmp_path / "out"))
    assert [(r.presentation, r.rating) for r in ds.rating_rows()] == [(1, -30.0), (2, -10.0)]


def test_hdf5_recordings(source, tmp_path):
    h5py = pytest.importorskip("h5py", reason="HDF5 import needs h5py")
    folder = source["src"] / "recordings" / "wood_2"
    (folder / "only.npz").unlink()
    with h5py.File(folder / "a.h5", "w") as fh:
        for kind, data, rate, units in [
            ("accel", np.full((3000, 3), 0.5), 2000.0, "g"),
            ("force", np.full(1000, 2.0), 1000.0, "N"),
            ("position", np.linspace(0, 0.2, 500), 500.0, "m"),
        ]:
            ds = fh.create_dataset(kind, data=data)
            ds.attrs["rate_hz"] = rate
            ds.attrs["units"] = units
    out = build_recordings(source["src"], tmp_path / "out", rating_scale="0-100")
    assert check_dataset(out) == []
    (rec,) = Dataset(out).recordings("wood_2")
    assert rec.speed is None and rec.accel.rate_hz == 2000.0
    np.testing.assert_allclose(rec.accel.data, 0.5 * G, rtol=1e-6)
    np.testing.assert_allclose(rec.position.data[-1], 200.0, rtol=1e-6)  # m → mm

    with h5py.File(folder / "a.h5", "a") as fh:
        del fh["force"].attrs["rate_hz"]
    with pytest.raises(ValueError, match=r"a.h5: dataset 'force' has no rate_hz attribute"):
        build_recordings(source["src"], tmp_path / "out2", rating_scale="0-100")


def test_non_uniform_time_column_is_refused(tmp_path):
    folder = tmp_path / "rec"
    csv_recording(folder)
    t = np.arange(N) * 0.002
    t[700:] += 0.0005  # one interval 25 % long
    write_csv(folder / "force.csv", t, np.ones(N), header="t,fz")
    with pytest.raises(ValueError) as err:
        read_csv_recording(folder)
    assert str(err.value) == (
        f"{folder / 'force.csv'}: not uniformly sampled (intervals vary by more than 5%); resample it first"
    )


@pytest.mark.parametrize(
    "file, content, message",
    [
        ("force.csv", "t,fz\n0,1\n0,2\n0.002,3\n", r"force.csv: time column \(s\) must increase strictly"),
        ("force.csv", "t,fz\n0,1\n", r"force.csv: need a time column and at least one data column over ≥ 2 rows"),
        ("force.csv", "t,fz\n0,1\n0.002,heavy\n", r"force.csv: not a numeric CSV with a header row"),
        ("accel.csv", "t,x,y\n0,1,2\n0.002,1,2\n", r"accel.csv: accel: shape must be \(n, 3\), got \(2, 2\)"),
        ("channels.json", '{"accel": {"units": "furlongs"}}', r"accel.csv: accel: units must be one of"),
        ("channels.json", '{"temperature": {"units": "K"}}', r"channels.json: unknown channel\(s\) \['temperature'\]"),
        ("channels.json", "{", r"channels.json: invalid JSON"),
        ("speed.csv", None, r"recording needs a speed or a position channel"),
        ("accel.csv", None, r"missing channel 'accel'"),
    ],
)
def test_bad_csv_recordings_are_named(tmp_path, file, content, message):
    folder = tmp_path / "rec"
    csv_recording(folder)
    if content is None:
        (folder / file).unlink()
    else:
        (folder / file).write_text(content)
    with pytest.raises(ValueError, match=message):
        read_csv_recording(folder)


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda s: (s / "ratings.csv").write_text("texture,rater,attribute,rating\nwood,a,warmness,5\n"),
            r"ratings.csv line 2: unknown attribute 'warmness'",
        ),
        (
            lambda s: (s / "ratings.csv").write_text("texture,rater,attribute,rating\nwood,a,hard_soft,soft\n"),
            r"ratings.csv line 2: rating 'soft' / presentation None is not a number",
        ),
        (
            lambda s: (s / "ratings.csv").write_text("texture,rater,attribute,rating\nghost,a,hard_soft,5\n"),
            r"ratings.csv line 2: texture 'ghost' is not in textures.csv",
        ),
        (
            lambda s: (s / "ratings.csv").write_text("texture,rater,attribute,rating\nwood,a,hard_soft,101\n"),
            r"ratings.csv line 2: rating 101 is outside 0–100",
        ),
        (
            lambda s: (s / "textures.csv").write_text("texture,name,group\nwood,W,w\nwood,W,w\n"),
            r"textures.csv: texture\(s\) listed twice: \['wood'\]",
        ),
        (
            lambda s: (s / "textures.csv").write_text(
                "texture,name,group\nwood,W,w\nwood_2,W,w\nfoam,F,f\noak,Oak,w\n"
            ),
            r"texture 'oak': no recordings folder",
        ),
        (
            lambda s: (s / "textures.csv").write_text("texture,name\nwood,W\n"),
            r"textures.csv: missing column\(s\) \['group'\]",
        ),
        (
            lambda s: [p.unlink() for p in (s / "recordings" / "wood_2").iterdir()],
            r"texture 'wood_2': .* holds no recordings",
        ),
        (
            lambda s: (s / "textures.csv").write_text(
                "texture,name,group,rated\nwood,W,w,no\nwood_2,W,w,yes\nfoam,F,f,withheld\n"
            ),
            r"texture 'wood': textures.csv says rated=no but ratings.csv has ratings for it",
        ),
    ],
)
def test_bad_sources_are_named(source, tmp_path, edit, message):
    edit(source["src"])
    with pytest.raises(ValueError, match=message):
        build_recordings(source["src"], tmp_path / "out", rating_scale="0-100")


def test_a_recording_too_long_to_load_back_is_refused_by_name(source, tmp_path, monkeypatch, capsys):
    """It was written, and the dataset then could not be loaded. The CSV recording is 30 kB as float32."""
    import texture_library.npzfile as npzfile

    monkeypatch.setattr(npzfile, "MAX_NPZ_BYTES", 20_000)
    out = tmp_path / "out"
    argv = ["dataset", "build", "--source", "recordings", "--path", str(source["src"]), "--out", str(out)]
    assert hapticlink([*argv, "--rating-scale", "0-100", "--no-features"]) == 2
    err = capsys.readouterr().err
    rec1, written = source["src"] / "recordings" / "wood" / "rec1", out / "textures" / "wood" / "recording_000.npz"
    assert err.startswith(f"hapticlink dataset: error: {rec1}: cannot be imported ({written}: would hold ")
    assert "at most 20,000 bytes (0.0 MiB) are read, so it is not written); split it into shorter recordings" in err
    assert not written.exists()


def test_build_dispatch_needs_a_path_and_a_known_source(tmp_path):
    with pytest.raises(ValueError, match="--source recordings needs --path"):
        build("recordings", tmp_path / "out")
    with pytest.raises(ValueError, match="unknown source 'csv'"):
        build("csv", tmp_path / "out")
    for source in ("hatt-texnet", "hassan2023", "recordings"):  # it said "does not look like …: missing textures.csv"
        with pytest.raises(ValueError, match="--path .*/nope: no such folder"):
            build(source, tmp_path / "out", tmp_path / "nope")
