"""Liveness and readiness, answered the same way on the service's port and on a probe port of their own.

`health(instance)` and `readiness_report(readiness, runtime)` build the answers of GET /health and
GET /ready (the routes in service/routes/ops.py call them). `ProbeServer` answers the same two paths
from a thread of its own (`HAPTICLINK_PROBE_PORT`), with the standard library's threading HTTP
server: it needs nothing of the event loop, so a loop that ingest keeps busy cannot delay it. Its
threads only read the state (under the GIL, one attribute read at a time), and the short GIL switch
interval the service sets (`gil_switch_interval_s`) bounds how long they wait for the interpreter
behind the loop and the pools.
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import sys
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from starlette.types import ASGIApp, Receive, Scope, Send

from service.log_throttle import LogThrottle
from service.runtime import Runtime
from service.schemas import BackboneOut, HealthOut, ReadyOut

log = logging.getLogger(__name__)
_dropped = LogThrottle(log)
#: connections the probe port serves at once; beyond it a new one is closed at once (a probe is one short request,
#: so only a client holding connections open reaches this: it costs threads, never memory without bound)
MAX_PROBE_CONNECTIONS = 64
#: a request (from the wait for its first byte to its answer) gets this long, however slowly its bytes drip in
PROBE_REQUEST_S = 5.0
#: connections the kernel queues before the probe thread accepts them (socketserver's default is 5: a client
#: connecting in a loop made liveness probes time out)
PROBE_LISTEN_BACKLOG = 128


def health(instance: str, probe_port: int | None = None) -> HealthOut:
    """GET /health: the process runs; probe_port: the port orchestrators should probe, when one is set."""
    return HealthOut(status="ok", instance=instance, probe_port=probe_port)


def readiness_report(readiness: tuple[bool, str], rt: Runtime | None) -> tuple[ReadyOut, int]:
    """GET /ready from (ready, why) and the runtime once loaded: (the answer, 200 when ready else 503)."""
    ok, why = readiness
    if rt is None:
        return ReadyOut(ready=ok, detail=why), 200 if ok else 503
    body = ReadyOut(
        ready=ok,
        detail=why,
        model=rt.model_name,
        modality=rt.predictor.card.modality,
        tactile_model=rt.tactile.card.model if rt.tactile else None,
        library=rt.library.name,
        library_entries=len(rt.library.ids),
        backbone=rt.backbone.name if rt.backbone else None,
        backbone_check=None if rt.backbone_status is None else BackboneOut(**rt.backbone_status.to_dict()),
    )
    return body, 200 if ok else 503


Live = Callable[[], HealthOut]
Ready = Callable[[], tuple[ReadyOut, int]]
PATHS = ("/health", "/ready")


def answer(path: str, live: Live, ready: Ready) -> tuple[bytes, int]:
    """The JSON body and status of GET `path`, one of PATHS (both servers answer through this)."""
    if path == "/health":
        body, status = live().model_dump(exclude_none=True), 200
    else:
        out, status = ready()
        body = out.model_dump()
    return json.dumps(body).encode(), status


class ProbeAnswers:
    """ASGI middleware: GET (and HEAD: the same status and headers, no body; `curl -I`, some load balancers) /health
    and /ready answered from `live()` / `ready()` without entering the app; every other request (and every other
    method on those paths) goes on to `app` unchanged."""

    def __init__(self, app: ASGIApp, live: Live, ready: Ready) -> None:
        self.app = app
        self.live = live
        self.ready = ready

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in ("GET", "HEAD") or scope["path"] not in PATHS:
            await self.app(scope, receive, send)
            return
        data, status = answer(scope["path"], self.live, self.ready)
        headers = [(b"content-type", b"application/json"), (b"content-length", str(len(data)).encode())]
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": b"" if scope["method"] == "HEAD" else data})


class ProbeServer:
    """GET (and HEAD) /health and /ready on (host, port) from daemon threads; `port` 0 picks a free one (see `.port`).
    live / ready: build the two answers (called on the probe threads: they must only read)."""

    def __init__(self, live: Live, ready: Ready, host: str, port: int) -> None:

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"
            timeout = PROBE_REQUEST_S  # each read; the whole request is bounded by handle_one_request's deadline
            disable_nagle_algorithm = True  # headers and body are two writes: no 40 ms delayed-ACK wait between them

            def handle_one_request(self) -> None:
                # One byte every few seconds would reset the per-read timeout forever (a slowloris holding the
                # thread): past the deadline the socket is shut, the read sees its end and the request is over.
                deadline = threading.Timer(PROBE_REQUEST_S, self._cut)
                deadline.daemon = True
                deadline.start()
                try:
                    super().handle_one_request()
                finally:
                    deadline.cancel()

            def _cut(self) -> None:
                with contextlib.suppress(OSError):
                    self.connection.shutdown(socket.SHUT_RDWR)

            def do_GET(self) -> None:  # noqa: N802 - the standard library's name
                self._answer(body=True)

            def do_HEAD(self) -> None:  # noqa: N802 - the standard library's name
                self._answer(body=False)

            def _answer(self, body: bool) -> None:
                path = self.path.split("?", 1)[0]
                if path in PATHS:
                    data, status = answer(path, live, ready)
                else:
                    data, status = (
                        json.dumps({"detail": "the probe port answers GET and HEAD /health and /ready only"}).encode(),
                        404,
                    )
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                if body:
                    self.wfile.write(data)

            def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - the standard library's name
                pass  # one line per probe would flood the log

        self._server = _BoundedProbeServer((host, port), Handler)
        self._server.daemon_threads = True
        self._server.timeout = 1.0
        self.port = self._server.server_address[1]
        self._thread = threading.Thread(target=self._server.serve_forever, name="hapticlink-probes", daemon=True)

    def start(self) -> None:
        self._thread.start()
        log.info("liveness and readiness also on port %d (GET /health, GET /ready)", self.port)

    def stop(self) -> None:
        self._server.shutdown()
        self._server.server_close()


class _BoundedProbeServer(ThreadingHTTPServer):
    """ThreadingHTTPServer with at most MAX_PROBE_CONNECTIONS connections at once, and a client's dropped link (a
    broken pipe, a reset, a read past its deadline) one rate-limited WARNING instead of socketserver's traceback."""

    request_queue_size = PROBE_LISTEN_BACKLOG

    def __init__(self, address: tuple[str, int], handler: type[BaseHTTPRequestHandler]) -> None:
        super().__init__(address, handler)
        self._slots = threading.BoundedSemaphore(MAX_PROBE_CONNECTIONS)

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):
            _dropped.warning("full", "probe port: %d connections open; closing a new one", MAX_PROBE_CONNECTIONS)
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()

    def handle_error(self, request: Any, client_address: Any) -> None:
        if not isinstance(sys.exc_info()[1], OSError):  # not the client's doing: the answer itself failed
            log.exception("probe port: answering a request failed")
            return
        _dropped.warning(
            "dropped",
            "probe port: a connection from %s ended before its answer was sent",
            client_address[0] if client_address else "?",
        )
