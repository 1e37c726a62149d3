"""Faults of the touch channels. accel: (n, 3) m/s² at rate_hz; every function returns a new array.

Power and range are measured on the signal given (so a test segment is faulted by its own
statistics); randomness comes from the caller's generator, so a study is reproducible.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
from scipy.signal import resample_poly

from texture_library.trajectory import Trajectory


def _signal(name: str, x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim not in (1, 2) or x.shape[0] < 2:
        raise ValueError(f"{name} must be (n,) or (n, k) with n ≥ 2 samples, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} has NaN or Inf samples")
    return x


def _rate(rate_hz: float) -> float:
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz must be a finite rate > 0 Hz, got {rate_hz}")
    return float(rate_hz)


def ac_power(x: np.ndarray) -> float:
    """Mean power of the signal about its per-column mean (gravity and offsets are not signal)."""
    x = _signal("x", x)
    return float(np.mean((x - x.mean(axis=0)) ** 2))


def add_noise(x: np.ndarray, snr_db: float, rng: np.random.Generator) -> np.ndarray:
    """White Gaussian noise at `snr_db` below the signal's AC power (every column the same noise power).

    x: (n,) or (n, k); snr_db: finite, dB (0 dB: noise as strong as the vibration)."""
    x = _signal("x", x)
    if not math.isfinite(snr_db):
        raise ValueError(f"snr_db must be finite, got {snr_db}")
    noise_power = ac_power(x) / 10.0 ** (snr_db / 10.0)
    return x + math.sqrt(noise_power) * rng.standard_normal(x.shape)


def clip_range(x: np.ndarray, fraction: float) -> np.ndarray:
    """A sensor whose full scale spans only `fraction` of the signal's range, centred on it.

    Per column: the band [c − f·w/2, c + f·w/2] with c the mid-range and w = max − min; the
    output's range is exactly f·w. fraction in (0, 1] (1: nothing clipped)."""
    x = _signal("x", x)
    if not (math.isfinite(fraction) and 0 < fraction <= 1):
        raise ValueError(f"fraction must lie in (0, 1], got {fraction}")
    lo, hi = x.min(axis=0), x.max(axis=0)
    centre, half = (lo + hi) / 2, fraction * (hi - lo) / 2
    return np.clip(x, centre - half, centre + half)


def periodic_segments(n: int, rate_hz: float, duration_s: float, every_s: float, offset_s: float = 0.0) -> np.ndarray:
    """(n,) bool: True inside segments of `duration_s` starting at offset_s, offset_s + every_s, …"""
    rate = _rate(rate_hz)
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"duration_s must be > 0 s, got {duration_s}")
    if not (math.isfinite(every_s) and every_s > duration_s):
        raise ValueError(f"every_s must exceed duration_s = {duration_s} s, got {every_s}")
    if not (math.isfinite(offset_s) and offset_s >= 0):
        raise ValueError(f"offset_s must be ≥ 0 s, got {offset_s}")
    length, period, offset = round(duration_s * rate), round(every_s * rate), round(offset_s * rate)
    if length < 1:
        raise ValueError(f"duration_s = {duration_s} s is shorter than one sample at {rate:g} Hz")
    k = np.arange(n) - offset
    return (k >= 0) & (k % period < length)


def dropout_hold(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A sensor that freezes: inside `mask` every sample repeats the last good one before it
    (a segment at the very start repeats the first good sample after it)."""
    x = _signal("x", x)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (x.shape[0],):
        raise ValueError(f"mask must be ({x.shape[0]},) bool, got {mask.shape}")
    if mask.all():
        raise ValueError("mask drops every sample; nothing to hold")
    idx = np.where(~mask, np.arange(x.shape[0]), 0)
    np.maximum.accumulate(idx, out=idx)
    first_good = int(np.argmax(~mask))
    idx[:first_good] = first_good
    return x[idx]


def remove_gaps(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Samples lost in transit: those inside `mask` are gone and the stream closes up (shorter output)."""
    x = _signal("x", x)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (x.shape[0],):
        raise ValueError(f"mask must be ({x.shape[0]},) bool, got {mask.shape}")
    return x[~mask]


def rate_mismatch(x: np.ndarray, error: float) -> np.ndarray:
    """A sensor clock running (1 + error) times the declared rate: the same time span yields
    (1 + error)·n samples that are read at the declared rate, so a tone at f Hz appears at
    f / (1 + error) Hz. Polyphase resampling (band-limited). error in (−0.5, 1]."""
    x = _signal("x", x)
    if not (math.isfinite(error) and -0.5 < error <= 1.0):
        raise ValueError(f"error must lie in (−0.5, 1], got {error}")
    ratio = Fraction(1.0 + error).limit_denominator(1000)
    if ratio == 1:
        return x.copy()
    return resample_poly(x, ratio.numerator, ratio.denominator, axis=0, padtype="line")


def rotation_matrix(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """3×3 rotation by `angle_deg` about `axis` (Rodrigues)."""
    axis = np.asarray(axis, dtype=np.float64)
    if axis.shape != (3,) or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) == 0:
        raise ValueError(f"axis must be a finite non-zero 3-vector, got {axis}")
    if not math.isfinite(angle_deg):
        raise ValueError(f"angle_deg must be finite, got {angle_deg}")
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = math.radians(angle_deg)
    return np.eye(3) + math.sin(a) * kx + (1 - math.cos(a)) * kx @ kx


def rotate_sensor(accel: np.ndarray, angle_deg: float, axis: np.ndarray) -> np.ndarray:
    """The accelerometer mounted turned by `angle_deg` about `axis`: accel (n, 3) → (n, 3)."""
    accel = _signal("accel", accel)
    if accel.ndim != 2 or accel.shape[1] != 3:
        raise ValueError(f"accel must be (n, 3), got {accel.shape}")
    return accel @ rotation_matrix(axis, angle_deg).T


def add_bias(x: np.ndarray, bias: float) -> np.ndarray:
    """A constant offset of `bias` (units of x) on every column."""
    x = _signal("x", x)
    if not math.isfinite(bias):
        raise ValueError(f"bias must be finite, got {bias}")
    return x + bias


def add_drift(x: np.ndarray, rate_hz: float, slope_per_s: float) -> np.ndarray:
    """An offset growing linearly from 0 at `slope_per_s` (units of x per second) on every column."""
    x = _signal("x", x)
    rate = _rate(rate_hz)
    if not math.isfinite(slope_per_s):
        raise ValueError(f"slope_per_s must be finite, got {slope_per_s}")
    ramp = slope_per_s * np.arange(x.shape[0]) / rate
    return x + (ramp[:, None] if x.ndim == 2 else ramp)


def scale_trajectory(trajectory: Trajectory, speed_factor: float = 1.0, force_factor: float = 1.0) -> Trajectory:
    """The same stroke pattern driven `speed_factor` times as fast and pressed `force_factor` times
    as hard (position scales with speed). Factors in (0, 100]."""
    for name, f in (("speed_factor", speed_factor), ("force_factor", force_factor)):
        if not (math.isfinite(f) and 0 < f <= 100):
            raise ValueError(f"{name} must lie in (0, 100], got {f}")
    return Trajectory(
        speed=trajectory.speed * speed_factor,
        force=trajectory.force * force_factor,
        position=trajectory.position * speed_factor,
        rate_hz=trajectory.rate_hz,
    )
