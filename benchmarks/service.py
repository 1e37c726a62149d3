"""Load benchmark of the real-time service: N simulated robots on loopback, each with an operator.

Run from the repository root:  python -m benchmarks.service  [--robots 1 10 50 100] [--duration 20] [--replicas 1 2]

For each N, the service runs in its own process (`hapticlink serve`, uvicorn), so the clients'
load does not run on its interpreter; with --replicas R, in R processes, robot k pinned to
replica k mod R as nginx pins sessions in deploy/ (one process is one GIL: one core at most).
Each robot opens a session, streams 1 kHz accel (3 axes), force (3 axes) and speed in 20 ms
binary blocks over WS /ingest at real-time pace (a block is sent when its span has ended,
starts staggered over one window), rendered by the library's vibration models along freehand
strokes (texture_library.stroke); an operator per session reads WS /events. Reported per N:

- windows/s published and received; windows lost = expected (⌊duration / hop⌋ per robot) − received
- latency, ms: end-to-end (subscriber receive − send of the block that completed the window, one
  clock: the client's) and the service's own stages from the events' latency_ms, p50/p99
- server CPU % (of one core; 200 % = both cores of this machine) and RSS from /proc
- how late the client managed to send (its own lag, which would distort the end-to-end numbers)

Writes reports/bench/service.json and prints a table.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import random
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

from drivers.blocks import encode_binary
from drivers.source import blocks_from_arrays
from texture_library.library import Library
from texture_library.stroke import stroke
from texture_library.trajectory import freehand, model_ranges

DEFAULT_OUT = Path("reports/bench/service.json")
STAGES = ("queue", "features", "model", "lookup", "total")


# ---- assets --------------------------------------------------------------------------------------
def prepare_assets(root: Path) -> tuple[Path, Path]:
    """A synthetic library and a ridge-tactile model trained on a synthetic dataset (cached in root)."""
    from models.datasets.build import build
    from models.train import train_and_export
    from texture_library.synthetic_library import build_synthetic_library

    library, model = root / "library", root / "ridge-tactile.onnx"
    if not (library / "library.json").is_file():
        build_synthetic_library(library, n_textures=12, image_size=256)
    if not model.is_file():
        dataset = build("synthetic", root / "dataset", n_textures=12, duration_s=6)
        train_and_export(dataset, "ridge-tactile", model)
    return model, library


def robot_streams(library_dir: Path, n_streams: int, seconds: float, block_s: float, seed: int = 0) -> list[list[bytes]]:
    """n_streams encoded block sequences (seq from 0), each `seconds` long, over the library's textures."""
    lib = Library.load(library_dir)
    out = []
    for k in range(n_streams):
        model = lib.model(lib.ids[k % len(lib.ids)])
        rng = np.random.default_rng([seed, k])
        traj = freehand(seconds + 0.5, rng, rate_hz=model.rate_hz, **model_ranges(model.max_speed, model.max_force))
        s = stroke(model, traj, rng)
        n = int(round(seconds * s.rate_hz))
        channels = {"accel": (s.accel[:n], s.rate_hz, "m/s^2"), "force": (s.force[:n], s.rate_hz, "N"),
                    "speed": (s.speed[:n], s.rate_hz, "mm/s")}
        out.append([encode_binary(b) for b in blocks_from_arrays(channels, block_s)])
    return out


# ---- CPU accounting ------------------------------------------------------------------------------
def process_cpu_seconds(pid: int | str) -> float:
    """utime + stime of a process (all its threads), s."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def machine_cpu_seconds() -> float:
    """Busy CPU time of the whole machine (all cores), s: everything but idle and iowait."""
    values = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    return (sum(values) - values[3] - values[4]) / os.sysconf("SC_CLK_TCK")


# ---- the server process --------------------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """`hapticlink serve` in a child process; CPU and memory read from /proc/<pid>."""

    def __init__(self, model: Path, library: Path, env: dict[str, str], instance_id: str = "bench") -> None:
        self.port = free_port()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve", "--model", str(model), "--library", str(library),
             "--port", str(self.port), "--log-level", "warning", "--instance-id", instance_id],
            env={**os.environ, **env}, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )
        self.url = f"http://127.0.0.1:{self.port}"
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{self.url}/ready", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the service did not start: {self.proc.stderr.read() if self.proc.stderr else ''}")
            time.sleep(0.1)

    def cpu_seconds(self) -> float:
        return process_cpu_seconds(self.proc.pid)

    def memory_mb(self) -> tuple[float, float]:
        """(RSS, peak RSS) in MiB."""
        status = dict(line.split(":", 1) for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines() if ":" in line)
        return int(status["VmRSS"].split()[0]) / 1024, int(status["VmHWM"].split()[0]) / 1024

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()


# ---- the clients ---------------------------------------------------------------------------------
@dataclass
class RobotResult:
    windows: int = 0
    e2e_ms: list[float] = field(default_factory=list)
    stages_ms: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in STAGES})
    send_lag_ms: list[float] = field(default_factory=list)
    acks_failed: int = 0
    closed_saturated: int = 0
    stopped: bool = False  # closed by the service; a real robot would reconnect and resend, this one stops


async def run_robot(url: str, blocks: list[bytes], block_s: float, start: float, result: RobotResult,
                    session: dict, streaming_done: asyncio.Event) -> None:
    from websockets.asyncio.client import connect

    ws_base = url.replace("http://", "ws://") + f"/sessions/{session['session_id']}"
    sent_at: dict[int, float] = {}
    async with connect(f"{ws_base}/events?token={session['operator_token']}", max_size=2**20) as events, \
            connect(f"{ws_base}/ingest?token={session['robot_token']}", max_size=2**20, compression=None) as ingest:
        await events.recv()  # "subscribed"

        async def read_events() -> None:
            async for message in events:
                now = time.perf_counter()
                event = json.loads(message)
                if event.get("type") != "window":
                    continue
                result.windows += 1
                seq = event["block_seq"]
                if seq in sent_at:
                    result.e2e_ms.append((now - sent_at[seq]) * 1e3)
                for stage in STAGES:
                    result.stages_ms[stage].append(event["latency_ms"][stage])

        async def read_acks() -> None:
            async for message in ingest:
                if '"ok": true' not in message:  # cheaper than parsing 50 acks/s per robot
                    result.acks_failed += 1

        reader, acker = asyncio.create_task(read_events()), asyncio.create_task(read_acks())
        try:
            for i, payload in enumerate(blocks):
                due = start + (i + 1) * block_s  # a block leaves when its span has ended
                delay = due - time.perf_counter()
                if delay > 0:
                    await asyncio.sleep(delay)
                now = time.perf_counter()
                result.send_lag_ms.append(max(0.0, now - due) * 1e3)
                sent_at[i] = now
                try:
                    await ingest.send(payload)
                except Exception:  # noqa: BLE001 - the service closed the socket (4429: saturated); this robot stops
                    result.closed_saturated += int(getattr(ingest, "close_code", None) == 4429)
                    result.stopped = True
                    break
            streaming_done.set()
            await asyncio.sleep(2.0)  # the last windows are in flight
        finally:
            reader.cancel()
            acker.cancel()
            await asyncio.gather(reader, acker, return_exceptions=True)


async def run_load(urls: list[str], streams: list[list[bytes]], block_s: float, hop_s: float, seed: int) -> tuple[list[RobotResult], float]:
    """Robot k streams to replica k mod R (as nginx pins a session to the replica that created it)."""
    robot_urls = [urls[k % len(urls)] for k in range(len(streams))]
    async with httpx.AsyncClient(timeout=30) as client:
        sessions = [(await client.post(f"{u}/sessions", json={"name": f"bench-{k}"})).json() for k, u in enumerate(robot_urls)]
    rng = random.Random(seed)
    start = time.perf_counter() + 1.0 + 0.01 * len(streams)  # time to open every connection first
    results = [RobotResult() for _ in streams]
    done = [asyncio.Event() for _ in streams]
    offsets = [rng.uniform(0, hop_s) for _ in streams]  # robots do not start in lockstep
    tasks = [asyncio.create_task(run_robot(u, s, block_s, start + off, r, sess, d))
             for u, s, r, sess, d, off in zip(robot_urls, streams, results, sessions, done, offsets)]
    await asyncio.gather(*tasks)
    return results, start


def _run(coro):
    """asyncio.run, on uvloop when installed (the client should cost as little CPU as it can)."""
    try:
        import uvloop
    except ImportError:
        return asyncio.run(coro)
    return uvloop.run(coro)


def percentile(values: list[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)), 3) if values else None


def measure(n: int, model: Path, library: Path, streams: list[list[bytes]], duration_s: float, block_s: float,
            hop_s: float, seed: int, server_env: dict[str, str], replicas: int = 1) -> dict:
    """n robots against `replicas` server processes; CPU, memory and drops summed over them."""
    servers: list[ServerProcess] = []
    try:
        for k in range(replicas):
            servers.append(ServerProcess(model, library, server_env, instance_id=f"bench{k}"))

        def server_cpu() -> float:
            return sum(s.cpu_seconds() for s in servers)

        cpu0, client0, machine0, wall0 = server_cpu(), process_cpu_seconds("self"), machine_cpu_seconds(), time.perf_counter()
        results, start = _run(run_load([s.url for s in servers], streams[:n], block_s, hop_s, seed))
        cpu1, client1, machine1, wall1 = server_cpu(), process_cpu_seconds("self"), machine_cpu_seconds(), time.perf_counter()
        memory = [s.memory_mb() for s in servers]
        rss, peak = sum(m[0] for m in memory), sum(m[1] for m in memory)
        dropped_per_server = [_metric(httpx.get(f"{s.url}/metrics").text, "hapticlink_events_dropped_total") for s in servers]
    finally:
        for s in servers:
            s.stop()
    expected = n * int(duration_s / hop_s + 1e-9)
    received = sum(r.windows for r in results)
    e2e = [x for r in results for x in r.e2e_ms]
    lag = [x for r in results for x in r.send_lag_ms]
    stages = {s: [x for r in results for x in r.stages_ms[s]] for s in STAGES}
    dropped = None if None in dropped_per_server else sum(dropped_per_server)
    return {
        "robots": n,
        "replicas": replicas,
        "duration_s": duration_s,
        "windows_expected": expected,
        "windows_received": received,
        "windows_lost": expected - received,
        "windows_per_s": round(received / duration_s, 2),
        "events_dropped_by_service": dropped,
        "acks_failed": sum(r.acks_failed for r in results),
        "closed_saturated": sum(r.closed_saturated for r in results),
        "robots_stopped": sum(r.stopped for r in results),
        "e2e_ms": {"p50": percentile(e2e, 50), "p99": percentile(e2e, 99), "max": percentile(e2e, 100)},
        "stages_ms": {s: {"p50": percentile(v, 50), "p99": percentile(v, 99)} for s, v in stages.items()},
        "client_send_lag_ms": {"p50": percentile(lag, 50), "p99": percentile(lag, 99)},
        "server_cpu_percent": round(100 * (cpu1 - cpu0) / (wall1 - wall0), 1),
        "client_cpu_percent": round(100 * (client1 - client0) / (wall1 - wall0), 1),
        # other processes on this (shared) machine during the run: they compete for the same 2 cores
        "others_cpu_percent": round(100 * ((machine1 - machine0) - (cpu1 - cpu0) - (client1 - client0)) / (wall1 - wall0), 1),
        "server_rss_mb": round(rss, 1),
        "server_peak_rss_mb": round(peak, 1),
        "blocks_per_s": round(n / block_s, 1),
    }


async def _pump(url: str, blocks: list[bytes], in_flight: int) -> int:
    """Send blocks as fast as acknowledgements allow (in_flight unacknowledged); returns blocks acknowledged."""
    from websockets.asyncio.client import connect

    async with httpx.AsyncClient(base_url=url, timeout=30) as client:
        session = (await client.post("/sessions", json={"name": "capacity"})).json()
    ws_url = url.replace("http://", "ws://") + f"/sessions/{session['session_id']}/ingest?token={session['robot_token']}"
    acked = 0
    async with connect(ws_url, compression=None) as ws:
        window = asyncio.Semaphore(in_flight)

        async def read_acks() -> None:
            nonlocal acked
            async for _ in ws:
                acked += 1
                window.release()
                if acked == len(blocks):
                    return

        reader = asyncio.create_task(read_acks())
        for payload in blocks:
            await window.acquire()
            if reader.done():  # closed by the service
                break
            await ws.send(payload)
        await reader
    return acked


def measure_capacity(model: Path, library: Path, blocks: list[bytes]) -> dict:
    """One session fed as fast as the service acknowledges: server CPU per block, windows included.

    CPU time per block is what the service costs, and holds up on a busy machine, where latencies
    measure the neighbours as much as the service.
    """
    server = ServerProcess(model, library, {"HAPTICLINK_SESSION_QUEUE_WINDOWS": "1000"})
    try:
        cpu0, wall0 = server.cpu_seconds(), time.perf_counter()
        acked = _run(_pump(server.url, blocks, in_flight=32))
        cpu1, wall1 = server.cpu_seconds(), time.perf_counter()
    finally:
        server.stop()
    per_block_us = 1e6 * (cpu1 - cpu0) / max(acked, 1)
    return {
        "blocks": acked,
        "blocks_per_s": round(acked / (wall1 - wall0), 1),
        "server_cpu_us_per_block": round(per_block_us, 1),
        # a 20 ms-block robot sends 50 blocks/s: the share of one core each robot costs
        "server_core_percent_per_robot": round(per_block_us * 50 / 1e4, 2),
    }


def _metric(text: str, name: str) -> float | None:
    for line in text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    return None


def print_table(rows: list[dict]) -> None:
    head = (f"{'robots':>6} {'repl':>4} {'blocks/s':>8} {'win/s':>6} {'lost':>5} {'e2e p50':>8} {'e2e p99':>8} {'total p99':>9} "
            f"{'queue p99':>9} {'feat p99':>8} {'model p99':>9} {'cpu %':>6} {'rss MB':>7} {'send lag p99':>12} {'others %':>8}")
    print(head)
    print("-" * len(head))
    for r in rows:
        st = r["stages_ms"]
        print(f"{r['robots']:>6} {r['replicas']:>4} {r['blocks_per_s']:>8.0f} {r['windows_per_s']:>6.1f} {r['windows_lost']:>5} "
              f"{r['e2e_ms']['p50']:>8.2f} {r['e2e_ms']['p99']:>8.2f} {st['total']['p99']:>9.2f} {st['queue']['p99']:>9.2f} "
              f"{st['features']['p99']:>8.2f} {st['model']['p99']:>9.2f} {r['server_cpu_percent']:>6.1f} "
              f"{r['server_rss_mb']:>7.1f} {r['client_send_lag_ms']['p99']:>12.2f} {r['others_cpu_percent']:>8.1f}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, nargs="+", default=[1, 10, 50, 100])
    p.add_argument("--duration", type=float, default=20.0, help="seconds of stream per robot (default 20)")
    p.add_argument("--block-s", type=float, default=0.02, help="seconds per block (default 0.02)")
    p.add_argument("--model", type=Path, help="a model to serve (default: ridge-tactile trained on synthetic data)")
    p.add_argument("--library", type=Path, help="a library (default: 12 synthetic textures)")
    p.add_argument("--assets", type=Path, default=Path(tempfile.gettempdir()) / "hapticlink-bench-assets",
                   help="where the default model and library are built and cached")
    p.add_argument("--replicas", type=int, nargs="+", default=[1],
                   help="service processes, robots pinned round-robin as nginx pins sessions (default 1); "
                        "each count runs every --robots N")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    if (args.model is None) != (args.library is None):
        p.error("give both --model and --library, or neither")
    if min(args.replicas) < 1 or min(args.robots) < 1:
        p.error("--robots and --replicas must be ≥ 1")
    model, library = (args.model, args.library) if args.model else prepare_assets(args.assets)
    hop_s = 0.5
    print(f"rendering {max(args.robots)} streams of {args.duration:g} s …", flush=True)
    streams = robot_streams(library, max(args.robots), args.duration, args.block_s, args.seed)
    print("capacity: one session as fast as acknowledged …", flush=True)
    capacity = measure_capacity(model, library, robot_streams(library, 1, 100.0, args.block_s, args.seed + 1)[0])
    print(f"  {capacity['server_cpu_us_per_block']:.0f} µs server CPU per block (windows included), "
          f"{capacity['blocks_per_s']:.0f} blocks/s; {capacity['server_core_percent_per_robot']:.2f} % of a core per 20 ms-block robot",
          flush=True)
    rows = []
    for replicas, n in [(r, n) for r in args.replicas for n in args.robots]:
        print(f"{n} robot(s) on {replicas} replica(s) for {args.duration:g} s …", flush=True)
        rows.append(measure(n, model, library, streams, args.duration, args.block_s, hop_s, args.seed, {}, replicas))
        if rows[-1]["robots_stopped"]:
            print(f"  {rows[-1]['robots_stopped']} robot(s) were closed by the service "
                  f"({rows[-1]['closed_saturated']} with 4429: saturated) and stopped", flush=True)
    print()
    print_table(rows)
    report = {
        "benchmark": "service",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "config": {"block_s": args.block_s, "duration_s": args.duration, "hop_s": hop_s, "transport": "WebSocket, binary blocks",
                   "channels": "accel (n,3) + force (n,3) + speed (n,) at 1 kHz", "model": str(model)},
        "capacity": capacity,
        "results": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
