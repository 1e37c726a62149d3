"""Request body size limits, enforced before the body is kept: a pure ASGI middleware, and a route's tighter limit.

The credential comes first: the app judges a request's credential (its dependencies) before it reads the body, and
the first read of a body whose declared Content-Length is over the limit fails with BodyTooLarge (413) before a byte
of it is taken; a body without one (chunked) is counted as it streams in and the read fails as soon as it passes the
limit, so no request can make the service hold more than `max_bytes` of it.
A route whose body is small (POST /sessions) lowers its own request's limit with `limit_body` before reading it:
the same count and the same refusal, with the route's reason.

A refused body is drained (read and dropped, at most DRAIN_MAX_BYTES within DRAIN_S) before the answer goes out,
and the connection closes after it: a client still sending when the server closes gets a TCP reset, which destroys
the answer it has not read yet, so without the drain a 10 MB upload never reads its 413.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass

from starlette.requests import Request
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import ServiceError

#: where BodySizeLimit keeps a request's BodyLimit in its ASGI scope
SCOPE_KEY = "hapticlink.body_limit"
#: the most of a refused body read and dropped before its 413 goes out (past it the answer goes out at once and the
#: client may not read it): a declared length is refused before any of it is read, so this bounds what one refused
#: request costs, 64 MiB of reading at loopback speed (tens of milliseconds)
DRAIN_MAX_BYTES = 64 * 1024 * 1024
#: the longest a refused body is drained for: a client that trickles it gets its answer then
DRAIN_S = 5.0


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
    complete: bool = False  # the whole body has been received (or the client left)

    @property
    def over(self) -> bool:
        return max(self.declared or 0, self.seen) > self.limit

    def check(self) -> None:
        """BodyTooLarge when the declared length or the bytes seen so far pass the limit."""
        if self.over:
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
        scope[SCOPE_KEY] = body
        if not body.declared:  # nothing declared (or 0): there may be nothing to read
            body.complete = body.declared == 0

        async def counted() -> Message:
            body.check()  # a declared length over the limit: refused at the first read, before a byte is taken
            message = await receive()
            if message["type"] == "http.request":
                body.complete = not message.get("more_body", False)
                body.count(len(message.get("body", b"")))
            else:  # http.disconnect
                body.complete = True
            return message

        async def answered(message: Message) -> None:
            if message["type"] == "http.response.start" and body.over:
                # refused (413, or answered without reading, a 401): read what the client is still sending, then
                # close after the answer, so that the client reads it instead of a reset
                if not body.complete:
                    await _drain(receive, body)
                headers = [(k, v) for k, v in message.get("headers", []) if k.lower() != b"connection"]
                message = {**message, "headers": [*headers, (b"connection", b"close")]}
            await send(message)

        await self.app(scope, counted, answered)


def _content_length(scope: Scope) -> int | None:
    for name, value in scope.get("headers", []):
        if name == b"content-length":
            # digits only: int() would also read "1_000" or "+13", which no HTTP parser should pass on
            digits = value.strip()
            return int(digits) if digits.isdigit() else None
    return None


async def _drain(receive: Receive, body: BodyLimit) -> None:
    """Read and drop the rest of a refused body: at most DRAIN_MAX_BYTES, for at most DRAIN_S (a client that sends
    more, or slower, gets its answer then, and the connection closes on what it has not sent)."""
    deadline = time.monotonic() + DRAIN_S
    drained = 0
    while not body.complete and drained < DRAIN_MAX_BYTES:
        left = deadline - time.monotonic()
        if left <= 0:
            return
        try:
            message = await asyncio.wait_for(receive(), left)
        except TimeoutError:
            return
        if message["type"] != "http.request":
            return
        drained += len(message.get("body", b""))
        body.complete = not message.get("more_body", False)
