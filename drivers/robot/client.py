"""The robot-side client: streams a sensor source to the hapticlink service, losing nothing to short outages.

Blocks (sample blocks and tap blocks alike) get consecutive sequence numbers and wait, encoded, in an ordered resend buffer
(drivers/robot/resend.py) until the service acknowledges them. When the connection fails the client
reconnects with capped exponential backoff (with jitter) and resends from the oldest unacknowledged
block; the service drops any seq it already has (acknowledged as a duplicate), so nothing is
processed twice. The buffer holds at most `max_buffer_s` seconds of data: past that the oldest
blocks are dropped and counted as lost. Transports: WebSocket (ws.py) or HTTP (http.py); frames go
by HTTP POST (frames.py), only the few newest waiting out an outage. Sessions are opened with the
fleet API key (session.py). See docs/drivers.md.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import math
import random
import time
from collections import deque
from dataclasses import asdict, dataclass
from typing import Literal
from urllib.parse import urlsplit

import httpx

from drivers.blocks import Block, Frame, SampleBlock, TapBlock, encode_binary, encode_json
from drivers.robot.backoff import Backoff
from drivers.robot.frames import FRAME_QUEUE, send_frames
from drivers.robot.http import send_http
from drivers.robot.resend import Pending, ResendBuffer
from drivers.robot.session import SessionInfo, api_key_from_env, open_session
from drivers.robot.ws import send_ws
from drivers.source import SensorSource, check_positive

log = logging.getLogger("drivers.robot")

LOST_LOG_EVERY_S = 5.0


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
    frames_refused: int = 0  # answered 429 (the service's visual queue was full); the newest is sent later

    def as_dict(self) -> dict:
        return asdict(self)


class RobotClient:
    """Streams `source` to the service at `url` (http(s)://host:port[/prefix]).

    session_id + robot_token: stream into an existing session; neither: create one (its operator
    token and console link are kept in `session`). transport "ws" (blocks over one WebSocket,
    up to `window` unacknowledged in flight) or "http" (one POST per block, in order);
    binary=False sends JSON blocks (WebSocket text messages) instead of the binary format. max_buffer_s: seconds of unacknowledged data kept for resending.
    backoff: (first, longest) wait in seconds between reconnection attempts. start_seq: seq of the
    first block (when resuming a session that already has blocks, pass more than its last seq).
    api_key: the fleet API key that opens sessions (default $HAPTICLINK_API_KEY). `run()` closes the source
    when it returns.
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
        api_key: str | None = None,
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
        self.api_key = api_key_from_env(api_key)
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
    async def open_session(self) -> SessionInfo:
        """Create a session (POST /sessions with the fleet API key), retrying while the service is unreachable
        or busy; RobotAuthError for a refused key, ServiceRefused for any other refusal."""
        if self.session_id is not None:
            raise RuntimeError("this client already has a session")
        http = self._http or httpx.AsyncClient(timeout=self.request_timeout_s)
        try:
            info = await open_session(
                http,
                self.url,
                self.api_key,
                self.session_name,
                Backoff(self._block_backoff.base_s, self._block_backoff.cap_s),
            )
        finally:
            if http is not self._http:
                await http.aclose()
        self.session_id, self.robot_token, self.session = info.session_id, info.robot_token, info
        return info

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
        RobotAuthError / ServiceRefused when the service refuses the token or the session.
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
                sender = asyncio.create_task(
                    send_ws(self) if self.transport == "ws" else send_http(self), name="robot-sender"
                )
                framer = asyncio.create_task(send_frames(self), name="robot-frames")
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
                log.error(
                    "%d block(s) (%.1f s of data) were never acknowledged", self.stats.unsent, self._buffer.held_s
                )
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
            log.error(
                "gave up delivering after %.0f s: %d block(s) still unacknowledged, %d frame(s) unsent",
                self.drain_timeout_s,
                len(self._buffer),
                len(self._frames),
            )

    # ---- source → buffer ------------------------------------------------------------------------
    async def _read_source(self) -> None:
        async for item in self.source:
            if isinstance(item, (SampleBlock, TapBlock)):
                self._enqueue_block(item)
            elif isinstance(item, Frame):
                self._enqueue_frame(item)
            else:
                log.warning("source %s yielded a %s; ignored", getattr(self.source, "name", "?"), type(item).__name__)

    def _enqueue_block(self, block: Block) -> None:
        """Number a sample or tap block (one seq sequence for both), encode it and buffer it for sending."""
        seq = self._next_seq
        self._next_seq += 1
        numbered = dataclasses.replace(block, seq=seq)
        payload = encode_binary(numbered) if self.binary else json.dumps(encode_json(numbered)).encode()
        # stream time the block holds (a tap block: none of the stroke's)
        duration = 0.0 if isinstance(block, TapBlock) else max(c.duration_s for c in block.channels.values())
        self.stats.read += 1
        dropped = self._buffer.append(Pending(seq, payload, duration))
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
                log.warning(
                    "the service already had block %d: this session received blocks before; pass start_seq above its last seq",
                    seq,
                )
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
