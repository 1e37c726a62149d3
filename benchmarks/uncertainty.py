"""Per-window cost of the uncertainty the service emits: OOD check, interval, EMA state, frame check.

    python -m benchmarks.uncertainty [--n 2000] [--out reports/bench/uncertainty.json]

`service_window`: the service's own pipeline (`service.pipeline.estimate_batch`, one session, a job of
4 windows as `service.warmup.synthetic_job` makes it) with a calibrated card (`ridge-tactile` trained
with intervals and detector on an 8-texture synthetic world) against the same runtime with the
card's calibration and detector removed, interleaved; the difference per window is what intervals
and flags cost the service (compare: the framework's floor per block, `capacity` in
reports/bench/service.json; a window is 25 blocks of 20 ms).

A detector fitted on random features of the real shapes (79 training textures × 32 windows of
526 tactile features; 8 views of 1536 visual features), so its cost equals a served card's.
One window at a time (the serving case) and a batch of 16, with the frame's visual check done once
per frame (check_visual) as the service would; p50 over `n` calls after a warm-up.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from benchmarks.report_file import write_report

DEFAULT_OUT = Path("reports") / "bench" / "uncertainty.json"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.uncertainty", description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2000, help="timed calls per step (default 2000)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    if args.n < 10:
        parser.error("--n must be ≥ 10")

    from models.inference.intervals import EmaUncertainty, IntervalCalibration
    from models.inference.ood import OODDetector, frame_statistics
    from models.offline.nets.latency import call_latency

    rng = np.random.default_rng(0)
    tactile = [rng.normal(size=(32, 526)) for _ in range(79)]
    visual = rng.normal(size=(79, 8, 1536))
    frames = np.array([frame_statistics(rng.random((256, 256)).astype(np.float32)) for _ in range(79)])
    det = OODDetector.fit(tactile, visual, frames)
    truth = rng.normal(size=(1580, 4)) * 30
    cal = IntervalCalibration.fit(
        truth + rng.normal(size=(1580, 4)) * 8, truth, groups=np.arange(1580) // 20, prior_ratings=truth[::20]
    )
    one, batch, v = rng.normal(size=(1, 526)), rng.normal(size=(16, 526)), rng.normal(size=1536)
    pred1, pred16 = rng.normal(size=(1, 4)), rng.normal(size=(16, 4))
    frame = rng.random((1024, 1024)).astype(np.float32)
    state = EmaUncertainty(0.5)
    framecheck = det.check_visual(v)
    n = args.n
    steps = {
        "ood_check_visual_per_frame_us": call_latency(lambda: det.check_visual(v), n=n, warmup=50),
        "ood_check_1_window_us": call_latency(lambda: det.check(one, frame=framecheck), n=n, warmup=50),
        "ood_check_16_windows_us": call_latency(lambda: det.check(batch, frame=framecheck), n=n, warmup=50),
        "interval_1_window_us": call_latency(
            lambda: cal.interval(pred1, None, 0.9, ood=np.array([False])), n=n, warmup=50
        ),
        "interval_16_windows_us": call_latency(
            lambda: cal.interval(pred16, None, 0.9, ood=np.zeros(16, bool)), n=n, warmup=50
        ),
        "ema_state_update_us": call_latency(lambda: state.update(False, 1.2), n=n, warmup=50),
        "check_frame_1024px_us": call_latency(lambda: det.check_frame(frame), n=max(10, n // 20), warmup=5),
    }
    steps.update(_service_window(max(20, n // 10)))
    card_bytes = len(json.dumps(det.to_dict())) + len(json.dumps(cal.to_dict()))
    result = {
        "benchmark": "uncertainty",
        "command": " ".join(["python -m benchmarks.uncertainty", *(argv or sys.argv[1:])]),
        "steps": steps,
        "card_json_bytes": card_bytes,
        "loadavg_1_5_15": list(os.getloadavg()),
        "note": "single thread numpy; timed under whatever load the machine has",
    }
    write_report(args.out, result)
    for k, v in steps.items():
        print(f"{k:<40} p50 {v['p50_us']:9.1f} µs" + (f"   p90 {v['p90_us']:9.1f} µs" if "p90_us" in v else ""))
    print(f"detector + one calibration in the card: {card_bytes / 1e3:.0f} kB of JSON; wrote {args.out}")
    return result


def _service_window(n: int) -> dict:
    """Per-window µs of estimate_batch with and without the card's uncertainty (see the module docstring)."""
    import dataclasses
    import tempfile
    import time

    from models.offline.datasets.build import build
    from models.offline.train import train_and_export
    from service.live_session import stream_contract
    from service.pipeline import estimate_batch
    from service.runtime import load_runtime
    from service.settings import Settings
    from service.warmup import WARM_UP_WINDOWS, synthetic_job
    from texture_library.synthetic_library import build_synthetic_library

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        model = train_and_export(
            build("synthetic", root / "dataset", n_textures=8, duration_s=4), "ridge-tactile", root / "model.onnx"
        )
        build_synthetic_library(root / "library", n_textures=8, image_size=64)
        settings = Settings(model_path=model, library_dir=root / "library", instance_id="bench", api_keys="unused")
        full = load_runtime(settings)
        if full.main.calibration is None or full.main.detector is None:
            raise RuntimeError("the benchmark model has no calibration or detector")
        bare = dataclasses.replace(
            full, main=dataclasses.replace(full.main, calibration=None, window_calibration=None, detector=None)
        )
        contract = stream_contract(full, settings)
        rng = np.random.default_rng(0)
        times: dict[str, list[float]] = {"with": [], "without": []}
        for i in range(n + 5):
            for name, rt in (("with", full), ("without", bare)) if i % 2 else (("without", bare), ("with", full)):
                job = synthetic_job(rt, settings, contract, rng, None, {})
                t0 = time.perf_counter()
                (result,) = estimate_batch(rt, [job])
                elapsed = time.perf_counter() - t0
                if result.error is not None:
                    raise result.error
                if i >= 5:  # warm-up calls
                    times[name].append(elapsed / WARM_UP_WINDOWS * 1e6)
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {
        "service_window_with_uncertainty_us": {"p50_us": med["with"]},
        "service_window_without_uncertainty_us": {"p50_us": med["without"]},
        "service_uncertainty_per_window_us": {"p50_us": med["with"] - med["without"]},
    }


if __name__ == "__main__":
    main()
