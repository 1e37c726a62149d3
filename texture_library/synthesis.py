"""Render a vibration model along a (speed, force) trajectory, one sample per millisecond."""

from __future__ import annotations

import numba
import numpy as np

from texture_library.lsf import poly_from_checked_lsf
from texture_library.vibration import VibrationModel


@numba.njit(cache=True)
def _least_outside(
    s: np.ndarray,
    f: np.ndarray,
    x0: np.ndarray,
    y0: np.ndarray,
    x1: np.ndarray,
    y1: np.ndarray,
    x2: np.ndarray,
    y2: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """For each point (s, f): the triangle whose smallest barycentric weight is largest (the enclosing one, else
    the one it is least outside of; first on ties; degenerate triangles never win) and its weights, clipped ≥ 0
    and renormalised. Compiled: the real-time renderer calls it on every block."""
    n, t = s.shape[0], x0.shape[0]
    best = np.zeros(n, np.int64)
    w = np.empty((n, 3))
    det = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
    for i in range(n):
        top = -np.inf
        b0 = b1 = b2 = np.nan
        for k in range(t):
            if abs(det[k]) < 1e-15:
                continue
            l0 = ((y1[k] - y2[k]) * (s[i] - x2[k]) + (x2[k] - x1[k]) * (f[i] - y2[k])) / det[k]
            l1 = ((y2[k] - y0[k]) * (s[i] - x2[k]) + (x0[k] - x2[k]) * (f[i] - y2[k])) / det[k]
            l2 = 1.0 - l0 - l1
            worst = min(min(l0, l1), l2)
            if worst > top:
                top, best[i], b0, b1, b2 = worst, k, l0, l1, l2
        b0, b1, b2 = max(b0, 0.0), max(b1, 0.0), max(b2, 0.0)
        total = b0 + b1 + b2
        w[i, 0], w[i, 1], w[i, 2] = b0 / total, b1 / total, b2 / total
    return best, w


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
    best, w = _least_outside(
        s, f, gs[tri[:, 0]], gf[tri[:, 0]], gs[tri[:, 1]], gf[tri[:, 1]], gs[tri[:, 2]], gf[tri[:, 2]]
    )
    idx = tri[best].astype(np.int64)
    return idx, w


def quietest_point(model: VibrationModel) -> tuple[float, float, float] | None:
    """(speed mm/s, force N, variance (m/s²)²) of the grid point with the smallest non-zero variance (the first of
    equals); None when every point's variance is 0."""
    variance = np.asarray(model.variance, float)
    live = np.flatnonzero(variance > 0)
    if live.size == 0:
        return None
    k = int(live[np.argmin(variance[live])])
    return float(model.speeds[k]), float(model.forces[k]), float(variance[k])


def corner_floor(model: VibrationModel, speed: np.ndarray, force: np.ndarray) -> np.ndarray:
    """The least variance (n,) the operator's renderer plays at (speed, force): v_r·min(1, s/s_r)²·min(1, f/f_r), with
    (s_r, f_r, v_r) the model's quietest vibrating grid point (`quietest_point`) and s, f clamped to the grid's range.

    Why: a grid whose edge rows (speed 0, force 0) hold no vibration has triangles between them whose three
    corners are all silent — the synthetic world's cell below 87.5 mm/s and 1.25 N — so plain barycentric blending
    is silent over a whole region where the surface does vibrate. The floor lets the level there fall smoothly
    towards the silent edges instead (amplitude ∝ speed, power ∝ force); it never binds where every corner of
    the triangle vibrates (a blend is at least its smallest corner), so HaTT's models render as before."""
    s = np.clip(np.asarray(speed, float), 0.0, model.max_speed)
    f = np.clip(np.asarray(force, float), 0.0, model.max_force)
    ref = quietest_point(model)
    if ref is None:
        return np.zeros(s.shape)
    s_r, f_r, v_r = ref
    rs = np.minimum(1.0, s / s_r) if s_r > 0 else np.ones(s.shape)
    rf = np.minimum(1.0, f / f_r) if f_r > 0 else np.ones(f.shape)
    return v_r * (rs * rs) * rf


def interpolate(
    model: VibrationModel, speed: np.ndarray, force: np.ndarray, *, floor: bool = False
) -> dict[str, np.ndarray]:
    """Per-point ARMA parameters: AR/MA coefficients (n, p+1)/(n, q+1), variance (n,), gain (n,).

    floor: raise the variance to `corner_floor` (the operator's renderer does; the robot's world does not)."""
    idx, w = barycentric(model, speed, force)

    def mix(arr: np.ndarray) -> np.ndarray:
        arr = np.asarray(arr, float)
        if arr.ndim == 1:  # einsum's own summation order, kept: results stay the same to the bit
            return np.einsum("nk,nk->n", w, arr[idx])
        return _mix(w, idx, arr)

    variance = np.maximum(mix(model.variance), 0.0)
    if floor:
        variance = np.maximum(variance, corner_floor(model, speed, force))
    return {
        # The model's rows were checked when it was made; their blends need no second check.
        "ar": poly_from_checked_lsf(mix(model.ar_lsf)),
        "ma": poly_from_checked_lsf(mix(model.ma_lsf)),
        "variance": variance,
        "gain": mix(model.gain),
    }


@numba.njit(cache=True)
def _mix(w: np.ndarray, idx: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(n, d) barycentric blend Σₖ w[i,k]·values[idx[i,k]] of (m, d) grid values, summed k = 0, 1, 2 in order (as
    numpy's einsum sums rows of LSFs). Compiled: the real-time renderer blends LSFs on every block."""
    n, d = w.shape[0], values.shape[1]
    out = np.empty((n, d))
    for i in range(n):
        for c in range(d):
            out[i, c] = w[i, 0] * values[idx[i, 0], c] + w[i, 1] * values[idx[i, 1], c] + w[i, 2] * values[idx[i, 2], c]
    return out


@numba.njit(cache=True)
def arma_filter(
    ar: np.ndarray, ma: np.ndarray, excitation: np.ndarray, e_history: np.ndarray, y_history: np.ndarray
) -> np.ndarray:
    """Time-varying ARMA: y[n] = Σⱼ ma[n,j]·e[n−j] − Σᵢ₌₁ ar[n,i]·y[n−i], continuing from a history.

    ar: (n, p+1) monic AR coefficients; ma: (n, q+1) MA coefficients already scaled by the gain; excitation:
    (n,) e, already scaled by √variance. e_history: (q,) and y_history: (p,), the q excitations and p outputs
    before this block, oldest first (zeros: a filter at rest). Returns y (n,). The streaming renderer
    (texture_library.renderer) and `render` both run this one loop.
    """
    n = excitation.shape[0]
    p = ar.shape[1] - 1
    q = ma.shape[1] - 1
    e = np.empty(q + n)
    e[:q] = e_history[e_history.shape[0] - q :]
    e[q:] = excitation
    y = np.zeros(p + n)
    y[:p] = y_history[y_history.shape[0] - p :]
    for t in range(n):
        acc = 0.0
        for j in range(q + 1):
            acc += ma[t, j] * e[q + t - j]
        for i in range(1, p + 1):
            acc -= ar[t, i] * y[p + t - i]
        y[p + t] = acc
    return y[p:]


def check_trajectory(speed: np.ndarray, force: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(speed, force) as float arrays; ValueError unless both are 1-D, of equal length and finite."""
    speed = np.asarray(speed, float)
    force = np.asarray(force, float)
    if speed.ndim != 1 or speed.shape != force.shape:
        raise ValueError(f"speed and force must be 1-D of equal length, got {speed.shape} and {force.shape}")
    if not (np.all(np.isfinite(speed)) and np.all(np.isfinite(force))):
        raise ValueError("speed and force must be finite (no NaN/Inf)")
    return speed, force


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
    speed, force = check_trajectory(speed, force)
    if speed.size == 0:
        return np.zeros(0)
    if excitation is None:
        if rng is None:
            raise ValueError("render needs an rng or an explicit excitation")
        excitation = rng.standard_normal(speed.size)
    excitation = np.asarray(excitation, float)
    if excitation.shape != speed.shape:
        raise ValueError(f"excitation must have shape {speed.shape}, got {excitation.shape}")
    params = interpolate(model, speed, force)
    ma = params["ma"] * params["gain"][:, None]
    at_rest = np.zeros(max(ma.shape[1], params["ar"].shape[1]))
    return arma_filter(params["ar"], ma, excitation * np.sqrt(params["variance"]), at_rest, at_rest)
