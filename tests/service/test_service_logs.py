"""Logs clients cannot write to, on a real uvicorn with real clients: refused handshakes, a text frame that is
not UTF-8, a request body cut off by a dropped link and a garbled HTTP request log at most one WARNING per kind
(rate-limited), with no traceback and never at ERROR; the service keeps serving."""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import time
from collections import Counter

import httpx
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

REPEATS = 5
WATCHED = ("", "uvicorn", "uvicorn.error", "uvicorn.access", "service")


class Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if not any(r is record for r in self.records):  # a record reaches every watched ancestor
            self.records.append(record)


@pytest.fixture
def captured():
    """Every record of the root, uvicorn's and the service's loggers (uvicorn's do not propagate to the root)."""
    handler = Records()
    loggers = [logging.getLogger(name) for name in WATCHED]
    for logger in loggers:
        logger.addHandler(handler)
    try:
        yield handler.records
    finally:
        for logger in loggers:
            logger.removeHandler(handler)


def _refused(url: str) -> int | None:
    """Open a WebSocket the server refuses → the HTTP status of the refusal, or the close code after an accept."""
    try:
        with connect(url) as ws:
            ws.recv(timeout=5)
    except InvalidStatus as exc:
        return exc.response.status_code
    except ConnectionClosed as exc:
        return exc.rcvd.code if exc.rcvd else None
    return None


def test_client_mistakes_write_no_error_and_one_warning_per_kind(kit, server, client, captured):
    session = kit.create_session(client)
    sid = session["session_id"]
    operator_events = f"{server.ws_url}/sessions/{sid}/events?token={session['operator_token']}"
    cases = {
        "unknown session, ingest": (f"{server.ws_url}/sessions/test-a.nobody/ingest?token=x", 404),
        "unknown session, events": (f"{server.ws_url}/sessions/test-a.nobody/events?token=x", 404),
        "wrong token, events": (f"{server.ws_url}/sessions/{sid}/events?token=wrong", 401),
        "wrong token, ingest": (f"{server.ws_url}/sessions/{sid}/ingest?token=wrong", 1008),
        "robot token, events": (f"{server.ws_url}/sessions/{sid}/events?token={session['robot_token']}", 403),
        "unknown view, events": (f"{operator_events}&view=x", 422),
    }
    for name, (url, expected) in cases.items():
        for _ in range(REPEATS):
            assert _refused(url) == expected, name
    for _ in range(REPEATS):  # a text frame that is not UTF-8: the socket closes 1007
        with connect(kit.socket_url(server, session, "ingest")) as ws:
            with ws.send_context():
                ws.protocol.send_text(b"\xff\xfe{")
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=5)
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 1007
    for path, kind in (("blocks", "application/json"), ("frames", "image/png"), ("scene", "application/octet-stream")):
        for _ in range(REPEATS):  # headers and part of the body, then the link drops
            with socket.create_connection(("127.0.0.1", server.port), timeout=5) as raw:
                raw.sendall(
                    f"POST /sessions/{sid}/{path} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
                    f"{session['robot_token']}\r\nContent-Type: {kind}\r\nContent-Length: 2048\r\n\r\n".encode()
                    + b"\0" * 10
                )
                time.sleep(0.05)  # the request reaches the route, which waits for the rest of its body
    for _ in range(REPEATS):  # not HTTP at all
        with socket.create_connection(("127.0.0.1", server.port), timeout=5) as raw:
            raw.sendall(b"\x16\x03\x01 not http\r\n\r\n")
            assert raw.recv(1024).startswith(b"HTTP/1.1 400")
    # the service is unharmed
    block = kit.recording_blocks(kit.stroke_recording(server.settings.library_dir, "synth_001", 0.1))[0]
    assert kit.post_block(client, session, block).status_code == 202
    assert httpx.get(f"{server.url}/health", timeout=5).status_code == 200

    mine = [r for r in captured if not r.name.startswith(("httpx", "httpcore", "websockets"))]
    assert [r.getMessage() for r in mine if r.levelno >= logging.ERROR] == []
    assert [r.getMessage() for r in mine if r.exc_info] == []
    warnings = Counter(r.getMessage() for r in mine if r.levelno == logging.WARNING)
    # at most one line per kind of mistake (9 kinds), not one per request (55)
    assert all(n == 1 for n in warnings.values()) and sum(warnings.values()) <= len(cases) + 3, warnings
    assert any("closed its connection before its request body was read" in w for w in warnings), warnings


def test_a_session_request_cut_off_by_a_dropped_link_logs_one_warning(kit, base_settings, captured):
    """POST /sessions whose body never arrives whole: one throttled WARNING naming the route, as on every other
    route (FastAPI turns the dropped link into its own bare 400 first), no ERROR, nothing created."""
    settings = base_settings.model_copy(update={"instance_id": "cut-off"})
    with kit.running(settings) as srv:
        for _ in range(REPEATS):
            with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as raw:
                raw.sendall(
                    b"POST /sessions HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
                    + kit.API_KEY.encode()
                    + b'\r\nContent-Type: application/json\r\nContent-Length: 100\r\n\r\n{"name":'
                )
                time.sleep(0.05)  # the request reaches the route, which waits for the rest of its body
        kit.wait_for(lambda: any("closed its connection" in r.getMessage() for r in captured), timeout_s=5)
        assert srv.app.state.service.directory.sessions == {}
    mine = [r for r in captured if not r.name.startswith(("httpx", "httpcore", "websockets"))]
    assert [r.getMessage() for r in mine if r.levelno >= logging.ERROR] == []
    cut = [r.getMessage() for r in mine if "closed its connection" in r.getMessage()]
    assert len(cut) == 1 and "(POST /sessions)" in cut[0], cut


def test_a_socket_on_a_path_with_none_is_refused_404_with_a_reason(server):
    """Starlette closed such a handshake before accepting it, which uvicorn answers 403 with no body."""
    for path in ("/health", "/nonexistent", "/sessions/x/blocks"):
        with pytest.raises(InvalidStatus) as refused:
            with connect(f"{server.ws_url}{path}"):
                pass
        assert refused.value.response.status_code == 404, path
        detail = json.loads(refused.value.response.body)["detail"]
        assert f"no WebSocket at {path}" in detail and "/sessions/{id}/ingest" in detail, detail


def test_refused_handshakes_write_a_few_lines_not_two_per_refusal(kit, base_settings):
    """uvicorn (and the websockets library under it) wrote two INFO lines for every refused handshake, the request
    line and 'connection rejected (…)': 2,000 unauthenticated upgrades were 4,002 lines. Now each kind is
    throttled like uvicorn's client WARNINGs: one line every 10 s."""
    settings = base_settings.model_copy(update={"instance_id": "refusals"})
    handler = Records()
    with kit.running(settings, log_level="info") as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        logging.getLogger("uvicorn.error").addHandler(handler)  # after the start: uvicorn's log config resets it
        try:
            session = kit.create_session(client)
            urls = [
                f"{srv.ws_url}/sessions/{session['session_id']}/events?token=wrong",  # 401
                f"{srv.ws_url}/sessions/refusals.nobody/events?token=x",  # 404
            ]
            for _ in range(20):
                for url in urls:
                    assert _refused(url) in (401, 404)
        finally:
            logging.getLogger("uvicorn.error").removeHandler(handler)
    lines = [r.getMessage() for r in handler.records]
    refusals = [m for m in lines if '"WebSocket /sessions/' in m]
    rejected = [m for m in lines if "connection rejected" in m]
    assert 1 <= len(refusals) <= 2 and 1 <= len(rejected) <= 2, (refusals, rejected)


def test_a_client_that_leaves_with_pipelined_answers_unread_writes_no_error(kit, server, captured):
    """Pipelined requests whose answers the client never reads, then the link drops: uvicorn marked only the newest
    parsed request disconnected, so the one still answering wrote to the closed transport and logged an ERROR with
    a traceback per connection, for any client, without a credential."""
    for _ in range(3):
        with socket.create_connection(("127.0.0.1", server.port), timeout=5) as raw:
            raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            raw.setblocking(False)
            with contextlib.suppress(BlockingIOError):
                raw.send(b"GET /openapi.json HTTP/1.1\r\nHost: x\r\n\r\n" * 100)
            time.sleep(0.5)  # the server's write buffer fills behind the unread answers
    time.sleep(0.5)
    assert httpx.get(f"{server.url}/health", timeout=5).status_code == 200
    mine = [r for r in captured if not r.name.startswith(("httpx", "httpcore", "websockets"))]
    assert [r.getMessage() for r in mine if r.levelno >= logging.ERROR] == []
    assert [r.getMessage() for r in mine if r.exc_info] == []


def test_escape_controls_known_answers():
    from service.server import EscapeControls

    def record(msg, *args, exc_info=None):
        return logging.LogRecord("service.x", logging.WARNING, __file__, 1, msg, args, exc_info)

    forged = record("session %r from %s refused", "a\nb", "c\rd\x1b[2J\u2028e")
    assert EscapeControls().filter(forged) is True
    assert forged.getMessage() == "session 'a\\nb' from c\\rd\\x1b[2J\\u2028e refused"
    plain = record("session %s created for %s", "hl.1", "10.0.0.1")
    EscapeControls().filter(plain)
    assert plain.args == ("hl.1", "10.0.0.1")  # a clean record is left as it was, its arguments unformatted
    try:
        raise ValueError("boom")
    except ValueError:
        import sys

        failed = record("estimation failed:\n%s", "x", exc_info=sys.exc_info())
    EscapeControls().filter(failed)
    text = logging.Formatter("%(levelname)s %(message)s").format(failed)
    assert text.startswith("WARNING estimation failed:\\nx\nTraceback")  # the traceback keeps its own lines


@pytest.mark.parametrize(
    "path",
    [
        "/sessions/s1/ingest?token=SECRET",
        "/sessions/s1/ingest?v='&token=SECRET",
        '/sessions/s1/events?v="&token=SECRET',
        "/sessions/s1/events?view=render&token=SECRET&x=1",
    ],
)
def test_redact_queries_cuts_the_whole_query_a_quote_in_it_included(path):
    """The query was cut only up to a quote: `?v='&token=…` wrote a live token into the log."""
    from service.server import RedactQueries

    as_argument = logging.LogRecord("uvicorn.error", logging.INFO, __file__, 1, '%s - "WebSocket %s" [accepted]',
                                    ("127.0.0.1:5", path), None)  # fmt: skip
    as_text = logging.LogRecord("uvicorn.error", logging.INFO, __file__, 1, f'GET {path} HTTP/1.1" 404', (), None)
    for record in (as_argument, as_text):
        assert RedactQueries().filter(record) is True
        message = record.getMessage()
        assert "SECRET" not in message and "/sessions/s1/" in message
