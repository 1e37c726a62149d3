"""A restart of the service under a fleet: the `restart` object of reports/bench/hostile.json.

Run from the repository root:  python -m benchmarks.hostile --only restart [--restart-robots 8]
                                   [--restart-stream-s 20]

One service process on a loopback port serves `--restart-robots` real `RobotClient`s (simulated strokes in real
time, each with its own robot id), each followed by an operator by the robot's id (`WS /robots/{id}/events` with the
fleet API key: every event of the robot's sessions, one after another), never by a session id. A few seconds in, the
service gets SIGTERM and a new process starts on the same port. Reported:

- robots: how many streamed; robots_resumed: how many opened a new session after the restart and had a block
  acknowledged in it; resume_s_max: the slowest of those, from the new process's first 200 on /ready (polled every
  20 ms) to that acknowledgement;
- operators_followed: robots whose follower received windows of the new session with no action;
- acked_blocks_lost: blocks the service acknowledged whose samples no window event covers (the old and the new
  session's windows together), between the first window's start and the last window's end its follower received;
- windows_duplicated: window events of one robot stamped with the same start (robot clock) more than once;
- robot_exits: runs that ended with an error (the robot command never exits because of a restart).
"""

from __future__ import annotations

import asyncio
import json
import signal
import threading
import time
from dataclasses import dataclass, field

import httpx
from websockets.asyncio.client import connect

from benchmarks.service import Assets, ServerProcess
from drivers.robot import RobotClient
from drivers.simulated import SimulatedSource
from service.launcher import free_port
from texture_library.library import Library

BLOCK_S = 0.25  # the robot client's default block
FOLLOW_GRACE_S = 3.0  # the followers listen this long after the robots are done


@dataclass
class Follower:
    """What one robot's follower saw: window (start, end) on the robot's clock per session, in arrival order."""

    robot: str
    sessions: list[str] = field(default_factory=list)
    windows: list[tuple[str, float, float]] = field(default_factory=list)


@dataclass
class RobotRun:
    robot: str
    acked: set[int] = field(default_factory=set)
    sessions: list[tuple[str, float]] = field(default_factory=list)  # (session id, wall time opened)
    first_ack_after: dict[str, float] = field(default_factory=dict)  # session id → wall time of its first ack
    error: str | None = None


async def follow(url: str, api_key: str, f: Follower) -> None:
    """Follow robot f.robot by its id until cancelled: `WS /robots/{id}/events` with the fleet API key carries every
    event of the robot's sessions, one after another; reconnected after a restart (every 0.1 s)."""
    feed = f"{url.replace('http', 'ws', 1)}/robots/{f.robot}/events?token={api_key}"
    while True:
        try:
            async with connect(feed, open_timeout=10, max_size=1 << 20) as ws:
                async for message in ws:
                    event = json.loads(message)
                    if event.get("type") == "window":
                        sid = str(event["session_id"])
                        if sid not in f.sessions:
                            f.sessions.append(sid)
                        f.windows.append((sid, float(event["t_start_s"]), float(event["t_end_s"])))
        except Exception:  # noqa: BLE001 - the service restarting: connect again
            await asyncio.sleep(0.1)


async def stream(url: str, api_key: str, library, entry: str, run: RobotRun, seconds: float, seed: int) -> None:
    """One robot: a RobotClient over a simulated stroke, its acknowledgements and sessions recorded."""
    source = SimulatedSource(library.model(entry), seed=seed, block_s=BLOCK_S, realtime=True, duration_s=seconds)
    client = RobotClient(
        url,
        source,
        api_key=api_key,
        robot_id=run.robot,
        seed=seed,
        on_session=lambda info: run.sessions.append((info.session_id, time.time())),
    )
    buffer = client.outbox.buffer
    settle = buffer.settle

    def settled(seq: int):
        removed = settle(seq)
        run.acked.update(p.seq for p in removed)
        if removed and run.sessions and run.sessions[-1][0] not in run.first_ack_after:
            run.first_ack_after[run.sessions[-1][0]] = time.time()
        return removed

    buffer.settle = settled  # type: ignore[method-assign]
    try:
        await client.run()
    except Exception as exc:  # noqa: BLE001 - reported: a robot must not end because of a restart
        run.error = f"{type(exc).__name__}: {exc}"


def run_restart(assets: Assets, api_key: str, robots: int, stream_s: float, kill_after_s: float = 3.0) -> dict:
    """The restart case (see the module docstring) → the report's `restart` object. The service is stopped
    kill_after_s after every robot has had blocks acknowledged."""
    port = free_port()
    library = Library.load(assets.library)
    entries = library.ids
    runs = [RobotRun(f"restart-robot-{k}") for k in range(robots)]
    followers = [Follower(r.robot) for r in runs]
    url = f"http://127.0.0.1:{port}"
    first = _serve(assets, api_key, port)

    async def fleet() -> None:
        following = [asyncio.create_task(follow(url, api_key, f)) for f in followers]
        await asyncio.gather(
            *(stream(url, api_key, library, entries[k % len(entries)], r, stream_s, k) for k, r in enumerate(runs))
        )
        await asyncio.sleep(FOLLOW_GRACE_S)  # the last windows reach the followers
        for task in following:
            task.cancel()
        await asyncio.gather(*following, return_exceptions=True)

    thread = threading.Thread(target=lambda: asyncio.run(fleet()), daemon=True)
    thread.start()
    second = None
    try:
        deadline = time.time() + 120
        while time.time() < deadline and not all(r.sessions and len(r.acked) >= 4 for r in runs):
            time.sleep(0.1)  # every robot streams in a session of the first process before it is stopped
        time.sleep(kill_after_s)
        first.proc.send_signal(signal.SIGTERM)
        first.proc.wait(timeout=30)
        killed_at = time.time()
        ready: list[float] = []
        poller = threading.Thread(target=_first_ready, args=(url, ready), daemon=True)
        poller.start()
        second = _serve(assets, api_key, port)
        poller.join(timeout=30)
        ready_at = ready[0] if ready else time.time()
        thread.join(timeout=stream_s + 180)
    finally:
        for server in (first, second):
            if server is not None and server.proc.poll() is None:
                server.stop(signal.SIGTERM)
    resumed = [r for r in runs if len(r.sessions) > 1 and r.sessions[-1][0] in r.first_ack_after]
    resume_s = [r.first_ack_after[r.sessions[-1][0]] - ready_at for r in resumed]
    lost = duplicated = followed = 0
    missed: list[tuple[str, int]] = []
    for r, f in zip(runs, followers, strict=True):
        starts = [round(s, 6) for _, s, _ in f.windows]
        duplicated += len(starts) - len(set(starts))
        if resumed and any(sid == r.sessions[-1][0] for sid, _, _ in f.windows):
            followed += 1
        # between the first window's start (the service skips the stream's first skip_s) and the last one's end
        first_start = min((s for _, s, _ in f.windows), default=0.0)
        last_end = max((e for _, _, e in f.windows), default=0.0)
        for seq in r.acked:
            t0, t1 = seq * BLOCK_S, (seq + 1) * BLOCK_S
            if first_start <= t0 and t1 <= last_end and not any(s < t1 and t0 < e for _, s, e in f.windows):
                lost += 1
                missed.append((r.robot, seq))
    return {
        "robots": robots,
        "robots_resumed": len(resumed),
        "resume_s_max": round(max(resume_s), 2) if resume_s else None,
        "down_s": round(ready_at - killed_at, 1),
        "operators_followed": followed,
        "acked_blocks": sum(len(r.acked) for r in runs),
        "acked_blocks_lost": lost,
        "windows": sum(len(f.windows) for f in followers),
        "windows_duplicated": duplicated,
        "acked_blocks_lost_first": missed[:10],
        "robot_exits": [r.error for r in runs if r.error][:5],
        "stream_s": stream_s,
        "kill_after_s": kill_after_s,
    }


def _first_ready(url: str, out: list[float], every_s: float = 0.02, timeout_s: float = 300.0) -> None:
    """Append the wall time of the first 200 on url/ready, polled every `every_s`."""
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        try:
            if httpx.get(f"{url}/ready", timeout=1).status_code == 200:
                out.append(time.time())
                return
        except httpx.HTTPError:
            pass
        time.sleep(every_s)


def _serve(assets: Assets, api_key: str, port: int) -> ServerProcess:
    """The service on `port`, once its /ready answers 200."""
    return ServerProcess.service(assets, api_key, instance_id="restart", port=port)
