"""What the studies share: the reference data, image views per model, strict JSON."""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from models.offline.evaluation.data import TextureData, load_texture_data
from models.offline.evaluation.estimator_registry import CLASSICAL, POOLED_BASES, POOLED_MEANS
from models.offline.featurize import DEFAULT_VIEWS, visual_table
from models.visual.config import VisualConfig
from models.visual.embedding import VisualPart, part_columns, visual_layout
from texture_library.atomic_file import write_text

POOLING_MODELS = (*POOLED_BASES, *POOLED_MEANS, "selected")  # classical models that pool a texture's views


def views_for(model: str) -> int:
    """Image views a model trains on: the networks and the *-views SVRs pair windows with augmented
    views, the *-pooled models and `selected` pool them (8, as in their LOOCV); the other classical
    models read view 0 only, so 1 saves embedding. At test time every model sees one frame."""
    base = model.removeprefix("shuffled-")
    single = base in CLASSICAL and not base.endswith("-views") and base not in POOLING_MODELS
    return 1 if single else DEFAULT_VIEWS


def with_visual(
    data: TextureData, root: str | Path, config: VisualConfig, *, n_views: int, part: VisualPart = "both", backbone=None
) -> TextureData:
    """`data` (loaded without visual features) with the visual features of `config` attached."""
    table = visual_table(root, config, n_views=n_views, backbone=backbone)
    index = {t: i for i, t in enumerate(table.textures)}
    cols, _ = part_columns(visual_layout(table.backbone_dim, config), part)
    vis = table.X[[index[t] for t in data.textures]][:, :, cols]
    meta = {
        **data.meta,
        "backbone": table.backbone,
        "backbone_dim": table.backbone_dim,
        "backbone_fingerprint": table.fingerprint,
        "visual_hash": config.hash(),
        "visual_config": config.computation(),
        "visual_part": part,
    }
    return replace(data, visual=vis, meta=meta)


def tactile_data(root: str | Path, workers: int | None = 1) -> TextureData:
    """The rated textures with their tactile windows (all of them) and mean ratings, no visual features."""
    return load_texture_data(root, visual=False, workers=workers)


def load_state() -> dict:
    """Machine load now: studies run on a shared machine, and say so."""
    return {"loadavg_1_5_15": [round(x, 2) for x in os.getloadavg()], "cpu_count": os.cpu_count()}


def write_json(path: Path, payload: dict) -> Path:
    return write_text(path, json.dumps(payload, indent=1, default=_plain, allow_nan=False) + "\n")  # strict JSON


def _plain(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} as JSON")
