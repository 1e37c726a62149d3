"""The operators' event socket: `WS /sessions/{id}/events?token=<operator token>` (any replica, via the broker).

`?view=render` gives a renderer the lean feed instead (drivers/render_feed.py: the chosen entry, its model
version and the ratings; nothing else). `?models=push` (the render view's default; `fetch` for the full view)
sends each chosen model the connection does not hold just before the choice that names it, as a delta when it
holds an earlier version of the same id (service/model_push.py); `?library=<digest>` says it holds the whole
library, and hold messages from the operator say what else it holds."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re

from fastapi import APIRouter, Query, WebSocket
from starlette.websockets import WebSocketDisconnect, WebSocketState

from drivers import render_feed
from drivers.protocol import SESSION_LOST, Close
from drivers.render_feed import RenderView
from service.auth import OPERATOR_ONLY
from service.bus import ROBOT_ROOM
from service.deps import Refused, refuse, socket_session
from service.errors import ServiceError
from service.events import encode, status_event
from service.model_push import ModelPush
from service.render_models import ServedRenderModel
from service.schemas import ROBOT_ID_PATTERN
from service.state import ServiceState
from service.surface_models import SESSION_PREFIX

router = APIRouter()
#: the feeds an operator may ask for (?view=)
VIEWS = ("full", "render")
#: how models reach the operator (?models=): pushed on this socket, or fetched by the operator (GET …/model)
MODES = ("push", "fetch")
LIBRARY_DIGEST = re.compile(r"[0-9a-f]{16}")


@router.websocket("/sessions/{session_id}/events")
async def events_socket(
    websocket: WebSocket,
    session_id: str,
    token: str | None = Query(None),
    view: str = Query("full"),
    models: str | None = Query(None),
    library: str | None = Query(None),
) -> None:
    state: ServiceState = websocket.app.state.service

    def admissible() -> None:  # the view is checked here, not by FastAPI: its refusal is a bare 403 that says nothing
        _check_feed(view, models, library)
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
        push = await _push(websocket, state, session_id, view, models, library)
        forward = asyncio.create_task(_forward(websocket, subscription, state, lean, push))
        listen = asyncio.create_task(_listen(websocket, state, session_id, push))
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
    models: str | None = Query(None),
    library: str | None = Query(None),
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
        _check_feed(view, models, library)
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
        push = await _push(websocket, state, None, view, models, library)
        forward = asyncio.create_task(_forward(websocket, subscription, state, lean, push))
        listen = asyncio.create_task(_listen(websocket, state, "", push))
        await asyncio.wait({forward, listen}, return_when=asyncio.FIRST_COMPLETED)
        for task in (forward, listen):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        await state.bus.unsubscribe(subscription)


def _check_feed(view: str, models: str | None, library: str | None) -> None:
    """The feed's query: a view, a way models travel, a library digest (16 hex digits, with models pushed)."""
    if view not in VIEWS:
        raise ServiceError(422, f"view must be one of {', '.join(VIEWS)}, got {view[:40]!r}")
    if models is not None and models not in MODES:
        raise ServiceError(422, f"models must be one of {', '.join(MODES)}, got {models[:40]!r}")
    if library is not None:
        if (models or _default_mode(view)) != "push":
            raise ServiceError(422, "library= says what a connection holds of pushed models: it needs models=push")
        if not LIBRARY_DIGEST.fullmatch(library):
            raise ServiceError(422, f"library must be a library digest (16 hex digits), got {library[:40]!r}")


def _default_mode(view: str) -> str:
    return "push" if view == "render" else "fetch"


async def _push(
    websocket: WebSocket,
    state: ServiceState,
    session_id: str | None,
    view: str,
    models: str | None,
    library: str | None,
) -> ModelPush | None:
    """This connection's ModelPush (None: models are fetched), holding the library its digest names."""
    runtime = state.runtime
    if (models or _default_mode(view)) != "push" or runtime is None:
        return None

    def resolve(chosen: str, version: str | None) -> ServedRenderModel | None:
        if chosen.startswith(SESSION_PREFIX):  # a learnt model: only where its session runs (else it is fetched)
            live = state.directory.sessions.get(chosen.removeprefix(SESSION_PREFIX))
            surface = None if live is None else live.surface
            if surface is None:
                return None
            return surface.served if version is None else surface.recent.get(version)
        entry = runtime.render_models.models.get(chosen)
        return entry if entry is not None and version in (None, entry.version) else None

    push = ModelPush(resolve, runtime.render_models, session_id)
    if library is not None and (why := push.hold_library(library)) is not None:
        await websocket.send_text(encode(status_event(session_id or "", "refused", why)))
    return push


async def _forward(
    websocket: WebSocket, subscription, state: ServiceState, lean: RenderView | None, push: ModelPush | None
) -> None:
    """Send events (or, with `lean`, the render feed made of them) until the subscription ends (session ended);
    counts events dropped for this slow connection. With `push`, a choice's model goes just before it."""
    reported = 0
    while True:
        text = await subscription.get()
        if subscription.dropped > reported:
            state.metrics.events_dropped.inc(subscription.dropped - reported)
            reported = subscription.dropped
        if text is None:
            return
        message: str | bytes | None = text if lean is None else lean.render(text)
        if message is None:
            continue
        if push is not None and (choice := _choice(message)) is not None:
            prior = lean.library_pick if lean is not None else json.loads(text).get("library_pick")
            model = push.bring(*choice, prior=prior)
            if model is not None:
                await websocket.send_bytes(model)
        if isinstance(message, bytes):
            await websocket.send_bytes(message)
        else:
            await websocket.send_text(message)


def _choice(message: str | bytes) -> tuple[str, str | None] | None:
    """(chosen, version) of a choice (lean) or window event (full), else None."""
    if isinstance(message, bytes):
        if message[:1] != render_feed.CHOICE_TAG:
            return None
    elif not message.startswith('{"type":"window"'):
        return None
    msg = render_feed.parse(message)
    return None if msg.kind != "choice" or msg.chosen is None else (msg.chosen, msg.version)


async def _listen(websocket: WebSocket, state: ServiceState, session_id: str, push: ModelPush | None) -> None:
    """Until the operator disconnects: its hold messages (with models pushed), each answered at once (a model it
    lacks, or a refusal naming why); anything else it sends is ignored without models pushed."""
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return
        if push is None:
            continue
        text, data = message.get("text"), message.get("bytes")
        data = text if text is not None else (data or b"")
        models, why = push.take_hold(data)
        for model in models:
            await websocket.send_bytes(model)
        if why is not None:
            state.refusal_log.warning(("hold", session_id[:8]), "events socket %s: %s", session_id[:8], why[:200])
            await websocket.send_text(encode(status_event(session_id, "refused", why)))
        if push.exhausted:
            await websocket.close(int(Close.POLICY), "too many refused hold messages")
            return
