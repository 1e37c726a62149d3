"""The hostile-client probe's worst cases against a live service, beside well-behaved robots.

Run from the repository root:  python -m benchmarks.hostile [--robots 20] [--burst-robots 150] [--duration 20]

One service process (the `served` configuration of benchmarks/service.py: visual+tactile model,
tactile-only fallback, camera frames at 1 fps). `--robots` well-behaved robots (the real RobotClient)
stream in real time with an operator each, while, in this order:
1. a client posts the probe's 2.8 MB block (10 Hz, 100 000 samples per channel) a few times;
2. a client sends 300 `POST /sessions` within a second (with a valid key; its own address via
   X-Forwarded-For, since every robot here shares 127.0.0.1, whose budget is set to 200);
3. a client sends a block with seq 2^62 into its own session, then good blocks;
4. `--burst-robots` more robots start together, each with a camera frame at once.
Meanwhile /health is polled every 20 ms. Reported: /health p50/p99/max, the well-behaved robots'
windows lost and end-to-end p99, what was refused (and how), and whether the seq-2^62 session still
produced windows. Writes reports/bench/hostile.json.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import secrets
import sys
import time
from pathlib import Path

import httpx
import numpy as np

from benchmarks.loadgen import frame_of, robot_streams
from benchmarks.report_file import write_report
from benchmarks.service import (
    DEFAULT_ASSETS,
    HOP_S,
    ServerProcess,
    _metric_sum,
    _run,
    percentile,
    prepare_assets,
    run_load,
)
from drivers.blocks import ChannelBlock, SampleBlock, encode_binary
from drivers.protocol import BINARY_CONTENT_TYPE, bearer, session_path

DEFAULT_OUT = Path("reports/bench/hostile.json")


async def poll_health(url: str, stop: asyncio.Event, out: list[float]) -> None:
    async with httpx.AsyncClient(timeout=10) as client:
        while not stop.is_set():
            t0 = time.perf_counter()
            r = await client.get(f"{url}/health")
            if r.status_code == 200:
                out.append((time.perf_counter() - t0) * 1e3)
            await asyncio.sleep(0.02)


async def attacks(url: str, api_key: str, block_s: float, report: dict) -> None:
    """The probe's requests, one after another, each answer recorded."""
    async with httpx.AsyncClient(timeout=30) as client:
        session = (await client.post(f"{url}/sessions", json={"name": "attacker"}, headers=bearer(api_key))).json()
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
            for i, b in enumerate(robot_streams(_library[0], 1, 2.0, block_s, seed=7, taps=_taps[0])[0])
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


_library: list[Path] = []
_taps: list[bool] = []


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, default=20, help="well-behaved robots streaming throughout")
    p.add_argument("--burst-robots", type=int, default=150, help="robots that start together, each with a frame")
    p.add_argument("--duration", type=float, default=20.0)
    p.add_argument("--block-s", type=float, default=0.02)
    p.add_argument("--assets", type=Path, default=DEFAULT_ASSETS, help="the demo's assets (built when missing)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    api_key = secrets.token_urlsafe(24)
    assets = prepare_assets(args.assets)["served"]
    _library.append(assets.library)
    _taps.append(assets.taps)
    n = args.robots + args.burst_robots
    streams = robot_streams(assets.library, n, args.duration, args.block_s, taps=assets.taps)
    frames = [frame_of(assets.library, k) for k in range(n)]
    server = ServerProcess.service(
        assets,
        api_key,
        instance_id="hostile",
        # every robot of this process is one address: a budget for them all
        extra={"HAPTICLINK_SESSION_BURST": "200", "HAPTICLINK_MAX_SESSIONS": "512"},
    )
    report: dict = {"robots": args.robots, "burst_robots": args.burst_robots, "duration_s": args.duration}
    health: list[float] = []

    async def scenario():
        stop = asyncio.Event()
        poller = asyncio.create_task(poll_health(server.url, stop, health))
        # the well-behaved robots open their sessions before the flood (the flood may not starve them)
        steady = asyncio.create_task(
            run_load([server.url], streams[: args.robots], frames[: args.robots], args.block_s, api_key, 0)
        )
        await asyncio.sleep(3.0)
        await attacks(server.url, api_key, args.block_s, report)
        burst = asyncio.create_task(
            run_load(
                [server.url], streams[args.robots :], frames[args.robots :], args.block_s, api_key, 1, realtime=True
            )
        )
        steady_result, burst_result = await asyncio.gather(steady, burst, return_exceptions=True)
        stop.set()
        await poller
        return steady_result, burst_result

    try:
        steady_result, burst_result = _run(scenario())
        metrics = httpx.get(f"{server.url}/metrics").text
    finally:
        server.stop()
    if isinstance(steady_result, BaseException):
        raise steady_result
    _, views, _ = steady_result
    expected = args.robots * int(args.duration / HOP_S + 1e-9)
    e2e = [x for v in views for x in v.e2e_ms]
    report["health_ms"] = {
        "p50": percentile(health, 50),
        "p99": percentile(health, 99),
        "max": percentile(health, 100),
        "polls": len(health),
    }
    report["well_behaved"] = {
        "windows_expected": expected,
        "windows_received": sum(v.windows for v in views),
        "windows_lost": expected - sum(v.windows for v in views),
        "e2e_ms": {"p50": percentile(e2e, 50), "p99": percentile(e2e, 99)},
        "features_ms_p99": percentile([x for v in views for x in v.stages_ms["features"]], 99),
    }
    if isinstance(burst_result, BaseException):
        report["burst"] = {"error": f"{type(burst_result).__name__}: {burst_result}"}
    else:
        _, bviews, _ = burst_result
        bexpected = args.burst_robots * int(args.duration / HOP_S + 1e-9)
        report["burst"] = {
            "windows_expected": bexpected,
            "windows_received": sum(v.windows for v in bviews),
            "windows_tactile_only": sum(v.inputs.get("tactile", 0) for v in bviews),
            "e2e_ms_p99": percentile([x for v in bviews for x in v.e2e_ms], 99),
        }
    report["refused"] = {
        "blocks": int(_metric_sum(metrics, "hapticlink_blocks_total", outcome="refused")),
        "frames": int(_metric_sum(metrics, "hapticlink_frames_total", outcome="refused")),
        "sessions_rate": int(_metric_sum(metrics, "hapticlink_sessions_refused_total", reason="rate")),
        "frames_embedded": int(_metric_sum(metrics, "hapticlink_visual_embedding_seconds_count")),
    }
    print(json.dumps(report, indent=2))
    write_report(args.out, report)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
