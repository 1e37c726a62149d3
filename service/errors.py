"""One exception for every refusal the service answers with a 4xx/5xx and a message."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

from starlette.responses import JSONResponse

from drivers.protocol import SESSION_LOST


class ServiceError(Exception):
    """A refusal: HTTP `status` with `detail` (the message the client sees) and optional headers.

    WebSocket handlers map it to an error acknowledgement or a close code instead.
    """

    def __init__(self, status: int, detail: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.headers = headers or {}


class ErrorResponse(JSONResponse):
    """The JSON answer of a refusal, in ASCII: a detail that quotes what a client sent (a channel's name, a field)
    may hold characters UTF-8 cannot encode (a lone surrogate, legal in a JSON string), which JSONResponse's UTF-8
    rendering would turn into a 500."""

    def render(self, content: Any) -> bytes:
        return json.dumps(content, ensure_ascii=True, allow_nan=False, separators=(",", ":")).encode("ascii")


def saturated(what: str, retry_after_s: float) -> ServiceError:
    """429 with Retry-After (whole seconds are what HTTP caches understand; fractions are accepted by our robot)."""
    return ServiceError(429, what, {"Retry-After": f"{retry_after_s:g}"})


def bad_input(exc: ValueError) -> ServiceError:
    """A ValueError from the shared validation code, as 422 with its message."""
    return ServiceError(422, str(exc))


def not_json(reason: object) -> ServiceError:
    """400: a body that is not JSON Python can read (its syntax, an integer of thousands of digits, bytes that are
    not UTF-8, nesting too deep), with the reason."""
    return ServiceError(400, f"body is not valid JSON: {reason}")


def invalid_fields(errors: Sequence[Mapping[str, Any]], *, under: tuple[str, ...] = ()) -> ServiceError:
    """422 naming each field pydantic refused, in one sentence ("body.name: String should have at most 200
    characters"); under: where the validated object sits (("body",) for a request body validated by hand)."""
    parts = [".".join(str(p) for p in (*under, *e.get("loc", ()))) + f": {e.get('msg')}" for e in errors]
    return ServiceError(422, "; ".join(parts) or "invalid request")


def session_not_found(session_id: str) -> ServiceError:
    return ServiceError(404, f"no session {session_id!r}")


def session_lost(session_id: str, reason: str) -> ServiceError:
    """410: the session existed, but the replica holding its state is gone; nothing can resume it."""
    return ServiceError(SESSION_LOST, f"session {session_id} is lost: {reason}; open a new session")
