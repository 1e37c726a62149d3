"""Render a vibration model along a (speed, force) trajectory, one sample per millisecond."""

from __future__ import annotations

import numba
import numpy as np

from texture_library.lsf import lsf_to_poly
from texture_library.vibration import VibrationModel

_CHUNK = 8192  # points per barycentric batch: bounds memory at (chunk × triangles × 3)


def barycentric(model: VibrationModel, speed: np.ndarray, force: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Enclosing triangle and barycentric weights for each (speed, force) point.

    Points are clamped to [0, max_speed] × [0, max_force] first. A point that no
    triangle contains (a hole or round-off on an edge) takes the triangle it is
    least outside of, with weights clipped to ≥ 0 and renormalised.
    Returns (vertex indices (n, 3) int, weights (n, 3) float).
    """
    s = np.clip(np.asarray(speed, float), 0.0, model.max_speed)
    f = np.clip(np.asarray(force, float), 0.0, model.max_force)
    # Normalise both axes so "least outside" is not dominated by the mm/s scale.
    gs = np.asarray(model.speeds) / model.max_speed
    gf = np.asarray(model.forces) / model.max_force
    s, f = s / model.max_speed, f / model.max_force
    tri = np.asarray(model.triangles)
    x0, y0 = gs[tri[:, 0]], gf[tri[:, 0]]
    x1, y1 = gs[tri[:, 1]], gf[tri[:, 1]]
    x2, y2 = gs[tri[:, 2]], gf[tri[:, 2]]
    det = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
    det = np.where(np.abs(det) < 1e-15, np.nan, det)  # degenerate triangles never win
    idx = np.empty((s.size, 3), np.int64)
    w = np.empty((s.size, 3))
    for lo in range(0, s.size, _CHUNK):
        ps, pf = s[lo : lo + _CHUNK, None], f[lo : lo + _CHUNK, None]
        l0 = ((y1 - y2) * (ps - x2) + (x2 - x1) * (pf - y2)) / det
        l1 = ((y2 - y0) * (ps - x2) + (x0 - x2) * (pf - y2)) / det
        l2 = 1.0 - l0 - l1
        worst = np.nan_to_num(np.minimum(np.minimum(l0, l1), l2), nan=-np.inf)
        best = np.argmax(worst, axis=1)
        rows = np.arange(best.size)
        lam = np.stack([l0[rows, best], l1[rows, best], l2[rows, best]], axis=1)
        lam = np.clip(lam, 0.0, None)
        lam /= lam.sum(axis=1, keepdims=True)
        idx[lo : lo + _CHUNK] = tri[best]
        w[lo : lo + _CHUNK] = lam
    return idx, w


def interpolate(model: VibrationModel, speed: np.ndarray, force: np.ndarray) -> dict[str, np.ndarray]:
    """Per-point ARMA parameters: AR/MA coefficients (n, p+1)/(n, q+1), variance (n,), gain (n,)."""
    idx, w = barycentric(model, speed, force)

    def mix(arr: np.ndarray) -> np.ndarray:
        arr = np.asarray(arr, float)
        return np.einsum("nk,nk...->n...", w, arr[idx])

    return {
        "ar": lsf_to_poly(mix(model.ar_lsf)),
        "ma": lsf_to_poly(mix(model.ma_lsf)),
        "variance": np.maximum(mix(model.variance), 0.0),
        "gain": mix(model.gain),
    }


@numba.njit(cache=True)
def _arma_time_varying(ar: np.ndarray, ma: np.ndarray, excitation: np.ndarray) -> np.ndarray:
    """y[n] = Σⱼ ma[n,j]·e[n−j] − Σᵢ₌₁ ar[n,i]·y[n−i]; ma already scaled by the gain."""
    n = excitation.shape[0]
    p = ar.shape[1] - 1
    q = ma.shape[1] - 1
    y = np.zeros(n)
    for t in range(n):
        acc = 0.0
        for j in range(min(q, t) + 1):
            acc += ma[t, j] * excitation[t - j]
        for i in range(1, min(p, t) + 1):
            acc -= ar[t, i] * y[t - i]
        y[t] = acc
    return y


def render(
    model: VibrationModel,
    speed: np.ndarray,
    force: np.ndarray,
    rng: np.random.Generator | None = None,
    *,
    excitation: np.ndarray | None = None,
) -> np.ndarray:
    """Synthesize texture vibration along a trajectory.

    speed: (n,) mm/s and force: (n,) N, sampled at model.rate_hz (1 kHz).
    The excitation is unit-variance white noise drawn from `rng` (one `standard_normal(n)`
    call), or the given `excitation` (n,) — scaled by √variance at each point either way.
    Returns acceleration (n,) in m/s² at the same rate.
    """
    speed = np.asarray(speed, float)
    force = np.asarray(force, float)
    if speed.ndim != 1 or speed.shape != force.shape:
        raise ValueError(f"speed and force must be 1-D of equal length, got {speed.shape} and {force.shape}")
    if speed.size == 0:
        return np.zeros(0)
    if not (np.all(np.isfinite(speed)) and np.all(np.isfinite(force))):
        raise ValueError("speed and force must be finite (no NaN/Inf)")
    if excitation is None:
        if rng is None:
            raise ValueError("render needs an rng or an explicit excitation")
        excitation = rng.standard_normal(speed.size)
    excitation = np.asarray(excitation, float)
    if excitation.shape != speed.shape:
        raise ValueError(f"excitation must have shape {speed.shape}, got {excitation.shape}")
    params = interpolate(model, speed, force)
    ma = params["ma"] * params["gain"][:, None]
    return _arma_time_varying(params["ar"], ma, excitation * np.sqrt(params["variance"]))
