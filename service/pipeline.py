"""A block's way through the service, one typed step per stage:

    ingest      wire bytes ─▶ SampleBlock                                   (service.ingest, event loop)
    admission   SampleBlock ─▶ AdmittedBlock (StreamContract.advance)       (service.session, event loop)
    window batch  AdmittedBlocks of a session ─▶ PreparedWindows             (prepare_windows, pool thread)
    features    every session's windows at once ─▶ FeatureRows               (featurize: window_features)
    model       FeatureRows ─▶ RawRatings (the main model where the session's visual embedding has
                landed, the tactile-only model elsewhere)                   (predict)
    lookup      RawRatings ─▶ WindowEstimate per window: EMA, confidence,
                nearest library entries, hysteresis                          (lookup)
    publish     WindowEstimate ─▶ window event ─▶ broker                     (service.session, event loop)

`estimate_batch` runs window batch → lookup for many sessions in one pool call: window_features and
onnxruntime cost far less per window in a batch, and a pool thread that holds the GIL for fewer,
larger steps leaves the event loop more of it. A session is in at most one job at a time (the
batcher sees to it), so its estimator needs no lock. Durations use time.perf_counter_ns, the clock
ingest stamps blocks with.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from models.tactile.features import window_features
from models.tactile.preprocess import TactilePreprocessor, WindowBatch
from models.tactile.stream import StreamContract
from service.runtime import Runtime
from service.smoothing import ExponentialSmoother, SpreadConfidence
from texture_library.nearest import HysteresisSelector, Match
from texture_library.recording import Channel

#: what a window's estimate was computed from (the window event's "inputs")
Inputs = Literal["tactile", "tactile+visual"]


# ---- the typed steps -------------------------------------------------------------------------------
@dataclass(frozen=True)
class AdmittedBlock:
    """A block accepted into a session's stream: canonical channels (those the preprocessor uses).

    segment / origin_t0: its stream segment and that segment's first sample time (sender clock, s);
    windows: complete windows of the segment once this block is in (StreamContract's count);
    arrived_ns: time.perf_counter_ns() when its body had been read.
    """

    seq: int
    segment: int
    origin_t0: float
    channels: dict[str, Channel]
    windows: int
    arrived_ns: int


@dataclass(frozen=True)
class SessionJob:
    """A session's share of a batch: its estimator, its admitted blocks, its visual input (None: tactile-only)
    and how many windows those blocks complete."""

    estimator: "SessionEstimator"
    blocks: list[AdmittedBlock]
    visual: np.ndarray | None
    windows: int


@dataclass(frozen=True)
class PreparedWindows:
    """One session segment's windows after preprocessing. completed_by: (seq, arrived_ns) of the block that
    completed each window; preprocess_ns: what push + take cost."""

    estimator: "SessionEstimator"
    batch: WindowBatch
    origin_t0: float
    completed_by: list[tuple[int, int]]
    visual: np.ndarray | None
    preprocess_ns: int

    @property
    def inputs(self) -> Inputs:
        return "tactile" if self.visual is None else "tactile+visual"


@dataclass(frozen=True)
class FeatureRows:
    """window_features of every prepared window of a batch, stacked in order: rows (n, F); ms: their cost."""

    rows: np.ndarray
    ms: float


@dataclass(frozen=True)
class RawRatings:
    """The model's output per window (n, 4) bipolar, in FeatureRows order; ms: inference cost."""

    ratings: np.ndarray
    ms: float


@dataclass(frozen=True)
class WindowEstimate:
    """One window's result (what the window event is built from). Ratings (4,) bipolar; times in s
    (sender clock); durations in ms.

    completed_by: seq of the block whose samples completed the window; ingest_ns: when that block
    arrived; started_ns: when its batch's computation began (perf_counter_ns); inputs: what the
    estimate was computed from; model: which model produced it.
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
    inputs: Inputs
    model: str


@dataclass(frozen=True)
class SessionResult:
    """What a job produced for one session: its window estimates, or the error that stopped it (the other
    sessions of the batch are unaffected). windows: what the job was expected to complete."""

    estimates: list[WindowEstimate]
    windows: int
    error: Exception | None = None


# ---- per-session compute state -------------------------------------------------------------------
class SessionEstimator:
    """Per-session compute state: preprocessor (per stream segment), smoother, confidence, selector."""

    def __init__(self, runtime: Runtime, contract: StreamContract, *, alpha: float, confidence_windows: int,
                 top_k: int, hysteresis_margin: float, hysteresis_hold: int) -> None:
        self.runtime = runtime
        self.contract = contract
        self.config = contract.config
        self.top_k = top_k
        self.smoother = ExponentialSmoother(alpha)
        self.confidence = SpreadConfidence(confidence_windows)
        self.selector = HysteresisSelector(hysteresis_margin, hysteresis_hold)
        self.segment = -1
        self.taken = 0  # windows taken from the current segment
        self.next_index = 0  # session-wide window counter
        self._pre: TactilePreprocessor | None = None

    def restart(self) -> None:
        """Forget the current segment (after a failure left the preprocessor's state unknown)."""
        self.segment, self._pre = -1, None


def prepare_windows(job: SessionJob) -> list[PreparedWindows]:
    """Window batch step: push the job's blocks (in order, one push per segment) and take every window
    they complete, naming each window's completing block."""
    est = job.estimator
    out = []
    for group in _by_segment(job.blocks):
        first = group[0]
        if first.segment != est.segment or est._pre is None:  # a gap in the stream: windows never straddle it
            est.segment, est.taken = first.segment, 0
            est._pre = TactilePreprocessor(contract=est.contract)
        t0 = time.perf_counter_ns()
        est._pre.push(**_concatenate(group))
        batch = est._pre.take()
        if len(batch) == 0:
            continue
        completed_by = [_completing(group, est.taken + i) for i in range(len(batch))]
        est.taken += len(batch)
        out.append(PreparedWindows(est, batch, first.origin_t0, completed_by, job.visual, time.perf_counter_ns() - t0))
    return out


def featurize(runtime: Runtime, prepared: Sequence[PreparedWindows]) -> FeatureRows:
    """Features step: THE training feature function on every window of the batch at once."""
    t0 = time.perf_counter_ns()
    rows = window_features(np.concatenate([p.batch.accel for p in prepared]), np.concatenate([p.batch.speed for p in prepared]),
                           np.concatenate([p.batch.force for p in prepared]), runtime.tactile_config)
    return FeatureRows(rows, (time.perf_counter_ns() - t0) / 1e6)


def predict(runtime: Runtime, features: FeatureRows, prepared: Sequence[PreparedWindows]) -> RawRatings:
    """Model step: rows whose session has a visual embedding go to the main model with it (repeated per
    window); the others to the tactile model (the main one if it reads no images). One call per model."""
    t0 = time.perf_counter_ns()
    sizes = [len(p.batch) for p in prepared]
    bounds = np.cumsum([0] + sizes)
    out = np.empty((features.rows.shape[0], 4), dtype=np.float64)
    for uses_visual in (True, False):
        chosen = [i for i, p in enumerate(prepared) if (p.visual is not None) == uses_visual]
        if not chosen:
            continue
        rows = np.concatenate([np.arange(bounds[i], bounds[i + 1]) for i in chosen])
        predictor = runtime.predictor_for(uses_visual)
        visual = None
        if uses_visual:
            visual = np.concatenate([np.repeat(prepared[i].visual[None, :], sizes[i], axis=0) for i in chosen])  # type: ignore[index]
        tactile = features.rows[rows] if predictor.needs_tactile else None
        out[rows] = predictor.predict(tactile, visual)
    return RawRatings(out, (time.perf_counter_ns() - t0) / 1e6)


def lookup(p: PreparedWindows, raw: np.ndarray, started_ns: int, features_ms: float, model_ms: float) -> list[WindowEstimate]:
    """Lookup step: smoothing, confidence and the library's nearest entries of one session's windows, in order.
    raw: (n, 4) for p's windows."""
    est, rt = p.estimator, p.estimator.runtime
    model = rt.predictor_for(p.visual is not None).card.model
    out = []
    window_s = est.config.window_s
    for i, (seq, arrived_ns) in enumerate(p.completed_by):
        t0 = time.perf_counter_ns()
        smoothed = est.smoother.update(raw[i])
        confidence = est.confidence.update(raw[i])
        matches = rt.index.query(smoothed, est.top_k)
        chosen = est.selector.update(rt.index, smoothed)
        lookup_ms = (time.perf_counter_ns() - t0) / 1e6
        t_start = p.origin_t0 + float(p.batch.t_start_s[i])
        out.append(WindowEstimate(
            index=est.next_index, t_start_s=t_start, t_end_s=t_start + window_s,
            raw=raw[i].astype(np.float64), smoothed=smoothed, confidence=confidence,
            matches=matches, chosen=chosen, completed_by=seq, ingest_ns=arrived_ns,
            started_ns=started_ns, features_ms=p.preprocess_ns / 1e6 + features_ms, model_ms=model_ms,
            lookup_ms=lookup_ms, inputs=p.inputs, model=model,
        ))
        est.next_index += 1
    return out


def estimate_batch(runtime: Runtime, jobs: Sequence[SessionJob]) -> list[SessionResult]:
    """window batch → features → model → lookup for every job; one result per job, in order."""
    started = time.perf_counter_ns()
    prepared: list[list[PreparedWindows]] = []
    errors: list[Exception | None] = []
    for job in jobs:
        try:
            prepared.append(prepare_windows(job))
            errors.append(None)
        except Exception as exc:  # noqa: BLE001 - one session's failure must not cost the others their windows
            job.estimator.restart()
            prepared.append([])
            errors.append(exc)
    flat = [p for per_session in prepared for p in per_session]
    raw_rows: list[np.ndarray] = []
    features_ms = model_ms = 0.0
    if flat:
        features = featurize(runtime, flat)
        raw = predict(runtime, features, flat)
        features_ms, model_ms = features.ms, raw.ms
        bounds = np.cumsum([0] + [len(p.batch) for p in flat])
        raw_rows = [raw.ratings[bounds[i]:bounds[i + 1]] for i in range(len(flat))]
    results, row = [], 0
    for job, per_session, error in zip(jobs, prepared, errors, strict=True):
        estimates: list[WindowEstimate] = []
        for p in per_session:
            estimates += lookup(p, raw_rows[row], started, features_ms, model_ms)
            row += 1
        results.append(SessionResult(estimates, job.windows, error))
    return results


def _completing(group: Sequence[AdmittedBlock], window: int) -> tuple[int, int]:
    """(seq, arrived_ns) of the first block of `group` after which the segment had more than `window` windows."""
    for b in group:
        if b.windows > window:
            return b.seq, b.arrived_ns
    last = group[-1]
    return last.seq, last.arrived_ns


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
    return {kind: Channel(np.concatenate([c.data for c in chs]) if len(chs) > 1 else chs[0].data, chs[0].rate_hz)
            for kind, chs in parts.items()}
