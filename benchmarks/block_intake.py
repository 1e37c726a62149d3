"""What a sample block costs the event loop before the window pool: decoding and admission, in-process, no server.

Run from the repository root:  python -m benchmarks.block_intake [--seconds 300] [--block-s 0.1] [--repeats 5]

One robot's stream (the demo's library, a freehand stroke, tapped first, as `benchmarks.service` streams it) in
binary blocks of the robot client's default size, encoded once. Three passes over the same bytes, interleaved
`--repeats` times (the median of each is reported, thread CPU per block):
- floor: the library calls a decoder cannot do without — the header's `json.loads` and one `np.frombuffer` per
  channel;
- decode: `service.intake.decode_block` (header checks, every channel's samples checked: numbers, finite, within a
  sensor's range);
- decode + admission: the same, then `Session.ingest` (the stream contract, the session's queue), each complete
  window taken as the batcher takes it and handed back done (not estimated: that is the window pool's,
  `benchmarks.window_batch`; nor published).
Writes reports/bench/block_intake.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import statistics
import struct
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.report_file import command_line, machine, write_report

DEFAULT_OUT = Path("reports/bench/block_intake.json")


def floor(payload: bytes) -> dict[str, np.ndarray]:
    """The bare parse of a binary block: its header and a view of each channel's float32 samples (flat)."""
    (n,) = struct.unpack_from("<I", payload, 4)
    header = json.loads(payload[8 : 8 + n])
    offset, out = 8 + n, {}
    for kind, spec in header["channels"].items():
        count = math.prod(spec["shape"])
        out[kind] = np.frombuffer(payload, dtype="<f4", count=count, offset=offset)
        offset += 4 * count
    return out


def cpu_us_per_block(step, payloads: list[bytes]) -> float:
    t0 = time.thread_time()
    for p in payloads:
        step(p)
    return 1e6 * (time.thread_time() - t0) / len(payloads)


def main(argv: list[str] | None = None) -> int:
    from drivers.blocks import TapBlock, encode_binary
    from drivers.source import DEFAULT_BLOCK_S

    p = argparse.ArgumentParser(prog="python -m benchmarks.block_intake", description=__doc__.split("\n")[0])
    p.add_argument("--assets", type=Path, default=Path("artifacts/demo"), help="the demo's assets (built if missing)")
    p.add_argument("--seconds", type=float, default=300.0, help="seconds of stream (default 300)")
    p.add_argument("--block-s", type=float, default=DEFAULT_BLOCK_S, help=f"default {DEFAULT_BLOCK_S:g}")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    if args.seconds <= 0 or args.block_s <= 0 or args.repeats < 1:
        p.error("--seconds and --block-s must be > 0, --repeats ≥ 1")
    argv = sys.argv[1:] if argv is None else argv

    from benchmarks.loadgen import robot_streams
    from demo.assets import prepare_assets
    from service.intake import decode_block
    from service.live_session import Session
    from service.metrics import ServiceMetrics
    from service.pipeline import SessionResult
    from service.runtime import load_runtime
    from service.settings import Settings

    load_before = os.getloadavg()
    demo = prepare_assets(args.assets)
    settings = Settings(model_path=demo.tactile, library_dir=demo.library, instance_id="bench", api_keys="bench")
    runtime = load_runtime(settings)
    blocks = robot_streams(demo.library, 1, args.seconds, args.block_s, taps=runtime.needs_taps)[0]
    taps = [b for b in blocks if isinstance(b, TapBlock)]
    payloads = [encode_binary(b) for b in blocks if not isinstance(b, TapBlock)]

    async def admit_all(session: Session) -> None:
        for payload in payloads:
            session.ingest(decode_block(payload, True), time.perf_counter_ns())
            if session.has_work() and (job := session.take_job()) is not None:
                await session.apply_result(SessionResult([], job.windows))  # the job done, nothing to publish

    def admission() -> float:
        session = Session("bench", "bench", None, runtime, settings, None, None, ServiceMetrics(), lambda s: None)  # type: ignore[arg-type]
        for tap in taps:
            session.ingest(tap, 0)
        t0 = time.thread_time()
        asyncio.run(admit_all(session))
        return 1e6 * (time.thread_time() - t0) / len(payloads)

    passes = {
        "floor": lambda: cpu_us_per_block(floor, payloads),
        "decode": lambda: cpu_us_per_block(lambda b: decode_block(b, True), payloads),
        "decode_admission": admission,
    }
    for run in passes.values():  # warm-up: imports, caches
        run()
    samples: dict[str, list[float]] = {name: [] for name in passes}
    for _ in range(args.repeats):
        for name, run in passes.items():
            samples[name].append(run())
    us = {name: round(statistics.median(v), 2) for name, v in samples.items()}
    report = {
        "benchmark": "block_intake",
        "command": command_line("benchmarks.block_intake", argv),
        "blocks": len(payloads),
        "block_s": args.block_s,
        "channels": "accel (n, 3) + force (n, 3) + speed (n,) at 1 kHz, float32",
        "cpu_us_per_block": us,
        "samples_us": {name: [round(x, 2) for x in v] for name, v in samples.items()},
        "over_floor": {name: round(us[name] / us["floor"], 2) for name in ("decode", "decode_admission")},
        "machine": machine(load_before),
    }
    write_report(args.out, report)
    for name, value in us.items():
        ratio = "" if name == "floor" else f"  ({value / us['floor']:.1f}× the floor)"
        print(f"{name:>17}: {value:7.2f} µs of CPU per block{ratio}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
