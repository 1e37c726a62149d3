"""Sessions: open (fleet API key, rate-limited per client), read the status (operator), end (either token)."""

from __future__ import annotations

from fastapi import APIRouter

from service.deps import EitherSession, FleetClient, OperatorSession, State
from service.errors import ServiceError
from service.routes.common import errors, try_later
from service.schemas import SessionCreate, SessionCreated, SessionStatus

router = APIRouter(tags=["sessions"])


@router.post(
    "/sessions",
    status_code=201,
    response_model=SessionCreated,
    responses={
        **errors(400, 401, 422, 503),
        **try_later("too many sessions opened by this client; retry after Retry-After s"),
    },
    summary="Open a session (fleet API key)",
)
async def create_session(state: State, client: FleetClient, body: SessionCreate | None = None) -> SessionCreated:
    try:
        session, robot, operator = await state.create_session(body.name if body else None, client)
    except ServiceError:  # refused (not ready, full, at capacity): no session opened, so none counts against the rate
        state.session_limiter.refund(client)
        raise
    return SessionCreated(session_id=session.id, robot_token=robot, operator_token=operator)


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
