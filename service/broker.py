"""Event fan-out to operators: in-process (default) or Redis pub/sub across replicas, one interface.

Events travel as JSON text, serialised once per publish. Each subscriber has a bounded
`LatestQueue`: when an operator's connection is slow, older events are dropped (and
counted) so it always gets the latest state, and a slow subscriber never stalls the session
or the other subscribers. A *final* event (session ended) is never dropped; it ends the
subscription after it is delivered.

The broker also keeps the session directory (who owns which session, and the digests of
its tokens), so a replica can authorise an operator for a session another replica runs.
With Redis every replica also keeps a heartbeat there: a replica whose heartbeat has lapsed (or
that came back as a new process) has lost its sessions, and the replica that notices marks them
lost, so their robots and operators are told to open a new session instead of waiting forever.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import secrets
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import asdict, dataclass
from typing import Any

from service.auth import SessionCredentials

log = logging.getLogger(__name__)

CHANNEL_PREFIX = "hapticlink:events:"
DIRECTORY_PREFIX = "hapticlink:session:"
DIRECTORY_TTL_S = 7 * 24 * 3600  # a crashed replica's entries do not outlive a week
ROBOT_PREFIX = "hapticlink:robot:"  # + robot id → its newest session id
ALIVE_PREFIX = "hapticlink:alive:"  # + instance id → the running process's incarnation, expiring
HEARTBEAT_EVERY_S = 2.0
#: a replica silent this long is gone; generous, so a busy event loop is never taken for a dead one
REPLICA_TTL_S = 10.0
LOST_TTL_S = 3600.0  # how long a lost session's entry keeps answering 410 (with the reason) before it is unknown
_EVENT, _FINAL = "E", "F"  # one-character framing of Redis messages


@dataclass(frozen=True)
class SessionRecord:
    """What every replica may know of a session: its owner replica and its token digests."""

    session_id: str
    name: str
    instance: str
    credentials: SessionCredentials
    incarnation: str = ""  # the owner process's random id: a restarted replica is a new incarnation
    lost: str | None = None  # why the session is gone, once a replica found its owner gone


class LatestQueue:
    """A bounded queue of event texts that drops the oldest on overflow (counted in `dropped`)."""

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError(f"maxsize must be ≥ 1, got {maxsize}")
        self._items: deque[str] = deque()
        self.maxsize = maxsize
        self.dropped = 0
        self.closed = False
        self._ready = asyncio.Event()

    def offer(self, text: str, final: bool = False) -> None:
        """Never blocks. `final`: deliver this one, then end the subscription."""
        if self.closed:
            return
        if len(self._items) >= self.maxsize:
            self._items.popleft()
            self.dropped += 1
        self._items.append(text)
        self.closed = final
        self._ready.set()

    def close(self) -> None:
        self.closed = True
        self._ready.set()

    async def get(self) -> str | None:
        """The next event text, or None once closed and drained."""
        while not self._items:
            if self.closed:
                return None
            self._ready.clear()
            await self._ready.wait()
        return self._items.popleft()


class Subscription:
    """One operator connection's view of one session's events."""

    def __init__(self, session_id: str, maxsize: int) -> None:
        self.session_id = session_id
        self.queue = LatestQueue(maxsize)

    async def get(self) -> str | None:
        return await self.queue.get()

    @property
    def dropped(self) -> int:
        return self.queue.dropped


class Broker(ABC):
    """publish(session, event) reaches every subscription to that session, on any replica sharing the broker."""

    def __init__(self, subscriber_queue: int) -> None:
        self.subscriber_queue = subscriber_queue
        self.incarnation = secrets.token_hex(8)
        self._local: dict[str, set[Subscription]] = {}

    async def start(self) -> None:  # noqa: B027 - a hook: the in-memory broker has nothing to connect
        """Connect (no-op in memory)."""

    async def close(self) -> None:
        for subs in list(self._local.values()):
            for sub in subs:
                sub.queue.close()
        self._local.clear()

    @abstractmethod
    async def publish(self, session_id: str, text: str, final: bool = False) -> None:
        """Deliver one event text; `final` ends the subscriptions after it."""

    async def subscribe(self, session_id: str) -> Subscription:
        """A subscription that receives every event published after this returns."""
        sub = Subscription(session_id, self.subscriber_queue)
        first = session_id not in self._local
        self._local.setdefault(session_id, set()).add(sub)
        if first:
            try:
                await self._listen(session_id)
            except BaseException:
                self._forget(sub)
                raise
        return sub

    async def unsubscribe(self, sub: Subscription) -> None:
        if self._forget(sub):
            await self._unlisten(sub.session_id)

    def _forget(self, sub: Subscription) -> bool:
        """Remove `sub`; True if it was the session's last local subscription."""
        subs = self._local.get(sub.session_id)
        if not subs or sub not in subs:
            return False
        subs.discard(sub)
        if not subs:
            del self._local[sub.session_id]
            return True
        return False

    def subscribed(self) -> list[str]:
        """Sessions this process has operator subscriptions for."""
        return list(self._local)

    def deliver_locally(self, session_id: str, text: str, final: bool) -> None:
        for sub in list(self._local.get(session_id, ())):
            sub.queue.offer(text, final)

    async def _listen(self, session_id: str) -> None:  # noqa: B027 - a hook, as start
        """Start receiving the session's events from elsewhere (no-op in memory)."""

    async def _unlisten(self, session_id: str) -> None:  # noqa: B027 - a hook, as start
        """Stop receiving them (no-op in memory)."""

    # ---- session directory ---------------------------------------------------------------------
    @abstractmethod
    async def register(self, record: SessionRecord) -> None: ...

    @abstractmethod
    async def set_robot_session(self, robot: str, session_id: str) -> None:
        """Remember `session_id` as robot `robot`'s newest session (operators follow the robot by it)."""

    @abstractmethod
    async def robot_session(self, robot: str) -> str | None:
        """The robot's newest session id, or None."""

    @abstractmethod
    async def lookup(self, session_id: str) -> SessionRecord | None: ...

    @abstractmethod
    async def forget(self, session_id: str) -> None: ...

    @abstractmethod
    async def mark_lost(self, session_id: str, reason: str) -> bool:
        """Keep the entry a while as lost, with the reason; True for the one caller that marked it."""

    # ---- replica liveness ------------------------------------------------------------------------
    async def heartbeat(self) -> bool:
        """Tell the other replicas this process runs; True if its heartbeat had lapsed since the last call."""
        return False

    async def alive(self, record: SessionRecord) -> bool:
        """Whether the process that owns `record` still runs (one process: always)."""
        return True


class InMemoryBroker(Broker):
    """One process: publish hands the text straight to the local subscriptions."""

    def __init__(self, subscriber_queue: int) -> None:
        super().__init__(subscriber_queue)
        self._records: dict[str, SessionRecord] = {}
        self._robots: dict[str, str] = {}  # robot id → its newest session id

    async def publish(self, session_id: str, text: str, final: bool = False) -> None:
        self.deliver_locally(session_id, text, final)

    async def register(self, record: SessionRecord) -> None:
        self._records[record.session_id] = record

    async def set_robot_session(self, robot: str, session_id: str) -> None:
        self._robots[robot] = session_id

    async def robot_session(self, robot: str) -> str | None:
        return self._robots.get(robot)

    async def lookup(self, session_id: str) -> SessionRecord | None:
        return self._records.get(session_id)

    async def forget(self, session_id: str) -> None:
        self._records.pop(session_id, None)

    async def mark_lost(self, session_id: str, reason: str) -> bool:
        record = self._records.get(session_id)
        if record is None or record.lost is not None:
            return False
        self._records[session_id] = SessionRecord(
            record.session_id, record.name, record.instance, record.credentials, record.incarnation, reason
        )
        return True


class RedisBroker(Broker):
    """Redis pub/sub, one channel per session; a replica subscribes to a session's channel while it
    has operators for it. Every event, local ones included, goes through Redis so all replicas see
    the same order. The directory is a Redis hash per session (token digests only)."""

    def __init__(self, url: str, subscriber_queue: int, instance_id: str) -> None:
        super().__init__(subscriber_queue)
        self.url = url
        self.instance_id = instance_id
        self._redis: Any = None  # redis.asyncio.Redis once started (imported only when Redis is used)
        self._pubsub: Any = None
        self._reader: asyncio.Task | None = None
        self._confirmed: dict[str, asyncio.Event] = {}
        self._beats = 0

    async def start(self) -> None:
        import redis.asyncio as redis

        self._redis = redis.from_url(self.url, decode_responses=True)
        await self._redis.ping()
        self._pubsub = self._redis.pubsub()
        # The reader needs one subscription to exist before it can wait on the connection.
        control = f"hapticlink:instance:{self.instance_id}"
        self._confirmed[control] = asyncio.Event()
        await self._pubsub.subscribe(control)
        self._reader = asyncio.create_task(self._read(), name="redis-broker-reader")
        await asyncio.wait_for(self._confirmed[control].wait(), timeout=10)
        await self.heartbeat()  # alive before the first session is registered

    async def close(self) -> None:
        await super().close()
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reader
        if self._pubsub is not None:
            with contextlib.suppress(Exception):
                await self._pubsub.aclose()
        if self._redis is not None:
            with contextlib.suppress(Exception):
                await self._redis.aclose()

    async def publish(self, session_id: str, text: str, final: bool = False) -> None:
        assert self._redis is not None, "RedisBroker.start() was not awaited"
        await self._redis.publish(CHANNEL_PREFIX + session_id, (_FINAL if final else _EVENT) + text)

    async def _listen(self, session_id: str) -> None:
        assert self._pubsub is not None
        channel = CHANNEL_PREFIX + session_id
        confirmed = self._confirmed.setdefault(channel, asyncio.Event())
        try:
            await self._pubsub.subscribe(channel)
            await asyncio.wait_for(confirmed.wait(), timeout=10)
        except BaseException:  # no subscription is left listening to a channel nobody reads
            await self._unlisten(session_id)
            raise

    async def _unlisten(self, session_id: str) -> None:
        assert self._pubsub is not None
        channel = CHANNEL_PREFIX + session_id
        self._confirmed.pop(channel, None)
        with contextlib.suppress(Exception):
            await self._pubsub.unsubscribe(channel)

    async def _read(self) -> None:
        assert self._pubsub is not None
        while True:
            try:
                message = await self._pubsub.get_message(timeout=1.0)
            except asyncio.CancelledError:
                raise
            except Exception:  # noqa: BLE001 - a dropped connection: redis-py reconnects on the next call
                log.exception("redis broker: reading failed; retrying")
                await asyncio.sleep(0.5)
                continue
            if message is None:
                continue
            channel = message.get("channel", "")
            if message["type"] == "subscribe":
                event = self._confirmed.get(channel)
                if event is not None:
                    event.set()
            elif message["type"] == "message" and channel.startswith(CHANNEL_PREFIX):
                data = message["data"]
                self.deliver_locally(channel[len(CHANNEL_PREFIX) :], data[1:], data[:1] == _FINAL)

    async def register(self, record: SessionRecord) -> None:
        assert self._redis is not None
        key = DIRECTORY_PREFIX + record.session_id
        fields = {
            "name": record.name,
            "instance": record.instance,
            "incarnation": self.incarnation,
            **asdict(record.credentials),
        }
        await self._redis.hset(key, mapping=fields)
        await self._redis.expire(key, DIRECTORY_TTL_S)

    async def set_robot_session(self, robot: str, session_id: str) -> None:
        assert self._redis is not None
        await self._redis.set(ROBOT_PREFIX + robot, session_id, ex=DIRECTORY_TTL_S)

    async def robot_session(self, robot: str) -> str | None:
        assert self._redis is not None
        value = await self._redis.get(ROBOT_PREFIX + robot)
        return None if value is None else str(value)

    async def lookup(self, session_id: str) -> SessionRecord | None:
        assert self._redis is not None
        raw = await self._redis.hgetall(DIRECTORY_PREFIX + session_id)
        if not raw:
            return None
        try:
            creds = SessionCredentials(raw["robot_digest"], raw["operator_digest"])
            return SessionRecord(
                session_id, raw.get("name", ""), raw["instance"], creds, raw.get("incarnation", ""), raw.get("lost")
            )
        except KeyError:
            log.warning("redis broker: incomplete directory entry for %s: %s", session_id, json.dumps(sorted(raw)))
            return None

    async def forget(self, session_id: str) -> None:
        assert self._redis is not None
        await self._redis.delete(DIRECTORY_PREFIX + session_id)

    async def mark_lost(self, session_id: str, reason: str) -> bool:
        assert self._redis is not None
        key = DIRECTORY_PREFIX + session_id
        async with self._redis.pipeline(transaction=True) as pipe:
            marked, _ = await pipe.hsetnx(key, "lost", reason).pexpire(key, int(LOST_TTL_S * 1000)).execute()
        return bool(marked)

    async def heartbeat(self) -> bool:
        assert self._redis is not None
        previous = await self._redis.set(
            ALIVE_PREFIX + self.instance_id, self.incarnation, px=int(REPLICA_TTL_S * 1000), get=True
        )
        first, self._beats = self._beats == 0, self._beats + 1
        if previous not in (None, self.incarnation):
            if first:
                log.info("replica %s restarted: sessions of its previous process are lost", self.instance_id)
            else:
                log.error(
                    "another process also runs as replica %s: give every replica its own HAPTICLINK_INSTANCE_ID",
                    self.instance_id,
                )
        lapsed = not first and previous != self.incarnation
        if lapsed:
            log.warning(
                "this replica's heartbeat lapsed (no beat for %.0f s: a stalled event loop or Redis unreachable "
                "or restarted); other replicas may have marked its sessions lost",
                REPLICA_TTL_S,
            )
        return lapsed

    async def alive(self, record: SessionRecord) -> bool:
        assert self._redis is not None
        incarnation = await self._redis.get(ALIVE_PREFIX + record.instance)
        return incarnation is not None and (not record.incarnation or incarnation == record.incarnation)


def make_broker(kind: str, *, subscriber_queue: int, redis_url: str, instance_id: str) -> Broker:
    if kind == "memory":
        return InMemoryBroker(subscriber_queue)
    if kind == "redis":
        return RedisBroker(redis_url, subscriber_queue, instance_id)
    raise ValueError(f"broker must be 'memory' or 'redis', got {kind!r}")
