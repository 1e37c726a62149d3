"""What publishing a learnt surface model point by point saves on the wire and costs the operator, in-process.

Run from the repository root:  python -m benchmarks.publish_policy [--textures 4] [--seconds 60]

For each of `--textures` HaTT textures (a seeded draw from --hatt-source's models), the prior is the nearest other
HaTT model in spectrum (texture_library.spectrum.spectral_distance_db). A simulated robot hovers 0.5 s, then strokes
the texture's true model along a seeded freehand trajectory for `--seconds` (texture_library.stroke, 0.05 m/s²
sensor noise), fed in 20 ms blocks through models.tactile.surface_fit.SurfaceFitter; once per second of stream the
fitter fits, and the fit is offered at the same time to three publication rules:

  whole         the rule before: when models.tactile.surface_publish.perceptibly_different(held, fit) says so and
                MIN_INTERVAL_S has passed, the fit itself goes out;
  point         models.tactile.surface_publish.SurfacePublisher (the same gate and interval; the version keeps the
                held rows where the fit moved < POINT_DB at that grid point), offered the same fits;
  point+orders  the same publisher, offered the fits of a second fitter fed the same blocks that keeps its last
                fit's ARMA orders unless clearly beaten (SurfaceFitter.fit's keep_orders, as a session does).

Per rule: versions sent; bytes on the wire of the models (the first version as a whole compact payload, each later
one as a delta, texture_library.model_codec, against the version before it); and, over every fit after the first
version, the mean log-spectral distance over the nine operating points (dB) of the version the operator holds after
that fit's offer from the fit (`held_vs_fit`) and from the true model (`held_vs_truth`: what the operator feels,
against the real surface). `whole` and `point` see the same fits, so their difference is the rule's alone.
Writes reports/bench/publish_policy.json.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.report_file import command_line, write_report
from models.offline.provenance import file_input
from models.tactile.surface_fit import FitStatus, SurfaceFitter
from models.tactile.surface_publish import MIN_INTERVAL_S, POINT_DB, SurfacePublisher, perceptibly_different
from texture_library import model_codec
from texture_library.render_model import RenderModel
from texture_library.spectrum import spectral_distance_db
from texture_library.stroke import GRAVITY, stroke
from texture_library.trajectory import freehand, model_ranges
from texture_library.vibration import VibrationModel

DEFAULT_OUT = Path("reports/bench/publish_policy.json")
BLOCK = 20
FREE_S = 0.5
SEED = 0
RULES = ("whole", "point", "point+orders")


class Wire:
    """One rule's link: what the operator holds and the bytes it took (first whole, then deltas)."""

    def __init__(self, entry_id: str) -> None:
        self.entry_id = entry_id
        self.held: VibrationModel | None = None
        self.body: bytes | None = None
        self.versions = 0
        self.bytes = 0

    def send(self, model: VibrationModel) -> None:
        doc = RenderModel.from_vibration_model(self.entry_id, model)
        payload = model_codec.encode(doc)
        self.bytes += len(payload if self.body is None else model_codec.encode_delta(doc, self.body))
        self.body, self.held = model_codec.body(payload), model
        self.versions += 1


def run_texture(truth: VibrationModel, prior: VibrationModel, seconds: float, seed: int) -> dict:
    """One texture's stroke, fits and the three rules (see the module docstring)."""
    rng = np.random.default_rng(seed)
    traj = freehand(seconds, rng, rate_hz=truth.rate_hz, **model_ranges(truth.max_speed, truth.max_force))
    s = stroke(truth, traj, rng)
    n = int(FREE_S * 1000)
    accel = np.concatenate([np.array([0.0, 0.0, GRAVITY]) + 0.05 * rng.standard_normal((n, 3)), s.accel])
    force = np.concatenate([0.01 * rng.standard_normal((n, 3)), s.force])
    speed = np.concatenate([np.zeros(n), s.speed])
    plain, memory = SurfaceFitter(), SurfaceFitter()
    wires = {rule: Wire(rule) for rule in RULES}
    publishers = {"point": SurfacePublisher("point"), "point+orders": SurfacePublisher("point+orders")}
    last_whole_s = -np.inf
    orders: tuple[int, int] | None = None
    gaps: dict[str, list[tuple[float, float]]] = {rule: [] for rule in RULES}
    every = 1000  # samples between fits: one a second of stream
    for start in range(0, speed.size, every):
        stop = min(start + every, speed.size)
        for a in range(start, stop, BLOCK):
            b = min(a + BLOCK, stop)
            for fitter in (plain, memory):
                fitter.push(accel[a:b], force[a:b], speed[a:b])
        now = stop / 1000.0
        fit = plain.fit(prior, name=truth.name)
        kept = memory.fit(prior, name=truth.name, keep_orders=orders)
        if kept.status is FitStatus.ok:
            orders = (int(kept.extra["orders"][0]), int(kept.extra["orders"][1]))
        fits = {"whole": fit, "point": fit, "point+orders": kept}
        if fit.status is FitStatus.ok:
            whole = wires["whole"]
            if now - last_whole_s >= MIN_INTERVAL_S and (
                whole.held is None or perceptibly_different(whole.held, fit.model) is not None
            ):
                whole.send(fit.model)
                last_whole_s = now
        for rule, publisher in publishers.items():
            if fits[rule].status is FitStatus.ok:
                if publisher.offer(fits[rule].model, now) is not None and publisher.last is not None:
                    wires[rule].send(publisher.last)
        for rule, wire in wires.items():
            if wire.held is not None and fits[rule].status is FitStatus.ok:
                model = fits[rule].model
                gaps[rule].append((spectral_distance_db(wire.held, model), spectral_distance_db(wire.held, truth)))
    row: dict = {"prior": prior.name, "prior_vs_truth_db": round(spectral_distance_db(prior, truth), 2)}
    for rule, wire in wires.items():
        g = np.array(gaps[rule]).reshape(-1, 2)
        row[rule] = {
            "versions": wire.versions,
            "bytes": wire.bytes,
            "fits_scored": int(g.shape[0]),
            "held_vs_fit_db_mean": round(float(g[:, 0].mean()), 3) if g.size else None,
            "held_vs_fit_db_max": round(float(g[:, 0].max()), 3) if g.size else None,
            "held_vs_truth_db_mean": round(float(g[:, 1].mean()), 3) if g.size else None,
        }
    return row


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--textures", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=60.0, help="stroking per texture, s of stream")
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--hatt-source", type=Path, default=Path("../shared/data/hatt-texnet"))
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    from texture_library.hatt_xml import read_model

    paths = sorted((args.hatt_source / "models").glob("*.xml"))
    if len(paths) < 2:
        print(f"benchmarks.publish_policy: no HaTT models under {args.hatt_source} (--hatt-source)", file=sys.stderr)
        return 2
    models = [read_model(p) for p in paths]
    picks = np.random.default_rng(args.seed).choice(len(models), size=min(args.textures, len(models)), replace=False)
    rows = {}
    for k, i in enumerate(picks):
        truth = models[int(i)]
        prior = min((m for j, m in enumerate(models) if j != i), key=lambda m: spectral_distance_db(m, truth))
        rows[truth.name] = run_texture(truth, prior, args.seconds, args.seed + k)
        print(truth.name, rows[truth.name], flush=True)
    total = {}
    for rule in RULES:
        per = [r[rule] for r in rows.values()]
        total[rule] = {
            "versions": sum(p["versions"] for p in per),
            "bytes": sum(p["bytes"] for p in per),
            "bits_per_s": round(8 * sum(p["bytes"] for p in per) / (len(rows) * (args.seconds + FREE_S)), 1),
            "held_vs_fit_db_mean": round(float(np.mean([p["held_vs_fit_db_mean"] for p in per])), 3),
            "held_vs_fit_db_max": max(p["held_vs_fit_db_max"] for p in per),
            "held_vs_truth_db_mean": round(float(np.mean([p["held_vs_truth_db_mean"] for p in per])), 3),
        }
    print("total", total, flush=True)
    write_report(
        args.out,
        {
            "command": command_line("benchmarks.publish_policy", argv),
            "point_db": POINT_DB,
            "seconds": args.seconds,
            "textures": rows,
            "total": total,
        },
        [file_input("hatt source", args.hatt_source)],
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
