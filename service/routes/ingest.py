"""What robots send: sample blocks (HTTP POST or the ingest WebSocket), camera frames (HTTP POST) and scene checks
(HTTP POST: a frame's thumbnail in place of a refresh frame)."""

from __future__ import annotations

import asyncio
import logging
import time

from fastapi import APIRouter, Query, Request, WebSocket
from starlette.websockets import WebSocketDisconnect, WebSocketState

from drivers.camera import sniff_content_type
from drivers.protocol import (
    BINARY_CONTENT_TYPE,
    FRAME_CONTENT_TYPES,
    SCENE_CONTENT_TYPE,
    SESSION_LOST,
    Close,
    ack_error,
    ack_ok,
    peek_seq,
)
from drivers.scene_change import THUMBNAIL_BYTES, check_thumbnail_length
from service.auth import ROBOT_ONLY
from service.capacity import AtCapacity
from service.deps import ReadyRuntime, Refused, RobotSession, State, socket_session
from service.errors import ServiceError
from service.limits import limit_body
from service.routes.common import errors, media_type, try_later
from service.schemas import BLOCK_REQUEST_BODY, FRAME_REQUEST_BODY, SCENE_REQUEST_BODY, BlockAck, FrameAck, SceneCheck
from service.state import ServiceState

router = APIRouter(tags=["ingest"])
log = logging.getLogger("service.access")


@router.post(
    "/sessions/{session_id}/blocks",
    status_code=202,
    response_model=BlockAck,
    openapi_extra={"requestBody": BLOCK_REQUEST_BODY},
    responses={
        **errors(400, 401, 403, 404, 410, 413, 415, 421, 422, 503),
        **try_later("the session is saturated; resend after Retry-After s"),
    },
    summary="Send one block: samples or taps (robot token)",
)
async def post_block(request: Request, state: State, session: RobotSession, runtime: ReadyRuntime) -> dict:
    kind = media_type(request)
    if kind not in ("application/json", BINARY_CONTENT_TYPE):
        state.blocks.rejected(session)
        raise ServiceError(
            415, f"blocks are application/json or {BINARY_CONTENT_TYPE}, got {kind or 'no Content-Type'}"
        )
    # refused for capacity: held in line, its body unread, until its turn comes (or 429 with Retry-After); its own
    # windows' backlog full: held until the pool drains it (or 429)
    await state.blocks.hold(session, state.settings.readmit_hold_s)
    await session.wait_for_room(state.settings.readmit_hold_s)
    state.require_open()
    payload = await request.body()
    return state.blocks.receive(session, payload, kind == BINARY_CONTENT_TYPE, time.perf_counter_ns())


@router.post(
    "/sessions/{session_id}/frames",
    status_code=202,
    response_model=FrameAck,
    openapi_extra={"requestBody": FRAME_REQUEST_BODY},
    responses={
        **errors(401, 403, 404, 410, 413, 415, 421, 422, 503),
        **try_later(
            "the visual queue is full, or this session's previous frame is still being decoded; "
            "send the newest frame after Retry-After s"
        ),
    },
    summary="Send one camera frame (robot token)",
)
async def post_frame(request: Request, state: State, session: RobotSession, runtime: ReadyRuntime) -> FrameAck:
    kind = media_type(request)
    if kind not in FRAME_CONTENT_TYPES:
        state.frames.rejected(session)
        raise ServiceError(415, f"frames are {' or '.join(FRAME_CONTENT_TYPES)}, got {kind or 'no Content-Type'}")
    image = await request.body()
    # A label that lies is the client's bug, refused before anything is decoded; bytes that are neither format
    # are left to the decoder, which says what they are (422).
    sniffed = sniff_content_type(image)
    if sniffed is not None and sniffed != kind:
        state.frames.rejected(session)
        what = sniffed.removeprefix("image/").upper()
        raise ServiceError(415, f"the frame is declared {kind}, but the bytes are a {what} ({sniffed})")
    return await state.frames.receive(session, runtime, image)


@router.post(
    "/sessions/{session_id}/scene",
    response_model=SceneCheck,
    openapi_extra={"requestBody": SCENE_REQUEST_BODY},
    responses=errors(401, 403, 404, 410, 413, 415, 421, 422, 503),
    summary="Check the scene instead of sending a refresh frame: does the session want the frame? (robot token)",
)
async def post_scene(request: Request, state: State, session: RobotSession, runtime: ReadyRuntime) -> SceneCheck:
    kind = media_type(request)
    if kind != SCENE_CONTENT_TYPE:
        raise ServiceError(415, f"a scene check is {SCENE_CONTENT_TYPE}, got {kind or 'no Content-Type'}")
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit():  # refused before the body is read
        try:
            check_thumbnail_length(int(declared))
        except ValueError as exc:
            raise ServiceError(422, f"scene check: {exc}") from None
    # a body of undeclared length is cut where a thumbnail ends, not at the service's 8 MiB
    limit_body(request, THUMBNAIL_BYTES, f"scene check: a scene thumbnail is {THUMBNAIL_BYTES} bytes")
    return state.frames.check_scene(session, await request.body())


@router.websocket("/sessions/{session_id}/ingest")
async def ingest_socket(websocket: WebSocket, session_id: str, token: str | None = Query(None)) -> None:
    state: ServiceState = websocket.app.state.service
    try:
        session = await socket_session(websocket, session_id, token, ROBOT_ONLY)
    except Refused:
        return
    assert session is not None
    await websocket.accept()
    if state.sessions.get(session_id) is not session:  # it ended during the handshake: not kept for no one
        await _close_gone(websocket, state, session_id)
        return
    state.directory.attach_ingest(session_id, websocket)  # sync: nothing can end the session between check and attach
    why = "disconnected"
    try:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                return
            if websocket.application_state is WebSocketState.DISCONNECTED:  # closed by the directory
                why = getattr(websocket.state, "closed_why", why)  # its session ended, or a newer socket replaced it
                return
            arrived = time.perf_counter_ns()
            if session.saturated():
                # its own windows' backlog is full: the robot keeps its connection and this block waits for the pool
                # to drain it (no further message is read meanwhile), instead of a close, a reconnect and a resend
                await session.wait_for_room(state.settings.readmit_hold_s)
                if websocket.application_state is WebSocketState.DISCONNECTED:  # replaced, or its session ended
                    why = getattr(websocket.state, "closed_why", why)
                    return
            if state.shutting_down:  # not taken: the robot reconnects and resends it to its next session
                why = "shutting down"
                await websocket.close(int(Close.NOT_READY), "replica shutting down; reconnect and resend")
                return
            if state.sessions.get(session_id) is not session:
                why = await _close_gone(websocket, state, session_id)
                return
            data: bytes | None = message.get("bytes")
            binary = data is not None
            payload = data if data is not None else (message.get("text") or "").encode()
            try:
                ack = state.blocks.receive(session, payload, binary, arrived)
            except ServiceError as exc:
                if exc.status == 429:
                    why = "saturated"
                    if isinstance(exc, AtCapacity):
                        reason = f"replica at capacity; reconnect after Retry-After {exc.retry_after_s:g} s and resend"
                    elif waiting := session.waiting_for():  # a few words: they fit a close reason
                        reason = f"session saturated: {waiting}"
                    else:
                        reason = "session saturated; reconnect and resend"
                    await websocket.close(int(Close.SATURATED), reason)
                    return
                if not await _answer(websocket, ack_error(peek_seq(payload, binary), exc.detail)):
                    return
                continue
            if not await _answer(websocket, ack_ok(ack["seq"], ack["duplicate"])):
                return
            # A robot's blocks queue up in its socket (a backlog resent at once, or a stall's worth): receiving
            # them does not suspend, so without this one socket would hold the loop for all of them, and the
            # capacity guard, /health and every other robot would wait.
            await asyncio.sleep(0)
    except WebSocketDisconnect:
        return
    finally:
        state.directory.detach_ingest(session_id, websocket)
        await state.directory.robot_disconnected(session, why)


async def _answer(websocket: WebSocket, text: str) -> bool:
    """Send an acknowledgement; False when the connection closed while it waited for a client that stopped reading
    (uvicorn's keepalive timeout, or the directory's close): a disconnect, not an error."""
    try:
        await websocket.send_text(text)
    except (RuntimeError, OSError):  # starlette/uvicorn: a send after the close (uvicorn's ClientDisconnected: OSError)
        return False
    return True


async def _close_gone(websocket: WebSocket, state: ServiceState, session_id: str) -> str:
    """Close the ingest socket of a session no longer here → why, for the log: lost (4410 and the reason: this replica
    was silent too long and another one marked it lost) or ended (1000)."""
    code, reason = Close.SESSION_ENDED, "session ended"
    try:
        await state.directory.credentials(session_id)
    except ServiceError as exc:
        if exc.status == SESSION_LOST:
            code, reason = Close.LOST, exc.detail[:120]
    if websocket.application_state is not WebSocketState.DISCONNECTED:  # the directory may have closed it
        await websocket.close(int(code), reason)
    return "session lost" if code == Close.LOST else "session ended"
