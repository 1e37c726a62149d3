"""Build the hassan2023 dataset (Hassan, Joolee & Jeon 2023, Sci. Rep. 13:11684) from its folder, read in place.

An image-only dataset: one colour photo per texture (referenced by absolute path, never copied), the published
mean touch ratings mapped to the bipolar scale (published −50…+50 × 2), no recordings. Textures whose photo
could not be obtained are left out; withheld textures are built without ratings. The published 1D-CNN
predictions are not copied either: the header names their file, and the report reads it from there.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

from models.offline.datasets.format import DatasetWriter, RatingRow, TextureInfo, TextureMeta
from texture_library.attributes import ATTRIBUTES, RATING_MAX, RATING_MIN

LICENCE = (
    "Hassan, Joolee, Jeon (2023), Scientific Reports 13, 11684, doi:10.1038/s41598-023-38929-6, CC BY 4.0: "
    "cite the paper. Read from its folder; never copied into the project."
)
PUBLISHED_SCALE = 50.0  # the published ratings run −50 … +50
TO_BIPOLAR = RATING_MAX / PUBLISHED_SCALE  # × 2 onto the project's −100 … +100
RATER = "mean"  # only texture means were published: one pseudo-rater per texture
REFERENCE_NAME = "published-1dcnn"


def read_bipolar_table(path: Path) -> dict[str, tuple[float, ...]]:
    """`texture, rough_smooth, flat_bumpy, sticky_slippery, hard_soft` on the published −50…+50 scale →
    texture → (4,) bipolar −100…100 values; ValueError naming the line for a bad or out-of-range value."""
    if not path.is_file():
        raise ValueError(f"missing file: {path}")
    out: dict[str, tuple[float, ...]] = {}
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        missing = [c for c in ("texture", *ATTRIBUTES) if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}")
        for line, row in enumerate(reader, start=2):
            values = []
            for a in ATTRIBUTES:
                try:
                    v = float(row[a])
                except (TypeError, ValueError):
                    raise ValueError(f"{path} line {line}: {a} {row[a]!r} is not a number") from None
                if not math.isfinite(v) or abs(v) > PUBLISHED_SCALE:
                    raise ValueError(f"{path} line {line}: {a} = {row[a]} outside ±{PUBLISHED_SCALE:g}")
                values.append(min(max(v * TO_BIPOLAR, RATING_MIN), RATING_MAX))
            if row["texture"] in out:
                raise ValueError(f"{path} line {line}: texture {row['texture']!r} listed twice")
            out[row["texture"]] = tuple(values)
    return out


def build_hassan2023(src: str | Path, out: str | Path, *, limit: int | None = None) -> Path:
    """Build the image-only dataset from `src` (the hassan2023 folder); `limit` keeps the first N textures that
    have a photo (quick trials)."""
    src = Path(src).resolve()
    for needed in ("textures.csv", "ratings.csv", "published_predictions.csv", "images"):
        if not (src / needed).exists():
            raise ValueError(f"{src} does not look like hassan2023: missing {needed}")
    with open(src / "textures.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    ratings = read_bipolar_table(src / "ratings.csv")
    with_photo = [r for r in rows if r.get("image") == "yes"]
    if limit is not None:
        with_photo = with_photo[:limit]
    writer = DatasetWriter(
        out,
        name="hassan2023",
        source="hassan2023",
        licence=LICENCE,
        provenance=f"built from {src}: photos referenced in place; published mean touch ratings × {TO_BIPOLAR:g}",
        build={
            "src": str(src),
            "rating_map": f"bipolar = {TO_BIPOLAR:g} × published (−50…+50)",
            "without_photo": sorted(r["texture"] for r in rows if r.get("image") != "yes"),
        },
        modalities=("images",),
        reference_predictions={
            "name": REFERENCE_NAME,
            "path": str(src / "published_predictions.csv"),
            "scale": "published −50…+50; × 2 to bipolar",
            "note": "Hassan et al.'s image-feature 1D-CNN; the data do not say whether cross-validated",
        },
    )
    for r in with_photo:
        tid = r["texture"]
        image = src / "images" / f"{tid}.jpg"
        status = {"yes": "yes", "withheld": "withheld"}.get(r.get("ratings", ""), "no")
        if status == "yes" and tid not in ratings:
            raise ValueError(f"{src / 'textures.csv'}: texture {tid!r} is marked rated but has no row in ratings.csv")
        rated = [RatingRow(tid, RATER, 1, a, v) for a, v in zip(ATTRIBUTES, ratings[tid])] if status == "yes" else []
        writer.add_texture(TextureInfo(tid, tid, "unknown", status), TextureMeta(images=[str(image)]), rated)
    return writer.close()
