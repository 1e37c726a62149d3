"""How fast a ROS 2 bag becomes a sensor stream: RosbagSource against rosbags' own bare read of the same bag.

Run from the repository root:  python -m benchmarks.rosbag_read [--seconds 600] [--repeats 3]

A simulated robot strokes a library texture for --seconds (10 minutes by default); the stroke is written as a bag
the way an arm would record it (IMU 1 kHz, wrench 500 Hz, twist 100 Hz, a JPEG camera at 5 Hz), once as sqlite3
(.db3) and once as MCAP. On one core (the process pinned to one CPU), interleaved --repeats times, median wall time:
- raw: rosbags' Reader handing over every message's bytes (`reader.messages()`), the floor no bag source goes under;
- deserialized: the same, and `deserialize_cdr` of each message — what reading the bag with rosbags alone costs;
- RosbagSource: the whole source, as `hapticlink robot --source rosbag:PATH --no-realtime` runs it: both passes (the
  judging scan, then the blocks and the camera frames), every item taken. It reads a .db3 with rosbags' reader, an
  MCAP through its message index (drivers/rosbag_mcap.py).
Real-time factor = bag seconds ÷ wall seconds (and ÷ the process's CPU seconds, which a busy host inflates less).
Target: RosbagSource ≥ 50× real time. Writes reports/bench/rosbag_read.json with the host (lscpu model and flags),
the load average and the command.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.report_file import command_line, machine, write_report

DEFAULT_OUT = Path("reports/bench/rosbag_read.json")
TARGET_X = 50.0


def host() -> dict:
    """The CPU's model name and flags (lscpu), so an absolute figure names the machine it was measured on."""
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return {}
    fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
    flags = fields.get("Flags", "").split()
    return {
        "model": fields.get("Model name", "").strip(),
        "avx512_vnni": "avx512_vnni" in flags,
        "avx2": "avx2" in flags,
        "flags": " ".join(flags),
    }


def stroke(seconds: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, bytes]:
    """accel (n, 3) m/s², force (n, 3) N, speed (n,) mm/s at 1 kHz, and a JPEG of the texture, from the simulated
    robot stroking a procedural texture."""
    import io

    from PIL import Image

    from drivers.blocks import SampleBlock
    from drivers.simulated import SimulatedSource
    from texture_library.procedural import make_world

    texture = make_world(1, seed=11)[0]

    async def take():
        return [i async for i in SimulatedSource(texture.model, seed=seed, realtime=False, duration_s=seconds)]

    blocks = [i for i in asyncio.run(take()) if isinstance(i, SampleBlock)]
    accel, force, speed = (np.concatenate([b.channels[k].data for b in blocks]) for k in ("accel", "force", "speed"))
    buf = io.BytesIO()
    Image.fromarray(texture.image).convert("RGB").save(buf, format="JPEG", quality=85)
    return accel.astype(np.float64), force.astype(np.float64), speed.astype(np.float64), buf.getvalue()


def write(root: Path, storage: str, accel, force, speed, jpeg: bytes) -> Path:
    """The stroke as a bag: the numeric topics serialised a topic at a time, the camera's messages one by one."""
    import heapq

    from drivers.rosbag_writer import BagRates, stroke_messages, stroke_raw_messages, write_bag

    n = speed.shape[0]
    camera = (
        (t, s, m)
        for t, s, m in stroke_messages(accel[:1], force[:1], speed[:1], 1.0 / (n / 1000.0), jpeg, BagRates(1, 1, 1, 5))
        if t == "/camera/compressed"
    )
    numeric = stroke_raw_messages(accel, force, speed, 1000.0)
    merged = heapq.merge(numeric, camera, key=lambda m: m[1])
    return write_bag(root / storage, merged, storage)


def read_raw(bag: Path) -> int:
    from rosbags.rosbag2 import Reader

    n = 0
    with Reader(bag) as reader:
        for _ in reader.messages():
            n += 1
    return n


def read_deserialized(bag: Path) -> int:
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    deserialize = get_typestore(Stores.ROS2_HUMBLE).deserialize_cdr
    n = 0
    with Reader(bag) as reader:
        for conn, _, raw in reader.messages():
            deserialize(raw, conn.msgtype)
            n += 1
    return n


def read_source(bag: Path) -> int:
    from drivers.rosbag_source import RosbagSource

    async def take() -> int:
        return sum([1 async for _ in RosbagSource(bag, realtime=False)])

    return asyncio.run(take())


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(prog="python -m benchmarks.rosbag_read", description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=600.0, help="length of the bag, s (default 600: 10 minutes)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    load_before = os.getloadavg()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})  # one core, as the target says
    t0 = time.perf_counter()
    accel, force, speed, jpeg = stroke(args.seconds)
    print(f"stroke of {args.seconds:g} s simulated in {time.perf_counter() - t0:.1f} s", flush=True)
    results = {}
    with tempfile.TemporaryDirectory(prefix="hapticlink-rosbag-bench-") as tmp:
        for storage in ("sqlite3", "mcap"):
            t0 = time.perf_counter()
            bag = write(Path(tmp), storage, accel, force, speed, jpeg)
            size = sum(f.stat().st_size for f in bag.iterdir())
            print(f"{storage}: {size / 2**20:.0f} MiB written in {time.perf_counter() - t0:.1f} s", flush=True)
            runs: dict[str, list[float]] = {"raw": [], "deserialized": [], "source": []}
            cpu_runs: dict[str, list[float]] = {k: [] for k in runs}
            counts = {}
            for _ in range(args.repeats):
                for name, read in (("raw", read_raw), ("deserialized", read_deserialized), ("source", read_source)):
                    t, c = time.perf_counter(), time.process_time()
                    counts[name] = read(bag)
                    runs[name].append(time.perf_counter() - t)
                    cpu_runs[name].append(time.process_time() - c)
            wall = {k: statistics.median(v) for k, v in runs.items()}
            cpu = {k: statistics.median(v) for k, v in cpu_runs.items()}
            x = {k: args.seconds / v for k, v in wall.items()}
            results[storage] = {
                "bag_mib": round(size / 2**20, 1),
                "messages": counts["raw"],
                "items_streamed": counts["source"],
                "wall_s": {k: round(v, 3) for k, v in wall.items()},
                "wall_s_runs": {k: [round(t, 3) for t in v] for k, v in runs.items()},
                "realtime_x": {k: round(v, 1) for k, v in x.items()},
                "cpu_s": {k: round(v, 3) for k, v in cpu.items()},
                "cpu_s_runs": {k: [round(t, 3) for t in v] for k, v in cpu_runs.items()},
                "realtime_x_cpu": {k: round(args.seconds / v, 1) for k, v in cpu.items()},
                "source_vs_raw": round(wall["source"] / wall["raw"], 2),
                "source_vs_raw_cpu": round(cpu["source"] / cpu["raw"], 2),
                "source_vs_deserialized": round(wall["source"] / wall["deserialized"], 3),
                "meets_target": x["source"] >= TARGET_X,
            }
            r = results[storage]
            print(
                f"{storage}: raw {x['raw']:.0f}× real time, rosbags deserialize {x['deserialized']:.0f}×, "
                f"RosbagSource {x['source']:.0f}× (target ≥ {TARGET_X:g}×): {r['source_vs_raw']}× the raw read's "
                f"time, {r['source_vs_deserialized']}× rosbags' deserializing read's (CPU time: RosbagSource "
                f"{r['realtime_x_cpu']['source']:.0f}× real time, {r['source_vs_raw_cpu']}× the raw read's)",
                flush=True,
            )
    report = {
        "what": "reading a ROS 2 bag (IMU 1 kHz, wrench 500 Hz, twist 100 Hz, JPEG camera 5 Hz) on one core",
        "command": command_line("benchmarks.rosbag_read", argv),
        "bag_seconds": args.seconds,
        "repeats": args.repeats,
        "target_realtime_x": TARGET_X,
        "results": results,
        "host": host(),
        "machine": machine(load_before),
    }
    print(f"wrote {write_report(args.out, report)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
