"""What a session's learnt surface model costs the window pool, and how close it gets, in-process (no server).

Run from the repository root:  python -m benchmarks.surface_model [--seconds 5] [--textures 8]

For each texture: 0.5 s of hovering (gravity + the stroke's 0.05 m/s² noise) then `--seconds` of freehand
stroking, fed in 20 ms blocks through service.surface_models.SessionSurface (as an estimation job feeds it), then one
fit with the library neighbour nearest in spectrum as the prior. Reported, per texture: thread CPU of the feed as a
share of the stream's duration (the floor: real time, 1.0), thread CPU of the fit (s), and the mean log-spectral
distance over the nine operating points (texture_library.spectrum.spectral_distance_db) of the learnt model and of
its prior to the truth. Textures: a two-resonance ARMA texture that no library holds ("known", the real-uvicorn
test's), and the synthetic world's first `--textures` (each against the best of the others as prior).
Writes reports/bench/surface_model.json.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
from scipy.spatial import Delaunay

from benchmarks.report_file import write_report
from service.surface_models import SessionSurface
from texture_library.lsf import poles_to_poly, poly_to_lsf
from texture_library.procedural import make_world
from texture_library.recording import Channel
from texture_library.spectrum import spectral_distance_db
from texture_library.stroke import GRAVITY, stroke
from texture_library.trajectory import freehand, model_ranges
from texture_library.vibration import VibrationModel

DEFAULT_OUT = Path("reports/bench/surface_model.json")
BLOCK = 20
SEED = 7


def known_texture() -> VibrationModel:
    """A texture no library entry resembles (the synthetic world's library holds nothing like it): two resonances and
    a notch, the same shape everywhere, louder with speed; the benchmark's and the service test's known answer."""
    speeds, forces = np.meshgrid([0.0, 150.0, 320.0], [0.0, 2.0, 4.5], indexing="ij")
    s, f = speeds.ravel(), forces.ravel()
    m = s.size
    ar = poly_to_lsf(poles_to_poly(np.array([90.0, 260.0]), np.array([0.93, 0.9]), 1000.0))
    ma = poly_to_lsf(poles_to_poly(np.array([170.0]), np.array([0.8]), 1000.0))
    return VibrationModel(
        name="known",
        speeds=s,
        forces=f,
        triangles=Delaunay(np.stack([s / 320, f / 4.5], axis=1)).simplices.astype(np.int64),
        ar_lsf=np.tile(ar, (m, 1)),
        ma_lsf=np.tile(ma, (m, 1)),
        variance=0.05 * (0.2 + s / 150.0),
        gain=np.ones(m),
        mu=0.4,
        max_speed=320.0,
        max_force=4.5,
    )


def measure(truth: VibrationModel, prior: VibrationModel, seconds: float) -> dict:
    rng = np.random.default_rng(SEED)
    traj = freehand(seconds, rng, rate_hz=truth.rate_hz, **model_ranges(truth.max_speed, truth.max_force))
    s = stroke(truth, traj, rng)
    n = 500
    accel = np.concatenate([np.array([0.0, 0.0, GRAVITY]) + 0.05 * rng.standard_normal((n, 3)), s.accel])
    force = np.concatenate([0.01 * rng.standard_normal((n, 3)), s.force])
    speed = np.concatenate([np.zeros(n), s.speed])
    surface = SessionSurface("bench")
    t0 = time.thread_time()
    for a in range(0, speed.size, BLOCK):
        b = a + BLOCK
        surface.feed(0, {"accel": Channel(accel[a:b], 1000.0), "force": Channel(force[a:b], 1000.0),
                         "speed": Channel(speed[a:b], 1000.0)})  # fmt: skip
    feed_s = time.thread_time() - t0
    t0 = time.thread_time()
    outcome = surface.fit(prior, 0.0, prior.name)
    fit_s = time.thread_time() - t0
    learnt = outcome.served.model.to_vibration_model() if outcome.served is not None else prior
    return {
        "status": outcome.status.name,
        "feed_share_of_stream": round(feed_s / (speed.size / 1000.0), 4),
        "fit_cpu_s": round(fit_s, 3),
        "learnt_db": round(spectral_distance_db(learnt, truth), 2),
        "prior_db": round(spectral_distance_db(prior, truth), 2),
        "prior": prior.name,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--textures", type=int, default=8)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args()
    world = [t.model for t in make_world(args.textures, 0, image_size=64)]
    rows = {}
    known = known_texture()
    prior = min(world, key=lambda m: spectral_distance_db(m, known))
    rows["known"] = measure(known, prior, args.seconds)
    print("known", rows["known"], flush=True)
    for i, truth in enumerate(world):
        others = [m for j, m in enumerate(world) if j != i]
        prior = min(others, key=lambda m: spectral_distance_db(m, truth))
        rows[truth.name] = measure(truth, prior, args.seconds)
        print(truth.name, rows[truth.name], flush=True)
    write_report(
        args.out,
        {
            "host": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "seconds": args.seconds,
            "textures": rows,
        },
    )


if __name__ == "__main__":
    main()
