"""A block's way through the service, one typed step per stage:

    ingest      wire bytes ─▶ SampleBlock | TapBlock                        (service.intake, event loop)
    admission   SampleBlock ─▶ AdmittedBlock (StreamContract.advance)       (service.live_session, event loop)
                TapBlock ─▶ the session's tap features (models.tactile.taps.tap_features), carried by the
                AdmittedBlocks of the surface they were tapped on           (service.live_session, event loop)
    window batch  AdmittedBlocks of a session ─▶ PreparedWindows             (prepare_windows, pool thread)
    features    every session's windows at once ─▶ FeatureRows               (featurize: window_features)
    model       FeatureRows ─▶ RawRatings (the main model where the session's visual embedding has
                landed, the tactile-only model elsewhere; under the adaptive policy the cheap
                model first and the full one where it is not good enough) and each window's
                out-of-distribution check by the detector of the model that estimated it (predict)
    lookup      RawRatings ─▶ WindowEstimate per window: EMA, steadiness, interval and flag,
                nearest library entries, the selection rule's choice (the window's vibration
                against the library's precomputed spectra where the rule reads it) and its
                hysteresis                                                    (lookup)
    publish     WindowEstimate ─▶ window event ─▶ broker                     (service.live_session, event loop)

`estimate_batch` runs window batch → lookup for many sessions in one pool call: window_features and
onnxruntime cost far less per window in a batch, and a pool thread that holds the GIL for fewer,
larger steps leaves the event loop more of it. A session is in at most one job at a time (the
batcher sees to it), so its estimator needs no lock. Durations use time.perf_counter_ns, the clock
ingest stamps blocks with.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from models.inference.ood import FrameCheck
from models.tactile.features import window_features
from models.tactile.preprocess import TactilePreprocessor, WindowBatch
from models.tactile.stream import StreamContract
from service.log_throttle import LogThrottle
from service.runtime import Runtime
from service.smoothing import ExponentialSmoother, Steadiness
from service.surface_models import SessionSurface, feed_job
from service.uncertainty import Assessment, ServedModel, SessionUncertainty
from texture_library.nearest import Match, decision_margin
from texture_library.recording import Channel
from texture_library.selection import Choice, HysteresisChooser

log = logging.getLogger(__name__)
_batch_failures = LogThrottle(log)
_surface_failures = LogThrottle(log)

#: what a window's estimate was computed from (the window event's "inputs")
Inputs = Literal["tactile", "tactile+visual"]


# ---- the typed steps -------------------------------------------------------------------------------
@dataclass(frozen=True)
class AdmittedBlock:
    """A block accepted into a session's stream: canonical channels (those the preprocessor uses).

    segment / origin_t0: its stream segment and that segment's first sample time (sender clock, s);
    windows: complete windows of the segment once this block is in (StreamContract's count);
    arrived_ns: time.perf_counter_ns() when its body had been read;
    taps: (3,) tap features of the surface (models.tactile.taps.tap_features) for a model with the taps
    group, None until the surface has been tapped (or for a model without the group).
    """

    seq: int
    segment: int
    origin_t0: float
    channels: dict[str, Channel]
    windows: int
    arrived_ns: int
    taps: np.ndarray | None = None


@dataclass(frozen=True)
class SessionJob:
    """A session's share of a batch: its estimator, its admitted blocks, its visual input (None: tactile-only)
    and how many windows those blocks complete; frame_checks: the visual input's FrameCheck per model name
    (service.runtime.Runtime.frame_checks; empty without a visual input); frames_shed: it has no visual input because
    its frames were refused under load (its windows are marked missing the frame)."""

    estimator: SessionEstimator
    blocks: list[AdmittedBlock]
    visual: np.ndarray | None
    windows: int
    frame_checks: dict[str, FrameCheck | None] = field(default_factory=dict)
    frames_shed: bool = False
    surface: SessionSurface | None = None


@dataclass(frozen=True)
class PreparedWindows:
    """One session segment's windows after preprocessing. completed_by: (seq, arrived_ns) of the block that
    completed each window; preprocess_ns: what push + take cost; taps: (m, 3) tap features per window (those
    its completing block carried; zeros where it carried none) for a model with the taps group, else None;
    untapped: (m,) bool, the windows whose block carried no tap features (estimated by runtime.untapped), or None
    when every window has them; frames_shed: as SessionJob's."""

    estimator: SessionEstimator
    batch: WindowBatch
    origin_t0: float
    completed_by: list[tuple[int, int]]
    visual: np.ndarray | None
    preprocess_ns: int
    frame_checks: dict[str, FrameCheck | None] = field(default_factory=dict)
    taps: np.ndarray | None = None
    untapped: np.ndarray | None = None
    frames_shed: bool = False

    @property
    def inputs(self) -> Inputs:
        return "tactile" if self.visual is None else "tactile+visual"


@dataclass(frozen=True)
class FeatureRows:
    """window_features of every prepared window of a batch, stacked in order: rows (n, F); ms: their cost."""

    rows: np.ndarray
    ms: float


@dataclass(frozen=True)
class WindowCheck:
    """One window's out-of-distribution check (models.inference.ood.OODDetector.check): flag, reasons, distance
    (> 0)."""

    flagged: bool
    reasons: list[str]
    distance: float


@dataclass(frozen=True)
class RawRatings:
    """The models' output per window (n, 4) bipolar, in FeatureRows order; models: the model that estimated
    each window; checks: each window's check by that model's detector (None: it has none); escalated: windows
    the full model re-estimated after the cheap one; ms: inference and check cost."""

    ratings: np.ndarray
    models: list[ServedModel]
    checks: list[WindowCheck | None]
    escalated: int
    ms: float


@dataclass(frozen=True)
class WindowEstimate:
    """One window's result (what the window event is built from). Ratings (4,) bipolar; times in s
    (sender clock); durations in ms.

    completed_by: seq of the block whose samples completed the window; ingest_ns: when that block
    arrived; started_ns: when its batch's computation began (perf_counter_ns); inputs: what the
    estimate was computed from; model: which model produced it; missing: inputs the served model reads that this
    window lacked, so a fallback model estimated it (e.g. ("taps",)).
    """

    index: int
    t_start_s: float
    t_end_s: float
    raw: np.ndarray
    smoothed: np.ndarray
    steadiness: np.ndarray
    assessment: Assessment
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
    selection: Choice | None = None
    chosen_model_version: str | None = None
    missing: tuple[str, ...] = ()
    library_pick: str | None = None


@dataclass(frozen=True)
class SessionResult:
    """What a job produced for one session: its window estimates, or the error that stopped it (the other
    sessions of the batch are unaffected). windows: what the job was expected to complete."""

    estimates: list[WindowEstimate]
    windows: int
    error: Exception | None = None


# ---- per-session compute state -------------------------------------------------------------------
class SessionEstimator:
    """Per-session compute state: preprocessor (per stream segment), smoother, steadiness, uncertainty, selector."""

    mismatch: np.ndarray | None  # EMA of the windows' vibration mismatch per entry, dB

    def __init__(
        self,
        runtime: Runtime,
        contract: StreamContract,
        *,
        alpha: float,
        steadiness_windows: int,
        top_k: int,
        hysteresis_margin: float,
        hysteresis_hold: int,
        hysteresis_settle: int = 0,
        hysteresis_release_lead: float | None = None,
    ) -> None:
        self.runtime = runtime
        self.contract = contract
        self.config = contract.config
        self.top_k = top_k
        self.alpha = alpha
        self._steadiness_windows = steadiness_windows
        self._hysteresis = (hysteresis_margin, hysteresis_hold, hysteresis_settle, hysteresis_release_lead)
        self._start_tracking()
        self.segment = -1
        self.taken = 0  # windows taken from the current segment
        self.next_index = 0  # session-wide window counter
        self._pre: TactilePreprocessor | None = None

    @classmethod
    def from_settings(cls, runtime: Runtime, contract: StreamContract, settings) -> SessionEstimator:
        """With the service Settings' smoothing, steadiness, top-k and hysteresis."""
        return cls(
            runtime,
            contract,
            alpha=settings.smoothing_alpha,
            steadiness_windows=settings.steadiness_windows,
            top_k=settings.top_k,
            hysteresis_margin=settings.hysteresis_margin,
            hysteresis_hold=settings.hysteresis_hold,
            hysteresis_settle=settings.hysteresis_settle_windows,
            hysteresis_release_lead=settings.hysteresis_release_lead or None,
        )

    def smoothed_mismatch(self, mismatch: np.ndarray) -> np.ndarray:
        """The window's vibration mismatch (M,) dB, smoothed by the same EMA as the ratings."""
        if self.mismatch is None or self.mismatch.shape != mismatch.shape:
            self.mismatch = mismatch
        else:
            self.mismatch = self.alpha * mismatch + (1.0 - self.alpha) * self.mismatch
        return self.mismatch

    def _start_tracking(self) -> None:
        """What the lookup carries from window to window: smoother, steadiness, uncertainty, selector, mismatch."""
        self.smoother = ExponentialSmoother(self.alpha)
        self.steadiness = Steadiness(self._steadiness_windows)
        self.uncertainty = SessionUncertainty(self.alpha, self.runtime.interval_level)
        self.selector = HysteresisChooser(self.runtime.selection, *self._hysteresis)
        self.mismatch = None

    def restart(self, *, tracking: bool = False) -> None:
        """Forget the current segment (after a failure left the preprocessor's state unknown); tracking: also what
        the lookup carries from window to window (after a lookup failed partway: it holds windows never published)."""
        self.segment, self._pre = -1, None
        if tracking:
            self._start_tracking()


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
        completing = [_completing(group, est.taken + i) for i in range(len(batch))]
        est.taken += len(batch)
        taps = untapped = None
        if "taps" in est.config.extra_groups:
            missing = np.array([b.taps is None for b in completing])
            if missing.any():
                if est.runtime.untapped is None:
                    raise ValueError("a window's surface has no tap features; the session holds such windows back")
                untapped = missing
            taps = np.stack([np.zeros(3) if b.taps is None else b.taps for b in completing])
        out.append(
            PreparedWindows(
                est,
                batch,
                first.origin_t0,
                [(b.seq, b.arrived_ns) for b in completing],
                job.visual,
                time.perf_counter_ns() - t0,
                job.frame_checks,
                taps,
                untapped,
                job.frames_shed,
            )
        )
    return out


def featurize(runtime: Runtime, prepared: Sequence[PreparedWindows]) -> FeatureRows:
    """Features step: THE training feature function on every window of the batch at once."""
    t0 = time.perf_counter_ns()
    taps = np.concatenate([p.taps for p in prepared]) if runtime.needs_taps else None
    rows = window_features(
        np.concatenate([p.batch.accel for p in prepared]),
        np.concatenate([p.batch.speed for p in prepared]),
        np.concatenate([p.batch.force for p in prepared]),
        runtime.tactile_config,
        taps,
    )
    return FeatureRows(rows, (time.perf_counter_ns() - t0) / 1e6)


def predict(runtime: Runtime, features: FeatureRows, prepared: Sequence[PreparedWindows]) -> RawRatings:
    """Model step: rows whose session has a visual embedding go to the main model with it (repeated per
    window); the others to the tactile model (the main one if it reads no images). Under the adaptive policy
    with a cheap model, the cheap model estimates first and the full model re-estimates the rows the policy
    sends it (runtime.policy.needs_full: a wide interval, an out-of-distribution flag, or a library decision
    boundary near). One call per model; each row is checked by the detector of the model that estimated it."""
    t0 = time.perf_counter_ns()
    sizes = [len(p.batch) for p in prepared]
    bounds = np.cumsum([0] + sizes)
    n = features.rows.shape[0]
    out = np.empty((n, 4), dtype=np.float64)
    models: list[ServedModel] = [runtime.main] * n
    checks: list[WindowCheck | None] = [None] * n
    escalated = 0
    # windows of a surface not tapped: the untapped model, on the columns before the taps group
    untapped = np.concatenate([np.zeros(len(p.batch), bool) if p.untapped is None else p.untapped for p in prepared])
    owner_all = np.repeat(np.arange(len(prepared)), sizes)
    if untapped.any() and runtime.untapped is not None:
        rows = np.flatnonzero(untapped)
        k = runtime.untapped.predictor.tactile_config.n_features
        out[rows] = _run(runtime.untapped, features.rows[rows, :k], None)
        _check(runtime.untapped, features.rows[:, :k], prepared, rows, owner_all[rows], models, checks)
    for uses_visual in (True, False):
        chosen = [i for i, p in enumerate(prepared) if (p.visual is not None) == uses_visual]
        if not chosen:
            continue
        rows = np.concatenate([np.arange(bounds[i], bounds[i + 1]) for i in chosen])
        rows = rows[~untapped[rows]]
        if rows.size == 0:
            continue
        owner = owner_all[rows]  # the prepared item of each row
        visual = None
        if uses_visual:
            visual = np.concatenate([np.repeat(prepared[i].visual[None, :], sizes[i], axis=0) for i in chosen])  # type: ignore[index]
        first, full = runtime.first_model(uses_visual), runtime.full_model(uses_visual)
        out[rows] = _run(first, features.rows[rows], visual)
        _check(first, features.rows, prepared, rows, owner, models, checks)
        if first is full:
            continue
        flagged = distance = None
        if first.detector is not None:
            flagged = np.array([checks[r].flagged for r in rows])
            distance = np.array([checks[r].distance for r in rows])
        width = first.window_width(out[rows], flagged, distance, runtime.interval_level)
        margin = decision_margin(runtime.index.distances_many(out[rows]))
        need = runtime.policy.needs_full(width, margin, flagged)
        if need.any():
            again = rows[need]
            out[again] = _run(full, features.rows[again], None if visual is None else visual[need])
            _check(full, features.rows, prepared, again, owner[need], models, checks)
            escalated += int(need.sum())
    return RawRatings(out, models, checks, escalated, (time.perf_counter_ns() - t0) / 1e6)


def _run(model: ServedModel, tactile: np.ndarray, visual: np.ndarray | None) -> np.ndarray:
    p = model.predictor
    return p.predict(tactile if p.needs_tactile else None, visual if p.needs_visual else None)


def _check(
    model: ServedModel,
    rows_features: np.ndarray,
    prepared: Sequence[PreparedWindows],
    rows: np.ndarray,
    owner: np.ndarray,
    models: list[ServedModel],
    checks: list[WindowCheck | None],
) -> None:
    """Record `model` as the estimator of `rows` and its detector's check of them, one call per session segment
    (each has its own frame)."""
    for i in np.unique(owner):
        mine = rows[owner == i]
        result = model.check(rows_features[mine], prepared[int(i)].frame_checks.get(model.name))
        for k, r in enumerate(mine):
            models[r] = model
            checks[r] = (
                None
                if result is None
                else WindowCheck(bool(result.flags[k]), result.reasons[k], float(result.distance[k]))
            )


def lookup(
    p: PreparedWindows,
    raw: np.ndarray,
    models: Sequence[ServedModel],
    checks: Sequence[WindowCheck | None],
    started_ns: int,
    features_ms: float,
    model_ms: float,
) -> list[WindowEstimate]:
    """Lookup step: smoothing, steadiness, interval and flag, and the library's nearest entries of one session's
    windows, in order. raw: (n, 4) for p's windows; models, checks: (n,) who estimated each and its check."""
    est, rt = p.estimator, p.estimator.runtime
    out = []
    window_s = est.config.window_s
    for i, (seq, arrived_ns) in enumerate(p.completed_by):
        t0 = time.perf_counter_ns()
        smoothed = est.smoother.update(raw[i])
        steadiness = est.steadiness.update(raw[i])
        c = checks[i]
        assessment = est.uncertainty.update(
            models[i],
            smoothed,
            None if c is None else c.flagged,
            None if c is None else c.reasons,
            None if c is None else c.distance,
        )
        distances = rt.index.distances(smoothed)  # once, for the matches and the choice
        matches = rt.index.query(smoothed, est.top_k, distances)
        mismatch = None
        if rt.spectra is not None:
            force = p.batch.force[i]
            normal = force[:, 0] if force.ndim == 2 else force
            mismatch = est.smoothed_mismatch(
                rt.spectra.mismatch_db(
                    p.batch.accel[i], float(p.batch.speed[i].mean()), float(normal.mean()), rt.selection.mismatch_kind
                )
            )
        choice = est.selector.choose(rt.index.ids, rt.selection.costs(distances, mismatch))
        lookup_ms = (time.perf_counter_ns() - t0) / 1e6
        t_start = p.origin_t0 + float(p.batch.t_start_s[i])
        out.append(
            WindowEstimate(
                index=est.next_index,
                t_start_s=t_start,
                t_end_s=t_start + window_s,
                raw=raw[i].astype(np.float64),
                smoothed=smoothed,
                steadiness=steadiness,
                assessment=assessment,
                matches=matches,
                chosen=choice.id,
                completed_by=seq,
                ingest_ns=arrived_ns,
                started_ns=started_ns,
                features_ms=p.preprocess_ns / 1e6 + features_ms,
                model_ms=model_ms,
                lookup_ms=lookup_ms,
                model=models[i].name,
                inputs="tactile+visual" if p.visual is not None and models[i].predictor.needs_visual else "tactile",
                selection=choice,
                chosen_model_version=rt.render_models.version(choice.id),
                missing=_missing(p, i, models[i]),
            )
        )
        est.next_index += 1
    return out


def estimate_batch(runtime: Runtime, jobs: Sequence[SessionJob]) -> list[SessionResult]:
    """window batch → features → model → lookup for every job; one result per job, in order. A failure is the
    failing session's alone: its windows are dropped with the error and its stream restarts; the others' windows
    are estimated (if features or the model fail for the batch, each session is estimated on its own)."""
    started = time.perf_counter_ns()
    prepared: list[list[PreparedWindows]] = []
    errors: list[Exception | None] = []
    for job in jobs:
        try:
            prepared.append(prepare_windows(job))
            errors.append(None)
        except Exception as exc:  # noqa: BLE001 - one session's failure must not cost the others their windows
            prepared.append([])
            errors.append(exc)
        if job.surface is not None:
            try:
                feed_job(job.surface, job.blocks)
            except Exception:  # noqa: BLE001 - the learnt model is an extra: its failure never costs a window
                if _surface_failures.admit("feed") is not None:
                    log.warning("feeding a session's surface fitter failed", exc_info=True)
    rated: list[list[Rated]] = [[] for _ in jobs]
    owners = [i for i, per_session in enumerate(prepared) for _ in per_session]  # the job of each prepared item
    try:
        for i, per_item in zip(owners, _rate(runtime, [p for per in prepared for p in per]), strict=True):
            rated[i].append(per_item)
    except Exception as batch_error:  # noqa: BLE001 - find whose windows fail: each session alone
        alone_failed = False
        for i, per_session in enumerate(prepared):
            try:
                rated[i] = _rate(runtime, per_session)
            except Exception as exc:  # noqa: BLE001
                errors[i], alone_failed = exc, True
        if not alone_failed and _batch_failures.admit("batch") is not None:
            # a fault of the batch itself (its size, its memory): every such job now costs twice
            log.warning("features or the model failed for a batch but for none of its sessions", exc_info=batch_error)
    results = []
    for job, per_session, per_rated, error in zip(jobs, prepared, rated, errors, strict=True):
        estimates: list[WindowEstimate] = []
        est = job.estimator
        first_index = est.next_index
        tracking = False
        if error is None:
            try:
                for p, (raw, models, checks, features_ms, model_ms) in zip(per_session, per_rated, strict=True):
                    estimates += lookup(p, raw, models, checks, started, features_ms, model_ms)
            except Exception as exc:  # noqa: BLE001 - its windows are dropped, and what they moved on is undone
                error, estimates, tracking = exc, [], True
                est.next_index = first_index
        if error is not None:
            est.restart(tracking=tracking)
        results.append(SessionResult(estimates, job.windows, error))
    return results


#: one prepared item's share of the model step: raw (m, 4), models, checks, then features_ms and model_ms of its call
Rated = tuple[np.ndarray, list[ServedModel], list[WindowCheck | None], float, float]


def _rate(runtime: Runtime, prepared: Sequence[PreparedWindows]) -> list[Rated]:
    """Features and model steps for `prepared` in one call each; per item its rows (no session state changes)."""
    if not prepared:
        return []
    features = featurize(runtime, prepared)
    raw = predict(runtime, features, prepared)
    bounds = np.cumsum([0] + [len(p.batch) for p in prepared])
    return [
        (raw.ratings[a:b], raw.models[a:b], raw.checks[a:b], features.ms, raw.ms)
        for a, b in zip(bounds[:-1], bounds[1:])
    ]


def _missing(p: PreparedWindows, i: int, model: ServedModel) -> tuple[str, ...]:
    """Inputs window i of `p` lacked: the surface's taps (the untapped model estimated it), the camera frame (its
    session's frames were refused under load, and a model that reads images estimated it without one)."""
    out: tuple[str, ...] = ()
    if p.untapped is not None and p.untapped[i]:
        out += ("taps",)
    if p.frames_shed and not (p.visual is not None and model.predictor.needs_visual):
        out += ("frame",)
    return out


def _completing(group: Sequence[AdmittedBlock], window: int) -> AdmittedBlock:
    """The first block of `group` after which the segment had more than `window` windows."""
    for b in group:
        if b.windows > window:
            return b
    return group[-1]


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
    return {
        kind: Channel(np.concatenate([c.data for c in chs]) if len(chs) > 1 else chs[0].data, chs[0].rate_hz)
        for kind, chs in parts.items()
    }
