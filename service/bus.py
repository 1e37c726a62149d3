"""The event bus: a session's events go to its operators, on whichever replica they watch from.

`EventBus` serialises each event once and hands it to the broker's publish/subscribe half
(service/broker.py: in-process or Redis); a broker failure costs the event, never the session.
"""

from __future__ import annotations

import logging
import time

from service.broker import Broker, Subscription
from service.errors import ServiceError
from service.events import encode
from service.metrics import ServiceMetrics

log = logging.getLogger(__name__)

#: at most one WARNING per this many seconds about events the broker failed to publish
PUBLISH_ERROR_LOG_EVERY_S = 10.0
#: event sockets one session may hold open on one replica (a console, a renderer, an operator client, a few
#: viewers): each holds a queue, so one operator token cannot open them without bound
MAX_SUBSCRIBERS_PER_SESSION = 16
#: + a robot id: the room that carries every event of the robot's sessions, one after another (WS /robots/{id}/events)
ROBOT_ROOM = "robot:"


class EventBus:
    """publish / subscribe / unsubscribe over `broker`, counted in `metrics`."""

    def __init__(self, broker: Broker, metrics: ServiceMetrics) -> None:
        self.broker = broker
        self.metrics = metrics
        self._subscribers = 0
        self._per_session: dict[str, int] = {}
        self._last_publish_error = 0.0
        self._robot_rooms: dict[str, str] = {}  # session id → its robot's room

    async def publish(self, session_id: str, event: dict, final: bool) -> None:
        """Serialise once and hand to the broker; `final`: the session's last event (its subscriptions end)."""
        try:
            text = encode(event)
            await self.broker.publish(session_id, text, final)
            room = self._robot_rooms.get(session_id)
            if room is not None:  # its robot's followers: never final there (the robot's next session follows)
                await self.broker.publish(room, text, False)
        except Exception as exc:  # noqa: BLE001 - e.g. Redis unreachable: count, log at most every 10 s
            self.metrics.publish_errors.inc()
            now = time.monotonic()
            if now - self._last_publish_error > PUBLISH_ERROR_LOG_EVERY_S:
                self._last_publish_error = now
                log.warning("publishing an event of session %s failed: %s", session_id, exc)

    def carry(self, session_id: str, robot: str) -> None:
        """Publish `session_id`'s events in its robot's room too (until `release`)."""
        self._robot_rooms[session_id] = ROBOT_ROOM + robot

    def release(self, session_id: str) -> None:
        self._robot_rooms.pop(session_id, None)

    def require_room(self, session_id: str) -> None:
        """ServiceError 429 when `session_id` already has MAX_SUBSCRIBERS_PER_SESSION subscriptions here."""
        if self._per_session.get(session_id, 0) >= MAX_SUBSCRIBERS_PER_SESSION:
            raise ServiceError(
                429,
                f"session {session_id!r} already has {MAX_SUBSCRIBERS_PER_SESSION} event connections on this replica "
                "(the most it takes); close one first",
                {"Retry-After": "5"},
            )

    async def subscribe(self, session_id: str) -> Subscription:
        """A subscription to `session_id`'s events; ServiceError 429 past MAX_SUBSCRIBERS_PER_SESSION."""
        self.require_room(session_id)
        self._per_session[session_id] = self._per_session.get(session_id, 0) + 1  # before the await: no race
        try:
            sub = await self.broker.subscribe(session_id)
        except BaseException:
            self._release(session_id)
            raise
        self._subscribers += 1
        self.metrics.subscribers.set(self._subscribers)
        return sub

    async def unsubscribe(self, sub: Subscription) -> None:
        self._subscribers -= 1
        self.metrics.subscribers.set(self._subscribers)
        self._release(sub.session_id)
        await self.broker.unsubscribe(sub)

    def _release(self, session_id: str) -> None:
        left = self._per_session.pop(session_id, 1) - 1
        if left:
            self._per_session[session_id] = left

    @property
    def subscribers(self) -> int:
        """Operator subscriptions open on this replica."""
        return self._subscribers

    def watched(self) -> list[str]:
        """Sessions operators on this replica subscribe to (the broker's view; robots' rooms are not sessions)."""
        return [room for room in self.broker.subscribed() if not room.startswith(ROBOT_ROOM)]
