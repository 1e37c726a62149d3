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
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import multiprocessing as mp
import secrets
import sys
import time
from pathlib import Path

import httpx
import numpy as np

from benchmarks.health_poll import poll
from benchmarks.loadgen import frame_of, receive, robot_streams
from benchmarks.report_file import write_report
from benchmarks.service import (
    DEFAULT_ASSETS,
    HOP_S,
    SCRAPER,
    Assets,
    ServerProcess,
    _metric_sum,
    _run,
    percentile,
    prepare_assets,
    run_load,
    timeline,
)
from drivers.blocks import ChannelBlock, SampleBlock, encode_binary
from drivers.protocol import BINARY_CONTENT_TYPE, bearer, session_path

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


def robots_process(
    url: str, assets: Assets, ks: list[int], seconds: float, block_s: float, api_key: str, seed: int, conn
) -> None:
    """A process of robots: renders robots `ks`' streams (`seconds` long) and camera frames, sends ("ready",),
    waits for "go", streams them in real time (real RobotClients, an operator each) while timing its own event
    loop, and sends ("result", {...}) — or ("error", text)."""
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
        return
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
    p.add_argument("--block-s", type=float, default=0.02)
    p.add_argument("--assets", type=Path, default=DEFAULT_ASSETS, help="the demo's assets (built when missing)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    add_restart_arguments(p)
    args = p.parse_args(argv)
    if args.only == "restart":
        return restart_only(args, argv)
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
    import platform

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
    restart["machine"] = {**machine(load), "cpu": _cpu_model() or platform.processor()}
    report = json.loads(args.out.read_text()) if args.out.exists() else {}
    report["restart"] = restart
    print(json.dumps(restart, indent=2))
    write_report(args.out, report)
    print(f"wrote {args.out}")
    return 0


def _cpu_model() -> str | None:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return None


if __name__ == "__main__":
    sys.exit(main())
