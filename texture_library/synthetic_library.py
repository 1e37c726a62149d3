"""The demo's default library: textures of the synthetic world (HaTT's data cannot be shipped)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

from texture_library.library import Library, add_entry
from texture_library.procedural import make_world


def build_synthetic_library(out: str | Path, *, n_textures: int = 24, seed: int = 0, image_size: int = 448) -> Library:
    """A library of the synthetic world's textures, rated by their ground truth (the documented mapping)."""
    root = Path(out)
    (root / "images").mkdir(parents=True, exist_ok=True)
    entries = []
    for tex in make_world(n_textures, seed, image_size=image_size):
        buf = io.BytesIO()
        Image.fromarray(tex.image).save(buf, format="PNG")
        (root / "images" / f"{tex.texture_id}.png").write_bytes(buf.getvalue())
        entries.append(
            add_entry(
                root,
                tex.texture_id,
                tex.model,
                name=tex.texture_id.replace("_", " "),
                group=tex.group,
                ratings=np.round(tex.truth, 2),
                ratings_source="ground-truth",
                provenance="hapticlink synthetic world (procedural)",
                licence="Apache-2.0 (generated)",
                spread=np.std(tex.ratings, axis=0),
                image_path=f"images/{tex.texture_id}.png",
            )
        )
    lib = Library(root, f"synthetic-{n_textures}-s{seed}", entries)
    lib.save()
    return lib
