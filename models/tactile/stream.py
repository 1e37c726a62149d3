"""The tactile stream's rules, stated once: `StreamContract`.

A stream is a sequence of blocks, each holding some input channels (accel, force, speed,
position), each at its own constant rate. The contract says what may follow what, and what the
preprocessor will make of it:

- a channel keeps its rate and column count for the whole stream; a configuration with the
  friction group needs 3-column force (it reads the tangential force);
- each preprocessed *stream* (`STREAMS`: accel, speed, force) is fed by one input channel, the
  first of its `sources` that arrives (speed wins over position while neither has been seen;
  once position feeds speed, a speed channel is refused; once speed does, position is ignored);
- no stream may run more than `max_lag_s` seconds of input ahead of another (a channel that is
  never sent would otherwise buffer without bound);
- a block whose t0 is more than `gap_tolerance_s` after the expected continuation, or a whole sample or more
  before it (time going backwards), starts a new *segment* (the robot lost data or restarted its clock): windows
  never straddle the gap, and a clock running backwards is never merged into one stream. The
  expectation is per channel: where that channel's samples of the segment end (a 10 Hz channel in
  20 ms blocks, or each channel in its own block, is no gap); a channel the segment has not had yet
  may start anywhere within the segment's time so far;
- a block as it arrives (`admit`) spans at most `max_block_s` of stream time and completes at most
  `max_block_windows` windows (the cost of one block is bounded before it is accepted);
- the windows a segment has completed are counted exactly as `TactilePreprocessor` emits them
  (same resampled sample counts, same window starts), so whoever admits blocks knows how many
  windows they will produce without running the preprocessor.

The contract itself is pure: `advance(cursor, channels, t0)` (and `admit`) returns a new `StreamCursor` (or
raises ValueError naming the problem) and changes nothing. Service admission and
`TactilePreprocessor` both call it, so admission never accepts what the preprocessor refuses.

Adding a stream derived from an existing channel (e.g. tangential force from 3-column force)
is one more `StreamSpec` here plus its computation in the preprocessor; counting, lag and
window completion follow from the spec.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from models.tactile.config import TactileConfig
from models.tactile.resample import resampled_count
from texture_library.channels import CHANNEL_COLUMNS
from texture_library.recording import Channel

#: 2.5 blocks of 20 ms: sender clocks jitter (or drift per block) ahead of their sample count less than this, lost
#: blocks more
GAP_TOLERANCE_S = 0.05
#: how far back (in samples of its channel) a block may start before where its channel's samples end and still continue
#: them: less than one sample (a t0 rounded by its sender), never a whole one, which would place two samples at one time
BACKWARDS = 1.0 - 1e-6


@dataclass(frozen=True)
class StreamSpec:
    """One preprocessed stream: its name and the input channels that may feed it (first seen wins).

    held_back: input channels whose first resampled sample(s) produce output only once the next
    arrives (speed derived from position needs two positions) → {channel: samples held}.
    """

    name: str
    sources: tuple[str, ...]
    held_back: Mapping[str, int] = field(default_factory=dict)


#: the streams a window holds, in the order lag messages name them
STREAMS: tuple[StreamSpec, ...] = (
    StreamSpec("accel", ("accel",)),
    StreamSpec("speed", ("speed", "position"), {"position": 1}),
    StreamSpec("force", ("force",)),
)
#: allowed column counts per input channel (1 means shape (n,))
INPUT_COLUMNS: Mapping[str, tuple[int, ...]] = CHANNEL_COLUMNS
#: input channel → the stream it can feed
_FEEDS: Mapping[str, str] = {kind: spec.name for spec in STREAMS for kind in spec.sources}


@dataclass(frozen=True)
class StreamCursor:
    """Where a stream stands: what it has fixed and how much input its current segment holds.

    rates / columns: per input channel, fixed by its first block; sources: stream → the input
    channel feeding it; samples: input samples per channel in the current segment (the mappings are
    never changed once a cursor holds them: a new cursor gets new ones); segment: index
    of the current segment (−1 before the first block); origin_t0: sender time (s) of the
    segment's first sample; next_t0: where the last block's fastest channel ended (s), a block of every
    channel continues there; ends: per input channel, where its samples of the segment end (s).
    """

    rates: Mapping[str, float] = field(default_factory=dict)
    columns: Mapping[str, int] = field(default_factory=dict)
    sources: Mapping[str, str] = field(default_factory=dict)
    samples: Mapping[str, int] = field(default_factory=dict)
    segment: int = -1
    origin_t0: float = 0.0
    next_t0: float | None = None
    ends: Mapping[str, float] = field(default_factory=dict)
    windows: int = 0  # complete windows of the current segment (set by the contract)

    def restarted(self) -> StreamCursor:
        """The same stream with its segment broken: the next block starts a new one (after a failure)."""
        return replace(self, samples={}, next_t0=math.nan, ends={}, windows=0)


@dataclass(frozen=True)
class Advance:
    """What one block does to the stream: the cursor after it, the channels the preprocessor uses (ignored
    ones dropped), whether it starts a segment, and the segment's completed windows before and after it."""

    cursor: StreamCursor
    channels: dict[str, Channel]
    new_segment: bool
    windows_before: int
    windows_after: int
    span_s: float  # the block's longest channel, s

    @property
    def windows_added(self) -> int:
        return self.windows_after - self.windows_before


class StreamContract:
    """The rules of one tactile stream for a feature configuration (see the module docstring).

    max_lag_s / max_block_s / max_block_windows: None disables that bound (offline use).
    """

    def __init__(
        self,
        config: TactileConfig | None = None,
        *,
        max_lag_s: float | None = 5.0,
        gap_tolerance_s: float = GAP_TOLERANCE_S,
        max_block_s: float | None = None,
        max_block_windows: int | None = None,
        skip_s: float = 0.0,
    ) -> None:
        self.config = config if config is not None else TactileConfig()
        for name, value in (("max_lag_s", max_lag_s), ("max_block_s", max_block_s)):
            if value is not None and not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number of seconds > 0 or None, got {value!r}")
        if not (isinstance(gap_tolerance_s, (int, float)) and math.isfinite(gap_tolerance_s) and gap_tolerance_s >= 0):
            raise ValueError(f"gap_tolerance_s must be a finite number ≥ 0 s, got {gap_tolerance_s!r}")
        if max_block_windows is not None and (
            isinstance(max_block_windows, bool) or not isinstance(max_block_windows, int) or max_block_windows < 1
        ):
            raise ValueError(f"max_block_windows must be an integer ≥ 1 or None, got {max_block_windows!r}")
        if not (isinstance(skip_s, (int, float)) and math.isfinite(skip_s) and skip_s >= 0):
            raise ValueError(f"skip_s must be a finite number ≥ 0 s, got {skip_s!r}")
        self.max_lag_s = max_lag_s
        self.gap_tolerance_s = float(gap_tolerance_s)
        self.max_block_s = max_block_s
        self.max_block_windows = max_block_windows
        self.skip = int(round(skip_s * self.config.rate_hz))
        self._length, self._hop, self._rate = self.config.window_length, self.config.hop_length, self.config.rate_hz

    def start(self) -> StreamCursor:
        return StreamCursor()

    # ---- one block ---------------------------------------------------------------------------------
    def advance(
        self, cursor: StreamCursor, channels: Mapping[str, Channel], t0: float | None = None, *, bounded: bool = False
    ) -> Advance:
        """The stream after a block of `channels` (canonical units) starting at sender time t0 (s).

        t0=None: the block continues the current segment (the preprocessor, which sees no clock).
        ValueError names what the block contradicts; the cursor given is never changed.
        """
        for kind in channels:
            if kind not in _FEEDS:
                raise ValueError(
                    f"unknown channel(s) {sorted(k for k in channels if k not in _FEEDS)}; "
                    f"expected some of {sorted(INPUT_COLUMNS)}"
                )
        sources = cursor.sources
        used: dict[str, Channel] = {}
        for spec in STREAMS:
            chosen = sources.get(spec.name)
            for kind in spec.sources:
                if kind not in channels:
                    continue
                if chosen is None:  # the first of the spec's sources present in this block feeds the stream
                    chosen = kind
                    sources = {**sources, spec.name: kind}
                if kind == chosen:
                    used[kind] = channels[kind]
                elif spec.sources.index(kind) < spec.sources.index(chosen):  # a preferred source after a fallback
                    raise ValueError(
                        f"{kind}: got a {kind} channel after {spec.name} was already being derived from {chosen}"
                    )
        rates, columns = cursor.rates, cursor.columns
        span = 0.0
        step = (0.0, 0.0)  # (rate, stream time) of the block's fastest channel
        counts = []
        for kind, ch in used.items():
            data = ch.data
            shape = np.shape(data)
            cols = 1 if len(shape) == 1 else (shape[1] if len(shape) == 2 else -1)
            if cols not in INPUT_COLUMNS[kind]:
                allowed = " or ".join("(n,)" if c == 1 else f"(n, {c})" for c in INPUT_COLUMNS[kind])
                raise ValueError(f"{kind}: shape must be {allowed}, got {shape}")
            if kind == "force" and cols == 1 and self.config.force_columns > 1:
                raise ValueError(
                    "force: the friction features need 3-column force (tangential x, tangential y, "
                    "normal); this stream sends the normal force only — use a model without the "
                    "friction group"
                )
            rate = float(ch.rate_hz)
            known = rates.get(kind)
            if known is None:
                rates, columns = {**rates, kind: rate}, {**columns, kind: cols}
            elif rate != known:
                raise ValueError(f"{kind}: rate changed from {known:g} Hz to {rate:g} Hz mid-stream")
            elif cols != columns[kind]:
                raise ValueError(f"{kind}: column count changed from {columns[kind]} to {cols} mid-stream")
            counts.append((kind, shape[0]))
            span = max(span, shape[0] / rate)
            step = max(step, (rate, shape[0] / rate))
        if bounded and self.max_block_s is not None and span > self.max_block_s + 1e-9:
            raise ValueError(f"a block spans at most {self.max_block_s:g} s of stream time, got {span:g} s")
        new_segment = t0 is not None and not self._continues(cursor, counts, t0)
        before = 0 if new_segment else cursor.windows
        samples = {} if new_segment else dict(cursor.samples)
        for kind, n in counts:
            samples[kind] = samples.get(kind, 0) + n
        # A block of every channel continues where its fastest channel ends: that sample count says the block's length
        # finely, while a slow channel's (one 10 Hz sample in a 20 ms block "spans" 0.1 s) would not.
        ends = {} if new_segment else dict(cursor.ends)
        if t0 is None:
            segment, origin_t0, next_t0 = cursor.segment, cursor.origin_t0, cursor.next_t0
        else:
            ends.update({kind: t0 + n / rates[kind] for kind, n in counts if n})
            if new_segment:
                segment, origin_t0, next_t0 = cursor.segment + 1, t0, t0 + step[1]
            else:
                segment, origin_t0, next_t0 = cursor.segment, cursor.origin_t0, t0 + step[1]
        after = StreamCursor(rates, columns, sources, samples, segment, origin_t0, next_t0, ends)
        self._check_lag(after)
        windows = self.windows_in(self.covered(after))
        object.__setattr__(after, "windows", windows)  # frozen: set once, here
        if bounded and self.max_block_windows is not None and windows - before > self.max_block_windows:
            raise ValueError(
                f"this block would complete {windows - before} windows; a block may complete at most "
                f"{self.max_block_windows} (send every channel in every block, in shorter blocks)"
            )
        return Advance(after, used, new_segment, before, windows, span)

    def _continues(self, cursor: StreamCursor, counts: list[tuple[str, int]], t0: float) -> bool:
        """Whether a block at t0 carrying `counts` (channel, samples) continues the cursor's segment: each channel
        the segment has had from less than one of its samples before where its samples end to gap_tolerance_s after
        (time going backwards by a sample or more is a new segment, never merged), a channel it has not had within
        the segment's time so far."""
        if cursor.next_t0 is None or math.isnan(cursor.next_t0):  # the first block, or a broken segment
            return False
        tol = self.gap_tolerance_s
        latest = max(cursor.ends.values(), default=cursor.next_t0)
        for kind, n in counts:
            end = cursor.ends.get(kind)
            if end is None:
                if not cursor.origin_t0 - tol <= t0 <= latest + tol:
                    return False
            elif n and not -BACKWARDS * (1.0 / cursor.rates[kind]) < t0 - end <= tol:
                return False
        return True

    def admit(self, cursor: StreamCursor, channels: Mapping[str, Channel], t0: float) -> Advance:
        """`advance` for one block as it arrives, with its cost bounded before it is accepted: at most
        max_block_s of stream time and max_block_windows completed windows. (The preprocessor, fed
        many admitted blocks at once, checks only the stream's rules.)"""
        return self.advance(cursor, channels, t0, bounded=True)

    def _check_lag(self, cursor: StreamCursor) -> None:
        if self.max_lag_s is None:
            return
        seconds = {spec.name: self._seconds(cursor, spec) for spec in STREAMS}
        lead = max(seconds.values())
        behind = [name for name, s in seconds.items() if lead - s > self.max_lag_s]
        if behind:
            raise ValueError(
                f"{', '.join(behind)} lag(s) the other channels by more than {self.max_lag_s:g} s; "
                "is every channel being sent?"
            )

    @staticmethod
    def _seconds(cursor: StreamCursor, spec: StreamSpec) -> float:
        kind = cursor.sources.get(spec.name)
        return 0.0 if kind is None else cursor.samples.get(kind, 0) / cursor.rates[kind]

    # ---- windows -----------------------------------------------------------------------------------
    def stream_samples(self, cursor: StreamCursor, spec: StreamSpec) -> int:
        """Samples at the config rate the preprocessor has produced for `spec` in the current segment."""
        kind = cursor.sources.get(spec.name)
        if kind is None:
            return 0
        n = resampled_count(cursor.samples.get(kind, 0), cursor.rates[kind], self._rate)
        held = spec.held_back.get(kind, 0)
        return n if n > held else 0

    def covered(self, cursor: StreamCursor) -> int:
        """Samples at the config rate that every stream of the current segment has reached."""
        return min(self.stream_samples(cursor, spec) for spec in STREAMS)

    def windows_in(self, covered: int) -> int:
        """Complete windows among `covered` samples (windows start at skip + i·hop)."""
        length, hop = self._length, self._hop
        return 0 if covered < self.skip + length else 1 + (covered - self.skip - length) // hop

    def windows(self, cursor: StreamCursor) -> int:
        """Windows of the current segment whose samples have all arrived."""
        return cursor.windows
