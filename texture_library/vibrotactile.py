"""Vibrotactile detection threshold against frequency, and the spectral weights it gives.

The curve approximates the Pacinian (P) channel's U-shaped detection threshold for sinusoidal
vibration at the glabrous skin, Bolanowski, Gescheider, Verrillo & Checkosky, "Four channels mediate
the mechanical aspects of touch", J. Acoust. Soc. Am. 84(5):1680–1694, 1988 (after Verrillo 1963):
lowest near 250 Hz, about −20 dB re 1 µm of displacement, rising about 12 dB per octave on either
side. Below about 40 Hz the non-Pacinian channels set the threshold instead and the true curve
flattens; this one keeps rising, so it weighs 20–40 Hz somewhat less than people would. It is an
approximation for weighting over the 20–500 Hz band, not a model of any one person.
"""

from __future__ import annotations

import numpy as np

#: frequency of the lowest threshold, Hz
BEST_FREQUENCY_HZ = 250.0
#: threshold at BEST_FREQUENCY_HZ, dB re 1 µm peak displacement
MIN_THRESHOLD_DB = -20.0
#: rise of the Pacinian threshold per octave away from BEST_FREQUENCY_HZ, dB
SLOPE_DB_PER_OCTAVE = 12.0


def detection_threshold_db(freqs_hz: np.ndarray) -> np.ndarray:
    """(n,) detection threshold, dB re 1 µm displacement, at freqs_hz (n,) Hz > 0."""
    f = np.asarray(freqs_hz, float)
    if f.ndim != 1 or f.size == 0 or not np.all(np.isfinite(f)) or np.any(f <= 0):
        raise ValueError(f"freqs_hz must be a non-empty 1-D array of frequencies > 0 Hz, got {freqs_hz!r}")
    return MIN_THRESHOLD_DB + SLOPE_DB_PER_OCTAVE * np.abs(np.log2(f / BEST_FREQUENCY_HZ))


def sensitivity_weights(freqs_hz: np.ndarray) -> np.ndarray:
    """(n,) weights ∝ 1 / threshold (amplitude), summing to 1: an error at a frequency people detect at a
    smaller amplitude counts more (for `texture_library.spectrum.log_spectral_distance_db`)."""
    w = 10.0 ** (-detection_threshold_db(freqs_hz) / 20.0)
    return w / w.sum()
