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

import json
import logging
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from starlette.types import ASGIApp, Receive, Scope, Send

from service.runtime import Runtime
from service.schemas import HealthOut, ReadyOut

log = logging.getLogger(__name__)


def health(instance: str) -> HealthOut:
    """GET /health: the process runs."""
    return HealthOut(status="ok", instance=instance)


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
    )
    return body, 200 if ok else 503


Live = Callable[[], HealthOut]
Ready = Callable[[], tuple[ReadyOut, int]]
PATHS = ("/health", "/ready")


def answer(path: str, live: Live, ready: Ready) -> tuple[bytes, int]:
    """The JSON body and status of GET `path`, one of PATHS (both servers answer through this)."""
    if path == "/health":
        body, status = live().model_dump(), 200
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
            timeout = 5.0  # a connection that sends nothing holds its thread this long at most
            disable_nagle_algorithm = True  # headers and body are two writes: no 40 ms delayed-ACK wait between them

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

        self._server = ThreadingHTTPServer((host, port), Handler)
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
