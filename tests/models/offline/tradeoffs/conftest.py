"""A small world for the study machinery: the linear texture world of the evaluation tests with
hand-made faulted inputs (noise that grows, a blur that washes the image out), no disk, no backbone."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from models.offline.faults.catalog import FAULTS
from models.offline.tradeoffs.faulted import AUG_BLUR_SIGMA_PX, AUG_NOISE_SNR_DB, CLEAN, FaultedInputs, variant

_spec = importlib.util.spec_from_file_location(
    "eval_conftest", Path(__file__).resolve().parents[1] / "evaluation" / "conftest.py"
)
_eval = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_eval)
make_linear_world = _eval.make_linear_world


def faulted_world(n_textures: int = 24, seed: int = 0):
    data = _eval.make_linear_world(n_textures=n_textures, n_windows=8, n_tactile=14, n_visual=16, seed=seed, noise=1.0)
    rng = np.random.default_rng(seed + 1)
    tactile = {CLEAN: [w.copy() for w in data.tactile]}
    scale = float(np.std(np.concatenate(data.tactile)[:, :-6]))
    for snr in FAULTS["noise"].strengths + AUG_NOISE_SNR_DB:
        key = variant("aug_noise", snr) if snr in AUG_NOISE_SNR_DB else variant("noise", snr)
        amp = scale * 10 ** (-snr / 20) * 3
        noisy = []
        for w in data.tactile:
            x = w.copy()
            x[:, :-6] += amp * rng.standard_normal(x[:, :-6].shape)
            noisy.append(x.astype(np.float32))
        tactile[key] = noisy
    keys = (
        [CLEAN]
        + [variant("blur", s) for s in FAULTS["blur"].strengths]
        + [variant("aug_blur", s) for s in AUG_BLUR_SIGMA_PX]
    )
    clean = data.visual[:, 0]
    visual = []
    for key in keys:
        s = 0.0 if key == CLEAN else float(key.split("@")[1])
        visual.append(clean * np.exp(-s / 4) + (1 - np.exp(-s / 4)) * clean.mean(axis=0))  # blur washes the image out
    inputs = FaultedInputs(list(data.textures), tactile, np.stack(visual, axis=1).astype(np.float32), None, keys)
    return data, inputs


@pytest.fixture(scope="package")
def world():
    return faulted_world()
