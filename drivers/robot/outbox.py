"""What the robot client and its transports share: the session's endpoint, the resend buffer, the frame queue,
acknowledgements (settle / reject), the run's counters and the backoffs.

`RobotClient` (client.py) fills an `Outbox` from its source; the transports (ws.py, http.py, frames.py) empty it.
They meet here, so no transport needs the client itself.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import deque
from dataclasses import asdict, dataclass

import httpx

from drivers.blocks import Frame
from drivers.robot.backoff import Backoff
from drivers.robot.resend import Pending, ResendBuffer

log = logging.getLogger("drivers.robot")

LOST_LOG_EVERY_S = 5.0


@dataclass(frozen=True)
class Refresh:
    """A refresh of `frame`: its scene thumbnail (drivers/scene_change.thumbnail_bytes) goes first, and the frame only
    if the service's answer asks for it."""

    frame: Frame
    thumbnail: bytes


FRAME_QUEUE = 4  # frames kept during an outage: the newest matter, older ones are superseded


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
    resumed: int = 0  # new sessions opened after the session was gone (410 / 404: a restarted service)
    saturated: int = 0  # times the service said the session was saturated (429 / close 4429)
    replaced: int = 0  # times a newer ingest socket of the session took this one's place (close 4409)
    frames_read: int = 0
    frames_unchanged: int = 0  # not sent: the scene had not changed since the last frame sent (FrameGate)
    frames_sent: int = 0
    frames_dropped: int = 0  # superseded by newer frames during an outage
    frames_rejected: int = 0
    frames_refused: int = 0  # answered 429 (the service's visual queue was full); the newest is sent later
    refreshes_held: int = 0  # refreshes whose scene check the service answered "held": the frame was not sent

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Endpoint:
    """Where and how the transports deliver: service url, session, robot token and wire options.

    binary: blocks in the binary format (WebSocket binary messages) rather than JSON; window: blocks the
    WebSocket transport keeps in flight unacknowledged; request_timeout_s: per HTTP request / handshake."""

    url: str
    session_id: str
    robot_token: str
    binary: bool = True
    window: int = 64
    request_timeout_s: float = 10.0


class Outbox:
    """Blocks and frames on their way to the service, and what became of them.

    Blocks wait, encoded, in `buffer` (seq order) until acknowledged (`settle`) or refused (`reject`);
    frames wait in `frames` (only the FRAME_QUEUE newest). `blocks_changed` / `frames_changed` wake a
    waiting transport; `draining` says the source has ended (deliver what is left, then return). Counters
    go to `stats`; transports wait `block_backoff` / `frame_backoff` between attempts. `ingest_open` is set while
    the service takes the robot's blocks (its ingest socket accepted, or its last block accepted): frames go only
    then. A session the service has not let start, or sheds, refuses its frames too, and a robot that kept posting
    them would double the requests a replica at capacity has to refuse.
    """

    def __init__(self, max_buffer_s: float, backoff: tuple[float, float], rng, start_seq: int = 0) -> None:
        self.buffer = ResendBuffer(max_buffer_s)
        self.frames: deque[Frame | Refresh] = deque()
        self.blocks_changed = asyncio.Event()
        self.frames_changed = asyncio.Event()
        self.ingest_open = asyncio.Event()
        self.block_backoff = Backoff(*backoff, rng=rng)
        self.frame_backoff = Backoff(*backoff, rng=rng)
        self.stats = RobotStats()
        self.draining = False
        self.http: httpx.AsyncClient | None = None
        self.next_seq = start_seq
        self._max_sent_seq = start_seq - 1
        self._last_lost_log = -math.inf
        self._warned_duplicate_start = False

    # ---- in ---------------------------------------------------------------------------------------
    def add_block(self, payload: bytes, duration_s: float) -> int:
        """Number an encoded block (the next seq, already written in `payload`) and buffer it; returns its seq.
        A full buffer drops its oldest blocks (counted in stats.lost, logged at most every few seconds)."""
        seq = self.next_seq
        self.next_seq += 1
        self.stats.read += 1
        dropped = self.buffer.append(Pending(seq, payload, duration_s))
        if dropped:
            self.stats.lost += len(dropped)
            self.stats.lost_s += sum(d.duration_s for d in dropped)
            now = time.monotonic()
            if now - self._last_lost_log >= LOST_LOG_EVERY_S:
                self._last_lost_log = now
                log.error(
                    "resend buffer full (%.0f s): dropping the oldest blocks — %d lost so far (%.1f s of data); "
                    "the service has been unreachable too long",
                    self.buffer.max_s,
                    self.stats.lost,
                    self.stats.lost_s,
                )
        self.blocks_changed.set()
        return seq

    def add_frame(self, frame: Frame | Refresh) -> None:
        """Queue a frame for sending; past FRAME_QUEUE the oldest is superseded (stats.frames_dropped)."""
        if len(self.frames) >= FRAME_QUEUE:
            self.frames.popleft()
            self.stats.frames_dropped += 1
        self.frames.append(frame)
        self.frames_changed.set()

    def drain(self) -> None:
        """No more blocks or frames will come: the transports deliver what is left and return."""
        self.draining = True
        self.blocks_changed.set()
        self.frames_changed.set()

    # ---- out --------------------------------------------------------------------------------------
    def count_send(self, seq: int) -> None:
        """Block `seq` went on the wire (a resend when it had been sent before)."""
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

    def settle(self, seq: int, duplicate: bool) -> None:
        """The service has block `seq`: everything up to it leaves the buffer."""
        if not self._acknowledges_sent(seq):
            return
        # Earlier entries leave too: the service drops any seq ≤ one it has, so resending them is pointless.
        removed = self.buffer.settle(seq)
        self.stats.acked += len(removed)
        if duplicate and removed and removed[-1].seq == seq:
            self.stats.duplicates += 1
            if self.stats.resent == 0 and not self._warned_duplicate_start:
                self._warned_duplicate_start = True
                log.warning(
                    "the service already had block %d: this session received blocks before; "
                    "pass start_seq above its last seq",
                    seq,
                )
        self.block_backoff.reset()
        self.blocks_changed.set()

    def reject(self, seq: int, why: str) -> None:
        """The service refused block `seq` as bad: drop it, never resend it."""
        if not self._acknowledges_sent(seq):
            return
        removed = self.buffer.settle(seq)
        if removed and removed[-1].seq == seq:
            self.stats.rejected += 1
            self.stats.acked += len(removed) - 1
            log.error("the service rejected block %d: %s (dropped)", seq, why)
        else:
            self.stats.acked += len(removed)
        self.blocks_changed.set()
