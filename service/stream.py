"""Admission of sample blocks into a session's stream, on the event loop, before any processing.

Blocks are checked here against what the session has already accepted — the same rules the
TactilePreprocessor enforces (constant rate and column count per channel, speed not after
position-derived speed) plus a bound on how far one channel may run ahead of another — so a
refused block leaves nothing behind and the preprocessor, fed later in bulk, never refuses.
Bookkeeping is in samples per stream; it says when a window is complete (by stream time), which
lets the session push many blocks at once into the preprocessor (its cost is per call, not per
sample) instead of one call per 20 ms block.

A block whose t0 is off the expected continuation by more than GAP_TOLERANCE_S starts a new
*segment* (the robot lost data or restarted its clock): windows never straddle the gap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drivers.blocks import SampleBlock
from models.tactile.config import TactileConfig
from texture_library.channels import UNIT_SCALE
from texture_library.recording import Channel

GAP_TOLERANCE_S = 0.05  # 2.5 blocks of 20 ms: sender clocks jitter less than this, lost blocks more
STREAMS = ("accel", "force", "motion")  # motion: speed, or position to derive it from


@dataclass(frozen=True)
class AdmittedBlock:
    """A block accepted into the stream: canonical channels plus what the pipeline needs to time it.

    origin_t0: sender time (s) of the segment's first sample; covered: samples of the slowest
    stream at the config rate after this block, counted from the segment start;
    arrived_ns: time.perf_counter_ns() when its body had been read.
    """

    seq: int
    segment: int
    origin_t0: float
    channels: dict[str, Channel]
    covered: int
    arrived_ns: int


def canonical_channels(block: SampleBlock) -> dict[str, Channel]:
    """The block's channels converted from their units to canonical ones (m/s², N, mm/s, mm), float64."""
    out = {}
    for kind, c in block.channels.items():
        scale = UNIT_SCALE[kind][c.units]
        data = c.data.astype(np.float64)
        if scale != 1.0:
            data *= scale
        out[kind] = Channel(data, c.rate_hz)
    return out


class StreamAdmission:
    """Per-session stream bookkeeping (event-loop side). `admit` refuses with ValueError and changes nothing then."""

    def __init__(self, config: TactileConfig, max_lag_s: float) -> None:
        self.config = config
        self.max_lag_s = max_lag_s
        self.rates: dict[str, float] = {}
        self.columns: dict[str, int] = {}
        self.motion: str | None = None  # "speed" or "position", fixed by the first block carrying either
        self.segment = 0
        self.origin_t0 = 0.0  # sender time of the current segment's first sample, s
        self._next_t0: float | None = None
        self._samples = dict.fromkeys(STREAMS, 0)  # input samples per stream in this segment
        self.windows_taken = 0  # windows of this segment the pipeline has taken

    # ---- admission -------------------------------------------------------------------------------
    def admit(self, block: SampleBlock, arrived_ns: int) -> AdmittedBlock:
        channels = canonical_channels(block)
        motion = self._motion_for(channels)
        if motion == "speed":
            channels.pop("position", None)  # the preprocessor ignores position once speed is used
        for kind, ch in channels.items():
            cols = 1 if ch.data.ndim == 1 else ch.data.shape[1]
            if kind in self.rates and ch.rate_hz != self.rates[kind]:
                raise ValueError(f"{kind}: rate changed from {self.rates[kind]:g} Hz to {ch.rate_hz:g} Hz mid-stream")
            if kind in self.columns and cols != self.columns[kind]:
                raise ValueError(f"{kind}: column count changed from {self.columns[kind]} to {cols} mid-stream")
        new_segment = self._is_gap(block.t0)
        samples = dict.fromkeys(STREAMS, 0) if new_segment else dict(self._samples)
        rates = {**self.rates, **{k: c.rate_hz for k, c in channels.items()}}
        for kind, ch in channels.items():
            samples["motion" if kind in ("speed", "position") else kind] += ch.data.shape[0]
        self._check_lag(samples, rates, motion)
        # accepted: commit
        if new_segment:
            if self._next_t0 is not None:  # not the very first block
                self.segment += 1
            self.origin_t0 = block.t0
            self.windows_taken = 0
        span = max(ch.data.shape[0] / ch.rate_hz for ch in channels.values())
        self._next_t0 = block.t0 + span
        self.motion = motion
        self.rates = rates
        for kind, ch in channels.items():
            self.columns.setdefault(kind, 1 if ch.data.ndim == 1 else ch.data.shape[1])
        self._samples = samples
        return AdmittedBlock(block.seq, self.segment, self.origin_t0, channels, self.covered(), arrived_ns)

    def _motion_for(self, channels: dict[str, Channel]) -> str | None:
        if self.motion == "position" and "speed" in channels:
            raise ValueError("speed: got a speed channel after speed was already being derived from position")
        if self.motion is None and ("speed" in channels or "position" in channels):
            return "speed" if "speed" in channels else "position"
        return self.motion

    def _is_gap(self, t0: float) -> bool:
        return self._next_t0 is None or not abs(t0 - self._next_t0) <= GAP_TOLERANCE_S

    def _rate_of(self, stream: str, rates: dict[str, float], motion: str | None) -> float | None:
        kind = motion if stream == "motion" else stream
        return rates.get(kind) if kind else None

    def _check_lag(self, samples: dict[str, int], rates: dict[str, float], motion: str | None) -> None:
        seconds = {}
        for stream in STREAMS:
            rate = self._rate_of(stream, rates, motion)
            seconds[stream] = 0.0 if rate is None else samples[stream] / rate
        lead = max(seconds.values())
        behind = [s if s != "motion" else "speed/position" for s in STREAMS if lead - seconds[s] > self.max_lag_s]
        if behind:
            raise ValueError(
                f"{', '.join(behind)} lag(s) the other channels by more than {self.max_lag_s:g} s; is every channel being sent?"
            )

    # ---- windows ---------------------------------------------------------------------------------
    def covered(self) -> int:
        """Samples at the config rate that every stream of this segment has reached."""
        counts = []
        for stream in STREAMS:
            rate = self._rate_of(stream, self.rates, self.motion)
            if rate is None:
                return 0
            counts.append(math.floor(self._samples[stream] * self.config.rate_hz / rate + 1e-6))
        return min(counts)

    def windows_complete(self) -> int:
        """Windows of this segment whose samples have all arrived."""
        n, length, hop = self.covered(), self.config.window_length, self.config.hop_length
        return 0 if n < length else 1 + (n - length) // hop

    def backlog(self) -> int:
        """Complete windows not yet taken by the pipeline (0 when it keeps up)."""
        return max(0, self.windows_complete() - self.windows_taken)

    def break_segment(self) -> None:
        """Make the next block start a new segment (after a failure left the pipeline's state unknown)."""
        self._next_t0 = float("nan")  # every t0 is a gap from NaN
        self._samples = dict.fromkeys(STREAMS, 0)
        self.windows_taken = 0

    def note_taken(self, segment: int, taken: int) -> None:
        """The pipeline has taken `taken` windows of `segment` (ignored for a segment already left)."""
        if segment == self.segment:
            self.windows_taken = max(self.windows_taken, taken)
