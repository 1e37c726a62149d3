"""Faulted test inputs, computed once per texture and reused by every model and fold.

A fault acts on the held-out texture only, at test time, through the one feature
implementation: the touch segment (or the re-rendered stroke) goes through
`recording_features`, the faulted image through `visual_features`. Nothing here depends on a
model, so each texture's variants are computed once (and cached under the work folder; faulted
image embeddings also land in the content-addressed visual cache).

Touch: a 10.5 s segment of the texture's recording from 2.0 s (the first 0.5 s settles the
filters, so windows start at 2.5 s like the dataset's), up to SEGMENT_WINDOWS windows of 0.5 s.
Camera: the texture's photo (view 0). Augmentation variants (noise at SNRs and blur at sigmas
between the studied ones) are computed the same way; only training textures' ever reach a fit.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.offline.datasets.format import Dataset
from models.offline.datasets.simulate import simulated_recording, texture_rng
from models.offline.faults.catalog import FAULTS, TRAJECTORY_FAULTS, apply_camera, apply_touch, trajectory_transform
from models.offline.featurize import dataset_fingerprint
from models.offline.jobs import run_jobs
from models.tactile.config import TactileConfig
from models.tactile.features import recording_features
from models.visual.config import VisualConfig
from texture_library.atomic_file import atomic_path

SEGMENT_START_S = 2.0
SETTLE_S = 0.5
SEGMENT_WINDOWS = 20
CLEAN = "clean"
AUG_NOISE_SNR_DB = (35.0, 25.0, 15.0, 5.0)
AUG_BLUR_SIGMA_PX = (1.0, 3.0, 6.0)


def variant(name: str, strength: float) -> str:
    return f"{name}@{strength:g}"


def touch_variants() -> list[tuple[str, str, float]]:
    """(key, fault, strength) of every studied touch fault, then the augmentation variants."""
    out = [(variant(f.name, s), f.name, s) for f in FAULTS.values() if f.family == "touch" for s in f.strengths]
    return out + [(variant("aug_noise", s), "noise", s) for s in AUG_NOISE_SNR_DB]


def camera_variants() -> list[tuple[str, str, float]]:
    out = [
        (variant(f.name, s), f.name, s)
        for f in FAULTS.values()
        if f.family == "camera" and f.name != "no_frame"
        for s in f.strengths
    ]
    return out + [(variant("aug_blur", s), "blur", s) for s in AUG_BLUR_SIGMA_PX]


def _rng(seed: int, texture: str, key: str) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(texture.encode()), zlib.crc32(key.encode())])


def _segment_features(rec, config: TactileConfig) -> np.ndarray:
    span = SETTLE_S + (SEGMENT_WINDOWS - 1) * config.hop_s + config.window_s
    feats, _ = recording_features(rec, config, skip_s=SETTLE_S, stop_s=min(span, rec.duration_s))
    return feats[:SEGMENT_WINDOWS]


def _tactile_job(job: dict) -> dict[str, np.ndarray]:
    from texture_library.vibration import VibrationModel

    ds = Dataset(job["root"])
    texture, cfg = job["texture"], TactileConfig(**job["config"])
    rec = ds.recordings(texture)[0]
    span = SETTLE_S + (SEGMENT_WINDOWS - 1) * cfg.hop_s + cfg.window_s
    segment = rec.crop(SEGMENT_START_S, SEGMENT_START_S + span)
    out = {CLEAN: _segment_features(segment, cfg)}
    build = ds.header.get("build", {})
    model = None
    for key, name, strength in touch_variants():
        if name in TRAJECTORY_FAULTS:
            if model is None:
                model = VibrationModel.load(ds.vibration_model_path(texture))
            # the dataset's own stroke (same generator), along the scaled trajectory, same segment
            full = simulated_recording(
                model,
                float(build["duration_s"]),
                texture_rng(int(build["seed"]), texture),
                transform=trajectory_transform(name, strength),
            )
            faulted = full.crop(SEGMENT_START_S, SEGMENT_START_S + span)
        else:
            faulted = apply_touch(name, strength, segment, _rng(job["seed"], texture, key))
        try:
            out[key] = _segment_features(faulted, cfg)
        except ValueError:  # the fault left no complete window
            out[key] = np.zeros((0, cfg.n_features), np.float32)
    return out


def _visual_job(job: dict) -> tuple[np.ndarray, np.ndarray]:
    from models.inference.ood import frame_statistics
    from models.offline.featurize import cache_root, checked_backbone
    from models.visual.cache import FeatureCache
    from models.visual.embedding import visual_features
    from models.visual.image import load_image

    cfg = VisualConfig(**job["config"])
    backbone, _ = checked_backbone(cfg, intra_op_threads=1)
    cache = FeatureCache(cache_root() / "visual")
    img = load_image(job["image"], min_size=cfg.patch_size)
    keys = [(CLEAN, None, None), *camera_variants()]
    vecs, frames = [], []
    for key, name, strength in keys:
        seen = img if name is None else apply_camera(name, strength, img, _rng(job["seed"], job["texture"], key))
        vecs.append(visual_features(seen, cfg, backbone, cache))
        frames.append(frame_statistics(seen))
    return np.stack(vecs), np.stack(frames)


@dataclass(frozen=True)
class FaultedInputs:
    """tactile[variant][i]: (n, F) windows of texture i; visual: (T, n_variants, D); frames: (T, n_variants, 5);
    visual_keys: the variants along visual's axis 1 (index 0 is clean)."""

    textures: list[str]
    tactile: dict[str, list[np.ndarray]]
    visual: np.ndarray | None
    frames: np.ndarray | None
    visual_keys: list[str]

    def visual_of(self, key: str) -> np.ndarray:
        return self.visual[:, self.visual_keys.index(key)]

    def frames_of(self, key: str) -> np.ndarray | None:
        """(T, 5) frame statistics of a camera variant, or None when they were not computed."""
        return None if self.frames is None else self.frames[:, self.visual_keys.index(key)]


def faulted_inputs(
    root: str | Path,
    textures: list[str],
    work: Path,
    *,
    tactile_config: TactileConfig | None = None,
    visual_config: VisualConfig | None = None,
    visual: bool = True,
    seed: int = 0,
    workers: int | None = 2,
) -> FaultedInputs:
    """Every texture's faulted inputs (cached in `work`)."""
    ds = Dataset(root)
    tcfg = tactile_config or TactileConfig()
    fp = dataset_fingerprint(ds)
    work.mkdir(parents=True, exist_ok=True)
    tkeys = [CLEAN] + [k for k, _, _ in touch_variants()]
    tpath = work / f"faulted-tactile-{tcfg.hash()}-{fp}-s{seed}.npz"
    tactile: dict[str, list[np.ndarray]] = {k: [] for k in tkeys}
    cached = _load(tpath, textures)
    if cached is None:
        jobs = [{"root": str(ds.root), "texture": t, "config": tcfg.to_dict(), "seed": seed} for t in textures]
        arrays = {}
        for t, res in zip(textures, run_jobs(_tactile_job, jobs, workers, "faulted touch inputs", threads=1)):
            for k in tkeys:
                arrays[f"{t}|{k}"] = res[k]
        _save(tpath, textures, arrays)
        cached = arrays
    for t in textures:
        for k in tkeys:
            tactile[k].append(cached[f"{t}|{k}"])
    vis = frames = None
    vkeys = [CLEAN] + [k for k, _, _ in camera_variants()]
    if visual:
        vcfg = visual_config or VisualConfig()
        vpath = work / f"faulted-visual-{vcfg.hash()}-{fp}-s{seed}.npz"
        cached = _load(vpath, textures)
        if cached is None:
            jobs = [
                {"image": str(ds.image_paths(t)[0]), "texture": t, "config": vcfg.model_dump(mode="json"), "seed": seed}
                for t in textures
            ]
            results = list(run_jobs(_visual_job, jobs, workers, "faulted camera inputs", threads=1))
            cached = {"X": np.stack([r[0] for r in results]), "frames": np.stack([r[1] for r in results])}
            _save(vpath, textures, cached)
        vis, frames = cached["X"], cached["frames"]
    return FaultedInputs(list(textures), tactile, vis, frames, vkeys)


def _load(path: Path, textures: list[str]) -> dict | None:
    if not path.is_file():
        return None
    with np.load(path, allow_pickle=False) as z:
        if list(z["__textures__"]) != list(textures):
            return None
        return {k: z[k] for k in z.files if k != "__textures__"}


def _save(path: Path, textures: list[str], arrays: dict) -> None:
    with atomic_path(path) as tmp:
        np.savez(tmp, __textures__=np.array(textures), **arrays)
