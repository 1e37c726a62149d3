"""Opening a session: `POST /sessions` with the fleet API key, retried while the service is unreachable or busy."""

from __future__ import annotations

import asyncio
import logging
import os
import time
from dataclasses import dataclass
from urllib.parse import urlencode

import httpx

from drivers.protocol import API_KEY_ENV, bearer
from drivers.robot.backoff import Backoff, detail, retry_after
from drivers.robot.errors import RobotAuthError, ServiceRefused, ServiceUnavailable

log = logging.getLogger("drivers.robot")


@dataclass(frozen=True)
class SessionInfo:
    session_id: str
    robot_token: str
    operator_token: str | None
    console_url: str | None


def api_key_from_env(api_key: str | None) -> str | None:
    """`api_key` if given, else $HAPTICLINK_API_KEY (None if neither)."""
    return api_key if api_key is not None else (os.environ.get(API_KEY_ENV) or None)


async def open_session(
    http: httpx.AsyncClient,
    url: str,
    api_key: str | None,
    name: str | None,
    backoff: Backoff,
    *,
    timeout_s: float | None = 60.0,
    robot: str | None = None,
    first_seq: int = 0,
) -> SessionInfo:
    """Create a session at the service `url`, retrying transport errors, 5xx and 429 (after Retry-After) for at
    most `timeout_s` seconds (None: for ever); then ServiceUnavailable, naming the last answer. robot: the robot's
    own id (operators follow the robot by it); first_seq: the seq of the session's first block (a robot resuming
    after its session was lost goes on with its own numbering).

    The operator token and console link are in the result, never in the log: logs travel further than
    the people who should read the session. RobotAuthError for a refused or missing API key,
    ServiceRefused for any other 4xx.
    """
    body: dict[str, object] = {"name": name} if name else {}
    if robot is not None:
        body["robot"] = robot
    if first_seq:
        body["first_seq"] = first_seq
    headers = bearer(api_key) if api_key else {}
    deadline = None if timeout_s is None else time.monotonic() + timeout_s

    async def wait(delay: float, why: str) -> None:
        """Sleep `delay` before the next attempt, or give up when that would pass the deadline."""
        if deadline is not None and time.monotonic() + delay > deadline:
            raise ServiceUnavailable(
                f"could not create a session at {url} within {timeout_s:g} s: {why} "
                "(is the service running, and does its /ready answer 200?)"
            )
        await asyncio.sleep(delay)

    while True:
        try:
            r = await http.post(f"{url}/sessions", json=body, headers=headers)
        except httpx.TransportError as exc:
            delay = backoff.next()
            log.warning("cannot reach %s (%s); retrying in %.1f s", url, exc, delay)
            await wait(delay, f"cannot reach it ({type(exc).__name__}: {exc})")
            continue
        if r.status_code == 503 and "API key" in detail(r):  # the service is not configured for fleets
            raise ServiceRefused(f"creating a session: HTTP 503: {detail(r)}")
        if r.status_code >= 500 or r.status_code == 429:
            delay = backoff.next(retry_after(r))
            log.warning("creating a session: HTTP %d; retrying in %.1f s", r.status_code, delay)
            await wait(delay, f"the last answer was HTTP {r.status_code}: {detail(r)}")
            continue
        if r.status_code in (401, 403):
            raise RobotAuthError(
                f"creating a session: HTTP {r.status_code}: {detail(r)}"
                + ("" if api_key else f" (pass --api-key or set {API_KEY_ENV})")
            )
        if r.status_code not in (200, 201):
            raise ServiceRefused(f"creating a session: HTTP {r.status_code}: {detail(r)}")
        doc = r.json()
        break
    try:
        sid, robot, operator = str(doc["session_id"]), str(doc["robot_token"]), doc.get("operator_token")
    except (KeyError, TypeError):
        raise ServiceRefused(f"creating a session: unexpected answer {str(doc)[:200]}") from None
    console = f"{url}/console?{urlencode({'session': sid, 'token': operator})}" if operator else None
    log.info("session %s created", sid)
    return SessionInfo(sid, robot, operator, console)
