"""One model, one seed: every fit of the robustness and interval studies, each used for every input it has to predict.

Tasks (each fits once on its training textures, then predicts):
  loocv i         held-out texture i: clean (all its windows, as LOOCV scores it) and every
                  touch and camera variant (texture-level and per window), no frame at all
                  (the training-mean image vector in place of the frame)
  calib key       the calibration models of models.offline.tradeoffs.folds: their held-out textures'
                  clean predictions (texture-level and per window)
  aug i           like loocv, trained with augmented training textures (noisy touch windows
                  and blurred image views of the training textures only), predicting the
                  variants augmentation targets
  shift g         without material group g: its textures, clean
  shift_inner g k inner folds inside the training groups: out-of-fold clean predictions that
                  calibrate intervals under shift
Faults reach held-out textures only; every fit sees training textures only.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from models.offline.calibrate import Prediction, predict
from models.offline.evaluation.data import TextureData
from models.offline.evaluation.estimator_registry import EstimatorSpec
from models.offline.jobs import run_jobs
from models.offline.tradeoffs.faulted import AUG_BLUR_SIGMA_PX, AUG_NOISE_SNR_DB, CLEAN, FaultedInputs, variant
from models.offline.tradeoffs.folds import calibration_keys, inner_folds, key_excludes

SHIFT_INNER_FOLDS = 5
AUGMENTED_FAULTS = ("noise", "blur")  # the variants an augmented fit is asked to predict


@dataclass
class StudyRun:
    model: str
    seed: int
    options: dict
    textures: list[str]
    loocv: dict[str, list[Prediction | None]] = field(default_factory=dict)  # variant → per texture
    calib: dict[tuple[int, ...], dict[int, Prediction]] = field(default_factory=dict)
    aug: dict[str, list[Prediction | None]] = field(default_factory=dict)
    shift: dict[int, Prediction] = field(default_factory=dict)  # texture → prediction
    shift_inner: dict[str, dict[int, Prediction]] = field(default_factory=dict)  # group → texture → prediction
    seconds: dict[str, float] = field(default_factory=dict)
    held_out: list[int] | None = None  # the LOOCV folds run (None: every texture); the others stay None in loocv/aug


# ---- augmentation ------------------------------------------------------------------------------------
def augment(train: TextureData, inputs: FaultedInputs, index: np.ndarray) -> TextureData:
    """Training textures with their noisy windows (every AUG_NOISE_SNR_DB) added to their windows and their
    blurred photos (every AUG_BLUR_SIGMA_PX) added as image views. Texture-level models (ridge: mean
    window, view 0) instead see each augmented copy as one more training texture with the same ratings."""
    noisy = [[inputs.tactile[variant("aug_noise", s)][i] for s in AUG_NOISE_SNR_DB] for i in index]
    blurred = (
        None
        if inputs.visual is None
        else np.stack([inputs.visual_of(variant("aug_blur", s))[index] for s in AUG_BLUR_SIGMA_PX], axis=1)
    )
    return replace(train, meta={**train.meta, "augmentation": {"noisy": noisy, "blurred": blurred}})


def expand_for_texture_models(train: TextureData) -> TextureData:
    """Augmented copies as extra training textures (for models that read a texture's mean window and view 0)."""
    aug = train.meta["augmentation"]
    textures, groups, tactile, visual, targets = [], [], [], [], []
    for i in range(len(train)):
        copies = [(train.tactile[i], None)] + [(w, None) for w in aug["noisy"][i] if len(w)]
        if aug["blurred"] is not None:
            copies += [(train.tactile[i], aug["blurred"][i, k]) for k in range(aug["blurred"].shape[1])]
        for w, v in copies:
            textures.append(train.textures[i])
            groups.append(train.groups[i])
            tactile.append(w)
            base = train.visual[i] if train.visual is not None else None
            if base is not None:
                visual.append(base if v is None else np.concatenate([v[None], base[1:]]))
            targets.append(train.targets[i])
    meta = {k: v for k, v in train.meta.items() if k != "augmentation"}
    return TextureData(textures, groups, tactile, np.stack(visual) if visual else None, np.array(targets), meta)


def expand_for_window_models(train: TextureData) -> TextureData:
    """Augmented windows join each texture's windows; blurred photos join its image views (nets pair them at random)."""
    aug = train.meta["augmentation"]
    tactile = [np.concatenate([w] + [x for x in aug["noisy"][i] if len(x)]) for i, w in enumerate(train.tactile)]
    visual = train.visual
    if aug["blurred"] is not None and visual is not None:
        visual = np.concatenate([visual, aug["blurred"].astype(visual.dtype)], axis=1)
    meta = {k: v for k, v in train.meta.items() if k != "augmentation"}
    return replace(train, tactile=tactile, visual=visual, meta=meta)


def _is_window_model(est) -> bool:
    from models.offline.evaluation.net_estimator import NetEnsemble, NetEstimator

    return isinstance(est, (NetEstimator, NetEnsemble))


# ---- tasks ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Study:
    """What every task of one run reads: the data, its faulted inputs, the model and the calibration partition."""

    data: TextureData
    inputs: FaultedInputs
    spec: EstimatorSpec
    part: np.ndarray


def _fit(study: _Study, train_idx: np.ndarray, seed: int, augmented: bool = False):
    train = study.data.take(train_idx)
    est = study.spec.build()
    if augmented:
        train = augment(train, study.inputs, train_idx)
        train = expand_for_window_models(train) if _is_window_model(est) else expand_for_texture_models(train)
    return est.fit(train, seed)


def _clean(study: _Study, est, i: int) -> Prediction | None:
    data, inputs = study.data, study.inputs
    v = data.visual[i, 0] if data.visual is not None else None
    return predict(est, data, inputs.tactile[CLEAN][i], v, texture_tactile=data.tactile[i])


def _variants(
    study: _Study, est, i: int, train_idx: np.ndarray, only: tuple[str, ...] | None = None
) -> dict[str, Prediction | None]:
    data, inputs = study.data, study.inputs
    out: dict[str, Prediction | None] = {CLEAN: _clean(study, est, i)}
    v_clean = data.visual[i, 0] if data.visual is not None else None

    def wanted(key: str) -> bool:
        return only is None or key.split("@")[0] in only

    for key, per_texture in inputs.tactile.items():
        if key != CLEAN and not key.startswith("aug_") and wanted(key):
            out[key] = predict(est, data, per_texture[i], v_clean)
    if inputs.visual is not None and data.visual is not None:
        for key in inputs.visual_keys[1:]:
            if not key.startswith("aug_") and wanted(key):
                out[key] = predict(est, data, inputs.tactile[CLEAN][i], inputs.visual_of(key)[i])
        if wanted("no_frame@1"):
            mean_view = data.visual[train_idx, 0].mean(axis=0)  # what the model knows of images in general
            out["no_frame@1"] = predict(est, data, inputs.tactile[CLEAN][i], mean_view)
    return out


def _task(study: _Study, task: tuple) -> tuple[tuple, object, float]:
    kind, arg, seed = task
    t0 = time.perf_counter()
    data, part = study.data, study.part
    n = len(data)
    if kind == "loocv":
        train = np.array([j for j in range(n) if j != arg])
        result = _variants(study, _fit(study, train, seed), arg, train)
    elif kind == "aug":
        train = np.array([j for j in range(n) if j != arg])
        result = _variants(study, _fit(study, train, seed, augmented=True), arg, train, only=AUGMENTED_FAULTS)
    elif kind == "calib":
        held = key_excludes(part, arg)
        est = _fit(study, np.flatnonzero(~held), seed)
        result = {int(j): _clean(study, est, j) for j in np.flatnonzero(held)}
    elif kind == "shift":
        groups = np.asarray(data.groups)
        est = _fit(study, np.flatnonzero(groups != arg), seed)
        result = {int(j): _clean(study, est, j) for j in np.flatnonzero(groups == arg)}
    elif kind == "shift_inner":
        group, fold = arg
        groups = np.asarray(data.groups)
        train_all = np.flatnonzero(groups != group)
        held = inner_folds(train_all, SHIFT_INNER_FOLDS, seed=0)[fold]
        est = _fit(study, np.setdiff1d(train_all, held), seed)
        result = {int(j): _clean(study, est, j) for j in held}
    else:
        raise ValueError(f"unknown task {kind!r}")
    return task, result, time.perf_counter() - t0


def run_study(
    data: TextureData,
    inputs: FaultedInputs,
    part: np.ndarray,
    model: str,
    *,
    seed: int = 0,
    options: dict | None = None,
    loocv: bool = True,
    calibration: bool = False,
    augmentation: bool = False,
    shift: bool = True,
    workers: int = 1,
    held_out: np.ndarray | None = None,
) -> StudyRun:
    """Every requested task of one (model, seed); folds in `workers` processes.

    held_out: texture indices whose LOOCV (and augmented) folds run, to cut the cost of slow models
    (None: all); their predictions of the other textures stay None and the analysis skips them."""
    spec = EstimatorSpec(model, options or {})
    n = len(data)
    folds = list(range(n)) if held_out is None else sorted({int(i) for i in held_out})
    if any(not 0 <= i < n for i in folds):
        raise ValueError(f"held_out indices must lie in 0…{n - 1}, got {folds}")
    tasks = []
    if loocv:
        tasks += [("loocv", i, seed) for i in folds]
    if calibration:
        tasks += [("calib", key, seed) for key in calibration_keys(int(part.max()) + 1)]
    if augmentation:
        tasks += [("aug", i, seed) for i in folds]
    if shift:
        groups = sorted(set(data.groups))
        tasks += [("shift", g, seed) for g in groups]
        if calibration:
            tasks += [("shift_inner", (g, k), seed) for g in groups for k in range(SHIFT_INNER_FOLDS)]
    run = StudyRun(model, seed, options or {}, list(data.textures), held_out=None if held_out is None else folds)
    task = partial(_task, _Study(data, inputs, spec, part))
    _collect(run, run_jobs(task, tasks, max(workers, 1), f"{model} seed {seed}", unit="fit", progress=True))
    return run


def _collect(run: StudyRun, results) -> None:
    for (kind, arg, _), result, seconds in results:
        run.seconds[kind] = run.seconds.get(kind, 0.0) + seconds
        if kind in ("loocv", "aug"):
            target = run.loocv if kind == "loocv" else run.aug
            for key, pred in result.items():
                target.setdefault(key, [None] * len(run.textures))[arg] = pred
        elif kind == "calib":
            run.calib[arg] = result
        elif kind == "shift":
            run.shift.update(result)
        else:
            run.shift_inner.setdefault(arg[0], {}).update(result)
