"""What each part of the deploy topology costs per block: nginx, the replicas and Redis, in CPU time.

Run from the repository root:  python -m benchmarks.deploy  [--robots 20] [--duration 30]

Brings up deploy/'s topology on loopback (deploy/local.py: nginx, two replicas and Redis exactly as
docker-compose.yml wires them, a synthetic ridge-tactile model and library: deploy.local.synthetic_assets). N
simulated robots — the real RobotClient, with the topology's fleet API key — stream 1 kHz accel/force/speed in the
client's default binary blocks through nginx at real-time pace, each with an operator WebSocket on the *other*
replica, so every window event crosses Redis. Over a steady stretch of
`--duration` seconds it reads the CPU time of every process from /proc (nginx: master and workers; each replica;
redis-server) and reports CPU µs per block for each, Redis's per window event, and the share of a core one robot
costs each part. CPU time per unit of work holds up on a busy machine, where latencies measure the neighbours.

Writes reports/bench/deploy.json and prints a table. docs/service.md sizes a 1,000-robot fleet from it.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.report_file import write_report
from benchmarks.service import machine_cpu_seconds, process_cpu_seconds
from deploy.local import Topology, synthetic_assets

DEFAULT_OUT = Path("reports/bench/deploy.json")
BLOCK_S = 0.02


def process_tree(pid: int) -> list[int]:
    """`pid` and its children (nginx's workers), from /proc."""
    children = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # exited meanwhile
        if int(fields[1]) == pid:
            children.append(int(stat.parent.name))
    return [pid, *children]


def tree_cpu_seconds(pids: list[int]) -> float:
    total = 0.0
    for pid in pids:
        try:
            total += process_cpu_seconds(pid)
        except OSError:
            pass
    return total


async def _stream(topology: Topology, robots: int, warmup_s: float, duration_s: float) -> dict:
    from websockets.asyncio.client import connect

    from drivers.robot import RobotClient
    from drivers.simulated import SimulatedSource

    library = topology.assets / "library"
    entries = [e["id"] for e in json.loads((library / "library.json").read_text())["entries"]]
    clients = [
        RobotClient(
            topology.url,
            SimulatedSource.from_library(library, entries[k % len(entries)], seed=k),
            seed=k,
            **topology.robot_options,
        )
        for k in range(robots)
    ]
    for client in clients:
        await client.open_session()
    instances = sorted(topology.replicas)
    events = {"windows": 0}

    async def operate(client: RobotClient) -> None:
        owner = client.session_id.split(".", 1)[0]
        other = topology.replicas[instances[1 - instances.index(owner)]]
        url = f"{other.ws_url}/sessions/{client.session_id}/events?token={client.session.operator_token}"
        async with connect(url, max_size=2**20) as ws:
            async for message in ws:
                if message.startswith('{"type":"window"'):
                    events["windows"] += 1

    operators = [asyncio.create_task(operate(c)) for c in clients]
    runs = [asyncio.create_task(c.run()) for c in clients]
    parts = {
        "nginx": process_tree(topology.services[topology.lb_name].proc.pid),
        "redis": [topology.services[topology.redis_name].proc.pid],
        **{i: [s.proc.pid] for i, s in topology.replicas.items()},
    }
    await asyncio.sleep(warmup_s)  # sessions started, buffers and batches in their steady state

    def snapshot() -> tuple[dict[str, float], int, int, float, float]:
        cpu = {name: tree_cpu_seconds(pids) for name, pids in parts.items()}
        return cpu, sum(c.stats.acked for c in clients), events["windows"], machine_cpu_seconds(), time.perf_counter()

    cpu0, acked0, windows0, machine0, wall0 = snapshot()
    await asyncio.sleep(duration_s)
    cpu1, acked1, windows1, machine1, wall1 = snapshot()
    for client in clients:
        client.stop()
    stats = await asyncio.gather(*runs)
    for task in operators:
        task.cancel()
    await asyncio.gather(*operators, return_exceptions=True)
    blocks, windows, wall = acked1 - acked0, windows1 - windows0, wall1 - wall0
    cpu = {name: cpu1[name] - cpu0[name] for name in parts}
    per_block = {name: round(1e6 * seconds / max(blocks, 1), 1) for name, seconds in cpu.items()}
    replicas_us = sum(per_block[i] for i in topology.replicas)
    robot_blocks_per_s = 1 / BLOCK_S
    return {
        "robots": robots,
        "duration_s": round(wall, 2),
        "blocks": blocks,
        "blocks_per_s": round(blocks / wall, 1),
        "window_events_received": windows,
        "cpu_percent": {name: round(100 * seconds / wall, 1) for name, seconds in cpu.items()},
        "cpu_us_per_block": {**per_block, "replicas": round(replicas_us, 1)},
        "redis_cpu_us_per_window_event": round(1e6 * cpu["redis"] / max(windows, 1), 1),
        # a 20 ms-block robot sends 50 blocks/s: the share of one core it costs each part
        "core_percent_per_robot": {
            "nginx": round(per_block["nginx"] * robot_blocks_per_s / 1e4, 3),
            "replicas": round(replicas_us * robot_blocks_per_s / 1e4, 3),
            "redis": round(per_block["redis"] * robot_blocks_per_s / 1e4, 3),
        },
        "others_cpu_percent": round(100 * ((machine1 - machine0) - sum(cpu.values())) / wall, 1),
        "robot_errors": sum(s.rejected + s.lost for s in stats),
        "reconnects": sum(s.reconnects for s in stats),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, default=20, help="simulated robots through nginx (default 20)")
    p.add_argument("--duration", type=float, default=30.0, help="seconds measured, after --warmup (default 30)")
    p.add_argument("--warmup", type=float, default=3.0, help="seconds streamed before measuring (default 3)")
    p.add_argument(
        "--assets",
        type=Path,
        default=Path(tempfile.gettempdir()) / "hapticlink-deploy-assets",
        help="where the synthetic model and library are built and cached (deploy.local.synthetic_assets)",
    )
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    if args.robots < 2 or not args.duration > 0:
        p.error("--robots must be ≥ 2 (one per replica) and --duration > 0")
    assets = synthetic_assets(args.assets)
    print(f"{args.robots} robots through nginx to two replicas for {args.duration:g} s …", flush=True)
    with Topology(assets) as topology:
        result = asyncio.run(_stream(topology, args.robots, args.warmup, args.duration))
    for part in (
        "nginx",
        *sorted(k for k in result["cpu_us_per_block"] if k.startswith("replica-")),
        "replicas",
        "redis",
    ):
        print(f"{part:>10}: {result['cpu_us_per_block'][part]:>7.1f} µs CPU per block")
    print(f"     redis: {result['redis_cpu_us_per_window_event']:>7.1f} µs CPU per window event")
    print(f"per robot (50 blocks/s), % of a core: {result['core_percent_per_robot']}")
    report = {
        "benchmark": "deploy",
        "command": " ".join(["python -m benchmarks.deploy", *(argv or sys.argv[1:])]),
        "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "loadavg_1_5_15": list(os.getloadavg()),
        },
        "config": {
            "block_s": BLOCK_S,
            "transport": "RobotClient, WebSocket, binary blocks, through nginx",
            "operators": "one per robot, on the other replica (events cross Redis)",
            "model": "ridge-tactile, 12 synthetic textures (deploy.local.synthetic_assets)",
        },
        "result": result,
    }
    write_report(args.out, report)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
