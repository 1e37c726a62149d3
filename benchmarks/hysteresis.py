"""Hysteresis that neither flips nor sticks: flips on steady strokes, windows held after a surface change.

Run from the repository root:  python -m benchmarks.hysteresis [--leads 0 36 48 60 72 96]

The service tests' world (a six-texture synthetic library, ridge-tactile trained on an eight-texture synthetic
dataset, the default Settings: hybrid rule, margin 12, hold 4, settle 6), built here. Every window is computed as
the service computes it (load_runtime; the serving hop, float32 samples as on the wire, the ratings' EMA, the
vibration mismatch's EMA, the rule's costs), then HysteresisChooser is replayed on the costs for each release lead:
  steady   a one-minute steady stroke (constant speed and force) over each texture, two seeds: choice changes
           after the settling windows (target 0), and the largest lead a challenger reached with no lead release
  change   20 s over one texture then 20 s over another in one stream, every ordered pair: windows held by
           hysteresis after the change before the choice first reaches the one the stream ends on (without
           and with a camera frame at the change, i.e. `release()`), for all pairs and the pair furthest apart
           in rating space (tests/service/test_service_selection.py streams that one through a real server)
Deterministic (fixed seeds): the numbers do not depend on the machine's load. Writes
reports/bench/hysteresis.json.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.report_file import write_report

DEFAULT_OUT = Path("reports/bench/hysteresis.json")
STEADY_S = 60.0
SURFACE_S = 20.0
STEADY_SEEDS = (1, 2)


def steady_recording(library, entry_id: str, seed: int, seconds: float):
    """`seconds` of stroking one entry at a constant 30 % of its speed range and 40 % of its force range (float32
    samples, as a robot sends them)."""
    from texture_library.recording import Channel, recording_from_stroke
    from texture_library.stroke import stroke
    from texture_library.trajectory import Trajectory

    model = library.model(entry_id)
    n = int(seconds * model.rate_hz)
    speed = np.full(n, 0.3 * model.max_speed)
    force = np.full(n, 0.4 * model.max_force)
    trajectory = Trajectory(speed, force, np.cumsum(speed) / model.rate_hz, model.rate_hz)
    s = stroke(model, trajectory, np.random.default_rng(seed))
    rec = recording_from_stroke(s.accel, s.force, s.speed, s.rate_hz)
    f32 = lambda c: Channel(c.data.astype(np.float32).astype(np.float64), c.rate_hz)  # noqa: E731
    return f32(rec.accel), f32(rec.force), f32(rec.speed)


def window_costs(runtime, alpha: float, channels: list[tuple]) -> np.ndarray:
    """(n_windows, n_entries) the selection rule's costs of each window of one stream (the recordings' samples
    one after the other), as the service's lookup step computes them before hysteresis."""
    from models.tactile.features import window_features
    from models.tactile.preprocess import TactilePreprocessor

    pre = TactilePreprocessor(runtime.tactile_config, max_buffer_s=None)
    for accel, force, speed in channels:
        pre.push(accel=accel, force=force, speed=speed)
    batch = pre.take()
    rows = window_features(batch.accel, batch.speed, batch.force, runtime.tactile_config, None)
    raw = runtime.predictor.predict(rows)
    smoothed = mismatch = None
    out = []
    for i in range(len(batch)):
        smoothed = raw[i] if smoothed is None else alpha * raw[i] + (1 - alpha) * smoothed
        force = batch.force[i]
        normal = force[:, 0] if force.ndim == 2 else force
        m = runtime.spectra.mismatch_db(
            batch.accel[i], float(batch.speed[i].mean()), float(normal.mean()), runtime.selection.mismatch_kind
        )
        mismatch = m if mismatch is None else alpha * m + (1 - alpha) * mismatch
        out.append(runtime.selection.costs(runtime.index.distances(smoothed), mismatch))
    return np.asarray(out)


def replay(runtime, settings, costs: np.ndarray, lead: float, release_at: int | None = None) -> list:
    """The Choices of HysteresisChooser over a stream's costs; `release()` before window `release_at`."""
    from texture_library.selection import HysteresisChooser

    chooser = HysteresisChooser(
        runtime.selection,
        settings.hysteresis_margin,
        settings.hysteresis_hold,
        settings.hysteresis_settle_windows,
        lead or None,
    )
    ids = runtime.index.ids
    choices = []
    for i, c in enumerate(costs):
        if i == release_at:
            chooser.release()
        choices.append(chooser.choose(ids, c))
    return choices


def flips(choices: list, settle: int) -> int:
    ids = [c.id for c in choices[settle:]]
    return sum(a != b for a, b in zip(ids, ids[1:], strict=False))


def held_before_switch(choices: list, change: int) -> int:
    """Windows from `change` on held by hysteresis before the choice first is the stream's last choice."""
    final, held = choices[-1].id, 0
    for c in choices[change:]:
        if c.id == final:
            return held
        held += c.held_by_hysteresis
    return held


def max_lead(ids: list[str], costs: np.ndarray, margin: float, hold: int, settle: int) -> float:
    """The largest cost advantage a challenger summed over consecutive windows as the rule's pick, with no lead
    release (what a release lead must stay above for a steady stroke not to flip)."""
    current, challenger, lead, streak, best = None, None, 0.0, 0, 0.0
    for w, c in enumerate(costs, 1):
        k = int(np.argmin(c))
        if current is None or ids[k] == current or w <= settle:
            current, challenger, lead, streak = ids[k], None, 0.0, 0
            continue
        gain = float(c[ids.index(current)] - c[k])
        if ids[k] != challenger:
            challenger, lead, streak = ids[k], 0.0, 0
        lead += gain
        streak = streak + 1 if gain >= margin else 0
        best = max(best, lead)
        if streak >= hold:
            current, challenger, lead, streak = ids[k], None, 0.0, 0
    return best


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--leads", type=float, nargs="+", default=[0, 36, 48, 60, 72, 96], help="0: no lead release")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)

    from models.offline.datasets.build import build
    from models.offline.train import train_and_export
    from service.runtime import load_runtime
    from service.settings import Settings
    from texture_library.library import Library
    from texture_library.synthetic_library import build_synthetic_library

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        build_synthetic_library(root / "library", n_textures=6, image_size=256)
        dataset = build("synthetic", root / "dataset", n_textures=8, duration_s=4)
        model = train_and_export(dataset, "ridge-tactile", root / "ridge-tactile.onnx")
        settings = Settings(model_path=model, library_dir=root / "library")
        runtime = load_runtime(settings)
        library = Library.load(root / "library")
        ids = list(runtime.index.ids)
        alpha = settings.smoothing_alpha
        steady = {
            (e, s): window_costs(runtime, alpha, [steady_recording(library, e, s, STEADY_S)])
            for e in library.ids
            for s in STEADY_SEEDS
        }
        change = {
            (a, b): window_costs(
                runtime,
                alpha,
                [steady_recording(library, a, 3, SURFACE_S), steady_recording(library, b, 4, SURFACE_S)],
            )
            for a in library.ids
            for b in library.ids
            if a != b
        }
    ratings = np.asarray(library.ratings, float)
    distance = np.linalg.norm(ratings[:, None] - ratings[None], axis=-1)
    i, j = np.unravel_index(int(np.argmax(distance)), distance.shape)
    far = (library.ids[i], library.ids[j])
    hop = settings.hop_s
    first_after = {k: int(np.ceil((SURFACE_S - runtime.tactile_config.window_s) / hop + 1e-9)) for k in change}
    m, h, settle = settings.hysteresis_margin, settings.hysteresis_hold, settings.hysteresis_settle_windows
    leads_steady = [max_lead(ids, c, m, h, settle) for c in steady.values()]
    print(
        f"steady strokes: {len(steady)} × {STEADY_S:g} s; the largest lead a challenger reached without a lead "
        f"release: {max(leads_steady):.1f} (per stream: {', '.join(f'{x:.0f}' for x in leads_steady)})",
        flush=True,
    )
    results = []
    for lead in args.leads:
        steady_flips = [flips(replay(runtime, settings, c, lead), settle) for c in steady.values()]
        held = {k: held_before_switch(replay(runtime, settings, c, lead), first_after[k]) for k, c in change.items()}
        camera = {
            k: held_before_switch(replay(runtime, settings, c, lead, first_after[k]), first_after[k])
            for k, c in change.items()
        }
        values = list(held.values())
        row = {
            "release_lead": lead,
            "steady_flips": sum(steady_flips),
            "steady_flips_per_minute_max": max(steady_flips) * 60.0 / STEADY_S,
            "held_mean": round(float(np.mean(values)), 2),
            "held_p90": float(np.percentile(values, 90)),
            "held_max": max(values),
            "held_far_pair": [held[far], held[far[::-1]]],
            "held_with_frame_max": max(camera.values()),
        }
        results.append(row)
        print(
            f"release lead {lead:5g}: steady flips {row['steady_flips']} (max {row['steady_flips_per_minute_max']:g}"
            f"/min); after a change held mean {row['held_mean']:.2f}, p90 {row['held_p90']:.1f}, max "
            f"{row['held_max']}; furthest pair {far[0]}↔{far[1]} {row['held_far_pair']}; with a frame at the "
            f"change max {row['held_with_frame_max']}",
            flush=True,
        )
    report = {
        "settings": {"rule": settings.selection_rule, "margin": m, "hold": h, "settle": settle, "hop_s": hop},
        "steady": {"streams": len(steady), "seconds": STEADY_S, "max_lead_without_release": max(leads_steady)},
        "change": {"pairs": len(change), "seconds_each": SURFACE_S, "furthest_pair": list(far)},
        "leads": results,
    }
    write_report(args.out, report)
    print(f"wrote {args.out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
