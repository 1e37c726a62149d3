"""Sessions: open (fleet API key, rate-limited per client), read the status (operator), end (either token); a
robot's newest session by its own id (fleet API key)."""

from __future__ import annotations

import json
import re

from fastapi import APIRouter, Request
from pydantic import ValidationError

from service.deps import EitherSession, FleetClient, OperatorSession, State, take_session_slot
from service.errors import ServiceError, invalid_fields, not_json
from service.limits import limit_body
from service.routes.common import errors, media_type, try_later
from service.schemas import (
    MAX_SESSION_REQUEST_BYTES,
    ROBOT_ID_PATTERN,
    SESSION_REQUEST_BODY,
    RobotSession,
    SessionCreate,
    SessionCreated,
    SessionStatus,
)

router = APIRouter(tags=["sessions"])


@router.post(
    "/sessions",
    status_code=201,
    response_model=SessionCreated,
    openapi_extra={"requestBody": SESSION_REQUEST_BODY},
    responses={
        **errors(400, 401, 413, 415, 422, 503),
        **try_later("too many sessions opened by this client; retry after Retry-After s"),
    },
    summary="Open a session (fleet API key)",
)
async def create_session(request: Request, state: State, client: FleetClient) -> SessionCreated:
    # The key is checked (FleetClient) before the body is read, the body is read and checked before the client's
    # session rate is spent: a refused request opens nothing, so it costs the rate nothing either.
    body = await session_request(request)
    take_session_slot(state, client)
    try:
        session, robot, operator = await state.create_session(
            body.name if body else None,
            client,
            robot=body.robot if body else None,
            first_seq=body.first_seq if body else 0,
        )
    except ServiceError:  # refused (not ready, full, at capacity): no session opened, so none counts against the rate
        state.session_limiter.refund(client)
        raise
    return SessionCreated(session_id=session.id, robot_token=robot, operator_token=operator)


async def session_request(request: Request) -> SessionCreate | None:
    """The body of POST /sessions: None when empty (or JSON null); 413 past MAX_SESSION_REQUEST_BYTES (a declared
    length before reading, else as it streams in: service.limits.limit_body), 415 for a body that is not
    application/json, 400 for one that is not JSON Python can read, 422 naming the field."""
    limit_body(
        request,
        MAX_SESSION_REQUEST_BYTES,
        f"a session request holds at most {MAX_SESSION_REQUEST_BYTES} bytes (a name)",
    )
    raw = await request.body()
    if not raw:
        return None
    kind = media_type(request)
    if kind != "application/json":
        raise ServiceError(415, f"a session request is application/json, got {kind or 'no Content-Type'}")
    try:
        obj = json.loads(raw)
    except (ValueError, RecursionError) as exc:  # its syntax, bytes not UTF-8, a huge integer, nesting too deep
        raise not_json(exc) from None
    if obj is None:
        return None
    try:
        return SessionCreate.model_validate(obj)
    except ValidationError as exc:
        raise invalid_fields(exc.errors(), under=("body",)) from None


@router.get(
    "/robots/{robot}/session",
    response_model=RobotSession,
    responses=errors(401, 404, 422, 503),
    summary="A robot's newest session, by the robot's own id (fleet API key): operators follow the robot across its "
    "sessions, a restart of the service included",
)
async def robot_session(state: State, _: FleetClient, robot: str) -> RobotSession:
    # the robot id is checked after the key (the credential first), by hand: FastAPI would check it before
    if not re.fullmatch(ROBOT_ID_PATTERN, robot):
        raise ServiceError(422, "path.robot: a robot id is 1–64 letters, digits, '_', '-', '.' or ':'")
    session_id, lost = await state.directory.robot_session(robot)
    return RobotSession(robot=robot, session_id=session_id, lost=lost)


@router.get(
    "/sessions/{session_id}",
    response_model=SessionStatus,
    responses=errors(401, 403, 404, 410, 421, 503),
    summary="A session's status and counters (operator token)",
)
async def get_session(session: OperatorSession) -> dict:
    return session.status()


@router.delete(
    "/sessions/{session_id}",
    response_model=SessionStatus,
    responses=errors(401, 403, 404, 410, 421, 503),
    summary="End a session (robot or operator token)",
)
async def delete_session(state: State, session: EitherSession) -> dict:
    return await state.directory.end(session.id, "ended by request")
