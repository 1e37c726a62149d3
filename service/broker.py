"""Event fan-out to operators: in-process (default) or Redis pub/sub across replicas, one interface.

Events travel as JSON text, serialised once per publish. Each subscriber has a bounded
`LatestQueue`: when an operator's connection is slow, older events are dropped (and
counted) so it always gets the latest state, and a slow subscriber never stalls the session
or the other subscribers. A *final* event (session ended) is never dropped; it ends the
subscription after it is delivered.

The broker also keeps the session directory (who owns which session, and the digests of
its tokens), so a replica can authorise an operator for a session another replica runs.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import asdict, dataclass

from service.auth import SessionCredentials

log = logging.getLogger(__name__)

CHANNEL_PREFIX = "hapticlink:events:"
DIRECTORY_PREFIX = "hapticlink:session:"
DIRECTORY_TTL_S = 7 * 24 * 3600  # a crashed replica's entries do not outlive a week
_EVENT, _FINAL = "E", "F"  # one-character framing of Redis messages


@dataclass(frozen=True)
class SessionRecord:
    """What every replica may know of a session: its owner replica and its token digests."""

    session_id: str
    name: str
    instance: str
    credentials: SessionCredentials


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
        self._local: dict[str, set[Subscription]] = {}

    async def start(self) -> None:
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

    def deliver_locally(self, session_id: str, text: str, final: bool) -> None:
        for sub in list(self._local.get(session_id, ())):
            sub.queue.offer(text, final)

    async def _listen(self, session_id: str) -> None:
        """Start receiving the session's events from elsewhere (no-op in memory)."""

    async def _unlisten(self, session_id: str) -> None:
        """Stop receiving them (no-op in memory)."""

    # ---- session directory ---------------------------------------------------------------------
    @abstractmethod
    async def register(self, record: SessionRecord) -> None: ...

    @abstractmethod
    async def lookup(self, session_id: str) -> SessionRecord | None: ...

    @abstractmethod
    async def forget(self, session_id: str) -> None: ...


class InMemoryBroker(Broker):
    """One process: publish hands the text straight to the local subscriptions."""

    def __init__(self, subscriber_queue: int) -> None:
        super().__init__(subscriber_queue)
        self._records: dict[str, SessionRecord] = {}

    async def publish(self, session_id: str, text: str, final: bool = False) -> None:
        self.deliver_locally(session_id, text, final)

    async def register(self, record: SessionRecord) -> None:
        self._records[record.session_id] = record

    async def lookup(self, session_id: str) -> SessionRecord | None:
        return self._records.get(session_id)

    async def forget(self, session_id: str) -> None:
        self._records.pop(session_id, None)


class RedisBroker(Broker):
    """Redis pub/sub, one channel per session; a replica subscribes to a session's channel while it
    has operators for it. Every event, local ones included, goes through Redis so all replicas see
    the same order. The directory is a Redis hash per session (token digests only)."""

    def __init__(self, url: str, subscriber_queue: int, instance_id: str) -> None:
        super().__init__(subscriber_queue)
        self.url = url
        self.instance_id = instance_id
        self._redis = None
        self._pubsub = None
        self._reader: asyncio.Task | None = None
        self._confirmed: dict[str, asyncio.Event] = {}

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
                self.deliver_locally(channel[len(CHANNEL_PREFIX):], data[1:], data[:1] == _FINAL)

    async def register(self, record: SessionRecord) -> None:
        assert self._redis is not None
        key = DIRECTORY_PREFIX + record.session_id
        fields = {"name": record.name, "instance": record.instance, **asdict(record.credentials)}
        await self._redis.hset(key, mapping=fields)
        await self._redis.expire(key, DIRECTORY_TTL_S)

    async def lookup(self, session_id: str) -> SessionRecord | None:
        assert self._redis is not None
        raw = await self._redis.hgetall(DIRECTORY_PREFIX + session_id)
        if not raw:
            return None
        try:
            creds = SessionCredentials(raw["robot_digest"], raw["operator_digest"])
            return SessionRecord(session_id, raw.get("name", ""), raw["instance"], creds)
        except KeyError:
            log.warning("redis broker: incomplete directory entry for %s: %s", session_id, json.dumps(sorted(raw)))
            return None

    async def forget(self, session_id: str) -> None:
        assert self._redis is not None
        await self._redis.delete(DIRECTORY_PREFIX + session_id)


def make_broker(kind: str, *, subscriber_queue: int, redis_url: str, instance_id: str) -> Broker:
    if kind == "memory":
        return InMemoryBroker(subscriber_queue)
    if kind == "redis":
        return RedisBroker(redis_url, subscriber_queue, instance_id)
    raise ValueError(f"broker must be 'memory' or 'redis', got {kind!r}")
