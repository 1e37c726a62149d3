"""HEAD for every GET route: a pure ASGI middleware.

HTTP says a resource served by GET answers HEAD with the same status and headers and no body (`curl -I`, link
checkers, some load balancers); FastAPI routes answer it 405. The request goes on as a GET — the same routing,
credentials and checks — and the response's body is dropped here (uvicorn drops it too; another server might not).
/health and /ready answer HEAD before reaching this (service.probes.ProbeAnswers).
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send


class HeadAsGet:
    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return

        async def headers_only(message: Message) -> None:
            if message["type"] == "http.response.body":
                message = {**message, "body": b""}
            await send(message)

        await self.app({**scope, "method": "GET"}, receive, headers_only)
