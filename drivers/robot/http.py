"""The HTTP transport: one `POST /sessions/{id}/blocks` per block, in order, retried through outages."""

from __future__ import annotations

import asyncio
import logging

import httpx

from drivers.protocol import BINARY_CONTENT_TYPE, RETRY_STATUSES, SESSION_LOST, bearer, session_path
from drivers.robot.backoff import detail, retry_after
from drivers.robot.errors import RobotAuthError, session_lost, session_unknown
from drivers.robot.outbox import Endpoint, Outbox

log = logging.getLogger("drivers.robot")


async def send_http(endpoint: Endpoint, outbox: Outbox) -> None:
    """Deliver the outbox's blocks by HTTP POST until drained; RobotAuthError / ServiceRefused (SessionLostError on
    410) when final."""
    http = outbox.http
    assert http is not None
    url = endpoint.url + session_path(str(endpoint.session_id), "blocks")
    headers = {
        **bearer(str(endpoint.robot_token)),
        "Content-Type": BINARY_CONTENT_TYPE if endpoint.binary else "application/json",
    }
    buffer = outbox.buffer
    outage = False
    while True:
        outbox.blocks_changed.clear()
        entry = buffer.first_from(0)
        if entry is None:
            if outbox.draining:
                return
            await outbox.blocks_changed.wait()
            continue
        try:
            r = await http.post(url, content=entry.payload, headers=headers)
        except httpx.TransportError as exc:
            if not isinstance(exc, (httpx.ConnectError, httpx.ConnectTimeout)):
                outbox.count_send(entry.seq)  # it may have arrived: the resend will tell
            outage = True
            outbox.ingest_open.clear()
            delay = outbox.block_backoff.next()
            log.warning(
                "POST block %d: %s: %s; retrying in %.2f s (%d block(s) buffered)",
                entry.seq,
                type(exc).__name__,
                exc,
                delay,
                len(buffer),
            )
            await asyncio.sleep(delay)
            continue
        outbox.count_send(entry.seq)
        status = r.status_code
        if status < 500 and outage:
            outage = False
            outbox.stats.reconnects += 1
            log.info("the service is reachable again; resending from block %d", entry.seq)
        if status in (200, 201, 202):
            try:
                duplicate = bool(r.json().get("duplicate", False))
            except (ValueError, AttributeError):
                duplicate = False
            outbox.ingest_open.set()
            outbox.settle(entry.seq, duplicate)
        elif status == 429:
            outbox.ingest_open.clear()
            outbox.stats.saturated += 1
            delay = outbox.block_backoff.next(retry_after(r))
            log.warning("session saturated (429); resending block %d in %.2f s", entry.seq, delay)
            await asyncio.sleep(delay)
        elif status in (401, 403):
            raise RobotAuthError(f"the service refused the robot token (HTTP {status}: {detail(r)})")
        elif status == 404:
            raise session_unknown(endpoint.session_id, detail(r))
        elif status == SESSION_LOST:
            raise session_lost(endpoint.session_id, detail(r))
        elif 400 <= status < 500 and status not in RETRY_STATUSES:
            outbox.reject(entry.seq, f"HTTP {status}: {detail(r)}")
        else:  # 5xx, 408, 421, 425: the service cannot take it now
            outage = True
            outbox.ingest_open.clear()
            delay = outbox.block_backoff.next()
            log.warning("POST block %d: HTTP %d; retrying in %.2f s", entry.seq, status, delay)
            await asyncio.sleep(delay)
