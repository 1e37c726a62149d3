"""The service's state: what one process holds between start-up and shutdown, and its lifecycle.

    ServiceState
      ├─ runtime      the model, library and backbone (loaded and warmed up in the background; /ready)
      ├─ bus          EventBus: events to operators (service/bus.py)
      ├─ directory    SessionDirectory: sessions here and elsewhere, auth, heartbeats, reaping (service/directory.py)
      ├─ blocks       BlockIntake: sample and tap blocks, bytes in (service/intake.py)
      ├─ frames       FrameIntake: camera frames, bytes in (service/intake.py)
      ├─ capacity     CapacityGuard: refuses new sessions and blocks the process cannot serve (service/capacity.py)
      ├─ batcher      WindowBatcher over the window pool (service/batcher.py)
      ├─ probes       ProbeServer: /health and /ready from a thread of their own, if a probe port is set
      └─ pools        window pool, frame (decode) pool, visual (embedding) pool

Routes are thin: dependencies (service/deps.py) hand them the parts they need; everything that can
be refused raises ServiceError with the status and message the client gets.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import sys
import time
from concurrent.futures import ThreadPoolExecutor

from service.auth import SessionCredentials
from service.batcher import WindowBatcher
from service.broker import Broker, make_broker
from service.bus import EventBus
from service.capacity import CapacityGuard
from service.directory import SessionDirectory
from service.errors import ServiceError
from service.fleet import ApiKeys, TokenBucket
from service.intake import BlockIntake, FrameIntake
from service.live_session import Session
from service.log_throttle import LogThrottle
from service.metrics import ServiceMetrics
from service.probes import ProbeServer, health, readiness_report
from service.runtime import Runtime, load_runtime
from service.schemas import HealthOut, ReadyOut
from service.settings import Settings
from service.thread_cpu import CpuMeter, ThreadCpu, lower_priority
from service.visual_queue import EmbeddingQueue
from service.warmup import warm_up

log = logging.getLogger(__name__)


class ServiceState:
    """Create with settings, `await start()` inside the event loop, `await close()` at shutdown. `cpu_meter`: what
    admission measures the service's threads by (a `ThreadCpu` of its own by default)."""

    def __init__(self, settings: Settings, cpu_meter: CpuMeter | None = None) -> None:
        self.settings = settings
        self.metrics = ServiceMetrics()
        self.broker: Broker = make_broker(
            settings.broker,
            subscriber_queue=settings.subscriber_queue,
            redis_url=settings.redis_url,
            instance_id=settings.instance_id,
        )
        self.runtime: Runtime | None = None
        self.load_error: str | None = None
        # admission measures the CPU of these pools' threads with the loop's (they share its GIL)
        self.threads: CpuMeter = cpu_meter if cpu_meter is not None else ThreadCpu()
        self.window_pool = ThreadPoolExecutor(
            settings.pool_threads, thread_name_prefix="hapticlink-window", initializer=self.threads.register
        )
        # the visual path has pools of its own, never the window pool: windows do not wait behind images.
        # Decoding (milliseconds) has its own thread so that it never waits behind an embedding (up to a second).
        self.frame_pool = ThreadPoolExecutor(
            1, thread_name_prefix="hapticlink-frames", initializer=self._start_visual_thread
        )
        self.visual_pool = ThreadPoolExecutor(
            1, thread_name_prefix="hapticlink-visual", initializer=self._start_visual_thread
        )
        # what frames wait for the visual pool, measured apart from the windows' queue (service/visual_queue.py)
        self.embedding_queue = EmbeddingQueue()
        self.bus = EventBus(self.broker, self.metrics)
        self.directory = SessionDirectory(settings, self.broker, self.bus, self.metrics)
        self.capacity = CapacityGuard(
            settings,
            self.metrics,
            lambda: self.directory.sessions.values(),
            lambda now: self.batcher.take_waits(now),
            self.threads.seconds,
            self.embedding_queue,
            self.threads.loop_seconds,
        )
        self.frames = FrameIntake(settings, self.metrics, self.bus, self.frame_pool, self.capacity)
        self.blocks = BlockIntake(self.metrics, self.capacity)
        self.api_keys = ApiKeys(settings.api_keys, settings.api_keys_file)
        self.session_limiter = TokenBucket(settings.session_rate_per_s, settings.session_burst)
        # clients choose how often they are refused: at most one line per kind every 10 s, per service (two in one
        # process — tests, a benchmark — each log their own)
        self.refusal_log = LogThrottle(logging.getLogger("service.access"))
        self.batcher = WindowBatcher(
            self.window_pool, max_jobs=settings.pool_threads, spill_after_s=settings.pool_spill_s
        )
        self._tasks: list[asyncio.Task] = []
        self._warming: Runtime | None = None
        self.probes: ProbeServer | None = None
        self.shutting_down = False  # set as a shutdown begins: nothing new is taken (require_open)

    # ---- lifecycle -------------------------------------------------------------------------------
    async def start(self) -> None:
        # Every socket write releases the GIL; with pool threads computing, getting it back can take a
        # whole switch interval (5 ms by default), per write. A short interval bounds that wait.
        sys.setswitchinterval(self.settings.gil_switch_interval_s)
        if self.settings.probe_port is not None:
            self.probes = ProbeServer(
                self.health_report,
                self.ready_report,
                self.settings.host,
                self.settings.probe_port,
            )
            self.probes.start()
        await self.broker.start()
        self.batcher.start()
        self.capacity.start()
        self._tasks = [
            asyncio.create_task(self._load(), name="load-runtime"),
            asyncio.create_task(self.directory.reap_idle(), name="reap-idle-sessions"),
            asyncio.create_task(self.directory.keep_alive(), name="replica-heartbeat"),
        ]

    async def _load(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            runtime = await loop.run_in_executor(self.window_pool, load_runtime, self.settings)
            self._warming = runtime  # a shutdown during the warm-up stops its embedding too
            warm_s = 0.0
            if runtime.problem is None:
                warm_s = await loop.run_in_executor(self.window_pool, warm_up, runtime, self.settings)
        except Exception as exc:  # noqa: BLE001 - e.g. onnxruntime refusing a corrupt file: /ready must say so
            self.load_error = str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"
            log.error("cannot serve: %s", self.load_error, exc_info=not isinstance(exc, ValueError))
            return
        # Everything loading and warming up allocated lives as long as the process: move it out of the
        # collector's generations, so no later full collection walks it (a 67 ms pause on a pool thread).
        gc.freeze()
        self.runtime = rt = runtime
        self.metrics.ready.set(1 if rt.problem is None else 0)
        log.info(
            "model %s (%s)%s and library %s (%d entries) loaded in %.1f s, warmed up in %.1f s%s",
            rt.model_name,
            rt.predictor.card.modality,
            f" with tactile-only {rt.tactile.card.model}" if rt.tactile else "",
            rt.library.name,
            len(rt.library.ids),
            rt.load_s,
            warm_s,
            f"; NOT READY: {rt.problem}" if rt.problem else "",
        )

    async def end_sessions(self, flush_s: float = 1.0, estimate_s: float = 5.0) -> None:
        """Shutdown, first step: nothing new is taken (`require_open`: 503, ingest sockets closed 1013, so robots keep
        what they have not had acknowledged), the complete windows of acknowledged blocks are estimated and published
        (up to `estimate_s`: an acknowledged block's windows are not dropped by a restart), then every local session
        ends as lost (its state cannot outlive the process) and its operators' feeds get the final event and close
        (1000), waiting up to `flush_s` for them, before the server closes the connections (uvicorn closes every
        WebSocket 1012 before the lifespan shutdown)."""
        self.shutting_down = True
        self.capacity.release_held()  # robots waiting in line for room: answered 503 now, not at the end of their wait
        deadline = time.monotonic() + estimate_s
        while time.monotonic() < deadline and any(
            s.backlog() and not s.waiting_for() for s in self.directory.sessions.values()
        ):
            await asyncio.sleep(0.01)
        await self.directory.end_all(f"its replica {self.settings.instance_id} shut down")
        deadline = time.monotonic() + flush_s
        while self.bus.subscribers and time.monotonic() < deadline:
            await asyncio.sleep(0.01)

    async def close(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        # their state ends with this process: robots are told to open new sessions
        await self.directory.end_all(f"its replica {self.settings.instance_id} shut down")
        await self.capacity.close()
        await self.batcher.close()
        await self.broker.close()
        self.stop_runtime()
        for pool in (self.window_pool, self.frame_pool, self.visual_pool):
            pool.shutdown(wait=False, cancel_futures=True)
        if self.probes is not None:
            self.probes.stop()

    def _start_visual_thread(self) -> None:
        """A visual-path thread (decoding, embedding), as it starts: counted with the service's own, and behind the
        tactile path when the cores are contended (a burst of frames would otherwise slow every session's windows)."""
        self.threads.register()
        if not lower_priority(self.settings.visual_nice):
            log.warning("could not lower a visual thread's priority (HAPTICLINK_VISUAL_NICE); it runs as the rest")

    def stop_runtime(self) -> None:
        """End an embedding in flight (a session's, or the warm-up's) and refuse later ones, so that the pools'
        threads, which the interpreter joins at exit, finish within milliseconds; idempotent."""
        for runtime in {id(r): r for r in (self.runtime, self._warming) if r is not None}.values():
            runtime.stop()

    def readiness(self) -> tuple[bool, str]:
        """(ready, why): ready once the model and library are loaded, cross-checked and warmed up."""
        if self.load_error is not None:
            return False, self.load_error
        if self.runtime is None:
            return False, "loading and warming up the model and library"
        if self.runtime.problem is not None:
            return False, self.runtime.problem
        return True, "ready"

    def health_report(self) -> HealthOut:
        """GET /health: the process runs (and, on either port, which port orchestrators should probe)."""
        return health(self.settings.instance_id, self.probes.port if self.probes is not None else None)

    def ready_report(self) -> tuple[ReadyOut, int]:
        """GET /ready's answer and status (200 ready, 503 not), whichever port or route asks."""
        return readiness_report(self.readiness(), self.runtime)

    def require_open(self) -> None:
        """503 (Retry-After) once a shutdown has begun: no new session, and no block, frame or ingest socket that the
        process could acknowledge but no longer estimate — the robot keeps it and resends it to its next session."""
        if self.shutting_down:
            raise ServiceError(
                503,
                f"replica {self.settings.instance_id} is shutting down; resend after Retry-After (sessions open "
                "again on another replica, or on this one once it is back)",
                {"Retry-After": "1"},
            )

    def require_runtime(self) -> Runtime:
        ready, why = self.readiness()
        if not ready or self.runtime is None:
            raise ServiceError(503, f"not ready: {why}", {"Retry-After": "1"})
        return self.runtime

    # ---- sessions --------------------------------------------------------------------------------
    @property
    def sessions(self) -> dict[str, Session]:
        """This replica's sessions by id (the directory's)."""
        return self.directory.sessions

    async def create_session(
        self, name: str | None, client: str = "local", *, robot: str | None = None, first_seq: int = 0
    ) -> tuple[Session, str, str]:
        """A new session for `client` → (session, robot token, operator token); 503 not ready, 429 when the process
        is at capacity, 503 past max_sessions. robot: the robot's own id (operators follow it); first_seq: the seq
        of its first block (a robot resuming after its session was lost goes on with its own numbering)."""
        self.require_open()
        runtime = self.require_runtime()
        self.capacity.admit_session(len(self.directory.sessions))

        def build(session_id: str, name: str, credentials: SessionCredentials) -> Session:
            return Session(
                session_id,
                name,
                credentials,
                runtime,
                self.settings,
                self.visual_pool,
                self.bus.publish,
                self.metrics,
                self.batcher.notify,
                self.frames.visual_done,
                self.embedding_queue,
                robot=robot,
                first_seq=first_seq,
            )

        return await self.directory.open(name, client, runtime.model_name, build, robot)
