"""Camera frames: which ones go (`FrameGate`: only a changed scene, and a refresh), and `POST /sessions/{id}/frames`
(a refresh asks `POST /sessions/{id}/scene` with the frame's thumbnail first); only the few newest wait out an outage
or a busy visual queue."""

from __future__ import annotations

import asyncio
import logging
import random

import httpx
import numpy as np

from drivers.camera import frame_gray
from drivers.protocol import RETRY_STATUSES, SCENE_CONTENT_TYPE, SESSION_LOST, bearer, session_path
from drivers.robot.backoff import detail, retry_after
from drivers.robot.errors import RobotAuthError, session_lost, session_unknown
from drivers.robot.outbox import Endpoint, Outbox, Refresh
from drivers.scene_change import FRAME_CHANGE, scene_changed, thumbnail

log = logging.getLogger("drivers.robot")

FRAME_REFRESH_S = 10.0
#: each refresh comes after refresh_s × (1 + u·REFRESH_JITTER), u uniform in [0, 1) drawn anew
REFRESH_JITTER = 0.25


class FrameGate:
    """Which camera frames a robot sends: one whose scene changed since the last frame sent (drivers/scene_change.py:
    its thumbnail differs by more than `change`), or any once `refresh_s` seconds have passed since then, so that a
    service that did not keep the scene (a frame it rejected, a replica that took the session over) sees it again.
    change=0 sends every frame.

    Why on the robot: the service embeds only a changed scene anyway, but it would decode every frame to find out — a
    robot that looks at one surface at 1 fps would cost it a decode a second for nothing. The service runs its own
    test on what arrives, so the gate saves work and decides nothing.

    The refresh comes `refresh_s` to `refresh_s` × (1 + `jitter`) after the last frame sent, drawn anew each time from
    `rng` (None: seeded by the OS): robots started together would otherwise refresh together, every `refresh_s`,
    and the service would decode a fleet's frames at once. It is due at `refresh_at`, and the robot client sends its
    newest frame then rather than wait for the camera's next one: the cameras of robots started together tick
    together, and at 1 fps a refresh held to the next tick would gather a third of a fleet's refreshes into the same
    quarter of a second.

    `admit(thumb, now)`: thumb is `frame_thumbnail(frame.image)` (None: unreadable, or change=0), now in seconds of
    a monotonic clock. An unreadable frame goes: the service's answer says what is wrong with it."""

    def __init__(
        self,
        change: float = FRAME_CHANGE,
        refresh_s: float = FRAME_REFRESH_S,
        jitter: float = REFRESH_JITTER,
        rng: random.Random | None = None,
    ) -> None:
        if not 0 <= change <= 2:
            raise ValueError(f"frame change must lie in [0, 2] (0: send every frame), got {change!r}")
        if not refresh_s > 0:
            raise ValueError(f"frame refresh must be a positive number of seconds, got {refresh_s!r}")
        if not 0 <= jitter <= 1:
            raise ValueError(f"frame refresh jitter must lie in [0, 1], got {jitter!r}")
        self.change = change
        self.refresh_s = refresh_s
        self.jitter = jitter
        self._rng = rng if rng is not None else random.Random()
        self._sent: np.ndarray | None = None  # thumbnail of the last frame let through
        self._sent_at: float | None = None
        self._refresh_after = refresh_s  # s after the last frame sent, drawn when it went

    @property
    def reads_frames(self) -> bool:
        """Whether admit needs the frames' thumbnails (not when every frame goes)."""
        return self.change > 0

    @property
    def refresh_at(self) -> float | None:
        """When the refresh is due (s, the clock `admit` is given); None before the first frame."""
        return None if self._sent_at is None else self._sent_at + self._refresh_after

    def admit(self, thumb: np.ndarray | None, now: float) -> bool:
        """Send this frame? Remembers it as the scene sent when it goes."""
        due = self._sent_at is None or now >= self._sent_at + self._refresh_after
        if self.reads_frames and thumb is not None and not due and not scene_changed(self._sent, thumb, self.change):
            return False
        self._sent, self._sent_at = thumb, now
        self._refresh_after = self.refresh_s * (1.0 + self.jitter * self._rng.random())
        return True


def frame_thumbnail(image: bytes) -> np.ndarray | None:
    """An encoded frame's scene-change thumbnail (drivers/scene_change.py), or None when it cannot be decoded."""
    try:
        return thumbnail(frame_gray(image))
    except ValueError:
        return None


async def send_frames(endpoint: Endpoint, outbox: Outbox) -> None:
    """Send the outbox's queued frames in order until drained, each once the service takes the robot's blocks
    (`Outbox.ingest_open`); 429 (visual queue full) waits Retry-After and sends the newest. A `Refresh` first asks
    `POST /sessions/{sid}/scene` with the frame's thumbnail, and sends the frame only when the answer wants it (or
    the service cannot check: the frame's own answer then says what is wrong)."""
    http = outbox.http
    assert http is not None
    url = endpoint.url + session_path(str(endpoint.session_id), "frames")
    scene_url = endpoint.url + session_path(str(endpoint.session_id), "scene")
    auth = bearer(str(endpoint.robot_token))
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
        item = frames[0]
        what = "scene check" if isinstance(item, Refresh) else "frame"
        try:
            if isinstance(item, Refresh):
                r = await http.post(
                    scene_url, content=item.thumbnail, headers={**auth, "Content-Type": SCENE_CONTENT_TYPE}
                )
            else:
                r = await http.post(url, content=item.image, headers={**auth, "Content-Type": item.content_type})
        except httpx.TransportError as exc:
            delay = outbox.frame_backoff.next()
            log.warning("POST %s: %s: %s; retrying in %.2f s", what, type(exc).__name__, exc, delay)
            await asyncio.sleep(delay)
            continue
        status = r.status_code
        if status in (401, 403):
            raise RobotAuthError(f"the service refused the robot token for a {what} (HTTP {status}: {detail(r)})")
        if status == SESSION_LOST:
            raise session_lost(endpoint.session_id, detail(r))
        if status == 404:
            raise session_unknown(endpoint.session_id, detail(r))
        if status == 429 or status >= 500 or status in RETRY_STATUSES:
            outbox.stats.frames_refused += status == 429 and not isinstance(item, Refresh)
            delay = outbox.frame_backoff.next(retry_after(r) if status == 429 else None)
            await asyncio.sleep(delay)
            continue
        if isinstance(item, Refresh):
            if frames and frames[0] is item:  # else a newer frame superseded it meanwhile
                if status == 200 and not _frame_needed(r):
                    frames.popleft()
                    outbox.stats.refreshes_held += 1
                    outbox.frame_backoff.reset()
                else:
                    frames[0] = item.frame
            continue
        if frames and frames[0] is item:
            frames.popleft()
        else:  # add_frame superseded it while it was on its way, and counted it dropped; but it arrived
            outbox.stats.frames_dropped -= 1
        if 200 <= status < 300:
            outbox.stats.frames_sent += 1
            outbox.frame_backoff.reset()
        else:
            outbox.stats.frames_rejected += 1
            log.error("the service rejected a frame (%s): HTTP %d: %s", item.content_type, status, detail(r))


def _frame_needed(r: httpx.Response) -> bool:
    """A scene check's answer: does the service want the frame? (Yes, when the answer cannot be read.)"""
    try:
        return bool(r.json()["frame_needed"])
    except (ValueError, KeyError, TypeError):
        return True
