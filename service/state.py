"""The service's state: runtime (loaded in the background), sessions, broker, pools, metrics.

Routes are thin: they authenticate, parse, and call into this object; everything that can be
refused raises ServiceError with the status and message the client gets.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import secrets
import sys
import time
from concurrent.futures import ThreadPoolExecutor

from starlette.requests import Request

from service.auth import Role, SessionCredentials, authorize, issue_credentials
from service.batcher import WindowBatcher
from service.broker import HEARTBEAT_EVERY_S, REPLICA_TTL_S, Broker, SessionRecord, Subscription, make_broker
from service.errors import ServiceError, saturated
from service.events import encode, status_event
from service.fleet import ApiKeys, TokenBucket
from service.metrics import ServiceMetrics
from service.runtime import Runtime, load_runtime
from service.scene_change import thumbnail
from service.schemas import FrameAck
from service.session import RETRY_AFTER_S, Session, session_lost, session_not_found
from service.settings import Settings
from service.warmup import warm_up

log = logging.getLogger(__name__)

REAP_EVERY_S = 5.0


class ServiceState:
    """Create with settings, `await start()` inside the event loop, `await close()` at shutdown."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.metrics = ServiceMetrics()
        self.broker: Broker = make_broker(
            settings.broker,
            subscriber_queue=settings.subscriber_queue,
            redis_url=settings.redis_url,
            instance_id=settings.instance_id,
        )
        self.sessions: dict[str, Session] = {}
        self.runtime: Runtime | None = None
        self.load_error: str | None = None
        self.window_pool = ThreadPoolExecutor(settings.pool_threads, thread_name_prefix="hapticlink-window")
        # the visual path has pools of its own, never the window pool: windows do not wait behind images.
        # Decoding (milliseconds) has its own thread so that it never waits behind an embedding (up to a second).
        self.frame_pool = ThreadPoolExecutor(1, thread_name_prefix="hapticlink-frames")
        self.visual_pool = ThreadPoolExecutor(1, thread_name_prefix="hapticlink-visual")
        self.visual_load = 0  # frames being decoded or waiting for/in an embedding, all sessions (≤ visual_queue)
        self.api_keys = ApiKeys(settings.api_keys, settings.api_keys_file)
        self.session_limiter = TokenBucket(settings.session_rate_per_s, settings.session_burst)
        self.batcher = WindowBatcher(self.window_pool, max_jobs=settings.pool_threads)
        self._tasks: list[asyncio.Task] = []
        self._subscribers = 0
        self._last_publish_error = 0.0

    # ---- lifecycle -------------------------------------------------------------------------------
    async def start(self) -> None:
        # Every socket write releases the GIL; with pool threads computing, getting it back can take a
        # whole switch interval (5 ms by default), per write. A short interval bounds that wait.
        sys.setswitchinterval(self.settings.gil_switch_interval_s)
        await self.broker.start()
        self.batcher.start()
        self._tasks = [
            asyncio.create_task(self._load(), name="load-runtime"),
            asyncio.create_task(self._reap_idle(), name="reap-idle-sessions"),
            asyncio.create_task(self._keep_alive(), name="replica-heartbeat"),
        ]

    async def _load(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            runtime = await loop.run_in_executor(self.window_pool, load_runtime, self.settings)
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

    async def close(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        for sid in list(self.sessions):  # their state ends with this process: robots are told to open new sessions
            await self.end_session(sid, f"its replica {self.settings.instance_id} shut down", lost=True)
        await self.batcher.close()
        await self.broker.close()
        for pool in (self.window_pool, self.frame_pool, self.visual_pool):
            pool.shutdown(wait=False, cancel_futures=True)

    def readiness(self) -> tuple[bool, str]:
        """(ready, why): ready once the model and library are loaded, cross-checked and warmed up."""
        if self.load_error is not None:
            return False, self.load_error
        if self.runtime is None:
            return False, "loading and warming up the model and library"
        if self.runtime.problem is not None:
            return False, self.runtime.problem
        return True, "ready"

    def require_runtime(self) -> Runtime:
        ready, why = self.readiness()
        if not ready or self.runtime is None:
            raise ServiceError(503, f"not ready: {why}", {"Retry-After": "1"})
        return self.runtime

    # ---- sessions --------------------------------------------------------------------------------
    async def create_session(self, name: str | None, client: str = "local") -> tuple[Session, str, str]:
        """A new session for `client` (its address, for the log) → (session, robot token, operator token)."""
        runtime = self.require_runtime()
        if len(self.sessions) >= self.settings.max_sessions:
            raise ServiceError(
                503, f"this replica already runs {len(self.sessions)} sessions (max_sessions)", {"Retry-After": "5"}
            )
        # The replica's name prefixes the id so a load balancer can send all of a session's traffic here.
        session_id = f"{self.settings.instance_id}.{secrets.token_urlsafe(9)}"
        robot, operator, credentials = issue_credentials()
        name = name or session_id
        session = Session(
            session_id,
            name,
            credentials,
            runtime,
            self.settings,
            self.visual_pool,
            self.publish,
            self.metrics,
            self.batcher.notify,
            self._visual_done,
        )
        self.sessions[session_id] = session
        self.metrics.sessions_active.set(len(self.sessions))
        try:
            await self.broker.register(SessionRecord(session_id, name, self.settings.instance_id, credentials))
        except Exception as exc:  # noqa: BLE001 - e.g. Redis unreachable
            await self._drop(session_id)
            raise _directory_unavailable(exc) from None
        await self.publish(
            session_id,
            status_event(session_id, "session_created", f"session {name!r} created", model=runtime.model_name),
            False,
        )
        log.info("session %s created for %s", session_id, client)
        return session, robot, operator

    async def end_session(self, session_id: str, why: str, lost: bool = False) -> dict:
        """End a local session; `lost`: its directory entry stays a while as lost (410 `why`, not 404)."""
        session = self.sessions.get(session_id)
        if session is None:
            raise session_not_found(session_id)
        status = session.status()
        await self._drop(session_id)
        with contextlib.suppress(Exception):
            await (self.broker.mark_lost(session_id, why) if lost else self.broker.forget(session_id))
        event = (
            _lost_event(session_id, why, self.settings.instance_id)
            if lost
            else status_event(session_id, "session_ended", why)
        )
        await self.publish(session_id, {**event, "counters": status["counters"]}, True)
        return {**status, "state": "ended"}

    async def _drop(self, session_id: str) -> None:
        session = self.sessions.pop(session_id, None)
        self.metrics.sessions_active.set(len(self.sessions))
        if session is not None:
            await session.close()

    async def _reap_idle(self) -> None:
        every = min(REAP_EVERY_S, self.settings.session_idle_s / 2, self.settings.session_first_block_s / 2)
        while True:
            await asyncio.sleep(every)
            for sid, why in reap_due(self.sessions.values(), time.monotonic(), self.settings):
                log.info("ending session %s: %s", sid, why)
                self.metrics.sessions_reaped.inc()
                with contextlib.suppress(ServiceError):
                    await self.end_session(sid, why)

    async def _keep_alive(self) -> None:
        """Heartbeat for the other replicas; end the sessions of a replica found gone that operators here watch."""
        while True:
            await asyncio.sleep(HEARTBEAT_EVERY_S)
            try:
                if await self.broker.heartbeat():
                    await self._reconcile_directory()
                for sid in self.broker.subscribed():
                    if sid not in self.sessions:
                        with contextlib.suppress(ServiceError):
                            await self.credentials(
                                sid
                            )  # marks it lost (and ends its subscriptions) if its owner is gone
            except Exception as exc:  # noqa: BLE001 - e.g. Redis unreachable: the next beat tries again
                log.warning("replica heartbeat failed: %s: %s", type(exc).__name__, exc)

    async def _reconcile_directory(self) -> None:
        """After a lapse: re-enter sessions the directory lost (Redis restarted), end those another replica marked lost."""
        for sid, session in list(self.sessions.items()):
            record = await self.broker.lookup(sid)
            if record is None:
                await self.broker.register(
                    SessionRecord(sid, session.name, self.settings.instance_id, session.credentials)
                )
            elif record.lost is not None:  # its operators were told by the replica that marked it; its robot gets 410
                log.warning("session %s was marked lost while this replica was silent; ending it here", sid)
                await self._drop(sid)

    async def credentials(self, session_id: str) -> tuple[SessionCredentials, Session | None]:
        """The session's credentials and, if it runs here, the session; 404 if no replica knows it, 410 if the
        replica that ran it is gone."""
        session = self.sessions.get(session_id)
        if session is not None:
            return session.credentials, session
        record = await self._lookup(session_id)
        if record is None:
            raise session_not_found(session_id)
        if record.lost is None:
            try:
                if not await self.broker.alive(record):
                    await self._mark_lost(record)
                    record = await self.broker.lookup(session_id) or record
            except Exception as exc:  # noqa: BLE001 - e.g. Redis unreachable: 503, not 500
                raise _directory_unavailable(exc) from None
        if record.lost is not None:
            raise session_lost(session_id, record.lost)
        return record.credentials, None

    async def _mark_lost(self, record: SessionRecord) -> None:
        """The owner of `record` is gone: the first replica to notice tells the session's operators, everywhere."""
        reason = f"its replica {record.instance} is gone (stopped, crashed or restarted)"
        if await self.broker.mark_lost(record.session_id, reason):
            log.warning("session %s is lost: %s", record.session_id, reason)
            self.metrics.sessions_lost.inc()
            await self.publish(record.session_id, _lost_event(record.session_id, reason, record.instance), True)

    async def _lookup(self, session_id: str) -> SessionRecord | None:
        try:
            return await self.broker.lookup(session_id)
        except Exception as exc:  # noqa: BLE001 - e.g. Redis unreachable: 503, not 500
            raise _directory_unavailable(exc) from None

    async def authorized(
        self, session_id: str, token: str | None, roles: frozenset[Role]
    ) -> tuple[Role, Session | None]:
        creds, session = await self.credentials(session_id)
        return authorize(creds, token, roles, session_id), session

    async def local_session(self, session_id: str, token: str | None, roles: frozenset[Role]) -> Session:
        """The session if it runs on this replica and `token` may do this; 421 if another replica runs it."""
        _, session = await self.authorized(session_id, token, roles)
        if session is None:
            record = await self._lookup(session_id)
            owner = record.instance if record else "another replica"
            raise ServiceError(
                421,
                f"session {session_id} runs on {owner}; route its traffic by session id "
                f"(if {owner} is down, this becomes 410 within {REPLICA_TTL_S:g} s)",
            )
        return session

    # ---- robots ----------------------------------------------------------------------------------
    async def robot_disconnected(self, session: Session, why: str) -> None:
        """The robot's ingest socket closed: one INFO line, a status event for operators."""
        self.metrics.robot_disconnects.inc(reason=why.replace(" ", "_"))
        log.info("robot of session %s disconnected (%s)", session.id, why)
        if not session.closed:
            await self.publish(
                session.id,
                status_event(session.id, "robot_disconnected", f"the robot's ingest socket closed: {why}", reason=why),
                False,
            )

    async def receive_frame(self, session: Session, runtime: Runtime, request: Request) -> FrameAck:
        """One camera frame: refused early (429) when the visual queue is full or the session's previous frame is
        still decoding; otherwise decoded (visual pool), and embedded only if the scene changed."""
        if self.visual_load >= self.settings.visual_queue or session.decoding_frame:
            self.metrics.frames.inc(outcome="refused")
            session.counters.frames_refused += 1
            what = (
                f"session {session.id} is still decoding its previous frame"
                if session.decoding_frame
                else f"the visual queue is full ({self.settings.visual_queue} frames)"
            )
            raise saturated(f"{what}; send the newest frame later", RETRY_AFTER_S)
        session.decoding_frame = True
        self.visual_load += 1
        try:
            payload = await request.body()
            gray, thumb = await asyncio.get_running_loop().run_in_executor(self.frame_pool, _decode, runtime, payload)
        except ValueError as exc:
            session.counters.frames_rejected += 1
            self.metrics.frames.inc(outcome="rejected")
            raise ServiceError(422, f"frame: {exc}") from None
        finally:
            session.decoding_frame = False
            self.visual_load -= 1
        if session.closed:  # ended while the frame was decoded
            raise session_not_found(session.id)
        outcome = session.offer_frame(gray, thumb)
        if outcome == "embedding":
            self.visual_load += 1  # released by _visual_done when the embedding ends
        self.metrics.frames.inc(outcome=outcome)
        height, width = gray.shape
        used = outcome != "ignored"
        message = {
            "ignored": f"frame received (ignored: model {runtime.model_name} reads no images)",
            "unchanged": "frame received (scene unchanged: the current embedding stays)",
            "embedding": "frame received (scene changed: embedding it)",
            "superseded": "frame received (replaces a frame waiting for the embedder)",
        }[outcome]
        await self.publish(
            session.id,
            status_event(session.id, "frame_received", message, used=used, outcome=outcome, width=width, height=height),
            False,
        )
        return FrameAck(used=used, outcome=outcome, width=width, height=height)

    def _visual_done(self) -> None:
        self.visual_load -= 1

    # ---- events ----------------------------------------------------------------------------------
    async def publish(self, session_id: str, event: dict, final: bool) -> None:
        """Serialise once and hand to the broker; a broker failure costs the event, never the session."""
        try:
            await self.broker.publish(session_id, encode(event), final)
        except Exception as exc:  # noqa: BLE001 - e.g. Redis unreachable: count, log at most every 10 s
            self.metrics.publish_errors.inc()
            now = time.monotonic()
            if now - self._last_publish_error > 10:
                self._last_publish_error = now
                log.warning("publishing an event of session %s failed: %s", session_id, exc)

    async def subscribe(self, session_id: str) -> Subscription:
        sub = await self.broker.subscribe(session_id)
        self._subscribers += 1
        self.metrics.subscribers.set(self._subscribers)
        return sub

    async def unsubscribe(self, sub: Subscription) -> None:
        self._subscribers -= 1
        self.metrics.subscribers.set(self._subscribers)
        await self.broker.unsubscribe(sub)


def _decode(runtime: Runtime, payload: bytes):
    """Frame pool: frame bytes → (grey image, its thumbnail)."""
    gray = runtime.decode_frame(payload)
    return gray, thumbnail(gray)


def reap_due(sessions, now: float, settings: Settings) -> list[tuple[str, str]]:
    """(session id, why) of sessions to end now: never streamed within session_first_block_s of their creation,
    or no traffic for session_idle_s. now: time.monotonic()."""
    due = []
    for s in sessions:
        if s.last_seq < 0 and now - s.opened_at > settings.session_first_block_s:
            due.append((s.id, f"no block within {settings.session_first_block_s:g} s of its creation"))
        elif now - s.last_activity > settings.session_idle_s:
            due.append((s.id, f"no traffic for {settings.session_idle_s:g} s"))
    return due


def _lost_event(session_id: str, reason: str, instance: str) -> dict:
    """The final event of a session whose replica is gone: operators learn that its robot must start over."""
    return status_event(
        session_id,
        "session_ended",
        f"session lost: {reason}; the robot must open a new session",
        lost=True,
        instance=instance,
    )


def _directory_unavailable(exc: Exception) -> ServiceError:
    log.warning("the session directory (broker) failed: %s: %s", type(exc).__name__, exc)
    return ServiceError(503, "the session directory is unavailable; try again", {"Retry-After": "1"})
