"""FastAPI dependencies: the service state, the runtime once ready, and the session a request's token opens.

Routes declare what they need (`state: State`, `session: RobotSession`, …) and never repeat the
lookup or the authorisation inline. A dependency that does no blocking work is `async def`: FastAPI runs
a plain `def` one in anyio's thread pool, where under load it queues behind every other request's
(a hop to another thread and back, and the GIL, for an attribute read). `fleet_member` stays plain:
it may re-read the API key file. WebSocket routes use `socket_session`, which refuses the
handshake the protocol's way (`drivers.protocol.Close`) instead of raising.
"""

from __future__ import annotations

import hmac
from collections.abc import Callable
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.requests import HTTPConnection
from starlette.websockets import WebSocket

from drivers.protocol import HANDSHAKE_REFUSALS, Close
from service.auth import EITHER, OPERATOR_ONLY, ROBOT_ONLY, Role, digest
from service.errors import ErrorResponse, ServiceError
from service.events import status_event
from service.fleet import NOT_CONFIGURED
from service.live_session import Session
from service.log_throttle import REFUSING_SOCKET
from service.runtime import Runtime
from service.state import ServiceState


async def get_state(connection: HTTPConnection) -> ServiceState:
    return connection.app.state.service


State = Annotated[ServiceState, Depends(get_state)]


async def get_runtime(state: State) -> Runtime:
    """The runtime, or 503 (Retry-After) until the model and library are loaded and warmed up."""
    return state.require_runtime()


ReadyRuntime = Annotated[Runtime, Depends(get_runtime)]

_bearer = HTTPBearer(
    auto_error=False, description="a session's robot or operator token, or (POST /sessions) a fleet API key"
)


async def bearer_token(credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> str | None:
    """The request's bearer token (absence is answered 401 by whoever needs one)."""
    return credentials.credentials if credentials is not None else None


Token = Annotated[str | None, Depends(bearer_token)]


async def robot_session(session_id: str, state: State, token: Token) -> Session:
    session = await state.directory.local(session_id, token, ROBOT_ONLY)
    state.require_open()  # a block or frame taken now could not be estimated: the robot keeps it for its next session
    return session


async def operator_session(session_id: str, state: State, token: Token) -> Session:
    return await state.directory.local(session_id, token, OPERATOR_ONLY)


async def any_session(session_id: str, state: State, token: Token) -> Session:
    return await state.directory.local(session_id, token, EITHER)


RobotSession = Annotated[Session, Depends(robot_session)]
OperatorSession = Annotated[Session, Depends(operator_session)]
EitherSession = Annotated[Session, Depends(any_session)]


def client_of(connection: HTTPConnection) -> str:
    """The client's address (behind nginx, the proxy's: uvicorn's proxy_headers rewrites it from X-Forwarded-For)."""
    return connection.client.host if connection.client else "unknown"


def fleet_member(request: Request, state: State, token: Token) -> str:
    """A valid fleet API key → the client's address. Checked before the request's body is read: a client without
    a key costs its headers alone.

    503 when no key is configured (the endpoint is closed, and says how to open it), 401 for a missing or
    unknown key."""
    client = client_of(request)
    if not state.api_keys.configured:
        raise ServiceError(503, NOT_CONFIGURED)
    if not state.api_keys.check(token):
        state.metrics.sessions_refused.labels(reason="api_key").inc()
        state.refusal_log.warning(
            ("api_key", token is None),
            "POST /sessions from %s refused: %s API key",
            client,
            "no" if token is None else "an unknown",
        )
        raise ServiceError(
            401,
            "a fleet API key is required: send 'Authorization: Bearer <key>' (HAPTICLINK_API_KEY for the robot client)"
            if token is None
            else "the API key is not valid",
            {"WWW-Authenticate": "Bearer"},
        )
    return client


METRICS_CLOSED = (
    "GET /metrics is closed: no metrics token is configured; set HAPTICLINK_METRICS_TOKEN and have the scraper "
    "send 'Authorization: Bearer <token>'"
)


async def metrics_reader(state: State, token: Token) -> None:
    """The scraper's token, or 401 (none, or another); 403 when no token is configured: no credential opens it."""
    configured = state.settings.metrics_token
    if configured is None:
        raise ServiceError(403, METRICS_CLOSED)
    if token is None:
        raise ServiceError(
            401,
            "a metrics token is required: send 'Authorization: Bearer <token>' (HAPTICLINK_METRICS_TOKEN)",
            {"WWW-Authenticate": "Bearer"},
        )
    # digests of equal length: compare_digest's time then says nothing of the token's length either
    if not hmac.compare_digest(digest(token), digest(configured.get_secret_value())):
        raise ServiceError(401, "the metrics token is not valid", {"WWW-Authenticate": "Bearer"})


def take_session_slot(state: ServiceState, client: str) -> None:
    """One session from `client`'s session-creation rate; 429 + Retry-After past it (refund it with
    state.session_limiter.refund when no session is opened after all)."""
    wait = state.session_limiter.take(client)
    if wait > 0:
        state.metrics.sessions_refused.labels(reason="rate").inc()
        raise ServiceError(
            429,
            f"too many sessions opened from {client}; at most {state.settings.session_rate_per_s:g}/s "
            f"after a burst of {state.settings.session_burst}",
            {"Retry-After": f"{max(1, round(wait))}"},
        )


FleetClient = Annotated[str, Depends(fleet_member)]
MetricsReader = Depends(metrics_reader)


async def socket_session(
    websocket: WebSocket,
    session_id: str,
    token: str | None,
    roles: frozenset[Role],
    check: Callable[[], None] | None = None,
) -> Session | None:
    """The session a WebSocket's ?token= opens (None for an operator whose session runs on another replica);
    raises Refused after refusing the handshake (one WARNING line):

    unknown session → HTTP 404 at the handshake, lost session (its replica is gone) → HTTP 410, a robot whose
    session the replica sheds → HTTP 429 with Retry-After; the robot's
    ingest socket closes 1008 on an auth failure, 4421 when misdirected, 1013 when not ready; the events socket
    answers the handshake with the HTTP status.
    The operator's events socket may attach on any replica (its session may run elsewhere), hence `local`.
    check: the route's own check (ServiceError), once the token is accepted, refused in the same way."""
    state: ServiceState = websocket.app.state.service
    robot = roles == ROBOT_ONLY
    try:
        if robot:
            local = await state.directory.local(session_id, token, roles)
            state.require_open()
            state.require_runtime()
            # a shed session's robot reconnecting, or one refused a start: held in line before the upgrade (its
            # token accepted first) and let in the moment its turn comes, or refused with Retry-After
            await state.capacity.hold(local, state.settings.readmit_hold_s)
            state.require_open()  # it may have begun to shut down meanwhile
            return local
        if roles == OPERATOR_ONLY and state.api_keys.check(token):
            # a fleet key follows any session of the fleet (an operator following a robot across its sessions)
            _, session = await state.directory.credentials(session_id)
        else:
            _, session = await state.directory.authorized(session_id, token, roles)
        if check is not None:
            check()
        return session
    except ServiceError as exc:
        state.refusal_log.warning(
            ("socket", robot, exc.status),
            "%s socket for session %r from %s refused: %d %s",
            "ingest" if robot else "events",
            session_id,
            client_of(websocket),
            exc.status,
            exc.detail,
        )
        if robot:
            state.metrics.sockets_refused.labels(status=str(exc.status)).inc()
            known = state.sessions.get(session_id)
            # someone tried this session's ingest: say so, at most once every 10 s (anyone who knows the id can try)
            if (
                known is not None
                and exc.status in (401, 403)
                and (left_out := known.notices.admit("refused")) is not None
            ):
                more = f" (and {left_out} more since the last such event)" if left_out else ""
                await state.bus.publish(
                    session_id,
                    status_event(session_id, "robot_refused", f"an ingest connection was refused: {exc.detail}{more}"),
                    False,
                )
        await refuse(websocket, exc, robot=robot)
        raise Refused() from None


class Refused(Exception):
    """The WebSocket handshake was refused (and already answered): the route just returns."""


async def refuse(websocket: WebSocket, exc: ServiceError, *, robot: bool) -> None:
    if robot and exc.status not in HANDSHAKE_REFUSALS:
        code = {401: Close.POLICY, 403: Close.POLICY, 421: Close.MISDIRECTED}.get(exc.status, Close.NOT_READY)
        refusing = REFUSING_SOCKET.set(True)  # uvicorn's lines for this acceptance are throttled
        try:
            await websocket.accept()
        finally:
            REFUSING_SOCKET.reset(refusing)
        await websocket.close(int(code), exc.detail[:120])
        return
    try:
        await websocket.send_denial_response(
            ErrorResponse({"detail": exc.detail}, status_code=exc.status, headers=exc.headers)
        )
    except RuntimeError:  # the server cannot send HTTP denials: a close before accept becomes 403
        await websocket.close(int(Close.POLICY))
