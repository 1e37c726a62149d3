"""Refuse early, answer always: /health and /ready under overload, what admission refused, memory after a burst.

Run from the repository root:  python -m benchmarks.admission [--robots 150] [--burst 300] [--duration 20]
                                   [--block-s 0.02] [--start together|spread]

One service process (a ridge-tactile model on a small synthetic world, trained here first; the probe port
on). In order:
1. idle: RSS;
2. a burst of `--burst` `POST /sessions` (50 at a time) — created, refused for capacity (429) or past
   max_sessions (503);
3. `--robots` of the created sessions stream in real time (`--block-s` binary blocks, 20 ms by default, over the
   ingest WebSocket, pre-encoded, from two generator processes; each robot sends a block once the previous one is
   acknowledged or due, whichever is later). `--start together` (the default, the hostile case): every robot's
   first block is due at one instant, so every robot completes its windows at the same moment, every hop;
   `--start spread`: robot k starts at a random offset within one 0.5 s hop (seed 0), as robots that were not
   started together would. Reported: each block's acknowledgement time, and the blocks refused
   (close 4429, or its reconnection refused at the handshake with HTTP 429: the robot tries again after Retry-After's
   2 s and resends from its oldest unacknowledged block),
   by the reason the close and the service's counters give;
4. every session is deleted; RSS again after 6 s.
Meanwhile a process of its own polls GET /health and /ready on the service port and GET /health on the probe
port every 20 ms. Reported: each probe's p50/p99/max, the robots' acknowledgement p50/p99 (the oldest half
and the newest half of the streaming sessions apart: admission keeps the oldest at full speed), refusals,
the loop lag and CPU share the service measured, the windows admitted and lost (admitted, never published), the
share of windows published within 100 ms of their last block's arrival, the window latency operators of the 10
oldest and the 10 newest streaming sessions see (their events' latency_ms.total), and RSS idle / loaded / after. Writes
reports/bench/admission.json. Timings on a shared machine are upper bounds: say what else ran.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import multiprocessing as mp
import os
import platform
import sys
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path

import httpx
import numpy as np

from benchmarks.health_poll import poll
from benchmarks.report_file import write_report
from benchmarks.service import memory_mb, percentile
from drivers.blocks import encode_binary
from drivers.protocol import bearer, session_path
from service.launcher import ServerProcess, free_port
from service.metrics import LATENCY_BUCKETS_S

DEFAULT_OUT = Path("reports/bench/admission.json")
API_KEY = "admission-benchmark-key-0123456789"
METRICS_TOKEN = "admission-benchmark-metrics-0123456789"  # the server's GET /metrics credential
BLOCK_S = 0.02  # the default block: the robot client's before it grew to 50 ms, the harder case
HOP_S = 0.5  # the service's window hop: `--start spread` offsets robots within one
#: the end-to-end bound windows are held to (block arrival → window event published), s; a histogram bucket bound
E2E_BOUND_S = 0.1
#: operators subscribe to the events of this many of the oldest and of the newest streaming sessions
WATCHED = 10


def _merged(counts: Iterable[dict[str, int]]) -> dict[str, int]:
    total: dict[str, int] = {}
    for c in counts:
        for key, n in c.items():
            total[key] = total.get(key, 0) + n
    return total


def summary(values: list[float]) -> dict:
    return {
        "n": len(values),
        "p50": percentile(values, 50),
        "p99": percentile(values, 99),
        "max": percentile(values, 100),
    }


def rss_mb(pid: int) -> float:
    """RSS of a process, MiB, to 0.1."""
    return round(memory_mb(pid)[0], 1)


def prepare(root: Path) -> tuple[Path, Path]:
    """(model, library): ridge-tactile on 8 synthetic textures, and a 6-texture synthetic library."""
    from models.offline.datasets.build import build
    from models.offline.train import train_and_export
    from texture_library.synthetic_library import build_synthetic_library

    dataset = build("synthetic", root / "dataset", n_textures=8, duration_s=4)
    model = train_and_export(dataset, "ridge-tactile", root / "ridge-tactile.onnx")
    build_synthetic_library(root / "library", n_textures=6, image_size=256)
    return model, root / "library"


# ---- robots (generator processes) ----------------------------------------------------------------------
def robots(
    ws_url: str, sessions: list[tuple[int, dict, float]], payloads: list[bytes], block_s: float, duration_s: float, out
) -> None:
    """Stream `payloads` (pre-encoded blocks of block_s, seq 0…) to each (rank, session, start offset s) in real
    time; out gets per-robot results."""
    out.put(asyncio.run(_robots(ws_url, sessions, payloads, block_s, duration_s)))


async def _robots(
    ws_url: str, sessions: list[tuple[int, dict, float]], payloads: list[bytes], block_s: float, duration_s: float
) -> list:
    start = time.perf_counter() + 0.5
    return await asyncio.gather(
        *(_robot(ws_url, rank, s, payloads, block_s, start + offset, duration_s) for rank, s, offset in sessions)
    )


async def _robot(
    ws_url: str, rank: int, session: dict, payloads: list[bytes], block_s: float, start: float, duration_s: float
):
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed, InvalidStatus

    url = f"{ws_url}{session_path(session['session_id'], 'ingest')}?token={session['robot_token']}"
    acks: list[float] = []
    refused = reconnects = 0
    closes: dict[str, int] = {}  # "code reason" of every close the service sent
    lag: list[float] = []  # how late the generator sent each block (its own health)
    seq = 0
    end = start + duration_s
    while seq < len(payloads) and time.perf_counter() < end:
        try:
            async with connect(url, max_size=None, compression=None) as ws:
                while seq < len(payloads):
                    due = start + seq * block_s
                    now = time.perf_counter()
                    if now >= end:
                        return _result(rank, acks, refused, reconnects, lag, closes)
                    if due > now:
                        await asyncio.sleep(due - now)
                    sent = time.perf_counter()
                    lag.append((sent - due) * 1e3)
                    await ws.send(payloads[seq])
                    ack = json.loads(await ws.recv())
                    acks.append((time.perf_counter() - sent) * 1e3)
                    if ack.get("ok"):
                        seq += 1
        except ConnectionClosed as exc:
            refused += exc.rcvd is not None and exc.rcvd.code == 4429
            if exc.rcvd is not None:
                why = f"{exc.rcvd.code} {exc.rcvd.reason}"
                closes[why] = closes.get(why, 0) + 1
            reconnects += 1
            await asyncio.sleep(2.0)  # the service's Retry-After
        except InvalidStatus as exc:  # a shed session's reconnection is refused at the handshake (429)
            status = exc.response.status_code
            refused += status == 429
            closes[f"HTTP {status}"] = closes.get(f"HTTP {status}", 0) + 1
            reconnects += 1
            await asyncio.sleep(2.0)
        except OSError:
            reconnects += 1
            await asyncio.sleep(2.0)
    return _result(rank, acks, refused, reconnects, lag, closes)


def _result(rank: int, acks: list[float], refused: int, reconnects: int, lag: list[float], closes: dict) -> dict:
    return {"rank": rank, "acks_ms": acks, "refused": refused, "reconnects": reconnects, "lag": lag, "closes": closes}


# ---- operators (a process of their own) ----------------------------------------------------------------------
def operators(ws_url: str, watched: dict[str, list[dict]], duration_s: float, out) -> None:
    """Subscribe to the events of each group's sessions for duration_s; out gets {group: [window latency_ms]} (the
    service's own measure per stage; total: the completing block's arrival → the window event published)."""
    out.put(asyncio.run(_operators(ws_url, watched, duration_s)))


async def _operators(ws_url: str, watched: dict[str, list[dict]], duration_s: float) -> dict[str, list[dict]]:
    end = time.perf_counter() + duration_s
    groups = {g: await asyncio.gather(*(_operator(ws_url, s, end) for s in ss)) for g, ss in watched.items()}
    return {g: [x for one in lists for x in one] for g, lists in groups.items()}


async def _operator(ws_url: str, session: dict, end: float) -> list[dict[str, float]]:
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed

    url = f"{ws_url}{session_path(session['session_id'], 'events')}?token={session['operator_token']}"
    totals: list[dict[str, float]] = []
    try:
        async with connect(url, max_size=None, compression=None) as ws:
            while (left := end - time.perf_counter()) > 0:
                try:
                    event = json.loads(await asyncio.wait_for(ws.recv(), left))
                except TimeoutError:
                    break
                if event.get("type") == "window":
                    totals.append(event["latency_ms"])
    except (ConnectionClosed, OSError):
        pass
    return totals


def stream_payloads(library: Path, seconds: float, block_s: float = BLOCK_S) -> list[bytes]:
    """One robot's blocks (the same stroke for every robot: the service's cost does not depend on it)."""
    from drivers.source import blocks_from_arrays
    from texture_library.library import Library
    from texture_library.stroke import stroke
    from texture_library.trajectory import freehand, model_ranges

    model = Library.load(library).model(Library.load(library).ids[0])
    rng = np.random.default_rng(0)
    traj = freehand(seconds + 0.5, rng, rate_hz=model.rate_hz, **model_ranges(model.max_speed, model.max_force))
    s = stroke(model, traj, rng)
    channels = {
        "accel": (s.accel, s.rate_hz, "m/s^2"),
        "force": (s.force, s.rate_hz, "N"),
        "speed": (s.speed, s.rate_hz, "mm/s"),
    }
    return [encode_binary(b) for b in blocks_from_arrays(channels, block_s)][: int(seconds / block_s)]


async def burst(url: str, n: int) -> tuple[list[dict], dict[int, int]]:
    created: list[dict] = []
    statuses: dict[int, int] = {}
    limit = asyncio.Semaphore(50)
    async with httpx.AsyncClient(timeout=30) as client:

        async def one(i: int) -> None:
            async with limit:
                r = await client.post(f"{url}/sessions", json={"name": f"b{i}"}, headers=bearer(API_KEY))
            statuses[r.status_code] = statuses.get(r.status_code, 0) + 1
            if r.status_code == 201:
                created.append(r.json())

        await asyncio.gather(*(one(i) for i in range(n)))
    return created, statuses


def metric(text: str, name: str, **labels: str) -> float:
    for line in text.splitlines():
        if line.startswith(name) and all(f'{k}="{v}"' in line for k, v in labels.items()):
            rest = line[len(name) :]
            if rest.startswith((" ", "{")):
                return float(line.rsplit(" ", 1)[1])
    return 0.0


def labelled(text: str, name: str, label: str) -> dict[str, float]:
    """{label value: sample} of a labelled counter or gauge in the metrics text."""
    found: dict[str, float] = {}
    prefix = f'{name}{{{label}="'
    for line in text.splitlines():
        if line.startswith(prefix):
            found[line[len(prefix) :].split('"', 1)[0]] = float(line.rsplit(" ", 1)[1])
    return found


def latency_within(text: str, stage: str, bound_s: float) -> tuple[float, float]:
    """(windows, the share of them published within bound_s of their last block's arrival) from the
    hapticlink_window_latency_seconds histogram (bound_s must be one of its bucket bounds)."""
    count = metric(text, "hapticlink_window_latency_seconds_count", stage=stage)
    within = metric(text, "hapticlink_window_latency_seconds_bucket", stage=stage, le=f"{bound_s}")
    return count, within / count if count else 1.0


def p99_bucket_s(text: str, stage: str) -> float:
    """The smallest bucket bound of hapticlink_window_latency_seconds that holds 99 % of the windows: an upper
    bound of their p99 (inf when the largest finite bucket does not)."""
    count = metric(text, "hapticlink_window_latency_seconds_count", stage=stage)
    for bound in LATENCY_BUCKETS_S:
        if (
            count
            and metric(text, "hapticlink_window_latency_seconds_bucket", stage=stage, le=f"{bound}") >= 0.99 * count
        ):
            return bound
    return math.inf


def drained(url: str, timeout_s: float = 15.0) -> str:
    """The metrics text once every admitted window is published (or timeout_s passed: the rest are lost)."""
    deadline = time.monotonic() + timeout_s
    while True:
        text = httpx.get(f"{url}/metrics", headers=bearer(METRICS_TOKEN), timeout=30).text
        done = metric(text, "hapticlink_windows_total") >= metric(text, "hapticlink_windows_admitted_total")
        if done or time.monotonic() > deadline:
            return text
        time.sleep(0.25)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robots", type=int, default=150)
    parser.add_argument("--burst", type=int, default=300)
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--block-s", type=float, default=BLOCK_S, help="seconds of stream per block (default 0.02)")
    parser.add_argument(
        "--start",
        choices=("together", "spread"),
        default="together",
        help="robots' first blocks due at one instant (default), or each at a random offset within one hop",
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    if not 0.001 <= args.block_s <= 1.0:
        parser.error(f"--block-s must be within 0.001…1 s, got {args.block_s}")

    with tempfile.TemporaryDirectory() as tmp:
        model, library = prepare(Path(tmp))
        probe_port = free_port()
        env = {
            "HAPTICLINK_API_KEYS": API_KEY,
            "HAPTICLINK_METRICS_TOKEN": METRICS_TOKEN,
            "HAPTICLINK_PROBE_PORT": str(probe_port),
            "HAPTICLINK_SESSION_BURST": str(args.burst + 10),
            "HAPTICLINK_MAX_SESSIONS": str(args.burst + 10),
            "HAPTICLINK_LOG_LEVEL": "warning",
        }
        cmd = [sys.executable, "-m", "service.cli", "serve", "--model", str(model), "--library", str(library)]
        server = ServerProcess(cmd, env)
        payloads = stream_payloads(library, args.duration + 1, args.block_s)
        report: dict = {
            "command": "python -m benchmarks.admission " + " ".join(argv or sys.argv[1:]),
            "args": {**vars(args), "out": str(args.out)},
        }
        report["machine"] = {
            "cpus": os.cpu_count(),
            "load_average": os.getloadavg(),
            "python": platform.python_version(),
        }
        try:
            time.sleep(2)
            report["rss_mb"] = {"idle": rss_mb(server.proc.pid)}
            ctx = mp.get_context("spawn")
            stop, polled = ctx.Event(), ctx.Queue()
            urls = {
                "service /health": f"{server.url}/health",
                "service /ready": f"{server.url}/ready",
                "probe port /health": f"http://127.0.0.1:{probe_port}/health",
            }
            poller = ctx.Process(target=poll, args=(urls, stop, polled))
            poller.start()
            created, statuses = asyncio.run(burst(server.url, args.burst))
            report["burst"] = {"requests": args.burst, "statuses": statuses}
            rng = np.random.default_rng(0)
            offsets = rng.uniform(0, HOP_S, len(created)) if args.start == "spread" else np.zeros(len(created))
            streaming = [(k, s, float(offsets[k])) for k, s in enumerate(created[: args.robots])]
            halves = [streaming[0::2], streaming[1::2]]
            results = ctx.Queue()
            ws_url = server.url.replace("http://", "ws://")
            gens = [
                ctx.Process(target=robots, args=(ws_url, h, payloads, args.block_s, args.duration, results))
                for h in halves
            ]
            # the operators of the WATCHED oldest and newest streaming sessions: their windows' latency
            ordered = [s for _, s, _ in streaming]
            watched = {"oldest": ordered[:WATCHED], "newest": ordered[-WATCHED:]}
            events = ctx.Queue()
            watcher = ctx.Process(target=operators, args=(ws_url, watched, args.duration + 2, events))
            watcher.start()
            lag_samples, cpu_samples, process_samples = [], [], []
            for g in gens:
                g.start()
            deadline = time.monotonic() + args.duration + 1
            peak = report["rss_mb"]["idle"]
            while time.monotonic() < deadline:
                time.sleep(1.0)
                text = httpx.get(f"{server.url}/metrics", headers=bearer(METRICS_TOKEN), timeout=30).text
                lag_samples.append(metric(text, "hapticlink_loop_lag_seconds") * 1e3)
                cpu_samples.append(metric(text, "hapticlink_loop_cpu_share"))
                process_samples.append(metric(text, "hapticlink_process_cpu_share"))
                peak = max(peak, rss_mb(server.proc.pid))
            per_robot = [r for _ in gens for r in results.get(timeout=120)]
            for g in gens:
                g.join(timeout=30)
            window_latency = events.get(timeout=60)
            watcher.join(timeout=30)
            final = drained(server.url)
            with httpx.Client(timeout=30) as client:
                for s in created:
                    client.delete(server.url + session_path(s["session_id"]), headers=bearer(s["robot_token"]))
            time.sleep(6)  # the service gives memory back on its next reaper pass (every 5 s)
            report["rss_mb"].update({"loaded_peak": peak, "after_sessions_deleted": rss_mb(server.proc.pid)})
            stop.set()
            probes = polled.get(timeout=60)
            poller.join(timeout=30)
        finally:
            server.stop()
    n = len(per_robot)
    ranked = sorted(per_robot, key=lambda r: r["rank"])
    oldest, newest = ranked[: n // 2], ranked[n // 2 :]
    report["probes_ms"] = {
        name: {**summary([t for t in ts if t >= 0]), "failed": sum(t < 0 for t in ts)} for name, ts in probes.items()
    }
    report["robots"] = {
        "streaming": n,
        "acks_ms_oldest_half": summary([a for r in oldest for a in r["acks_ms"]]),
        "acks_ms_newest_half": summary([a for r in newest for a in r["acks_ms"]]),
        "blocks_acknowledged": sum(len(r["acks_ms"]) for r in per_robot),
        "closed_4429": sum(r["refused"] for r in per_robot),
        "closes_by_reason": _merged(r["closes"] for r in per_robot),
        "reconnects": sum(r["reconnects"] for r in per_robot),
        "generator_lag_ms": summary([x for r in per_robot for x in r["lag"]]),
    }
    report["service"] = {
        "loop_lag_ms_each_second": [round(x, 1) for x in lag_samples],
        "loop_cpu_share_each_second": [round(x, 3) for x in cpu_samples],
        "process_cpu_share_each_second": [round(x, 3) for x in process_samples],
        "blocks_refused": metric(final, "hapticlink_blocks_total", outcome="refused"),
        "blocks_refused_by_reason": labelled(final, "hapticlink_blocks_refused_total", "reason"),
        "sessions_refused_capacity": metric(final, "hapticlink_sessions_refused_total", reason="capacity"),
        "sessions_shed": metric(final, "hapticlink_sessions_shed_total"),
    }
    admitted = metric(final, "hapticlink_windows_admitted_total")
    published = metric(final, "hapticlink_windows_total")
    windows, within = latency_within(final, "total", E2E_BOUND_S)
    report["windows"] = {
        "admitted": admitted,
        "published": published,
        "admitted_lost": admitted - published,
        # ingest → publish of every published window (the robots still streaming: the shed ones send nothing)
        f"published_within_{E2E_BOUND_S * 1e3:g}_ms": round(within, 4),
        "latency_p99_at_most_ms": {st: p99_bucket_s(final, st) * 1e3 for st in ("queue", "features", "model", "total")},
        "latency_observed": windows,
        # the service's latency of the windows the operators of the oldest / newest WATCHED sessions received
        "e2e_ms_oldest": summary([w["total"] for w in window_latency["oldest"]]),
        "e2e_ms_newest": summary([w["total"] for w in window_latency["newest"]]),
        # where the oldest sessions' windows spent their time (queue: arrival → their batch began)
        "stages_ms_oldest": {
            st: summary([w[st] for w in window_latency["oldest"]]) for st in ("queue", "features", "model", "lookup")
        },
    }
    report["machine"]["load_average_after"] = os.getloadavg()
    write_report(args.out, report)
    print(json.dumps({k: report[k] for k in ("burst", "probes_ms", "robots", "windows", "rss_mb")}, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
