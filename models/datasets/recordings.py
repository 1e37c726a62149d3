"""Import a user's own recordings, images and ratings (layout in docs/dataset-format.md).

    SRC/textures.csv                     texture,name,group[,rated]
    SRC/ratings.csv                      texture,rater,attribute,rating[,presentation]
    SRC/images/<texture>*.png|.jpg       one or more images per texture
    SRC/recordings/<texture>/<rec>.npz   hapticlink recording (see format.save_recording), or
    SRC/recordings/<texture>/<rec>.h5    HDF5: datasets accel, force, speed|position, each with attrs rate_hz, units, or
    SRC/recordings/<texture>/<rec>/      CSV folder: accel.csv (t,x,y,z), force.csv (t,fz | t,fx,fy,fz),
                                         speed.csv (t,speed) or position.csv (t,x[,y]); optional channels.json {kind: {units}}
Ratings are bipolar (−100…100) unless rating_scale="0-100" (0 = first pole, 100 = second pole).
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np

from models.datasets.format import (
    CHANNEL_KINDS,
    DatasetWriter,
    RatingRow,
    TextureInfo,
    TextureMeta,
    load_recording,
    read_csv,
    save_recording,
)
from models.datasets.recording import Channel, Recording, make_channel
from texture_library.attributes import ATTRIBUTES

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
MAX_RATE_JITTER = 0.05  # relative deviation of a sample interval from the median that still counts as uniform


def _csv_channel(path: Path, kind: str, units: str | None) -> Channel:
    try:
        table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as exc:
        raise ValueError(f"{path}: not a numeric CSV with a header row ({exc})") from None
    if table.shape[0] < 2 or table.shape[1] < 2:
        raise ValueError(f"{path}: need a time column and at least one data column over ≥ 2 rows, got shape {table.shape}")
    t = table[:, 0]
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ValueError(f"{path}: time column (s) must increase strictly")
    step = float(np.median(dt))
    if np.max(np.abs(dt - step)) > MAX_RATE_JITTER * step:
        raise ValueError(f"{path}: not uniformly sampled (intervals vary by more than {MAX_RATE_JITTER:.0%}); resample it first")
    try:
        return make_channel(kind, table[:, 1:], 1.0 / step, units)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def read_csv_recording(folder: Path) -> Recording:
    units = {}
    if (folder / "channels.json").is_file():
        units = {k: v.get("units") for k, v in json.loads((folder / "channels.json").read_text()).items()}
    chans = {k: _csv_channel(folder / f"{k}.csv", k, units.get(k)) for k in CHANNEL_KINDS if (folder / f"{k}.csv").is_file()}
    for needed in ("accel", "force"):
        if needed not in chans:
            raise ValueError(f"{folder}: missing {needed}.csv")
    try:
        return Recording(chans["accel"], chans["force"], chans.get("speed"), chans.get("position"))
    except ValueError as exc:
        raise ValueError(f"{folder}: {exc}") from None


def read_hdf5_recording(path: Path) -> Recording:
    try:
        import h5py
    except ImportError:
        raise ValueError(f"{path}: reading HDF5 needs h5py (pip install h5py)") from None
    chans = {}
    with h5py.File(path, "r") as fh:
        for kind in CHANNEL_KINDS:
            if kind in fh:
                ds = fh[kind]
                if "rate_hz" not in ds.attrs:
                    raise ValueError(f"{path}: dataset {kind!r} has no rate_hz attribute")
                units = ds.attrs.get("units")
                units = units.decode() if isinstance(units, bytes) else units
                try:
                    chans[kind] = make_channel(kind, ds[()], float(ds.attrs["rate_hz"]), units)
                except ValueError as exc:
                    raise ValueError(f"{path}: {exc}") from None
    for needed in ("accel", "force"):
        if needed not in chans:
            raise ValueError(f"{path}: missing dataset {needed!r}")
    try:
        return Recording(chans["accel"], chans["force"], chans.get("speed"), chans.get("position"))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def read_any_recording(path: Path) -> Recording:
    if path.is_dir():
        return read_csv_recording(path)
    if path.suffix == ".npz":
        return load_recording(path)
    if path.suffix in (".h5", ".hdf5"):
        return read_hdf5_recording(path)
    raise ValueError(f"{path}: unknown recording type (expected a CSV folder, .npz or .h5)")


def build_recordings(src: str | Path, out: str | Path, *, rating_scale: str = "bipolar") -> Path:
    src = Path(src)
    if rating_scale not in ("bipolar", "0-100"):
        raise ValueError(f"rating_scale must be 'bipolar' or '0-100', got {rating_scale!r}")
    textures = read_csv(src / "textures.csv", ("texture", "name", "group"))
    rating_rows = read_csv(src / "ratings.csv", ("texture", "rater", "attribute", "rating")) if (src / "ratings.csv").is_file() else []
    by_texture: dict[str, list[RatingRow]] = {}
    for line, r in enumerate(rating_rows, start=2):
        if r["attribute"] not in ATTRIBUTES:
            raise ValueError(f"{src / 'ratings.csv'} line {line}: unknown attribute {r['attribute']!r}; expected one of {list(ATTRIBUTES)}")
        value = float(r["rating"])
        if rating_scale == "0-100":
            value = 2.0 * value - 100.0
        by_texture.setdefault(r["texture"], []).append(
            RatingRow(r["texture"], r["rater"], int(r.get("presentation") or 1), r["attribute"], value)
        )
    writer = DatasetWriter(out, name=src.name, source="recordings", licence="user data", provenance=f"imported from {src.resolve()}",
                           build={"crop_s": 0.0, "rating_scale": rating_scale})
    for row in textures:
        tid = row["texture"]
        tdir = writer.texture_dir(tid)
        rec_dir = src / "recordings" / tid
        if not rec_dir.is_dir():
            raise ValueError(f"texture {tid!r}: no recordings folder {rec_dir}")
        names = []
        for k, item in enumerate(sorted(p for p in rec_dir.iterdir() if p.is_dir() or p.suffix in (".npz", ".h5", ".hdf5"))):
            name = f"recording_{k:03d}.npz"
            save_recording(tdir / name, read_any_recording(item))
            names.append(name)
        images = []
        for k, img in enumerate(sorted(p for p in (src / "images").glob(f"{tid}*") if p.suffix.lower() in IMAGE_SUFFIXES)):
            name = f"image_{k:03d}{img.suffix.lower()}"
            shutil.copyfile(img, tdir / name)
            images.append(name)
        rated = row.get("rated") or ("yes" if tid in by_texture else "no")
        writer.add_texture(TextureInfo(tid, row["name"], row["group"], rated), TextureMeta(images, names), by_texture.get(tid, []))
    return writer.close()
