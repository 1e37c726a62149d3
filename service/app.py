"""The FastAPI application: `create_app(settings)` assembles the routers (service/routes: sessions, ingest,
events, ops), the probe, body-size and CORS middlewares and the error handlers.

Routes are thin: FastAPI dependencies (service/deps.py) hand them the state, the runtime and the
session their token opens; ServiceError becomes a status and a readable `detail`. The app imports
no torch (a test checks it in a fresh interpreter).
"""

from __future__ import annotations

from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request, WebSocket
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.utils import get_openapi
from fastapi.responses import Response
from starlette.requests import ClientDisconnect

from service.deps import refuse
from service.errors import ErrorResponse, ServiceError, invalid_fields
from service.events import StatusEvent, WindowEvent
from service.http_head import HeadAsGet
from service.limits import BodySizeLimit
from service.probes import ProbeAnswers
from service.routes import events, ingest, library, ops, sessions
from service.schemas import JsonBlock, JsonTapBlock
from service.server import server_options
from service.settings import Settings
from service.state import ServiceState
from service.thread_cpu import CpuMeter

__all__ = ["create_app", "server_options", "route_paths"]

DESCRIPTION = """
Turns a robot's accelerometer, force and camera streams into four perceptual ratings
(rough_smooth, flat_bumpy, sticky_slippery, hard_soft; bipolar −100…100) and the nearest
texture-rendering model of the library, streamed to operators. See docs/service.md.

`POST /sessions` needs a fleet API key (`Authorization: Bearer <key>`); the session's routes take its
robot or operator token.

**WebSockets** (not expressible in OpenAPI; codes and formats in `drivers/protocol.py`):

* `WS /sessions/{session_id}/ingest?token=<robot_token>` — send binary (`application/x-hapticlink-block`
  layout) or text-JSON blocks; each is answered with `{"seq", "ok": true, "duplicate"}` or
  `{"seq": int|null, "ok": false, "error"}` (a bad block does not close the socket). Close code
  **4429**: the session is saturated, reconnect after a backoff and resend from the oldest
  unacknowledged block; **4409**: a newer ingest socket of the session replaced this one (at most two at
  once), the same; **1008**: authentication failed; **4421**: the session runs on another replica;
  **1013**: not ready yet; **1000**: the session ended. A handshake for a session no replica knows is answered
  HTTP 404, for a lost one (the replica that held it is gone) HTTP 410: open a new session.
* `WS /sessions/{session_id}/events?token=<operator_token>` — JSON events: `{"type": "window", …}`
  per analysed window (schema: `WindowEvent` in the components — ratings with their per-attribute
  prediction `interval` at the configured level, `out_of_distribution` with its `ood_reasons`, and
  `steadiness`) and `{"type": "status", "event": …}` (`StatusEvent`: subscribed, session_created,
  session_ended, frame_received, visual_updated, waiting_for_frame, robot_disconnected, error).
  A slow connection gets the latest events; older ones are dropped. `&view=render` gives a renderer the lean
  feed instead (binary): a choice (entry id, model version, ratings) when the chosen entry changes, 4 bytes of
  int8 ratings on other windows (drivers/render_feed.py).
"""


def create_app(settings: Settings | None = None, cpu_meter: CpuMeter | None = None) -> FastAPI:
    """The service as an ASGI app; state lives in `app.state.service` between lifespan start and end. `cpu_meter`:
    what admission measures the service's CPU by (service/thread_cpu.py; its own threads' CPU clocks by default)."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        state = ServiceState(settings, cpu_meter)
        await state.start()
        app.state.service = state
        try:
            yield
        finally:
            await state.close()

    app = FastAPI(title="hapticlink", version="0.1.0", description=DESCRIPTION, lifespan=lifespan)
    app.add_middleware(HeadAsGet)  # innermost: what answers a GET answers its HEAD, credentials and all
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)
    # Browsers only: no origin is allowed unless configured (preflights from others are answered 400).
    app.add_middleware(
        CORSMiddleware,
        allow_origins=list(settings.cors_origins),
        allow_methods=["GET", "POST", "DELETE"],
        allow_headers=["Authorization", "Content-Type"],
        max_age=600,
    )
    # Added last, so outermost: probes are answered before CORS, routing and dependency resolution, which under
    # load queue behind everything else (a probe needs none of them; a load balancer sends no Origin).
    app.add_middleware(
        ProbeAnswers,
        live=lambda: app.state.service.health_report(),
        ready=lambda: app.state.service.ready_report(),
    )
    app.add_exception_handler(ServiceError, _service_error)  # type: ignore[arg-type]  # BodyTooLarge (413) too
    app.add_exception_handler(RequestValidationError, _invalid)  # type: ignore[arg-type]
    app.add_exception_handler(ClientDisconnect, _client_gone)  # type: ignore[arg-type]
    for module in (sessions, ingest, events, library, ops):
        app.include_router(module.router)
    app.add_api_websocket_route("/{path:path}", _no_socket_here)  # last: only what no route above takes
    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    return app


def route_paths(app: FastAPI) -> set[str]:
    """Every HTTP and WebSocket path the app serves (routers included)."""
    paths: set[str] = set()

    def walk(routes) -> None:
        for r in routes:
            if getattr(r, "path", None):
                paths.add(r.path)
            elif hasattr(r, "original_router"):  # an included router
                walk(r.original_router.routes)

    walk(app.routes)
    return paths


async def _no_socket_here(websocket: WebSocket, path: str) -> None:
    """A WebSocket handshake on a path with no socket: 404 naming the two there are (Starlette would close it before
    accepting, which uvicorn answers 403 with no body)."""
    detail = f"no WebSocket at /{path}: the sockets are /sessions/{{id}}/ingest and /sessions/{{id}}/events"
    await refuse(websocket, ServiceError(404, detail), robot=False)


async def _service_error(request: Request, exc: ServiceError) -> ErrorResponse:
    return ErrorResponse({"detail": exc.detail}, status_code=exc.status, headers=exc.headers)


async def _client_gone(request: Request, exc: ClientDisconnect) -> Response:
    # The client closed its connection (or the read deadline closed it) before its body was read: a robot's link
    # dropping mid-upload. Nothing was accepted, and nobody reads an answer; one rate-limited WARNING, no traceback.
    route = request.scope.get("route")
    request.app.state.service.refusal_log.warning(
        "client_disconnect",
        "a client closed its connection before its request body was read (%s %s)",
        request.method,
        getattr(route, "path", "?"),  # the route's template: no session id, no token
    )
    return Response(status_code=400)


async def _invalid(request: Request, exc: RequestValidationError) -> ErrorResponse:
    # One readable sentence instead of pydantic's list, so every 4xx has the same shape.
    return await _service_error(request, invalid_fields(exc.errors()))


def _openapi(app: FastAPI) -> dict[str, Any]:
    """FastAPI's schema plus the JSON block models the raw request bodies refer to, and the events the operators'
    WebSocket sends (WindowEvent, StatusEvent: a WebSocket is no OpenAPI operation, so they are components)."""
    if app.openapi_schema is None:
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        for model in (JsonBlock, JsonTapBlock, WindowEvent, StatusEvent):
            schema_part = model.model_json_schema(ref_template="#/components/schemas/{model}")
            components.update(schema_part.pop("$defs", {}))
            components[model.__name__] = schema_part
        body = schema["paths"]["/sessions/{session_id}/blocks"]["post"]["requestBody"]["content"]["application/json"]
        body["schema"] = {
            "oneOf": [{"$ref": "#/components/schemas/JsonBlock"}, {"$ref": "#/components/schemas/JsonTapBlock"}]
        }
        body["example"] = JsonBlock.model_config["json_schema_extra"]["examples"][0]  # type: ignore[index]
        app.openapi_schema = schema
    return app.openapi_schema
