"""The out-of-distribution detector over the study's folds, independent of any model.

For every LOOCV fold a detector is fitted on the training textures (their tactile windows, image
views and photo statistics) and checks the held-out texture's inputs — clean and under every
fault. For every calibration model (models.tradeoffs.folds) a detector fitted on that model's
training textures gives the distances of the calibration windows (for distance-normalised
intervals). For every left-out material group, one detector flags that group's textures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from models import calibrate
from models.evaluation.data import TextureData
from models.ood import OODDetector
from models.tradeoffs.faulted import CLEAN, FaultedInputs
from models.tradeoffs.folds import calibration_keys, key_excludes

DETECTOR_WINDOWS = 32  # per training texture: enough for a 16-component subspace, fast to refit 150 times


@dataclass(frozen=True)
class Check:
    """One input checked: flags (n,) bool, reasons per window, distance (n,)."""

    flags: np.ndarray
    reasons: list[list[str]]
    distance: np.ndarray


def fit_detector(data: TextureData, inputs: FaultedInputs, train: np.ndarray, seed: int = 0) -> OODDetector:
    """The detector of the model trained on textures `train` (their photos' statistics included when computed)."""
    frames = inputs.frames_of(CLEAN)
    return calibrate.fit_detector(data.take(train), None if frames is None else frames[train],
                                  windows_per_texture=DETECTOR_WINDOWS, seed=seed)


def _check(det: OODDetector, tactile: np.ndarray, visual: np.ndarray | None, frame_stats: np.ndarray | None) -> Check:
    if len(tactile) == 0:
        return Check(np.zeros(0, bool), [], np.zeros(0))
    reasons = det.frame_reasons(frame_stats) if frame_stats is not None else []
    r = det.check(tactile, visual, frame_reasons=reasons)
    return Check(r.flags, r.reasons, r.distance)


def fold_checks(data: TextureData, inputs: FaultedInputs, *, with_visual: bool) -> dict[str, list[Check]]:
    """{variant: [Check of held-out texture i for every fold i]} — touch variants with the clean frame,
    camera variants with the clean touch segment, "no_frame@1" without a frame."""
    n = len(data)
    out: dict[str, list[Check]] = {}
    clean_frames = inputs.frames_of(CLEAN) if inputs.frames is not None else None
    for i in tqdm(range(n), desc="OOD detector per fold", unit="fold"):
        det = fit_detector(data, inputs, np.array([j for j in range(n) if j != i]))
        v_clean = inputs.visual_of(CLEAN)[i] if with_visual else None
        f_clean = clean_frames[i] if clean_frames is not None else None
        for key, per_texture in inputs.tactile.items():
            out.setdefault(key, []).append(_check(det, per_texture[i], v_clean, f_clean))
        if with_visual:
            for key in inputs.visual_keys[1:]:
                stats = inputs.frames_of(key)
                out.setdefault(key, []).append(_check(det, inputs.tactile[CLEAN][i], inputs.visual_of(key)[i],
                                                      None if stats is None else stats[i]))
            out.setdefault("no_frame@1", []).append(_check(det, inputs.tactile[CLEAN][i], None, None))
    return out


def calibration_distances(data: TextureData, inputs: FaultedInputs, part: np.ndarray, *,
                          with_visual: bool) -> dict[tuple[int, ...], dict[int, np.ndarray]]:
    """{key: {j: (n_j,) distance of texture j's clean segment windows}} for each calibration model's held-out textures."""
    out = {}
    keys = calibration_keys(int(part.max()) + 1)
    for key in tqdm(keys, desc="OOD detector per calibration model", unit="model"):
        held = key_excludes(part, key)
        det = fit_detector(data, inputs, np.flatnonzero(~held))
        out[key] = {int(j): _check(det, inputs.tactile[CLEAN][j], inputs.visual_of(CLEAN)[j] if with_visual else None,
                                   inputs.frames_of(CLEAN)[j] if inputs.frames is not None else None).distance
                    for j in np.flatnonzero(held)}
    return out


def shift_checks(data: TextureData, inputs: FaultedInputs, *, with_visual: bool) -> dict[int, Check]:
    """{texture i: Check of its clean segment by the detector fitted without i's material group}."""
    groups = np.asarray(data.groups)
    out = {}
    for g in tqdm(sorted(set(data.groups)), desc="OOD detector per left-out group", unit="group"):
        held = groups == g
        det = fit_detector(data, inputs, np.flatnonzero(~held))
        for i in np.flatnonzero(held):
            out[int(i)] = _check(det, inputs.tactile[CLEAN][i], inputs.visual_of(CLEAN)[i] if with_visual else None,
                                 inputs.frames_of(CLEAN)[i] if inputs.frames is not None else None)
    return out
