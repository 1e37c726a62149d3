"""Per-window cost of the selection rule: the hybrid's vibration fit against the perceptual rule alone.

    python -m benchmarks.selection [--hatt ../shared/data/hatt-texnet] [--n 2000] [--out reports/bench/selection.json]

A library of HaTT's 100 vibration models (read in place from --hatt, never copied), its spectral table
built once as the service builds it at load (`texture_library.selection.SpectralTable`, timed), and one
500 ms window of three-axis acceleration rendered from one of the models. Timed per window, interleaved,
p50 over `n` calls after a warm-up: `perceptual` — rating distances and the hysteresis chooser (the
floor: what the service spent before); `hybrid` — the same plus the window's Welch spectrum, the table
read at the window's speed and force, and the Whittle mismatch against every entry. The difference is
what the physical term costs per window (the window budget is its 500 ms hop).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.report_file import write_report

DEFAULT_OUT = Path("reports") / "bench" / "selection.json"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.selection", description=__doc__.splitlines()[0])
    parser.add_argument("--hatt", type=Path, default=Path("../shared/data/hatt-texnet"), help="HaTT–TexNet folder")
    parser.add_argument("--n", type=int, default=2000, help="timed calls per rule (default 2000)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    if args.n < 10:
        parser.error("--n must be ≥ 10")
    if not (args.hatt / "models").is_dir():
        parser.error(f"{args.hatt}: no models/ folder (HaTT–TexNet, read in place)")

    from texture_library.hatt_xml import read_model
    from texture_library.nearest import PerceptualIndex
    from texture_library.selection import HysteresisChooser, SelectionRule, SpectralTable
    from texture_library.synthesis import render

    paths = sorted((args.hatt / "models").glob("*.xml"))
    models = [read_model(p) for p in paths]
    ids = [p.stem for p in paths]
    t0 = time.perf_counter()
    table = SpectralTable(ids, models)
    build_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    index = PerceptualIndex(ids, rng.uniform(-100, 100, (len(ids), 4)))
    accel = np.stack([render(models[0], np.full(500, 100.0), np.full(500, 1.0), rng) for _ in range(3)], axis=1)
    rating = rng.uniform(-100, 100, 4)
    rules = {"perceptual": SelectionRule("perceptual"), "hybrid": SelectionRule("hybrid", 4.0)}
    choosers = {k: HysteresisChooser(r, 12.0, 4) for k, r in rules.items()}

    def one(name: str) -> None:
        d = index.distances(rating)
        mm = table.mismatch_db(accel, 100.0, 1.0) if rules[name].needs_spectrum else None
        choosers[name].choose(index.ids, rules[name].costs(d, mm))

    times: dict[str, list[float]] = {k: [] for k in rules}
    for _ in range(50):  # warm-up
        for k in rules:
            one(k)
    for _ in range(args.n):
        for k in rules:
            t = time.perf_counter_ns()
            one(k)
            times[k].append((time.perf_counter_ns() - t) / 1e3)
    p50 = {k: float(np.median(v)) for k, v in times.items()}
    result = {
        "library_entries": len(ids),
        "table": {
            "grid": [int(table.speeds.size), int(table.forces.size)],
            "bins": int(table.freqs_hz.size),
            "bytes": int(table.log_psd.nbytes),
            "build_s": round(build_s, 3),
        },
        "per_window_us_p50": {k: round(v, 1) for k, v in p50.items()},
        "hybrid_extra_us_p50": round(p50["hybrid"] - p50["perceptual"], 1),
        "window_budget_us": 500_000,
        "n": args.n,
        "command": " ".join(["python -m benchmarks.selection", *(sys.argv[1:] if argv is None else argv)]),
        "load_average_1_5_15_min": [round(v, 2) for v in os.getloadavg()],
        "note": "timings on a shared 2-core machine under load unless said otherwise",
    }
    print(json.dumps(result, indent=1))
    write_report(args.out, result)
    return result


if __name__ == "__main__":
    main()
