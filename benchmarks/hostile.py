"""The hostile-client probe's worst cases against a live service, beside well-behaved robots.

Run from the repository root:  python -m benchmarks.hostile [--robots 20] [--burst-robots 150] [--duration 20]
                                   [--lead-s 20]

One service process (the `served` configuration of benchmarks/service.py: visual+tactile model,
tactile-only fallback, camera frames at 1 fps). `--robots` well-behaved robots (the real RobotClient, in a
process of their own) stream in real time with an operator each for `--duration` + `--lead-s` seconds, while,
in this order:
1. a client posts the probe's 2.8 MB block (10 Hz, 100 000 samples per channel) a few times;
2. a client sends 300 `POST /sessions` within a second (with a valid key; its own address via
   X-Forwarded-For, since every robot here shares 127.0.0.1, whose budget is set to 200);
3. a client sends a block with seq 2^62 into its own session, then good blocks;
4. `--burst-robots` more robots (another process) start within one hop of each other, each with a camera
   frame at once, and stream for `--duration` seconds.
Meanwhile a third process polls /health every 20 ms: no load generator's event loop sits between the probe
and the service. Reported: /health p50/p99/max, the well-behaved robots' windows lost and end-to-end p50/p99
(overall and while the burst streamed), each robots process's own send lag and event-loop lag (a generator
that falls behind inflates the latencies it reports), what was refused (and how), and whether the seq-2^62
session still produced windows. Writes reports/bench/hostile.json.

`--case crowd` runs the crowd instead (`crowd_case`): one service process (the `served` configuration, its probe port
on), a burst of 300 `POST /sessions` from one client address that then sends nothing, and two seconds later
`--burst-robots` real RobotClients (two processes) with a camera frame at 1 fps each, starting within one hop and
streaming `--duration` s in the robot client's default blocks, an operator each, while a process of its own polls
/health on the service port and on the probe port every 20 ms. Per robot it records every window's arrival and
what the window was estimated from. It writes the `crowd` object into the report file (the other objects there are
kept): per run the fraction of the admitted robots' windows estimated (tactile-only ones, and those marked missing
the frame), the longest any admitted robot went without a window, the readmission wait of refused robots (the
service's `hapticlink_readmit_seconds`: from room for the robot to its next block accepted), /health p99 on both
ports, accepted windows lost (`hapticlink_windows_admitted_total` − `hapticlink_windows_total` after the drain), what
was refused and the ERROR lines of the service's log; the top-level figures are the worst of `--runs` runs.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import math
import multiprocessing as mp
import os
import secrets
import sys
import time
from pathlib import Path

import httpx
import numpy as np

from benchmarks.health_poll import poll
from benchmarks.loadgen import frame_of, receive, robot_streams
from benchmarks.report_file import write_report, write_section
from benchmarks.service import (
    DEFAULT_ASSETS,
    HOP_S,
    SCRAPER,
    Assets,
    ServerProcess,
    _metric_sum,
    _run,
    generator_lag_limit_ms,
    percentile,
    prepare_assets,
    run_load,
    timeline,
)
from drivers.blocks import ChannelBlock, SampleBlock, encode_binary
from drivers.protocol import BINARY_CONTENT_TYPE, bearer, session_path
from drivers.source import DEFAULT_BLOCK_S
from service.launcher import free_port

DEFAULT_OUT = Path("reports/bench/hostile.json")


async def attacks(url: str, api_key: str, assets: Assets, block_s: float, report: dict) -> None:
    """The probe's requests, one after another, each answer recorded."""
    async with httpx.AsyncClient(timeout=30) as client:
        while (
            r := await client.post(f"{url}/sessions", json={"name": "attacker"}, headers=bearer(api_key))
        ).status_code == 429:
            await asyncio.sleep(float(r.headers.get("Retry-After", "1")))  # the replica is busy with the robots' start
        r.raise_for_status()
        session = r.json()
        robot = {**bearer(session["robot_token"]), "Content-Type": BINARY_CONTENT_TYPE}
        blocks_url = url + session_path(session["session_id"], "blocks")
        # 1. the 2.8 MB, 10 Hz block
        n = 100_000
        rng = np.random.default_rng(0)
        huge = SampleBlock(
            0.0,
            {
                "accel": ChannelBlock(rng.normal(size=(n, 3)).astype(np.float32), 10.0, "m/s^2"),
                "force": ChannelBlock(rng.normal(size=(n, 3)).astype(np.float32), 10.0, "N"),
                "speed": ChannelBlock(np.full(n, 50.0, np.float32), 10.0, "mm/s"),
            },
            0,
        )
        payload = encode_binary(huge)
        answers = []
        for _ in range(3):
            t0 = time.perf_counter()
            r = await client.post(blocks_url, content=payload, headers=robot)
            answers.append(
                {
                    "status": r.status_code,
                    "ms": round((time.perf_counter() - t0) * 1e3, 1),
                    "detail": r.json().get("detail", "")[:120],
                }
            )
        report["huge_block"] = {"bytes": len(payload), "answers": answers}
        # 2. 300 session requests in about a second, from one client (named by X-Forwarded-For, which the
        # service trusts from loopback, as from nginx): the robots' own address keeps its budget
        t0 = time.perf_counter()
        flood = {**bearer(api_key), "X-Forwarded-For": "198.51.100.7"}
        codes = await asyncio.gather(*(client.post(f"{url}/sessions", json={}, headers=flood) for _ in range(300)))
        report["session_flood"] = {
            "requests": 300,
            "seconds": round(time.perf_counter() - t0, 2),
            "statuses": {str(s): sum(r.status_code == s for r in codes) for s in {r.status_code for r in codes}},
        }
        # 3. seq 2^62, then good blocks: the session must keep producing windows
        # (a taps model's stream opens with its tap block; seq numbers every block of it in order)
        good = [
            dataclasses.replace(b, seq=i)
            for i, b in enumerate(robot_streams(assets.library, 1, 2.0, block_s, seed=7, taps=assets.taps)[0])
        ]
        first = next(b for b in good if isinstance(b, SampleBlock))
        r = await client.post(
            blocks_url, content=encode_binary(SampleBlock(first.t0, first.channels, 2**62)), headers=robot
        )
        statuses = [r.status_code]
        for b in good:
            statuses.append((await client.post(blocks_url, content=encode_binary(b), headers=robot)).status_code)
        await asyncio.sleep(1.0)
        status = (
            await client.get(url + session_path(session["session_id"]), headers=bearer(session["operator_token"]))
        ).json()
        report["seq_2_62"] = {
            "first_answer": statuses[0],
            "good_blocks_accepted": statuses[1:].count(202),
            "good_blocks": len(good),
            "windows_after": status["counters"]["windows"],
        }


def loop_lag(out: list[float], every_s: float = 0.01):
    """A task that records how late this process's event loop wakes it (ms): the generator's own health."""

    async def tick() -> None:
        while True:
            t0 = time.perf_counter()
            await asyncio.sleep(every_s)
            out.append(max(0.0, time.perf_counter() - t0 - every_s) * 1e3)

    return asyncio.create_task(tick())


def _stream_robots(
    url: str, assets: Assets, ks: list[int], seconds: float, block_s: float, api_key: str, seed: int, conn
) -> tuple[list, list, list, list[float]] | None:
    """The part a robots' process shares: render robots `ks`' streams and frames, send ("ready",), wait for "go",
    stream them in real time while timing the process's event loop → (stats, views, sources, loop lag ms); None after
    sending ("error", text)."""
    streams = robot_streams(assets.library, len(ks), seconds, block_s, taps=assets.taps, indices=ks)
    frames = [frame_of(assets.library, k) for k in ks]
    conn.send(("ready", None))
    conn.recv()

    async def go():
        lag: list[float] = []
        ticking = loop_lag(lag)
        try:
            return await run_load([url], streams, frames, block_s, api_key, seed), lag
        finally:
            ticking.cancel()

    try:
        (stats, views, sources), lag = _run(go())
    except Exception as exc:  # noqa: BLE001 - reported in the row
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return None
    return stats, views, sources, lag


def robots_process(
    url: str, assets: Assets, ks: list[int], seconds: float, block_s: float, api_key: str, seed: int, conn
) -> None:
    """A process of robots: renders robots `ks`' streams (`seconds` long) and camera frames, sends ("ready",),
    waits for "go", streams them in real time (real RobotClients, an operator each) while timing its own event
    loop, and sends ("result", {...}) — or ("error", text)."""
    ran = _stream_robots(url, assets, ks, seconds, block_s, api_key, seed, conn)
    if ran is None:
        return
    stats, views, sources, lag = ran
    conn.send(
        (
            "result",
            {
                "windows": sum(v.windows for v in views),
                "windows_tactile_only": sum(v.inputs.get("tactile", 0) for v in views),
                "e2e": [(t, ms) for v in views for t, ms in zip(v.received_at, v.e2e_ms)],
                "features_ms": [x for v in views for x in v.stages_ms["features"]],
                "streaming": (min(s.start for s in sources), max(s.start for s in sources) + seconds),
                "send_lag_ms": [x for s in sources for x in s.send_lag_ms],
                "loop_lag_ms": lag,
                "operator_errors": [v.error for v in views if v.error],
                "robot_counts": {
                    name: sum(getattr(st, name) for st in stats)
                    for name in ("sent", "resent", "acked", "rejected", "lost", "reconnects", "saturated")
                },
            },
        )
    )


# ---- the crowd: robots with cameras after a session burst ----------------------------------------------------------
#: requests of the session burst that comes before the crowd (one client address, nothing sent after)
CROWD_BURST = 300
#: the crowd's robots, the longest any admitted one may go without a window (s)
CROWD_GAP_S = 2.0


def crowd_robots_process(
    url: str, assets: Assets, ks: list[int], seconds: float, block_s: float, api_key: str, seed: int, conn
) -> None:
    """A process of crowd robots (real RobotClients with camera frames, an operator each): as robots_process, but
    what comes back is per robot — its start, every window's arrival (perf_counter), what its windows were estimated
    from, its counters — so that gaps and the admitted robots can be told apart."""
    ran = _stream_robots(url, assets, ks, seconds, block_s, api_key, seed, conn)
    if ran is None:
        return
    stats, views, sources, lag = ran
    robots = [
        {
            "start": src.start,
            "received_at": list(v.received_at),
            "e2e_ms": list(v.e2e_ms),
            "windows": v.windows,
            "tactile_only": v.inputs.get("tactile", 0),
            "marked_frame": v.missing.get("frame", 0),
            "operator_error": v.error,
            **{name: getattr(st, name) for name in ("acked", "sent", "saturated", "frames_sent", "frames_refused")},
        }
        for st, v, src in zip(stats, views, sources)
    ]
    conn.send(
        (
            "result",
            {
                "robots": robots,
                "send_lag_ms": [x for src in sources for x in src.send_lag_ms],
                "loop_lag_ms": lag,
            },
        )
    )


def robot_gap_s(start: float, received_at: list[float], seconds: float, first_window_s: float) -> float:
    """The longest a robot streaming from `start` (perf_counter, s) for `seconds` went without a window: from its first
    window's due time (start + first_window_s) to its first window, between windows, and from its last window to the
    end of its stream (its last window is due then). No window at all: the whole stream. A robot refused a start
    counts from its stream's start: its session was admitted, its robot was not served."""
    times = [start + first_window_s, *sorted(received_at)]
    end = start + seconds
    gaps = [b - a for a, b in zip(times[:-1], times[1:])]
    if times[-1] < end:
        gaps.append(end - times[-1])
    return max([0.0, *gaps])


def histogram_quantile(metrics: str, name: str, q: float) -> tuple[float | None, int]:
    """(the q-quantile's bucket upper bound, observations) of Prometheus histogram `name` in the exposition `metrics`:
    the upper bound of the first bucket that holds a q share of the observations (None when there are none, inf when
    beyond the last finite bucket)."""
    buckets: list[tuple[float, float]] = []
    for line in metrics.splitlines():
        if line.startswith(f"{name}_bucket{{"):
            le = line.split('le="', 1)[1].split('"', 1)[0]
            buckets.append((math.inf if le == "+Inf" else float(le), float(line.rsplit(" ", 1)[1])))
    buckets.sort()
    total = buckets[-1][1] if buckets else 0.0
    if total == 0:
        return None, 0
    for bound, count in buckets:
        if count >= q * total:
            return bound, int(total)
    return math.inf, int(total)


def _p99(values: list[float]) -> float | None:
    return percentile(values, 99) if values else None


def crowd_run(assets: Assets, api_key: str, robots: int, seconds: float, block_s: float) -> dict:
    """One crowd run against a fresh service process (see the module docstring) → its figures."""
    probe_port = free_port()
    server = ServerProcess.service(
        assets,
        api_key,
        instance_id="crowd",
        extra={
            "HAPTICLINK_MAX_SESSIONS": "512",  # the burst's sessions all open: the crowd comes on top of them
            "HAPTICLINK_PROBE_PORT": str(probe_port),
        },
    )
    ctx = mp.get_context("spawn")
    half = (robots + 1) // 2
    shares = [list(range(0, half)), list(range(half, robots))]
    procs, pipes = [], []
    stop, polled = ctx.Event(), ctx.Queue()
    urls = {"service": f"{server.url}/health", "probe": f"http://127.0.0.1:{probe_port}/health"}
    poller = ctx.Process(target=poll, args=(urls, stop, polled), daemon=True)
    report: dict = {}
    try:
        for g, ks in enumerate(shares):
            parent, child = ctx.Pipe()
            proc = ctx.Process(
                target=crowd_robots_process,
                args=(server.url, assets, ks, seconds, block_s, api_key, g, child),
                daemon=True,
            )
            proc.start()
            procs.append(proc)
            pipes.append(parent)
        for pipe, proc in zip(pipes, procs):
            receive(pipe, proc, "ready")
        poller.start()
        report["session_burst"] = _run(session_burst(server.url, api_key))
        time.sleep(2.0)  # the burst's sessions stop counting as starting; the crowd comes
        for pipe in pipes:
            pipe.send("go")
        results = [receive(pipe, proc, "result") for pipe, proc in zip(pipes, procs)]
        stop.set()
        health = polled.get(timeout=30)
        metrics = _drained_metrics(server.url)
    finally:
        server.stop()
        for proc in [*procs, poller]:
            if proc.pid is not None:
                proc.join(timeout=10)
                if proc.is_alive():
                    proc.kill()
    log = server.proc.stderr.read() if server.proc.stderr else ""
    per_robot = [r for res in results for r in res["robots"]]
    admitted = [r for r in per_robot if r["acked"] > 0]
    per_robot_windows = int(seconds / HOP_S + 1e-9)
    expected = per_robot_windows * len(admitted)
    received = sum(r["windows"] for r in admitted)
    gaps = [robot_gap_s(r["start"], r["received_at"], seconds, 2 * HOP_S) for r in admitted]
    # the same from each robot's first window on: what a robot let start late went without once it streamed
    streamed = [r for r in admitted if r["received_at"]]
    gaps_after = [
        robot_gap_s(min(r["received_at"]), r["received_at"], seconds - (min(r["received_at"]) - r["start"]), 0.0)
        for r in streamed
    ]
    first_window_s = [min(r["received_at"]) - r["start"] for r in streamed]
    readmit_p99, readmitted = histogram_quantile(metrics, "hapticlink_readmit_seconds", 0.99)
    admitted_windows = _metric_sum(metrics, "hapticlink_windows_admitted_total")
    published = _metric_sum(metrics, "hapticlink_windows_total")
    for name in ("service", "probe"):
        failed = sum(x < 0 for x in health[name])
        health[name] = {"ok": [x for x in health[name] if x >= 0], "failed": failed}
    report.update(
        {
            "robots": len(per_robot),
            "robots_admitted": len(admitted),
            "windows_expected": expected,
            "windows_received": received,
            "windows_estimated_fraction": round(received / expected, 4) if expected else None,
            "windows_tactile_only": sum(r["tactile_only"] for r in admitted),
            "windows_marked_missing_frame": sum(r["marked_frame"] for r in admitted),
            "max_robot_gap_s": round(max(gaps), 3) if gaps else None,
            "robots_gap_over_2s": sum(g > CROWD_GAP_S for g in gaps),
            "robot_gap_s_p50": percentile(gaps, 50) if gaps else None,
            "robots_without_a_window": sum(not r["received_at"] for r in per_robot),
            "robots_never_started": len(per_robot) - len(admitted),
            "max_robot_gap_after_first_window_s": round(max(gaps_after), 3) if gaps_after else None,
            "first_window_s": {
                "p50": percentile(first_window_s, 50) if first_window_s else None,
                "max": round(max(first_window_s), 3) if first_window_s else None,
            },
            "readmit_s_p99": readmit_p99,
            "readmitted": readmitted,
            "health_p99_ms": {name: _p99(health[name]["ok"]) for name in ("service", "probe")},
            "health_max_ms": {name: percentile(health[name]["ok"], 100) for name in ("service", "probe")},
            "health_polls": {name: len(health[name]["ok"]) for name in ("service", "probe")},
            "health_failed": {name: health[name]["failed"] for name in ("service", "probe")},
            "windows_lost": int(admitted_windows - published),
            "windows_admitted_service": int(admitted_windows),
            "refused": {
                "frames": int(_metric_sum(metrics, "hapticlink_frames_total", outcome="refused")),
                "frames_embedded": int(_metric_sum(metrics, "hapticlink_visual_embedding_seconds_count")),
                "blocks_shed": int(_metric_sum(metrics, "hapticlink_blocks_refused_total", reason="capacity")),
                "sessions_shed": int(_metric_sum(metrics, "hapticlink_sessions_shed_total")),
                "sessions_capacity": int(_metric_sum(metrics, "hapticlink_sessions_refused_total", reason="capacity")),
            },
            "robot_counts": {
                name: sum(r[name] for r in per_robot)
                for name in ("sent", "acked", "saturated", "frames_sent", "frames_refused")
            },
            "operator_errors": [r["operator_error"] for r in per_robot if r["operator_error"]][:5],
            # the longest any window waited between its block leaving the robot and its operator receiving it: the
            # service's share of a robot's gap, whatever the generator's own lag
            "window_e2e_s_max": round(max((x for r in admitted for x in r["e2e_ms"]), default=0.0) / 1e3, 3),
            "window_e2e_ms_p99": _p99([x for r in admitted for x in r["e2e_ms"]]),
            "robots_e2e_over_2s": sum(max(r["e2e_ms"], default=0.0) > CROWD_GAP_S * 1e3 for r in admitted),
            "generator_send_lag_ms_p99": _p99([x for res in results for x in res["send_lag_ms"]]),
            "generator_loop_lag_ms_p99": _p99([x for res in results for x in res["loop_lag_ms"]]),
            # as benchmarks.service judges a row: a generator more than a quarter block late measured itself
            "valid": (_p99([x for res in results for x in res["send_lag_ms"]]) or 0.0)
            <= generator_lag_limit_ms(block_s),
            "error_lines": [line for line in log.splitlines() if " ERROR " in line or line.startswith("ERROR")][:5],
            "log_lines": len(log.splitlines()),
        }
    )
    return report


def _drained_metrics(url: str, within_s: float = 15.0) -> str:
    """The service's metrics once every window admitted has been published (or `within_s` has passed): windows still
    being estimated at the end are not lost."""
    deadline = time.monotonic() + within_s
    while True:
        metrics = httpx.get(f"{url}/metrics", headers=SCRAPER, timeout=30).text
        admitted = _metric_sum(metrics, "hapticlink_windows_admitted_total")
        if admitted <= _metric_sum(metrics, "hapticlink_windows_total") or time.monotonic() > deadline:
            return metrics
        time.sleep(0.5)


async def session_burst(url: str, api_key: str) -> dict:
    """CROWD_BURST session requests in about a second from one client address (X-Forwarded-For, which the service
    trusts from loopback, as from nginx); the sessions opened are left to idle."""
    async with httpx.AsyncClient(timeout=30) as client:
        t0 = time.perf_counter()
        flood = {**bearer(api_key), "X-Forwarded-For": "198.51.100.9"}
        codes = await asyncio.gather(
            *(client.post(f"{url}/sessions", json={}, headers=flood) for _ in range(CROWD_BURST))
        )
    return {
        "requests": CROWD_BURST,
        "seconds": round(time.perf_counter() - t0, 2),
        "statuses": {str(s): sum(r.status_code == s for r in codes) for s in {r.status_code for r in codes}},
    }


#: the crowd's figures and whether the worst run must be the largest (True) or the smallest (False) of them
CROWD_WORST = {
    "windows_estimated_fraction": False,
    "max_robot_gap_s": True,
    "readmit_s_p99": True,
    "windows_lost": True,
}


def crowd_case(args: argparse.Namespace) -> dict:
    """`--runs` crowd runs → the `crowd` object: the issue's figures as the worst over the runs, and every run."""
    api_key = secrets.token_urlsafe(24)
    assets = prepare_assets(args.assets)["served"]
    block_s = args.block_s if args.block_s is not None else DEFAULT_BLOCK_S
    cpu = next(
        (
            line.split(":", 1)[1].strip()
            for line in Path("/proc/cpuinfo").read_text().splitlines()
            if "model name" in line
        ),
        "unknown",
    )
    load_before = os.getloadavg()
    runs = []
    for i in range(args.runs):
        print(f"crowd run {i + 1} of {args.runs} …", flush=True)
        runs.append(crowd_run(assets, api_key, args.burst_robots, args.duration, block_s))
        print(json.dumps({k: runs[-1][k] for k in (*CROWD_WORST, "health_p99_ms")}), flush=True)
    crowd: dict = {}
    for name, largest in CROWD_WORST.items():
        values = [r[name] for r in runs if r[name] is not None]
        crowd[name] = (max(values) if largest else min(values)) if values else None
    crowd["health_p99_ms"] = {
        port: max((r["health_p99_ms"][port] for r in runs if r["health_p99_ms"][port] is not None), default=None)
        for port in ("service", "probe")
    }
    crowd.update(
        {
            "summary": f"worst of {len(runs)} runs",
            "command": "python -m benchmarks.hostile --case crowd "
            + f"--burst-robots {args.burst_robots} --duration {args.duration:g} --runs {args.runs}"
            + (f" --block-s {args.block_s:g}" if args.block_s is not None else ""),
            "setup": {
                "session_burst": CROWD_BURST,
                "robots": args.burst_robots,
                "duration_s": args.duration,
                "block_s": block_s,
                "frame_every_s": 1.0,
                "config": "served",
            },
            "host": {"cpu": cpu, "cpus": os.cpu_count(), "load_average_before": [round(x, 2) for x in load_before]},
            "runs": runs,
        }
    )
    crowd["host"]["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    return crowd


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, default=20, help="well-behaved robots streaming throughout")
    p.add_argument("--burst-robots", type=int, default=150, help="robots that start together, each with a frame")
    p.add_argument("--duration", type=float, default=20.0, help="the burst robots' stream, s")
    p.add_argument(
        "--lead-s",
        type=float,
        default=20.0,
        help="the well-behaved robots stream this much longer than the burst, s (the attacks and the burst's "
        "set-up come first)",
    )
    p.add_argument(
        "--block-s",
        type=float,
        default=None,
        help="block length, s (the probe case: 0.02; the crowd: the robot client's default)",
    )
    p.add_argument("--assets", type=Path, default=DEFAULT_ASSETS, help="the demo's assets (built when missing)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument(
        "--case",
        choices=("probe", "crowd"),
        default="probe",
        help="probe: the hostile probe's worst cases beside well-behaved robots (the report's top level); crowd: "
        "robots with cameras after a session burst (its `crowd` object)",
    )
    p.add_argument("--runs", type=int, default=2, help="crowd runs (the host is shared: its figures are the worst)")
    add_restart_arguments(p)
    args = p.parse_args(argv)
    if args.only == "restart":
        return restart_only(args, argv)
    if args.case == "crowd":
        crowd = crowd_case(args)
        print(json.dumps({k: v for k, v in crowd.items() if k != "runs"}, indent=2))
        write_section(args.out, "crowd", crowd)
        print(f"wrote {args.out} (crowd)")
        return 0
    if args.block_s is None:
        args.block_s = 0.02
    api_key = secrets.token_urlsafe(24)
    assets = prepare_assets(args.assets)["served"]
    server = ServerProcess.service(
        assets,
        api_key,
        instance_id="hostile",
        # every robot of this process is one address: a budget for them all
        extra={"HAPTICLINK_SESSION_BURST": "200", "HAPTICLINK_MAX_SESSIONS": "512"},
    )
    steady_s = args.duration + args.lead_s
    report: dict = {
        "robots": args.robots,
        "burst_robots": args.burst_robots,
        "duration_s": args.duration,
        "well_behaved_duration_s": steady_s,
    }
    ctx = mp.get_context("spawn")  # fresh interpreters: each loop measures only its own robots
    roles = {
        "well_behaved": (list(range(args.robots)), steady_s, 0),
        "burst": (list(range(args.robots, args.robots + args.burst_robots)), args.duration, 1),
    }
    procs, pipes = {}, {}
    stop, polled = ctx.Event(), ctx.Queue()
    poller = ctx.Process(target=poll, args=({"health": f"{server.url}/health"}, stop, polled), daemon=True)
    try:
        for role, (ks, seconds, seed) in roles.items():
            pipes[role], child = ctx.Pipe()
            procs[role] = ctx.Process(
                target=robots_process,
                args=(server.url, assets, ks, seconds, args.block_s, api_key, seed, child),
                daemon=True,
            )
            procs[role].start()
        for role in roles:
            receive(pipes[role], procs[role], "ready")
        poller.start()
        pipes["well_behaved"].send("go")
        t_go = time.perf_counter()
        time.sleep(3.0)  # the well-behaved robots open their sessions before the flood (it may not starve them)
        _run(attacks(server.url, api_key, assets, args.block_s, report))
        t_attacked = time.perf_counter()
        pipes["burst"].send("go")
        results = {role: receive(pipes[role], procs[role], "result") for role in roles}
        stop.set()
        health = polled.get(timeout=30)["health"]
        metrics = httpx.get(f"{server.url}/metrics", headers=SCRAPER).text
    finally:
        server.stop()
        for proc in [*procs.values(), poller]:
            if proc.pid is not None:
                proc.join(timeout=10)
                if proc.is_alive():
                    proc.kill()
    failed = [x for x in health if x < 0]
    health = [x for x in health if x >= 0]
    report["health_ms"] = {
        "p50": percentile(health, 50),
        "p99": percentile(health, 99),
        "max": percentile(health, 100),
        "polls": len(health),
        "failed": len(failed),
    }
    steady, burst = results["well_behaved"], results["burst"]
    b0, b1 = burst["streaming"]
    expected = args.robots * int(steady_s / HOP_S + 1e-9)
    e2e = [ms for _, ms in steady["e2e"]]
    during = [ms for t, ms in steady["e2e"] if b0 <= t <= b1]
    report["phases_s"] = {  # from the well-behaved robots' go
        "attacks": [3.0, round(t_attacked - t_go, 1)],
        "burst_streaming": [round(b0 - t_go, 1), round(b1 - t_go, 1)],
        "well_behaved_streaming": [round(x - t_go, 1) for x in steady["streaming"]],
    }
    report["well_behaved_timeline"] = timeline(steady["e2e"], t_go)
    report["well_behaved"] = {
        "windows_expected": expected,
        "windows_received": steady["windows"],
        "windows_lost": expected - steady["windows"],
        "e2e_ms": {"p50": percentile(e2e, 50), "p99": percentile(e2e, 99)},
        "e2e_ms_during_burst": {"n": len(during), "p50": percentile(during, 50), "p99": percentile(during, 99)},
        "features_ms_p99": percentile(steady["features_ms"], 99),
        "generator_send_lag_ms_p99": percentile(steady["send_lag_ms"], 99),
        "generator_loop_lag_ms_p99": percentile(steady["loop_lag_ms"], 99),
        "operator_errors": steady["operator_errors"][:5],
        "robot_counts": steady["robot_counts"],
    }
    bexpected = args.burst_robots * int(args.duration / HOP_S + 1e-9)
    report["burst"] = {
        "windows_expected": bexpected,
        "windows_received": burst["windows"],
        "windows_tactile_only": burst["windows_tactile_only"],
        "e2e_ms_p99": percentile([ms for _, ms in burst["e2e"]], 99),
        "generator_send_lag_ms_p99": percentile(burst["send_lag_ms"], 99),
        "generator_loop_lag_ms_p99": percentile(burst["loop_lag_ms"], 99),
        "robot_counts": burst["robot_counts"],
    }
    report["refused"] = {
        "blocks": int(_metric_sum(metrics, "hapticlink_blocks_total", outcome="refused")),
        "frames": int(_metric_sum(metrics, "hapticlink_frames_total", outcome="refused")),
        "blocks_shed": int(_metric_sum(metrics, "hapticlink_blocks_refused_total", reason="capacity")),
        "blocks_session_queue_full": int(
            _metric_sum(metrics, "hapticlink_blocks_refused_total", reason="session_queue")
        ),
        "sessions_shed": int(_metric_sum(metrics, "hapticlink_sessions_shed_total")),
        "sessions_rate": int(_metric_sum(metrics, "hapticlink_sessions_refused_total", reason="rate")),
        "sessions_capacity": int(_metric_sum(metrics, "hapticlink_sessions_refused_total", reason="capacity")),
        "frames_embedded": int(_metric_sum(metrics, "hapticlink_visual_embedding_seconds_count")),
    }
    print(json.dumps(report, indent=2))
    if args.out.exists():  # the other cases' objects stay
        previous = json.loads(args.out.read_text())
        report.update({k: previous[k] for k in ("crowd", "restart") if k in previous})
    write_report(args.out, report)
    print(f"wrote {args.out}")
    return 0


# ---- the restart case (benchmarks/restart.py) ------------------------------------------------------------------
def add_restart_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--only",
        choices=("all", "restart"),
        default="all",
        help="restart: only the restart case (the file's other objects are kept as they are)",
    )
    p.add_argument("--restart-robots", type=int, default=8, help="restart: robots streaming through the restart")
    p.add_argument("--restart-stream-s", type=float, default=20.0, help="restart: each robot's stream, s")
    p.add_argument(
        "--restart-assets",
        choices=("synthetic", "demo"),
        default="synthetic",
        help="restart: a small synthetic tactile model and library built once under artifacts/bench-restart "
        "(deploy.local.synthetic_assets, default), or the demo's tactile-only configuration (--assets)",
    )


def restart_only(args: argparse.Namespace, argv: list[str] | None) -> int:
    """The restart case alone, its object written into the report file beside the others."""
    import os

    from benchmarks.report_file import command_line, machine
    from benchmarks.restart import run_restart

    load = os.getloadavg()
    if args.restart_assets == "demo":
        assets = prepare_assets(args.assets)["tactile"]
    else:
        from deploy.local import synthetic_assets

        root = synthetic_assets(Path("artifacts/bench-restart"))
        assets = Assets("synthetic", root / "model.onnx", None, None, root / "library", frames=False)
    restart = run_restart(assets, secrets.token_urlsafe(24), args.restart_robots, args.restart_stream_s)
    restart["assets"] = args.restart_assets
    restart["command"] = command_line("benchmarks.hostile", list(argv if argv is not None else sys.argv[1:]))
    restart["machine"] = machine(load)
    print(json.dumps(restart, indent=2))
    write_section(args.out, "restart", restart)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
