"""Window estimation, batched across sessions. Runs in a pool thread.

    per session:  admitted blocks ─▶ TactilePreprocessor.push (one call per channel and segment) ─▶ take()
    the batch:    window_features (THE training function) on every session's windows at once
                  ─▶ Predictor.predict, one call
    per session:  EMA smoothing ─▶ PerceptualIndex.query ─▶ HysteresisSelector, window by window

Batching matters on a busy service: window_features and onnxruntime cost far less per window
in a batch, and a pool thread that holds the GIL for fewer, larger steps leaves the event loop
more of it. A session is in at most one job at a time (the batcher sees to it), so its
estimator needs no lock. Latency stages are measured with time.perf_counter_ns, the clock
ingest stamps blocks with.
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

    def prepare(self, blocks: Sequence[AdmittedBlock], visual: np.ndarray | None) -> list["PreparedWindows"]:
        """Push the blocks (in order) and take every window they complete, per stream segment."""
        out = []
        for group in _by_segment(blocks):
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
                continue
            self.taken += len(batch)
            length, rate = self.config.window_length, self.config.rate_hz
            marks = [self._completing_block(int(round(t * rate)) + length) for t in batch.t_start_s]
            out.append(PreparedWindows(self, batch, first.origin_t0, marks, visual, time.perf_counter_ns() - t0))
        return out

    def finish(self, prepared: "PreparedWindows", raw: np.ndarray, started_ns: int, features_ms: float,
               model_ms: float) -> list[WindowEstimate]:
        """Smoothing, confidence and the library lookup of prepared windows, in order. raw: (n, 4)."""
        out = []
        window_s = self.config.window_s
        for i, mark in enumerate(prepared.marks):
            t0 = time.perf_counter_ns()
            smoothed = self.smoother.update(raw[i])
            confidence = self.confidence.update(raw[i])
            matches = self.runtime.index.query(smoothed, self.top_k)
            chosen = self.selector.update(self.runtime.index, smoothed)
            lookup_ms = (time.perf_counter_ns() - t0) / 1e6
            t_start = prepared.origin_t0 + float(prepared.batch.t_start_s[i])
            out.append(WindowEstimate(
                index=self.next_index, t_start_s=t_start, t_end_s=t_start + window_s,
                raw=raw[i].astype(np.float64), smoothed=smoothed, confidence=confidence,
                matches=matches, chosen=chosen, completed_by=mark.seq, ingest_ns=mark.arrived_ns,
                started_ns=started_ns, features_ms=features_ms, model_ms=model_ms, lookup_ms=lookup_ms,
            ))
            self.next_index += 1
        return out

    def _completing_block(self, end_sample: int) -> _Mark:
        """The first block whose arrival made `end_sample` samples available (older marks are dropped)."""
        while len(self._marks) > 1 and self._marks[0].covered < end_sample:
            self._marks.popleft()
        return self._marks[0]


@dataclass(frozen=True)
class PreparedWindows:
    """One session segment's windows after preprocessing, waiting for features and the model.

    marks: the completing block of each window; visual: the model's visual input (D,) or None;
    preprocess_ns: time its push + take took.
    """

    estimator: SessionEstimator
    batch: WindowBatch
    origin_t0: float
    marks: list[_Mark]
    visual: np.ndarray | None
    preprocess_ns: int


@dataclass(frozen=True)
class SessionJob:
    """A session's share of a batch: its estimator, its pending blocks, its visual input (or None)."""

    estimator: SessionEstimator
    blocks: list[AdmittedBlock]
    visual: np.ndarray | None


@dataclass(frozen=True)
class SessionResult:
    """What a job produced for one session: its window estimates and stream position, or the error
    that stopped it (the other sessions of the batch are unaffected)."""

    estimates: list[WindowEstimate]
    segment: int
    taken: int
    error: Exception | None = None


def estimate_batch(runtime: Runtime, jobs: Sequence[SessionJob]) -> list[SessionResult]:
    """Estimate every window the jobs' blocks complete: per-session preprocessing, one window_features
    and one model call for all of them, then each session's lookups. One result per job, in order."""
    started = time.perf_counter_ns()
    prepared: list[list[PreparedWindows]] = []
    errors: list[Exception | None] = []
    for job in jobs:
        try:
            prepared.append(job.estimator.prepare(job.blocks, job.visual))
            errors.append(None)
        except Exception as exc:  # noqa: BLE001 - one session's failure must not cost the others their windows
            prepared.append([])
            errors.append(exc)
    flat = [p for per_session in prepared for p in per_session]
    raw_rows: list[np.ndarray] = []
    features_ms = model_ms = 0.0
    if flat:
        config = runtime.tactile_config
        t0 = time.perf_counter_ns()
        features = window_features(np.concatenate([p.batch.accel for p in flat]), np.concatenate([p.batch.speed for p in flat]),
                                   np.concatenate([p.batch.force for p in flat]), config)
        t1 = time.perf_counter_ns()
        raw = _predict(runtime, features, flat)
        t2 = time.perf_counter_ns()
        features_ms, model_ms = (t1 - t0) / 1e6, (t2 - t1) / 1e6
        bounds = np.cumsum([0] + [len(p.batch) for p in flat])
        raw_rows = [raw[bounds[i]:bounds[i + 1]] for i in range(len(flat))]
    results, row = [], 0
    for job, per_session, error in zip(jobs, prepared, errors, strict=True):
        estimates: list[WindowEstimate] = []
        for p in per_session:
            estimates += job.estimator.finish(p, raw_rows[row], started, p.preprocess_ns / 1e6 + features_ms, model_ms)
            row += 1
        results.append(SessionResult(estimates, job.estimator.segment, job.estimator.taken, error))
    return results


def _predict(runtime: Runtime, features: np.ndarray, prepared: list[PreparedWindows]) -> np.ndarray:
    """The model on the batch: tactile rows as computed, each session's visual vector repeated per window."""
    predictor = runtime.predictor
    tactile = features if predictor.needs_tactile else None
    visual = None
    if predictor.needs_visual:
        if any(p.visual is None for p in prepared):
            raise ValueError(f"model {runtime.model_name} needs a camera frame first")
        visual = np.concatenate([np.repeat(p.visual[None, :], len(p.batch), axis=0) for p in prepared])
    return predictor.predict(tactile, visual)


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
