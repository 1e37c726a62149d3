"""DFT band features (the paper's DFT ablation).

For one DFT321 window s (N samples at rate r; 500 at 1 kHz): multiply by a periodic Hann
window (so a tone does not leak into far bands), take |rfft| (bins at k·r/N Hz, 2 Hz apart
at the defaults), split [fmin, fmax] into ``dft_bins`` equal-width bands (edges
linspace(fmin, fmax, dft_bins + 1); a bin belongs to band b when edge_b ≤ f < edge_{b+1},
the last band also takes f = fmax), and per band

    value_b = log10(mean_{k in band b} |S_k| + 1e-10)      (|S_k| in m/s² · samples)

→ ``dft_bins`` values (32 bands of 15 Hz over 20–500 Hz by default), followed by the 6
speed/force statistics (features.py).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.fft
import scipy.signal

from models.tactile.config import TactileConfig

LOG_FLOOR = 1e-10


@lru_cache(maxsize=16)
def band_matrix(rate_hz: float, n: int, fmin: float, fmax: float, n_bands: int) -> np.ndarray:
    """(n//2 + 1, n_bands) averaging matrix: column b is 1/count over the bins of band b."""
    freqs = np.arange(n // 2 + 1) * rate_hz / n
    edges = np.linspace(fmin, fmax, n_bands + 1)
    band = np.searchsorted(edges, freqs, side="right") - 1
    band[freqs == fmax] = n_bands - 1  # last band is closed on the right
    inside = (band >= 0) & (band < n_bands)
    m = np.zeros((freqs.size, n_bands))
    m[np.flatnonzero(inside), band[inside]] = 1.0
    counts = m.sum(axis=0)
    if np.any(counts == 0):
        raise ValueError(f"DFT bands {np.flatnonzero(counts == 0).tolist()} hold no bin; use fewer dft_bins")
    m /= counts
    m.setflags(write=False)
    return m


def band_edges(config: TactileConfig) -> np.ndarray:
    """Band edges in Hz, (dft_bins + 1,)."""
    return np.linspace(config.fmin, config.fmax, config.dft_bins + 1)


def dft_features(signal: np.ndarray, config: TactileConfig) -> np.ndarray:
    """Log band-mean magnitudes. signal: (n, window_length) float, m/s² → (n, dft_bins) float64."""
    signal = np.asarray(signal, dtype=np.float64)
    if signal.ndim != 2 or signal.shape[1] != config.window_length:
        raise ValueError(f"signal must have shape (n, {config.window_length}), got {signal.shape}")
    n = config.window_length
    hann = scipy.signal.get_window("hann", n, fftbins=True)
    mag = np.abs(scipy.fft.rfft(signal * hann, axis=-1))
    bands = mag @ band_matrix(config.rate_hz, n, config.fmin, config.fmax, config.dft_bins)
    return np.log10(bands + LOG_FLOOR)
