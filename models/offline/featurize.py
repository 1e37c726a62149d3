"""Compute and cache a dataset's features: tactile windows per recording, visual vectors per image view.

Caches live in DIR/features/ and are keyed by the feature configuration's hash
and a fingerprint of the dataset header, so a changed config or a rebuilt
dataset never reuses stale features.
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from models.offline.datasets.format import Dataset
from models.offline.jobs import run_jobs
from models.tactile.config import TactileConfig
from models.tactile.features import recording_features
from models.tactile.taps import tap_features
from models.visual.config import VisualConfig
from texture_library.atomic_file import atomic_path

if TYPE_CHECKING:
    from models.visual.embedding import PatchEmbedder
    from models.visual.onnx_backbone import OnnxBackbone

DEFAULT_VIEWS = 8  # augmented views per image (view 0 is the original)
#: the int8 EfficientNet-Lite0 (models.offline.backbones.quantize)
INT8_BACKBONE = "efficientnet_lite0_int8"
#: the image configuration the served models read: the one the speed–accuracy frontier's fixed rule picks
#: (2×2 patches at native size, no GLCM: reports/tradeoffs; the int8 backbone: reports/tradeoffs/frontier-quant.json,
#: picked on inner CV with `selected`, inside the folds), so a frame costs the int8 backbone on 4 patches
SERVED_VISUAL = VisualConfig(grid=2, glcm=False, backbone=INT8_BACKBONE)


def cache_root() -> Path:
    """Where derived artefacts shared across datasets live (backbone ONNX, per-view features)."""
    return Path(os.environ.get("HAPTICLINK_CACHE", "cache"))


@dataclass(frozen=True)
class TactileTable:
    """Per-window tactile features of a dataset.

    X: (n_windows, n_features) float32; texture: (n_windows,) index into `textures`;
    recording: (n_windows,) recording index within its texture; t_start: (n_windows,) s.
    """

    X: np.ndarray
    texture: np.ndarray
    recording: np.ndarray
    t_start: np.ndarray
    textures: list[str]
    config: TactileConfig


@dataclass(frozen=True)
class VisualTable:
    """Visual feature vectors: X (n_textures, n_views, dim) float32, in `textures` order; fingerprint: the weights
    fingerprint of the backbone that computed them (an int8 copy's names its recipe; a fallback's is its fp32
    source's), so a report records which numerics its features came from."""

    X: np.ndarray
    textures: list[str]
    backbone: str
    backbone_dim: int
    config_hash: str
    fingerprint: str


def dataset_fingerprint(ds: Dataset) -> str:
    """Changes whenever the dataset is rebuilt differently (header content)."""
    return hashlib.sha256(json.dumps(ds.header, sort_keys=True).encode()).hexdigest()[:12]


def _crop_s(ds: Dataset) -> float:
    return float(ds.header.get("build", {}).get("crop_s", 0.0))


def texture_tap_features(ds: Dataset, texture: str) -> np.ndarray:
    """(3,) tap features of a texture's recorded taps (models.tactile.taps); ValueError if it has none."""
    taps = ds.taps(texture)
    if taps is None:
        raise ValueError(
            f"texture {texture!r} has no tap transients (its vibration.npz holds none); "
            "use a feature configuration without the taps group"
        )
    try:
        return tap_features(taps.speeds, taps.accel)
    except ValueError as exc:
        raise ValueError(f"texture {texture!r}: {exc}") from None


def _tactile_job(job: dict) -> list[tuple[np.ndarray, np.ndarray]]:
    ds = Dataset(job["root"])
    cfg = TactileConfig(**job["config"])
    out = []
    crop = job["crop_s"]
    names = ds.meta(job["texture"]).recordings
    taps = texture_tap_features(ds, job["texture"]) if "taps" in cfg.extra_groups else None
    for name, rec in zip(names, ds.recordings(job["texture"])):
        try:
            feats, t0 = recording_features(rec, cfg, skip_s=crop, stop_s=rec.duration_s - crop, taps=taps)
        except ValueError as exc:
            raise ValueError(f"texture {job['texture']!r}, {name} (crop_s={crop:g} s at both ends): {exc}") from None
        out.append((feats, t0))
    return out


def tactile_table(root: str | Path, config: TactileConfig | None = None, *, workers: int | None = None) -> TactileTable:
    """Tactile features of every texture's recordings (cached); ValueError for an image-only dataset."""
    ds = Dataset(root)
    if not ds.has_recordings:
        raise ValueError(f"{ds.root}: dataset {ds.name!r} is image-only (no recordings): it has no tactile features")
    cfg = config or TactileConfig()
    textures = ds.texture_ids()
    cache = ds.features_dir / f"tactile-{cfg.hash()}-{dataset_fingerprint(ds)}.npz"
    if cache.is_file():
        with np.load(cache, allow_pickle=False) as z:
            if list(z["textures"]) == textures:
                return TactileTable(z["X"], z["texture"], z["recording"], z["t_start"], textures, cfg)
    jobs = [{"root": str(ds.root), "texture": t, "config": cfg.to_dict(), "crop_s": _crop_s(ds)} for t in textures]
    X, tex, rec, ts = [], [], [], []
    for i, per_recording in enumerate(run_jobs(_tactile_job, jobs, workers, "tactile features")):
        for k, (feats, t0) in enumerate(per_recording):
            X.append(feats)
            tex.append(np.full(len(feats), i))
            rec.append(np.full(len(feats), k))
            ts.append(t0)
    table = TactileTable(
        np.concatenate(X).astype(np.float32),
        np.concatenate(tex),
        np.concatenate(rec),
        np.concatenate(ts),
        textures,
        cfg,
    )
    with atomic_path(cache) as tmp:
        np.savez(
            tmp,
            X=table.X,
            texture=table.texture,
            recording=table.recording,
            t_start=table.t_start,
            textures=np.array(textures),
            config=np.array(json.dumps(cfg.to_dict())),
        )
    return table


# Backbone files carry their load-time probe since this tag (onnx_backbone.PROBE_KEY): a cached file from before
# has another name, so it is exported again rather than served unchecked. The weights are the same.
FILE_TAG = "-probed"


def backbone_onnx(config: VisualConfig) -> Path:
    """The resolved backbone exported to ONNX once (keyed by its weights and the visual config).

    Bulk extraction runs through onnxruntime, several times faster than torch on CPU, and
    the service runs the very same file.
    """
    from models.offline.backbones.cnn import resolve_backbone
    from models.offline.backbones.onnx_export import export_backbone_onnx

    if config.backbone == INT8_BACKBONE:
        return int8_backbone_onnx(config)
    backbone = resolve_backbone(config)
    path = cache_root() / "backbones" / f"{backbone.name}-{backbone.fingerprint[:12]}-{config.hash()}{FILE_TAG}.onnx"
    if not path.is_file():
        with atomic_path(path) as tmp:
            export_backbone_onnx(backbone, tmp, config_hash=config.hash())
    return path


def int8_backbone_onnx(config: VisualConfig, kind: str | None = None, fp32_convs: int | None = None) -> Path:
    """The int8 copy of the EfficientNet-Lite0 file for `config`, quantized once from it (deterministic: same
    fp32 file and recipe, same bytes); its name holds the int8 fingerprint, so a changed recipe is a new file.
    kind: one of quantize.RECIPES, fp32_convs: leading convolutions kept fp32 (defaults: the served recipe,
    quantize.DEFAULT_RECIPE and quantize.FP32_CONVS)."""
    from models.offline.backbones.quantize import DEFAULT_RECIPE, FP32_CONVS, int8_fingerprint, quantize_backbone_onnx
    from models.visual.onnx_backbone import OnnxBackbone

    kind = kind or DEFAULT_RECIPE
    fp32_convs = FP32_CONVS if fp32_convs is None else fp32_convs
    fp32_path = backbone_onnx(config.model_copy(update={"backbone": "efficientnet_lite0"}))
    fingerprint = int8_fingerprint(OnnxBackbone(fp32_path, min_probe_cosine=None).fingerprint, kind, fp32_convs)
    path = cache_root() / "backbones" / f"{INT8_BACKBONE}-{fingerprint[:12]}-{config.hash()}{FILE_TAG}.onnx"
    if not path.is_file():
        with atomic_path(path) as tmp:
            quantize_backbone_onnx(fp32_path, tmp, kind=kind, fp32_convs=fp32_convs)
    return path


def checked_backbone(config: VisualConfig, intra_op_threads: int | None = None) -> tuple[OnnxBackbone, str]:
    """(the backbone to compute with, the name of the one exported for `config`): that one after its load-time
    check; where an int8 copy fails it on this CPU (onnxruntime's u8s8 kernels saturate without VNNI), its fp32
    source, as the service serves, with a warning. Features then cache under the fp32 backbone's name and
    fingerprint (what was computed), while a model card names the configured backbone, which the service then
    serves, or its fp32 source where it fails there too."""
    from models.visual.onnx_backbone import OnnxBackbone

    backbone = OnnxBackbone(
        backbone_onnx(config), intra_op_threads=intra_op_threads, expected_config_hash=config.hash()
    )
    if backbone.check is None or backbone.check.passed or backbone.source is None:
        return backbone, backbone.name
    fp32 = OnnxBackbone(
        backbone_onnx(config.model_copy(update={"backbone": backbone.source[0]})),
        intra_op_threads=intra_op_threads,
        expected_config_hash=config.hash(),
    )
    warnings.warn(
        f"{backbone.name} fails its load-time check on this CPU ({backbone.check.describe()}): computing "
        f"{fp32.name} features instead, as the service would serve here",
        stacklevel=2,
    )
    return fp32, backbone.name


def visual_table(
    root: str | Path,
    config: VisualConfig | None = None,
    *,
    n_views: int = DEFAULT_VIEWS,
    seed: int = 0,
    backbone: PatchEmbedder | None = None,
) -> VisualTable:
    """Visual features of every texture's first image, n_views augmented views each (cached).

    backbone: an embedder to use instead of the one exported for `config` (a sweep over
    patching configurations runs one ONNX file for all of them; the cache keys name both)."""
    from models.visual.cache import FeatureCache
    from models.visual.embedding import batch_visual_features

    ds = Dataset(root)
    cfg = config or VisualConfig()
    textures = ds.texture_ids()
    configured = None
    if backbone is None:
        backbone, configured = checked_backbone(cfg)
    cache = ds.features_dir / (
        f"visual-{backbone.name}-{backbone.fingerprint[:12]}-{cfg.hash()}-v{n_views}-s{seed}-{dataset_fingerprint(ds)}.npz"
    )
    if cache.is_file():
        with np.load(cache, allow_pickle=False) as z:
            if list(z["textures"]) == textures:
                return VisualTable(
                    z["X"], textures, configured or backbone.name, backbone.dim, cfg.hash(), backbone.fingerprint
                )
    images = []
    for t in textures:
        paths = ds.image_paths(t)
        if not paths:
            raise ValueError(f"texture {t!r} has no image")
        images.append(paths[0])
    feats = batch_visual_features(
        images, cfg, backbone, n_views=n_views, seed=seed, cache=FeatureCache(cache_root() / "visual"), progress=True
    )
    table = VisualTable(
        feats.values, textures, configured or feats.backbone, feats.backbone_dim, cfg.hash(), backbone.fingerprint
    )
    with atomic_path(cache) as tmp:
        np.savez(tmp, X=table.X, textures=np.array(textures))
    return table


def featurize_dataset(
    root: str | Path,
    *,
    workers: int | None = None,
    visual: bool = True,
    tactile_config: TactileConfig | None = None,
    visual_config: VisualConfig | None = None,
) -> str:
    """Fill the feature caches of a dataset (tactile: the given configuration, default the paper's; none for an
    image-only dataset; visual: the given configuration, default VisualConfig()); returns a one-line summary."""
    if Dataset(root).has_recordings:
        t = tactile_table(root, tactile_config, workers=workers)
        summary = f"tactile {t.X.shape[0]} windows × {t.X.shape[1]} features over {len(t.textures)} textures"
    else:
        summary = "image-only: no tactile features"
    if visual:
        v = visual_table(root, visual_config)
        summary += f"; visual {v.X.shape[0]} textures × {v.X.shape[1]} views × {v.X.shape[2]} ({v.backbone})"
    return summary
