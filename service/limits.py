"""Request body size limits, enforced before the body is read: a pure ASGI middleware, and a route's tighter limit.

A declared Content-Length over the limit is answered 413 at once; a body without one (chunked)
is counted as it streams in and the read fails with BodyTooLarge (answered 413) as soon as it
passes the limit, so no request can make the service hold more than `max_bytes` of it.
A route whose body is small (POST /sessions) lowers its own request's limit with `limit_body` before reading it:
the same count and the same refusal, with the route's reason.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from starlette.requests import Request
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import ServiceError

#: where BodySizeLimit keeps a request's BodyLimit in its ASGI scope
SCOPE_KEY = "hapticlink.body_limit"


class BodyTooLarge(ServiceError):
    """413 with the limit's reason; the rest of the body is left unread, so the connection cannot carry another
    request."""

    def __init__(self, detail: str) -> None:
        super().__init__(413, detail, {"Connection": "close"})


def too_large_detail(limit: int) -> str:
    return f"request body too large: at most {limit} bytes (HAPTICLINK_MAX_BODY_BYTES)"


@dataclass
class BodyLimit:
    """One request's body against `limit` bytes: its declared length (None: not declared) and what has streamed in
    so far; `detail` is the refusal's reason."""

    limit: int
    detail: str
    declared: int | None
    seen: int = 0

    def check(self) -> None:
        """BodyTooLarge when the declared length or the bytes seen so far pass the limit."""
        if max(self.declared or 0, self.seen) > self.limit:
            raise BodyTooLarge(self.detail)

    def count(self, n: int) -> None:
        self.seen += n
        self.check()


def limit_body(request: Request, limit: int, detail: str) -> None:
    """Lower this request's body limit to `limit` bytes (refused 413 with `detail`) before reading its body;
    BodyTooLarge at once when its declared length is already over. A limit above the service's keeps the service's."""
    body: BodyLimit | None = request.scope.get(SCOPE_KEY)
    if body is None:
        raise RuntimeError("limit_body needs the BodySizeLimit middleware")
    if limit < body.limit:
        body.limit, body.detail = limit, detail
    body.check()


class BodySizeLimit:
    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        body = BodyLimit(self.max_bytes, too_large_detail(self.max_bytes), _content_length(scope))
        try:
            body.check()
        except BodyTooLarge as exc:
            await _reject(scope, send, exc)
            return
        scope[SCOPE_KEY] = body

        async def counted() -> Message:
            message = await receive()
            if message["type"] == "http.request":
                body.count(len(message.get("body", b"")))
            return message

        await self.app(scope, counted, send)


def _content_length(scope: Scope) -> int | None:
    for name, value in scope.get("headers", []):
        if name == b"content-length":
            # digits only: int() would also read "1_000" or "+13", which no HTTP parser should pass on
            digits = value.strip()
            return int(digits) if digits.isdigit() else None
    return None


async def _reject(scope: Scope, send: Send, exc: BodyTooLarge) -> None:
    """The refusal, answered here (the app never runs); a HEAD gets its headers alone, as HeadAsGet gives them."""
    body = json.dumps({"detail": exc.detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": exc.status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                *((k.lower().encode(), v.encode()) for k, v in exc.headers.items()),
            ],
        }
    )
    await send({"type": "http.response.body", "body": b"" if scope.get("method") == "HEAD" else body})
