"""The WebSocket transport: blocks over one `WS /sessions/{id}/ingest` connection, up to `window` unacknowledged
in flight; reconnects with backoff and resends from the oldest unacknowledged block."""

from __future__ import annotations

import asyncio
import logging
from collections import deque

from drivers.protocol import SESSION_LOST, Close, parse_ack, ws_url
from drivers.robot.backoff import body_detail, retry_after
from drivers.robot.errors import RobotAuthError, ServiceRefused, session_lost, session_unknown
from drivers.robot.outbox import Endpoint, Outbox

log = logging.getLogger("drivers.robot")


class Disconnected(Exception):
    """The WebSocket closed or failed; close_code says how (None: no close frame)."""

    def __init__(self, close_code: int | None, reason: str = "") -> None:
        super().__init__(f"connection closed (code {close_code}{': ' + reason if reason else ''})")
        self.close_code = close_code
        self.reason = reason


async def send_ws(endpoint: Endpoint, outbox: Outbox) -> None:
    """Deliver the outbox's blocks over WebSocket until drained; RobotAuthError / ServiceRefused (SessionLostError
    on 410) when final."""
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus

    uri = ws_url(endpoint.url, str(endpoint.session_id), "ingest", str(endpoint.robot_token))
    failed = False
    while True:
        if outbox.draining and not outbox.buffer:
            return
        hinted: float | None = None  # s, the service's Retry-After, when it gave one
        try:
            async with connect(
                uri,
                open_timeout=endpoint.request_timeout_s,
                close_timeout=2.0,
                max_size=2**20,
                compression=None,
                proxy=None,
            ) as ws:
                if failed:
                    outbox.stats.reconnects += 1
                    log.info("reconnected to %s; resending from block %s", endpoint.url, outbox.buffer.oldest_seq)
                failed = False
                outbox.ingest_open.set()
                await _stream(endpoint, outbox, ws)
                return
        except InvalidStatus as exc:
            status = exc.response.status_code
            if status in (401, 403):
                raise RobotAuthError(f"the service refused the robot token (HTTP {status})") from None
            if status == 404:
                raise session_unknown(endpoint.session_id, body_detail(exc.response.body)) from None
            if status == SESSION_LOST:
                raise session_lost(endpoint.session_id, body_detail(exc.response.body)) from None
            if status == 429:  # the replica sheds this session: it says when to come back
                outbox.stats.saturated += 1
                hinted = retry_after(exc.response)
            why = f"HTTP {status}"
        except Disconnected as exc:
            if exc.close_code == Close.POLICY:
                raise RobotAuthError(
                    f"the service closed the connection: authentication failed ({exc.reason or 'close 1008'})"
                ) from None
            if exc.close_code == Close.LOST:
                raise session_lost(endpoint.session_id, exc.reason or f"close {int(Close.LOST)}") from None
            if exc.close_code == Close.SESSION_ENDED and exc.reason == "session ended":
                raise ServiceRefused(f"the service ended session {endpoint.session_id!r}") from None
            if exc.close_code == Close.SATURATED:
                outbox.stats.saturated += 1
            elif exc.close_code == Close.REPLACED:  # another client holds this robot token, or an old link of ours
                outbox.stats.replaced += 1
            why = str(exc)
        except (OSError, TimeoutError, InvalidHandshake, ConnectionClosed) as exc:
            why = f"{type(exc).__name__}: {exc}"
        failed = True
        outbox.ingest_open.clear()
        delay = outbox.block_backoff.next(hinted)
        log.warning(
            "WebSocket to %s: %s; reconnecting in %.2f s (%d block(s) buffered)",
            endpoint.url,
            why,
            delay,
            len(outbox.buffer),
        )
        await asyncio.sleep(delay)


async def _stream(endpoint: Endpoint, outbox: Outbox, ws) -> None:
    """Send over one connection, from the oldest unacknowledged block, until drained (return) or the
    connection ends (Disconnected)."""
    from websockets.exceptions import ConnectionClosed

    # The service answers every message in order, so the n-th answer is about the n-th block
    # sent on this connection; that names the block even when an error answer carries no seq.
    sent_order: deque[int] = deque()
    receiver = asyncio.create_task(_receive(outbox, ws, sent_order), name="robot-acks")
    buffer = outbox.buffer
    next_seq = buffer.oldest_seq if buffer.oldest_seq is not None else outbox.next_seq
    try:
        while not receiver.done():
            outbox.blocks_changed.clear()
            entry = buffer.first_from(next_seq)
            if entry is not None and buffer.count_before(entry.seq) < endpoint.window:
                sent_order.append(entry.seq)
                await ws.send(entry.payload if endpoint.binary else entry.payload.decode())
                outbox.count_send(entry.seq)
                next_seq = entry.seq + 1
                continue
            if outbox.draining and not buffer:
                return
            await outbox.blocks_changed.wait()
    except ConnectionClosed:
        pass
    finally:
        receiver.cancel()
        await asyncio.gather(receiver, return_exceptions=True)
    raise Disconnected(ws.close_code, ws.close_reason or "")


async def _receive(outbox: Outbox, ws, sent_order: deque[int]) -> None:
    from websockets.exceptions import ConnectionClosed

    try:
        async for message in ws:
            expected = sent_order.popleft() if sent_order else None
            try:
                ack = parse_ack(message)
            except ValueError:
                log.warning("ignoring an unreadable acknowledgement: %r", message[:200])
                continue
            seq = expected if ack.seq is None else ack.seq
            if seq is None:
                log.warning("ignoring an acknowledgement for no block sent on this connection: %r", message[:200])
            elif ack.ok:
                outbox.settle(seq, ack.duplicate)
            else:
                outbox.reject(seq, ack.error or "no reason given")
    except ConnectionClosed:
        pass
    finally:
        outbox.blocks_changed.set()  # wake the sender: the connection is gone
