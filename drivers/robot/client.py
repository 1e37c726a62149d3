"""The robot-side client: streams a sensor source to the hapticlink service, losing nothing to short outages.

Blocks (sample blocks and tap blocks alike) get consecutive sequence numbers and wait, encoded, in an ordered
resend buffer (drivers/robot/resend.py) until the service acknowledges them. When the connection fails the
client reconnects with capped exponential backoff (with jitter) and resends from the oldest unacknowledged
block; the service drops any seq it already has (acknowledged as a duplicate), so nothing is processed twice.
The buffer holds at most `max_buffer_s` seconds of data: past that the oldest blocks are dropped and counted
as lost. Transports: WebSocket (ws.py) or HTTP (http.py); frames go by HTTP POST (frames.py), only the few
newest waiting out an outage. The client fills, and the transports empty, one `Outbox` (outbox.py): buffer,
frame queue, acknowledgements, counters, backoffs. Sessions are opened with the fleet API key (session.py).
See docs/drivers.md.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import random
from collections.abc import Callable
from typing import Literal

import httpx
import numpy as np

from drivers.blocks import Block, Frame, SampleBlock, TapBlock, encode_binary, encode_json
from drivers.protocol import check_service_url
from drivers.robot.backoff import Backoff
from drivers.robot.errors import ServiceUnavailable, SessionGone
from drivers.robot.frames import FRAME_REFRESH_S, FrameGate, frame_thumbnail, send_frames
from drivers.robot.http import send_http
from drivers.robot.outbox import Endpoint, Outbox, Refresh, RobotStats
from drivers.robot.session import SessionInfo, api_key_from_env, open_session
from drivers.robot.ws import send_ws
from drivers.scene_change import FRAME_CHANGE, thumbnail_bytes
from drivers.source import SensorSource, check_positive

log = logging.getLogger("drivers.robot")

#: seconds a stopped device source has to hand over what it already read (its reader thread sees a stop within
#: 0.1 s) before its reading is cancelled
FINISH_S = 1.0

__all__ = ["RobotClient", "RobotStats"]


class RobotClient:
    """Streams `source` to the service at `url` (http(s)://host:port[/prefix]).

    session_id + robot_token: stream into an existing session; neither: create one once the source has given its
    first item (a device that does not open ends the run before any session exists; its operator token and console
    link are kept in `session`, and given to `on_session`). transport "ws" (blocks over one WebSocket,
    up to `window` unacknowledged in flight) or "http" (one POST per block, in order);
    binary=False sends JSON blocks (WebSocket text messages) instead of the binary format. max_buffer_s: seconds
    of unacknowledged data kept for resending.
    backoff: (first, longest) wait in seconds between reconnection attempts. start_seq: seq of the
    first block (when resuming a session that already has blocks, pass more than its last seq).
    api_key: the fleet API key that opens sessions (default $HAPTICLINK_API_KEY). open_timeout_s: how long
    opening a session may keep retrying an unreachable or not-ready service before ServiceUnavailable (None:
    for ever). frame_change, frame_refresh_s: a camera frame is sent only when its scene changed by more than
    frame_change since the last frame sent, or frame_refresh_s after it, up to a quarter more (drawn anew each time;
    drivers/robot/frames.py's `FrameGate`; frame_change=0 sends every frame). `run()` closes the source when it returns.

    What the transports share with the client — the resend buffer, the frame queue, acknowledgements,
    counters and backoffs — is `outbox` (drivers/robot/outbox.py); `stats` is its counters.
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
        backoff: tuple[float, float] = (0.2, 2.0),
        session_name: str | None = None,
        start_seq: int = 0,
        window: int = 64,
        drain_timeout_s: float = 30.0,
        request_timeout_s: float = 10.0,
        seed: int | None = None,
        api_key: str | None = None,
        open_timeout_s: float | None = 60.0,
        frame_change: float = FRAME_CHANGE,
        frame_refresh_s: float = FRAME_REFRESH_S,
        on_session: Callable[[SessionInfo], None] | None = None,
        robot_id: str | None = None,
    ) -> None:
        check_service_url(url)
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
        if open_timeout_s is not None:
            check_positive("open_timeout_s", open_timeout_s)
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
        self.open_timeout_s = open_timeout_s
        self.outbox = Outbox(max_buffer_s, backoff, random.Random(seed), start_seq)
        self.frame_gate = FrameGate(frame_change, frame_refresh_s)
        self.on_session = on_session  # told each session run() opens (where its operators can watch)
        self.robot_id = robot_id
        # the newest frame read and its thumbnail: what a refresh sends, and a repeat of its bytes is not decoded again
        self._newest: tuple[Frame, np.ndarray | None] | None = None
        self._refresh: asyncio.TimerHandle | None = None  # sends the newest frame when the gate's refresh is due
        self._stopping = False
        self._ran = False
        self._reader: asyncio.Task | None = None
        self._first_item = asyncio.Event()  # the source has given something (its device opened)
        self._stop_asked = asyncio.Event()  # stop() was called: a session still being opened gets drain_timeout_s

    @property
    def stats(self) -> RobotStats:
        """The run's counters (live while it runs)."""
        return self.outbox.stats

    # ---- session ------------------------------------------------------------------------------
    async def open_session(self, first_seq: int = 0, forever: bool = False) -> SessionInfo:
        """Create a session (POST /sessions with the fleet API key), retrying while the service is unreachable
        or busy for at most open_timeout_s (forever: for ever; then ServiceUnavailable); RobotAuthError for a refused
        key, ServiceRefused for any other refusal. first_seq: its first block's seq."""
        if self.session_id is not None:
            raise RuntimeError("this client already has a session")
        http = self.outbox.http or httpx.AsyncClient(timeout=self.request_timeout_s)
        backoff = self.outbox.block_backoff
        try:
            info = await open_session(
                http,
                self.url,
                self.api_key,
                self.session_name,
                Backoff(backoff.base_s, backoff.cap_s),
                timeout_s=None if forever else self.open_timeout_s,
                robot=self.robot_id,
                first_seq=first_seq,
            )
        finally:
            if http is not self.outbox.http:
                await http.aclose()
        self.session_id, self.robot_token, self.session = info.session_id, info.robot_token, info
        return info

    # ---- run ----------------------------------------------------------------------------------
    def stop(self) -> None:
        """Stop reading the source; run() then delivers what is buffered (up to drain_timeout_s) and returns."""
        self._stopping = True
        self._stop_asked.set()
        reader = self._reader
        if reader is None or reader.done():
            return
        finish = getattr(self.source, "finish", None)
        if callable(finish):  # a device source: what it already sent (its partial block) comes out first
            finish()
            reader.get_loop().call_later(FINISH_S, reader.cancel)  # however slowly its thread ends
        else:
            reader.cancel()

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
        outbox = self.outbox
        tasks: list[asyncio.Task] = []
        timer = None
        try:
            async with httpx.AsyncClient(timeout=self.request_timeout_s) as http:
                outbox.http = http
                self._reader = asyncio.create_task(self._read_source(), name="robot-reader")
                tasks = [self._reader]
                if self._stopping:
                    self._reader.cancel()
                if duration_s is not None:  # from the start: an unreachable service does not stretch the reading
                    timer = loop.call_later(duration_s, self.stop)
                if self.session_id is None:
                    await self._source_started()
                    info = await self._open_until_stopped()
                    if self.on_session is not None:
                        self.on_session(info)
                while True:
                    sender, framer = self._start_senders()
                    tasks = [self._reader, sender, framer]
                    try:
                        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
                        for task in (sender, framer):
                            if task.done():
                                task.result()  # they end early only on a fatal error: raise it
                        await asyncio.wait([self._reader])
                        source_error = None if self._reader.cancelled() else self._reader.exception()
                        await self._drain(sender, framer)  # what was read before a source failed still goes out
                    except SessionGone as exc:
                        if self.api_key is None:  # no key, no new session: the run ends with its error
                            raise
                        for task in (sender, framer):
                            task.cancel()
                        await asyncio.gather(sender, framer, return_exceptions=True)
                        await self._resume(exc)
                        continue
                    if source_error is not None:
                        raise source_error
                    break
        finally:
            if timer is not None:
                timer.cancel()
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await self.source.aclose()
            outbox.http = None
            self.stats.unsent = len(outbox.buffer)
            if self.stats.unsent:
                log.error(
                    "%d block(s) (%.1f s of data) were never acknowledged", self.stats.unsent, outbox.buffer.held_s
                )
        return self.stats

    def _start_senders(self) -> tuple[asyncio.Task, asyncio.Task]:
        """The block and frame senders of the current session."""
        endpoint = Endpoint(
            self.url,
            str(self.session_id),
            str(self.robot_token),
            binary=self.binary,
            window=self.window,
            request_timeout_s=self.request_timeout_s,
        )
        send_blocks = send_ws if self.transport == "ws" else send_http
        sender = asyncio.create_task(send_blocks(endpoint, self.outbox), name="robot-sender")
        framer = asyncio.create_task(send_frames(endpoint, self.outbox), name="robot-frames")
        return sender, framer

    async def _resume(self, gone: SessionGone) -> None:
        """The session is gone (a restarted or stopped replica): open a new one that goes on with this robot's
        numbering from the oldest unacknowledged block, which is resent with everything after it. Opening retries
        for ever (a restart takes as long as it takes), until stop()."""
        outbox = self.outbox
        first_seq = outbox.buffer.oldest_seq if outbox.buffer.oldest_seq is not None else outbox.next_seq
        log.warning(
            "%s; opening a new session and resending %d unacknowledged block(s) from seq %d",
            gone,
            len(outbox.buffer),
            first_seq,
        )
        outbox.ingest_open.clear()
        self.session_id = self.robot_token = None
        info = await self._open_until_stopped(first_seq, forever=True)
        self.stats.resumed += 1
        log.info("resumed in session %s", info.session_id)
        if self.on_session is not None:
            self.on_session(info)

    async def _open_until_stopped(self, first_seq: int = 0, *, forever: bool = False) -> SessionInfo:
        """open_session, which retries an unreachable service for up to open_timeout_s (forever: for ever); once
        stop() is called (a Ctrl-C, the --duration) it gets drain_timeout_s more, as delivering what is buffered
        would."""
        opening = asyncio.create_task(self.open_session(first_seq, forever))
        stopped = asyncio.create_task(self._stop_asked.wait())
        try:
            await asyncio.wait({opening, stopped}, return_when=asyncio.FIRST_COMPLETED)
            if not opening.done():
                await asyncio.wait({opening}, timeout=self.drain_timeout_s)
            if not opening.done():
                raise ServiceUnavailable(
                    f"stopped, and no session could be opened at {self.url} within the {self.drain_timeout_s:g} s "
                    "given to deliver what was read (is the service running, and does its /ready answer 200?)"
                )
            return opening.result()
        finally:
            for task in (opening, stopped):
                task.cancel()
            await asyncio.gather(opening, stopped, return_exceptions=True)

    async def _source_started(self) -> None:
        """Wait until the source has given its first item, or ended: a device that does not open (a wrong serial
        port, a missing DAQ) ends the run with its error here, before a session is opened that nothing would reach.
        A source that gave items and then failed, or was stopped, has its items delivered as ever (a session is
        opened for them, and run() raises its error after)."""
        assert self._reader is not None
        first = asyncio.create_task(self._first_item.wait())
        try:
            await asyncio.wait({first, self._reader}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            first.cancel()
        failed = self._reader.done() and not self._reader.cancelled() and self._reader.exception() is not None
        if failed and not self._first_item.is_set():
            raise self._reader.exception()  # type: ignore[misc]

    async def _drain(self, sender: asyncio.Task, framer: asyncio.Task) -> None:
        """Let the senders deliver what is buffered, for at most drain_timeout_s; a sender's fatal error (a lost
        session, a refused token) ends it at once: the other may wait for ever for an ingest that never opens again."""
        self.outbox.drain()
        done, pending = await asyncio.wait(
            [sender, framer], timeout=self.drain_timeout_s, return_when=asyncio.FIRST_EXCEPTION
        )
        for task in done:
            task.result()
        if pending:
            log.error(
                "gave up delivering after %.0f s: %d block(s) still unacknowledged, %d frame(s) unsent",
                self.drain_timeout_s,
                len(self.outbox.buffer),
                len(self.outbox.frames),
            )

    # ---- source → buffer ------------------------------------------------------------------------
    async def _read_source(self) -> None:
        try:
            async for item in self.source:
                self._first_item.set()
                if isinstance(item, (SampleBlock, TapBlock)):
                    self._enqueue_block(item)
                elif isinstance(item, Frame):
                    await self._enqueue_frame(item)
                else:
                    log.warning(
                        "source %s yielded a %s; ignored", getattr(self.source, "name", "?"), type(item).__name__
                    )
        finally:  # no refresh of a camera that has stopped
            if self._refresh is not None:
                self._refresh.cancel()
                self._refresh = None

    def _enqueue_block(self, block: Block) -> None:
        """Number a sample or tap block (one seq sequence for both), encode it and buffer it for sending."""
        numbered = dataclasses.replace(block, seq=self.outbox.next_seq)
        payload = encode_binary(numbered) if self.binary else json.dumps(encode_json(numbered)).encode()
        # stream time the block holds (a tap block: none of the stroke's)
        duration = 0.0 if isinstance(block, TapBlock) else max(c.duration_s for c in block.channels.values())
        self.outbox.add_block(payload, duration)

    async def _enqueue_frame(self, frame: Frame) -> None:
        """Queue a frame for sending if its scene changed (or is due again); decoded in a thread, off the loop, unless
        its bytes repeat the last frame's (a file or a simulated camera)."""
        self.stats.frames_read += 1
        gate = self.frame_gate
        thumb = None
        if gate.reads_frames:
            if self._newest is not None and self._newest[0].image == frame.image:
                thumb = self._newest[1]
            else:
                thumb = await asyncio.to_thread(frame_thumbnail, frame.image)
        self._newest = (frame, thumb)
        if gate.admit(thumb, asyncio.get_running_loop().time()):
            self._send_frame(frame)
        else:
            self.stats.frames_unchanged += 1

    def _send_frame(self, frame: Frame | Refresh) -> None:
        """Queue a frame the gate let through, and time the next refresh from it."""
        self.outbox.add_frame(frame)
        self._time_refresh()

    def _time_refresh(self) -> None:
        if self._refresh is not None:
            self._refresh.cancel()
        at = self.frame_gate.refresh_at
        self._refresh = None if at is None else asyncio.get_running_loop().call_at(at, self._refresh_due)

    def _refresh_due(self) -> None:
        """The refresh is due: the newest frame goes now, not with the camera's next frame (FrameGate)."""
        self._refresh = None
        assert self._newest is not None  # timed only once a frame was sent
        frame, thumb = self._newest
        if self.frame_gate.admit(thumb, asyncio.get_running_loop().time()):
            # the service decodes a frame to learn its scene; the thumbnail (2 kB) tells it without a decode
            self._send_frame(frame if thumb is None else Refresh(frame, thumbnail_bytes(thumb)))
        else:  # woken a hair early (the loop's clock resolution)
            self._time_refresh()
