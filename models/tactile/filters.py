"""Butterworth filters in second-order-section form, and a stateful SOS filter for streams.

The paper band-passes acceleration 20–500 Hz after resampling to 1 kHz; 500 Hz is the
Nyquist frequency there, so the upper edge does nothing and the filter is really a
20 Hz high-pass. Designing it as a band-pass with an edge at Nyquist is ill-posed
(scipy rejects Wn = 1), so we design the high-pass directly. SOS form keeps low cut-offs
(20 Hz at 1 kHz, 25 Hz low-pass) numerically stable where (b, a) polynomials are not.
"""

from __future__ import annotations

import functools
import math
from typing import Literal

import numpy as np
from scipy import signal

try:  # the compiled kernel behind signal.sosfilt, which spends ≈ 2/3 of a 500-sample call on argument handling
    from scipy.signal._sosfilt import _sosfilt as _sos_kernel
except ImportError:  # another SciPy layout: the public function, same numbers
    _sos_kernel = None


def _check_design(cutoff_hz: float, rate_hz: float, order: int) -> None:
    if not (isinstance(rate_hz, (int, float, np.floating, np.integer)) and math.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz must be a finite number > 0, got {rate_hz!r}")
    if not (math.isfinite(cutoff_hz) and 0 < cutoff_hz < rate_hz / 2):
        raise ValueError(f"cutoff_hz must lie in (0, rate_hz/2 = {rate_hz / 2:g}) Hz, got {cutoff_hz!r}")
    if int(order) != order or not 1 <= order <= 12:
        raise ValueError(f"order must be an integer in [1, 12], got {order!r}")


@functools.lru_cache(maxsize=256)
def _butter(order: int, cutoff_hz: float, btype: str, rate_hz: float) -> np.ndarray:
    # Designing costs about a millisecond; every stream segment's preprocessor needs the same few filters.
    sos = signal.butter(order, cutoff_hz, btype=btype, fs=rate_hz, output="sos")
    sos.flags.writeable = False  # shared between callers
    return sos


@functools.lru_cache(maxsize=256)
def _steady_zi(sos_bytes: bytes, n_sections: int) -> np.ndarray:
    zi = signal.sosfilt_zi(np.frombuffer(sos_bytes).reshape(n_sections, 6))
    zi.flags.writeable = False
    return zi


def design_highpass(cutoff_hz: float, rate_hz: float, order: int) -> np.ndarray:
    """Butterworth high-pass, −3 dB at ``cutoff_hz``. Returns sos: (ceil(order/2), 6) float (designed once per
    set of arguments)."""
    _check_design(cutoff_hz, rate_hz, order)
    return _butter(int(order), float(cutoff_hz), "highpass", float(rate_hz)).copy()


def design_lowpass(cutoff_hz: float, rate_hz: float, order: int) -> np.ndarray:
    """Butterworth low-pass, −3 dB at ``cutoff_hz``. Returns sos: (ceil(order/2), 6) float (designed once per
    set of arguments)."""
    _check_design(cutoff_hz, rate_hz, order)
    return _butter(int(order), float(cutoff_hz), "lowpass", float(rate_hz)).copy()


class StatefulSOS:
    """An SOS filter that carries its state across blocks, so chunked == one-shot.

    ``process(x)`` takes x: (n,) or (n, k) (time along axis 0) and returns the same shape.
    The first block fixes the column count. ``init="zero"`` starts from rest (equals
    ``scipy.signal.sosfilt(sos, x, axis=0)``); ``init="steady"`` starts in the steady state
    for a constant input equal to the first sample (equals ``sosfilt`` with
    ``zi = sosfilt_zi(sos) * x[0]``), which avoids the start-up step of gravity in the
    accelerometer or of a non-zero force/speed.
    """

    def __init__(self, sos: np.ndarray, init: Literal["zero", "steady"] = "zero") -> None:
        sos = np.asarray(sos, dtype=np.float64)
        if sos.ndim != 2 or sos.shape[1] != 6 or sos.shape[0] < 1:
            raise ValueError(f"sos must have shape (n_sections, 6), got {sos.shape}")
        if init not in ("zero", "steady"):
            raise ValueError(f"init must be 'zero' or 'steady', got {init!r}")
        if not np.all(sos[:, 3] == 1.0):  # as scipy.signal.sosfilt requires: the kernel divides by nothing
            raise ValueError(f"every section's a0 (column 3) must be 1, got {sos[:, 3]}")
        self.sos = np.ascontiguousarray(sos)
        self.init = init
        # (k, n_sections, 2): the kernel's own layout, one row per column of x, kept between blocks
        self._zi: np.ndarray | None = None
        self._ndim: int | None = None
        self._cols: int | None = None

    def reset(self) -> None:
        """Forget the state; the next block starts a new stream."""
        self._zi = None
        self._ndim = None
        self._cols = None

    def process(self, x: np.ndarray) -> np.ndarray:
        """Filter the next block. x: (n,) or (n, k) float; returns float64 of the same shape."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim not in (1, 2):
            raise ValueError(f"x must have shape (n,) or (n, k), got {x.shape}")
        x2 = x[:, None] if x.ndim == 1 else x
        if self._ndim is None:
            self._ndim, self._cols = x.ndim, x2.shape[1]
        elif x.ndim != self._ndim or x2.shape[1] != self._cols:
            expected = "(n,)" if self._ndim == 1 else f"(n, {self._cols})"
            raise ValueError(f"x must keep the shape of the first block, {expected}; got {x.shape}")
        if x2.shape[0] == 0:
            return x.copy()
        if self._zi is None:
            zi = np.zeros((x2.shape[1], self.sos.shape[0], 2))
            if self.init == "steady":
                zi = _steady_zi(self.sos.tobytes(), self.sos.shape[0])[None, :, :] * x2[0][:, None, None]
            self._zi = np.ascontiguousarray(zi)
        y = np.array(x2.T, order="C")  # (k, n), filtered in place
        if _sos_kernel is not None:
            _sos_kernel(self.sos, y, self._zi)
        else:
            y, zi = signal.sosfilt(self.sos, y, axis=-1, zi=self._zi.transpose(1, 0, 2))
            self._zi = np.ascontiguousarray(zi.transpose(1, 0, 2))
        return y[0] if x.ndim == 1 else y.T
