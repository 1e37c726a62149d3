"""One streaming session on the event loop: admission, its bounded queue of pending blocks, its frames.

    ingest (loop) ─▶ StreamAdmission.admit ─▶ pending blocks ─(a window is complete)─▶ WindowBatcher
    batcher: the session's blocks, with other sessions', estimated in the window pool ─▶ apply_result ─▶ broker
    frames: decode (window pool) ─▶ latest-frame slot ─▶ embed (visual pool, one at a time)

Bounds: pending blocks ≤ session_queue_blocks and complete-but-unprocessed windows <
session_queue_windows, else ingest is refused (429 / close 4429) without taking anything; a
session is in at most one estimation job and one embedding job at a time; frames arriving during
an embedding replace each other (only the newest is embedded).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import Executor
from dataclasses import asdict

import numpy as np

from drivers.blocks import SampleBlock
from service.auth import SessionCredentials
from service.errors import ServiceError, bad_input, saturated
from service.events import status_event, window_event
from service.metrics import ServiceMetrics
from service.pipeline import SessionEstimator, SessionJob, SessionResult
from service.runtime import Runtime
from service.schemas import SessionCounters
from service.settings import Settings
from service.stream import StreamAdmission

log = logging.getLogger(__name__)

Publish = Callable[[str, dict, bool], Awaitable[None]]
Notify = Callable[["Session"], None]  # tells the batcher a session has complete windows
MAX_SEQ = 2**63  # a seq beyond int64 is garbage, and accepting it would make every later block a duplicate
RETRY_AFTER_S = 1.0  # a saturated session has seconds of windows queued; retrying sooner only adds load


class Session:
    """A session's state on its owner replica (see the module docstring)."""

    def __init__(self, session_id: str, name: str, credentials: SessionCredentials, runtime: Runtime,
                 settings: Settings, window_pool: Executor, visual_pool: Executor, publish: Publish,
                 metrics: ServiceMetrics, notify: Notify) -> None:
        self.id = session_id
        self.name = name
        self.credentials = credentials
        self.runtime = runtime
        self.settings = settings
        self.created_at = time.time()
        self.last_activity = time.monotonic()
        self.last_seq = -1
        self.counters = SessionCounters()
        self.admission = StreamAdmission(runtime.tactile_config, settings.max_lag_s)
        self.estimator = SessionEstimator(
            runtime, alpha=settings.smoothing_alpha, confidence_windows=settings.confidence_windows,
            top_k=settings.top_k, hysteresis_margin=settings.hysteresis_margin,
            hysteresis_hold=settings.hysteresis_hold, max_buffer_s=settings.max_lag_s + 1.0,
        )
        self.visual: np.ndarray | None = None
        self._window_pool = window_pool
        self._visual_pool = visual_pool
        self._publish = publish
        self._metrics = metrics
        self._notify = notify
        self._pending: list = []
        self._frame: np.ndarray | None = None
        self._told_waiting = False
        self._embedder: asyncio.Task | None = None
        self.in_job = False  # set by the batcher while the session's blocks are being estimated
        self.decoding_frame = False  # set by POST /frames while one of its frames is in the window pool
        self.closed = False

    # ---- ingest (event loop) ---------------------------------------------------------------------
    def touch(self) -> None:
        self.last_activity = time.monotonic()

    def ingest(self, block: SampleBlock, arrived_ns: int) -> dict:
        """Admit one decoded block → the acknowledgement {seq, duplicate, windows_ready}.

        ServiceError 429 when saturated, 422 when the block contradicts the stream; nothing is taken then.
        """
        self.touch()
        if block.seq >= MAX_SEQ:
            raise ServiceError(422, f"seq must be below 2^63, got {block.seq}")
        if block.seq <= self.last_seq:
            self.counters.blocks_duplicate += 1
            return {"seq": block.seq, "duplicate": True, "windows_ready": self.admission.backlog()}
        if self.saturated():
            self.counters.blocks_refused += 1
            raise saturated(
                f"session {self.id} is saturated ({self.admission.backlog()} windows, {len(self._pending)} blocks "
                f"waiting); resend block {block.seq} later", RETRY_AFTER_S)
        try:
            admitted = self.admission.admit(block, arrived_ns)
        except ValueError as exc:
            raise bad_input(exc) from None
        self._pending.append(admitted)
        self.last_seq = block.seq
        self.counters.blocks_accepted += 1
        backlog = self.admission.backlog()
        if backlog:
            self._notify(self)
        return {"seq": block.seq, "duplicate": False, "windows_ready": backlog}

    def saturated(self) -> bool:
        """True when ingest must refuse (429 / close 4429) until the pipeline catches up."""
        return (self.admission.backlog() >= self.settings.session_queue_windows
                or len(self._pending) >= self.settings.session_queue_blocks)

    # ---- estimation (called by the batcher) ------------------------------------------------------------
    def waiting_for_frame(self) -> bool:
        return self.runtime.needs_visual and self.visual is None

    def take_job(self) -> SessionJob | None:
        """Hand the pending blocks to an estimation job; None when there is nothing to do or a visual
        model still waits for its first frame (the blocks then stay, counting against the bound)."""
        if self.closed or not self._pending or self.waiting_for_frame():
            return None
        blocks, self._pending = self._pending, []
        return SessionJob(self.estimator, blocks, self.visual)

    async def tell_waiting(self) -> None:
        """Tell operators, once, that windows wait for a camera frame."""
        if not self._told_waiting:
            self._told_waiting = True
            await self._status("waiting_for_frame", f"model {self.runtime.model_name} needs a camera frame; windows wait for it")

    async def apply_result(self, result: SessionResult) -> None:
        """Publish a job's windows; after a failure the stream restarts cleanly at the next block."""
        if self.closed:
            return
        if result.error is not None:
            log.error("session %s: estimation failed: %r", self.id, result.error)
            self.counters.pipeline_errors += 1
            self.admission.break_segment()
            await self._status("error", f"estimation failed ({type(result.error).__name__}: {result.error}); "
                                        "the stream restarts at the next block")
            return
        self.admission.note_taken(result.segment, result.taken)
        for w in result.estimates:
            event = window_event(self.id, self.runtime.model_name, w, time.perf_counter_ns())
            await self._publish(self.id, event, False)
            self._observe(event["latency_ms"])
        self.counters.windows += len(result.estimates)

    def has_work(self) -> bool:
        return not self.closed and bool(self._pending) and self.admission.backlog() > 0

    def _observe(self, latency_ms: dict[str, float]) -> None:
        self._metrics.windows.inc()
        for stage, ms in latency_ms.items():
            self._metrics.latency.observe(ms / 1e3, stage=stage)

    async def _status(self, event: str, message: str, **extra: object) -> None:
        await self._publish(self.id, status_event(self.id, event, message, **extra), False)  # type: ignore[arg-type]

    # ---- frames ----------------------------------------------------------------------------------
    def offer_frame(self, gray: np.ndarray) -> bool:
        """Keep a decoded frame for embedding; True if it will be used (the model reads images)."""
        self.touch()
        self.counters.frames_received += 1
        if not self.runtime.needs_visual:
            return False
        if self._frame is not None:
            self.counters.frames_superseded += 1
        self._frame = gray
        if self._embedder is None or self._embedder.done():
            self._embedder = asyncio.create_task(self._embed_frames(), name=f"embed-{self.id}")
        return True

    async def _embed_frames(self) -> None:
        loop = asyncio.get_running_loop()
        while self._frame is not None:
            gray, self._frame = self._frame, None
            started = time.perf_counter()
            try:
                vector = await loop.run_in_executor(self._visual_pool, self.runtime.embed_frame, gray)
            except Exception as exc:  # noqa: BLE001 - a frame that cannot be embedded must not end the session
                log.exception("session %s: embedding a frame failed", self.id)
                self.counters.pipeline_errors += 1
                await self._status("error", f"embedding the frame failed ({type(exc).__name__}: {exc})")
                continue
            seconds = time.perf_counter() - started
            self._metrics.visual_seconds.observe(seconds)
            first = self.visual is None
            self.visual = vector
            self.counters.frames_embedded += 1
            await self._status("visual_updated", "visual embedding updated" + (" (first frame)" if first else ""),
                               embed_ms=round(seconds * 1e3, 1))
            if self.has_work():
                self._notify(self)

    # ---- lifecycle -------------------------------------------------------------------------------
    async def close(self) -> None:
        """Stop the embedder; an estimation job in flight finishes, but its windows are not published."""
        self.closed = True
        if self._embedder is not None and not self._embedder.done():
            self._embedder.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._embedder

    def state(self) -> str:
        if self.runtime.needs_visual and self.visual is None:
            return "waiting_for_frame"
        return "saturated" if self.saturated() else "streaming" if self.last_seq >= 0 else "open"

    def status(self) -> dict:
        """What GET /sessions/{id} answers."""
        return {
            "session_id": self.id,
            "name": self.name,
            "instance": self.settings.instance_id,
            "state": self.state(),
            "created_at": round(self.created_at, 3),
            "idle_s": round(time.monotonic() - self.last_activity, 3),
            "model": self.runtime.model_name,
            "needs_visual": self.runtime.needs_visual,
            "visual_ready": self.visual is not None,
            "last_seq": self.last_seq,
            "segments": self.admission.segment + 1 if self.last_seq >= 0 else 0,
            "windows_ready": self.admission.backlog(),
            "pending_blocks": len(self._pending),
            "counters": asdict(self.counters),
        }


def session_not_found(session_id: str) -> ServiceError:
    return ServiceError(404, f"no session {session_id!r}")


def session_lost(session_id: str, reason: str) -> ServiceError:
    """410: the session existed, but the replica holding its state is gone; nothing can resume it."""
    return ServiceError(410, f"session {session_id} is lost: {reason}; open a new session")
