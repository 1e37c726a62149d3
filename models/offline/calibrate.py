"""Calibrating a model's uncertainty from out-of-fold predictions (training side; imports estimators).

`hapticlink train` calls `cv_uncertainty`: K-fold cross-validation over the training textures
gives each texture a prediction from a model that never saw it, and a distance from an OOD
detector fitted without it; conformal quantiles of those residuals become the
`IntervalCalibration`s stored in the model card, and an `OODDetector` fitted on every training
texture goes beside them. The robustness study (models.offline.tradeoffs) runs the same pieces inside
its leave-one-texture-out folds to measure the coverage this procedure delivers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.inference.intervals import IntervalCalibration, ema
from models.inference.ood import OODDetector
from models.offline.evaluation.data import TextureData
from models.offline.evaluation.estimator_registry import EstimatorSpec
from models.tactile.config import STAT_NAMES, TactileConfig
from texture_library.attributes import RATING_MAX, RATING_MIN

CALIBRATION_WINDOWS = 20  # contiguous windows per texture (10 s of stroking): the window and EMA targets
EMA_ALPHA = 0.5  # the service's default smoothing
TARGETS = ("window", "ema", "texture")


@dataclass
class Prediction:
    """texture: (4,) bipolar, the texture-level prediction; windows: (n, 4), one per window in time order."""

    texture: np.ndarray
    windows: np.ndarray


def _one_frame(data: TextureData, visual: np.ndarray, n: int) -> np.ndarray:
    """(n, V, D): one frame's vector (D,) in every one of the V view slots the training data stores, so a
    model that pools V views pools exactly that frame (as models.offline.evaluation.loocv.seen_through does)."""
    views = 1 if data.visual is None else data.visual.shape[1]
    return np.tile(np.asarray(visual, np.float32).reshape(1, 1, -1), (n, views, 1))


def one_texture(data: TextureData, tactile: np.ndarray, visual: np.ndarray | None) -> TextureData:
    """A one-texture TextureData (no ratings) of windows (n, F) and one frame's visual vector (D,) or None."""
    vis = None if visual is None else _one_frame(data, visual, 1)
    return TextureData(["held-out"], ["?"], [np.asarray(tactile, np.float32)], vis, None, data.meta)


def per_window(data: TextureData, tactile: np.ndarray, visual: np.ndarray | None) -> TextureData:
    """Each window as its own pseudo-texture, so texture-level estimators predict window by window."""
    n = len(tactile)
    vis = None if visual is None else _one_frame(data, visual, n)
    return TextureData(
        ["w"] * n, ["?"] * n, [np.asarray(tactile[k : k + 1], np.float32) for k in range(n)], vis, None, data.meta
    )


def predict(
    est, data: TextureData, tactile: np.ndarray, visual: np.ndarray | None, *, texture_tactile: np.ndarray | None = None
) -> Prediction | None:
    """Texture-level prediction (from `texture_tactile`, default the same windows) and per-window predictions,
    clipped to the rating range as exported models clip. None when there is no window."""
    if len(tactile) == 0:
        return None
    v = visual if est.modality in ("visual", "both") else None
    whole = tactile if texture_tactile is None else texture_tactile
    texture = est.predict(one_texture(data, whole, v))[0]
    windows = est.predict(per_window(data, tactile, v))
    return Prediction(np.clip(texture, RATING_MIN, RATING_MAX), np.clip(windows, RATING_MIN, RATING_MAX))


def rows_of(pred: Prediction, truth: np.ndarray, distance: np.ndarray, target: str):
    """(pred (m, 4), truth (m, 4), distance (m,)) of one texture's estimates for a target:
    its windows, their EMA (distances smoothed alike), or the texture (mean distance)."""
    if target == "window":
        p, d = pred.windows, distance
    elif target == "ema":
        p, d = ema(pred.windows, EMA_ALPHA), ema(distance[:, None], EMA_ALPHA)[:, 0]
    elif target == "texture":
        p, d = pred.texture[None], np.array([float(np.mean(distance))])
    else:
        raise ValueError(f"unknown target {target!r}; one of {TARGETS}")
    return p, np.repeat(np.asarray(truth, float)[None], len(p), axis=0), d


def calibrate(
    material: list[tuple[int, Prediction, np.ndarray]],
    truth: np.ndarray,
    prior: np.ndarray,
    target: str,
    scale_kind: str,
    levels: tuple[float, ...] | None = None,
    method: str = "",
) -> IntervalCalibration:
    """An IntervalCalibration from out-of-fold material [(texture j, its prediction, its windows' distances)];
    truth: (T, 4) ratings indexed by j; prior: (T', 4) training ratings (the OOD fallback band)."""
    parts = []
    for j, p, d in material:
        rows = rows_of(p, truth[j], d, target)
        parts.append(rows + (np.full(len(rows[0]), j),))
    pred = np.concatenate([x[0] for x in parts])
    tru = np.concatenate([x[1] for x in parts])
    dist = np.concatenate([x[2] for x in parts])
    groups = np.concatenate([x[3] for x in parts])
    extra = {} if levels is None else {"levels": tuple(levels)}
    return IntervalCalibration.fit(
        pred,
        tru,
        groups=groups,
        scale=np.sqrt(dist) if scale_kind == "distance" else None,
        scale_kind=scale_kind,
        prior_ratings=prior,
        target=target,
        ema_alpha=EMA_ALPHA if target == "ema" else None,
        method=method,
        **extra,
    )


def fit_detector(data: TextureData, frames: np.ndarray | None = None, **options) -> OODDetector:
    """An OODDetector on a TextureData's windows, image views and photo statistics (T, 5) or None; the
    speed/force statistics are found from the data's tactile configuration (before any extra group's columns), and
    so are the taps group's columns (their training range flags windows whose taps the model never met)."""
    config = data.meta.get("tactile_config")
    if config is not None and "stat_start" not in options:
        options["stat_start"] = TactileConfig(**config).group_slices()["base"].stop - len(STAT_NAMES)
    if config is not None and "taps_start" not in options:
        options["taps_start"] = getattr(TactileConfig(**config).group_slices().get("taps"), "start", None)
    return OODDetector.fit(list(data.tactile), data.visual, frames, **options)


def photo_statistics(root, textures: list[str]) -> np.ndarray:
    """(T, 5) `frame_statistics` of each texture's first photo (the detector's frame ranges)."""
    from models.inference.ood import frame_statistics
    from models.offline.datasets.format import Dataset
    from models.visual.image import load_image

    ds = Dataset(root)
    out = []
    for t in textures:
        paths = ds.image_paths(t)
        if not paths:
            raise ValueError(f"texture {t!r} has no image")
        out.append(frame_statistics(load_image(paths[0], min_size=8)))
    return np.array(out)


def cv_uncertainty(
    data: TextureData,
    spec: EstimatorSpec,
    seed: int = 0,
    *,
    folds: int = 10,
    scale_kind: str = "none",
    frames: np.ndarray | None = None,
    detector_windows: int = 32,
) -> tuple[dict[str, IntervalCalibration], OODDetector]:
    """Interval calibrations for every target and the OOD detector of a model trained on all of `data`.

    K-fold over the textures (seeded): the fold's model predicts its held-out textures (CALIBRATION_WINDOWS
    contiguous windows each, with the photo's original view) and a detector fitted on the same training
    textures measures their distances."""
    n = len(data)
    if data.targets is None:
        raise ValueError("calibration needs rated textures")
    if not 2 <= folds <= n:
        raise ValueError(f"folds must lie in [2, {n}] textures, got {folds}")
    order = np.random.default_rng(seed).permutation(n)
    material = []
    for f in range(folds):
        held = np.sort(order[f::folds])
        train = np.setdiff1d(np.arange(n), held)
        est = spec.build().fit(data.take(train), seed)
        det = fit_detector(
            data.take(train), None if frames is None else frames[train], windows_per_texture=detector_windows, seed=seed
        )
        for j in held:
            windows = data.tactile[j][:CALIBRATION_WINDOWS]
            v = data.visual[j, 0] if data.visual is not None else None
            p = predict(est, data, windows, v, texture_tactile=data.tactile[j])
            material.append((int(j), p, det.check(windows, v if det.visual is not None else None).distance))
    prior = data.targets.astype(float)
    method = f"{folds}-fold CV over {n} training textures (seed {seed}), {CALIBRATION_WINDOWS} windows each"
    cals = {t: calibrate(material, prior, prior, t, scale_kind, method=method) for t in TARGETS}
    detector = fit_detector(data, frames, windows_per_texture=detector_windows, seed=seed)
    return cals, detector
