"""The robot-side client: streams a sensor source to the hapticlink service, losing nothing to short outages.

Blocks get consecutive sequence numbers and wait, encoded, in an ordered resend buffer until the
service acknowledges them. When the connection fails the client reconnects with capped exponential
backoff (with jitter) and resends from the oldest unacknowledged block; the service drops any
seq it already has (acknowledged as a duplicate), so nothing is processed twice. The buffer holds
at most `max_buffer_s` seconds of data: past that the oldest blocks are dropped and counted as
lost. Frames go by HTTP POST; only the few newest wait out an outage. See docs/drivers.md.
"""

from __future__ import annotations

import asyncio
import email.utils
import json
import logging
import math
import random
import time
from collections import deque
from dataclasses import asdict, dataclass
from typing import Literal
from urllib.parse import quote, urlencode, urlsplit, urlunsplit

import httpx

from drivers.blocks import BINARY_CONTENT_TYPE, Frame, SampleBlock, encode_binary, encode_json
from drivers.source import SensorSource, check_positive

log = logging.getLogger(__name__)

WS_SATURATED = 4429  # close code: the session is saturated; reconnect after a backoff
WS_POLICY_VIOLATION = 1008  # close code: authentication failed; fatal
#: HTTP statuses that say "not now" rather than "bad block": 408 timeout, 421 misdirected (another replica), 425 too early
RETRY_STATUSES = frozenset({408, 421, 425})
MAX_RETRY_AFTER_S = 60.0
FRAME_QUEUE = 4  # frames kept during an outage: the newest matter, older ones are superseded
LOST_LOG_EVERY_S = 5.0


class ServiceError(RuntimeError):
    """The service refused the client in a way retrying cannot fix (unknown session, bad request)."""


class RobotAuthError(ServiceError, PermissionError):
    """The robot token was refused (HTTP 401/403, WebSocket close 1008)."""


class SessionLostError(ServiceError):
    """The service lost the session (HTTP 410: the replica that held it is gone); only a new session goes on."""


def _lost(session_id: str | None, detail: str) -> SessionLostError:
    return SessionLostError(f"the service cannot resume session {session_id} (HTTP 410): {detail}")


@dataclass
class RobotStats:
    """Counts of one run. Every block read ends up acked, rejected, lost or unsent."""

    read: int = 0  # blocks taken from the source
    sent: int = 0  # block transmissions, resends included
    resent: int = 0  # transmissions of a block that had been sent before (after an outage)
    acked: int = 0  # blocks the service acknowledged (newly accepted or duplicate)
    duplicates: int = 0  # of those, acknowledged as already received
    rejected: int = 0  # blocks the service refused as bad (4xx / ok:false): logged and dropped
    lost: int = 0  # blocks dropped from a full resend buffer
    lost_s: float = 0.0  # seconds of data those held
    unsent: int = 0  # blocks still unacknowledged when the run ended
    reconnects: int = 0  # recoveries after a failed connection or outage
    saturated: int = 0  # times the service said the session was saturated (429 / close 4429)
    frames_read: int = 0
    frames_sent: int = 0
    frames_dropped: int = 0  # superseded by newer frames during an outage
    frames_rejected: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class SessionInfo:
    session_id: str
    robot_token: str
    operator_token: str | None
    console_url: str | None


class Backoff:
    """Capped exponential backoff with jitter: attempt k waits uniform(½, 1)·min(cap, base·2^k) s.

    The jitter spreads out robots that lost the service at the same moment; reset() after progress.
    """

    def __init__(self, base_s: float, cap_s: float, rng: random.Random | None = None) -> None:
        if not (math.isfinite(base_s) and math.isfinite(cap_s) and 0 < base_s <= cap_s):
            raise ValueError(f"backoff must be (base, cap) seconds with 0 < base ≤ cap, got ({base_s!r}, {cap_s!r})")
        self.base_s, self.cap_s = base_s, cap_s
        self._rng = rng or random.Random()
        self._attempt = 0

    def next(self) -> float:
        """Seconds to wait before the next attempt."""
        ceiling = min(self.cap_s, self.base_s * 2.0 ** min(self._attempt, 62))
        self._attempt += 1
        return ceiling * self._rng.uniform(0.5, 1.0)

    def reset(self) -> None:
        self._attempt = 0


@dataclass(frozen=True)
class _Pending:
    seq: int
    payload: bytes
    duration_s: float


class ResendBuffer:
    """Encoded blocks not yet acknowledged, in seq order, holding at most max_s seconds of data.

    Entries leave from the front only (acknowledged, or dropped when full), so the seqs held are
    always one consecutive run.
    """

    def __init__(self, max_s: float) -> None:
        check_positive("max_buffer_s", max_s)
        self.max_s = max_s
        self._items: deque[_Pending] = deque()
        self.held_s = 0.0

    def __len__(self) -> int:
        return len(self._items)

    def append(self, entry: _Pending) -> list[_Pending]:
        """Add the newest block; return the oldest ones dropped to stay within max_s (never the new one)."""
        if self._items and entry.seq != self._items[-1].seq + 1:
            raise ValueError(f"resend buffer: seq {entry.seq} does not follow {self._items[-1].seq}")
        self._items.append(entry)
        self.held_s += entry.duration_s
        dropped = []
        while self.held_s > self.max_s + 1e-9 and len(self._items) > 1:
            old = self._items.popleft()
            self.held_s -= old.duration_s
            dropped.append(old)
        return dropped

    def settle(self, seq: int) -> list[_Pending]:
        """Remove and return every entry with seq ≤ `seq` (the service has seen them)."""
        out = []
        while self._items and self._items[0].seq <= seq:
            old = self._items.popleft()
            self.held_s -= old.duration_s
            out.append(old)
        if not self._items:
            self.held_s = 0.0  # no round-off creeping in
        return out

    def first_from(self, seq: int) -> _Pending | None:
        """The oldest entry with seq ≥ `seq`, or None."""
        if not self._items:
            return None
        i = max(0, seq - self._items[0].seq)
        return self._items[i] if i < len(self._items) else None

    def count_before(self, seq: int) -> int:
        """Entries with seq < `seq` (sent and waiting for their acknowledgement)."""
        if not self._items:
            return 0
        return max(0, min(seq - self._items[0].seq, len(self._items)))

    @property
    def oldest_seq(self) -> int | None:
        return self._items[0].seq if self._items else None


class _Disconnected(Exception):
    """The WebSocket closed or failed; close_code says how (None: no close frame)."""

    def __init__(self, close_code: int | None, reason: str = "") -> None:
        super().__init__(f"connection closed (code {close_code}{': ' + reason if reason else ''})")
        self.close_code = close_code
        self.reason = reason


def _retry_after(response: httpx.Response) -> float | None:
    """Seconds from a Retry-After header (delta-seconds, fractional accepted, or an HTTP date), capped."""
    value = response.headers.get("retry-after")
    if not value:
        return None
    try:
        seconds = float(value)
    except ValueError:
        try:
            seconds = email.utils.parsedate_to_datetime(value).timestamp() - time.time()
        except (TypeError, ValueError):
            return None
    return min(max(seconds, 0.0), MAX_RETRY_AFTER_S) if math.isfinite(seconds) else None


def _detail(response: httpx.Response) -> str:
    return _body_detail(response.content)


def _body_detail(content: bytes | None) -> str:
    """The `detail` of a JSON error body, else its first 200 characters."""
    try:
        body = json.loads(content or b"")
        return str(body.get("detail", body)) if isinstance(body, dict) else str(body)
    except ValueError:
        return (content or b"")[:200].decode(errors="replace")


class RobotClient:
    """Streams `source` to the service at `url` (http(s)://host:port[/prefix]).

    session_id + robot_token: stream into an existing session; neither: create one (its operator
    token and console link are kept in `session`). transport "ws" (blocks over one WebSocket,
    up to `window` unacknowledged in flight) or "http" (one POST per block, in order);
    binary=False sends JSON blocks (WebSocket text messages) instead of the binary format. max_buffer_s: seconds of unacknowledged data kept for resending.
    backoff: (first, longest) wait in seconds between reconnection attempts. start_seq: seq of the
    first block (when resuming a session that already has blocks, pass more than its last seq).
    `run()` closes the source when it returns.
    """

    def __init__(
        self,
        url: str,
        source: SensorSource,
        *,
        session_id: str | None = None,
        robot_token: str | None = None,
        transport: Literal["ws", "http"] = "ws",
        binary: bool = True,
        max_buffer_s: float = 60.0,
        backoff: tuple[float, float] = (0.2, 5.0),
        session_name: str | None = None,
        start_seq: int = 0,
        window: int = 64,
        drain_timeout_s: float = 30.0,
        request_timeout_s: float = 10.0,
        seed: int | None = None,
    ) -> None:
        parts = urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.netloc:
            raise ValueError(f"url must be http://host[:port] or https://…, got {url!r}")
        if (session_id is None) != (robot_token is None):
            raise ValueError("give both session_id and robot_token (stream into that session) or neither (create one)")
        if transport not in ("ws", "http"):
            raise ValueError(f"transport must be 'ws' or 'http', got {transport!r}")
        if isinstance(start_seq, bool) or not isinstance(start_seq, int) or start_seq < 0:
            raise ValueError(f"start_seq must be an integer ≥ 0, got {start_seq!r}")
        if window < 1:
            raise ValueError(f"window must be ≥ 1 block, got {window}")
        check_positive("drain_timeout_s", drain_timeout_s)
        check_positive("request_timeout_s", request_timeout_s)
        self.url = url.rstrip("/")
        self.source = source
        self.session_id = session_id
        self.robot_token = robot_token
        self.session: SessionInfo | None = None
        self.transport = transport
        self.binary = binary
        self.session_name = session_name
        self.window = window
        self.drain_timeout_s = drain_timeout_s
        self.request_timeout_s = request_timeout_s
        rng = random.Random(seed)
        self._block_backoff = Backoff(*backoff, rng=rng)
        self._frame_backoff = Backoff(*backoff, rng=rng)
        self._buffer = ResendBuffer(max_buffer_s)
        self._next_seq = start_seq
        self._max_sent_seq = start_seq - 1
        self._frames: deque[Frame] = deque()
        self._blocks_changed = asyncio.Event()
        self._frames_changed = asyncio.Event()
        self._draining = False
        self._stopping = False
        self._ran = False
        self._reader: asyncio.Task | None = None
        self._http: httpx.AsyncClient | None = None
        self._last_lost_log = -math.inf
        self._warned_duplicate_start = False
        self.stats = RobotStats()

    # ---- session ------------------------------------------------------------------------------
    def _auth(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.robot_token}"}

    def _session_url(self, tail: str) -> str:
        return f"{self.url}/sessions/{quote(str(self.session_id), safe='')}/{tail}"

    async def open_session(self) -> SessionInfo:
        """Create a session (POST /sessions), retrying while the service is unreachable or failing.

        The operator token and console link are in the result (and `self.session`), never in the log: logs
        travel further than the people who should read the session. ServiceError if the service refuses (4xx).
        """
        if self.session_id is not None:
            raise RuntimeError("this client already has a session")
        http = self._http or httpx.AsyncClient(timeout=self.request_timeout_s)
        backoff = Backoff(self._block_backoff.base_s, self._block_backoff.cap_s)
        body = {"name": self.session_name} if self.session_name else {}
        try:
            while True:
                try:
                    r = await http.post(f"{self.url}/sessions", json=body)
                except httpx.TransportError as exc:
                    delay = backoff.next()
                    log.warning("cannot reach %s (%s); retrying in %.1f s", self.url, exc, delay)
                    await asyncio.sleep(delay)
                    continue
                if r.status_code >= 500 or r.status_code == 429:
                    delay = _retry_after(r) or backoff.next()
                    log.warning("creating a session: HTTP %d; retrying in %.1f s", r.status_code, delay)
                    await asyncio.sleep(delay)
                    continue
                if r.status_code not in (200, 201):
                    raise ServiceError(f"creating a session: HTTP {r.status_code}: {_detail(r)}")
                doc = r.json()
                break
        finally:
            if http is not self._http:
                await http.aclose()
        try:
            sid, robot, operator = str(doc["session_id"]), str(doc["robot_token"]), doc.get("operator_token")
        except (KeyError, TypeError):
            raise ServiceError(f"creating a session: unexpected answer {str(doc)[:200]}") from None
        console = f"{self.url}/console?{urlencode({'session': sid, 'token': operator})}" if operator else None
        self.session_id, self.robot_token = sid, robot
        self.session = SessionInfo(sid, robot, operator, console)
        log.info("session %s created", sid)
        return self.session

    # ---- run ----------------------------------------------------------------------------------
    def stop(self) -> None:
        """Stop reading the source; run() then delivers what is buffered (up to drain_timeout_s) and returns."""
        self._stopping = True
        if self._reader is not None and not self._reader.done():
            self._reader.cancel()

    async def run(self, duration_s: float | None = None) -> RobotStats:
        """Stream until the source ends, stop() is called or duration_s (wall clock) has passed,
        then deliver what is buffered (at most drain_timeout_s) and return the stats.

        A source that fails ends the run with its error, after what it delivered has been sent.
        RobotAuthError / ServiceError when the service refuses the token or the session.
        Cancelling it stops at once: tasks and connections closed, the source closed, unsent
        blocks counted in stats.unsent."""
        if duration_s is not None:
            check_positive("duration_s", duration_s)
        if self._ran:
            raise RuntimeError("a RobotClient runs once (its source is closed afterwards); make a new one")
        self._ran = True
        loop = asyncio.get_running_loop()
        tasks: list[asyncio.Task] = []
        timer = None
        try:
            async with httpx.AsyncClient(timeout=self.request_timeout_s) as http:
                self._http = http
                if self.session_id is None:
                    await self.open_session()
                self._reader = asyncio.create_task(self._read_source(), name="robot-reader")
                if self._stopping:
                    self._reader.cancel()
                sender = asyncio.create_task(self._send_ws() if self.transport == "ws" else self._send_http(), name="robot-sender")
                framer = asyncio.create_task(self._send_frames(), name="robot-frames")
                tasks = [self._reader, sender, framer]
                if duration_s is not None:
                    timer = loop.call_later(duration_s, self.stop)
                await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
                for task in (sender, framer):
                    if task.done():
                        task.result()  # they end early only on a fatal error: raise it
                await asyncio.wait([self._reader])
                source_error = None if self._reader.cancelled() else self._reader.exception()
                await self._drain(sender, framer)  # what was read before a source failed still goes out
                if source_error is not None:
                    raise source_error
        finally:
            if timer is not None:
                timer.cancel()
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await self.source.aclose()
            self._http = None
            self.stats.unsent = len(self._buffer)
            if self.stats.unsent:
                log.error("%d block(s) (%.1f s of data) were never acknowledged", self.stats.unsent, self._buffer.held_s)
        return self.stats

    async def _drain(self, sender: asyncio.Task, framer: asyncio.Task) -> None:
        """Let the senders deliver what is buffered, for at most drain_timeout_s."""
        self._draining = True
        self._blocks_changed.set()
        self._frames_changed.set()
        done, pending = await asyncio.wait([sender, framer], timeout=self.drain_timeout_s)
        for task in done:
            task.result()
        if pending:
            log.error("gave up delivering after %.0f s: %d block(s) still unacknowledged", self.drain_timeout_s, len(self._buffer))

    # ---- source → buffer ------------------------------------------------------------------------
    async def _read_source(self) -> None:
        async for item in self.source:
            if isinstance(item, SampleBlock):
                self._enqueue_block(item)
            elif isinstance(item, Frame):
                self._enqueue_frame(item)
            else:
                log.warning("source %s yielded a %s; ignored", getattr(self.source, "name", "?"), type(item).__name__)

    def _enqueue_block(self, block: SampleBlock) -> None:
        seq = self._next_seq
        self._next_seq += 1
        numbered = SampleBlock(block.t0, block.channels, seq)
        payload = encode_binary(numbered) if self.binary else json.dumps(encode_json(numbered)).encode()
        duration = max(c.duration_s for c in block.channels.values())
        self.stats.read += 1
        dropped = self._buffer.append(_Pending(seq, payload, duration))
        if dropped:
            self.stats.lost += len(dropped)
            self.stats.lost_s += sum(d.duration_s for d in dropped)
            now = time.monotonic()
            if now - self._last_lost_log >= LOST_LOG_EVERY_S:
                self._last_lost_log = now
                log.error(
                    "resend buffer full (%.0f s): dropping the oldest blocks — %d lost so far (%.1f s of data); the service has been unreachable too long",
                    self._buffer.max_s,
                    self.stats.lost,
                    self.stats.lost_s,
                )
        self._blocks_changed.set()

    def _enqueue_frame(self, frame: Frame) -> None:
        self.stats.frames_read += 1
        if len(self._frames) >= FRAME_QUEUE:
            self._frames.popleft()
            self.stats.frames_dropped += 1
        self._frames.append(frame)
        self._frames_changed.set()

    # ---- acknowledgements ---------------------------------------------------------------------
    def _count_send(self, seq: int) -> None:
        self.stats.sent += 1
        if seq <= self._max_sent_seq:
            self.stats.resent += 1
        else:
            self._max_sent_seq = seq

    def _acknowledges_sent(self, seq: int) -> bool:
        if seq > self._max_sent_seq:
            log.warning("ignoring an acknowledgement for block %d, which was never sent", seq)
            return False
        return True

    def _settle(self, seq: int, duplicate: bool) -> None:
        """The service has block `seq`: everything up to it leaves the buffer."""
        if not self._acknowledges_sent(seq):
            return
        # Earlier entries leave too: the service drops any seq ≤ one it has, so resending them is pointless.
        removed = self._buffer.settle(seq)
        self.stats.acked += len(removed)
        if duplicate and removed and removed[-1].seq == seq:
            self.stats.duplicates += 1
            if self.stats.resent == 0 and not self._warned_duplicate_start:
                self._warned_duplicate_start = True
                log.warning("the service already had block %d: this session received blocks before; pass start_seq above its last seq", seq)
        self._block_backoff.reset()
        self._blocks_changed.set()

    def _reject(self, seq: int, why: str) -> None:
        """The service refused block `seq` as bad: drop it, never resend it."""
        if not self._acknowledges_sent(seq):
            return
        removed = self._buffer.settle(seq)
        if removed and removed[-1].seq == seq:
            self.stats.rejected += 1
            self.stats.acked += len(removed) - 1
            log.error("the service rejected block %d: %s (dropped)", seq, why)
        else:
            self.stats.acked += len(removed)
        self._blocks_changed.set()

    # ---- WebSocket transport ------------------------------------------------------------------
    def _ws_url(self) -> str:
        parts = urlsplit(self._session_url("ingest"))
        scheme = "wss" if parts.scheme == "https" else "ws"
        return urlunsplit((scheme, parts.netloc, parts.path, urlencode({"token": self.robot_token}), ""))

    async def _send_ws(self) -> None:
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus

        uri = self._ws_url()
        failed = False
        while True:
            if self._draining and not self._buffer:
                return
            try:
                async with connect(uri, open_timeout=self.request_timeout_s, close_timeout=2.0, max_size=2**20, compression=None, proxy=None) as ws:
                    if failed:
                        self.stats.reconnects += 1
                        log.info("reconnected to %s; resending from block %s", self.url, self._buffer.oldest_seq)
                    failed = False
                    await self._ws_stream(ws)
                    return
            except InvalidStatus as exc:
                status = exc.response.status_code
                if status in (401, 403):
                    raise RobotAuthError(f"the service refused the robot token (HTTP {status})") from None
                if status == 404:
                    raise ServiceError(f"the service has no session {self.session_id!r} (HTTP 404)") from None
                if status == 410:
                    raise _lost(self.session_id, _body_detail(exc.response.body)) from None
                if status == 429:
                    self.stats.saturated += 1
                why = f"HTTP {status}"
            except _Disconnected as exc:
                if exc.close_code == WS_POLICY_VIOLATION:
                    raise RobotAuthError(f"the service closed the connection: authentication failed ({exc.reason or 'close 1008'})") from None
                if exc.close_code == WS_SATURATED:
                    self.stats.saturated += 1
                why = str(exc)
            except (OSError, TimeoutError, InvalidHandshake, ConnectionClosed) as exc:
                why = f"{type(exc).__name__}: {exc}"
            failed = True
            delay = self._block_backoff.next()
            log.warning("WebSocket to %s: %s; reconnecting in %.2f s (%d block(s) buffered)", self.url, why, delay, len(self._buffer))
            await asyncio.sleep(delay)

    async def _ws_stream(self, ws) -> None:
        """Send over one connection, from the oldest unacknowledged block, until drained (return)
        or the connection ends (_Disconnected)."""
        from websockets.exceptions import ConnectionClosed

        # The service answers every message in order, so the n-th answer is about the n-th block
        # sent on this connection; that names the block even when an error answer carries no seq.
        sent_order: deque[int] = deque()
        receiver = asyncio.create_task(self._ws_receive(ws, sent_order), name="robot-acks")
        next_seq = self._buffer.oldest_seq if self._buffer.oldest_seq is not None else self._next_seq
        try:
            while not receiver.done():
                self._blocks_changed.clear()
                entry = self._buffer.first_from(next_seq)
                if entry is not None and self._buffer.count_before(entry.seq) < self.window:
                    sent_order.append(entry.seq)
                    await ws.send(entry.payload if self.binary else entry.payload.decode())
                    self._count_send(entry.seq)
                    next_seq = entry.seq + 1
                    continue
                if self._draining and not self._buffer:
                    return
                await self._blocks_changed.wait()
        except ConnectionClosed:
            pass
        finally:
            receiver.cancel()
            await asyncio.gather(receiver, return_exceptions=True)
        raise _Disconnected(ws.close_code, ws.close_reason or "")

    async def _ws_receive(self, ws, sent_order: deque[int]) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            async for message in ws:
                expected = sent_order.popleft() if sent_order else None
                try:
                    ack = json.loads(message)
                    seq, ok = ack.get("seq"), bool(ack["ok"])
                    seq = expected if seq is None else int(seq)
                except (ValueError, KeyError, TypeError, AttributeError):
                    log.warning("ignoring an unreadable acknowledgement: %r", message[:200])
                    continue
                if seq is None:
                    log.warning("ignoring an acknowledgement for no block sent on this connection: %r", message[:200])
                elif ok:
                    self._settle(seq, bool(ack.get("duplicate", False)))
                else:
                    self._reject(seq, str(ack.get("error", "no reason given")))
        except ConnectionClosed:
            pass
        finally:
            self._blocks_changed.set()  # wake the sender: the connection is gone

    # ---- HTTP transport -----------------------------------------------------------------------
    async def _send_http(self) -> None:
        assert self._http is not None
        url = self._session_url("blocks")
        headers = {**self._auth(), "Content-Type": BINARY_CONTENT_TYPE if self.binary else "application/json"}
        outage = False
        while True:
            self._blocks_changed.clear()
            entry = self._buffer.first_from(0)
            if entry is None:
                if self._draining:
                    return
                await self._blocks_changed.wait()
                continue
            try:
                r = await self._http.post(url, content=entry.payload, headers=headers)
            except httpx.TransportError as exc:
                if not isinstance(exc, (httpx.ConnectError, httpx.ConnectTimeout)):
                    self._count_send(entry.seq)  # it may have arrived: the resend will tell
                outage = True
                delay = self._block_backoff.next()
                log.warning("POST block %d: %s; retrying in %.2f s (%d block(s) buffered)", entry.seq, exc, delay, len(self._buffer))
                await asyncio.sleep(delay)
                continue
            self._count_send(entry.seq)
            status = r.status_code
            if status < 500 and outage:
                outage = False
                self.stats.reconnects += 1
                log.info("the service is reachable again; resending from block %d", entry.seq)
            if status in (200, 201, 202):
                try:
                    duplicate = bool(r.json().get("duplicate", False))
                except (ValueError, AttributeError):
                    duplicate = False
                self._settle(entry.seq, duplicate)
            elif status == 429:
                self.stats.saturated += 1
                delay = _retry_after(r) or self._block_backoff.next()
                log.warning("session saturated (429); resending block %d in %.2f s", entry.seq, delay)
                await asyncio.sleep(delay)
            elif status in (401, 403):
                raise RobotAuthError(f"the service refused the robot token (HTTP {status}: {_detail(r)})")
            elif status == 404:
                raise ServiceError(f"the service has no session {self.session_id!r} (HTTP 404: {_detail(r)})")
            elif status == 410:
                raise _lost(self.session_id, _detail(r))
            elif 400 <= status < 500 and status not in RETRY_STATUSES:
                self._reject(entry.seq, f"HTTP {status}: {_detail(r)}")
            else:  # 5xx, 408, 421, 425: the service cannot take it now
                outage = True
                delay = self._block_backoff.next()
                log.warning("POST block %d: HTTP %d; retrying in %.2f s", entry.seq, status, delay)
                await asyncio.sleep(delay)

    # ---- frames -------------------------------------------------------------------------------
    async def _send_frames(self) -> None:
        assert self._http is not None
        url = self._session_url("frames")
        while True:
            self._frames_changed.clear()
            if not self._frames:
                if self._draining:
                    return
                await self._frames_changed.wait()
                continue
            frame = self._frames[0]
            try:
                r = await self._http.post(url, content=frame.image, headers={**self._auth(), "Content-Type": frame.content_type})
            except httpx.TransportError as exc:
                delay = self._frame_backoff.next()
                log.warning("POST frame: %s; retrying in %.2f s", exc, delay)
                await asyncio.sleep(delay)
                continue
            status = r.status_code
            if status in (401, 403):
                raise RobotAuthError(f"the service refused the robot token for frames (HTTP {status}: {_detail(r)})")
            if status == 410:
                raise _lost(self.session_id, _detail(r))
            if status == 429 or status >= 500 or status in RETRY_STATUSES:
                delay = (_retry_after(r) if status == 429 else None) or self._frame_backoff.next()
                await asyncio.sleep(delay)
                continue
            if self._frames and self._frames[0] is frame:  # it may have been superseded meanwhile
                self._frames.popleft()
            if 200 <= status < 300:
                self.stats.frames_sent += 1
                self._frame_backoff.reset()
            else:
                self.stats.frames_rejected += 1
                log.error("the service rejected a frame (%s): HTTP %d: %s", frame.content_type, status, _detail(r))
