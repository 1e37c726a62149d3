"""What the robot client raises when the service refuses it for good (retrying cannot help)."""

from __future__ import annotations


class ServiceRefused(RuntimeError):
    """The service refused the client in a way retrying cannot fix (unknown session, bad request, no API key).

    (The service's own `service.errors.ServiceError` is the refusal it sends; this is the client's view of
    a final one.)"""


class RobotAuthError(ServiceRefused, PermissionError):
    """The robot token or the fleet API key was refused (HTTP 401/403, WebSocket close 1008)."""


class ServiceUnavailable(ServiceRefused):
    """The service stayed unreachable or not ready (HTTP 503) for longer than the client was told to wait."""


class SessionGone(ServiceRefused):
    """The session is gone: lost (410, close 4410) or no longer known to the service (404: a restarted service
    that keeps nothing). Retrying cannot bring it back; a client with the fleet API key opens a new session and
    resends what was never acknowledged (RobotClient does)."""


class SessionLostError(SessionGone):
    """The service lost the session (HTTP 410: the replica that held its state is gone — stopped, crashed or
    restarted); retrying cannot bring it back, only a new session goes on."""


def session_unknown(session_id: str | None, detail: str) -> SessionGone:
    """The error for a 404 on a session's route: the service does not know the session (any more)."""
    return SessionGone(f"the service has no session {session_id!r} (HTTP 404: {detail})")


def session_lost(session_id: str | None, detail: str) -> SessionLostError:
    """The error for a 410 answer; `detail` is the service's reason (which replica, what to do)."""
    return SessionLostError(f"the service cannot resume session {session_id} (HTTP 410): {detail}")
