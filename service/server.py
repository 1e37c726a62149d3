"""Serving with uvicorn without a proxy in front: options, a read deadline for requests, logs without tokens.

- `server_options(settings)`: the uvicorn.Config keywords `hapticlink serve`, the demo, the benchmark
  and the tests run with (WebSocket messages get the HTTP body limit, keep-alive timeout, the
  deadline protocol below).
- `DeadlineHttpProtocol`: uvicorn's httptools protocol with a deadline on reading a request: from the
  connection (or the first byte of the next request) until the request's headers and body are in,
  at most `request_read_timeout_s`; past it the connection is closed. A client that sends half a
  request (or nothing) cannot hold a connection forever; keep-alive idling is uvicorn's
  `timeout_keep_alive`.
- `RefusingWebSocketProtocol`: uvicorn's WebSocket protocol, with what clients send kept out of the
  ERROR log: a handshake the app refuses with an HTTP answer (404, 410, 401, …) counts as completed
  (uvicorn would log "ASGI callable returned without completing handshake" at ERROR for every one), an upgrade
  request the websockets library refuses itself (a line over 8 kB, too many headers) is answered and closed
  (uvicorn held it open, unanswered), and a text frame that is not UTF-8 closes the socket 1007 with one
  rate-limited WARNING instead of an ERROR with a traceback.
- `SessionEndingServer`: uvicorn's server, ending every session (its operators told it is lost, their feeds closed
  1000) before it closes the connections: uvicorn closes every WebSocket (1012) before the lifespan shutdown, where
  the final events would reach no one.
- `RedactQueries`: a logging filter that cuts query strings (WebSocket URLs carry `?token=`) out of
  uvicorn's log lines; `EscapeControls` escapes line breaks and control characters in every record's message
  (what a client sent can never start a log line of its own); `install_log_redaction()` puts both on uvicorn's
  loggers (EscapeControls on the root's handlers too), with a throttle on the lines uvicorn writes about
  clients — malformed requests, refused WebSocket handshakes (one per kind every 10 s).
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import socket
from typing import Any

import uvicorn
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

from service.log_throttle import LogThrottle, RefusedSocketFilter, ThrottleFilter
from service.settings import Settings

log = logging.getLogger(__name__)
_client_warnings = LogThrottle(log)
#: what uvicorn logs about a client, throttled to one line per kind every 10 s: its WARNINGs about what a client sent
#: (httptools_impl), and its INFO lines for each refused WebSocket handshake (the request line with the status, and
#: the websockets library's "connection rejected" / "HTTP response sent"), which any client could write two at a
#: time without credentials
UVICORN_CLIENT_LINES = (
    "Invalid HTTP request received.",
    "Unsupported upgrade request.",
    '%s - "WebSocket %s" 403',
    '%s - "WebSocket %s" %d',
    "connection rejected (%d %s)",
    "HTTP response sent (%d %s)",
)
#: its two INFO lines for an accepted WebSocket, throttled the same way for a socket accepted only to be closed (a
#: robot's wrong token: accepted, then closed 1008)
UVICORN_ACCEPT_LINES = ('%s - "WebSocket %s" [accepted]', "connection open")
#: a query string, to the next whitespace: a target holds none, while a quote may sit inside the query (`?v='&token=…`
#: kept the token when the cut stopped at quotes)
_QUERY = re.compile(r"\?\S*")
#: a request's line and headers together (a robot's are a few hundred bytes; nginx's default is 4 × 8 kB)
MAX_REQUEST_HEAD_BYTES = 64 * 1024


class DeadlineHttpProtocol(HttpToolsProtocol):
    """HttpToolsProtocol that closes a connection whose request does not arrive whole within the deadline, and
    answers 431 to a request whose line and headers pass MAX_REQUEST_HEAD_BYTES (httptools sets no bound: one
    64 MB header, sent with no credential, held the event loop for seconds)."""

    read_timeout_s = 10.0  # set per server by server_options (a subclass per Settings)

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._answering: Any = None  # the request whose answer is being written (uvicorn's RequestResponseCycle)
        self._deadline: asyncio.TimerHandle | None = None
        self._head: int | None = 0  # bytes of the current request's line and headers so far (None: they are in)
        self._tail = b""  # the last bytes of the head so far: its blank line may straddle two reads
        self._arm()

    def data_received(self, data: bytes) -> None:
        if self._deadline is None and (self.cycle is None or self.cycle.response_complete):
            self._arm()  # the first bytes of the next request on a kept-alive connection
        if self._head is not None:
            # the blank line that ends the head: across the last read's tail, else in this read (searched in place:
            # an HTTP block's first read holds its body too, which is not copied for this)
            joint = (self._tail + data[:3]).find(b"\r\n\r\n")
            inside = data.find(b"\r\n\r\n") if joint < 0 else -1
            if joint >= 0:
                self._head += joint + 4 - len(self._tail)
            else:
                self._head += len(data) if inside < 0 else inside + 4
            self._tail = data[-3:]
            if self._head > MAX_REQUEST_HEAD_BYTES:
                self._refuse_head()
                return
        super().data_received(data)

    def on_headers_complete(self) -> None:
        self._head = None
        super().on_headers_complete()

    def on_message_complete(self) -> None:
        self._disarm()
        self._head, self._tail = 0, b""  # the next request's head may follow on this connection
        super().on_message_complete()

    def handle_websocket_upgrade(self) -> None:
        self._disarm()
        super().handle_websocket_upgrade()

    def _refuse_head(self) -> None:
        _client_warnings.warning(
            "head",
            "closing a connection from %s: request line and headers over %d bytes (431)",
            _peer(self.client),
            MAX_REQUEST_HEAD_BYTES,
        )
        body = json.dumps({"detail": f"request line and headers exceed {MAX_REQUEST_HEAD_BYTES} bytes"}).encode()
        self.transport.write(
            b"HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-type: application/json\r\n"
            b"content-length: %d\r\nconnection: close\r\n\r\n%s" % (len(body), body)
        )
        self.transport.close()

    def _start_asgi_task(self, cycle: Any, app: Any) -> None:
        self._answering = cycle
        super()._start_asgi_task(cycle, app)

    def shutdown(self) -> None:
        if self._deadline is not None:
            # a request still arriving cannot be answered before its client sends the rest, which the graceful
            # shutdown would wait for, then cancel (an ERROR and a traceback for any client that sends half a body):
            # closed now, its route sees the client gone
            self._disarm()
            self.transport.close()
            return
        super().shutdown()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        # uvicorn marks only the newest request it parsed as disconnected; with requests pipelined, the one being
        # answered is older, and it would write to the closed transport (an ERROR and a traceback, for any client)
        if self._answering is not None and not self._answering.response_complete:
            self._answering.disconnected = True
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
        if self.transport.is_closing():
            return
        if self._head == 0:
            # not a byte of a request: a browser's spare connection, opened ahead in case the page needs it (every
            # console visit leaves one), is closed without a word; a client that started a request and stalled is
            # worth a line
            log.debug(
                "closing an idle connection from %s: no request within %g s", _peer(self.client), self.read_timeout_s
            )
        else:
            _client_warnings.warning(
                "deadline",
                "closing a connection from %s: no complete request within %g s",
                _peer(self.client),
                self.read_timeout_s,
            )
        self.transport.close()


class RefusingWebSocketProtocol(WebSocketsSansIOProtocol):
    """uvicorn's WebSocket protocol, quiet about refused handshakes and non-UTF-8 text (module docstring), and
    bounded against ping floods: uvicorn writes a pong for every ping whether or not the client reads them, so a
    client pinging without reading grew the server's memory without bound (22 MB/s in a probe). Past
    `max_pings_per_s` the socket closes 1008; a pong is written only while the client reads what it is sent."""

    #: pings a client may send in one second (a keepalive sends one every few seconds)
    max_pings_per_s = 50
    _ping_second = float("-inf")  # when the current one-second count of pings began (loop time)
    _pings = 0

    async def send(self, message: Any) -> None:
        await super().send(message)
        if message["type"] == "websocket.http.response.body" and not message.get("more_body", False):
            self.handshake_complete = True  # refused with an HTTP answer: the handshake is over, and answered

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if not self.handshake_initiated and not self.close_sent and self.conn.handshake_exc is not None:
            self._refuse_upgrade()

    def _refuse_upgrade(self) -> None:
        """websockets refused the upgrade request itself (a line over 8 kB, more than 128 headers, not valid HTTP)
        and queued its answer (414, 431 or the end of the stream), which uvicorn writes only with an event, so the
        connection was held open, unanswered, for ever; and at shutdown uvicorn's 500 on top of it raised.
        Write the answer and close."""
        _client_warnings.warning(
            "upgrade",
            "refusing a WebSocket upgrade from %s: %s",
            _peer(self.client),
            str(self.conn.handshake_exc)[:120],
        )
        self.handshake_complete = self.close_sent = True  # answered: uvicorn's shutdown adds nothing
        self.transport.write(b"".join(self.conn.data_to_send()))
        self.transport.close()

    def handle_ping(self) -> None:
        pong = self.conn.data_to_send()  # what websockets queued in answer
        if self.close_sent:
            return
        now = self.loop.time()
        if now - self._ping_second >= 1.0:
            self._ping_second, self._pings = now, 0
        self._pings += 1
        if self._pings > self.max_pings_per_s:
            _client_warnings.warning(
                "pings",
                "closing a WebSocket from %s: more than %d pings in a second (1008)",
                _peer(self.client),
                self.max_pings_per_s,
            )
            self._close(1008, "too many pings")
            return
        if self.writable.is_set():  # the transport's buffer is under its high-water mark: the client reads
            self.transport.write(b"".join(pong))

    def _close(self, code: int, reason: str) -> None:
        """Close as the app's websocket.close does: the app told, the close frame sent, and the connection closed
        once the client answers it (or after close_timeout). Closed at once, a client still sending would get a
        reset, which can discard the close frame before the client reads it."""
        self.queue.put_nowait({"type": "websocket.disconnect", "code": code, "reason": reason})
        self.conn.send_close(code, reason)
        self.transport.write(b"".join(self.conn.data_to_send()))
        self.close_sent = True
        if self.read_paused:  # the client's answer must be read
            self.read_paused = False
            self.transport.resume_reading()
        self.close_timer = self.loop.call_later(self.close_timeout, self.transport.close)

    def send_receive_event_to_app(self) -> None:
        if self.curr_msg_data_type == "text" and not self.close_sent:
            try:
                b"".join(self.frames).decode()
            except UnicodeDecodeError:
                self.frames = []
                _client_warnings.warning(
                    "utf8", "closing a WebSocket from %s: a text frame that is not UTF-8 (1007)", _peer(self.client)
                )
                self._close(1007, "text frames must be UTF-8")
                return
        super().send_receive_event_to_app()


class SessionEndingServer(uvicorn.Server):
    """uvicorn.Server that ends the service's sessions first on shutdown (SIGINT, SIGTERM, should_exit)."""

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        state = getattr(getattr(self.config.app, "state", None), "service", None)  # None before the lifespan start
        if state is not None:
            await state.end_sessions()
        await super().shutdown(sockets)


def check_port_free(host: str, port: int) -> None:
    """ValueError naming the port when something already listens on (host, port), the port is outside 0–65535 or the
    host is no address of this machine: `serve` and the demo say so before they load anything (uvicorn found it only
    after start-up, with an ERROR line or a traceback). Port 0 is any free port: only the host is checked."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port < 65536:
        raise ValueError(f"--port must be a TCP port, 1–65535, or 0 for any free one; got {port!r}")
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds: a closing socket is no user
        try:
            probe.bind((host, port))
        except socket.gaierror as exc:  # the name resolves to nothing: no use stopping anything or changing the port
            raise ValueError(f"--host {host!r} is no address of this machine ({exc.strerror})") from None
        except OSError as exc:
            raise ValueError(
                f"{host}:{port} is not free ({exc.strerror}): stop what uses it (another demo or service?) or pass "
                "--port"
            ) from None


def bind_socket(host: str, port: int) -> socket.socket:
    """A socket bound to (host, port) as uvicorn binds one, for `Server.serve(sockets=…)`: a caller that passes port
    0 (any free port) learns the bound one from getsockname() before it serves. OSError when it cannot bind."""
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    return sock


def serve(app: Any, settings: Settings, **overrides: Any) -> None:
    """Run `app` with server_options(settings, **overrides) until SIGINT/SIGTERM (uvicorn.run's way, sessions
    ended first)."""
    try:
        SessionEndingServer(uvicorn.Config(app, **server_options(settings, **overrides))).run()
    except KeyboardInterrupt:  # uvicorn re-raises the SIGINT it handled; uvicorn.run exits 0 on it, and so do we
        pass


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


#: characters that would start a new line (or rewrite one) in a log file or terminal, and how a record shows them
_CONTROLS = {c: f"\\x{c:02x}" for c in (*range(0x20), 0x7F, 0x85)} | {
    ord("\n"): "\\n",
    ord("\r"): "\\r",
    ord("\t"): "\\t",
    0x2028: "\\u2028",
    0x2029: "\\u2029",
}


class EscapeControls(logging.Filter):
    """Escapes line breaks and other control characters in a record's message (its arguments formatted in): what a
    client sent (a URL's path, a field) can never start a line of its own — a forged ERROR line or traceback. The
    record's traceback (exc_info), which the formatter adds, keeps its lines."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        escaped = message.translate(_CONTROLS)
        if escaped != message:
            record.msg, record.args = escaped, None
        return True


_REDACTION = RedactQueries()
_ESCAPES = EscapeControls()
_THROTTLE = ThrottleFilter(UVICORN_CLIENT_LINES)
_REFUSED_ACCEPTS = RefusedSocketFilter(UVICORN_ACCEPT_LINES)


def install_log_redaction() -> None:
    """Put RedactQueries and EscapeControls on uvicorn's loggers, EscapeControls on the root's handlers (the
    service's records), and the throttle on uvicorn's client-caused lines (idempotent)."""
    for name in ("uvicorn.error", "uvicorn.access", "uvicorn"):
        logger = logging.getLogger(name)
        for f in (_REDACTION, _ESCAPES):
            if f not in logger.filters:
                logger.addFilter(f)
    for handler in logging.getLogger().handlers:  # the service's own records reach the log through the root's
        if _ESCAPES not in handler.filters:
            handler.addFilter(_ESCAPES)
    error = logging.getLogger("uvicorn.error")
    for throttle in (_THROTTLE, _REFUSED_ACCEPTS):
        if throttle not in error.filters:
            error.addFilter(throttle)


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
        "ws": RefusingWebSocketProtocol,
        "proxy_headers": True,
        "forwarded_allow_ips": settings.forwarded_allow_ips,
        "access_log": settings.log_level == "debug",  # lines without query strings (RedactQueries), but many
    }
    return {**options, **overrides}
