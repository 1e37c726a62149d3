"""What a window costs the window pool by job size: `estimate_batch` alone, in-process, no server.

Run from the repository root:  python -m benchmarks.window_batch [--sessions 64] [--jobs 1 8 32 64] [--rounds 4]

The demo's tactile model and library (`artifacts/demo`, built first if missing), one freehand stroke per session
over a library entry (float32 samples in 50 ms blocks, tap features as a tapped surface has), admitted by the
session's StreamContract as the service admits them. Each round gives every session its next window; a round's
sessions are cut into jobs of `--jobs` sessions and each job is one `estimate_batch` call, as the batcher makes
them. Reported: thread CPU per window (ms) for each job size, the sizes measured in turn, and the first size again
at the end (warm caches against the first pass). The floor: a job of one session. Writes
reports/bench/window_batch.json.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.report_file import write_report

DEFAULT_OUT = Path("reports/bench/window_batch.json")
BLOCK_S = 0.05
WARMUP_ROUNDS = 2


def session_jobs(runtime, settings, library, k: int, seconds: float) -> tuple[object, list[tuple[list, int]]]:
    """Session k's estimator and its stream cut into per-window shares: [(admitted blocks, windows they complete)]."""
    from drivers.source import blocks_from_arrays
    from service.live_session import canonical_channels, stream_contract
    from service.pipeline import AdmittedBlock, SessionEstimator
    from texture_library.recording import recording_from_stroke
    from texture_library.stroke import stroke
    from texture_library.trajectory import freehand, model_ranges

    model = library.model(library.ids[k % len(library.ids)])
    rng = np.random.default_rng(k)
    traj = freehand(seconds, rng, rate_hz=model.rate_hz, **model_ranges(model.max_speed, model.max_force))
    s = stroke(model, traj, rng)
    rec = recording_from_stroke(s.accel, s.force, s.speed, s.rate_hz)
    channels = {
        "accel": (rec.accel.data, rec.accel.rate_hz, "m/s^2"),
        "force": (rec.force.data, rec.force.rate_hz, "N"),
        "speed": (rec.speed.data, rec.speed.rate_hz, "mm/s"),
    }
    taps = np.array([0.5, 0.5, 0.5]) if runtime.needs_taps else None
    contract = stream_contract(runtime, settings)
    cursor = contract.start()
    shares, blocks, windows = [], [], 0
    for b in blocks_from_arrays(channels, BLOCK_S):
        adv = contract.admit(cursor, canonical_channels(b), b.t0)
        cursor = adv.cursor
        blocks.append(AdmittedBlock(b.seq, cursor.segment, cursor.origin_t0, adv.channels, adv.windows_after, 0, taps))
        windows += adv.windows_added
        if adv.windows_added:
            shares.append((blocks, windows))
            blocks, windows = [], 0
    return SessionEstimator.from_settings(runtime, contract, settings), shares


def measure(runtime, sessions, job_size: int, first_round: int, rounds: int) -> tuple[float, int]:
    """Thread CPU per window (ms) over `rounds` rounds from `first_round`, jobs of `job_size` sessions."""
    from service.pipeline import SessionJob, estimate_batch

    cpu, windows = 0.0, 0
    for r in range(first_round, first_round + rounds):
        for start in range(0, len(sessions), job_size):
            group = sessions[start : start + job_size]
            jobs = [SessionJob(est, shares[r][0], None, shares[r][1]) for est, shares in group]
            t0 = time.thread_time()
            results = estimate_batch(runtime, jobs)
            cpu += time.thread_time() - t0
            for result in results:
                if result.error is not None:
                    raise RuntimeError(f"estimation failed: {result.error}")
                windows += len(result.estimates)
    return 1e3 * cpu / max(windows, 1), windows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.window_batch", description=__doc__.split("\n")[0])
    p.add_argument("--assets", type=Path, default=Path("artifacts/demo"), help="the demo's assets (built if missing)")
    p.add_argument("--sessions", type=int, default=64)
    p.add_argument("--jobs", type=int, nargs="+", default=[1, 8, 32, 64], help="sessions per job, measured in turn")
    p.add_argument("--rounds", type=int, default=4, help="windows per session per job size")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    if args.sessions < 1 or args.rounds < 1 or min(args.jobs) < 1:
        p.error("--sessions, --rounds and every --jobs size must be ≥ 1")

    from demo.assets import prepare_assets
    from service.runtime import load_runtime
    from service.settings import Settings
    from texture_library.library import Library

    demo = prepare_assets(args.assets)
    settings = Settings(model_path=demo.tactile, library_dir=demo.library, instance_id="bench", api_keys="bench")
    runtime = load_runtime(settings)
    library = Library.load(demo.library)
    sizes = [*args.jobs, args.jobs[0]]
    seconds = BLOCK_S + 0.5 * (WARMUP_ROUNDS + args.rounds * len(sizes) + 2)  # 0.5 s hop, plus the first window
    sessions = [session_jobs(runtime, settings, library, k, seconds) for k in range(args.sessions)]
    load_before = os.getloadavg()
    measure(runtime, sessions, 1, 0, WARMUP_ROUNDS)
    rows, r = [], WARMUP_ROUNDS
    for size in sizes:
        ms, n = measure(runtime, sessions, size, r, args.rounds)
        r += args.rounds
        rows.append({"sessions_per_job": size, "cpu_ms_per_window": round(ms, 3), "windows": n})
        print(f"jobs of {size:3d} session(s): {ms:.3f} ms of CPU per window ({n} windows)")
    report = {
        "benchmark": "window_batch",
        "command": "python -m benchmarks.window_batch " + " ".join(argv if argv is not None else sys.argv[1:]),
        "model": str(demo.tactile),
        "sessions": args.sessions,
        "rows": rows,
        "machine": {"cpus": os.cpu_count(), "load_average": load_before, "load_average_after": os.getloadavg()},
    }
    write_report(args.out, report)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
