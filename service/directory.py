"""The session directory: which sessions run here, which replica runs the others, and who may use them.

`SessionDirectory` holds this replica's live sessions and the broker's shared directory half
(in-process, or Redis for several replicas): it opens and ends sessions, answers "who owns session
X and may this token use it" (404 unknown, 410 lost, 421 elsewhere, 401/403 by service.auth), keeps
this replica's heartbeat, marks sessions of a replica found gone as lost, and reaps abandoned
sessions.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
import time
from collections.abc import Callable, Iterable
from typing import Any

from drivers.protocol import SESSION_LOST, Close
from service import memory
from service.auth import Role, SessionCredentials, authorize, issue_credentials, missing_token
from service.broker import HEARTBEAT_EVERY_S, REPLICA_TTL_S, Broker, SessionRecord
from service.bus import EventBus
from service.errors import ServiceError, session_lost, session_not_found
from service.events import status_event
from service.live_session import Session
from service.metrics import ServiceMetrics
from service.settings import Settings

log = logging.getLogger(__name__)

REAP_EVERY_S = 5.0
#: ingest sockets one session holds at once: its robot's, and one more while a reconnect overlaps a link not yet known
#: dead; a further one replaces the oldest (each may hold a message of up to the size limit while it arrives)
MAX_INGEST_SOCKETS = 2
#: how long closing a socket may wait for its client: a close frame waits behind what the client has not read, and a
#: client that stopped reading would hold it (and the DELETE, reaper or newer socket that closes it) for ever
CLOSE_WAIT_S = 2.0

#: (session id, name, credentials) → a new Session on this replica
SessionFactory = Callable[[str, str, SessionCredentials], Session]
#: hex digits of the process's incarnation a session id carries after the replica's name: "<instance>.<boot><random>"
BOOT_CHARS = 8


class SessionDirectory:
    """This replica's sessions and the shared directory (see the module docstring)."""

    def __init__(self, settings: Settings, broker: Broker, bus: EventBus, metrics: ServiceMetrics) -> None:
        self.settings = settings
        self.broker = broker
        self.bus = bus
        self.metrics = metrics
        self.sessions: dict[str, Session] = {}
        self._ingest: dict[str, list[Any]] = {}  # session id → its open ingest sockets (WebSockets), oldest first
        self._closing: set[asyncio.Task] = set()  # closes under way (see _close_soon)
        self._ended = 0  # sessions ended since memory was last given back
        self.boot = broker.incarnation[:BOOT_CHARS]

    # ---- open and end ----------------------------------------------------------------------------
    async def open(
        self, name: str | None, client: str, model: str, build: SessionFactory, robot_id: str | None = None
    ) -> tuple[Session, str, str]:
        """A new session for `client` (its address, for the log) → (session, robot token, operator token);
        503 past max_sessions or when the shared directory is unreachable. `robot_id`: the robot's own id, under which
        the directory keeps its newest session (operators follow it: `robot_session`)."""
        if len(self.sessions) >= self.settings.max_sessions:
            raise ServiceError(
                503, f"this replica already runs {len(self.sessions)} sessions (max_sessions)", {"Retry-After": "5"}
            )
        # The replica's name prefixes the id so a load balancer can send all of a session's traffic here; the process's
        # incarnation follows, so that after a restart this replica can say a session of its previous process is lost
        # (410) rather than unknown (404), with nothing kept across the restart.
        session_id = f"{self.settings.instance_id}.{self.boot}{secrets.token_urlsafe(9)}"
        robot, operator, credentials = issue_credentials()
        name = name or session_id
        session = build(session_id, name, credentials)
        self.sessions[session_id] = session
        self.metrics.sessions_active.set(len(self.sessions))
        try:
            await self.broker.register(SessionRecord(session_id, name, self.settings.instance_id, credentials))
            if robot_id is not None:
                await self.broker.set_robot_session(robot_id, session_id)
                self.bus.carry(session_id, robot_id)
        except Exception as exc:  # noqa: BLE001 - e.g. Redis unreachable
            await self.drop(session_id)
            raise directory_unavailable(exc) from None
        await self.bus.publish(
            session_id, status_event(session_id, "session_created", f"session {name!r} created", model=model), False
        )
        log.info("session %s created for %s", session_id, client)
        return session, robot, operator

    async def end(self, session_id: str, why: str, lost: bool = False) -> dict:
        """End a local session; `lost`: its directory entry stays a while as lost (410 `why`, not 404)."""
        session = self.sessions.get(session_id)
        if session is None:
            raise session_not_found(session_id)
        status = session.status()
        await self.drop(session_id)
        # its robot is told now, not at its next block (an idle socket would outlive the session)
        code, reason = (Close.LOST, why) if lost else (Close.SESSION_ENDED, "session ended")
        for socket in self._ingest.pop(session_id, []):
            self._close_soon(socket, code, reason, "session lost" if lost else "session ended")
        with contextlib.suppress(Exception):
            await (self.broker.mark_lost(session_id, why) if lost else self.broker.forget(session_id))
        event = (
            lost_event(session_id, why, self.settings.instance_id)
            if lost
            else status_event(session_id, "session_ended", why)
        )
        await self.bus.publish(session_id, {**event, "counters": status["counters"]}, True)
        self.bus.release(session_id)
        return {**status, "state": "ended"}

    async def drop(self, session_id: str) -> None:
        """Forget a local session (no event, no directory change) and release what it holds."""
        session = self.sessions.pop(session_id, None)
        self.metrics.sessions_active.set(len(self.sessions))
        if session is not None:
            self._ended += 1
            await session.close()

    def attach_ingest(self, session_id: str, socket: Any) -> None:
        """A robot's ingest socket (an accepted starlette WebSocket) opened; past MAX_INGEST_SOCKETS the oldest is
        closed 4409: a robot reconnects and resends, and one robot token cannot hold sockets without bound."""
        sockets = self._ingest.setdefault(session_id, [])
        sockets.append(socket)
        while len(sockets) > MAX_INGEST_SOCKETS:
            reason = "replaced by a newer ingest connection; reconnect and resend"
            self._close_soon(sockets.pop(0), Close.REPLACED, reason, "replaced")

    def detach_ingest(self, session_id: str, socket: Any) -> None:
        """A robot's ingest socket closed."""
        sockets = self._ingest.get(session_id, [])
        if socket in sockets:
            sockets.remove(socket)
        if not sockets:
            self._ingest.pop(session_id, None)

    def _close_soon(self, socket: Any, code: Close, reason: str, why: str) -> None:
        """Close a WebSocket in a task of its own, within CLOSE_WAIT_S (past it, the client's keepalive ends it): no
        caller waits for a client. `why`, a few words, is what its handler logs and counts."""
        socket.state.closed_why = why
        task = asyncio.create_task(_close(socket, code, reason), name="close-socket")
        self._closing.add(task)
        task.add_done_callback(self._closing.discard)

    async def end_all(self, why: str) -> None:
        """Shutdown: every local session ends as lost (their state cannot outlive the process)."""
        for sid in list(self.sessions):
            if sid in self.sessions:  # (the reaper may end one while an earlier one is ended)
                await self.end(sid, why, lost=True)

    # ---- background duties -----------------------------------------------------------------------
    async def reap_idle(self) -> None:
        """Forever: end sessions that never streamed or went quiet (reap_due); after sessions ended, give their
        memory back to the system (service/memory.py)."""
        every = min(REAP_EVERY_S, self.settings.session_idle_s / 2, self.settings.session_first_block_s / 2)
        while True:
            await asyncio.sleep(every)
            for sid, why in reap_due(self.sessions.values(), time.monotonic(), self.settings):
                log.info("ending session %s: %s", sid, why)
                self.metrics.sessions_reaped.inc()
                with contextlib.suppress(ServiceError):
                    await self.end(sid, why)
            if self._ended:
                self._ended = 0
                memory.release()

    async def keep_alive(self) -> None:
        """Forever: heartbeat for the other replicas; end the sessions of a replica found gone that operators here
        watch."""
        while True:
            await asyncio.sleep(HEARTBEAT_EVERY_S)
            try:
                if await self.broker.heartbeat():
                    await self._reconcile()
                for sid in self.bus.watched():
                    if sid not in self.sessions:
                        with contextlib.suppress(ServiceError):
                            await self.credentials(sid)  # marks it lost (ending its subscriptions) if its owner is gone
            except Exception as exc:  # noqa: BLE001 - e.g. Redis unreachable: the next beat tries again
                log.warning("replica heartbeat failed: %s: %s", type(exc).__name__, exc)

    async def _reconcile(self) -> None:
        """After a lapse: re-enter sessions the directory lost (Redis restarted), end those another replica marked
        lost."""
        for sid, session in list(self.sessions.items()):
            record = await self.broker.lookup(sid)
            if record is None:
                await self.broker.register(
                    SessionRecord(sid, session.name, self.settings.instance_id, session.credentials)
                )
            elif record.lost is not None:  # its operators were told by the replica that marked it; its robot gets 410
                log.warning("session %s was marked lost while this replica was silent; ending it here", sid)
                await self.drop(sid)
                self.bus.release(sid)

    # ---- who owns a session, and may this token use it ---------------------------------------------
    async def credentials(self, session_id: str) -> tuple[SessionCredentials, Session | None]:
        """The session's credentials and, if it runs here, the session; 404 if no replica knows it, 410 if the
        replica that ran it is gone."""
        session = self.sessions.get(session_id)
        if session is not None:
            return session.credentials, session
        record = await self._lookup(session_id)
        if record is None:
            if (why := self.minted_before(session_id)) is not None:
                raise session_lost(session_id, why)
            raise session_not_found(session_id)
        if record.lost is None:
            try:
                if not await self.broker.alive(record):
                    await self._mark_lost(record)
                    record = await self.broker.lookup(session_id) or record
            except Exception as exc:  # noqa: BLE001 - e.g. Redis unreachable: 503, not 500
                raise directory_unavailable(exc) from None
        if record.lost is not None:
            raise session_lost(session_id, record.lost)
        return record.credentials, None

    def minted_before(self, session_id: str) -> str | None:
        """Why a session id this directory does not know is lost, if this replica's previous process opened it: the id
        names this replica, and another incarnation (a restart between). None for any other id (unknown: 404).

        Anyone can write such an id, and learns nothing from the 410 but that this replica restarted; the caller has
        already sent a token (the credential first), and no state is read."""
        instance, dot, rest = session_id.partition(".")
        boot = rest[:BOOT_CHARS]
        if not dot or instance != self.settings.instance_id or len(rest) <= BOOT_CHARS or boot == self.boot:
            return None
        if any(c not in "0123456789abcdef" for c in boot):
            return None
        return (
            f"its replica {instance} restarted since it was opened (a new process; the session's state did not survive)"
        )

    async def authorized(
        self, session_id: str, token: str | None, roles: frozenset[Role]
    ) -> tuple[Role, Session | None]:
        """The caller's role and the session if it runs here. The credential first: no token is 401 before the
        session is looked up (an unknown or lost session is 404 or 410 only for a caller who sent one)."""
        if token is None:
            raise missing_token()
        creds, session = await self.credentials(session_id)
        return authorize(creds, token, roles, session_id), session

    async def local(self, session_id: str, token: str | None, roles: frozenset[Role]) -> Session:
        """The session if it runs on this replica and `token` may do this; 421 if another replica runs it."""
        _, session = await self.authorized(session_id, token, roles)
        if session is None:
            record = await self._lookup(session_id)
            if record is not None and record.instance == self.settings.instance_id:
                # ending here: out of the local table, its directory entry not yet forgotten. Not "elsewhere": a
                # 421 would send its robot to retry.
                raise session_not_found(session_id)
            owner = record.instance if record else "another replica"
            raise ServiceError(
                421,
                f"session {session_id} runs on {owner}; route its traffic by session id "
                f"(if {owner} is down, this becomes 410 within {REPLICA_TTL_S:g} s)",
            )
        return session

    async def robot_session(self, robot: str) -> tuple[str, str | None]:
        """(the robot's newest session id, why it is lost or None); 404 when the robot has opened none that the
        directory remembers (after a restart of a one-process service: until the robot opens its next one)."""
        try:
            session_id = await self.broker.robot_session(robot)
        except Exception as exc:  # noqa: BLE001 - e.g. Redis unreachable: 503, not 500
            raise directory_unavailable(exc) from None
        if session_id is None:
            raise ServiceError(
                404,
                f"robot {robot!r} has no session here (yet): it opens one when it starts, or resumes after a restart",
            )
        try:
            await self.credentials(session_id)
        except ServiceError as exc:
            if exc.status in (404, SESSION_LOST):
                return session_id, exc.detail
            raise
        return session_id, None

    async def _mark_lost(self, record: SessionRecord) -> None:
        """The owner of `record` is gone: the first replica to notice tells the session's operators, everywhere."""
        reason = f"its replica {record.instance} is gone (stopped, crashed or restarted)"
        if await self.broker.mark_lost(record.session_id, reason):
            log.warning("session %s is lost: %s", record.session_id, reason)
            self.metrics.sessions_lost.inc()
            await self.bus.publish(record.session_id, lost_event(record.session_id, reason, record.instance), True)

    async def _lookup(self, session_id: str) -> SessionRecord | None:
        try:
            return await self.broker.lookup(session_id)
        except Exception as exc:  # noqa: BLE001 - e.g. Redis unreachable: 503, not 500
            raise directory_unavailable(exc) from None

    # ---- robots ----------------------------------------------------------------------------------
    async def robot_disconnected(self, session: Session, why: str) -> None:
        """The robot's ingest socket closed: one INFO line, a status event for operators."""
        self.metrics.robot_disconnects.labels(reason=why.replace(" ", "_")).inc()
        log.info("robot of session %s disconnected (%s)", session.id, why)
        if not session.closed:
            await self.bus.publish(
                session.id,
                status_event(session.id, "robot_disconnected", f"the robot's ingest socket closed: {why}", reason=why),
                False,
            )


async def _close(socket: Any, code: Close, reason: str) -> None:
    """Close a WebSocket with `code` and `reason` (cut to fit a close frame), whatever state it is in, waiting at most
    CLOSE_WAIT_S for its client."""
    with contextlib.suppress(Exception):  # it may be closing already, or its client not reading (TimeoutError)
        await asyncio.wait_for(socket.close(int(code), reason[:120]), CLOSE_WAIT_S)


def reap_due(sessions: Iterable[Session], now: float, settings: Settings) -> list[tuple[str, str]]:
    """(session id, why) of sessions to end now: never streamed within session_first_block_s of their creation or
    their robot's last sign (a frame, or a first block refused for capacity), or no sign of its robot (traffic, or a
    try refused for capacity) for session_idle_s. now: time.monotonic()."""
    due = []
    for s in sessions:
        if s.last_seq < 0 and now - s.last_contact > settings.session_first_block_s:
            due.append((s.id, f"no block within {settings.session_first_block_s:g} s of its creation or last try"))
        elif now - s.last_contact > settings.session_idle_s:
            due.append((s.id, f"no traffic for {settings.session_idle_s:g} s"))
    return due


def lost_event(session_id: str, reason: str, instance: str) -> dict:
    """The final event of a session whose replica is gone: operators learn that its robot must start over."""
    return status_event(
        session_id,
        "session_ended",
        f"session lost: {reason}; the robot must open a new session",
        lost=True,
        instance=instance,
    )


def directory_unavailable(exc: Exception) -> ServiceError:
    log.warning("the session directory (broker) failed: %s: %s", type(exc).__name__, exc)
    return ServiceError(503, "the session directory is unavailable; try again", {"Retry-After": "1"})
