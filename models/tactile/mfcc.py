"""Fast batched MFCC of 0.5 s windows, equal to librosa's per-window MFCC.

Per window (500 samples at 1 kHz, defaults):
  1. frames of ``frame_length`` = 25 samples every ``frame_hop`` = 12 (center=False) → 40 frames;
  2. periodic Hann window of 25, zero-padded to ``n_fft`` = 64, power spectrum (33 bins);
  3. Slaney mel filterbank (26 bands, 20–500 Hz, librosa's own matrix);
  4. ``power_to_db(ref=1, amin=1e-10, top_db)`` where the top_db floor is relative to the
     maximum of *this window* (as librosa does when called on one window);
  5. orthonormal DCT-II over the mel axis, first ``n_mfcc`` = 13 coefficients.

Steps 1–2 are one matmul against a precomputed windowed DFT matrix (cos | sin columns),
steps 3 and 5 are matmuls too; all matrices are cached per configuration. The arithmetic
is float32 (twice as fast as float64; the features are stored as float32 anyway): the
rounding, ~1e-7 of the window's peak power, lies far below the top_db = 80 dB floor, and
results stay within ~1e-6 relative of librosa's float64 MFCC.

librosa's ``stft`` always cuts frames of ``n_fft`` samples and places the short window in
their centre, so ``librosa.feature.mfcc(..., n_fft=64, win_length=25, center=False)`` on a
500-sample window gives 1 + (500 − 64) // 12 = 37 frames whose 25 effective samples start
at 19, 31, …. Our frames start at 0, 12, … (40 of them). ``librosa_mfcc`` therefore pads the
window with (n_fft − frame_length) // 2 zeros in front (and zeros behind) so that librosa's
effective frames are exactly ours; the zeros fall under the zero part of its window.
The power spectrum does not depend on where the frame sits inside the n_fft buffer.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
import scipy.fft
import scipy.signal

from models.tactile.config import TactileConfig
from models.tactile.windows import sliding_windows
from texture_library.channels import check_array

#: power_to_db floor and reference, as librosa.feature.mfcc uses them
AMIN = 1e-10
REF = 1.0


@lru_cache(maxsize=16)
def _matrices(
    rate_hz: float, frame_length: int, n_fft: int, n_mels: int, n_mfcc: int, fmin: float, fmax: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dft (frame_length, 2·n_bins) Hann-windowed cos|−sin, mel2 (2·n_bins, n_mels), dct (n_mels, n_mfcc)).

    mel2 is the mel filterbank stacked twice, so (frames @ dft)² @ mel2 = |rfft|² @ mel:
    the re² + im² sum rides in the mel matmul.
    """
    import librosa

    hann = scipy.signal.get_window("hann", frame_length, fftbins=True)  # periodic, as librosa
    n_bins = n_fft // 2 + 1
    phase = 2 * np.pi * np.outer(np.arange(frame_length), np.arange(n_bins)) / n_fft
    dft = np.concatenate([hann[:, None] * np.cos(phase), -hann[:, None] * np.sin(phase)], axis=1)
    # librosa's own (float32) filterbank, so results match its mfcc to rounding
    mel = librosa.filters.mel(sr=rate_hz, n_fft=n_fft, n_mels=n_mels, fmin=fmin, fmax=fmax).astype(np.float64)
    dct = scipy.fft.dct(np.eye(n_mels), type=2, norm="ortho", axis=0)[:n_mfcc]  # (n_mfcc, n_mels)
    mel2 = np.concatenate([mel.T, mel.T], axis=0)
    dft32, mel32, dct32 = (np.ascontiguousarray(m, dtype=np.float32) for m in (dft, mel2, dct.T))
    for m in (dft32, mel32, dct32):
        m.setflags(write=False)
    return dft32, mel32, dct32


@lru_cache(maxsize=16)
def _frame_index(window_length: int, frame_length: int, frame_hop: int) -> np.ndarray:
    """(n_frames, frame_length) sample indices of the center=False frames of one window.

    A gather into a contiguous array: the matmul needs contiguous frames anyway, and it is
    cheaper per call than building a strided view (serving featurises one window at a time).
    """
    index = sliding_windows(np.arange(window_length), frame_length, frame_hop)
    index = np.ascontiguousarray(index)
    index.setflags(write=False)
    return index


def mfcc_matrices(config: TactileConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cached (dft, mel2, dct) matrices for ``config`` (see ``_matrices``)."""
    c = config
    return _matrices(c.rate_hz, c.frame_length, c.n_fft, c.n_mels, c.n_mfcc, c.fmin, c.fmax)


def mfcc(windows: np.ndarray, config: TactileConfig) -> np.ndarray:
    """MFCC per window. windows: (n, window_length) float (DFT321 accel, m/s²) → (n, n_frames, n_mfcc) float32."""
    windows = check_array("windows", windows, (None, config.window_length), dtype=np.float32)
    dft, mel2, dct = mfcc_matrices(config)
    frames = windows[:, _frame_index(config.window_length, config.frame_length, config.frame_hop)]  # (n, F, L)
    spec = frames @ dft  # (n, F, 2B): re | im of the zero-padded rfft
    np.square(spec, out=spec)
    db = spec @ mel2  # (n, F, n_mels) mel power
    np.maximum(db, AMIN, out=db)
    np.log10(db, out=db)
    db *= 10.0
    db -= np.float32(10.0 * np.log10(max(AMIN, REF)))  # ref = 1 → 0 dB
    floor = db.max(axis=(1, 2), keepdims=True) - config.top_db  # per window, as librosa per call
    np.maximum(db, floor, out=db)
    return db @ dct


def librosa_mfcc(window: np.ndarray, config: TactileConfig) -> np.ndarray:
    """The reference: librosa.feature.mfcc on one window, framed like ``mfcc``.

    window: (window_length,) float → (n_frames, n_mfcc) float64.
    """
    import librosa

    window = check_array("windows", np.asarray(window)[None], (None, config.window_length))[0]
    c = config
    lpad = (c.n_fft - c.frame_length) // 2
    total = (c.n_frames - 1) * c.frame_hop + c.n_fft
    padded = np.zeros(total + max(0, len(window) + lpad - total))
    padded[lpad : lpad + len(window)] = window
    kwargs: dict[str, Any] = dict(
        sr=c.rate_hz,
        n_fft=c.n_fft,
        win_length=c.frame_length,
        hop_length=c.frame_hop,
        window="hann",
        center=False,
        n_mels=c.n_mels,
        fmin=c.fmin,
        fmax=c.fmax,
    )
    y = padded[:total]
    if c.top_db == 80.0:  # librosa.feature.mfcc's own power_to_db default
        out = librosa.feature.mfcc(y=y, n_mfcc=c.n_mfcc, **kwargs)
    else:  # mfcc() cannot pass top_db through; do its two steps explicitly
        mel_db = librosa.power_to_db(librosa.feature.melspectrogram(y=y, **kwargs), top_db=c.top_db)
        out = librosa.feature.mfcc(S=mel_db, n_mfcc=c.n_mfcc)
    return out.T
