"""Serving with uvicorn without a proxy in front: options, a read deadline for requests, logs without tokens.

- `server_options(settings)`: the uvicorn.Config keywords `hapticlink serve`, the demo, the benchmark
  and the tests run with (WebSocket messages get the HTTP body limit, keep-alive timeout, the
  deadline protocol below).
- `DeadlineHttpProtocol`: uvicorn's httptools protocol with a deadline on reading a request: from the
  connection (or the first byte of the next request) until the request's headers and body are in,
  at most `request_read_timeout_s`; past it the connection is closed. A client that sends half a
  request (or nothing) cannot hold a connection forever; keep-alive idling is uvicorn's
  `timeout_keep_alive`.
- `RedactQueries`: a logging filter that cuts query strings (WebSocket URLs carry `?token=`) out of
  uvicorn's log lines; `install_log_redaction()` puts it on uvicorn's loggers.
"""

from __future__ import annotations

import asyncio
import logging
import re
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.settings import Settings

log = logging.getLogger(__name__)
_QUERY = re.compile(r"\?[^\s\"']*")


class DeadlineHttpProtocol(HttpToolsProtocol):
    """HttpToolsProtocol that closes a connection whose request does not arrive whole within the deadline."""

    read_timeout_s = 10.0  # set per server by server_options (a subclass per Settings)

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._deadline: asyncio.TimerHandle | None = None
        self._arm()

    def data_received(self, data: bytes) -> None:
        if self._deadline is None and (self.cycle is None or self.cycle.response_complete):
            self._arm()  # the first bytes of the next request on a kept-alive connection
        super().data_received(data)

    def on_message_complete(self) -> None:
        self._disarm()
        super().on_message_complete()

    def handle_websocket_upgrade(self) -> None:
        self._disarm()
        super().handle_websocket_upgrade()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _arm(self) -> None:
        self._disarm()
        self._deadline = self.loop.call_later(self.read_timeout_s, self._expired)

    def _disarm(self) -> None:
        deadline = getattr(self, "_deadline", None)
        if deadline is not None:
            deadline.cancel()
            self._deadline = None

    def _expired(self) -> None:
        self._deadline = None
        if not self.transport.is_closing():
            log.warning(
                "closing a connection from %s: no complete request within %g s", _peer(self.client), self.read_timeout_s
            )
            self.transport.close()


def _peer(client: tuple[str, int] | None) -> str:
    return f"{client[0]}:{client[1]}" if client else "?"


class RedactQueries(logging.Filter):
    """Cuts `?query` out of a log record's message and string arguments (tokens travel in WebSocket URLs)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str) and "?" in record.msg:
            record.msg = _QUERY.sub("", record.msg)
        if isinstance(record.args, tuple) and any(isinstance(a, str) and "?" in a for a in record.args):
            record.args = tuple(_QUERY.sub("", a) if isinstance(a, str) else a for a in record.args)
        return True


_REDACTION = RedactQueries()


def install_log_redaction() -> None:
    """Put RedactQueries on uvicorn's loggers (idempotent)."""
    for name in ("uvicorn.error", "uvicorn.access", "uvicorn"):
        logger = logging.getLogger(name)
        if _REDACTION not in logger.filters:
            logger.addFilter(_REDACTION)


def server_options(settings: Settings, **overrides: Any) -> dict[str, Any]:
    """uvicorn options for `settings` (uvicorn.run / uvicorn.Config keywords)."""
    install_log_redaction()
    protocol = type(
        "DeadlineHttpProtocol", (DeadlineHttpProtocol,), {"read_timeout_s": settings.request_read_timeout_s}
    )
    options: dict[str, Any] = {
        "host": settings.host,
        "port": settings.port,
        "log_level": settings.log_level,
        "ws_max_size": settings.max_body_bytes,
        "timeout_graceful_shutdown": 5,
        # small JSON messages on a LAN: compressing every event and ack costs more CPU than it saves
        "ws_per_message_deflate": False,
        "timeout_keep_alive": settings.timeout_keep_alive_s,
        "http": protocol,
        "proxy_headers": True,
        "forwarded_allow_ips": settings.forwarded_allow_ips,
        "access_log": settings.log_level == "debug",  # lines without query strings (RedactQueries), but many
    }
    return {**options, **overrides}
