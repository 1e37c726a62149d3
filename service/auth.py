"""Per-session tokens: one for the robot (writes), one for operators (reads).

Tokens are `secrets.token_urlsafe(32)` (never beginning with "-"); only their SHA-256 is kept (in memory and in Redis),
and checks compare digests with `hmac.compare_digest`, so a token never leaks through
timing or through the broker.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass
from enum import Enum

from service.errors import ServiceError

TOKEN_BYTES = 32


class Role(str, Enum):  # noqa: UP042 - StrEnum would change str(Role.X) in messages
    ROBOT = "robot"  # sends blocks and frames
    OPERATOR = "operator"  # reads events and the session's status


@dataclass(frozen=True)
class SessionCredentials:
    """Which tokens open a session: SHA-256 hex digests of the robot and operator tokens."""

    robot_digest: str
    operator_digest: str


def new_token() -> str:
    """A fresh token that never begins with "-": tokens are given on command lines (`--token T`), where argparse
    reads a value that begins with "-" as an option (one token in 64 would be refused; the draw costs < 0.03 bit)."""
    while (token := secrets.token_urlsafe(TOKEN_BYTES)).startswith("-"):
        pass
    return token


def digest(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def issue_credentials() -> tuple[str, str, SessionCredentials]:
    """(robot token, operator token, what the service keeps of them)."""
    robot, operator = new_token(), new_token()
    return robot, operator, SessionCredentials(digest(robot), digest(operator))


def role_of(credentials: SessionCredentials, token: str) -> Role | None:
    """The role `token` carries for this session, or None. Both digests are always compared (constant work)."""
    given = digest(token)
    is_robot = hmac.compare_digest(given, credentials.robot_digest)
    is_operator = hmac.compare_digest(given, credentials.operator_digest)
    if is_robot:
        return Role.ROBOT
    if is_operator:
        return Role.OPERATOR
    return None


def missing_token() -> ServiceError:
    """401 for a request that carries no session token."""
    return ServiceError(
        401,
        "missing token: send 'Authorization: Bearer <token>' (WebSockets: ?token=)",
        {"WWW-Authenticate": "Bearer"},
    )


def authorize(credentials: SessionCredentials, token: str | None, allowed: frozenset[Role], session_id: str) -> Role:
    """The caller's role if it may do this; else 401 (no or unknown token) or 403 (the other role's token)."""
    if token is None:
        raise missing_token()
    role = role_of(credentials, token)
    if role is None:
        raise ServiceError(401, f"the token is not valid for session {session_id}", {"WWW-Authenticate": "Bearer"})
    if role not in allowed:
        needed = " or ".join(sorted(r.value for r in allowed))
        article = "an" if role.value[0] in "aeiou" else "a"
        raise ServiceError(403, f"{article} {role.value} token cannot do this; it needs the {needed} token")
    return role


ROBOT_ONLY = frozenset({Role.ROBOT})
OPERATOR_ONLY = frozenset({Role.OPERATOR})
EITHER = frozenset({Role.ROBOT, Role.OPERATOR})
