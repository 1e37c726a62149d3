"""Per-window cost of the tactile features: ours (batched) vs the straightforward librosa call.

Run from the repository root:  python -m benchmarks.features  [--batch 256] [--repeats 7]

Times, in one run and on the same windows (from a synthetic stroke pushed through the
TactilePreprocessor): window_features on a batch (µs per window = batch time / batch),
window_features on one window at a time (the serving case), the MFCC step alone
(batched), and librosa.feature.mfcc per window (``models.tactile.mfcc.librosa_mfcc``).
Then the extra feature groups: window_features with friction + spatial (the demo model's
features) and with every group, batched and one window per call, and each group's own
function alone (friction, spatial per window; tap_features once per texture's tap set).
Checks that our MFCC equals librosa's and writes reports/bench/features.json.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

import librosa
import numpy as np
import scipy

from benchmarks.report_file import write_report
from models.tactile.config import TactileConfig
from models.tactile.dft321 import dft321
from models.tactile.features import window_features
from models.tactile.friction import friction_features
from models.tactile.mfcc import librosa_mfcc, mfcc
from models.tactile.preprocess import TactilePreprocessor
from models.tactile.spatial import spatial_features
from models.tactile.taps import tap_features
from texture_library.recording import Recording, make_channel

DEFAULT_OUT = Path("reports/bench/features.json")


def stroke_windows(n_windows: int, config: TactileConfig, seed: int = 0):
    """n_windows preprocessed windows of a synthetic stroke (accel 3 kHz, force 500 Hz, speed 1 kHz)."""
    rng = np.random.default_rng(seed)
    duration = n_windows * config.hop_s + config.window_s
    ta = np.arange(int(duration * 3000)) / 3000
    accel = 0.5 * rng.standard_normal((ta.size, 3)) + np.outer(np.sin(2 * np.pi * 180 * ta), [2.0, 0.5, 0.2])
    accel[:, 2] += 9.81
    nf = int(duration * 500)
    normal = 1.5 + 0.3 * np.sin(2 * np.pi * 0.7 * np.arange(nf) / 500) + 0.02 * rng.standard_normal(nf)
    # (tangential x, tangential y, normal): Coulomb friction μ = 0.5 along x; the paper's features read column 2
    force = np.column_stack([0.5 * normal, 0.01 * rng.standard_normal(nf), normal])
    tm = np.arange(int(duration * 1000)) / 1000
    speed = 80 + 20 * np.sin(2 * np.pi * 0.3 * tm)
    rec = Recording(
        make_channel("accel", accel, 3000), make_channel("force", force, 500), make_channel("speed", speed, 1000)
    )
    pre = TactilePreprocessor(config, max_buffer_s=None)
    pre.push(**rec.channels())
    pre.flush()
    batch = pre.take()
    return batch.accel[:n_windows], batch.speed[:n_windows], batch.force[:n_windows]


def median_seconds(fn: Callable[[], object], repeats: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def group_timings(per_window: dict[str, float], n: int, repeats: int) -> None:
    """Seconds per window of the extra feature groups, added to per_window (see the module docstring)."""
    demo = TactileConfig(extra_groups=("friction", "spatial"))
    every = TactileConfig(extra_groups=("friction", "spatial", "taps"))
    accel, speed, force = stroke_windows(n, demo)
    taps_rng = np.random.default_rng(1)
    tap_speeds = taps_rng.uniform(5, 80, 10)
    t = np.arange(100) / 1000
    tap_accel = tap_speeds[:, None] * np.exp(-t / 0.008) * np.sin(
        2 * np.pi * 200 * t
    ) + 0.05 * taps_rng.standard_normal((10, 100))
    taps = np.tile(tap_features(tap_speeds, tap_accel), (n, 1))
    for name, config, extra in (("friction_spatial", demo, ()), ("all_groups", every, (taps,))):
        print(f"timing window_features with {name} (batched, then one window per call) ...", flush=True)
        per_window[f"window_features_batched_{name}"] = (
            median_seconds(
                lambda config=config, extra=extra: window_features(accel, speed, force, config, *extra), repeats
            )
            / n
        )
        per_window[f"window_features_single_{name}"] = (
            median_seconds(
                lambda config=config, extra=extra: [
                    window_features(
                        accel[i : i + 1], speed[i : i + 1], force[i : i + 1], config, *(e[i : i + 1] for e in extra)
                    )
                    for i in range(n)
                ],
                repeats,
            )
            / n
        )
    print("timing friction, spatial and tap features alone ...", flush=True)
    per_window["friction_batched"] = (
        median_seconds(lambda: friction_features(force[:, :, 0], force[:, :, 1]), repeats) / n
    )
    per_window["spatial_batched"] = (
        median_seconds(lambda: spatial_features(accel[:, :, 3:], force[:, :, 0], speed, demo.rate_hz), repeats) / n
    )
    per_window["tap_features_per_texture"] = median_seconds(lambda: tap_features(tap_speeds, tap_accel), repeats)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=256, help="windows per batch (default 256)")
    parser.add_argument("--repeats", type=int, default=7, help="timed repeats per measurement (median)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"JSON report (default {DEFAULT_OUT})")
    args = parser.parse_args(argv)
    if args.batch < 1 or args.repeats < 1:
        parser.error("--batch and --repeats must be ≥ 1")

    config = TactileConfig()
    n = args.batch
    print(f"config {config.hash()}: {config.n_features} features per window; {n} windows")
    accel, speed, force = stroke_windows(n, config)
    folded = dft321(accel)

    per_window: dict[str, float] = {}
    print("timing window_features (batched) ...", flush=True)
    per_window["window_features_batched"] = (
        median_seconds(lambda: window_features(accel, speed, force, config), args.repeats) / n
    )
    print("timing window_features (one window per call) ...", flush=True)
    per_window["window_features_single"] = (
        median_seconds(
            lambda: [window_features(accel[i : i + 1], speed[i : i + 1], force[i : i + 1], config) for i in range(n)],
            args.repeats,
        )
        / n
    )
    print("timing mfcc step alone (batched) ...", flush=True)
    per_window["mfcc_batched"] = median_seconds(lambda: mfcc(folded, config), args.repeats) / n
    print("timing librosa.feature.mfcc per window ...", flush=True)
    per_window["librosa_mfcc"] = (
        median_seconds(lambda: [librosa_mfcc(w, config) for w in folded], max(3, args.repeats // 2), warmup=1) / n
    )
    group_timings(per_window, n, args.repeats)
    per_window_us = {k: round(v * 1e6, 3) for k, v in per_window.items()}

    ours = mfcc(folded, config)
    ref = np.stack([librosa_mfcc(w, config) for w in folded])
    feats = window_features(accel, speed, force, config)
    max_abs_diff = float(np.max(np.abs(ours - ref)))
    max_abs_diff_features = float(np.max(np.abs(feats[:, : config.n_tactile] - ref.reshape(n, -1))))
    scale = float(np.max(np.abs(ref)))

    ratios = {
        "librosa_over_mfcc_batched": per_window["librosa_mfcc"] / per_window["mfcc_batched"],
        "librosa_over_window_features_batched": per_window["librosa_mfcc"] / per_window["window_features_batched"],
        "librosa_over_window_features_single": per_window["librosa_mfcc"] / per_window["window_features_single"],
    }
    print()
    print(f"{'step':<38}{'µs / window':>14}")
    for k, v in per_window_us.items():
        print(f"{k:<38}{v:>14.1f}")
    for k, v in ratios.items():
        print(f"ratio {k:<32}{v:>14.1f}×")
    print(
        f"max |ours − librosa| MFCC: {max_abs_diff:.3g} (features: {max_abs_diff_features:.3g}; "
        f"librosa max |value| {scale:.3g})"
    )

    report = {
        "per_window_us": per_window_us,
        "ratio_librosa_over_ours": round(ratios["librosa_over_window_features_batched"], 2),
        "ratios": {k: round(v, 2) for k, v in ratios.items()},
        "max_abs_diff": max_abs_diff,
        "max_abs_diff_features": max_abs_diff_features,
        "librosa_max_abs_value": scale,
        "batch": n,
        "repeats": args.repeats,
        "config_hash": config.hash(),
        "config": config.to_dict(),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "scipy": scipy.__version__,
            "librosa": librosa.__version__,
        },
        "load_average_1_5_15_min": [round(v, 2) for v in os.getloadavg()],  # the machine is shared
        "command": "python -m benchmarks.features"
        + ("" if not (argv or sys.argv[1:]) else " " + " ".join(argv or sys.argv[1:])),
        "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    write_report(args.out, report)
    print(f"wrote {args.out}")
    return report


if __name__ == "__main__":
    main()
