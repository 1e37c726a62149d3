"""Camera frames: `POST /sessions/{id}/frames`; only the few newest wait out an outage or a busy visual queue."""

from __future__ import annotations

import asyncio
import logging

import httpx

from drivers.protocol import RETRY_STATUSES, SESSION_LOST, bearer, session_path
from drivers.robot.backoff import detail, retry_after
from drivers.robot.errors import RobotAuthError, session_lost
from drivers.robot.outbox import Endpoint, Outbox

log = logging.getLogger("drivers.robot")


async def send_frames(endpoint: Endpoint, outbox: Outbox) -> None:
    """Send the outbox's queued frames in order until drained, each once the service takes the robot's blocks
    (`Outbox.ingest_open`); 429 (visual queue full) waits Retry-After and sends the newest."""
    http = outbox.http
    assert http is not None
    url = endpoint.url + session_path(str(endpoint.session_id), "frames")
    frames = outbox.frames
    while True:
        outbox.frames_changed.clear()
        if not frames:
            if outbox.draining:
                return
            await outbox.frames_changed.wait()
            continue
        if not outbox.ingest_open.is_set():
            await outbox.ingest_open.wait()
            continue  # newer frames may have superseded it meanwhile
        frame = frames[0]
        try:
            r = await http.post(
                url,
                content=frame.image,
                headers={**bearer(str(endpoint.robot_token)), "Content-Type": frame.content_type},
            )
        except httpx.TransportError as exc:
            delay = outbox.frame_backoff.next()
            log.warning("POST frame: %s: %s; retrying in %.2f s", type(exc).__name__, exc, delay)
            await asyncio.sleep(delay)
            continue
        status = r.status_code
        if status in (401, 403):
            raise RobotAuthError(f"the service refused the robot token for frames (HTTP {status}: {detail(r)})")
        if status == SESSION_LOST:
            raise session_lost(endpoint.session_id, detail(r))
        if status == 429 or status >= 500 or status in RETRY_STATUSES:
            outbox.stats.frames_refused += status == 429
            delay = outbox.frame_backoff.next(retry_after(r) if status == 429 else None)
            await asyncio.sleep(delay)
            continue
        if frames and frames[0] is frame:  # it may have been superseded meanwhile
            frames.popleft()
        if 200 <= status < 300:
            outbox.stats.frames_sent += 1
            outbox.frame_backoff.reset()
        else:
            outbox.stats.frames_rejected += 1
            log.error("the service rejected a frame (%s): HTTP %d: %s", frame.content_type, status, detail(r))
