"""Import a user's own recordings, images and ratings (layout in docs/dataset-format.md).

    SRC/textures.csv                     texture,name,group[,rated]
    SRC/ratings.csv                      texture,rater,attribute,rating[,presentation]
    SRC/images/<texture>*.png|.jpg       one or more images per texture
    SRC/recordings/<texture>/<rec>.npz   hapticlink recording (see format.save_recording), or
    SRC/recordings/<texture>/<rec>.h5    HDF5: datasets accel, force, speed|position, each with attrs rate_hz, units, or
    SRC/recordings/<texture>/<rec>/      CSV folder: accel.csv (t,x,y,z), force.csv (t,fz | t,fx,fy,fz),
                                         speed.csv (t,speed) or position.csv (t,x[,y]);
                                         optional channels.json {kind: {units}}
    SRC/recordings/<texture>/<bag>       source "rosbag": ROS 2 bags (a bag folder, .db3 or .mcap), read through a
                                         topic map (drivers/rosbag_topics.yaml); each stretch in which accel, force
                                         and speed all run (≥ 1 s) is one recording; a texture without images in
                                         SRC/images takes its first bag's first camera image
Ratings are bipolar (−100…100) unless rating_scale="0-100" (0 = first pole, 100 = second pole).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from drivers.blocks import Frame
from drivers.rosbag_mapping import TopicMap, load_topic_map
from drivers.rosbag_source import bag_first_image, bag_recordings, scan_bag
from models.offline.datasets.format import (
    DatasetWriter,
    RatingRow,
    TextureInfo,
    TextureMeta,
    load_recording,
    read_csv,
    save_recording,
)
from texture_library.attributes import ATTRIBUTES
from texture_library.channels import CHANNEL_KINDS
from texture_library.recording import Channel, Recording, make_channel, recording_from_channels

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
MAX_RATE_JITTER = 0.05  # relative deviation of a sample interval from the median that still counts as uniform


def _csv_channel(path: Path, kind: str, units: str | None) -> Channel:
    try:
        table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as exc:
        raise ValueError(f"{path}: not a numeric CSV with a header row ({exc})") from None
    if table.shape[0] < 2 or table.shape[1] < 2:
        raise ValueError(
            f"{path}: need a time column and at least one data column over ≥ 2 rows, got shape {table.shape}"
        )
    t = table[:, 0]
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ValueError(f"{path}: time column (s) must increase strictly")
    step = float(np.median(dt))
    if np.max(np.abs(dt - step)) > MAX_RATE_JITTER * step:
        raise ValueError(
            f"{path}: not uniformly sampled (intervals vary by more than {MAX_RATE_JITTER:.0%}); resample it first"
        )
    try:
        return make_channel(kind, table[:, 1:], 1.0 / step, units)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def read_csv_recording(folder: Path) -> Recording:
    units = {}
    if (folder / "channels.json").is_file():
        try:
            spec = json.loads((folder / "channels.json").read_text())
        except ValueError as exc:
            raise ValueError(f"{folder / 'channels.json'}: invalid JSON ({exc})") from None
        if not isinstance(spec, dict) or not all(isinstance(v, dict) for v in spec.values()):
            raise ValueError(f'{folder / "channels.json"}: expected {{channel: {{"units": …}}, …}}')
        unknown = sorted(set(spec) - set(CHANNEL_KINDS))
        if unknown:
            raise ValueError(
                f"{folder / 'channels.json'}: unknown channel(s) {unknown}; expected some of {list(CHANNEL_KINDS)}"
            )
        units = {k: v.get("units") for k, v in spec.items()}
    chans = {
        k: _csv_channel(folder / f"{k}.csv", k, units.get(k)) for k in CHANNEL_KINDS if (folder / f"{k}.csv").is_file()
    }
    return recording_from_channels(chans, str(folder))


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
    return recording_from_channels(chans, str(path))


BAG_SUFFIXES = (".db3", ".mcap")


def is_bag(path: Path) -> bool:
    """A ROS 2 bag: a .db3 or .mcap file, or a bag folder (it holds metadata.yaml)."""
    return path.suffix in BAG_SUFFIXES or (path.is_dir() and (path / "metadata.yaml").is_file())


def read_any_recording(path: Path) -> Recording:
    if path.is_dir():
        return read_csv_recording(path)
    if path.suffix == ".npz":
        return load_recording(path)
    if path.suffix in (".h5", ".hdf5"):
        return read_hdf5_recording(path)
    raise ValueError(f"{path}: unknown recording type (expected a CSV folder, .npz or .h5)")


def _assign_images(image_dir: Path, textures: list[str]) -> dict[str, list[Path]]:
    """Images named <texture>*.ext, each given to the texture with the longest id that prefixes its
    name (so `wood_2.png` goes to texture `wood_2`, not to `wood`, when both exist)."""
    out: dict[str, list[Path]] = {t: [] for t in textures}
    if not image_dir.is_dir():
        return out
    by_length = sorted(textures, key=len, reverse=True)
    for img in sorted(image_dir.iterdir()):
        if not img.is_file() or img.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        owner = next((t for t in by_length if img.name.startswith(t)), None)
        if owner is not None:
            out[owner].append(img)
    return out


def _read_item(item: Path, topic_map: TopicMap | None) -> tuple[list[Recording], Frame | None]:
    """The recordings in one item of a texture's folder, and the first camera image of a bag (else None)."""
    if topic_map is None:
        return [read_any_recording(item)], None
    scan = scan_bag(item, topic_map)
    return bag_recordings(scan), bag_first_image(scan)


def build_recordings(
    src: str | Path,
    out: str | Path,
    *,
    rating_scale: str = "bipolar",
    topics: str | Path | None = None,
    source: str = "recordings",
) -> Path:
    """Import SRC (layout above) into a dataset at out. source "rosbag": its recordings are ROS 2 bags read through
    the topic map in `topics` (None: the defaults). ValueError names the file and line at fault."""
    src = Path(src)
    topic_map = load_topic_map(topics) if source == "rosbag" else None
    if source not in ("recordings", "rosbag"):
        raise ValueError(f"source must be 'recordings' or 'rosbag', got {source!r}")
    if rating_scale not in ("bipolar", "0-100"):
        raise ValueError(f"rating_scale must be 'bipolar' or '0-100', got {rating_scale!r}")
    textures = read_csv(src / "textures.csv", ("texture", "name", "group"))
    ids = [row["texture"] for row in textures]
    dupes = sorted({t for t in ids if ids.count(t) > 1})
    if dupes:
        raise ValueError(f"{src / 'textures.csv'}: texture(s) listed twice: {dupes}")
    rating_rows = (
        read_csv(src / "ratings.csv", ("texture", "rater", "attribute", "rating"))
        if (src / "ratings.csv").is_file()
        else []
    )
    by_texture: dict[str, list[RatingRow]] = {}
    for line, r in enumerate(rating_rows, start=2):
        where = f"{src / 'ratings.csv'} line {line}"
        if r["texture"] not in ids:
            raise ValueError(f"{where}: texture {r['texture']!r} is not in textures.csv")
        if r["attribute"] not in ATTRIBUTES:
            raise ValueError(f"{where}: unknown attribute {r['attribute']!r}; expected one of {list(ATTRIBUTES)}")
        try:
            value = float(r["rating"])
            presentation = int(r.get("presentation") or 1)
        except (TypeError, ValueError):
            raise ValueError(
                f"{where}: rating {r['rating']!r} / presentation {r.get('presentation')!r} is not a number"
            ) from None
        if rating_scale == "0-100":
            if not 0.0 <= value <= 100.0:
                raise ValueError(f"{where}: rating {value:g} is outside 0–100 (--rating-scale 0-100)")
            value = 2.0 * value - 100.0
        elif not -100.0 <= value <= 100.0:
            raise ValueError(
                f"{where}: rating {value:g} is outside −100…100 (bipolar; use --rating-scale 0-100 for 0–100 ratings)"
            )
        by_texture.setdefault(r["texture"], []).append(
            RatingRow(r["texture"], r["rater"], presentation, r["attribute"], value)
        )
    images = _assign_images(src / "images", ids)
    writer = DatasetWriter(
        out,
        name=src.name,
        source=source,
        licence="user data",
        provenance=f"imported from {src.resolve()}",
        build={"crop_s": 0.0, "rating_scale": rating_scale},
    )
    for row in textures:
        tid = row["texture"]
        rec_dir = src / "recordings" / tid
        if not rec_dir.is_dir():
            raise ValueError(f"texture {tid!r}: no recordings folder {rec_dir}")
        if topic_map is None:
            items = sorted(p for p in rec_dir.iterdir() if p.is_dir() or p.suffix in (".npz", ".h5", ".hdf5"))
            what = "CSV folders, .npz or .h5"
        else:
            items = sorted(p for p in rec_dir.iterdir() if is_bag(p))
            what = "ROS 2 bags: bag folders, .db3 or .mcap"
        if not items:
            raise ValueError(f"texture {tid!r}: {rec_dir} holds no recordings ({what})")
        tdir = writer.texture_dir(tid)
        names = []
        bag_image: Frame | None = None
        for item in items:
            recordings, first_image = _read_item(item, topic_map)
            bag_image = bag_image or first_image
            for recording in recordings:
                name = f"recording_{len(names):03d}.npz"
                try:
                    save_recording(tdir / name, recording)
                except ValueError as exc:  # too long for a dataset to load back: the message names the copy
                    raise ValueError(f"{item}: cannot be imported ({exc}); split it into shorter recordings") from None
                names.append(name)
        image_names = []
        for k, img in enumerate(images[tid]):
            name = f"image_{k:03d}{img.suffix.lower()}"
            shutil.copyfile(img, tdir / name)
            image_names.append(name)
        if not image_names and bag_image is not None:
            name = "image_000" + (".png" if bag_image.content_type == "image/png" else ".jpg")
            (tdir / name).write_bytes(bag_image.image)
            image_names.append(name)
        rated = row.get("rated") or ("yes" if tid in by_texture else "no")
        if rated == "no" and tid in by_texture:
            raise ValueError(f"texture {tid!r}: textures.csv says rated=no but ratings.csv has ratings for it")
        # withheld: the ratings exist but stay out of the project (docs/dataset-format.md)
        rows = by_texture.get(tid, []) if rated == "yes" else []
        writer.add_texture(TextureInfo(tid, row["name"], row["group"], rated), TextureMeta(image_names, names), rows)
    return writer.close()
