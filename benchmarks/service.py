"""Load benchmark of the real-time service: N simulated robots on loopback, each with an operator.

Run from the repository root:
    python -m benchmarks.service  [--robots 1 10 50 100 200] [--replicas 1 2] [--configs served tactile]
                                  [--duration 20] [--block-s S] [--generators G] [--profile]

Two configurations:
- `served`: the models the demo serves — `ridge-both` reading touch and vision, with the EfficientNet-Lite0
  backbone — and `ridge-tactile` as the tactile-only model for windows before a session's first
  frame; every robot sends its texture's photo as a camera frame at 1 fps through the real visual
  path (decode, scene-change test, embedding when the scene changed).
- `tactile`: `ridge-tactile` alone, no frames.

The robots and their operators are the load generator of benchmarks/loadgen.py: several processes, blocks
encoded before the clock starts, 1 kHz accel (3 axes), force (3 axes) and speed in blocks of the robot
client's default size (drivers.source.DEFAULT_BLOCK_S) sent at real-time pace (a block when its span has
ended; starts staggered over one hop), rendered by the library's vibration models along freehand strokes;
binary blocks over WebSocket with the fleet API key. Robot k is pinned to replica k mod R, as nginx pins
sessions in deploy/. Each service replica is its own process (`hapticlink serve`). Reported per row:

- the generator's own send lag (p50/p99/max) and `valid`: false when its p99 exceeds a quarter of a block
  (at most 10 ms) or a robot or operator failed — such a row measured the generator, not the service;
- windows received, lost (= ⌊duration / hop⌋ per robot − received), and what the service refused
  (blocks refused with 429/4429, frames refused): overload must be refused early and visibly, never by
  losing windows that were accepted;
- latency, ms: end-to-end (operator receive − the moment the block that completed the window left the
  generator; one clock) and the service's stages from the events' latency_ms, p50/p99; the first window
  of each session against the median (cold start);
- service CPU by accounting: CPU time of the service processes over the streaming phase ÷ robot-seconds of
  stream sent (`service_cpu_ms_per_robot_s`) and the robots per core that follows; server CPU % (of one
  core; 200 % = both cores), RSS; the generators' CPU and everyone else's.

Capacity, in the same run: one session fed as fast as it is acknowledged, with an operator attached,
against the service and against the framework's floor — a bare uvicorn WebSocket endpoint that
receives the same blocks, decodes them with numpy (drivers.blocks.decode_binary) and acknowledges
them, and does nothing else. Server CPU per block of both, and their ratio, go to
`capacity` in reports/bench/service.json. `--profile` samples the service with py-spy during the
capacity run and prints where its CPU went.

Writes reports/bench/service.json and prints a table.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import random
import secrets
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

from benchmarks import loadgen
from benchmarks.loadgen import STAGES, robot_streams
from benchmarks.report_file import command_line, machine, write_report
from drivers.blocks import Block, Frame, TapBlock
from drivers.protocol import ws_url
from drivers.robot import RobotClient
from drivers.robot.frames import FRAME_REFRESH_S, REFRESH_JITTER
from drivers.scene_change import FRAME_CHANGE
from drivers.source import DEFAULT_BLOCK_S
from models.inference.modelfile import read_card
from service import launcher

DEFAULT_OUT = Path("reports/bench/service.json")
HOP_S = 0.5
GENERATOR_LAG_LIMIT_MS = 10.0  # send lag p99 beyond which a row's load generator fell behind (see measure)
CONFIGS = ("served", "tactile")
#: this process's scrape credential of its servers' GET /metrics (ServerProcess.service gives it to each)
METRICS_TOKEN = secrets.token_urlsafe(24)
SCRAPER = {"Authorization": f"Bearer {METRICS_TOKEN}"}


# ---- assets --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Assets:
    """What a configuration serves: model, optional tactile-only model and backbone, library (its images are the
    frames); taps: its models read tap features (each robot taps its surface before stroking)."""

    name: str
    model: Path
    tactile: Path | None
    backbone: Path | None
    library: Path
    frames: bool
    taps: bool = False


DEFAULT_ASSETS = Path("artifacts/demo")  # `make demo`'s assets: the benchmark serves what the demo serves


def prepare_assets(root: Path) -> dict[str, Assets]:
    """Both configurations from the demo's assets under root (built once, shared with `hapticlink demo`: a
    synthetic world of 96 textures, its library of 24)."""
    from demo.assets import prepare_assets as demo_assets

    demo = demo_assets(root)
    taps = "taps" in read_card(demo.model).tactile_config.get("extra_groups", ())
    return {
        "served": Assets("served", demo.model, demo.tactile, demo.backbone, demo.library, frames=True, taps=taps),
        "tactile": Assets("tactile", demo.tactile, None, None, demo.library, frames=False, taps=taps),
    }


# ---- CPU accounting ------------------------------------------------------------------------------
def process_cpu_seconds(pid: int | str) -> float:
    """utime + stime of a process (all its threads), s."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def memory_mb(pid: int | str) -> tuple[float, float]:
    """(RSS, peak RSS) of a process in MiB, from /proc/<pid>/status."""
    status = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
    return int(status["VmRSS"].split()[0]) / 1024, int(status["VmHWM"].split()[0]) / 1024


def machine_cpu_seconds() -> float:
    """Busy CPU time of the whole machine (all cores), s: everything but idle and iowait."""
    values = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    return (sum(values) - values[3] - values[4]) / os.sysconf("SC_CLK_TCK")


# ---- server processes ----------------------------------------------------------------------------
class ServerProcess(launcher.ServerProcess):
    """The service, or the floor, in a child process; CPU and memory read from /proc/<pid>."""

    @classmethod
    def service(
        cls, assets: Assets, api_key: str, instance_id: str = "bench", extra: dict[str, str] | None = None
    ) -> ServerProcess:
        argv = [
            sys.executable,
            "-m",
            "service.cli",
            "serve",
            "--model",
            str(assets.model),
            "--library",
            str(assets.library),
            "--log-level",
            "warning",
            "--instance-id",
            instance_id,
        ]
        if assets.backbone is not None:
            argv += ["--backbone", str(assets.backbone)]
        env = {
            "HAPTICLINK_API_KEYS": api_key,
            "HAPTICLINK_METRICS_TOKEN": METRICS_TOKEN,
            # one benchmark process is one client address for every robot: lift the per-client session rate;
            # every session is opened before any streams: give them time to start
            "HAPTICLINK_SESSION_BURST": "100000",
            "HAPTICLINK_SESSION_FIRST_BLOCK_S": "300",
            **(extra or {}),
        }
        if assets.tactile is not None:
            env["HAPTICLINK_TACTILE_MODEL_PATH"] = str(assets.tactile)
        return cls(argv, env)

    @classmethod
    def floor(cls) -> ServerProcess:
        return cls([sys.executable, "-m", "benchmarks.service_floor"], {}, ready_path="/health")

    def cpu_seconds(self) -> float:
        return process_cpu_seconds(self.proc.pid)

    def memory_mb(self) -> tuple[float, float]:
        """(RSS, peak RSS) in MiB."""
        return memory_mb(self.proc.pid)


# ---- the robots ----------------------------------------------------------------------------------
class PacedSource:
    """A robot's sensor source: its blocks at real-time pace from `start` (perf_counter), a camera frame every
    `frame_every_s`; stamps the moment each block is yielded (the robot has it) in `yielded[seq]`."""

    name = "bench"

    def __init__(
        self,
        blocks: list[Block],
        block_s: float,
        start: float,
        frame: bytes | None,
        frame_every_s: float,
        realtime: bool = True,
    ) -> None:
        self.blocks, self.block_s, self.start = blocks, block_s, start
        self.frame, self.frame_every = frame, max(1, int(round(frame_every_s / block_s)))
        self.frame_type = loadgen.frame_content_type(frame) if frame is not None else ""
        self.realtime = realtime
        self.yielded: dict[int, float] = {}
        self.send_lag_ms: list[float] = []
        self.finished = math.nan  # perf_counter when its robot had sent and settled every block (run_load)

    async def _items(self):
        n = 0  # sample blocks so far (a tap block holds no stream time: it leaves at once)
        for i, block in enumerate(self.blocks):
            if isinstance(block, TapBlock):
                self.yielded[i] = time.perf_counter()
                yield block
                continue
            n += 1
            if self.realtime:
                due = self.start + n * self.block_s  # a block leaves when its span has ended
                delay = due - time.perf_counter()
                if delay > 0:
                    await asyncio.sleep(delay)
                self.send_lag_ms.append(max(0.0, time.perf_counter() - due) * 1e3)
            elif i % 256 == 0:
                await asyncio.sleep(0)
            if self.frame is not None and (n - 1) % self.frame_every == 0:
                yield Frame(block.t0, self.frame, self.frame_type)
            self.yielded[i] = time.perf_counter()
            yield block

    def __aiter__(self):
        return self._items()

    async def aclose(self) -> None:
        pass


@dataclass
class OperatorView:
    windows: int = 0
    e2e_ms: list[float] = field(default_factory=list)
    received_at: list[float] = field(default_factory=list)  # perf_counter when each e2e_ms entry's window arrived
    first_features_ms: float | None = None
    stages_ms: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in STAGES})
    inputs: Counter = field(default_factory=Counter)
    error: str | None = None


async def operate(
    url: str, session, source: PacedSource, view: OperatorView, ready: asyncio.Event, done: asyncio.Event
) -> None:
    """An operator: reads the session's events until `done`, measuring each window against its block's yield time.
    An operator that cannot attach is recorded (view.error) and its windows count as lost."""
    try:
        await _operate(url, session, source, view, ready, done)
    except Exception as exc:  # noqa: BLE001 - e.g. the handshake timed out on a starved machine
        view.error = f"{type(exc).__name__}: {exc}"
    finally:
        ready.set()


async def _operate(
    url: str, session, source: PacedSource, view: OperatorView, ready: asyncio.Event, done: asyncio.Event
) -> None:
    from websockets.asyncio.client import connect

    async with connect(ws_url(url, session.session_id, "events", str(session.operator_token)), max_size=2**20) as ws:
        await ws.recv()  # "subscribed"
        ready.set()

        async def read() -> None:
            async for message in ws:
                now = time.perf_counter()
                if '"type":"window"' not in message[:20]:
                    continue
                event = json.loads(message)
                view.windows += 1
                view.inputs[event["inputs"]] += 1
                yielded = source.yielded.get(event["block_seq"])
                if yielded is not None:
                    view.e2e_ms.append((now - yielded) * 1e3)
                    view.received_at.append(now)
                for stage in STAGES:
                    view.stages_ms[stage].append(event["latency_ms"][stage])
                if view.first_features_ms is None:
                    view.first_features_ms = event["latency_ms"]["features"]

        reader = asyncio.create_task(read())
        await done.wait()
        reader.cancel()
        await asyncio.gather(reader, return_exceptions=True)


async def run_load(
    urls: list[str],
    streams: list[list[Block]],
    frames: list[bytes | None],
    block_s: float,
    api_key: str,
    seed: int,
    realtime: bool = True,
    window: int = 64,
    max_buffer_s: float | None = None,
) -> tuple[list, list[OperatorView], list[PacedSource]]:
    """Robot k (a real RobotClient) streams to replica k mod R; an operator per session. Returns stats, views,
    sources (each with `finished`: perf_counter when its robot had sent and settled everything). max_buffer_s: the
    robots' resend buffer (None: the client's default); a source that is not real time yields every block at once,
    so it must hold the whole stream, or the client drops the oldest."""
    robot_urls = [urls[k % len(urls)] for k in range(len(streams))]
    rng = random.Random(seed)
    offsets = [rng.uniform(0, HOP_S) if realtime else 0.0 for _ in streams]  # robots do not start in lockstep
    # the start is set once every session and operator is connected (a robot due before would send a backlog)
    sources = [PacedSource(s, block_s, 0.0, f, 1.0, realtime) for s, f in zip(streams, frames)]
    clients = [
        RobotClient(
            u,
            src,
            api_key=api_key,
            session_name=f"bench-{k}",
            window=window,
            seed=k,
            drain_timeout_s=10,
            **({} if max_buffer_s is None else {"max_buffer_s": max_buffer_s}),
        )
        for k, (u, src) in enumerate(zip(robot_urls, sources))
    ]
    for c in clients:
        await c.open_session()
    views = [OperatorView() for _ in clients]
    readies = [asyncio.Event() for _ in clients]
    done = asyncio.Event()
    operators = [
        asyncio.create_task(operate(u, c.session, src, v, r, done))
        for u, c, src, v, r in zip(robot_urls, clients, sources, views, readies)
    ]
    await asyncio.gather(*(r.wait() for r in readies))
    start = time.perf_counter() + 1.0
    for src, off in zip(sources, offsets):
        src.start = start + off
    outcomes = await asyncio.gather(*(c.run() for c in clients), return_exceptions=True)
    for src in sources:
        src.finished = time.perf_counter()
    for k, o in enumerate(outcomes):
        if isinstance(o, BaseException):
            print(f"  robot {k} stopped: {type(o).__name__}: {o}", flush=True)
    stats = [c.stats for c in clients]  # a robot that stopped keeps the counts it had
    await asyncio.sleep(2.0)  # the last windows are in flight
    done.set()
    await asyncio.gather(*operators, return_exceptions=True)
    return stats, views, sources


def _run(coro):
    """asyncio.run, on uvloop when installed (the client should cost as little CPU as it can)."""
    try:
        import uvloop
    except ImportError:
        return asyncio.run(coro)
    return uvloop.run(coro)


def percentile(values: list[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)), 3) if values else None


def timeline(e2e: list[tuple[float, float]], t0: float, bin_s: float = 2.0) -> list[dict]:
    """Windows per `bin_s` bin from t0 with their end-to-end p50 and p99 (ms; None in a bin no window reached: every
    robot shed, or the service stalled). e2e: (t, ms) pairs, t in seconds on t0's clock (when the window arrived, or
    when its block left)."""
    bins: dict[int, list[float]] = {}
    for t, ms in e2e:
        bins.setdefault(int((t - t0) // bin_s), []).append(ms)
    return [
        {"t_s": k * bin_s, "windows": len(v), "e2e_p50": percentile(v, 50), "e2e_p99": percentile(v, 99)}
        for k in range(min(bins, default=0), max(bins, default=-1) + 1)
        for v in [bins.get(k, [])]
    ]


def _metric_sum(text: str, name: str, **labels: str) -> float:
    """Sum of a metric's samples whose labels include `labels`."""
    total = 0.0
    for line in text.splitlines():
        if not line.startswith(name):
            continue
        key, _, value = line.rpartition(" ")
        if key == name or (key.startswith(name + "{") and all(f'{k}="{v}"' in key for k, v in labels.items())):
            total += float(value)
    return total


def generator_lag_limit_ms(block_s: float) -> float:
    """The send lag p99 beyond which a row's generator fell behind: a quarter of a block, at most 10 ms."""
    return min(GENERATOR_LAG_LIMIT_MS, 250 * block_s)


def invalid_because(lag_p99_ms: float | None, limit_ms: float, failures: list[str]) -> str | None:
    """Why a row did not measure the service serving its load (None: it did): the generator fell behind (its send
    lag p99 over the limit), sent nothing (no lag to judge), or a robot or operator failed (the first failure)."""
    reasons = []
    if lag_p99_ms is None:
        reasons.append("the generator sent no block")
    elif lag_p99_ms > limit_ms:
        reasons.append(f"generator send lag p99 {lag_p99_ms} ms > {limit_ms:g} ms")
    if failures:
        reasons.append(f"{len(failures)} generator failure(s): {failures[0]}")
    return "; ".join(reasons) or None


def measure(
    n: int,
    assets: Assets,
    duration_s: float,
    block_s: float,
    seed: int,
    replicas: int,
    api_key: str,
    generators: int,
    frame_change: float = FRAME_CHANGE,
    frame_refresh_jitter: float = REFRESH_JITTER,
) -> dict:
    """n robots against `replicas` service processes, generated by `generators` processes (benchmarks/loadgen.py);
    CPU, memory and refusals summed over the replicas. The row is `valid` only when every generator kept its
    send lag p99 within generator_lag_limit_ms, every robot and operator connected, and no generator failed."""
    servers: list[ServerProcess] = []
    try:
        for k in range(replicas):
            servers.append(ServerProcess.service(assets, api_key, instance_id=f"bench{k}"))
        plan = loadgen.Plan(
            urls=tuple(s.url for s in servers),
            library=assets.library,
            api_key=api_key,
            robots=n,
            duration_s=duration_s,
            block_s=block_s,
            generators=max(1, min(generators, n)),
            seed=seed,
            taps=assets.taps,
            frames=assets.frames,
            frame_change=frame_change,
            frame_refresh_jitter=frame_refresh_jitter,
            hop_s=HOP_S,
        )
        metrics0 = [httpx.get(f"{s.url}/metrics", headers=SCRAPER).text for s in servers]
        at_start: list[float] = []

        def started() -> None:  # the service's CPU from the moment the streams start (sessions already open)
            at_start.extend([sum(s.cpu_seconds() for s in servers), machine_cpu_seconds(), time.perf_counter()])

        at_end: list[float] = []

        def ended() -> None:  # … until every generator has streamed and received its last windows
            at_end.extend([sum(s.cpu_seconds() for s in servers), machine_cpu_seconds(), time.perf_counter()])

        results = loadgen.run_generators(plan, on_start=started, on_end=ended)
        cpu0, machine0, wall0 = at_start
        cpu1, machine1, wall1 = at_end
        memory = [s.memory_mb() for s in servers]
        metrics = [httpx.get(f"{s.url}/metrics", headers=SCRAPER).text for s in servers]
    finally:
        for s in servers:
            s.stop()

    def counted(name: str, **labels: str) -> int:
        """A counter's increase over the run, summed over the replicas."""
        return int(
            sum(_metric_sum(m, name, **labels) for m in metrics) - sum(_metric_sum(m, name, **labels) for m in metrics0)
        )

    expected = n * int(duration_s / HOP_S + 1e-9)
    received = sum(r.windows for r in results)
    e2e = [x for r in results for x in r.e2e_ms]
    e2e_by_sent = [(t, x) for r in results for t, x in zip(r.e2e_sent_s, r.e2e_ms, strict=True)]
    lag = [x for r in results for x in r.send_lag_ms]
    stages = {st: [x for r in results for x in r.stages_ms[st]] for st in STAGES}
    firsts = [x for r in results for x in r.first_features_ms]
    failures = [f for r in results for f in r.failures]
    median_features = percentile(stages["features"], 50)
    lag_p99 = percentile(lag, 99)
    limit = generator_lag_limit_ms(block_s)
    why_invalid = invalid_because(lag_p99, limit, failures)
    # the generator's stream phase: from the common start to its last window (the generators' own wall clocks)
    served_s = n * duration_s  # robot-seconds of stream the service was sent
    server_cpu_s = cpu1 - cpu0
    generator_cpu_s = sum(r.cpu_s for r in results)
    ms_per_robot_s = 1e3 * server_cpu_s / served_s
    return {
        "config": assets.name,
        "robots": n,
        "replicas": replicas,
        "generators": plan.generators,
        "duration_s": duration_s,
        "block_s": block_s,
        "valid": why_invalid is None,
        "invalid_because": why_invalid,
        "generator_lag_ms": {"p50": percentile(lag, 50), "p99": lag_p99, "max": percentile(lag, 100), "limit": limit},
        "windows_expected": expected,
        "windows_received": received,
        "windows_lost": expected - received,
        # of those, windows that accepted blocks had completed: overload must never cost these
        "windows_lost_after_acceptance": counted("hapticlink_windows_admitted_total") - received,
        "windows_tactile_only": sum(r.windows_tactile_only for r in results) if assets.frames else None,
        "blocks_sent": sum(r.blocks_sent for r in results),
        "blocks_refused": counted("hapticlink_blocks_total", outcome="refused"),
        "blocks_rejected": counted("hapticlink_blocks_total", outcome="rejected"),
        "ingest_closed_saturated": sum(r.saturated_closes for r in results),
        "frames_sent": sum(r.frames_sent for r in results),
        "frames_unchanged": sum(r.frames_unchanged for r in results),
        "refreshes_held": sum(r.refreshes_held for r in results),
        "frames_refused": counted("hapticlink_frames_total", outcome="refused"),
        "frames_embedded": counted("hapticlink_visual_embedding_seconds_count"),
        "events_dropped_by_service": counted("hapticlink_events_dropped_total"),
        "e2e_ms": {"p50": percentile(e2e, 50), "p99": percentile(e2e, 99), "max": percentile(e2e, 100)},
        # by when the window's block left (2 s bins from the start): the robots' first frames and their refreshes
        # show as bursts here
        "e2e_ms_timeline": timeline(e2e_by_sent, 0.0),
        "stages_ms": {st: {"p50": percentile(v, 50), "p99": percentile(v, 99)} for st, v in stages.items()},
        "cold_start": {
            "first_window_features_ms_max": round(max(firsts), 3) if firsts else None,
            "features_median_ms": median_features,
            "first_over_median": round(max(firsts) / median_features, 2) if firsts and median_features else None,
        },
        # CPU by accounting: the service processes' CPU time over the run ÷ the robot-seconds of stream sent
        "service_cpu_ms_per_robot_s": round(ms_per_robot_s, 3),
        "robots_per_core": round(1e3 / ms_per_robot_s, 1) if ms_per_robot_s > 0 else None,
        "server_cpu_percent": round(100 * server_cpu_s / (wall1 - wall0), 1),
        "generator_cpu_percent": round(100 * generator_cpu_s / (wall1 - wall0), 1),
        # other processes on this (shared) machine during the run: they compete for the same cores
        "others_cpu_percent": round(
            100 * ((machine1 - machine0) - server_cpu_s - generator_cpu_s) / (wall1 - wall0), 1
        ),
        "server_rss_mb": round(sum(m[0] for m in memory), 1),
        "server_peak_rss_mb": round(sum(m[1] for m in memory), 1),
        "blocks_per_s": round(n / block_s, 1),
        "failures": failures[:5],
    }


# ---- capacity: the service against the framework's floor -----------------------------------------
def _pump(server: ServerProcess, blocks: list[Block], api_key: str, block_s: float) -> tuple[int, float, float]:
    """One RobotClient (+ operator) sending `blocks` as fast as acknowledged → (blocks acked, server CPU s, wall s).
    The robot holds the whole stream (its blocks are all read at once): none is dropped, and every one is acked."""
    stream_s = block_s * len(blocks)
    cpu0 = server.cpu_seconds()
    stats, _, sources = _run(
        run_load(
            [server.url], [blocks], [None], block_s, api_key, 0, realtime=False, window=32, max_buffer_s=stream_s + 1
        )
    )
    cpu1 = server.cpu_seconds()
    if stats[0].acked != len(blocks):
        raise RuntimeError(f"the capacity pump had {stats[0].acked} of {len(blocks)} blocks acknowledged: {stats[0]}")
    first = min(sources[0].yielded.values())  # not real time: the source does not wait for its start
    return stats[0].acked, cpu1 - cpu0, sources[0].finished - first  # the streaming, not the set-up


def measure_capacity(
    assets: Assets, blocks: list[Block], api_key: str, block_s: float, profile_out: Path | None = None
) -> dict:
    """Server CPU per block of the service (windows, features, model, publishing included) and of the floor."""
    # every window of the stream may queue at once (the robot sends faster than real time)
    windows = int(block_s * len(blocks) / HOP_S) + 8
    service = ServerProcess.service(assets, api_key, extra={"HAPTICLINK_SESSION_QUEUE_WINDOWS": str(windows)})
    profiler = None
    try:
        if profile_out is not None:
            py_spy = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))  # installed beside python
            profiler = subprocess.Popen(
                [
                    py_spy,
                    "record",
                    "--pid",
                    str(service.proc.pid),
                    "--rate",
                    "250",
                    "--threads",
                    "--format",
                    "raw",
                    "--output",
                    str(profile_out),
                    "--nonblocking",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            time.sleep(1.0)
        acked, cpu, wall = _pump(service, blocks, api_key, block_s)
    finally:
        if profiler is not None:
            profiler.send_signal(signal.SIGINT)
            profiler.wait(timeout=30)
        service.stop()
    floor = ServerProcess.floor()
    try:
        floor_acked, floor_cpu, _ = _pump(floor, blocks, api_key, block_s)
    finally:
        floor.stop()
    per_block = 1e6 * cpu / max(acked, 1)
    floor_per_block = 1e6 * floor_cpu / max(floor_acked, 1)
    return {
        "blocks": acked,
        "blocks_per_s": round(acked / max(wall, 1e-9), 1),
        "server_cpu_us_per_block": round(per_block, 1),
        "floor_cpu_us_per_block": round(floor_per_block, 1),
        "server_over_floor": round(per_block / floor_per_block, 2),
        # a robot sends 1/block_s blocks a second: the share of one core each robot costs
        "server_core_percent_per_robot": round(per_block * (1 / block_s) / 1e4, 2),
    }


def summarize_profile(path: Path, top: int = 20) -> list[tuple[str, float]]:
    """py-spy raw (collapsed) stacks → the `top` functions by self time (the stack's innermost frame), % of samples."""
    total, own = 0, Counter()
    for line in path.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack:
            continue
        total += int(count)
        leaf = stack.split(";")[-1]
        name, _, where = leaf.partition(" (")
        own[f"{name} ({where.split(':')[0].rsplit('/', 1)[-1]})" if where else name] += int(count)
    return [(f, round(100 * c / total, 1)) for f, c in own.most_common(top)] if total else []


# ---- report --------------------------------------------------------------------------------------
def print_table(rows: list[dict]) -> None:
    head = (
        f"{'config':>7} {'robots':>6} {'repl':>4} {'gens':>4} {'valid':>5} {'lag p99':>8} {'win/s':>6} {'lost':>5} "
        f"{'refused':>7} {'e2e p50':>8} {'e2e p99':>8} {'queue p99':>9} {'feat p99':>8} {'ms/robot-s':>10} "
        f"{'robots/core':>11} {'cpu %':>6} {'gen %':>6} {'others %':>8}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        st = r["stages_ms"]
        print(
            f"{r['config']:>7} {r['robots']:>6} {r['replicas']:>4} {r['generators']:>4} {str(r['valid']):>5} "
            f"{r['generator_lag_ms']['p99'] or 0:>8.2f} {r['windows_received'] / r['duration_s']:>6.1f} "
            f"{r['windows_lost']:>5} {r['blocks_refused'] + r['frames_refused']:>7} {r['e2e_ms']['p50'] or 0:>8.2f} "
            f"{r['e2e_ms']['p99'] or 0:>8.2f} {st['queue']['p99'] or 0:>9.2f} {st['features']['p99'] or 0:>8.2f} "
            f"{r['service_cpu_ms_per_robot_s']:>10.2f} {r['robots_per_core'] or 0:>11.1f} "
            f"{r['server_cpu_percent']:>6.1f} {r['generator_cpu_percent']:>6.1f} {r['others_cpu_percent']:>8.1f}"
        )


def headline(rows: list[dict]) -> dict | None:
    """Robots per core of the served configuration by CPU accounting, from its largest valid row (the most
    robot-seconds over the fixed costs), and the largest valid load with its end-to-end p99 and windows lost."""
    served = [r for r in rows if r["config"] == "served" and r["valid"]]
    if not served:
        return None
    best = max(served, key=lambda r: (r["robots"], -r["replicas"]))
    return {
        "config": "served",
        "block_s": best["block_s"],
        "robots": best["robots"],
        "replicas": best["replicas"],
        "service_cpu_ms_per_robot_s": best["service_cpu_ms_per_robot_s"],
        "robots_per_core": best["robots_per_core"],
        "e2e_ms_p99": best["e2e_ms"]["p99"],
        "windows_lost": best["windows_lost"],
        "generator_lag_ms_p99": best["generator_lag_ms"]["p99"],
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, nargs="+", default=[1, 10, 50, 100, 200])
    p.add_argument(
        "--replicas",
        type=int,
        nargs="+",
        default=[1, 2],
        help="service processes, robots pinned round-robin as nginx pins sessions; each runs every --robots N",
    )
    p.add_argument("--configs", nargs="+", choices=CONFIGS, default=list(CONFIGS))
    p.add_argument("--duration", type=float, default=20.0, help="seconds of stream per robot (default 20)")
    p.add_argument(
        "--block-s",
        type=float,
        default=DEFAULT_BLOCK_S,
        help=f"seconds per block (default {DEFAULT_BLOCK_S:g}: the robot client's default)",
    )
    p.add_argument(
        "--generators",
        type=int,
        default=None,
        help="load-generator processes (default: one per 25 robots, at most the cores less one but 2 on 2 cores)",
    )
    p.add_argument(
        "--capacity-s",
        type=float,
        default=300.0,
        help="seconds of stream pumped for the capacity measurement (default 300: enough samples for --profile)",
    )
    p.add_argument(
        "--frame-change",
        type=float,
        default=FRAME_CHANGE,
        help=f"the robots' scene-change gate for camera frames (default {FRAME_CHANGE:g}, the robot client's; 0: "
        "every frame is sent, as before the gate)",
    )
    p.add_argument(
        "--frame-refresh-jitter",
        type=float,
        default=REFRESH_JITTER,
        help=f"each robot's frame refresh comes {FRAME_REFRESH_S:g} s × (1 + u·J) after its last frame, u drawn anew "
        f"in [0, 1) (default {REFRESH_JITTER:g}, the robot client's; 0: robots started together refresh together)",
    )
    p.add_argument("--no-capacity", action="store_true", help="skip the capacity measurement")
    p.add_argument("--profile", action="store_true", help="sample the service with py-spy during the capacity run")
    p.add_argument(
        "--assets",
        type=Path,
        default=DEFAULT_ASSETS,
        help=f"the demo's assets, built there when missing (default {DEFAULT_ASSETS}, shared with `make demo`)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    load_before = os.getloadavg()
    if min(args.replicas) < 1 or min(args.robots) < 1 or (args.generators is not None and args.generators < 1):
        p.error("--robots, --replicas and --generators must be ≥ 1")
    api_key = secrets.token_urlsafe(24)  # this run's fleet key
    print("preparing assets (cached) …", flush=True)
    all_assets = prepare_assets(args.assets)
    library = all_assets["tactile"].library
    taps = all_assets["tactile"].taps  # both configurations serve the demo's features
    capacity = None
    profile = None
    if not args.no_capacity:
        print("capacity: one session as fast as acknowledged, the service (tactile) and the floor …", flush=True)
        blocks = robot_streams(library, 1, args.capacity_s, args.block_s, args.seed + 1, taps=taps)[0]
        profile_path = args.out.with_name("service-profile.txt") if args.profile else None
        capacity = measure_capacity(all_assets["tactile"], blocks, api_key, args.block_s, profile_path)
        print(
            f"  service {capacity['server_cpu_us_per_block']:.0f} µs, "
            f"floor {capacity['floor_cpu_us_per_block']:.0f} µs server CPU per block: "
            f"{capacity['server_over_floor']:.2f} × the floor; "
            f"{capacity['server_core_percent_per_robot']:.2f} % of a core per {args.block_s * 1e3:g} ms-block robot",
            flush=True,
        )
        if profile_path is not None and profile_path.is_file():
            profile = summarize_profile(profile_path)
            print("  where the service's CPU went (share of samples, self time):")
            for name, share in profile:
                print(f"    {share:5.1f} %  {name}")
    rows = []
    for config in args.configs:
        for replicas, n in [(r, n) for r in args.replicas for n in args.robots]:
            print(f"{config}: {n} robot(s) on {replicas} replica(s) for {args.duration:g} s …", flush=True)
            generators = args.generators or min(-(-n // 25), max(2, (os.cpu_count() or 2) - 1))
            rows.append(
                measure(
                    n,
                    all_assets[config],
                    args.duration,
                    args.block_s,
                    args.seed,
                    replicas,
                    api_key,
                    generators,
                    args.frame_change,
                    args.frame_refresh_jitter,
                )
            )
            r = rows[-1]
            print(
                f"  valid {r['valid']} (generator lag p99 {r['generator_lag_ms']['p99']} ms), "
                f"lost {r['windows_lost']}, e2e p99 {r['e2e_ms']['p99']} ms, "
                f"{r['service_cpu_ms_per_robot_s']:.2f} ms service CPU per robot-second → "
                f"{r['robots_per_core']} robots per core",
                flush=True,
            )
    print()
    print_table(rows)
    report = {
        "benchmark": "service",
        "command": command_line("benchmarks.service", argv if argv is not None else sys.argv[1:]),
        "machine": machine(load_before),
        "config": {
            "block_s": args.block_s,
            "duration_s": args.duration,
            "hop_s": HOP_S,
            "transport": "WebSocket, binary blocks, drivers.robot.RobotClient",
            "channels": "accel (n,3) + force (n,3) + speed (n,) at 1 kHz",
            "configs": {
                k: {
                    "model": str(a.model),
                    "tactile_model": str(a.tactile) if a.tactile else None,
                    "backbone": str(a.backbone) if a.backbone else None,
                    "frames": (
                        f"1 fps, the texture's photo, sent when the robot's FrameGate lets it go (change "
                        f"{args.frame_change:g}, refresh {FRAME_REFRESH_S:g} s, jitter {args.frame_refresh_jitter:g})"
                    )
                    if a.frames
                    else None,
                }
                for k, a in all_assets.items()
                if k in args.configs
            },
        },
        "robots_per_core": headline(rows),
        "capacity": capacity,
        "profile_top": profile,
        "results": rows,
    }
    write_report(args.out, report)
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
