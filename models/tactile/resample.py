"""Streaming resampling to the feature rate (1 kHz) by anti-aliased linear interpolation.

Output sample k sits at t_k = k / rate_out seconds after the stream's first input sample
(input sample i sits at i / rate_in). It is the linear interpolation between the two input
samples around t_k, so output k is emitted as soon as input reaches t_k. When
rate_in > rate_out, the input first passes a stateful Butterworth low-pass (order 8,
−3 dB at 0.45·rate_out, started in steady state) against aliasing; its group delay
(a few input samples) is not compensated — streaming cannot look ahead. Equal rates pass
through untouched. ``resample`` is the stateful ``Resampler`` run over a whole array, so
offline and streaming give the same samples.
"""

from __future__ import annotations

import math

import numpy as np

from models.tactile.filters import StatefulSOS, design_lowpass
from texture_library.channels import check_rate

#: anti-alias cut-off as a fraction of the output rate, and its order
ANTIALIAS_FRACTION = 0.45
ANTIALIAS_ORDER = 8


def resampled_count(n_in: int, rate_in: float, rate_out: float) -> int:
    """Output samples a Resampler has emitted after n_in input samples (before flush): every k with
    k·rate_in/rate_out ≤ n_in − 1 (the same float arithmetic `Resampler.process` uses), n_in at equal rates."""
    if n_in <= 0:
        return 0
    if rate_in == rate_out:
        return n_in
    last = n_in - 1
    k = int(math.floor(last * rate_out / rate_in)) + 1
    while k > 0 and float(k - 1) * rate_in / rate_out > last:
        k -= 1
    while float(k) * rate_in / rate_out <= last:
        k += 1
    return k


class Resampler:
    """Stateful resampler: feed blocks (n,) or (n, k) at rate_in, get blocks at rate_out."""

    def __init__(self, rate_in: float, rate_out: float = 1000.0) -> None:
        self.rate_in = check_rate(rate_in, "rate_in")
        self.rate_out = check_rate(rate_out, "rate_out")
        self._aa: StatefulSOS | None = None
        if self.rate_in > self.rate_out:
            sos = design_lowpass(ANTIALIAS_FRACTION * self.rate_out, self.rate_in, ANTIALIAS_ORDER)
            self._aa = StatefulSOS(sos, init="steady")
        self._n_in = 0  # input samples consumed
        self._k = 0  # next output index
        self._last: np.ndarray | None = None  # last input sample (after anti-aliasing), (k,) or ()
        self._shape_tail: tuple[int, ...] | None = None
        self._flushed = False

    @property
    def n_out(self) -> int:
        """Output samples emitted so far."""
        return self._k

    def process(self, x: np.ndarray) -> np.ndarray:
        """Resample the next block. x: (n,) or (n, k) float at rate_in → (m,) or (m, k) at rate_out."""
        if self._flushed:
            raise ValueError("x: this stream was flushed; start a new Resampler")
        x = np.asarray(x, dtype=np.float64)
        if x.ndim not in (1, 2):
            raise ValueError(f"x must have shape (n,) or (n, k), got {x.shape}")
        if self._shape_tail is None:
            self._shape_tail = x.shape[1:]
        elif x.shape[1:] != self._shape_tail:
            raise ValueError(f"x must keep the columns of the first block {self._shape_tail}, got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"x has {int(np.count_nonzero(~np.isfinite(x)))} NaN or Inf value(s)")
        if x.shape[0] == 0:
            return x.copy()
        if self.rate_in == self.rate_out:
            self._n_in += x.shape[0]
            self._k += x.shape[0]
            self._last = x[-1].copy()
            return x.copy()
        if self._aa is not None:
            x = self._aa.process(x)
        if self._last is None:
            buf, base = x, 0
        else:
            buf, base = np.concatenate([self._last[None], x]), self._n_in - 1
        self._n_in += x.shape[0]
        # positions in input samples of every output now due (resampled_count states which are)
        ks = np.arange(
            self._k, max(self._k, resampled_count(self._n_in, self.rate_in, self.rate_out)), dtype=np.float64
        )
        pos = ks * self.rate_in / self.rate_out
        self._last = buf[-1].copy()
        if pos.size == 0:
            return np.empty((0,) + x.shape[1:])
        self._k += pos.size
        i0 = np.floor(pos).astype(np.int64)
        frac = pos - i0
        i0 -= base
        i1 = np.minimum(i0 + 1, buf.shape[0] - 1)
        if buf.ndim == 2:
            frac = frac[:, None]
        return buf[i0] + frac * (buf[i1] - buf[i0])

    def flush(self) -> np.ndarray:
        """End of stream: emit the outputs with t_k < n_in / rate_in that lie past the last input
        sample, holding its value (at most ceil(rate_out / rate_in) − 1 samples). Then the output
        count is ceil(n_in · rate_out / rate_in), i.e. the input duration at rate_out.
        (m,) or (m, k); no further blocks may follow."""
        extra = 0
        if self._last is not None:
            # outputs still due: n_in − 1 < k·rate_in/rate_out < n_in (all earlier ones were emitted)
            k_hi = int(math.ceil(self._n_in * self.rate_out / self.rate_in)) + 1
            ks = np.arange(self._k, max(self._k, k_hi), dtype=np.float64)
            extra = int(np.count_nonzero(ks * self.rate_in / self.rate_out < self._n_in))
        self._flushed = True
        if extra == 0 or self._last is None:
            return np.empty((0,) + (self._shape_tail or ()))
        self._k += extra
        return np.repeat(self._last[None], extra, axis=0)


def resample(x: np.ndarray, rate_in: float, rate_out: float = 1000.0, flush: bool = False) -> np.ndarray:
    """Resample a whole signal x: (n,) or (n, k) from rate_in to rate_out (Hz), as a stream would.

    flush=True also emits the held tail (``Resampler.flush``), so the output spans the input's duration.
    """
    r = Resampler(rate_in, rate_out)
    y = r.process(x)
    return np.concatenate([y, r.flush()]) if flush else y
