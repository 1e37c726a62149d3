"""Log lines a client can cause, rate-limited: a client must not be able to flood (or alarm) the log.

`LogThrottle.warning(key, msg, *args)` logs at most one WARNING per key every `every_s` seconds;
the next one that gets through says how many were left out. Keys are a small fixed set (a kind of
refusal), never a client address or anything else a client chooses, so the throttle's memory is
bounded. `ThrottleFilter` does the same for records of another library's logger (uvicorn's
"Invalid HTTP request received." and the like) picked by their message; `RefusedSocketFilter` for the lines of a
WebSocket accepted only to be closed (`REFUSING_SOCKET` set around that acceptance).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Hashable, Iterable
from contextvars import ContextVar

#: at most one WARNING per kind of client-caused event per this many seconds
EVERY_S = 10.0
#: True while the app accepts a WebSocket only to close it at once (a robot's wrong token: its close code says why)
REFUSING_SOCKET: ContextVar[bool] = ContextVar("refusing_socket", default=False)


class LogThrottle:
    """At most one record per key every `every_s` (thread-safe: the loop and pool threads may share it)."""

    def __init__(self, logger: logging.Logger, every_s: float = EVERY_S) -> None:
        self.logger = logger
        self.every_s = every_s
        self._last: dict[Hashable, tuple[float, int]] = {}  # key → (when last logged, left out since)
        self._lock = threading.Lock()

    def admit(self, key: Hashable) -> int | None:
        """None when a record for `key` must be left out now; else how many were left out before it."""
        now = time.monotonic()
        with self._lock:
            last, skipped = self._last.get(key, (-float("inf"), 0))
            if now - last < self.every_s:
                self._last[key] = (last, skipped + 1)
                return None
            self._last[key] = (now, 0)
            return skipped

    def warning(self, key: Hashable, msg: str, *args: object) -> None:
        skipped = self.admit(key)
        if skipped is None:
            return
        if skipped:
            msg += " (and %d more like it in the last %g s, not logged)"
            args = (*args, skipped, self.every_s)
        self.logger.warning(msg, *args)


class ThrottleFilter(logging.Filter):
    """A logging filter that lets through at most one record every `every_s` per message among `messages`
    (their unformatted text), and every other record."""

    def __init__(self, messages: Iterable[str], every_s: float = EVERY_S) -> None:
        super().__init__()
        self.messages = frozenset(messages)
        self._throttle = LogThrottle(logging.getLogger(__name__), every_s)

    def filter(self, record: logging.LogRecord) -> bool:
        if not isinstance(record.msg, str) or record.msg not in self.messages:
            return True
        return self._throttle.admit(record.msg) is not None


class RefusedSocketFilter(ThrottleFilter):
    """ThrottleFilter for the lines a WebSocket's acceptance writes, applied only to a socket accepted to be refused
    (REFUSING_SOCKET): any client can cause those, while every accepted robot's and operator's lines are kept."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not REFUSING_SOCKET.get() or super().filter(record)
