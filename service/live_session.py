"""One streaming session on the event loop: admission, its bounded queue of admitted blocks, its frames.

    ingest (loop) ─▶ admit: seq rules, StreamContract.admit, bounds ─▶ pending AdmittedBlocks
        ─(a window is complete)─▶ WindowBatcher ─▶ pipeline.estimate_batch (window pool) ─▶ apply_result ─▶ broker
    frames: decode + scene-change test (frame pool) ─▶ the serving policy: embed it? ─▶ latest-frame slot
        ─▶ embed + frame checks (visual pool, one at a time) ─▶ the scene's pooled visual input
    a frame of another scene (any model) ─▶ the rendered entry's hysteresis settles again (HysteresisChooser.release)

Tap blocks (the tap exploratory procedure): a model whose features include the taps group gets the
surface's tap features from them, computed on admission by the same pure function the datasets use
(models.tactile.taps.tap_features); other models acknowledge and ignore them. Tap features belong to
the surface under the tool: they hold for every sample block admitted after the tap block — across
stream gaps, clock resets and new segments, which do not change the surface — and for the blocks
still waiting for them, until the camera shows that the scene changed (a frame whose thumbnail
differs from the tapped surface's by more than frame_change; a taps model looks at frames for this
even when it reads no images). Windows of a surface without tap features are estimated by the
untapped fallback model (a tactile model trained on the same features without the taps group:
HAPTICLINK_TACTILE_MODEL_PATH) and marked `"missing_inputs": ["taps"]`; without one they wait, like
windows waiting for a first frame (bounded the same way). Either way the session is told once per
untapped surface (an `input_missing` status event) that a tap block would restore the full model.

Bounds, checked before anything is taken: a block that would leave more than
session_queue_windows complete-but-unpublished windows, or more than session_queue_blocks pending
blocks, is refused (429 / close 4429); a session is in at most one estimation job and one
embedding job at a time; frames arriving during an embedding replace each other (only the newest
is embedded).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import Executor
from dataclasses import asdict, replace
from typing import Literal

import numpy as np

from drivers.blocks import Block, SampleBlock, TapBlock
from drivers.scene_change import scene_changed
from models.inference.ood import FrameCheck
from models.tactile.stream import StreamContract
from models.tactile.taps import tap_features
from models.visual.onnx_backbone import BackboneStopped
from service.adaptive import SceneViews
from service.auth import SessionCredentials
from service.errors import ServiceError, bad_input, saturated
from service.events import status_event, window_event
from service.log_throttle import LogThrottle
from service.metrics import ServiceMetrics
from service.pipeline import AdmittedBlock, SessionEstimator, SessionJob, SessionResult
from service.runtime import Runtime
from service.schemas import SessionCounters
from service.settings import Settings
from service.surface_models import FitOutcome, SessionSurface
from service.visual_queue import EmbeddingQueue
from texture_library.attributes import ATTRIBUTES
from texture_library.channels import UNIT_SCALE
from texture_library.recording import Channel

log = logging.getLogger(__name__)

Publish = Callable[[str, dict, bool], Awaitable[None]]
Notify = Callable[["Session"], None]  # tells the batcher a session has complete windows
FrameOutcome = Literal["ignored", "unchanged", "embedding", "superseded"]
MAX_SEQ = 2**63  # a seq beyond int64 is garbage
RETRY_AFTER_S = 1.0  # a saturated session has seconds of windows queued; retrying sooner only adds load
PUBLISH_YIELD_EVERY = 8  # events published between yields to the event loop


def stream_contract(runtime: Runtime, settings: Settings) -> StreamContract:
    """The stream rules a session of this service enforces (the preprocessor gets the same object)."""
    return StreamContract(
        runtime.tactile_config,
        max_lag_s=settings.max_lag_s,
        max_block_s=settings.max_block_s,
        max_block_windows=settings.max_block_windows,
    )


def canonical_channels(block: SampleBlock) -> dict[str, Channel]:
    """The block's channels in canonical units (m/s², N, mm/s, mm): as they came when already canonical (the
    preprocessor converts to float64 once, on the concatenated blocks), else scaled in their own dtype (float32 off
    the wire): a session's pending samples cost the same whatever units its robot sends."""
    out = {}
    for kind, c in block.channels.items():
        scale = UNIT_SCALE[kind][c.units]
        out[kind] = Channel(c.data if scale == 1.0 else c.data * c.data.dtype.type(scale), c.rate_hz)
    return out


class Session:
    """A session's state on its owner replica (see the module docstring)."""

    def __init__(
        self,
        session_id: str,
        name: str,
        credentials: SessionCredentials,
        runtime: Runtime,
        settings: Settings,
        visual_pool: Executor,
        publish: Publish,
        metrics: ServiceMetrics,
        notify: Notify,
        visual_done: Callable[[int], None] = lambda pixels: None,
        visual_queue: EmbeddingQueue | None = None,
        *,
        robot: str | None = None,
        first_seq: int = 0,
    ) -> None:
        self.id = session_id
        self.robot = robot  # the robot's own id: operators follow it across its sessions
        # a robot resuming after its session was lost goes on with its own numbering: its first block is first_seq
        self.first_seq = first_seq
        self.name = name
        self.credentials = credentials
        self.runtime = runtime
        self.settings = settings
        self.created_at = time.time()
        # last_activity: its robot's last block or frame (what counts it as streaming); last_contact: its robot's last
        # sign of any kind, a try refused for capacity too (what keeps it from being reaped as abandoned)
        self.opened_at = self.last_activity = self.last_contact = time.monotonic()
        self.last_seq = -1
        self.counters = SessionCounters()
        # what anyone who knows the session's id can make it tell its operators (a refused ingest connection)
        self.notices = LogThrottle(log)
        self.contract = stream_contract(runtime, settings)
        self.cursor = self.contract.start()
        self.estimator = SessionEstimator.from_settings(runtime, self.contract, settings)
        self.visual: np.ndarray | None = None  # the current scene's pooled visual input (policy.views_pooled frames)
        self.frame_checks: dict[str, FrameCheck | None] = {}  # of self.visual, per visual model
        self._scene = SceneViews(runtime.policy, settings.frame_change)
        self._visual_pool = visual_pool
        self._publish = publish
        self._metrics = metrics
        self._notify = notify
        self._visual_done = visual_done
        # the replica's embedding queue (admission reads its delay and bounds it in time); its own when alone
        self._visual_queue = EmbeddingQueue() if visual_queue is None else visual_queue
        # a frame of this session was refused under load (frames degraded) and none embedded since: its windows are
        # estimated tactile-only and marked missing the frame
        self.frames_shed = False
        # pixels of the frames the embedding job holds (the one it embeds, the one waiting for it): what the caller
        # charged to the visual queue, given back through visual_done as each is done with
        self._embedding_pixels = 0
        self._pending: list[AdmittedBlock] = []
        self._pending_added: list[int] = []  # windows each pending block completes
        self._pending_windows = 0  # windows the pending blocks complete
        self._windows_admitted = 0  # complete windows admitted, all segments
        self._windows_done = 0  # of those, estimated and published (or lost to a failed job)
        self._frame: tuple[np.ndarray, bool] | None = None  # (gray, starts a new scene) waiting for the embedder
        self._told_waiting = False
        self._told_waiting_taps = False
        self._taps: np.ndarray | None = None  # tap features of the surface now under the tool (taps models)
        self._tapped_scene: np.ndarray | None = None  # thumbnail of the tapped surface (its first frame after the taps)
        self._chosen_scene: np.ndarray | None = None  # thumbnail of the scene the rendered entry was chosen on
        self._told_missing_taps = False
        self._embedder: asyncio.Task | None = None
        # the session's learnt surface model (None: settings.surface_model is off) and the library entry the selection
        # rule picked last (its prior)
        self.surface = SessionSurface(session_id) if settings.surface_model else None
        self.library_pick: str | None = None
        self.in_job = False  # set by the batcher while the session's blocks are being estimated
        self.decoding_frame = False  # set by POST /frames while one of its frames is decoded (frame pool)
        self.closed = False
        # set each time windows leave the backlog (a job's result) or the session closes: a robot's socket whose
        # session is saturated waits on it instead of being closed (wait_for_room)
        self._backlog_fell = asyncio.Event()

    # ---- ingest (event loop) ---------------------------------------------------------------------
    def touch(self) -> None:
        self.last_activity = self.last_contact = time.monotonic()

    def heard(self) -> None:
        """Its robot tried (a block or frame refused for capacity): it is there, but it did not stream."""
        self.last_contact = time.monotonic()

    def ingest(self, block: Block, arrived_ns: int) -> dict:
        """Admit one decoded block → the acknowledgement {seq, duplicate, windows_ready}.

        ServiceError 422 when the block contradicts the stream or its seq is unusable, 429 when its windows
        would not fit the session's queue; nothing is taken then.
        """
        self.touch()
        if block.seq >= MAX_SEQ:
            raise ServiceError(422, f"seq must be below 2^63, got {block.seq}")
        if block.seq <= self.last_seq or block.seq < self.first_seq:  # below first_seq: its previous session's
            self.counters.blocks_duplicate += 1
            return {"seq": block.seq, "duplicate": True, "windows_ready": self.backlog()}
        if block.seq - max(self.last_seq, self.first_seq) > self.settings.max_seq_gap:
            raise ServiceError(
                422,
                f"seq jumps from {self.last_seq} to {block.seq}, more than max_seq_gap "
                f"({self.settings.max_seq_gap}) blocks; send the blocks that follow {self.last_seq}, "
                "or open a new session for a new stream",
            )
        if isinstance(block, TapBlock):
            return self._ingest_taps(block)
        try:
            advance = self.contract.admit(self.cursor, canonical_channels(block), block.t0)
        except ValueError as exc:
            raise bad_input(exc) from None
        if (
            self.backlog() + advance.windows_added > self.settings.session_queue_windows
            or len(self._pending) >= self.settings.session_queue_blocks
        ):
            self.counters.blocks_refused += 1
            why = self.waiting_for()
            raise saturated(
                f"session {self.id} is saturated ({self.backlog()} windows, {len(self._pending)} blocks waiting"
                f"{'; ' + why if why else ''}); resend block {block.seq} later",
                RETRY_AFTER_S,
            )
        self.cursor = advance.cursor  # a new segment keeps the surface's taps: a gap does not move the tool
        self._pending.append(
            AdmittedBlock(
                block.seq,
                advance.cursor.segment,
                advance.cursor.origin_t0,
                advance.channels,
                advance.windows_after,
                arrived_ns,
                self._taps,
            )
        )
        self._pending_added.append(advance.windows_added)
        self._pending_windows += advance.windows_added
        self._windows_admitted += advance.windows_added
        if advance.windows_added:
            self._metrics.windows_admitted.inc(advance.windows_added)
        self.last_seq = block.seq
        self.counters.blocks_accepted += 1
        if self._pending_windows:
            self._notify(self)
        return {"seq": block.seq, "duplicate": False, "windows_ready": self.backlog()}

    def _ingest_taps(self, block: TapBlock) -> dict:
        """A tap block: its features for a taps model (422 if they cannot be computed), ignored otherwise; its
        transients for the learnt surface model either way."""
        if self.surface is not None:
            scale = UNIT_SCALE["accel"][block.accel.units]
            self.surface.queue_taps(block.speeds, block.accel.data.astype(np.float64) * scale, block.accel.rate_hz)
        if self.runtime.needs_taps:
            accel = block.accel
            scale = UNIT_SCALE["accel"][accel.units]
            try:
                features = tap_features(block.speeds, accel.data.astype(np.float64) * scale, accel.rate_hz)
            except ValueError as exc:
                raise bad_input(exc) from None
            self._taps, self._tapped_scene = features, None  # the next frame shows the tapped surface
            self._told_waiting_taps = self._told_missing_taps = False  # the next untapped surface is told again
            # blocks admitted before the taps were waiting for them (or for the untapped model): they are of
            # this surface, which the camera has not seen change since
            for i, b in enumerate(self._pending):
                if b.taps is None:
                    self._pending[i] = replace(b, taps=features)
            self.counters.tap_blocks_used += 1
        else:
            self.counters.tap_blocks_ignored += 1
        self.last_seq = block.seq
        self.counters.blocks_accepted += 1
        if self._pending_windows:
            self._notify(self)
        return {"seq": block.seq, "duplicate": False, "windows_ready": self.backlog()}

    @property
    def embedding_pixels(self) -> int:
        """Pixels of the frames this session's embedding job holds: the one it embeds and the one waiting for it."""
        return self._embedding_pixels

    def backlog(self) -> int:
        """Complete windows admitted and not yet published (0 when the pipeline keeps up)."""
        return self._windows_admitted - self._windows_done

    async def wait_for_room(self, timeout_s: float) -> bool:
        """While the session is saturated by its own backlog of windows (which the pool drains by itself: nothing
        waits for a frame or taps), wait up to `timeout_s` (s) for it to fall below the bound, costing no CPU; the
        robot's next blocks wait unread in its connection meanwhile (its socket is not read: the bound on what is
        held stays). True when a block completing a window would be admitted now (as far as the backlog says)."""
        deadline = time.monotonic() + timeout_s
        while self.saturated() and not self.closed and self.waiting_for() is None:
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            self._backlog_fell.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._backlog_fell.wait(), left)
        return not self.closed and not self.saturated()

    def saturated(self) -> bool:
        """True when the next block that completes a window would be refused."""
        return (
            self.backlog() >= self.settings.session_queue_windows
            or len(self._pending) >= self.settings.session_queue_blocks
        )

    # ---- estimation (called by the batcher) ------------------------------------------------------------
    def waiting_for_frame(self) -> bool:
        """True while windows must wait: a visual model, no embedding yet, and no tactile-only model."""
        return self.visual is None and not self.runtime.can_estimate_without_frame

    def waiting_for_taps(self) -> bool:
        """True while windows must wait: a taps model without an untapped fallback, and a pending block whose
        surface has not been tapped."""
        return self.missing_taps() and self.runtime.untapped is None

    def waiting_for(self) -> str | None:
        """What the session's windows wait for, in a few words a robot's operator can act on (None: nothing)."""
        if self.waiting_for_frame():
            return "its windows wait for a first camera frame (the model reads images): send one"
        if self.waiting_for_taps():
            return "its windows wait for a tap block of this surface (the model reads taps): send one (robot --taps)"
        return None

    def missing_taps(self) -> bool:
        """True when a pending block's surface has not been tapped (a taps model)."""
        return self.runtime.needs_taps and any(b.taps is None for b in self._pending)

    def take_job(self, max_windows: int | None = None) -> SessionJob | None:
        """Hand the pending blocks to an estimation job; None when there is nothing to do or windows wait for
        the first frame or for the surface's taps (the blocks then stay, counting against the bounds: the wait
        ends in 429s, not memory). max_windows: take only the oldest blocks, those that complete at most that many
        windows (at least the first window's); the rest stay pending, in order, for the next job."""
        if self.closed or not self._pending or self.waiting_for_frame() or self.waiting_for_taps():
            return None
        cut, windows = len(self._pending), self._pending_windows
        if max_windows is not None and windows > max_windows:
            windows = 0
            for i, added in enumerate(self._pending_added):
                if windows and windows + added > max_windows:
                    cut = i
                    break
                windows += added
        blocks, self._pending = self._pending[:cut], self._pending[cut:]
        self._pending_added = self._pending_added[cut:]
        self._pending_windows -= windows
        return SessionJob(
            self.estimator,
            blocks,
            self.visual,
            windows,
            self.frame_checks,
            self.frames_shed and self.visual is None,
            self.surface,
        )

    async def tell_waiting(self) -> None:
        """Tell operators, once, why windows wait."""
        if self.waiting_for_taps() and not self.waiting_for_frame():
            if not self._told_waiting_taps:
                self._told_waiting_taps = True
                await self._status(
                    "waiting_for_taps",
                    f"model {self.runtime.model_name} reads tap features and the "
                    "surface under the tool has not been tapped; windows wait for a tap block, at most "
                    f"{self.settings.session_queue_windows} of them, then blocks are refused (429); no untapped "
                    "fallback model is configured (HAPTICLINK_TACTILE_MODEL_PATH)",
                    send="taps",
                )
            return
        if not self._told_waiting:
            self._told_waiting = True
            await self._status(
                "waiting_for_frame",
                f"model {self.runtime.model_name} needs a camera frame and no "
                "tactile-only model is configured (HAPTICLINK_TACTILE_MODEL_PATH); windows wait for the "
                f"first frame, at most {self.settings.session_queue_windows} of them, then blocks are refused (429)",
            )

    async def apply_result(self, result: SessionResult) -> None:
        """Publish a job's windows (yielding to the event loop every few events); after a failure the stream
        restarts cleanly at the next block."""
        self._windows_done += result.windows
        self._backlog_fell.set()
        if self.closed:
            return
        if result.error is not None:
            log.error("session %s: estimation failed: %r", self.id, result.error, exc_info=result.error)
            self.counters.pipeline_errors += 1
            self.cursor = self.cursor.restarted()
            await self._status(
                "error",
                f"estimation failed ({type(result.error).__name__}: {result.error}); "
                "the stream restarts at the next block",
            )
            return
        if not self._told_missing_taps and any("taps" in w.missing for w in result.estimates):
            self._told_missing_taps = True
            untapped = self.runtime.untapped
            await self._status(
                "input_missing",
                f"model {self.runtime.model_name} reads tap features and the surface under the tool has not been "
                f"tapped{' since the scene changed' if self._tapped_scene is not None else ''}; its windows are "
                f"estimated by {untapped.name if untapped else 'the fallback model'} without them (marked "
                "missing_inputs) until the robot sends a tap block of this surface",
                missing="taps",
                send="taps",
            )
        for i, w in enumerate(result.estimates):
            if i and i % PUBLISH_YIELD_EVERY == 0:
                await asyncio.sleep(0)  # many events: let ingest and /health run between them
            self.library_pick = w.chosen
            served = None if self.surface is None else self.surface.served
            if served is not None:  # operators render the surface's own model; the rule's pick is its prior
                w = replace(w, chosen=served.model.id, chosen_model_version=served.version, library_pick=w.chosen)
            event = window_event(self.id, w, time.perf_counter_ns())
            for missing in w.missing:
                self._metrics.windows_degraded.labels(missing=missing).inc()
            await self._publish(self.id, event, False)
            self._observe(event["latency_ms"])
        self.counters.windows += len(result.estimates)
        await self._tell_surface()

    async def apply_fit(self, outcome: FitOutcome) -> None:
        """A fit of the learnt surface model (service.surface_models): serve its new version, if any (the next window
        events name it), and tell bad input once."""
        if self.closed or self.surface is None:
            return
        if outcome.served is not None and outcome.generation == self.surface.generation:  # not of a surface left
            self.surface.serve(outcome.served, outcome.learnt)
        await self._tell_surface()

    async def _tell_surface(self) -> None:
        if self.surface is None:
            return
        for reason in self.surface.untold():
            keeps = "the library pick" if self.surface.served is None else "its last version"
            await self._status(
                "surface_model",
                f"the session's learnt surface model keeps {keeps}: {reason.value}",
                reason=reason.name,
            )

    def has_work(self) -> bool:
        return not self.closed and self._pending_windows > 0

    def _observe(self, latency_ms: dict[str, float]) -> None:
        self._metrics.windows.inc()
        for stage, ms in latency_ms.items():
            self._metrics.latency.labels(stage=stage).observe(ms / 1e3)

    async def _status(self, event: str, message: str, **extra: object) -> None:
        await self._publish(self.id, status_event(self.id, event, message, **extra), False)  # type: ignore[arg-type]

    # ---- frames ----------------------------------------------------------------------------------
    def offer_frame(self, gray: np.ndarray, thumb: np.ndarray) -> FrameOutcome:
        """A decoded frame (and its scene_change.thumbnail): embedded when the serving policy says so (adaptive:
        a changed scene and its first pool_frames frames; always-full: every frame).

        ignored: the model reads no images; unchanged: the policy does not embed it (same scene, already
        pooled); embedding: an embedding job starts (the caller charges the frame's pixels to the visual queue until
        `visual_done` gives them back); superseded: replaces a frame waiting for the running embedding job."""
        self.touch()
        self.counters.frames_received += 1
        self._release_choice_on_new_scene(thumb)
        if self.runtime.needs_taps:
            self._watch_surface(thumb)
        if not self.runtime.needs_visual:
            return "ignored"
        take, changed = self._scene.offer(thumb)
        if not take:
            self.counters.frames_unchanged += 1
            return "unchanged"
        if self._embedder is not None and not self._embedder.done():
            new_scene = changed
            if self._frame is not None:
                self.counters.frames_superseded += 1
                new_scene = new_scene or self._frame[1]
                self._embedding_pixels -= self._frame[0].size
            self._frame = (gray, new_scene)
            self._embedding_pixels += gray.size
            return "superseded"
        self._frame = (gray, changed)
        self._embedding_pixels = gray.size
        self._embedder = asyncio.create_task(self._embed_frames(), name=f"embed-{self.id}")
        return "embedding"

    def frame_wanted(self, thumb: np.ndarray) -> str | None:
        """A robot's scene check (its newest frame's scene_change.thumbnail, in place of the frame): why the session
        wants that frame, or None when offer_frame would change nothing with it (the scene it holds, no view to add).
        One question per scene memory offer_frame keeps — the chosen entry's, the tapped surface's, the pooled
        views' — so that a held frame is one offer_frame would have dropped (a test holds the two together)."""
        self.touch()
        if self._chosen_scene is None:
            return "no frame of this session has been received"
        if scene_changed(self._chosen_scene, thumb, self.settings.frame_change):
            return "the scene changed since the last frame received"
        if self.runtime.needs_taps and self._taps is not None:
            if self._tapped_scene is None:
                return "no frame shows the tapped surface yet"
            if scene_changed(self._tapped_scene, thumb, self.settings.frame_change):
                return "the scene changed since the frame of the tapped surface"
        if self.runtime.needs_visual and self._scene.wants(thumb):
            return "the model embeds another view of this scene"
        return None

    def _release_choice_on_new_scene(self, thumb: np.ndarray) -> None:
        """A frame of another scene: the tool is over another surface, so the entry chosen for the last one is not
        held against the new one's by hysteresis (HysteresisChooser.release). Whatever the model reads: a
        tactile-only model's choice changes with the surface too."""
        if not scene_changed(self._chosen_scene, thumb, self.settings.frame_change):
            return
        if self._chosen_scene is not None:  # the first frame shows the surface the session started on
            self.estimator.selector.release()
            if self.surface is not None:
                self.surface.scene_changed()
        self._chosen_scene = thumb

    def _watch_surface(self, thumb: np.ndarray) -> None:
        """Taps models: the first frame after a tap block shows the tapped surface; a later frame of another scene
        means the tool is over another surface, whose taps are not known (blocks from now on carry none)."""
        if self._taps is None:
            return
        if self._tapped_scene is None:
            self._tapped_scene = thumb
        elif scene_changed(self._tapped_scene, thumb, self.settings.frame_change):
            log.info("session %s: the scene changed; the tapped surface's features no longer apply", self.id)
            self._taps = None
            self._told_waiting_taps = self._told_missing_taps = False

    async def _embed_frames(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            while self._frame is not None:
                (gray, new_scene), self._frame = self._frame, None
                started = time.perf_counter()
                job = self._visual_queue.submit()
                try:
                    vector, reasons = await loop.run_in_executor(
                        self._visual_pool, job.run, self.runtime.embed_and_inspect, gray
                    )
                except BackboneStopped:
                    return  # the service is shutting down: nothing failed
                except Exception as exc:  # noqa: BLE001 - a frame that cannot be embedded must not end the session
                    log.exception("session %s: embedding a frame failed", self.id)
                    self.counters.pipeline_errors += 1
                    self._scene.forget()  # the next frame is tried whatever it shows
                    await self._status("error", f"embedding the frame failed ({type(exc).__name__}: {exc})")
                    continue
                finally:
                    self._visual_queue.done(job)
                    self._give_back_pixels(gray.size)
                seconds = time.perf_counter() - started
                self._metrics.visual_seconds.observe(seconds)
                first = self.visual is None
                self.visual = self._scene.add(vector, new_scene)
                self.frames_shed = False
                self.frame_checks = self.runtime.frame_checks(reasons, self.visual)
                self.counters.frames_embedded += 1
                flagged = sorted({r for c in self.frame_checks.values() if c is not None for r in c.reasons})
                await self._status(
                    "visual_updated",
                    "visual embedding updated" + (" (first frame)" if first else ""),
                    embed_ms=round(seconds * 1e3, 1),
                    views=self._scene.views,
                    frame_reasons=flagged,
                )
                if self.has_work():
                    self._notify(self)
        finally:
            self._give_back_pixels(self._embedding_pixels)  # a frame left waiting when the job ended early

    def _give_back_pixels(self, pixels: int) -> None:
        self._embedding_pixels -= pixels
        self._visual_done(pixels)

    # ---- lifecycle -------------------------------------------------------------------------------
    async def close(self) -> None:
        """Stop the embedder; an estimation job in flight finishes, but its windows are not published."""
        self.closed = True
        self._backlog_fell.set()
        if self._embedder is not None and not self._embedder.done():
            self._embedder.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._embedder

    def state(self) -> str:
        if self.waiting_for_frame():
            return "waiting_for_frame"
        if self.waiting_for_taps():
            return "waiting_for_taps"
        return "saturated" if self.saturated() else "streaming" if self.streamed else "open"

    @property
    def streamed(self) -> bool:
        """Whether a block has been accepted."""
        return self.last_seq >= 0

    def status(self) -> dict:
        """What GET /sessions/{id} answers."""
        return {
            "session_id": self.id,
            "name": self.name,
            "robot": self.robot,
            "instance": self.settings.instance_id,
            "state": self.state(),
            "created_at": round(self.created_at, 3),
            "idle_s": round(time.monotonic() - self.last_activity, 3),
            "model": self.runtime.model_name,
            "needs_visual": self.runtime.needs_visual,
            "visual_ready": self.visual is not None,
            "last_seq": self.last_seq,
            "segments": self.cursor.segment + 1,
            "windows_ready": self.backlog(),
            "pending_blocks": len(self._pending),
            "counters": asdict(self.counters),
            "backbone": None if self.runtime.backbone_status is None else self.runtime.backbone_status.to_dict(),
            "surface_model": None if self.surface is None else {**self.surface.status(), "ratings": self._ratings()},
        }

    def _ratings(self) -> dict[str, float] | None:
        """The session's smoothed ratings now (None before its first window)."""
        smoothed = self.estimator.smoother.state
        return None if smoothed is None else dict(zip(ATTRIBUTES, map(float, np.round(smoothed, 2)), strict=True))
