"""`hapticlink library import-hatt`: a library of HaTT's 100 rendering models with perceptual ratings.

Ratings come from TexNet's raters where they are known; other textures take a
model's predictions (a CSV from `hapticlink predict`) or are left out. The
library lives outside the repository: HaTT may not be redistributed.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from texture_library.attributes import ATTRIBUTES, check_ratings
from texture_library.hatt_xml import read_model
from texture_library.library import Library, add_entry
from texture_library.texnet import read_texnet_ratings

LICENCE = "HaTT (c) 2013 University of Pennsylvania: non-profit research use only, no redistribution"


def read_predictions(path: str | Path) -> dict[str, np.ndarray]:
    """CSV with columns texture + the four attributes (bipolar) → {texture: (4,)}."""
    out = {}
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        missing = [c for c in ("texture", *ATTRIBUTES) if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}")
        for line, r in enumerate(reader, start=2):
            try:
                out[r["texture"]] = check_ratings(np.array([float(r[a]) for a in ATTRIBUTES]), f"{path} line {line}")
            except ValueError as exc:
                raise ValueError(f"{path} line {line}: {exc}") from None
    return out


def import_hatt(
    src: str | Path, out: str | Path, *, predictions: str | Path | None = None
) -> tuple[Library, list[str]]:
    """Build the library; returns it and the textures left out (no human ratings, no prediction)."""
    src, out = Path(src), Path(out)
    if not (src / "models").is_dir() or not (src / "textures.csv").is_file():
        raise ValueError(f"{src} does not look like hatt-texnet (needs models/ and textures.csv)")
    human = read_texnet_ratings(src / "ratings.csv") if (src / "ratings.csv").is_file() else {}
    predicted = read_predictions(predictions) if predictions else {}
    with open(src / "textures.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    entries, skipped = [], []
    for r in rows:
        tid = r["texture"]
        if tid in human:
            per_attr = [np.array([v for _, p, v in human[tid][a] if p == 1]) for a in ATTRIBUTES]
            ratings, spread, source = (
                np.array([x.mean() for x in per_attr]),
                np.array([x.std() for x in per_attr]),
                "human",
            )
        elif tid in predicted:
            ratings, spread, source = predicted[tid], None, "predicted"
        else:
            skipped.append(tid)
            continue
        taps = src / "taps" / f"{tid}.xml"
        model = read_model(src / "models" / f"{tid}.xml", taps if taps.is_file() else None, name=tid)
        entries.append(
            add_entry(
                out,
                tid,
                model,
                name=r["name"],
                group=r["group"] or "unknown",
                ratings=np.round(ratings, 2),
                ratings_source=source,
                provenance=model.provenance,
                licence=LICENCE,
                spread=spread,
            )
        )
    lib = Library(out, "hatt", entries)
    lib.save()
    return lib, skipped
