"""Everything a model sees of a dataset, per texture: tactile windows, image views, mean ratings."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from models.offline.datasets.format import Dataset
from models.offline.featurize import tactile_table
from models.tactile.config import TactileConfig
from models.visual.config import VisualConfig
from models.visual.embedding import part_columns, visual_layout

#: meta entries with one row per texture (the synthetic world's true ratings): `take` keeps the rows of the textures
#: it takes, and a texture stripped of its ratings (`with_targets(None)`) loses them too
PER_TEXTURE_META = ("true_ratings",)


@dataclass(frozen=True)
class TextureData:
    """Per-texture inputs and targets.

    tactile: list of (n_i, F) float32 window features, one entry per texture;
    visual: (T, V, D) float32 image-view features or None; targets: (T, 4) mean bipolar ratings or None.
    """

    textures: list[str]
    groups: list[str]
    tactile: list[np.ndarray]
    visual: np.ndarray | None
    targets: np.ndarray | None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        t = len(self.textures)
        if len(self.groups) != t or len(self.tactile) != t:
            raise ValueError("textures, groups and tactile must have one entry per texture")
        if self.visual is not None and self.visual.shape[0] != t:
            raise ValueError(f"visual has {self.visual.shape[0]} textures, expected {t}")
        if self.targets is not None and self.targets.shape != (t, 4):
            raise ValueError(f"targets must be ({t}, 4), got {self.targets.shape}")

    @property
    def has_tactile(self) -> bool:
        """False for an image-only dataset (its textures have no windows)."""
        return not self.meta.get("image_only", False)

    def __len__(self) -> int:
        return len(self.textures)

    def take(self, idx) -> TextureData:
        idx = np.atleast_1d(np.asarray(idx))
        return replace(
            self,
            textures=[self.textures[i] for i in idx],
            groups=[self.groups[i] for i in idx],
            tactile=[self.tactile[i] for i in idx],
            visual=None if self.visual is None else self.visual[idx],
            targets=None if self.targets is None else self.targets[idx],
            meta={k: np.asarray(v)[idx] if k in PER_TEXTURE_META else v for k, v in self.meta.items()},
        )

    def with_targets(self, targets: np.ndarray | None) -> TextureData:
        if targets is None:
            meta = {k: v for k, v in self.meta.items() if k not in PER_TEXTURE_META}
            return replace(self, targets=None, meta=meta)
        return replace(self, targets=np.asarray(targets, np.float32))


def load_texture_data(
    root: str | Path,
    *,
    tactile_config: TactileConfig | None = None,
    visual: bool = True,
    visual_part: str = "both",
    rated: str | None = "yes",
    workers: int | None = None,
    visual_config: VisualConfig | None = None,
) -> TextureData:
    """Assemble TextureData for the textures whose `rated` status matches (None: all).

    An image-only dataset gives every texture an empty (0, 0) window array and meta["image_only"] = True;
    meta["visual_blocks"] names the column block of each visual feature group (backbone, glcm, descriptors)."""
    ds = Dataset(root)
    infos = [t for t in ds.textures() if rated is None or t.rated == rated]
    if not infos:
        raise ValueError(f"{root}: no textures with rated={rated!r}")
    meta: dict = {"dataset": ds.name}
    if ds.has_recordings:
        tt = tactile_table(root, tactile_config, workers=workers)
        index = {t: i for i, t in enumerate(tt.textures)}
        tactile = [tt.X[tt.texture == index[t.texture]] for t in infos]
        meta.update(tactile_config=tt.config.to_dict(), tactile_hash=tt.config.hash())
    else:
        tactile = [np.zeros((0, 0), np.float32) for _ in infos]
        meta["image_only"] = True
    vis = None
    if visual:
        from models.offline.featurize import visual_table

        vcfg = visual_config or VisualConfig()
        vt = visual_table(root, vcfg)
        vindex = {t: i for i, t in enumerate(vt.textures)}
        cols, blocks = part_columns(visual_layout(vt.backbone_dim, vcfg), visual_part)
        vis = vt.X[[vindex[t.texture] for t in infos]][:, :, cols]
        meta.update(
            backbone=vt.backbone,
            backbone_dim=vt.backbone_dim,
            backbone_fingerprint=vt.fingerprint,
            visual_hash=vt.config_hash,
            visual_config=vcfg.computation(),
            visual_part=visual_part,
            visual_blocks=blocks,
        )
    targets = None
    if rated == "yes":
        means = ds.mean_ratings()
        targets = np.array([means[t.texture] for t in infos], np.float32)
        # the synthetic world knows the noise-free ratings its raters were drawn around
        truth = [ds.meta(t.texture).extra.get("true_ratings") for t in infos]
        if all(x is not None for x in truth):
            meta["true_ratings"] = np.array(truth, np.float32)
    return TextureData([t.texture for t in infos], [t.group for t in infos], tactile, vis, targets, meta)
