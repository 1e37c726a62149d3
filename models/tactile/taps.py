"""Hardness features of tap transients: how hard, how fast and how high a surface rings when tapped.

A tool of mass m tapping a surface of contact stiffness k at speed v bounces off a spring:
the peak deceleration grows like v·√(k/m), the contact rings at √(k/m)/2π and softer, lossier
surfaces damp it faster. HaTT ships 9–15 recorded taps per texture (100 ms at 1 kHz, one axis,
each with its tap speed); the synthetic world renders taps by that model
(texture_library.procedural.tap_transients). Per tap (baseline = the trace's median removed):

  peak          max |a|, m/s²
  decay         time from the peak until the envelope max|a[t:]| first falls below peak/e, s
                (the trace's length after the peak if it never does)
  centroid      power-weighted mean frequency of the ringing: the trace from the peak over
                max(MIN_TAP_SAMPLES, 4 × decay) samples (Hann window, zero-padded to ≥ 64), Hz

and over the set of taps, medians (robust to a missed or double tap):

  tap_log_peak_per_speed   log10 median(peak / tap speed), log10((m/s²)/(mm/s))
  tap_log_decay_s          log10 median(decay), log10 s
  tap_centroid_hz          median(centroid), Hz

``tap_features`` is the one function that turns taps into features: datasets call it on each
texture's TapSet; the service calls it on the tap blocks a robot sends (drivers.blocks.TapBlock,
service.live_session), so a served model sees the features it was trained on.
"""

from __future__ import annotations

import numpy as np

TAP_NAMES: tuple[str, ...] = ("tap_log_peak_per_speed", "tap_log_decay_s", "tap_centroid_hz")
#: tap speeds below this (mm/s) are too slow to normalise a peak by
MIN_TAP_SPEED = 0.5
MIN_TAP_SAMPLES = 16


def tap_features(speeds: np.ndarray, accel: np.ndarray, rate_hz: float = 1000.0) -> np.ndarray:
    """speeds: (k,) tap speeds, mm/s; accel: (k, n) acceleration of each tap, m/s², at rate_hz →
    (3,) float64 in TAP_NAMES order. ValueError on shapes, non-finite values, too-short taps, or
    no tap faster than MIN_TAP_SPEED."""
    speeds = np.asarray(speeds, dtype=np.float64)
    accel = np.asarray(accel, dtype=np.float64)
    if speeds.ndim != 1 or accel.ndim != 2 or accel.shape[0] != speeds.shape[0] or speeds.shape[0] == 0:
        raise ValueError(f"taps: need speeds (k,) and accel (k, n) with k ≥ 1, got {speeds.shape} and {accel.shape}")
    if accel.shape[1] < MIN_TAP_SAMPLES:
        raise ValueError(f"taps: each tap needs at least {MIN_TAP_SAMPLES} samples, got {accel.shape[1]}")
    if not (np.all(np.isfinite(speeds)) and np.all(np.isfinite(accel))):
        raise ValueError("taps: contain NaN or Inf")
    if not (isinstance(rate_hz, (int, float)) and np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"taps: rate_hz must be a finite number > 0, got {rate_hz!r}")
    keep = speeds >= MIN_TAP_SPEED
    if not keep.any():
        raise ValueError(f"taps: no tap is faster than {MIN_TAP_SPEED} mm/s (speeds {speeds.tolist()})")
    speeds, accel = speeds[keep], accel[keep]
    a = np.abs(accel - np.median(accel, axis=1, keepdims=True))
    k, n = a.shape
    peak_at = np.argmax(a, axis=1)
    peak = a[np.arange(k), peak_at]
    # envelope: the largest |a| still to come; it can only fall
    envelope = np.maximum.accumulate(a[:, ::-1], axis=1)[:, ::-1]
    decay = np.empty(k)
    centroid = np.empty(k)
    for i in range(k):
        after = envelope[i, peak_at[i] :] < peak[i] / np.e
        steps = int(np.argmax(after)) if after.any() else n - peak_at[i]
        decay[i] = max(steps, 1) / rate_hz
        # the ringing only: after a few time constants a fast-decaying tap is sensor noise
        start = min(peak_at[i], n - MIN_TAP_SAMPLES)
        tail = accel[i, start : start + max(MIN_TAP_SAMPLES, 4 * steps)] - np.median(accel[i])
        power = np.abs(np.fft.rfft(tail * np.hanning(tail.size), n=max(64, tail.size))) ** 2
        freqs = np.fft.rfftfreq(max(64, tail.size), 1.0 / rate_hz)
        centroid[i] = float(power @ freqs / power.sum()) if power.sum() > 0 else 0.0
    peak_per_speed = np.maximum(peak / speeds, 1e-12)
    return np.array([np.log10(np.median(peak_per_speed)), np.log10(np.median(decay)), np.median(centroid)])


#: a tap a learnt model keeps is the local mean of this many recorded taps nearest in speed (itself included) …
TAP_NEIGHBOURS = 3
#: … each shifted by up to this many samples to line up with it
TAP_MAX_LAG = 3


def local_mean_taps(
    speeds: np.ndarray, accel: np.ndarray, neighbours: int = TAP_NEIGHBOURS, max_lag: int = TAP_MAX_LAG
) -> np.ndarray:
    """(k, n) m/s²: each recorded tap replaced by the mean of the `neighbours` taps nearest to it in log speed
    (itself included), each divided by its own speed, shifted by the lag (|lag| ≤ max_lag samples, zero-filled)
    that best lines it up with the tap, and scaled back to the tap's speed.

    A recorded tap carries its sensor's noise and its own jitter; the renderer plays the stored tap nearest in
    speed, scaled by speed, so a stored tap that is the local mean of its neighbours is nearer to the surface's
    next tap than any one recording is. Chosen on textures outside the online study's report (its tuning set:
    rendered taps against held-out ones, minus the spread between the held-out ones, HaTT / synthetic: +0.94 /
    −0.24 dB for the recordings themselves, −1.65 / −0.13 for this mean). speeds: (k,) mm/s, > 0; accel: (k, n)."""
    s = np.asarray(speeds, float)
    a = np.asarray(accel, float)
    if s.ndim != 1 or a.ndim != 2 or a.shape[0] != s.size:
        raise ValueError(f"taps need speeds (k,) and accel (k, n), got {s.shape} and {a.shape}")
    if not np.all(s > 0) or not np.all(np.isfinite(a)):
        raise ValueError("tap speeds must be > 0 mm/s and the traces finite")
    if neighbours < 1 or max_lag < 0:
        raise ValueError(f"neighbours must be ≥ 1 and max_lag ≥ 0, got {neighbours} and {max_lag}")
    unit = a / s[:, None]
    log_s = np.log(s)
    n = a.shape[1]
    out = np.empty_like(a)
    for i in range(s.size):
        near = np.argsort(np.abs(log_s - log_s[i]), kind="stable")[:neighbours]
        lined: list[np.ndarray] = []
        for j in near:
            shifts = [_shifted(unit[j], lag, n) for lag in range(-max_lag, max_lag + 1)]
            lined.append(max(shifts, key=lambda x: float(np.dot(x, unit[i]))))
        out[i] = np.mean(lined, axis=0) * s[i]
    return out


def _shifted(x: np.ndarray, lag: int, n: int) -> np.ndarray:
    """x delayed by lag samples (advanced when negative), zero-filled, length n."""
    y = np.zeros(n)
    if lag >= 0:
        y[lag:] = x[: n - lag]
    else:
        y[:lag] = x[-lag:]
    return y
