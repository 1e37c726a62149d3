"""Freehand stroke trajectories: how a hand (or a robot imitating one) drags a tool.

Back-and-forth strokes of 0.8–2 s; within a stroke the speed rises and falls
(sin² profile between a turnaround speed and a per-stroke peak) and the normal
force wanders smoothly around a per-stroke level. Everything stays inside the
ranges given, so a vibration model is never driven outside its grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, sosfiltfilt


@dataclass(frozen=True)
class Trajectory:
    """speed: (n,) mm/s; force: (n,) N; position: (n,) mm along the stroke line; at rate_hz."""

    speed: np.ndarray
    force: np.ndarray
    position: np.ndarray
    rate_hz: float


def freehand(
    duration_s: float,
    rng: np.random.Generator,
    *,
    rate_hz: float = 1000.0,
    speed_range: tuple[float, float] = (20.0, 300.0),
    force_range: tuple[float, float] = (0.2, 4.0),
    stroke_s: tuple[float, float] = (0.8, 2.0),
) -> Trajectory:
    """A seeded freehand trajectory of duration_s seconds.

    speed_range: (turnaround, highest peak) mm/s; force_range: (min, max) N.
    """
    if not duration_s > 0:
        raise ValueError(f"duration_s must be > 0, got {duration_s}")
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
    v_lo, v_hi = speed_range
    f_lo, f_hi = force_range
    if not (0 <= v_lo < v_hi):
        raise ValueError(f"speed_range must satisfy 0 ≤ low < high, got {speed_range}")
    if not (0 <= f_lo < f_hi):
        raise ValueError(f"force_range must satisfy 0 ≤ low < high, got {force_range}")
    s_lo, s_hi = stroke_s
    if not (0 < s_lo <= s_hi) or s_lo * rate_hz < 2:
        # a stroke of 0 samples would never advance the loop below
        raise ValueError(f"stroke_s must satisfy 0 < low ≤ high with low ≥ 2 samples at {rate_hz:g} Hz, got {stroke_s}")
    n = int(round(duration_s * rate_hz))
    speed = np.empty(n)
    level = np.empty(n)
    direction = np.empty(n)
    i, sign = 0, 1.0
    while i < n:
        m = int(rng.uniform(*stroke_s) * rate_hz)
        peak = rng.uniform(v_lo + 0.3 * (v_hi - v_lo), v_hi)
        phase = np.sin(np.pi * (np.arange(m) + 0.5) / m) ** 2
        seg = slice(i, min(i + m, n))
        k = seg.stop - seg.start
        speed[seg] = v_lo + (peak - v_lo) * phase[:k]
        level[seg] = rng.uniform(f_lo + 0.1 * (f_hi - f_lo), f_hi - 0.1 * (f_hi - f_lo))
        direction[seg] = sign
        sign = -sign
        i += m
    # Force: per-stroke level, smoothed across strokes, plus a slow wander (≈ 3 Hz).
    sos = butter(2, 3.0, fs=rate_hz, output="sos")
    wander = rng.standard_normal(n)
    wander = sosfiltfilt(sos, wander) if n > 15 else np.zeros(n)
    wander *= 0.08 * (f_hi - f_lo) / max(wander.std(), 1e-12)
    force = sosfiltfilt(sos, level) + wander if n > 15 else level
    force = np.clip(force, f_lo, f_hi)
    position = np.cumsum(direction * speed) / rate_hz
    return Trajectory(speed=speed, force=force, position=position, rate_hz=rate_hz)


def model_ranges(max_speed: float, max_force: float) -> dict[str, tuple[float, float]]:
    """Keyword ranges for freehand() that stay inside a vibration model's grid (5 % margin)."""
    return {
        "speed_range": (20.0, min(300.0, 0.95 * max_speed)),
        "force_range": (0.2, min(4.0, 0.95 * max_force)),
    }
