"""The FastAPI application: `create_app(settings)`.

HTTP and WebSocket routes are thin: authenticate, parse, call ServiceState, map ServiceError
to a status and a message. The app imports no torch (a test checks it in a fresh interpreter).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from contextlib import asynccontextmanager
from typing import Annotated, Any

from fastapi import Depends, FastAPI, Query, Request, WebSocket
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import HTMLResponse, JSONResponse, PlainTextResponse, Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.websockets import WebSocketDisconnect, WebSocketState

from drivers.blocks import BINARY_CONTENT_TYPE, SampleBlock, decode_binary, decode_json
from service import console
from service.auth import EITHER, OPERATOR_ONLY, ROBOT_ONLY
from service.errors import ServiceError, saturated
from service.events import encode, status_event
from service.limits import BodySizeLimit, BodyTooLarge, too_large_detail
from service.metrics import CONTENT_TYPE as METRICS_CONTENT_TYPE
from service.schemas import (
    BLOCK_REQUEST_BODY,
    FRAME_REQUEST_BODY,
    BlockAck,
    ErrorOut,
    FrameAck,
    HealthOut,
    JsonBlock,
    LibraryEntryOut,
    LibraryOut,
    ReadyOut,
    SessionCreate,
    SessionCreated,
    SessionStatus,
)
from service.session import RETRY_AFTER_S, session_not_found
from service.settings import Settings
from service.state import ServiceState

log = logging.getLogger(__name__)

FRAME_TYPES = ("image/png", "image/jpeg")
WS_SATURATED = 4429
WS_MISDIRECTED = 4421
WS_TRY_AGAIN = 1013
_OK_ACK = '{"seq": %d, "ok": true, "duplicate": %s}'  # the per-block answer, formatted without json.dumps
#: what a malformed payload can raise inside the shared decoders (huge ints overflow, deep nesting recurses)
DECODE_ERRORS = (ValueError, TypeError, OverflowError, RecursionError)

DESCRIPTION = """
Turns a robot's accelerometer, force and camera streams into four perceptual ratings
(rough_smooth, flat_bumpy, sticky_slippery, hard_soft; bipolar −100…100) and the nearest
texture-rendering model of the library, streamed to operators. See docs/service.md.

**WebSockets** (not expressible in OpenAPI):

* `WS /sessions/{session_id}/ingest?token=<robot_token>` — send binary (`application/x-hapticlink-block`
  layout) or text-JSON blocks; each is answered with `{"seq", "ok": true, "duplicate"}` or
  `{"seq": int|null, "ok": false, "error"}` (a bad block does not close the socket). Close code
  **4429**: the session is saturated, reconnect after a backoff and resend from the oldest
  unacknowledged block; **1008**: authentication failed; **1013**: not ready yet. A handshake for a session no
  replica knows is answered HTTP 404, for a lost one (its replica is gone) HTTP 410: open a new session.
* `WS /sessions/{session_id}/events?token=<operator_token>` — JSON events: `{"type": "window", …}`
  per analysed window and `{"type": "status", "event": …}` (subscribed, session_created,
  session_ended, frame_received, visual_updated, waiting_for_frame, error). A slow connection
  gets the latest events; older ones are dropped.
"""


_bearer = HTTPBearer(auto_error=False, description="the session's robot or operator token")
#: the request's bearer credentials, if any (absence is answered 401 by the session check, not here)
Token = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


def token_of(credentials: HTTPAuthorizationCredentials | None) -> str | None:
    return credentials.credentials if credentials is not None else None


def _errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: {"model": ErrorOut} for code in codes}


def _try_later(description: str) -> dict[int | str, dict[str, Any]]:
    """The documented 429 answer, with its Retry-After header."""
    return {429: {"model": ErrorOut, "description": description, "headers": {"Retry-After": {"schema": {"type": "string"}}}}}


def create_app(settings: Settings | None = None) -> FastAPI:
    """The service as an ASGI app; state lives in `app.state.service` between lifespan start and end."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        state = ServiceState(settings)
        await state.start()
        app.state.service = state
        try:
            yield
        finally:
            await state.close()

    app = FastAPI(title="hapticlink", version="0.1.0", description=DESCRIPTION, lifespan=lifespan)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)

    def state_of(request: Request | WebSocket) -> ServiceState:
        return request.app.state.service

    # ---- errors ------------------------------------------------------------------------------------
    @app.exception_handler(ServiceError)
    async def _service_error(request: Request, exc: ServiceError) -> JSONResponse:
        return JSONResponse({"detail": exc.detail}, status_code=exc.status, headers=exc.headers)

    @app.exception_handler(BodyTooLarge)
    async def _too_large(request: Request, exc: BodyTooLarge) -> JSONResponse:
        return JSONResponse({"detail": too_large_detail(exc.limit)}, status_code=413, headers={"Connection": "close"})

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        # One readable sentence instead of pydantic's list, so every 4xx has the same shape.
        parts = [f"{'.'.join(str(p) for p in e.get('loc', ()))}: {e.get('msg')}" for e in exc.errors()]
        return JSONResponse({"detail": "; ".join(parts) or "invalid request"}, status_code=422)

    # ---- sessions ----------------------------------------------------------------------------------
    @app.post("/sessions", status_code=201, response_model=SessionCreated, tags=["sessions"],
              responses=_errors(400, 422, 503), summary="Open a session")
    async def create_session(request: Request, body: SessionCreate | None = None) -> SessionCreated:
        session, robot, operator = await state_of(request).create_session(body.name if body else None)
        return SessionCreated(session_id=session.id, robot_token=robot, operator_token=operator)

    @app.get("/sessions/{session_id}", response_model=SessionStatus, tags=["sessions"],
             responses=_errors(401, 403, 404, 410, 421, 503), summary="A session's status and counters (operator token)")
    async def get_session(request: Request, session_id: str, credentials: Token) -> dict:
        session = await state_of(request).local_session(session_id, token_of(credentials), OPERATOR_ONLY)
        return session.status()

    @app.delete("/sessions/{session_id}", response_model=SessionStatus, tags=["sessions"],
                responses=_errors(401, 403, 404, 410, 421, 503), summary="End a session (robot or operator token)")
    async def delete_session(request: Request, session_id: str, credentials: Token) -> dict:
        state = state_of(request)
        await state.local_session(session_id, token_of(credentials), EITHER)
        return await state.end_session(session_id, "ended by request")

    @app.post("/sessions/{session_id}/blocks", status_code=202, response_model=BlockAck, tags=["ingest"],
              openapi_extra={"requestBody": BLOCK_REQUEST_BODY},
              responses={**_errors(400, 401, 403, 404, 410, 413, 415, 421, 422, 503),
                         **_try_later("the session is saturated; resend after Retry-After s")},
              summary="Send one sample block (robot token)")
    async def post_block(request: Request, session_id: str, credentials: Token) -> dict:
        state = state_of(request)
        session = await state.local_session(session_id, token_of(credentials), ROBOT_ONLY)
        state.require_runtime()
        kind = _media_type(request)
        if kind not in ("application/json", BINARY_CONTENT_TYPE):
            _count_rejected(state, session)
            raise ServiceError(415, f"blocks are application/json or {BINARY_CONTENT_TYPE}, got {kind or 'no Content-Type'}")
        payload = await request.body()
        return _receive_block(state, session, payload, kind == BINARY_CONTENT_TYPE, time.perf_counter_ns())

    @app.post("/sessions/{session_id}/frames", status_code=202, response_model=FrameAck, tags=["ingest"],
              openapi_extra={"requestBody": FRAME_REQUEST_BODY},
              responses={**_errors(401, 403, 404, 410, 413, 415, 421, 422, 503),
                         **_try_later("the session's previous frame is still being decoded; send the newest after Retry-After s")},
              summary="Send one camera frame (robot token)")
    async def post_frame(request: Request, session_id: str, credentials: Token) -> FrameAck:
        state = state_of(request)
        session = await state.local_session(session_id, token_of(credentials), ROBOT_ONLY)
        runtime = state.require_runtime()
        kind = _media_type(request)
        if kind not in FRAME_TYPES:
            session.counters.frames_rejected += 1
            state.metrics.frames.inc(outcome="rejected")
            raise ServiceError(415, f"frames are {' or '.join(FRAME_TYPES)}, got {kind or 'no Content-Type'}")
        if session.decoding_frame:  # one frame per session in the pool at a time: a flood of frames is refused
            state.metrics.frames.inc(outcome="refused")
            raise saturated(f"session {session.id} is still decoding its previous frame; send the newest one later",
                            RETRY_AFTER_S)
        session.decoding_frame = True
        try:
            payload = await request.body()
            gray = await asyncio.get_running_loop().run_in_executor(state.window_pool, runtime.decode_frame, payload)
        except ValueError as exc:
            session.counters.frames_rejected += 1
            state.metrics.frames.inc(outcome="rejected")
            raise ServiceError(422, f"frame: {exc}") from None
        finally:
            session.decoding_frame = False
        if session.closed:  # ended while the frame was decoded
            raise session_not_found(session.id)
        used = session.offer_frame(gray)
        state.metrics.frames.inc(outcome="used" if used else "ignored")
        height, width = gray.shape
        message = "frame received" + ("" if used else f" (ignored: model {runtime.model_name} reads no images)")
        await state.publish(session.id, status_event(session.id, "frame_received", message, used=used,
                                                     width=width, height=height), False)
        return FrameAck(used=used, width=width, height=height)

    # ---- WebSockets --------------------------------------------------------------------------------
    @app.websocket("/sessions/{session_id}/ingest")
    async def ingest_ws(websocket: WebSocket, session_id: str, token: str | None = Query(None)) -> None:
        state = state_of(websocket)
        try:
            session = await state.local_session(session_id, token, ROBOT_ONLY)
            state.require_runtime()
        except ServiceError as exc:
            await _refuse_ws(websocket, exc, robot=True)
            return
        await websocket.accept()
        try:
            while True:
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    return
                arrived = time.perf_counter_ns()
                if state.sessions.get(session_id) is not session:
                    await websocket.close(1000, "session ended")
                    return
                payload = message.get("bytes")
                binary = payload is not None
                if not binary:
                    payload = (message.get("text") or "").encode()
                try:
                    ack = _receive_block(state, session, payload, binary, arrived)
                except ServiceError as exc:
                    if exc.status == 429:
                        await websocket.close(WS_SATURATED, "session saturated; reconnect and resend")
                        return
                    await websocket.send_text(json.dumps({"seq": _peek_seq(payload, binary), "ok": False,
                                                          "error": exc.detail}))
                    continue
                await websocket.send_text(_OK_ACK % (ack["seq"], "true" if ack["duplicate"] else "false"))
        except WebSocketDisconnect:
            return

    @app.websocket("/sessions/{session_id}/events")
    async def events_ws(websocket: WebSocket, session_id: str, token: str | None = Query(None)) -> None:
        state = state_of(websocket)
        try:
            await state.authorized(session_id, token, OPERATOR_ONLY)
        except ServiceError as exc:
            await _refuse_ws(websocket, exc, robot=False)
            return
        await websocket.accept()
        subscription = await state.subscribe(session_id)
        try:
            try:
                await state.credentials(session_id)
            except ServiceError as exc:  # it ended while this socket was set up: its final event has passed
                gone = exc.status == 404
                await websocket.close(1000 if gone else 1011, "session ended" if gone else exc.detail[:120])
                return
            await websocket.send_text(encode(status_event(session_id, "subscribed", "receiving events",
                                                          instance=state.settings.instance_id)))
            forward = asyncio.create_task(_forward(websocket, subscription, state))
            listen = asyncio.create_task(_until_disconnect(websocket))
            done, pending = await asyncio.wait({forward, listen}, return_when=asyncio.FIRST_COMPLETED)
            for task in pending:
                task.cancel()
            for task in (forward, listen):  # collect every outcome: a send to a vanished client raises
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
            ended = forward in done and forward.exception() is None
            if ended and websocket.application_state == WebSocketState.CONNECTED:
                with contextlib.suppress(Exception):
                    await websocket.close(1000, "session ended")
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            await state.unsubscribe(subscription)

    # ---- service -----------------------------------------------------------------------------------
    @app.get("/library", response_model=LibraryOut, tags=["service"], responses=_errors(503),
             summary="The texture library: ids, names, groups, ratings")
    async def library(request: Request) -> LibraryOut:
        lib = state_of(request).require_runtime().library
        return LibraryOut(name=lib.name, entries=[
            LibraryEntryOut(id=e.id, name=e.name, group=e.group, ratings=e.to_json()["ratings"]) for e in lib.entries])

    @app.get("/health", response_model=HealthOut, tags=["service"], summary="Liveness")
    async def health() -> HealthOut:
        return HealthOut(status="ok", instance=settings.instance_id)

    @app.get("/ready", response_model=ReadyOut, tags=["service"],
             responses={503: {"model": ReadyOut, "description": "not ready; detail says why"}},
             summary="Readiness: model and library loaded, checked and warmed up")
    async def ready(request: Request) -> JSONResponse:
        state = state_of(request)
        ok, why = state.readiness()
        rt = state.runtime
        body = ReadyOut(ready=ok, detail=why)
        if rt is not None:
            body = ReadyOut(ready=ok, detail=why, model=rt.model_name, modality=rt.predictor.card.modality,
                            library=rt.library.name, library_entries=len(rt.library.ids),
                            backbone=rt.backbone.name if rt.backbone else None)
        return JSONResponse(body.model_dump(), status_code=200 if ok else 503)

    @app.get("/metrics", tags=["service"], response_class=PlainTextResponse,
             responses={200: {"content": {"text/plain": {"example": "hapticlink_windows_total 1234\n"}}}},
             summary="Prometheus metrics (text exposition)")
    async def metrics(request: Request) -> Response:
        return Response(state_of(request).metrics.render(), media_type=METRICS_CONTENT_TYPE)

    @app.get("/console", response_class=HTMLResponse, tags=["service"],
             summary="The operator console (open with ?session=…&token=<operator token>)")
    async def console_page() -> HTMLResponse:
        return HTMLResponse(console.page())

    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    return app


def server_options(settings: Settings, **overrides: Any) -> dict[str, Any]:
    """uvicorn options for `settings` (uvicorn.run / uvicorn.Config keywords): what `hapticlink serve`, the demo
    and the tests run with, so WebSocket messages get the same size limit as HTTP bodies everywhere."""
    options: dict[str, Any] = {
        "host": settings.host, "port": settings.port, "log_level": settings.log_level,
        "ws_max_size": settings.max_body_bytes, "timeout_graceful_shutdown": 5,
        "access_log": settings.log_level == "debug",  # access lines would carry the ?token= of WebSocket URLs
    }
    return {**options, **overrides}


# ---- helpers ---------------------------------------------------------------------------------------
def _media_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


def _receive_block(state: ServiceState, session, payload: bytes, binary: bool, arrived_ns: int) -> dict:
    """Decode and admit one block → its acknowledgement; ServiceError (400/422/429) otherwise. Counts outcomes."""
    try:
        block = _decode_block(payload, binary)
        ack = session.ingest(block, arrived_ns)
    except ServiceError as exc:
        if exc.status == 429:
            state.metrics.blocks.inc(outcome="refused")
        else:
            _count_rejected(state, session)
        raise
    state.metrics.blocks.inc(outcome="duplicate" if ack["duplicate"] else "accepted")
    return ack


def _count_rejected(state: ServiceState, session) -> None:
    state.metrics.blocks.inc(outcome="rejected")
    session.counters.blocks_rejected += 1


def _decode_block(payload: bytes, binary: bool) -> SampleBlock:
    """Wire bytes → SampleBlock; ServiceError 400 (not JSON) or 422 (not a valid block) with the decoder's message."""
    try:
        if binary:
            return decode_binary(payload)
        try:
            obj = json.loads(payload, parse_int=_json_int)
        except (ValueError, RecursionError) as exc:
            raise ServiceError(400, f"body is not valid JSON: {exc}") from None
        return decode_json(obj)
    except DECODE_ERRORS as exc:
        if isinstance(exc, ValueError):
            detail = str(exc)
        elif isinstance(exc, OverflowError):
            detail = f"a number in the block is out of range ({exc})"
        else:
            detail = f"invalid block ({type(exc).__name__}: {exc})"
        raise ServiceError(422, detail) from None


def _json_int(text: str) -> int | float:
    """JSON integers beyond float range become ±inf, so the validators name the field instead of overflowing."""
    value = int(text)
    if abs(value) > 2**1023:
        return float("inf") if value > 0 else float("-inf")
    return value


def _peek_seq(payload: bytes, binary: bool) -> int | None:
    """The seq a (possibly bad) block declares, so the robot can match the error to it; None if unreadable."""
    try:
        if binary:
            if payload[:4] != b"HLB1":
                return None
            n = int.from_bytes(payload[4:8], "little")
            header = json.loads(payload[8:8 + n])
        else:
            header = json.loads(payload)
        seq = header.get("seq") if isinstance(header, dict) else None
        return seq if isinstance(seq, int) and not isinstance(seq, bool) else None
    except (ValueError, RecursionError):
        return None


async def _refuse_ws(websocket: WebSocket, exc: ServiceError, *, robot: bool) -> None:
    """Refuse a WebSocket: unknown session → HTTP 404 at the handshake, lost session → HTTP 410; the robot's
    ingest socket closes 1008 on an auth failure (the contract), 4421 when misdirected, 1013 when not ready;
    events answer the handshake with the HTTP status."""
    if robot and exc.status not in (404, 410):
        code = {401: 1008, 403: 1008, 421: WS_MISDIRECTED}.get(exc.status, WS_TRY_AGAIN)
        await websocket.accept()
        await websocket.close(code, exc.detail[:120])
        return
    try:
        await websocket.send_denial_response(JSONResponse({"detail": exc.detail}, status_code=exc.status))
    except RuntimeError:  # the server cannot send HTTP denials: a close before accept becomes 403
        await websocket.close(1008)


async def _forward(websocket: WebSocket, subscription, state: ServiceState) -> None:
    """Send events until the subscription ends (session ended); counts events dropped for this slow connection."""
    reported = 0
    while True:
        text = await subscription.get()
        if subscription.dropped > reported:
            state.metrics.events_dropped.inc(subscription.dropped - reported)
            reported = subscription.dropped
        if text is None:
            return
        await websocket.send_text(text)


async def _until_disconnect(websocket: WebSocket) -> None:
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return


def _openapi(app: FastAPI) -> dict:
    """FastAPI's schema plus the JSON block models the raw request bodies refer to."""
    if app.openapi_schema is None:
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        block = JsonBlock.model_json_schema(ref_template="#/components/schemas/{model}")
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        components.update(block.pop("$defs", {}))
        components["JsonBlock"] = block
        body = schema["paths"]["/sessions/{session_id}/blocks"]["post"]["requestBody"]["content"]["application/json"]
        body["schema"] = {"$ref": "#/components/schemas/JsonBlock"}
        body["example"] = JsonBlock.model_config["json_schema_extra"]["examples"][0]  # type: ignore[index]
        app.openapi_schema = schema
    return app.openapi_schema
