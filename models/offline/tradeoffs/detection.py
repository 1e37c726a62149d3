"""The out-of-distribution detector over the study's folds, independent of any model.

For every LOOCV fold a detector is fitted on the training textures (their tactile windows, image
views and photo statistics) and checks the held-out texture's inputs — clean and under every
fault. For every calibration model (models.offline.tradeoffs.folds) a detector fitted on that model's
training textures gives the distances of the calibration windows (for distance-normalised
intervals). For every left-out material group, one detector flags that group's textures.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from models.inference.ood import OODDetector
from models.offline import calibrate
from models.offline.evaluation.data import TextureData
from models.offline.jobs import run_jobs
from models.offline.tradeoffs.faulted import CLEAN, FaultedInputs
from models.offline.tradeoffs.folds import calibration_keys, key_excludes

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
    return calibrate.fit_detector(
        data.take(train), None if frames is None else frames[train], windows_per_texture=DETECTOR_WINDOWS, seed=seed
    )


def _check(det: OODDetector, tactile: np.ndarray, visual: np.ndarray | None, frame_stats: np.ndarray | None) -> Check:
    if len(tactile) == 0:
        return Check(np.zeros(0, bool), [], np.zeros(0))
    reasons = det.frame_reasons(frame_stats) if frame_stats is not None else []
    r = det.check(tactile, visual, frame_reasons=reasons)
    return Check(r.flags, r.reasons, r.distance)


@dataclass(frozen=True)
class _Inputs:
    """What every detector job reads."""

    data: TextureData
    inputs: FaultedInputs
    with_visual: bool


def _map(fn, items: list, inputs: _Inputs, workers: int, desc: str, unit: str) -> list:
    """fn(inputs, item) over items, in this process or in `workers` processes, one BLAS thread each."""
    return list(run_jobs(partial(fn, inputs), items, workers, desc, unit=unit, threads=1, progress=True))


def _clean_inputs(study: _Inputs, j: int) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    inputs = study.inputs
    return (
        inputs.tactile[CLEAN][j],
        inputs.visual_of(CLEAN)[j] if study.with_visual else None,
        inputs.frames_of(CLEAN)[j] if inputs.frames is not None else None,
    )


def _fold(study: _Inputs, i: int) -> dict[str, Check]:
    data, inputs, with_visual = study.data, study.inputs, study.with_visual
    n = len(data)
    det = fit_detector(data, inputs, np.array([j for j in range(n) if j != i]))
    _, v_clean, f_clean = _clean_inputs(study, i)
    out = {key: _check(det, per_texture[i], v_clean, f_clean) for key, per_texture in inputs.tactile.items()}
    if with_visual:
        for key in inputs.visual_keys[1:]:
            stats = inputs.frames_of(key)
            out[key] = _check(
                det, inputs.tactile[CLEAN][i], inputs.visual_of(key)[i], None if stats is None else stats[i]
            )
        out["no_frame@1"] = _check(det, inputs.tactile[CLEAN][i], None, None)
    return out


def fold_checks(
    data: TextureData, inputs: FaultedInputs, *, with_visual: bool, workers: int = 1
) -> dict[str, list[Check]]:
    """{variant: [Check of held-out texture i for every fold i]} — touch variants with the clean frame,
    camera variants with the clean touch segment, "no_frame@1" without a frame."""
    study = _Inputs(data, inputs, with_visual)
    per_fold = _map(_fold, list(range(len(data))), study, workers, "OOD detector per fold", "fold")
    out: dict[str, list[Check]] = {}
    for checks in per_fold:
        for key, c in checks.items():
            out.setdefault(key, []).append(c)
    return out


def _calibration(study: _Inputs, task: tuple[np.ndarray, tuple[int, ...]]) -> dict[int, np.ndarray]:
    part, key = task
    held = key_excludes(part, key)
    det = fit_detector(study.data, study.inputs, np.flatnonzero(~held))
    return {int(j): _check(det, *_clean_inputs(study, j)).distance for j in np.flatnonzero(held)}


def calibration_distances(
    data: TextureData, inputs: FaultedInputs, part: np.ndarray, *, with_visual: bool, workers: int = 1
) -> dict[tuple[int, ...], dict[int, np.ndarray]]:
    """{key: {j: (n_j,) distance of texture j's clean segment windows}} for each calibration model's
    held-out textures."""
    keys = calibration_keys(int(part.max()) + 1)
    results = _map(
        _calibration,
        [(part, k) for k in keys],
        _Inputs(data, inputs, with_visual),
        workers,
        "OOD detector per calibration model",
        "model",
    )
    return dict(zip(keys, results))


def _shift(study: _Inputs, g: str) -> dict[int, Check]:
    groups = np.asarray(study.data.groups)
    held = groups == g
    det = fit_detector(study.data, study.inputs, np.flatnonzero(~held))
    return {int(i): _check(det, *_clean_inputs(study, i)) for i in np.flatnonzero(held)}


def shift_checks(data: TextureData, inputs: FaultedInputs, *, with_visual: bool, workers: int = 1) -> dict[int, Check]:
    """{texture i: Check of its clean segment by the detector fitted without i's material group}."""
    out: dict[int, Check] = {}
    for checks in _map(
        _shift,
        sorted(set(data.groups)),
        _Inputs(data, inputs, with_visual),
        workers,
        "OOD detector per left-out group",
        "group",
    ):
        out.update(checks)
    return out
