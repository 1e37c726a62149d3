"""The wire protocol between robots and the service, defined once: routes, credentials, WebSocket close
codes, block acknowledgements, limits a client must respect.

The block codec (the `HLB1` binary layout and JSON) is `drivers.blocks`; this module adds what travels
around blocks. The service, the robot client, the benchmarks and the tests all import it, so a code
or a format changes in one place.

WebSocket ingest (`WS /sessions/{id}/ingest?token=<robot token>`): every message is one block
(binary or JSON text) and is answered, in order, by one text message — `ack_ok` or `ack_error`.
Close codes (`Close`): 4429 saturated (reconnect after a backoff, resend from the oldest
unacknowledged block), 4409 replaced by a newer ingest socket of the session (the same), 1008
authentication failed (fatal), 4421 misdirected (the session lives on another replica), 1013 not ready
(retry), 1000 the session ended (fatal for this session), 4410 the session is lost (fatal: its replica
dropped it as lost; the reason says why). A handshake
for a session no replica knows is refused with HTTP 404, for a lost one (`SESSION_LOST`) with HTTP 410.

HTTP: `RETRY_STATUSES` say "not now" (back off, resend); `SESSION_LOST` (410) says the replica that held
the session's state is gone (stopped, crashed or restarted): nothing resumes it, open a new session.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from enum import IntEnum
from urllib.parse import quote, urlencode, urlsplit, urlunsplit

from drivers.blocks import BINARY_CONTENT_TYPE, MAGIC, peek_header

__all__ = [
    "BINARY_CONTENT_TYPE",
    "MAGIC",
    "FRAME_CONTENT_TYPES",
    "API_KEY_ENV",
    "Close",
    "Ack",
    "ack_ok",
    "ack_error",
    "parse_ack",
    "peek_seq",
    "bearer",
    "session_path",
    "ws_url",
    "RETRY_STATUSES",
    "SESSION_LOST",
    "HANDSHAKE_REFUSALS",
    "FATAL_CLOSES",
]

#: what a fleet's API key is read from by the robot client and the CLIs (`--api-key` overrides it)
API_KEY_ENV = "HAPTICLINK_API_KEY"
FRAME_CONTENT_TYPES = ("image/png", "image/jpeg")
#: a scene check's body: the newest frame's thumbnail (drivers/scene_change.thumbnail_bytes)
SCENE_CONTENT_TYPE = "application/octet-stream"
#: HTTP statuses that say "not now" rather than "bad request": 408 timeout, 421 misdirected, 425 too early
RETRY_STATUSES = frozenset({408, 421, 425})
#: HTTP status of a lost session: its replica is gone, and its state with it; final — open a new session
SESSION_LOST = 410
#: statuses a WebSocket handshake is refused with as HTTP, never as a close code: unknown session, lost session, and
#: a session whose blocks the replica sheds (429 with Retry-After: the robot waits before it tries again)
HANDSHAKE_REFUSALS = frozenset({404, SESSION_LOST, 429})


class Close(IntEnum):
    """WebSocket close codes of the ingest and events sockets."""

    SESSION_ENDED = 1000  # the session ended (DELETE, idle reaping, shutdown); open a new one
    POLICY = 1008  # authentication failed
    TOO_BIG = 1009  # a message larger than the service's limit
    SERVER_ERROR = 1011
    RESTARTING = 1012  # the replica is shutting down (uvicorn's close of every socket left); the session is lost
    NOT_READY = 1013  # the service is loading; try again
    MISDIRECTED = 4421  # the session runs on another replica
    SATURATED = 4429  # the session has too much work queued; reconnect after a backoff and resend
    REPLACED = 4409  # a newer ingest socket of the same session took this one's place; reconnect and resend
    LOST = 4410  # the session is lost (HTTP 410's meaning, on an open socket); open a new session


#: closes after which reconnecting to the same session cannot help
FATAL_CLOSES = frozenset({Close.SESSION_ENDED, Close.POLICY, Close.LOST})


@dataclass(frozen=True)
class Ack:
    """The service's answer to one block: ok (accepted or duplicate) or an error naming the problem.
    seq is None when the service could not read it from the message."""

    seq: int | None
    ok: bool
    duplicate: bool = False
    error: str | None = None


_OK = '{"seq": %d, "ok": true, "duplicate": %s}'  # formatted without json.dumps: one per block, on the hot path


def ack_ok(seq: int, duplicate: bool) -> str:
    return _OK % (seq, "true" if duplicate else "false")


def ack_error(seq: int | None, error: str) -> str:
    return json.dumps({"seq": seq, "ok": False, "error": error})


def parse_ack(text: str | bytes) -> Ack:
    """An acknowledgement text → Ack; ValueError if it is not one."""
    try:
        obj = json.loads(text)
        ok = obj["ok"]
        seq = obj.get("seq")
    except (ValueError, KeyError, TypeError, AttributeError):
        raise ValueError(f"not an acknowledgement: {str(text)[:200]!r}") from None
    if not isinstance(ok, bool) or not (seq is None or (isinstance(seq, int) and not isinstance(seq, bool))):
        raise ValueError(f"not an acknowledgement: {str(text)[:200]!r}")
    return Ack(seq, ok, bool(obj.get("duplicate", False)), None if ok else str(obj.get("error", "no reason given")))


def peek_seq(payload: bytes, binary: bool) -> int | None:
    """The seq a (possibly bad) block declares, so an error can name it; None if unreadable."""
    header = peek_header(payload, binary)
    seq = header.get("seq") if isinstance(header, dict) else None
    return seq if isinstance(seq, int) and not isinstance(seq, bool) else None


def bearer(token: str) -> dict[str, str]:
    """The HTTP header carrying a session token or a fleet API key."""
    return {"Authorization": f"Bearer {token}"}


def session_path(session_id: str, tail: str = "") -> str:
    """`/sessions/{id}[/tail]` with the id quoted."""
    path = f"/sessions/{quote(str(session_id), safe='')}"
    return f"{path}/{tail}" if tail else path


def check_service_url(url: str) -> None:
    """ValueError unless `url` is the service's http(s)://host[:port][/prefix] (a bare host:port would be read as a
    path, and every request would fail without saying why)."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.netloc:
        raise ValueError(f"url must be http://host[:port] or https://…, got {url!r}")


def ws_url(base_url: str, session_id: str, route: str, token: str) -> str:
    """ws(s):// URL of a session's WebSocket `route` ("ingest" or "events") from the service's http(s) URL."""
    parts = urlsplit(base_url.rstrip("/"))
    scheme = "wss" if parts.scheme == "https" else "ws"
    return urlunsplit(
        (scheme, parts.netloc, parts.path + session_path(session_id, route), urlencode({"token": token}), "")
    )
