"""The hapticlink dataset format, version 1 (documented in docs/dataset-format.md).

DIR/dataset.json                 format, version, name, source, attributes, rating scale, licence, build
DIR/textures.csv                 texture,name,group,rated            (rated: yes | withheld | no)
DIR/ratings.csv                  texture,rater,presentation,attribute,rating   (bipolar −100…100)
DIR/textures/<id>/meta.json      images, recordings, vibration model, extra
DIR/textures/<id>/recording_*.npz  one stroke recording (channels with their own rates and units)
DIR/textures/<id>/image_*.png    images (or absolute paths to images kept outside, e.g. HaTT's)
DIR/textures/<id>/vibration.npz  the texture's rendering model, when known (with its tap transients, if any)
DIR/features/                    feature caches (derived; safe to delete)
"""

from __future__ import annotations

import csv
import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from texture_library.attributes import ATTRIBUTES, RATING_MAX, RATING_MIN
from texture_library.recording import Recording, load_recording, save_recording  # noqa: F401 - part of the format
from texture_library.taps import TapSet
from texture_library.vibration import VibrationModel

FORMAT = "hapticlink-dataset"
VERSION = 1
RATED_VALUES = ("yes", "withheld", "no")
TEXTURE_COLUMNS = ("texture", "name", "group", "rated")
RATING_COLUMNS = ("texture", "rater", "presentation", "attribute", "rating")
MODALITIES = ("recordings", "images")  # what a dataset's textures carry; dataset.json "modalities", absent = both


@dataclass(frozen=True)
class TextureInfo:
    texture: str
    name: str
    group: str
    rated: str  # yes | withheld | no


@dataclass(frozen=True)
class RatingRow:
    texture: str
    rater: str
    presentation: int
    attribute: str
    rating: float


@dataclass
class TextureMeta:
    images: list[str] = field(default_factory=list)
    recordings: list[str] = field(default_factory=list)
    vibration_model: str | None = None
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "images": self.images,
            "recordings": self.recordings,
            "vibration_model": self.vibration_model,
            "extra": self.extra,
        }


# ---- writing ------------------------------------------------------------------------------------
class DatasetWriter:
    """Builds a dataset directory texture by texture; `close()` writes the tables and the header."""

    def __init__(
        self,
        root: str | Path,
        *,
        name: str,
        source: str,
        licence: str,
        provenance: str,
        build: dict | None = None,
        modalities: tuple[str, ...] = MODALITIES,
        reference_predictions: dict | None = None,
    ):
        """modalities: what every texture carries (("images",): an image-only dataset, no recordings);
        reference_predictions: {"name", "path", …} of a published prediction table kept outside the dataset."""
        unknown = [m for m in modalities if m not in MODALITIES]
        if unknown or not modalities:
            raise ValueError(f"modalities must be a non-empty subset of {MODALITIES}, got {modalities}")
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        (self.root / "textures").mkdir(exist_ok=True)
        self.header = {
            "format": FORMAT,
            "version": VERSION,
            "name": name,
            "source": source,
            "attributes": list(ATTRIBUTES),
            "rating_scale": [RATING_MIN, RATING_MAX],
            "licence": licence,
            "provenance": provenance,
            "build": build or {},
        }
        if tuple(modalities) != MODALITIES:
            # written only when it differs from the default, so every dataset built before keeps its fingerprint
            self.header["modalities"] = [m for m in MODALITIES if m in modalities]
        if reference_predictions is not None:
            self.header["reference_predictions"] = reference_predictions
        self.textures: list[TextureInfo] = []
        self.ratings: list[RatingRow] = []

    def texture_dir(self, texture: str) -> Path:
        d = self.root / "textures" / texture
        d.mkdir(parents=True, exist_ok=True)
        return d

    def add_texture(self, info: TextureInfo, meta: TextureMeta, ratings: list[RatingRow] = ()) -> None:
        if info.rated not in RATED_VALUES:
            raise ValueError(f"texture {info.texture!r}: rated must be one of {RATED_VALUES}, got {info.rated!r}")
        d = self.texture_dir(info.texture)
        (d / "meta.json").write_text(json.dumps(meta.to_json(), indent=1))
        self.textures.append(info)
        self.ratings.extend(ratings)

    def close(self) -> Path:
        write_csv(
            self.root / "textures.csv", TEXTURE_COLUMNS, [(t.texture, t.name, t.group, t.rated) for t in self.textures]
        )
        write_csv(
            self.root / "ratings.csv",
            RATING_COLUMNS,
            [(r.texture, r.rater, r.presentation, r.attribute, f"{r.rating:.10g}") for r in self.ratings],
        )
        (self.root / "dataset.json").write_text(json.dumps(self.header, indent=1))
        return self.root


def write_csv(path: Path, columns: tuple[str, ...], rows) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(columns)
        w.writerows(rows)


# ---- reading ------------------------------------------------------------------------------------
class Dataset:
    """Read access to a dataset directory. Construction checks only the header; run
    `models.offline.datasets.check.check_dataset` for a full validation."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        header_path = self.root / "dataset.json"
        if not header_path.is_file():
            raise ValueError(f"{self.root}: not a hapticlink dataset (no dataset.json)")
        try:
            self.header = json.loads(header_path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{header_path}: invalid JSON ({exc})") from None
        if self.header.get("format") != FORMAT:
            raise ValueError(f"{header_path}: format is {self.header.get('format')!r}, expected {FORMAT!r}")
        if self.header.get("version") != VERSION:
            raise ValueError(
                f"{header_path}: unsupported version {self.header.get('version')!r} (this hapticlink reads {VERSION})"
            )

    @property
    def name(self) -> str:
        return str(self.header.get("name", self.root.name))

    @property
    def modalities(self) -> tuple[str, ...]:
        """What the textures carry: ("recordings", "images") unless dataset.json says less."""
        return tuple(self.header.get("modalities", MODALITIES))

    @property
    def has_recordings(self) -> bool:
        """False for an image-only dataset: no texture has a recording, and no model may ask for touch."""
        return "recordings" in self.modalities

    @property
    def reference_predictions(self) -> dict | None:
        """The published prediction table the header names ({"name", "path", …}), or None."""
        return self.header.get("reference_predictions")

    def textures(self) -> list[TextureInfo]:
        return [
            TextureInfo(r["texture"], r["name"], r["group"], r["rated"])
            for r in read_csv(self.root / "textures.csv", TEXTURE_COLUMNS)
        ]

    def texture_ids(self, rated: str | None = None) -> list[str]:
        return [t.texture for t in self.textures() if rated is None or t.rated == rated]

    def rating_rows(self) -> list[RatingRow]:
        return [
            RatingRow(r["texture"], r["rater"], int(r["presentation"]), r["attribute"], float(r["rating"]))
            for r in read_csv(self.root / "ratings.csv", RATING_COLUMNS)
        ]

    def rating_table(self) -> tuple[list[str], list[str], np.ndarray]:
        """(texture ids, rater ids, ratings (textures, raters, 4) with NaN where missing); first presentation only."""
        rows = [r for r in self.rating_rows() if r.presentation == 1]
        textures = sorted({r.texture for r in rows})
        raters = sorted({r.rater for r in rows})
        ti = {t: i for i, t in enumerate(textures)}
        ri = {r: i for i, r in enumerate(raters)}
        ai = {a: i for i, a in enumerate(ATTRIBUTES)}
        table = np.full((len(textures), len(raters), len(ATTRIBUTES)), np.nan)
        for r in rows:
            table[ti[r.texture], ri[r.rater], ai[r.attribute]] = r.rating
        return textures, raters, table

    def mean_ratings(self) -> dict[str, np.ndarray]:
        """Texture id → mean bipolar rating over raters (4,), first presentation only; NaN for an attribute
        nobody rated."""
        textures, _, table = self.rating_table()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # "Mean of empty slice": that NaN is the answer
            return {t: np.nanmean(table[i], axis=0) for i, t in enumerate(textures)}

    def meta(self, texture: str) -> TextureMeta:
        path = self.root / "textures" / texture / "meta.json"
        if not path.is_file():
            raise ValueError(f"texture {texture!r}: missing {path}")
        try:
            raw = json.loads(path.read_text())
        except ValueError as exc:
            raise ValueError(f"texture {texture!r}: {path}: invalid JSON ({exc})") from None
        if not isinstance(raw, dict):
            raise ValueError(f"texture {texture!r}: {path}: expected a JSON object")
        return TextureMeta(
            raw.get("images", []), raw.get("recordings", []), raw.get("vibration_model"), raw.get("extra", {})
        )

    def resolve(self, texture: str, name: str) -> Path:
        """A path from meta.json: absolute as is, else relative to the texture's folder."""
        p = Path(name)
        return p if p.is_absolute() else self.root / "textures" / texture / p

    def recordings(self, texture: str) -> list[Recording]:
        return [load_recording(self.resolve(texture, r)) for r in self.meta(texture).recordings]

    def image_paths(self, texture: str) -> list[Path]:
        return [self.resolve(texture, p) for p in self.meta(texture).images]

    def vibration_model_path(self, texture: str) -> Path | None:
        name = self.meta(texture).vibration_model
        return None if name is None else self.resolve(texture, name)

    def taps(self, texture: str) -> TapSet | None:
        """The texture's recorded tap transients (stored with its vibration model), or None."""
        path = self.vibration_model_path(texture)
        return None if path is None else VibrationModel.load(path).taps

    @property
    def features_dir(self) -> Path:
        return self.root / "features"


def read_csv(path: Path, columns: tuple[str, ...]) -> list[dict[str, str]]:
    if not path.is_file():
        raise ValueError(f"missing file: {path}")
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        missing = [c for c in columns if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}; expected {list(columns)}")
        return list(reader)
