"""Exact power spectra of vibration models and the log-spectral distance between two of them.

A vibration model at one operating point (speed, force) is an ARMA filter driven by white noise of
variance σ²: its one-sided power spectral density is

    S(f) = 2 σ² g² |B(e^{jω})|² / (f_s |A(e^{jω})|²),   ω = 2π f / f_s,

with B the MA polynomial, g its gain and A the AR polynomial, interpolated at that point exactly as
the renderer interpolates them (`texture_library.synthesis.interpolate`). Units: (m/s²)²/Hz.

The distance between two models is defined once: `spectral_distance_db`, the RMS dB difference over
[20, 500) Hz, averaged over the operating points. The Nyquist bin (500 Hz at 1 kHz) is left out, as the
selection's `band_mask` leaves it out: nearly every HaTT MA polynomial has a zero there, where its PSD
sits about 60 dB below the next bin and reaches `PSD_FLOOR`, so that one bin would weigh as much as a
wide stretch of the band. `pooled_spectral_distance_db` is the variant that pools the squared
differences of every operating point and frequency into one RMS, reported beside it.
"""

from __future__ import annotations

import numpy as np

from texture_library.synthesis import interpolate
from texture_library.vibration import VibrationModel

#: the band the log-spectral distance covers, Hz, low end in, high end out (the tactile features' band;
#: 500 Hz is Nyquist at 1 kHz)
BAND_HZ = (20.0, 500.0)
#: operating points (speed mm/s, normal force N) a model-to-model distance averages over
OPERATING_POINTS: tuple[tuple[float, float], ...] = tuple((s, f) for s in (50.0, 100.0, 200.0) for f in (0.5, 1.0, 2.0))
#: floor under a spectrum before taking logs, (m/s²)²/Hz: a silent model (zero variance) is very far, not -inf
PSD_FLOOR = 1e-12


def band_frequencies(n: int = 240, band_hz: tuple[float, float] = BAND_HZ) -> np.ndarray:
    """(n,) evenly spaced frequencies over [low, high), Hz: the low end included, the high end (Nyquist) not.
    The default grid: 20, 22, …, 498 Hz."""
    if n < 2:
        raise ValueError(f"n must be ≥ 2 frequencies, got {n}")
    lo, hi = band_hz
    if not 0.0 <= lo < hi:
        raise ValueError(f"band_hz must satisfy 0 ≤ low < high, got {band_hz}")
    return np.linspace(lo, hi, n, endpoint=False)


def arma_psd(model: VibrationModel, speeds: np.ndarray, forces: np.ndarray, freqs_hz: np.ndarray) -> np.ndarray:
    """One-sided PSD of `model` at each operating point.

    speeds: (k,) mm/s; forces: (k,) N; freqs_hz: (n,) Hz, at most model.rate_hz / 2.
    Returns (k, n) (m/s²)²/Hz.
    """
    speeds, forces = np.atleast_1d(np.asarray(speeds, float)), np.atleast_1d(np.asarray(forces, float))
    freqs = np.asarray(freqs_hz, float)
    if speeds.ndim != 1 or speeds.shape != forces.shape:
        raise ValueError(f"speeds and forces must be 1-D of equal length, got {speeds.shape} and {forces.shape}")
    if freqs.ndim != 1 or freqs.size == 0:
        raise ValueError(f"freqs_hz must be a non-empty 1-D array, got shape {freqs.shape}")
    if freqs.min() < 0.0 or freqs.max() > model.rate_hz / 2:
        raise ValueError(f"freqs_hz must lie in [0, {model.rate_hz / 2:g}] Hz, got [{freqs.min():g}, {freqs.max():g}]")
    params = interpolate(model, speeds, forces)
    z = np.exp(-2j * np.pi * freqs / model.rate_hz)  # z⁻¹ on the unit circle

    def response(coeffs: np.ndarray) -> np.ndarray:  # (k, order+1) → (k, n): Σ c_i z⁻ⁱ
        powers = z[None, :] ** np.arange(coeffs.shape[1])[:, None]
        return coeffs @ powers

    b, a = response(params["ma"]), response(params["ar"])
    scale = 2.0 * params["variance"] * params["gain"] ** 2 / model.rate_hz
    return scale[:, None] * np.abs(b) ** 2 / np.abs(a) ** 2


def log_spectral_distance_db(psd_a: np.ndarray, psd_b: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """RMS difference of 10·log10 spectra over the last axis, dB.

    psd_a, psd_b: (..., n) (m/s²)²/Hz on the same frequencies; weights: (n,) ≥ 0 (e.g. a perceptual weighting),
    None for equal weights. Returns (...) dB.
    """
    a, b = np.asarray(psd_a, float), np.asarray(psd_b, float)
    if a.shape != b.shape:
        raise ValueError(f"the two spectra must have the same shape, got {a.shape} and {b.shape}")
    if np.any(a < 0) or np.any(b < 0):
        raise ValueError("power spectra must be ≥ 0")
    diff = 10.0 * (np.log10(np.maximum(a, PSD_FLOOR)) - np.log10(np.maximum(b, PSD_FLOOR)))
    if weights is None:
        return np.sqrt(np.mean(diff**2, axis=-1))
    w = np.asarray(weights, float)
    if w.shape != a.shape[-1:] or np.any(w < 0) or w.sum() <= 0:
        raise ValueError(f"weights must be (n,) = {a.shape[-1:]} non-negative with a positive sum")
    return np.sqrt((diff**2 * w).sum(axis=-1) / w.sum())


def model_spectra(
    model: VibrationModel,
    freqs_hz: np.ndarray | None = None,
    points: tuple[tuple[float, float], ...] = OPERATING_POINTS,
) -> np.ndarray:
    """(len(points), n) PSDs of `model` at the operating points (the default band grid when freqs_hz is None)."""
    freqs = band_frequencies() if freqs_hz is None else freqs_hz
    speeds, forces = np.array(points, float).T
    return arma_psd(model, speeds, forces, freqs)


def spectral_distance_db(
    a: VibrationModel,
    b: VibrationModel,
    freqs_hz: np.ndarray | None = None,
    points: tuple[tuple[float, float], ...] = OPERATING_POINTS,
    weights: np.ndarray | None = None,
) -> float:
    """Log-spectral distance between two models, dB: the RMS over the band's frequencies (`band_frequencies`,
    Nyquist left out) at each operating point, then the mean over the points."""
    return float(
        np.mean(
            log_spectral_distance_db(model_spectra(a, freqs_hz, points), model_spectra(b, freqs_hz, points), weights)
        )
    )


def pooled_spectral_distance_db(
    a: VibrationModel,
    b: VibrationModel,
    freqs_hz: np.ndarray | None = None,
    points: tuple[tuple[float, float], ...] = OPERATING_POINTS,
) -> float:
    """The pooled variant, dB: one RMS over every (operating point, frequency) pair. Never below
    `spectral_distance_db` (a quadratic mean is at least the arithmetic mean of the per-point RMS), equal
    to it when every point is equally far."""
    return float(pooled_distance_db(model_spectra(a, freqs_hz, points), model_spectra(b, freqs_hz, points)))


def pooled_distance_db(spectra_a: np.ndarray, spectra_b: np.ndarray) -> np.ndarray:
    """RMS of the 10·log10 differences over the last two axes (operating points, frequencies), dB.

    spectra_a, spectra_b: (..., k, n) (m/s²)²/Hz. Returns (...) dB."""
    a, b = np.asarray(spectra_a, float), np.asarray(spectra_b, float)
    if a.ndim < 2:
        raise ValueError(f"spectra must be (..., points, frequencies), got shape {a.shape}")
    flat = a.shape[:-2] + (a.shape[-2] * a.shape[-1],)
    return log_spectral_distance_db(a.reshape(flat), b.reshape(b.shape[:-2] + (-1,)))
