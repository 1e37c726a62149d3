"""The operators' event socket: `WS /sessions/{id}/events?token=<operator token>` (any replica, via the broker).

`?view=render` gives a renderer the lean feed instead (drivers/render_feed.py: the chosen entry, its model
version and the ratings; nothing else)."""

from __future__ import annotations

import asyncio
import contextlib
import re

from fastapi import APIRouter, Query, WebSocket
from starlette.websockets import WebSocketDisconnect, WebSocketState

from drivers.protocol import SESSION_LOST, Close
from drivers.render_feed import RenderView
from service.auth import OPERATOR_ONLY
from service.bus import ROBOT_ROOM
from service.deps import Refused, refuse, socket_session
from service.errors import ServiceError
from service.events import encode, status_event
from service.schemas import ROBOT_ID_PATTERN
from service.state import ServiceState

router = APIRouter()
#: the feeds an operator may ask for (?view=)
VIEWS = ("full", "render")


@router.websocket("/sessions/{session_id}/events")
async def events_socket(
    websocket: WebSocket,
    session_id: str,
    token: str | None = Query(None),
    view: str = Query("full"),
) -> None:
    state: ServiceState = websocket.app.state.service

    def admissible() -> None:  # the view is checked here, not by FastAPI: its refusal is a bare 403 that says nothing
        if view not in VIEWS:
            raise ServiceError(422, f"view must be one of {', '.join(VIEWS)}, got {view[:40]!r}")
        state.bus.require_room(session_id)

    try:
        await socket_session(websocket, session_id, token, OPERATOR_ONLY, check=admissible)
    except Refused:
        return
    await websocket.accept()
    try:
        subscription = await state.bus.subscribe(session_id)
    except ServiceError as exc:  # others took the room while this one's handshake was answered
        await websocket.close(int(Close.SATURATED), exc.detail[:120])
        return
    try:
        try:
            await state.directory.credentials(session_id)
        except ServiceError as exc:  # it ended (or was lost) while this socket was set up: its final event has passed
            gone = exc.status in (404, SESSION_LOST)
            await websocket.close(
                int(Close.SESSION_ENDED if gone else Close.SERVER_ERROR),
                "session ended" if exc.status == 404 else exc.detail[:120],
            )
            return
        await websocket.send_text(
            encode(status_event(session_id, "subscribed", "receiving events", instance=state.settings.instance_id))
        )
        lean = RenderView() if view == "render" else None
        forward = asyncio.create_task(_forward(websocket, subscription, state, lean))
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
                await websocket.close(int(Close.SESSION_ENDED), "session ended")
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        await state.bus.unsubscribe(subscription)


@router.websocket("/robots/{robot}/events")
async def robot_events_socket(
    websocket: WebSocket,
    robot: str,
    token: str | None = Query(None),
    view: str = Query("full"),
) -> None:
    """Every event of a robot's sessions, one session after another — across restarts of the service, replicas lost
    and the robot's new sessions — for whoever holds the fleet API key (?token=): operators follow a robot, never a
    session id that dies with a process. A session's `session_ended` passes through; the feed goes on."""
    state: ServiceState = websocket.app.state.service
    room = ROBOT_ROOM + robot
    try:
        if token is None or not state.api_keys.check(token):  # the credential first
            raise ServiceError(401, "a fleet API key is required (?token=)", {"WWW-Authenticate": "Bearer"})
        if not re.fullmatch(ROBOT_ID_PATTERN, robot):
            raise ServiceError(422, "a robot id is 1–64 letters, digits, '_', '-', '.' or ':'")
        if view not in VIEWS:
            raise ServiceError(422, f"view must be one of {', '.join(VIEWS)}, got {view[:40]!r}")
        state.bus.require_room(room)
    except ServiceError as exc:
        state.refusal_log.warning(
            ("robot-events", exc.status),
            "events socket for robot %r refused: %d %s",
            robot[:64],
            exc.status,
            exc.detail,
        )
        await refuse(websocket, exc, robot=False)
        return
    await websocket.accept()
    try:
        subscription = await state.bus.subscribe(room)
    except ServiceError as exc:
        await websocket.close(int(Close.SATURATED), exc.detail[:120])
        return
    try:
        await websocket.send_text(
            encode(status_event("", "subscribed", f"following robot {robot}", instance=state.settings.instance_id))
        )
        lean = RenderView() if view == "render" else None
        forward = asyncio.create_task(_forward(websocket, subscription, state, lean))
        listen = asyncio.create_task(_until_disconnect(websocket))
        await asyncio.wait({forward, listen}, return_when=asyncio.FIRST_COMPLETED)
        for task in (forward, listen):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        await state.bus.unsubscribe(subscription)


async def _forward(websocket: WebSocket, subscription, state: ServiceState, lean: RenderView | None) -> None:
    """Send events (or, with `lean`, the render feed made of them) until the subscription ends (session ended);
    counts events dropped for this slow connection."""
    reported = 0
    while True:
        text = await subscription.get()
        if subscription.dropped > reported:
            state.metrics.events_dropped.inc(subscription.dropped - reported)
            reported = subscription.dropped
        if text is None:
            return
        if lean is None:
            await websocket.send_text(text)
            continue
        message = lean.render(text)
        if isinstance(message, bytes):
            await websocket.send_bytes(message)
        elif message is not None:
            await websocket.send_text(message)


async def _until_disconnect(websocket: WebSocket) -> None:
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return
