"""One session's estimation, block batch in → window estimates out. Runs in a pool thread.

    admitted blocks ─▶ TactilePreprocessor.push (one call per channel batch) ─▶ take()
        ─▶ window_features (THE training function) ─▶ Predictor.predict
        ─▶ EMA smoothing ─▶ PerceptualIndex.query ─▶ HysteresisSelector

`SessionEstimator.process` is called with at most one job in flight per session (the session's
worker awaits each), so its state needs no lock; numpy and onnxruntime release the GIL for the
heavy parts. Latency stages are measured here with time.perf_counter_ns, the clock ingest stamps
blocks with.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.tactile.features import window_features
from models.tactile.preprocess import TactilePreprocessor, WindowBatch
from service.runtime import Runtime
from service.smoothing import ExponentialSmoother, SpreadConfidence
from service.stream import AdmittedBlock
from texture_library.nearest import HysteresisSelector, Match
from texture_library.recording import Channel


@dataclass(frozen=True)
class WindowEstimate:
    """One window's result. Ratings (4,) bipolar; times in s (sender clock); durations in ms.

    completed_by: seq of the block whose samples completed the window; ingest_ns: when that block
    arrived; started_ns: when its batch's computation began (perf_counter_ns).
    """

    index: int
    t_start_s: float
    t_end_s: float
    raw: np.ndarray
    smoothed: np.ndarray
    confidence: np.ndarray
    matches: list[Match]
    chosen: str
    completed_by: int
    ingest_ns: int
    started_ns: int
    features_ms: float
    model_ms: float
    lookup_ms: float


@dataclass(frozen=True)
class _Mark:
    covered: int
    seq: int
    arrived_ns: int


class SessionEstimator:
    """Per-session compute state: preprocessor (per stream segment), smoother, confidence, selector."""

    def __init__(self, runtime: Runtime, *, alpha: float, confidence_windows: int, top_k: int,
                 hysteresis_margin: float, hysteresis_hold: int, max_buffer_s: float) -> None:
        self.runtime = runtime
        self.config = runtime.tactile_config
        self.top_k = top_k
        self.max_buffer_s = max(max_buffer_s, 2 * self.config.window_s)
        self.smoother = ExponentialSmoother(alpha)
        self.confidence = SpreadConfidence(confidence_windows)
        self.selector = HysteresisSelector(hysteresis_margin, hysteresis_hold)
        self.segment = -1
        self.taken = 0  # windows taken from the current segment
        self.next_index = 0  # session-wide window counter
        self._pre: TactilePreprocessor | None = None
        self._marks: deque[_Mark] = deque()

    def process(self, blocks: Sequence[AdmittedBlock], visual: np.ndarray | None) -> tuple[list[WindowEstimate], int, int]:
        """Feed blocks (in order) and estimate every window they complete.

        visual: the model's visual input (D,) or None for a tactile model.
        returns (estimates, current segment, windows taken from it)
        """
        started = time.perf_counter_ns()
        out: list[WindowEstimate] = []
        for group in _by_segment(blocks):
            out += self._process_segment(group, visual, started)
        return out, self.segment, self.taken

    def _process_segment(self, group: list[AdmittedBlock], visual: np.ndarray | None, started: int) -> list[WindowEstimate]:
        first = group[0]
        if first.segment != self.segment:  # a gap in the stream: windows never straddle it
            self.segment, self.taken = first.segment, 0
            self._pre = TactilePreprocessor(self.config, max_buffer_s=self.max_buffer_s)
            self._marks.clear()
        assert self._pre is not None
        t0 = time.perf_counter_ns()
        self._pre.push(**_concatenate(group))
        self._marks.extend(_Mark(b.covered, b.seq, b.arrived_ns) for b in group)
        batch = self._pre.take()
        if len(batch) == 0:
            return []
        self.taken += len(batch)
        features = window_features(batch.accel, batch.speed, batch.force, self.config)
        t1 = time.perf_counter_ns()
        raw = self._predict(features, visual)
        t2 = time.perf_counter_ns()
        return self._lookup(batch, raw, first.origin_t0, started, (t1 - t0) / 1e6, (t2 - t1) / 1e6)

    def _predict(self, features: np.ndarray, visual: np.ndarray | None) -> np.ndarray:
        predictor = self.runtime.predictor
        tactile = features if predictor.needs_tactile else None
        vis = None
        if predictor.needs_visual:
            if visual is None:
                raise ValueError(f"model {self.runtime.model_name} needs a camera frame first")
            vis = np.repeat(visual[None, :], features.shape[0], axis=0)
        return predictor.predict(tactile, vis)

    def _lookup(self, batch: WindowBatch, raw: np.ndarray, origin_t0: float, started: int,
                features_ms: float, model_ms: float) -> list[WindowEstimate]:
        out = []
        window_s, length, rate = self.config.window_s, self.config.window_length, self.config.rate_hz
        for i in range(len(batch)):
            t0 = time.perf_counter_ns()
            smoothed = self.smoother.update(raw[i])
            confidence = self.confidence.update(raw[i])
            matches = self.runtime.index.query(smoothed, self.top_k)
            chosen = self.selector.update(self.runtime.index, smoothed)
            lookup_ms = (time.perf_counter_ns() - t0) / 1e6
            mark = self._completing_block(int(round(batch.t_start_s[i] * rate)) + length)
            t_start = origin_t0 + float(batch.t_start_s[i])
            out.append(WindowEstimate(
                index=self.next_index, t_start_s=t_start, t_end_s=t_start + window_s,
                raw=raw[i].astype(np.float64), smoothed=smoothed, confidence=confidence,
                matches=matches, chosen=chosen, completed_by=mark.seq, ingest_ns=mark.arrived_ns,
                started_ns=started, features_ms=features_ms, model_ms=model_ms, lookup_ms=lookup_ms,
            ))
            self.next_index += 1
        return out

    def _completing_block(self, end_sample: int) -> _Mark:
        """The first block whose arrival made `end_sample` samples available (older marks are dropped)."""
        while len(self._marks) > 1 and self._marks[0].covered < end_sample:
            self._marks.popleft()
        return self._marks[0]


def _by_segment(blocks: Sequence[AdmittedBlock]) -> list[list[AdmittedBlock]]:
    groups: list[list[AdmittedBlock]] = []
    for b in blocks:
        if groups and groups[-1][0].segment == b.segment:
            groups[-1].append(b)
        else:
            groups.append([b])
    return groups


def _concatenate(blocks: list[AdmittedBlock]) -> dict[str, Channel]:
    """One Channel per kind: the blocks' samples back to back (each kind is continuous on its own)."""
    parts: dict[str, list[Channel]] = {}
    for b in blocks:
        for kind, ch in b.channels.items():
            parts.setdefault(kind, []).append(ch)
    return {kind: Channel(np.concatenate([c.data for c in chs]), chs[0].rate_hz) for kind, chs in parts.items()}
