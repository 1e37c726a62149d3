"""The real-time renderer's cost: µs of CPU per second of output, against a floor measured in the same run.

`python -m benchmarks.renderer [--hatt-source DIR] [--seconds 10] [--repeats 5]`

For a synthetic-world texture (AR order 8, MA 2, with bumps and taps) and, when HaTT's models are at hand, a HaTT
model with its recorded taps (AR 18-20, MA 16-18; no bumps), a seeded 10 s freehand stroke is rendered by
`texture_library.renderer.StreamRenderer` in blocks of 1, 10 and 20 ms (the operator client renders 10 ms blocks),
one thread, in all four dimensions: vibration, friction, the bumps at the stroke's position and a touchdown (a
tap) every 0.5 s at 20 mm/s. The floor: `scipy.signal.lfilter` of the same length with the model fixed at one
operating point (no interpolation, no per-sample coefficients: the least an ARMA renderer can cost in Python).
Also `synthesis.render` of the whole stroke at once (vibration only). The best of `repeats` runs of each,
process CPU time. `realtime_factor` is 1 s of output over the CPU it took; `over_floor` the renderer's cost in
units of the floor's, both measured in the same run (the ratio holds on a busy host; the factor less so).
Writes reports/bench/renderer.json with the host's CPU model.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

from benchmarks.report_file import machine, write_report
from models.offline.provenance import file_input
from texture_library.procedural import make_world
from texture_library.renderer import StreamRenderer
from texture_library.synthesis import interpolate, render
from texture_library.trajectory import freehand, model_ranges
from texture_library.vibration import VibrationModel

DEFAULT_HATT = Path("../shared/data/hatt-texnet")
OUT = Path("reports/bench/renderer.json")
BLOCKS_MS = (1, 10, 20)
TOUCHDOWN_MM_S = 20.0


def cpu_us_per_s(run, seconds: float, repeats: int) -> float:
    """Best of `repeats`: process CPU µs spent per second of output."""
    best = float("inf")
    for _ in range(repeats):
        t = time.process_time()
        run()
        best = min(best, time.process_time() - t)
    return best / seconds * 1e6


def measure(model: VibrationModel, seconds: float, repeats: int) -> dict:
    rng = np.random.default_rng(0)
    traj = freehand(seconds, rng, rate_hz=model.rate_hz, **model_ranges(model.max_speed, model.max_force))
    speed, force = traj.speed, traj.force
    n = speed.size
    params = interpolate(model, np.array([100.0]), np.array([1.0]))
    b, a = params["ma"][0] * params["gain"][0], params["ar"][0]
    e = rng.standard_normal(n) * np.sqrt(params["variance"][0])
    position = traj.position
    touchdown = np.zeros(n)
    touchdown[:: int(0.5 * model.rate_hz)] = TOUCHDOWN_MM_S
    render(model, speed[:100], force[:100], excitation=np.zeros(100))  # compile the kernels before timing
    StreamRenderer(model).process(speed[:100], force[:100], position=position[:100], touchdown=touchdown[:100])
    floor = cpu_us_per_s(lambda: lfilter(b, a, e), seconds, repeats)
    offline = cpu_us_per_s(lambda: render(model, speed, force, rng), seconds, repeats)
    row = {
        "model": model.name,
        "ar_order": model.ar_order,
        "ma_order": model.ma_order,
        "grid_points": int(np.shape(model.speeds)[0]),
        "dimensions": ["vibration", "friction"]
        + (["bumps"] if model.surface is not None else [])
        + (["taps"] if model.taps is not None else []),
        "floor_lfilter_us_per_s": round(floor, 1),
        "offline_render_us_per_s": round(offline, 1),
        "streaming": [],
    }
    for block_ms in BLOCKS_MS:
        k = block_ms

        def stream(k: int = k) -> None:
            r = StreamRenderer(model, np.random.default_rng(1))
            for lo in range(0, n, k):
                sl = slice(lo, lo + k)
                r.process(speed[sl], force[sl], position=position[sl], touchdown=touchdown[sl])

        us = cpu_us_per_s(stream, seconds, repeats)
        row["streaming"].append(
            {
                "block_ms": block_ms,
                "us_per_s": round(us, 1),
                "realtime_factor": round(1e6 / us, 1),
                "over_floor": round(us / floor, 1),
            }
        )
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hatt-source", type=Path, default=DEFAULT_HATT, help="HaTT–TexNet folder (models/*.xml)")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    load_before = os.getloadavg()
    models = [make_world(1, 0, image_size=64)[0].model]
    hatt = sorted((args.hatt_source / "models").glob("*.xml")) if args.hatt_source else []
    if hatt:
        from texture_library.hatt_xml import read_model

        taps = args.hatt_source / "taps" / hatt[0].name
        models.append(read_model(hatt[0], taps if taps.is_file() else None, name=hatt[0].stem))
    else:
        print(f"(no HaTT models under {args.hatt_source}: synthetic texture only)", flush=True)
    rows = [measure(m, args.seconds, args.repeats) for m in models]
    print(
        f"{'model':<16}{'p,q':>7}{'block':>7}{'µs/s':>10}{'× real time':>13}{'× floor':>9}   floor µs/s  offline µs/s"
    )
    for r in rows:
        for s in r["streaming"]:
            print(
                f"{r['model'][:15]:<16}{r['ar_order']:>3},{r['ma_order']:<3}{s['block_ms']:>5}ms{s['us_per_s']:>10.0f}"
                f"{s['realtime_factor']:>13.1f}{s['over_floor']:>9.1f}   {r['floor_lfilter_us_per_s']:>9.0f}"
                f"  {r['offline_render_us_per_s']:>11.0f}"
            )
    load = Path("/proc/loadavg").read_text().split()[0] if Path("/proc/loadavg").exists() else "?"
    doc = {
        "command": "python -m benchmarks.renderer " + " ".join(argv if argv is not None else sys.argv[1:]),
        "what": "process CPU µs per second of 1 kHz output, best of repeats; floor: scipy.signal.lfilter of the "
        "same length at one fixed operating point",
        "load_average_1min_at_end": load,
        "machine": machine(load_before),
        "rows": rows,
    }
    write_report(args.out, doc, [file_input("HaTT models", args.hatt_source / "models")] if hatt else ())
    print(f"wrote {args.out} (1-min load average {load})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
