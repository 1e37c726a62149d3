"""An image's visual feature vector: backbone features averaged over its patches ⊕ its GLCM ⊕ descriptors.

Torch-free: works with any embedder that has `name`, `dim`, `fingerprint` and
`embed()` — the torch `Backbone` in training, `OnnxBackbone` in the service.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from tqdm.auto import tqdm

from models.visual.augment import IDENTITY_VIEW, apply_view, view_params
from models.visual.cache import FeatureCache, cache_key
from models.visual.config import VisualConfig
from models.visual.descriptors import descriptor_vector, zoom_to
from models.visual.glcm import glcm_features
from models.visual.image import ImageSource, check_gray, load_colour, load_image, resize_shorter
from models.visual.patches import extract_patches

PROGRESS_THRESHOLD = 8  # views; below this a progress bar is noise
# Named column sets of the visual vector: "both" is every column (backbone ⊕ GLCM ⊕ any descriptors);
# "classic" every hand-made one (GLCM and the descriptors); "descriptors" only the descriptors.
VisualPart = Literal["both", "backbone", "glcm", "descriptors", "classic"]
VISUAL_PARTS: tuple[str, ...] = ("both", "backbone", "glcm", "descriptors", "classic")


def visual_layout(backbone_dim: int, config: VisualConfig) -> dict[str, slice]:
    """Column blocks of a visual vector: backbone, glcm (when on), then each descriptor `config` turns on."""
    layout = {"backbone": slice(0, backbone_dim)}
    if config.glcm:
        layout["glcm"] = slice(backbone_dim, backbone_dim + config.glcm_dim)
    start = backbone_dim + config.glcm_dim
    for name, width in config.descriptor_dims.items():
        layout[name] = slice(start, start + width)
        start += width
    return layout


def part_columns(layout: dict[str, slice], part: str) -> tuple[np.ndarray, dict[str, list[int]]]:
    """The columns of a named visual part (VISUAL_PARTS) and the blocks they hold, renumbered from 0:
    (column indices, block name → [start, stop)). Training and the service both cut a vector with it."""
    names = {
        "both": list(layout),
        "backbone": ["backbone"],
        "glcm": [n for n in layout if n == "glcm"],
        "descriptors": [n for n in layout if n not in ("backbone", "glcm")],
        "classic": [n for n in layout if n != "backbone"],
    }
    if part not in names:
        raise ValueError(f"visual part must be one of {list(VISUAL_PARTS)}, got {part!r}")
    if not names[part]:
        raise ValueError(f"visual part {part!r} is empty: the visual configuration computes none of its columns")
    cols, blocks, start = [], {}, 0
    for n in names[part]:
        sl = layout[n]
        cols.append(np.arange(sl.start, sl.stop))
        blocks[n] = [start, start + sl.stop - sl.start]
        start += sl.stop - sl.start
    return np.concatenate(cols), blocks


class PatchEmbedder(Protocol):
    """What `visual_features` needs of a backbone."""

    name: str
    dim: int
    fingerprint: str

    def embed(self, patches: np.ndarray) -> np.ndarray:
        """(n, 224, 224) float in [0, 1] → (n, dim) float32."""
        ...


@dataclass(frozen=True)
class VisualFeatures:
    """Feature arrays with what produced them.

    values               (..., backbone_dim + glcm_dim + descriptor_dim) float32: the backbone features,
                         then the flattened GLCM, then the texture descriptors (visual_layout)
    backbone             backbone name ("resnet50" | "efficientnet_lite0" | "efficientnet_lite0_int8")
    backbone_dim         2048 (resnet50) | 1280 (EfficientNet-Lite0 head) | 640 (its last block)
    glcm_dim             levels² (256), or 0 without GLCM (the served configuration)
    config_hash          VisualConfig.hash()
    weights_fingerprint  the backbone weights' fingerprint
    views                view parameters along the views axis, if there is one
    """

    values: np.ndarray
    backbone: str
    backbone_dim: int
    glcm_dim: int
    config_hash: str
    weights_fingerprint: str
    views: tuple[Mapping[str, Any], ...] = field(default=())
    descriptor_dim: int = 0

    def __post_init__(self) -> None:
        if self.values.shape[-1] != self.dim:
            raise ValueError(
                f"values last axis is {self.values.shape[-1]}, expected backbone_dim + glcm_dim + descriptor_dim = "
                f"{self.dim}"
            )

    @property
    def dim(self) -> int:
        """Total feature length."""
        return self.backbone_dim + self.glcm_dim + self.descriptor_dim

    @property
    def backbone_part(self) -> np.ndarray:
        """(..., backbone_dim) view of the backbone features."""
        return self.values[..., : self.backbone_dim]

    @property
    def glcm_part(self) -> np.ndarray:
        """(..., glcm_dim) view of the GLCM features."""
        return self.values[..., self.backbone_dim : self.backbone_dim + self.glcm_dim]

    def metadata(self) -> dict[str, str]:
        """String metadata to store beside the arrays (and in model files)."""
        return {
            "visual.backbone": self.backbone,
            "visual.backbone_dim": str(self.backbone_dim),
            "visual.glcm_dim": str(self.glcm_dim),
            "visual.dim": str(self.dim),
            "visual.config_hash": self.config_hash,
            "visual.weights_fingerprint": self.weights_fingerprint,
            **({"visual.descriptor_dim": str(self.descriptor_dim)} if self.descriptor_dim else {}),
        }


def visual_features(
    img: np.ndarray,
    config: VisualConfig,
    backbone: PatchEmbedder,
    cache: FeatureCache | None = None,
    view: Mapping[str, Any] | None = None,
    colour: np.ndarray | None = None,
) -> np.ndarray:
    """Feature vector of one view of one image.

    img      (H, W) float in [0, 1], H, W ≥ config.patch_size — the original image;
             `view` (default: identity) is applied here so the cache key names the original
    colour   (H, W, 3) float in [0, 1], the same frame in colour (image.load_colour); needed only when
             config.descriptors holds "colour"
    returns  (backbone.dim + config.glcm_dim + config.descriptor_dim,) float32: mean over the grid² patches
             of the backbone features, the flattened GLCM of the view, then the descriptors
             (models.visual.descriptors) of the view; with config.resize set, the image is first scaled to
             that shorter side (image.resize_shorter)
    """
    check_gray(img, config.patch_size)
    if config.needs_colour:
        if colour is None:
            raise ValueError("this visual configuration's colour descriptor needs the frame in colour (colour=…)")
        if colour.shape != (*img.shape, 3):
            raise ValueError(f"colour must be {(*img.shape, 3)} to match the gray frame, got {colour.shape}")
    params = dict(IDENTITY_VIEW if view is None else view)
    base = config.without_descriptors() if config.descriptors else config
    views: list[np.ndarray] = []  # the view, made at most once for both parts

    def seen_view() -> np.ndarray:
        if not views:
            views.append(apply_view(img if config.resize is None else resize_shorter(img, config.resize), params))
        return views[0]

    values = _backbone_glcm(img, base, backbone, cache, params, seen_view)
    if not config.descriptors:
        return values
    # Cached apart from the backbone part, keyed by the full configuration: turning descriptors on
    # reuses every cached backbone vector. Keyed by the colour frame when a descriptor reads colour: two photos of
    # one grey can differ in colour (and the grey is the colour frame's luma, so nothing else is lost).
    key = None
    if cache is not None:
        frame = colour if colour is not None and config.needs_colour else img  # checked above: needs_colour → colour
        key = cache_key(frame, params, config.hash(), "descriptors", "")
        hit = cache.get(key)
        if hit is not None and hit.shape == (config.descriptor_dim,):
            return np.concatenate([values, hit.astype(np.float32, copy=False)])
    seen = seen_view()
    seen_colour = None
    if colour is not None and config.needs_colour:  # checked above: needs_colour → colour was given
        size = min(config.descriptor_size, *img.shape)  # colour statistics are global: a small copy suffices
        seen_colour = np.stack(
            [apply_view(zoom_to(colour[..., c], size).astype(np.float32), params) for c in range(3)], axis=2
        )
    desc = descriptor_vector(seen, seen_colour, config)
    if cache is not None and key is not None:
        cache.put(key, desc)
    return np.concatenate([values, desc])


def _backbone_glcm(
    img: np.ndarray, config: VisualConfig, backbone: PatchEmbedder, cache: FeatureCache | None, params: dict, seen_view
) -> np.ndarray:
    """Backbone mean over patches ⊕ GLCM of one view (config without descriptors); seen_view() makes the view."""
    key = None
    if cache is not None:
        key = cache_key(img, params, config.hash(), backbone.name, backbone.fingerprint)
        hit = cache.get(key)
        if hit is not None and hit.shape == (backbone.dim + config.glcm_dim,):
            return hit.astype(np.float32, copy=False)
    seen = seen_view()
    patches = extract_patches(seen, config.patch_size, config.grid)
    embedded = backbone.embed(patches)
    if embedded.shape != (patches.shape[0], backbone.dim):
        raise ValueError(
            f"backbone {backbone.name!r} returned {embedded.shape}, expected ({patches.shape[0]}, {backbone.dim})"
        )
    values = embedded.mean(axis=0, dtype=np.float64).astype(np.float32)
    if config.glcm:
        texture = glcm_features(seen, config.glcm_levels, config.glcm_distances, config.glcm_angles_deg)
        values = np.concatenate([values, texture])
    if cache is not None and key is not None:
        cache.put(key, values)
    return values


def batch_visual_features(
    images: Sequence[ImageSource],
    config: VisualConfig,
    backbone: PatchEmbedder,
    *,
    n_views: int = 1,
    seed: int = 0,
    cache: FeatureCache | None = None,
    progress: bool | None = None,
) -> VisualFeatures:
    """Features of `n_views` views (`augment.view_params(n_views, seed)`) of every image.

    images    paths, bytes, PIL images or arrays (see image.load_image)
    progress  show a tqdm bar; None: only when there are ≥ PROGRESS_THRESHOLD views in all
    returns   VisualFeatures with values (len(images), n_views, backbone.dim + config.glcm_dim + config.descriptor_dim)
    """
    views = view_params(n_views, seed)
    total = len(images) * n_views
    show = total >= PROGRESS_THRESHOLD if progress is None else progress
    values = np.empty((len(images), n_views, backbone.dim + config.glcm_dim + config.descriptor_dim), dtype=np.float32)
    with tqdm(total=total, desc=f"visual features ({backbone.name})", unit="view", disable=not show) as bar:
        for i, source in enumerate(images):
            img = load_image(source, min_size=config.patch_size)
            colour = load_colour(source, min_size=config.patch_size) if config.needs_colour else None
            for j, params in enumerate(views):
                values[i, j] = visual_features(img, config, backbone, cache, params, colour)
                bar.update(1)
    return VisualFeatures(
        values=values,
        backbone=backbone.name,
        backbone_dim=backbone.dim,
        glcm_dim=config.glcm_dim,
        config_hash=config.hash(),
        weights_fingerprint=backbone.fingerprint,
        views=tuple(views),
        descriptor_dim=config.descriptor_dim,
    )
