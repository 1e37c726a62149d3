"""A texture library: entries with perceptual ratings, each with its rendering model.

    LIB/library.json      {"format": "hapticlink-library", "version": 1, "name": …, "entries": [entry, …]}
    LIB/models/<id>.npz   the entry's VibrationModel (friction μ and tap transients included)

entry = {"id", "name", "group", "ratings": {attr: bipolar}, "spread": {attr: sd} | null,
         "ratings_source": "human" | "predicted" | "ground-truth", "provenance", "licence",
         "model": "models/<id>.npz", "image": "images/<id>.png" | null}
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from texture_library.atomic_file import write_text
from texture_library.attributes import ATTRIBUTES, check_ratings
from texture_library.vibration import VibrationModel

FORMAT = "hapticlink-library"
VERSION = 1
RATING_SOURCES = ("human", "predicted", "ground-truth")
_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


@dataclass(frozen=True)
class LibraryEntry:
    id: str
    name: str
    group: str
    ratings: np.ndarray  # (4,) bipolar
    ratings_source: str
    provenance: str
    licence: str
    model_path: str
    spread: np.ndarray | None = None  # (4,) rater standard deviation, bipolar
    image_path: str | None = None  # a photo of the surface, relative to the library root

    def __post_init__(self) -> None:
        if not _ID.match(self.id):
            raise ValueError(f"library entry id {self.id!r} is not a valid name (letters, digits, _ . -)")
        check_ratings(self.ratings, f"entry {self.id!r} ratings")
        if self.spread is not None:
            spread = np.asarray(self.spread, float)
            if spread.shape != (len(ATTRIBUTES),) or not np.all(np.isfinite(spread)) or np.any(spread < 0):
                raise ValueError(
                    f"entry {self.id!r}: spread must be {len(ATTRIBUTES)} finite values ≥ 0, got {self.spread!r}"
                )
        if self.ratings_source not in RATING_SOURCES:
            raise ValueError(
                f"entry {self.id!r}: ratings_source must be one of {RATING_SOURCES}, got {self.ratings_source!r}"
            )

    def to_json(self) -> dict:
        return {
            "id": self.id,
            "name": self.name,
            "group": self.group,
            "ratings": dict(zip(ATTRIBUTES, map(float, self.ratings))),
            "spread": None if self.spread is None else dict(zip(ATTRIBUTES, map(float, self.spread))),
            "ratings_source": self.ratings_source,
            "provenance": self.provenance,
            "licence": self.licence,
            "model": self.model_path,
            "image": self.image_path,
        }

    @classmethod
    def from_json(cls, raw: dict) -> LibraryEntry:
        missing = [k for k in ("id", "name", "ratings", "model") if k not in raw]
        if missing:
            raise ValueError(f"library entry {raw.get('id', '?')!r}: missing key(s) {missing}")
        ratings = raw["ratings"]
        unknown = set(ratings) - set(ATTRIBUTES)
        if unknown or set(ratings) != set(ATTRIBUTES):
            raise ValueError(
                f"entry {raw['id']!r}: ratings must have exactly {list(ATTRIBUTES)}, got {sorted(ratings)}"
            )
        spread = raw.get("spread")
        if spread is not None and (not isinstance(spread, dict) or set(spread) != set(ATTRIBUTES)):
            raise ValueError(f"entry {raw['id']!r}: spread must be null or have exactly {list(ATTRIBUTES)}")
        return cls(
            id=raw["id"],
            name=raw["name"],
            group=raw.get("group", ""),
            ratings=np.array([ratings[a] for a in ATTRIBUTES], float),
            ratings_source=raw.get("ratings_source", "human"),
            provenance=raw.get("provenance", ""),
            licence=raw.get("licence", ""),
            model_path=raw["model"],
            spread=None if spread is None else np.array([spread[a] for a in ATTRIBUTES], float),
            image_path=raw.get("image"),
        )


@dataclass
class Library:
    root: Path
    name: str
    entries: list[LibraryEntry]
    _models: dict[str, VibrationModel] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        ids = [e.id for e in self.entries]
        dupes = sorted({i for i in ids if ids.count(i) > 1})
        if dupes:
            raise ValueError(f"library {self.name!r}: duplicate entry ids {dupes}")
        if not self.entries:
            raise ValueError(f"library {self.name!r} has no entries")

    @cached_property
    def ids(self) -> list[str]:
        return [e.id for e in self.entries]

    @cached_property
    def ratings(self) -> np.ndarray:
        """(M, 4) bipolar ratings in entry order."""
        return np.stack([e.ratings for e in self.entries])

    def entry(self, entry_id: str) -> LibraryEntry:
        for e in self.entries:
            if e.id == entry_id:
                return e
        raise ValueError(f"no entry {entry_id!r} in library {self.name!r}")

    def model(self, entry_id: str) -> VibrationModel:
        """The entry's rendering model (loaded once)."""
        if entry_id not in self._models:
            self._models[entry_id] = VibrationModel.load(self.root / self.entry(entry_id).model_path)
        return self._models[entry_id]

    def image(self, entry_id: str) -> bytes | None:
        """The entry's photo as encoded bytes, if it has one."""
        rel = self.entry(entry_id).image_path
        return None if rel is None else (self.root / rel).read_bytes()

    def save(self) -> Path:
        self.root.mkdir(parents=True, exist_ok=True)
        doc = {"format": FORMAT, "version": VERSION, "name": self.name, "entries": [e.to_json() for e in self.entries]}
        write_text(self.root / "library.json", json.dumps(doc, indent=1))
        return self.root

    @classmethod
    def load(cls, root: str | Path) -> Library:
        root = Path(root)
        path = root / "library.json"
        if not path.is_file():
            raise ValueError(f"{root}: not a texture library (no library.json)")
        try:
            doc = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: invalid JSON ({exc})") from None
        if doc.get("format") != FORMAT or doc.get("version") != VERSION:
            raise ValueError(f"{path}: format {doc.get('format')!r} v{doc.get('version')!r} is not {FORMAT} v{VERSION}")
        return cls(root, doc.get("name", root.name), [LibraryEntry.from_json(e) for e in doc.get("entries", [])])

    def validate(self) -> list[str]:
        """Problems with the rendering models (missing or unreadable files, or too large to serve: see
        texture_library.render_model.MAX_RENDER_MODEL_BYTES)."""
        from texture_library.render_model import RenderModel  # noqa: PLC0415 - render_model imports pydantic

        problems = []
        for e in self.entries:
            try:
                RenderModel.from_vibration_model(e.id, self.model(e.id))
            except (ValueError, OSError, KeyError) as exc:
                problems.append(f"entry {e.id!r}: {exc}")
        return problems


def add_entry(lib_root: Path, entry_id: str, model: VibrationModel, **fields) -> LibraryEntry:
    """Save `model` under lib_root/models/<id>.npz and return its entry (caller collects and saves)."""
    if not _ID.match(entry_id):  # before anything is written: the id becomes a file name
        raise ValueError(f"library entry id {entry_id!r} is not a valid name (letters, digits, _ . -)")
    (lib_root / "models").mkdir(parents=True, exist_ok=True)
    rel = f"models/{entry_id}.npz"
    model.save(lib_root / rel)
    return LibraryEntry(id=entry_id, model_path=rel, **fields)
