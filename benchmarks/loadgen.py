"""A load generator that does not fall behind unseen: robots and their operators spread over processes,
blocks encoded before the clock starts, and each process's own send lag measured.

`run_generators(plan)` starts `plan.generators` processes. Each renders its share of the robots' streams,
encodes every block (binary format, seq from 0) and, before the common start instant, opens the robots'
sessions (the fleet key), their ingest WebSockets and an operator's events WebSocket per session. From the
start instant each robot sends block k when its span has ended (start + offset + k·block_s; a tap block, when
the model reads taps, at once), a camera frame every `frame_every_s` when the configuration has frames — by HTTP
POST when the robot client's `FrameGate` lets it go (its scene changed; or, at the moment it is due and as the
client does, its jittered `frame_refresh_s` refresh, which first asks with the thumbnail and sends the frame only if
the service wants it; a robot's photo never changes, so its thumbnail is computed once) — and reads its
acknowledgements; the operator stamps every window event against the moment the block that completed it left the
generator (one clock: CLOCK_MONOTONIC, shared by the processes).

What comes back, per process: the send lag of every block (ms: how late after its due instant it went out —
the generator's own delay, which a valid measurement keeps small), end-to-end latencies (ms) and when each
window's block left (s after the start), the windows' stage latencies, windows received, acknowledgements,
refusals (ok:false answers, 4429 closes, frame 429s), failures, and the process's CPU time over the streaming
phase.

Lean on purpose: no RobotClient (its per-block encoding, buffering and resend logic are the robot's cost, not
the service's); a robot whose connection fails stops, and its remaining windows count as lost.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import multiprocessing as mp
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drivers.blocks import Block, encode_binary
from drivers.camera import sniff_content_type
from drivers.robot.backoff import retry_after
from drivers.robot.frames import FRAME_REFRESH_S, REFRESH_JITTER, FrameGate, frame_thumbnail
from drivers.scene_change import FRAME_CHANGE, thumbnail_bytes
from drivers.simulated import tap_block
from drivers.source import blocks_from_arrays
from texture_library.library import Library
from texture_library.stroke import stroke
from texture_library.trajectory import freehand, model_ranges

STAGES = ("queue", "features", "model", "lookup", "total")
SETUP_S = 1.0  # after every process is connected, before the first block is due
TAIL_S = 10.0  # after the last block, how long a generator waits for the windows still in flight


@dataclass(frozen=True)
class Plan:
    """What to generate: robots k = 0 … robots−1 (robot k streams texture k mod the library's size, to replica
    k mod len(urls)), each `duration_s` of stream in `block_s` blocks, spread over `generators` processes."""

    urls: tuple[str, ...]
    library: Path
    api_key: str
    robots: int
    duration_s: float
    block_s: float
    generators: int
    seed: int = 0
    taps: bool = False
    frames: bool = False
    frame_every_s: float = 1.0
    frame_change: float = FRAME_CHANGE  # the robot client's FrameGate; 0: every frame goes
    frame_refresh_s: float = FRAME_REFRESH_S
    frame_refresh_jitter: float = REFRESH_JITTER
    hop_s: float = 0.5


@dataclass
class GeneratorResult:
    """One process's measurements (plain lists and numbers: it crosses a pipe)."""

    robots: int = 0
    send_lag_ms: list[float] = field(default_factory=list)
    e2e_ms: list[float] = field(default_factory=list)
    e2e_sent_s: list[float] = field(default_factory=list)  # when each e2e_ms window's block left, s after the start
    stages_ms: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in STAGES})
    first_features_ms: list[float] = field(default_factory=list)
    windows: int = 0
    windows_tactile_only: int = 0
    blocks_sent: int = 0
    blocks_acked: int = 0
    blocks_refused: int = 0  # ok:false answers (a refused block is not resent here)
    saturated_closes: int = 0  # ingest sockets closed 4429
    frames_sent: int = 0  # let through by the gate and answered other than 429
    frames_unchanged: int = 0  # kept back by the robot's FrameGate
    frames_refused: int = 0
    refreshes_held: int = 0  # refreshes whose scene check the service answered "held" (no frame sent)
    failures: list[str] = field(default_factory=list)
    cpu_s: float = 0.0  # this process's CPU time over the streaming phase
    wall_s: float = 0.0


def robot_streams(
    library_dir: Path,
    n_streams: int,
    seconds: float,
    block_s: float,
    seed: int = 0,
    taps: bool = False,
    indices: list[int] | None = None,
) -> list[list[Block]]:
    """n_streams block sequences (seq from 0), each `seconds` long, over the library's textures; with `taps`
    each starts with its texture's tap block, as a robot serving a model that reads tap features does.
    indices: render robots `indices` (robot k: texture k mod the library's size, seed (seed, k)) instead of
    0 … n_streams − 1."""
    lib = Library.load(library_dir)
    out = []
    for k in range(n_streams) if indices is None else indices:
        model = lib.model(lib.ids[k % len(lib.ids)])
        head: list[Block] = [tap_block(model)] if taps else []
        rng = np.random.default_rng([seed, k])
        traj = freehand(seconds + 0.5, rng, rate_hz=model.rate_hz, **model_ranges(model.max_speed, model.max_force))
        s = stroke(model, traj, rng)
        n = int(round(seconds * s.rate_hz))
        channels = {
            "accel": (s.accel[:n], s.rate_hz, "m/s^2"),
            "force": (s.force[:n], s.rate_hz, "N"),
            "speed": (s.speed[:n], s.rate_hz, "mm/s"),
        }
        out.append(head + list(blocks_from_arrays(channels, block_s)))
    return out


def frame_of(library_dir: Path, k: int) -> bytes:
    """The photo of robot k's texture (encoded), its camera frame."""
    lib = Library.load(library_dir)
    image = lib.image(lib.ids[k % len(lib.ids)])
    if image is None:
        raise ValueError(
            f"library {library_dir} has no image for {lib.ids[k % len(lib.ids)]}: the served configuration needs one"
        )
    return image


def frame_content_type(image: bytes) -> str:
    """The Content-Type a frame's bytes call for: the service refuses a PNG labelled JPEG and the reverse (415)."""
    kind = sniff_content_type(image)
    if kind is None:
        raise ValueError(f"a frame must be a PNG or a JPEG; these bytes begin {image[:8]!r}")
    return kind


def encoded_streams(plan: Plan, ks: list[int]) -> list[list[bytes]]:
    """Robot k's blocks (a tap block first when plan.taps), binary-encoded with seq from 0."""
    streams = robot_streams(plan.library, len(ks), plan.duration_s, plan.block_s, plan.seed, plan.taps, indices=ks)
    return [[encode_binary(dataclasses.replace(b, seq=i)) for i, b in enumerate(blocks)] for blocks in streams]


class Robot:
    """One robot and its operator on open connections."""

    def __init__(self, k: int, payloads: list[bytes], taps: bool, frame: bytes | None) -> None:
        self.k, self.payloads, self.taps, self.frame = k, payloads, taps, frame
        # the scene-change thumbnail of its one photo, before the clock starts
        self.frame_thumb = frame_thumbnail(frame) if frame is not None else None
        self.sent_at: dict[int, float] = {}
        self.session: dict | None = None
        self.ingest = None
        self.events = None


async def _open(robot: Robot, url: str, api_key: str, http) -> None:
    from websockets.asyncio.client import connect

    from drivers.protocol import bearer, ws_url

    r = await http.post(f"{url}/sessions", json={"name": f"bench-{robot.k}"}, headers=bearer(api_key))
    r.raise_for_status()
    robot.session = r.json()
    sid = robot.session["session_id"]
    robot.events = await connect(
        ws_url(url, sid, "events", robot.session["operator_token"]), max_size=2**20, open_timeout=60
    )
    await robot.events.recv()  # "subscribed"
    robot.ingest = await connect(
        ws_url(url, sid, "ingest", robot.session["robot_token"]), max_size=2**20, open_timeout=60, compression=None
    )


async def _send(robot: Robot, start: float, block_s: float, out: GeneratorResult) -> None:
    from websockets.exceptions import ConnectionClosed

    from drivers.protocol import Close

    try:
        n = 0
        for i, payload in enumerate(robot.payloads):
            if not (robot.taps and i == 0):  # a tap block holds no stream time: it leaves at once
                n += 1
                due = start + n * block_s  # a block leaves when its span has ended
                delay = due - time.perf_counter()
                if delay > 0:
                    await asyncio.sleep(delay)
                now = time.perf_counter()
                out.send_lag_ms.append(max(0.0, now - due) * 1e3)
            robot.sent_at[i] = time.perf_counter()
            await robot.ingest.send(payload)
            out.blocks_sent += 1
    except ConnectionClosed as exc:
        if exc.rcvd is not None and exc.rcvd.code == Close.SATURATED:
            out.saturated_closes += 1
        out.failures.append(f"robot {robot.k}: ingest closed after {out.blocks_sent} blocks: {exc}")


async def _acks(robot: Robot, out: GeneratorResult) -> None:
    from websockets.exceptions import ConnectionClosed

    from drivers.protocol import parse_ack

    try:
        async for message in robot.ingest:
            ack = parse_ack(message)
            if ack.ok:
                out.blocks_acked += 1
            else:
                out.blocks_refused += 1
    except ConnectionClosed:
        pass


async def _operate(robot: Robot, start: float, out: GeneratorResult) -> None:
    from websockets.exceptions import ConnectionClosed

    first = True
    try:
        async for message in robot.events:
            now = time.perf_counter()
            if '"type":"window"' not in message[:20]:
                continue
            event = json.loads(message)
            out.windows += 1
            out.windows_tactile_only += event["inputs"] == "tactile"
            sent = robot.sent_at.get(event["block_seq"])
            if sent is not None:
                out.e2e_ms.append((now - sent) * 1e3)
                out.e2e_sent_s.append(sent - start)
            for stage in STAGES:
                out.stages_ms[stage].append(event["latency_ms"][stage])
            if first:
                out.first_features_ms.append(event["latency_ms"]["features"])
                first = False
    except ConnectionClosed:
        pass


async def _frames(robot: Robot, url: str, http, start: float, plan: Plan, out: GeneratorResult) -> None:
    from drivers.protocol import SCENE_CONTENT_TYPE, bearer, session_path

    assert robot.session is not None and robot.frame is not None
    target = url + session_path(robot.session["session_id"], "frames")
    headers = {**bearer(robot.session["robot_token"]), "Content-Type": frame_content_type(robot.frame)}
    scene_target = url + session_path(robot.session["session_id"], "scene")
    scene_headers = {**bearer(robot.session["robot_token"]), "Content-Type": SCENE_CONTENT_TYPE}
    # as a robot's own gate, with its refresh jitter seeded per robot
    gate = FrameGate(
        plan.frame_change, plan.frame_refresh_s, plan.frame_refresh_jitter, random.Random(f"{plan.seed}:{robot.k}")
    )
    k = 0
    while True:
        # the camera's next frame, or the refresh the robot client sends on time with its newest frame
        tick = start + k * plan.frame_every_s
        refresh = gate.refresh_at
        due = tick if refresh is None else min(tick, refresh)
        if due >= start + plan.duration_s:
            break
        delay = due - time.perf_counter()
        if delay > 0:
            await asyncio.sleep(delay)
        k += due == tick
        if not gate.admit(robot.frame_thumb, due):
            out.frames_unchanged += 1
            continue
        if due == refresh and robot.frame_thumb is not None:  # as the client does: the thumbnail asks first
            check = await http.post(scene_target, content=thumbnail_bytes(robot.frame_thumb), headers=scene_headers)
            if check.status_code == 200 and not check.json()["frame_needed"]:
                out.refreshes_held += 1
                continue
        # as the robot client does: a frame refused with 429 (the visual queue was full) goes again after Retry-After
        while (r := await http.post(target, content=robot.frame, headers=headers)).status_code == 429:
            out.frames_refused += 1
            if time.perf_counter() >= start + plan.duration_s:
                break
            await asyncio.sleep(retry_after(r) or 1.0)
        else:
            out.frames_sent += 1


async def _generate(plan: Plan, ks: list[int], conn) -> GeneratorResult:
    import httpx

    out = GeneratorResult(robots=len(ks))
    payloads = encoded_streams(plan, ks)
    frames: list[bytes | None] = [None] * len(ks)
    if plan.frames:
        frames = [frame_of(plan.library, k) for k in ks]
    robots = [Robot(k, p, plan.taps, f) for k, p, f in zip(ks, payloads, frames)]
    urls = [plan.urls[k % len(plan.urls)] for k in ks]
    limits = httpx.Limits(max_connections=max(10, len(ks)))
    async with httpx.AsyncClient(timeout=60, limits=limits) as http:
        try:
            for robot, url in zip(robots, urls):
                await _open(robot, url, plan.api_key, http)
        except Exception as exc:  # noqa: BLE001 - reported, and the row is invalid
            out.failures.append(f"set-up: {type(exc).__name__}: {exc}")
            conn.send(("ready", None))
            conn.recv()
            conn.send(("streamed", None))
            return out
        conn.send(("ready", None))
        start = conn.recv()  # the common instant (perf_counter: CLOCK_MONOTONIC, the same in every process)
        rng = random.Random(plan.seed * 7919 + ks[0] if ks else plan.seed)
        offsets = [rng.uniform(0, plan.hop_s) for _ in robots]  # robots do not start in lockstep
        cpu0, wall0 = time.process_time(), time.perf_counter()
        senders = [asyncio.create_task(_send(r, start + off, plan.block_s, out)) for r, off in zip(robots, offsets)]
        readers = [asyncio.create_task(_acks(r, out)) for r in robots]
        operators = [asyncio.create_task(_operate(r, start, out)) for r in robots]
        framers = [
            asyncio.create_task(_frames(r, u, http, start + off, plan, out))
            for r, u, off in zip(robots, urls, offsets)
            if r.frame is not None
        ]
        await asyncio.gather(*senders, *framers, return_exceptions=True)
        # the last windows are in flight: wait for every one the streams completed, at most TAIL_S
        expected = len(robots) * int(plan.duration_s / plan.hop_s + 1e-9)
        deadline = time.perf_counter() + TAIL_S
        while out.windows < expected and time.perf_counter() < deadline:
            await asyncio.sleep(0.05)
        out.cpu_s, out.wall_s = time.process_time() - cpu0, time.perf_counter() - wall0
        conn.send(("streamed", None))
        for r in robots:
            for ws in (r.ingest, r.events):
                if ws is not None:
                    await ws.close()
        await asyncio.gather(*readers, *operators, return_exceptions=True)
    return out


def _main(plan: Plan, ks: list[int], conn) -> None:
    """A generator process: run, then send its GeneratorResult's fields back."""
    try:
        import uvloop

        result = uvloop.run(_generate(plan, ks, conn))
    except ImportError:
        result = asyncio.run(_generate(plan, ks, conn))
    conn.send(("result", result.__dict__))
    conn.close()


def receive(pipe, proc, expected: str):
    """The value of a child process's next ("kind", value) message, which must be of kind `expected`; RuntimeError
    naming what happened when the process exited first, reported ("error", text), or sent something else."""
    try:
        kind, value = pipe.recv()
    except EOFError:
        proc.join(timeout=5)
        raise RuntimeError(f"a load-generator process exited (code {proc.exitcode}) before its {expected}") from None
    if kind == "error":
        raise RuntimeError(f"a load-generator process failed: {value}")
    if kind != expected:
        raise RuntimeError(f"a load-generator process sent {kind!r} instead of its {expected}")
    return value


def run_generators(
    plan: Plan, on_start: Callable[[], None] = lambda: None, on_end: Callable[[], None] = lambda: None
) -> list[GeneratorResult]:
    """Start the processes, release them at one instant once all are connected, collect their results.
    on_start() is called at that instant, on_end() once every process has streamed and received its last
    windows (before they close their connections)."""
    if plan.generators < 1 or plan.robots < 1:
        raise ValueError(f"need ≥ 1 generator and ≥ 1 robot, got {plan.generators} and {plan.robots}")
    shares = [list(range(g, plan.robots, plan.generators)) for g in range(min(plan.generators, plan.robots))]
    ctx = mp.get_context("spawn")  # a fresh interpreter: nothing of the parent's event loop or threads
    procs, pipes = [], []
    for ks in shares:
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_main, args=(plan, ks, child), daemon=True)
        proc.start()
        procs.append(proc)
        pipes.append(parent)

    try:
        for pipe, proc in zip(pipes, procs):
            receive(pipe, proc, "ready")
        start = time.perf_counter() + SETUP_S
        for pipe in pipes:
            pipe.send(start)
        time.sleep(max(0.0, start - time.perf_counter()))
        on_start()
        for pipe, proc in zip(pipes, procs):
            receive(pipe, proc, "streamed")
        on_end()
        results = [GeneratorResult(**receive(pipe, proc, "result")) for pipe, proc in zip(pipes, procs)]
    finally:
        for proc in procs:
            proc.join(timeout=30)
            if proc.is_alive():
                proc.kill()
    return results
