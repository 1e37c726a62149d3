"""The one streaming tactile preprocessor: raw sensor blocks in, aligned 1 kHz windows out.

Per channel (each at its own rate; all channels start at the same instant):
  accel (n, 3) m/s²        → resample to rate_hz → Butterworth high-pass per axis (20 Hz, order 4)
  force (n,) or (n, 3) N   → normal force (1-D as is; 3 columns → column 2, the normal)
                             → resample → low-pass (25 Hz, order 2)
  speed (n,) mm/s          → resample → low-pass
  position (n,)/(n, 2) mm  → (only without a speed channel) resample → speed = |Δposition|·rate_hz
                             (mm/s; the first sample takes the second's speed) → low-pass
Derived columns, only when the configuration's extra groups need them (else shapes as above):
  "spatial"  → accel windows (L, 6): columns 3–5 are the same axes high-passed at
               spatial_highpass_hz (order 2) instead, for the spatial spectrum (slow bumps in)
  "friction" → force windows (L, 2): column 0 the normal force, column 1 the tangential
               magnitude √(fx² + fy²) of 3-column force, resampled and low-passed alike;
               1-column force is refused (ValueError): it holds no friction
Every filter keeps its state across blocks and starts in steady state for its first sample
(no start-up step from gravity or a resting force), so any split of a stream into blocks
gives the same samples as one block. Offline features are this class run over a recording.

The stream's rules (constant rates and columns, which channel feeds speed, how far one channel
may lag another, how many windows are complete) are `models.tactile.stream.StreamContract`'s;
``push`` asks it before changing any state, so a refused block leaves the preprocessor as it was.

Windows of ``window_length`` samples start at ``skip + i·hop_length`` (1 kHz sample
indices from the stream start) and are emitted once all three streams reach their end.
Buffers keep only what the next window needs.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from models.tactile.config import TactileConfig
from models.tactile.filters import StatefulSOS, design_highpass, design_lowpass
from models.tactile.resample import Resampler
from models.tactile.stream import STREAMS as STREAM_SPECS
from models.tactile.stream import StreamContract
from models.tactile.windows import sliding_windows
from texture_library.channels import check_channel
from texture_library.recording import Channel

STREAMS = tuple(spec.name for spec in STREAM_SPECS)  # ("accel", "speed", "force")


@dataclass(frozen=True)
class TactileWindow:
    """One aligned window: accel (L, 3) m/s² high-passed; speed (L,) mm/s and force (L,) N low-passed
    (accel (L, 6) and force (L, 2) with derived columns, see the module docstring)."""

    index: int
    t_start_s: float
    accel: np.ndarray
    speed: np.ndarray
    force: np.ndarray


@dataclass(frozen=True)
class WindowBatch:
    """Windows stacked: index (m,), t_start_s (m,), accel (m, L, 3), speed (m, L), force (m, L)
    (accel (m, L, 6) and force (m, L, 2) with derived columns, see the module docstring)."""

    index: np.ndarray
    t_start_s: np.ndarray
    accel: np.ndarray
    speed: np.ndarray
    force: np.ndarray

    def __len__(self) -> int:
        return int(self.index.shape[0])


def channel_array(name: str, channel: object) -> tuple[np.ndarray, float]:
    """Validate a pushed channel → (data float64 (n,) or (n, k), n ≥ 0, rate Hz) by texture_library.channels'
    one validator (canonical units, an empty block allowed); ValueError naming ``name``."""
    if not isinstance(channel, Channel):
        raise ValueError(f"{name} must be a texture_library.recording.Channel, got {type(channel).__name__}")
    data, rate, _ = check_channel(name, channel.data, channel.rate_hz, copy=False, allow_empty=True)
    return data, rate


class PositionSpeed:
    """Stateful speed from position: |p_k − p_{k−1}|·rate_hz (mm/s) for p: (n,) or (n, 2) mm.

    The very first sample has no predecessor; it is held back until the second arrives and
    then takes the second sample's speed, so the output count equals the input count.
    """

    def __init__(self, rate_hz: float) -> None:
        self.rate_hz = float(rate_hz)
        self._last: np.ndarray | None = None
        self._first_pending = False
        self._last_speed = 0.0

    def process(self, p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, dtype=np.float64)
        p2 = p[:, None] if p.ndim == 1 else p
        if p2.shape[0] == 0:
            return np.empty(0)
        if self._last is None:
            self._last, self._first_pending = p2[0], True
            p2 = p2[1:]
            if p2.shape[0] == 0:
                return np.empty(0)
        seq = np.concatenate([self._last[None], p2])
        speed = np.sqrt(np.sum(np.diff(seq, axis=0) ** 2, axis=1)) * self.rate_hz
        self._last = p2[-1]
        self._last_speed = float(speed[-1])
        if self._first_pending:
            self._first_pending = False
            speed = np.concatenate([speed[:1], speed])
        return speed

    def flush(self, extra: int = 0) -> np.ndarray:
        """End of stream: a lone first sample still held back (speed 0), then ``extra`` samples
        holding the last speed (the tail a held position would otherwise turn into a stop)."""
        head = np.zeros(1) if self._first_pending else np.empty(0)
        self._first_pending = False
        return np.concatenate([head, np.full(extra, self._last_speed)])


class TactilePreprocessor:
    """Streaming preprocessor; see the module docstring.

    skip_s: drop windows starting before this time (s from the stream start; filters still
    run from the start). max_buffer_s: if a stream runs this far ahead of another (e.g. a
    channel that is never sent), ``push`` raises ValueError instead of buffering without
    bound; None disables the check (offline use).
    """

    def __init__(
        self,
        config: TactileConfig | None = None,
        skip_s: float = 0.0,
        max_buffer_s: float | None = 60.0,
        contract: StreamContract | None = None,
    ) -> None:
        if contract is None:
            config = config if config is not None else TactileConfig()
            if max_buffer_s is not None and not (math.isfinite(max_buffer_s) and max_buffer_s >= 2 * config.window_s):
                raise ValueError(
                    f"max_buffer_s must be ≥ 2·window_s = {2 * config.window_s} s or None, got {max_buffer_s!r}"
                )
            contract = StreamContract(config, max_lag_s=max_buffer_s, skip_s=skip_s)
        self.contract = contract
        self.config = c = contract.config
        self.skip = contract.skip
        self._cursor = contract.start()
        self._resamplers: dict[str, Resampler] = {}
        self._filters = {
            "accel": StatefulSOS(design_highpass(c.accel_highpass_hz, c.rate_hz, c.accel_filter_order), "steady"),
            "speed": StatefulSOS(design_lowpass(c.lowpass_hz, c.rate_hz, c.lowpass_order), "steady"),
            "force": StatefulSOS(design_lowpass(c.lowpass_hz, c.rate_hz, c.lowpass_order), "steady"),
        }
        # the spatial group's accel: same axes, high-passed only against gravity
        self._spatial = (
            StatefulSOS(design_highpass(c.spatial_highpass_hz, c.rate_hz, 2), "steady")
            if "spatial" in c.extra_groups
            else None
        )
        self._position_speed = PositionSpeed(c.rate_hz)
        force_shape = (0,) if c.force_columns == 1 else (0, c.force_columns)
        self._buf: dict[str, np.ndarray] = {
            "accel": np.empty((0, c.accel_columns)),
            "speed": np.empty(0),
            "force": np.empty(force_shape),
        }
        self._n: dict[str, int] = dict.fromkeys(STREAMS, 0)  # samples produced per stream
        self._buf_start = 0  # global 1 kHz index of each buffer's first sample
        self._next = 0  # index of the next window to emit
        self._flushed = False

    @property
    def speed_source(self) -> str | None:
        """ "speed" or "position": the channel feeding speed, fixed by the first block with either."""
        return self._cursor.sources.get("speed")

    # ---- input ---------------------------------------------------------------------------
    def push(
        self,
        accel: Channel | None = None,
        force: Channel | None = None,
        speed: Channel | None = None,
        position: Channel | None = None,
    ) -> int:
        """Feed the next block of any channels; returns how many complete windows are now ready.

        A speed channel wins over position: once speed has been seen, position blocks are
        ignored; once position has been used, a speed block is an error.
        """
        if self._flushed:
            raise ValueError("push: the stream was flushed; start a new TactilePreprocessor")
        given = {"accel": accel, "force": force, "speed": speed, "position": position}
        checked = {name: Channel(*channel_array(name, ch)) for name, ch in given.items() if ch is not None}
        advance = self.contract.advance(self._cursor, checked)  # validates everything before state changes
        self._cursor = advance.cursor
        for name, ch in advance.channels.items():
            data = ch.data
            if name not in self._resamplers:
                self._resamplers[name] = Resampler(ch.rate_hz, self.config.rate_hz)
            if name == "force" and data.ndim == 2:
                # (tangential x, tangential y, normal) → normal [, tangential magnitude]
                data = (
                    data[:, 2]
                    if self.config.force_columns == 1
                    else np.stack([data[:, 2], np.hypot(data[:, 0], data[:, 1])], axis=1)
                )
            self._feed(name, self._resamplers[name].process(data))
        self._trim()
        return self.n_ready

    def flush(self) -> int:
        """End of stream; returns windows ready. No push may follow.

        Emits each channel's resampler tail (its last value held up to the channel's
        duration, see ``Resampler.flush``; for position, the last speed held), so a recording
        of d seconds yields floor((d − skip_s − window_s) / hop_s) + 1 windows."""
        if not self._flushed:
            self._flushed = True
            for name, resampler in self._resamplers.items():
                self._feed(name, resampler.flush(), flush=True)
        return self.n_ready

    def _feed(self, name: str, out: np.ndarray, flush: bool = False) -> None:
        """Resampled samples of one channel → derived stream → filter → buffer (flush: a resampler tail)."""
        stream = name
        if name == "position":
            if flush:
                speed = self._position_speed.flush(extra=out.shape[0])
            else:
                speed = self._position_speed.process(out)
            out, stream = speed, "speed"
        filtered = self._filters[stream].process(out)
        if stream == "accel" and self._spatial is not None:
            filtered = np.concatenate([filtered, self._spatial.process(out)], axis=1)
        self._append(stream, filtered)

    def _append(self, stream: str, samples: np.ndarray) -> None:
        if samples.shape[0]:
            self._buf[stream] = np.concatenate([self._buf[stream], samples])
            self._n[stream] += samples.shape[0]

    # ---- output --------------------------------------------------------------------------
    def _start(self, index: int) -> int:
        return self.skip + index * self.config.hop_length

    @property
    def n_ready(self) -> int:
        """Complete windows buffered and not yet emitted."""
        available = min(self._n.values())
        first = self._start(self._next)
        length, hop = self.config.window_length, self.config.hop_length
        return 0 if available < first + length else 1 + (available - first - length) // hop

    def take(self) -> WindowBatch:
        """All ready windows, stacked (copies), and forget them."""
        m = self.n_ready
        c = self.config
        idx = np.arange(self._next, self._next + m)
        starts = self.skip + idx * c.hop_length
        if m == 0:
            L = c.window_length
            force = np.empty((0, L)) if c.force_columns == 1 else np.empty((0, L, c.force_columns))
            return WindowBatch(idx, starts / c.rate_hz, np.empty((0, L, c.accel_columns)), np.empty((0, L)), force)
        lo = int(starts[0]) - self._buf_start
        span = slice(lo, lo + (m - 1) * c.hop_length + c.window_length)
        views = {s: sliding_windows(self._buf[s][span], c.window_length, c.hop_length, axis=0) for s in STREAMS}
        batch = WindowBatch(
            index=idx,
            t_start_s=starts / c.rate_hz,
            accel=np.ascontiguousarray(np.swapaxes(views["accel"], 1, 2)),  # (m, 3, L) → (m, L, 3)
            speed=views["speed"].copy(),
            force=views["force"].copy()
            if views["force"].ndim == 2
            else np.ascontiguousarray(np.swapaxes(views["force"], 1, 2)),
        )
        self._next += m
        self._trim()
        return batch

    def windows(self) -> Iterator[TactileWindow]:
        """Yield every complete window not yet emitted, in order."""
        while self.n_ready:
            yield self.take_one()

    def take_one(self) -> TactileWindow:
        """The next ready window (ValueError if none is complete)."""
        if not self.n_ready:
            raise ValueError("no complete window is ready")
        c = self.config
        start = self._start(self._next)
        sl = slice(start - self._buf_start, start - self._buf_start + c.window_length)
        win = TactileWindow(
            index=self._next,
            t_start_s=start / c.rate_hz,
            accel=self._buf["accel"][sl].copy(),
            speed=self._buf["speed"][sl].copy(),
            force=self._buf["force"][sl].copy(),
        )
        self._next += 1
        self._trim()
        return win

    def _trim(self) -> None:
        """Drop samples before the next window's start (never past what every stream has produced)."""
        keep_from = min(self._start(self._next), *self._n.values())
        drop = keep_from - self._buf_start
        if drop > 0:
            for s in STREAMS:
                self._buf[s] = self._buf[s][drop:]
            self._buf_start = keep_from

    @property
    def buffered_samples(self) -> int:
        """Largest buffer length (samples), for monitoring the bound."""
        return max(b.shape[0] for b in self._buf.values())
