"""1-D discrete wavelet transform features (the paper's DWT ablation), numpy only.

Transform: an orthogonal Daubechies wavelet (``db1`` = Haar … ``db4`` = 8 taps, pywt's
naming) applied as a multi-level analysis filter bank. Each level extends the current
approximation a (length N) symmetrically by L − 1 samples on each side (half-sample
symmetric, numpy's ``pad(mode="symmetric")``, pywt's default mode), convolves it with the
decomposition low-pass h and high-pass g = (−1)^k h[L−1−k], and keeps every second output:

    a'[i] = Σ_k h[k] · ext[2i + 1 + (L−1) − k],   i = 0 … floor((N + L − 1) / 2) − 1

(the full convolution sampled at odd indices; pywt's output length for this mode).

At 1 kHz detail level j covers ≈ [500 / 2^j, 500 / 2^(j−1)] Hz: d1 250–500, d2 125–250,
d3 62.5–125, d4 31–62, d5 16–31 Hz, and the final approximation a_J the rest below.

Features of one window, per band in the order d1, …, dJ, aJ, three statistics each:
    log_energy = log10(Σ c² + 1e-12)     (c in m/s²)
    mean_abs   = mean |c|
    std        = standard deviation of c (population, ddof = 0)
→ 3·(J + 1) values (18 at J = 5), followed by the 6 speed/force statistics (features.py).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from models.tactile.config import TactileConfig

#: wavelets offered (pywt's names: dbN has N vanishing moments and 2N taps)
WAVELETS: tuple[str, ...] = ("db1", "db2", "db3", "db4")


@lru_cache(maxsize=8)
def daubechies_dec_lo(n_moments: int) -> np.ndarray:
    """Decomposition low-pass taps of the Daubechies wavelet dbN (pywt's ``dec_lo``), (2N,).

    Built by spectral factorisation rather than typed in: |H(ω)|² = cos^{2N}(ω/2)·P(sin²(ω/2))
    with P(y) = Σ_{k<N} C(N−1+k, k) yᵏ; each root y of P gives a pair z, 1/z of
    z² − (2 − 4y) z + 1; the minimum-phase filter keeps the roots inside the unit circle,
    times N zeros at z = −1, scaled to Σh = √2. pywt's dec_lo is that filter reversed.
    """
    if not 1 <= n_moments <= 10:
        raise ValueError(f"n_moments must lie in [1, 10], got {n_moments}")
    q = [math.comb(n_moments - 1 + k, k) for k in range(n_moments)]
    zeros: list[complex] = [-1.0] * n_moments
    for y in np.roots(q[::-1]) if n_moments > 1 else []:
        pair = np.roots([1.0, -(2.0 - 4.0 * y), 1.0])
        zeros.append(pair[np.argmin(np.abs(pair))])
    h = np.real(np.poly(zeros))
    h *= np.sqrt(2.0) / h.sum()
    out = h[::-1].copy()
    out.setflags(write=False)
    return out


LOG_FLOOR = 1e-12


def wavelet_filters(wavelet: str) -> tuple[np.ndarray, np.ndarray]:
    """(dec_lo, dec_hi) taps, each (2N,), of wavelet "dbN", signs as pywt: dec_hi = reverse((−1)^k · dec_lo[k])."""
    if wavelet not in WAVELETS:
        raise ValueError(f"wavelet must be one of {list(WAVELETS)}, got {wavelet!r}")
    lo = daubechies_dec_lo(int(wavelet[2:]))
    # pywt: dec_hi = reversed(rec_hi), rec_hi[k] = (−1)^k · dec_lo[k]
    hi = ((-1.0) ** np.arange(lo.size) * lo)[::-1]
    return lo, hi


def dwt_step(x: np.ndarray, wavelet: str) -> tuple[np.ndarray, np.ndarray]:
    """One analysis level along the last axis. x: (..., N) → (approx, detail), each (..., floor((N+L−1)/2))."""
    lo, hi = wavelet_filters(wavelet)
    taps = lo.size
    x = np.asarray(x, dtype=np.float64)
    if x.shape[-1] < taps - 1:
        raise ValueError(f"x has {x.shape[-1]} samples; {wavelet} needs at least {taps - 1} per level")
    pad = [(0, 0)] * (x.ndim - 1) + [(taps - 1, taps - 1)]
    ext = np.pad(x, pad, mode="symmetric")
    # full convolution at odd output indices: out[i] = Σ_k f[k] · ext[2i + 1 + (L−1) − k]
    # → windows of ext starting at 2i + 1 (length L) dotted with the reversed filter
    frames = sliding_window_view(ext, taps, axis=-1)[..., 1 : x.shape[-1] + taps - 1 : 2, :]
    n_out = (x.shape[-1] + taps - 1) // 2
    frames = frames[..., :n_out, :]
    return frames @ lo[::-1], frames @ hi[::-1]


def wavedec(x: np.ndarray, wavelet: str, levels: int) -> list[np.ndarray]:
    """Multi-level DWT along the last axis: [d1, d2, …, dJ, aJ] (finest detail first)."""
    if levels < 1:
        raise ValueError(f"levels must be ≥ 1, got {levels}")
    out: list[np.ndarray] = []
    approx = np.asarray(x, dtype=np.float64)
    for _ in range(levels):
        approx, detail = dwt_step(approx, wavelet)
        out.append(detail)
    out.append(approx)
    return out


def dwt_features(signal: np.ndarray, config: TactileConfig) -> np.ndarray:
    """DWT statistics. signal: (n, window_length) float, m/s² (DFT321 accel) → (n, 3·(dwt_levels+1)) float64."""
    signal = np.asarray(signal, dtype=np.float64)
    if signal.ndim != 2 or signal.shape[1] != config.window_length:
        raise ValueError(f"signal must have shape (n, {config.window_length}), got {signal.shape}")
    feats = []
    for c in wavedec(signal, config.dwt_wavelet, config.dwt_levels):
        feats.append(np.log10(np.sum(c * c, axis=-1) + LOG_FLOOR))
        feats.append(np.mean(np.abs(c), axis=-1))
        feats.append(np.std(c, axis=-1))
    return np.stack(feats, axis=-1)
