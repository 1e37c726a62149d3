"""A session's learnt surface model: the stroked surface's own RenderModel, served as it grows.

    accepted sample blocks ─(estimation job, window pool)─▶ SessionSurface.feed ─▶ SurfaceFitter.push
    tap blocks (event loop: queued) ────────────────────────────────────────────▶ SurfaceFitter.push_taps
    after a job, when due and no other session waits for the pool ─▶ SessionSurface.fit (window pool)
        ─▶ SurfaceFitter.fit(prior = the library pick's model, keep_orders = the last fit's) ─▶ SurfacePublisher.offer
        ─▶ a new served version

Both run while the session is in its estimation job (the batcher holds it there until the fit is done), so the
fitter is never used by two threads at once; the event loop only queues taps and scene changes for the next job.

The served model's id is `session:<session id>` (SESSION_PREFIX): not a library id (a colon is never one), so it
cannot shadow an entry. Once a version is out, window events name it as `chosen` (with its `chosen_model_version`;
`library_pick` keeps the selection rule's entry, the model's prior), and operators fetch it through
`GET /library/{id}/model` like any entry. Before usable contact the library pick stands; bad input (FitStatus) keeps
what was served (the prior, or the last version learnt from good data) and is told once per surface.

Bounds: one fit per FIT_EVERY_S of stream fed, at most one a second and FIT_COST_RATIO × its own duration apart, only
when no other session's windows wait for the pool (at most one version per SurfacePublisher.MIN_INTERVAL_S);
the fitter keeps MAX_SEGMENTS 128-sample segments (≈ 0.8 MB, ≈ 33 s of contact at 1 kHz), allocated at the first
block; taps and resampler tails are bounded below.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from fractions import Fraction

import numpy as np
from scipy.signal import resample_poly

from models.tactile.resample import Resampler
from models.tactile.surface_fit import CONTACT_N, FitStatus, SurfaceFitter
from models.tactile.surface_publish import SurfacePublisher
from service.render_models import ServedRenderModel
from texture_library import model_codec
from texture_library.recording import Channel
from texture_library.spectrum import spectral_distance_db
from texture_library.vibration import RENDER_RATE_HZ, VibrationModel

SESSION_PREFIX = "session:"
#: contact segments a session's fitter keeps (the newest): 512 × 64 samples ≈ 33 s at 1 kHz, ≈ 0.8 MB
MAX_SEGMENTS = 512
#: a fit runs after at least this much stream (s) has been fed since the last one, and this long (s) after it
FIT_EVERY_S = 1.0
#: … and after FIT_COST_RATIO × the last fit's own duration: a session's fits hold at most 1/FIT_COST_RATIO of one pool
#: thread (a fit: ≈ 0.3 s of thread CPU, 0.7–1 s of wall on a busy 2-core host; 30 grid points × 18 ARMA order pairs)
FIT_COST_RATIO = 4.0
#: tap blocks waiting for the next job, at most (older ones are dropped)
MAX_QUEUED_TAPS = 4
#: samples one channel may run ahead of the others in the fitter's alignment buffer (s of stream)
MAX_AHEAD_S = 2.0
#: versions a session keeps servable besides its newest (a window event may name one just replaced)
RECENT_VERSIONS = 4
#: the channels a fit needs (position is used when the robot sends it)
NEEDED = ("accel", "force", "speed")
#: reasons that are bad input (told once per surface); no_contact and ok are not
BAD_INPUT = frozenset(set(FitStatus) - {FitStatus.ok, FitStatus.no_contact})


def surface_entry_id(session_id: str) -> str:
    """The served id of a session's learnt surface model."""
    return SESSION_PREFIX + session_id


@dataclass(frozen=True)
class FitOutcome:
    """What one fit did: status (why the served model is not the data's, or ok); served: a new version to serve
    (None: the served one stands); refusal: why an ok fit was not sent (the publisher's last_refusal); learnt: what
    a new version was learnt from (contact_s, segments, prior, noise_source, learnt_at: Unix s); generation: the
    surface it was fitted on (SessionSurface.generation: a scene change during the fit makes it stale)."""

    status: FitStatus
    served: ServedRenderModel | None
    refusal: str | None
    learnt: dict | None = None
    generation: int = 0


class SessionSurface:
    """One session's fitter, publisher and served version (see the module docstring)."""

    def __init__(self, session_id: str, rate_hz: float = RENDER_RATE_HZ, max_segments: int = MAX_SEGMENTS) -> None:
        self.entry_id = surface_entry_id(session_id)
        self.rate_hz = rate_hz
        self.max_segments = max_segments
        self.publisher = SurfacePublisher(self.entry_id)
        self.served: ServedRenderModel | None = None
        self.recent: dict[str, ServedRenderModel] = {}  # the last RECENT_VERSIONS served, by version
        self.fits = 0
        # what the served version was learnt from: contact seconds, segments, the library pick it blended with, when
        self.learnt: dict | None = None
        self._fitter: SurfaceFitter | None = None
        self._segment = -1
        self._resamplers: dict[str, Resampler] = {}
        self._aligned: dict[str, np.ndarray] = {}
        self._fed_s = 0.0  # stream seconds fed since the last fit
        self._next_fit_s = -float("inf")  # time.monotonic() before which no fit runs
        self._touching = False  # the newest sample fed was in contact (a stroke going on)
        self._taps: list[tuple[np.ndarray, np.ndarray, float]] = []  # (speeds, accel m/s², rate) waiting
        self._scene_changed = False
        self.generation = 0  # surfaces seen (scene changes): an outcome of an earlier one is not served
        self._news: list[FitStatus] = []  # reasons found in the pool, for the event loop to tell
        self._told: set[FitStatus] = set()
        self._orders: tuple[int, int] | None = None  # the last ok fit's (AR, MA) orders, kept while not clearly beaten
        self._taps_from: str | None = None  # the library entry whose taps the surface's versions carry (fitter's)
        # what publishing less costs the operators: over ok fits with a version out, the spectral distance (dB) of
        # the version they hold after the offer from the fit itself: count, sum, max
        self._gaps = 0
        self._gap_sum_db = 0.0
        self._gap_max_db = 0.0

    # ---- event loop ------------------------------------------------------------------------------
    def queue_taps(self, speeds: np.ndarray, accel: np.ndarray, rate_hz: float) -> None:
        """A tap block (speeds (k,) mm/s, accel (k, n) m/s² at rate_hz), for the next job to push."""
        self._taps = [*self._taps, (np.asarray(speeds, float), np.asarray(accel, float), float(rate_hz))]
        self._taps = self._taps[-MAX_QUEUED_TAPS:]

    def scene_changed(self) -> None:
        """The camera shows another surface: the served model goes at once (operators get the library pick back);
        the fitter forgets the surface at the next job."""
        self._scene_changed = True
        self.generation += 1
        self.served = None
        self.learnt = None
        self._taps = []

    def serve(self, served: ServedRenderModel, learnt: dict | None) -> None:
        """A new version goes out (window events name it from now on); the last RECENT_VERSIONS stay servable."""
        self.served, self.learnt = served, learnt
        self.recent[served.version] = served
        while len(self.recent) > RECENT_VERSIONS:
            del self.recent[next(iter(self.recent))]

    def untold(self) -> list[FitStatus]:
        """Bad-input reasons not yet told for this surface (each once; a scene change tells anew)."""
        out = []
        for reason in self._news:
            if reason in BAD_INPUT and reason not in self._told:
                self._told.add(reason)
                out.append(reason)
        self._news = []
        return out

    def due(self, now_s: float) -> bool:
        """A fit would see FIT_EVERY_S of new stream, and the last one's cost has been paid off (FIT_COST_RATIO)."""
        return self._fed_s >= FIT_EVERY_S and now_s >= self._next_fit_s

    # ---- pool thread (the session's job) -----------------------------------------------------------
    def _fitter_now(self) -> SurfaceFitter:
        if self._fitter is None:
            self._fitter = SurfaceFitter(self.rate_hz, max_segments=self.max_segments)
        if self._scene_changed:
            self._scene_changed = False
            self._told = set()  # a new surface: its bad input is told anew
            self._news.append(self._fitter.scene_change())
            self.publisher = SurfacePublisher(self.entry_id)
            self._orders = None
            self._taps_from = None
            self._fed_s = 0.0
        return self._fitter

    def feed(self, segment: int, channels: dict[str, Channel]) -> None:
        """One accepted sample block (canonical units) of stream segment `segment`: its accel, force, speed (and
        position) resampled to the fitter's rate, aligned, pushed. A block without those channels is skipped."""
        fitter = self._fitter_now()
        if segment != self._segment:  # a gap: no sample straddles it (the samples still waiting are dropped)
            self._segment, self._resamplers, self._aligned = segment, {}, {}
        kinds = [k for k in (*NEEDED, "position") if k in channels]
        if not all(k in kinds for k in NEEDED):
            return
        for kind in kinds:
            ch = channels[kind]
            data = np.asarray(ch.data, float)
            if kind == "position" and data.ndim == 2:
                data = data[:, 0] if data.shape[1] == 1 else np.hypot(data[:, 0], data[:, 1])
            if kind == "speed" and data.ndim == 2:
                data = data[:, 0]
            if kind not in self._resamplers:
                self._resamplers[kind] = Resampler(ch.rate_hz, self.rate_hz)
            out = self._resamplers[kind].process(data)
            held = self._aligned.get(kind)
            self._aligned[kind] = out if held is None else np.concatenate([held, out])
        n = min(self._aligned[k].shape[0] for k in kinds)
        limit = int(MAX_AHEAD_S * self.rate_hz)
        if n == 0:
            for k in kinds:  # a channel that never comes would hold the others for ever
                self._aligned[k] = self._aligned[k][-limit:]
            return
        take = {k: self._aligned[k][:n] for k in kinds}
        self._aligned = {k: self._aligned[k][n:][-limit:] for k in kinds}
        force = take["force"]
        if force.ndim == 2 and force.shape[1] == 1:
            force = force[:, 0]
        normal = force[:, 2] if force.ndim == 2 else force
        self._touching = bool(normal[-1] >= CONTACT_N)
        reason = fitter.push(take["accel"], force, take["speed"], take.get("position"))
        if reason is not None:
            self._news.append(reason)
        self._fed_s += n / self.rate_hz

    def push_taps(self) -> None:
        """The queued tap blocks, resampled to the fitter's rate."""
        fitter = self._fitter_now()
        taps, self._taps = self._taps, []
        for speeds, accel, rate in taps:
            if rate != self.rate_hz:
                ratio = Fraction(self.rate_hz / rate).limit_denominator(1000)
                accel = resample_poly(accel, ratio.numerator, ratio.denominator, axis=1)
            reason = fitter.push_taps(speeds, accel)
            if reason is not None:
                self._news.append(reason)

    def fit(self, prior: VibrationModel, now_s: float, prior_id: str = "") -> FitOutcome:
        """Fit (prior: the library pick's model, prior_id its entry) and offer the result to the publisher at now_s
        (monotonic s)."""
        generation = self.generation
        fitter = self._fitter_now()
        self.push_taps()
        self._fed_s = 0.0
        self.fits += 1
        started = time.perf_counter()
        held_taps = fitter.holds_fallback_taps
        fit = fitter.fit(prior, name=self.entry_id, keep_orders=self._orders)
        if not held_taps and fitter.holds_fallback_taps:
            self._taps_from = prior_id or None  # this fit fixed the surface's fallback taps: this prior's
        if fit.status is FitStatus.ok:
            p, q = fit.extra["orders"]
            self._orders = (int(p), int(q))
        self._next_fit_s = now_s + max(FIT_EVERY_S, FIT_COST_RATIO * (time.perf_counter() - started))
        if fit.status is not FitStatus.no_contact and not (fit.status is FitStatus.too_short and self._touching):
            self._news.append(fit.status)  # (a stroke still going on is not yet too short)
        if fit.status is not FitStatus.ok:
            return FitOutcome(fit.status, None, None, generation=generation)
        doc = self.publisher.offer(fit.model, now_s)
        held = self.publisher.last
        if held is not None:
            gap = spectral_distance_db(held, fit.model)
            self._gaps, self._gap_sum_db = self._gaps + 1, self._gap_sum_db + gap
            self._gap_max_db = max(self._gap_max_db, gap)
        if doc is None:
            return FitOutcome(fit.status, None, self.publisher.last_refusal, generation=generation)
        learnt = {
            "contact_s": round(fit.contact_s, 3),
            "segments": int(fit.extra.get("segments", 0)),
            "prior": prior_id,
            "noise_source": fit.noise_source,
            "learnt_at": round(time.time(), 3),
        }
        served = ServedRenderModel(doc, doc.to_json_bytes(), model_codec.encode(doc), self._taps_from)
        return FitOutcome(fit.status, served, None, learnt, generation)

    def status(self) -> dict:
        """What GET /sessions/{id} says of it (service.schemas.SurfaceModelStatus)."""
        return {
            "id": self.entry_id,
            "model_version": None if self.served is None else self.served.version,
            "versions": self.publisher.published,
            "fits": self.fits,
            "segments": self.segments,
            "held_gap_fits": self._gaps,
            "held_gap_db_mean": round(self._gap_sum_db / self._gaps, 3) if self._gaps else None,
            "held_gap_db_max": round(self._gap_max_db, 3) if self._gaps else None,
            **(self.learnt or {}),
        }

    @property
    def segments(self) -> int:
        """Contact segments held (≤ max_segments)."""
        return 0 if self._fitter is None else self._fitter.segments


def feed_job(surface: SessionSurface, blocks: list) -> None:
    """The queued taps and every sample block of an estimation job (AdmittedBlocks) into the session's fitter."""
    surface.push_taps()
    for b in blocks:
        surface.feed(b.segment, b.channels)
