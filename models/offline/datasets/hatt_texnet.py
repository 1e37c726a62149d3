"""Build the HaTT–TexNet dataset from ../shared/data/hatt-texnet (read in place, never copied).

Per texture: the HaTT vibration model and taps (parsed), one or more 60 s
recordings rendered along seeded freehand trajectories (model-derived, and
labelled as such), the photo referenced by absolute path, and TexNet ratings
converted to bipolar attributes (see texnet.py). Withheld and unrated
textures are built without ratings so they can be predicted later.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable
from pathlib import Path

from models.offline.datasets.format import DatasetWriter, RatingRow, TextureInfo, TextureMeta, save_recording
from models.offline.datasets.simulate import simulated_recording, texture_rng
from models.offline.jobs import run_jobs
from texture_library.hatt_xml import read_model
from texture_library.texnet import read_texnet_ratings

LICENCE = (
    "HaTT: (c) 2013 The Trustees of the University of Pennsylvania, non-profit research use only, no redistribution. "
    "TexNet ratings: (c) Ultraleap Limited 2020, internal evaluation only."
)
CROP_S = 2.5  # the paper discards the first and last 2.5 s of each recording


def _build_one(job: dict) -> None:
    src, out, tid = Path(job["src"]), Path(job["out"]), job["texture"]
    model = read_model(src / "models" / f"{tid}.xml", src / "taps" / f"{tid}.xml", name=tid)
    tdir = out / "textures" / tid
    tdir.mkdir(parents=True, exist_ok=True)
    model.save(tdir / "vibration.npz")
    rng = texture_rng(job["seed"], tid)
    for k in range(job["recordings"]):
        save_recording(tdir / f"recording_{k:03d}.npz", simulated_recording(model, job["duration_s"], rng))


def build_hatt(
    src: str | Path,
    out: str | Path,
    *,
    seed: int = 0,
    duration_s: float = 60.0,
    recordings: int = 1,
    limit: int | None = None,
    textures: Iterable[str] | None = None,
    workers: int | None = None,
) -> Path:
    """Build the dataset; `textures` keeps only those ids (in textures.csv order), `limit` the first N
    of what is left (for quick trials)."""
    src = Path(src).resolve()
    for needed in ("textures.csv", "ratings.csv", "models", "taps", "images"):
        if not (src / needed).exists():
            raise ValueError(f"{src} does not look like hatt-texnet: missing {needed}")
    with open(src / "textures.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    if textures is not None:
        wanted = set(textures)
        unknown = sorted(wanted - {r["texture"] for r in rows})
        if unknown:
            raise ValueError(f"{src / 'textures.csv'}: no texture(s) {unknown}")
        rows = [r for r in rows if r["texture"] in wanted]
    if limit is not None:
        rows = rows[:limit]
    ratings = {
        t: [RatingRow(t, rater, pres, attr, value) for attr, values in by_attr.items() for rater, pres, value in values]
        for t, by_attr in read_texnet_ratings(src / "ratings.csv").items()
    }
    writer = DatasetWriter(
        out,
        name="hatt-texnet",
        source="hatt-texnet",
        licence=LICENCE,
        provenance=(
            f"built from {src}; tactile streams rendered from HaTT vibration models along seeded freehand trajectories"
        ),
        build={"seed": seed, "duration_s": duration_s, "recordings": recordings, "crop_s": CROP_S, "src": str(src)},
    )
    jobs = [
        {
            "src": str(src),
            "out": str(writer.root),
            "texture": r["texture"],
            "seed": seed,
            "duration_s": duration_s,
            "recordings": recordings,
        }
        for r in rows
    ]
    for _ in run_jobs(_build_one, jobs, workers, "rendering HaTT textures"):
        pass
    for r in rows:
        tid = r["texture"]
        meta = TextureMeta(
            images=[str(src / "images" / f"{tid}.png")],
            recordings=[f"recording_{k:03d}.npz" for k in range(recordings)],
            vibration_model="vibration.npz",
        )
        status = r["ratings"] if r["ratings"] in ("yes", "withheld", "no") else "no"
        writer.add_texture(
            TextureInfo(tid, r["name"], r["group"] or "unknown", status),
            meta,
            ratings.get(tid, []) if status == "yes" else [],
        )
    return writer.close()
