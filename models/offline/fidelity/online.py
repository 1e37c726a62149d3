"""What the operator holds over time: the surface's own model, learnt online, scored leave-one-texture-out.

For each stroked texture (a fixed, evenly spaced subsample of the world's rated textures; see
`pick_textures`), the prior is the served `hybrid` rule's pick from a library of every *other* texture (its
weight tuned inside the fold, `study.run_rules`; the pick most windows made). A simulated robot then hovers
FREE_S seconds (contact-free: gravity and sensor noise), and strokes the texture's true model along a
seeded freehand trajectory for up to 30 s with the simulated robot's sensor noise (`texture_library.stroke`);
its blocks go through `models.tactile.surface_fit.SurfaceFitter` exactly as a session's would. After each
checkpoint the model the operator would hold (`online+prior`: the fit blended with the prior; at 0 s the prior
itself) is scored against the true model:

  grid      mean log-spectral distance (texture_library.spectrum) over the report's nine operating points;
  visited   the same over 60 (speed, force) points of the trajectory stroked so far (at 0 s: the first 2 s);
  signal    along an operator's own 10 s stroke (its own seed, not the robot's): the operator's rendering of the
            held model (vibration and bumps, texture_library.stroke with the tool upright) against what the tool on
            the true surface gives along the same stroke, both as the same accelerometer measures them (its
            NOISE_STD, drawn apart), per 2 s window: RMS dB between Welch spectra over 20 ≤ f < 500 Hz, SPQI and
            ST-SIM (vibromaf, at its own 8 kHz: the signals upsampled); the true model rendered the same way is the
            floor. Measured by the same sensor on both sides, what lies below its noise counts on neither: against
            a noiseless rendering, the quiet stretches of a surface (tens of dB below the sensor's noise on some
            synthetic ones) scored the sensor, and even the true model sat 7.95 dB from itself there. Taps are not
            in these strokes;
  taps      the robot sends every other recorded tap of the texture; each held-out tap against the transient
            the held model renders at its speed (its stored tap nearest in speed, scaled by speed), RMS dB of
            the spectra over 20–500 Hz, beside the same distance between the texture's own held-out taps;
  friction  |Δμ|;  bumps (models with a profile) the profile's spatial-spectrum line, 20·log10 of the height
            ratio, and the period's relative error.

Alongside `online+prior`: the `online` rule (the data alone wherever a segment fell); `served`, the version an
operator holds as the service publishes (a fit each MIN_INTERVAL_S of stream keeping its orders unless clearly
beaten, offered to a models.tactile.surface_publish.SurfacePublisher; the prior until the first version); and the
representation floor (`representation_floor`: what the fit makes of perfect data).

Noise sensitivity: the same robot with no contact-free blocks, the fitter told a noise density of ½× and 2×
the true one, scored at NOISE_SECONDS. Every mean gets a texture-level bootstrap 95 % interval; differences
against `hybrid` are paired over the same textures.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.signal import resample_poly

from models.offline.evaluation.bootstrap import bootstrap_mean
from models.offline.fidelity.study import World, hybrid_costs, run_rules
from models.tactile.surface_fit import FitStatus, SurfaceFitter
from models.tactile.surface_publish import MIN_INTERVAL_S, SurfacePublisher
from texture_library.atomic_file import write_text
from texture_library.selection import band_mask, welch_frequencies, window_psd
from texture_library.spectrum import (
    PSD_FLOOR,
    arma_psd,
    band_frequencies,
    log_spectral_distance_db,
    spectral_distance_db,
)
from texture_library.stroke import GRAVITY, random_rotation, stroke
from texture_library.taps import TapSet
from texture_library.trajectory import freehand, model_ranges
from texture_library.vibration import VibrationModel

CHECKPOINTS_S = (0.0, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0)
#: the simulated robot's accelerometer noise, m/s² RMS per axis (texture_library.stroke's default)
NOISE_STD = 0.05
FREE_S = 0.5
BLOCK = 100
NOISE_SECONDS = 10.0
#: that noise's one-sided density, (m/s²)²/Hz at 1 kHz
NOISE_PSD = 2.0 * NOISE_STD**2 / 1000.0
VISITED_POINTS = 60
#: the `online` rule: the prior counts as this many segments (the data alone wherever a segment fell; the prior
#: only where none did), against `online+prior`'s surface_fit.PRIOR_SEGMENTS
DATA_ONLY_SEGMENTS = 1e-3
#: the operator's stroke (not the robot's: its own seed), s, scored in windows of SIGNAL_WINDOW_S
OPERATOR_S = 10.0
SIGNAL_WINDOW_S = 2.0
#: vibromaf's metrics assume 8 kHz (their perceptual threshold's frequency axis): the 1 kHz signals go up by this
VIBROMAF_UPSAMPLE = 8


@dataclass(frozen=True)
class TextureRun:
    """One stroked texture's scores: per checkpoint (len(CHECKPOINTS_S),) grid and visited dB, |Δμ|; the
    prior's (hybrid's) own; noise sensitivity at NOISE_SECONDS for ½× and 2×; bump errors (NaN: no bumps).
    data_only, served: (len(CHECKPOINTS_S), 5) grid, visited and signal dB, SPQI, ST-SIM of the `online` rule and of
    the version the operator holds (`served`); versions: how many were published in max(CHECKPOINTS_S) seconds;
    floor_visited_db: the representation floor (`representation_floor`) over the visited points of the first
    NOISE_SECONDS; visited_with_silent_db: (len(CHECKPOINTS_S),) visited with the silent points in (at the PSD
    floor); silent_points: how many of the first NOISE_SECONDS' visited points are silent (visited_distances);
    visited_measured_db: (online+prior at NOISE_SECONDS, hybrid) visited over the bins where the truth reaches the
    sensor's noise (what a stream can measure)."""

    texture: str
    prior: str
    grid_db: np.ndarray
    visited_db: np.ndarray
    mu_diff: np.ndarray
    hybrid_grid_db: float
    hybrid_visited_db: np.ndarray
    hybrid_mu_diff: float
    noise_half_db: float
    noise_double_db: float
    bump_height_db: float
    bump_period_rel: float
    signal_db: np.ndarray
    spqi: np.ndarray
    st_sim: np.ndarray
    hybrid_signal: tuple[float, float, float]
    floor_signal: tuple[float, float, float]
    data_only: np.ndarray
    served: np.ndarray
    versions: int
    floor_visited_db: float
    visited_with_silent_db: np.ndarray
    silent_points: int
    visited_measured_db: tuple[float, float]
    taps_db: float
    hybrid_taps_db: float
    taps_spread_db: float


def pick_textures(textures: list[str], count: int) -> list[int]:
    """`count` evenly spaced indices into the (sorted) texture list: a fixed subsample, chosen before scoring."""
    if count >= len(textures):
        return list(range(len(textures)))
    return sorted(set(np.linspace(0, len(textures) - 1, count).round().astype(int).tolist()))


def hybrid_picks(world: World) -> list[int]:
    """Per stroked texture, the hybrid rule's most frequent window pick from the other textures, with the
    weight tuned inside its fold (as `run_rules` scores it)."""
    _, info = run_rules(world)
    picks = []
    T = len(world.textures)
    for i in range(T):
        library = np.ones(T, bool)
        library[i] = False
        costs = np.where(library, hybrid_costs(world, i, info["fold_weights"][i]), np.inf)
        picks.append(int(np.bincount(costs.argmin(axis=-1), minlength=T).argmax()))
    return picks


def _visited_spectra(
    model: VibrationModel, truth: VibrationModel, speed: np.ndarray, force: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    keep = np.linspace(0, speed.size - 1, VISITED_POINTS).round().astype(int)
    freqs = band_frequencies()
    return arma_psd(model, speed[keep], force[keep], freqs), arma_psd(truth, speed[keep], force[keep], freqs)


def visited_distances(
    model: VibrationModel,
    truth: VibrationModel,
    speed: np.ndarray,
    force: np.ndarray,
    measured_above: float | None = None,
) -> np.ndarray:
    """(VISITED_POINTS,) log-spectral distance of model from truth, dB, at evenly spaced points of the (speed, force)
    trajectory (mm/s, N; (n,) each); NaN where the true model is silent (zero variance over the band: HaTT's slowest
    corners). There a log distance has no value: any audible model is "infinitely" far, and the number is the
    PSD floor's (≈ 75 dB at texture_library.spectrum's), one such point of 60 adding ≈ 1.3 dB to the mean.
    measured_above: a PSD, (m/s²)²/Hz: only the bins where the truth reaches it count (NaN where none does)."""
    a, b = _visited_spectra(model, truth, speed, force)
    if measured_above is None:
        return np.where(b.max(axis=-1) > 0, log_spectral_distance_db(a, b), np.nan)
    seen = b >= measured_above
    diff = 10.0 * np.log10(np.maximum(a, PSD_FLOOR) / np.maximum(b, PSD_FLOOR))
    sums = np.where(seen, diff**2, 0.0).sum(axis=-1)
    return np.where(seen.any(axis=-1), np.sqrt(sums / np.maximum(seen.sum(axis=-1), 1)), np.nan)


def _visited(model: VibrationModel, truth: VibrationModel, speed: np.ndarray, force: np.ndarray) -> float:
    """The mean of visited_distances over the points where the truth is audible (NaN: silent everywhere)."""
    d = visited_distances(model, truth, speed, force)
    return float(np.nanmean(d)) if np.isfinite(d).any() else float("nan")


def _visited_with_silent(model: VibrationModel, truth: VibrationModel, speed: np.ndarray, force: np.ndarray) -> float:
    """The mean over every visited point, the silent ones at texture_library.spectrum's PSD floor."""
    return float(np.mean(log_spectral_distance_db(*_visited_spectra(model, truth, speed, force))))


def _normal_stroke(model: VibrationModel, traj, seed: int, noise_std: float) -> np.ndarray:
    """(n,) acceleration along the surface normal, m/s², of `model` stroked along `traj` (vibration and bumps,
    texture_library.stroke with the tool upright), plus white sensor noise of noise_std."""
    sig = stroke(model, traj, np.random.default_rng(seed), rotation=np.eye(3), noise_std=noise_std)
    return sig.accel[:, 2] - GRAVITY


def signal_scores(rendered: np.ndarray, real: np.ndarray) -> tuple[float, float, float]:
    """(spectral distance dB, SPQI, ST-SIM) of the operator's rendering against the real surface's signal, each
    the mean over SIGNAL_WINDOW_S windows: RMS dB between Welch spectra (128-sample segments) over 20 Hz ≤ f
    < 500 Hz, and vibromaf's SPQI and ST-SIM (reference: the real signal). ST-SIM is NaN when vibromaf returns
    a complex number (its temporal term is negative: two draws of a random texture are uncorrelated waveforms)."""
    from vibromaf.metrics.spqi import spqi
    from vibromaf.metrics.stsim import st_sim

    band = band_mask(welch_frequencies())
    n = int(SIGNAL_WINDOW_S * 1000)
    dbs, quality, similarity = [], [], []
    for a in range(0, real.size - n + 1, n):
        x, y = rendered[a : a + n], real[a : a + n]
        px, py = window_psd(x)[band], window_psd(y)[band]
        dbs.append(float(np.sqrt(np.mean((10 * np.log10(np.maximum(px, 1e-12) / np.maximum(py, 1e-12))) ** 2))))
        xu, yu = resample_poly(x, VIBROMAF_UPSAMPLE, 1), resample_poly(y, VIBROMAF_UPSAMPLE, 1)
        quality.append(float(spqi(xu, yu)))
        value = complex(st_sim(xu, yu))
        similarity.append(value.real if value.imag == 0 else float("nan"))
    return (
        float(np.mean(dbs)),
        float(np.mean(quality)),
        float(np.nanmean(similarity)) if np.isfinite(similarity).any() else float("nan"),
    )


def tap_distance_db(x: np.ndarray, y: np.ndarray) -> float:
    """RMS dB between two tap transients' power spectra (128-point FFT at 1 kHz) over 20 ≤ f < 500 Hz."""
    f = np.fft.rfftfreq(128, 1e-3)
    band = (f >= 20.0) & (f < 500.0)
    px = np.abs(np.fft.rfft(x, 128))[band] ** 2
    py = np.abs(np.fft.rfft(y, 128))[band] ** 2
    return float(np.sqrt(np.mean((10 * np.log10(np.maximum(px, 1e-12) / np.maximum(py, 1e-12))) ** 2)))


def rendered_tap(taps: TapSet, speed: float) -> np.ndarray:
    """The transient a renderer plays for a tap at `speed` mm/s: the stored tap nearest in speed, scaled by
    speed (a tap's peak grows with its speed: models.tactile.taps)."""
    k = int(np.argmin(np.abs(np.log(np.maximum(taps.speeds, 1e-3) / max(speed, 1e-3)))))
    return taps.accel[k] * (speed / max(float(taps.speeds[k]), 1e-3))


def tap_scores(model_taps: TapSet | None, held: TapSet) -> float:
    """Mean over the held-out taps of tap_distance_db(rendered, recorded); NaN without model taps."""
    if model_taps is None:
        return float("nan")
    return float(np.mean([tap_distance_db(rendered_tap(model_taps, v), a) for v, a in zip(held.speeds, held.accel)]))


def tap_spread(held: TapSet) -> float:
    """The between-tap spread: each held-out tap against the texture's other held-out tap nearest in speed,
    scaled the same way (NaN with fewer than two)."""
    if held.speeds.size < 2:
        return float("nan")
    out = []
    for i, (v, a) in enumerate(zip(held.speeds, held.accel)):
        others = TapSet(np.delete(held.speeds, i), np.delete(held.accel, i, axis=0))
        out.append(tap_distance_db(rendered_tap(others, v), a))
    return float(np.mean(out))


def _robot(truth: VibrationModel, seconds: float, seed: int, free_s: float):
    rng = np.random.default_rng(seed)
    traj = freehand(seconds, rng, **model_ranges(truth.max_speed, truth.max_force))
    rot = random_rotation(rng)
    sig = stroke(truth, traj, rng, rotation=rot, noise_std=NOISE_STD)
    n = int(free_s * 1000)
    free = (
        (rot @ np.array([0.0, 0.0, GRAVITY]))[None] + NOISE_STD * rng.standard_normal((n, 3)),
        0.01 * rng.standard_normal((n, 3)),
        np.zeros(n),
        np.zeros(n),
    )
    return traj, sig, free


def representation_floor(truth: VibrationModel) -> VibrationModel:
    """What the fit makes of perfect data: the true model's spectra at the fitter's grid points, on its bins, through
    the same ARMA step (SurfaceFitter.grid_model) as if a million samples stood behind each point. What remains between
    it and the truth is the representation's: the grid, its LSF interpolation, the orders and the bins."""
    fitter = SurfaceFitter()
    spectra = arma_psd(truth, fitter.grid_speeds, fitter.grid_forces, fitter.freqs)
    return fitter.grid_model(np.maximum(spectra, 1e-12), np.full(fitter.grid_speeds.size, 1e6), name=truth.name)[0]


def _feed(fitter: SurfaceFitter, sig, start: int, stop: int) -> None:
    for a in range(start, stop, BLOCK):
        b = min(a + BLOCK, stop)
        fitter.push(sig.accel[a:b], sig.force[a:b], sig.speed[a:b], sig.position[a:b])


def run_texture(truth: VibrationModel, prior: VibrationModel, seed: int, name: str, prior_name: str) -> TextureRun:
    """One texture's curve (see the module docstring)."""
    traj, sig, free = _robot(truth, max(CHECKPOINTS_S), seed, FREE_S)
    op_rng = np.random.default_rng(seed + 100_000)
    operator = freehand(OPERATOR_S, op_rng, **model_ranges(truth.max_speed, truth.max_force))
    real = _normal_stroke(truth, operator, seed + 200_000, NOISE_STD)
    signal: list[tuple[float, float, float]] = []
    data_only: list[tuple[float, ...]] = []
    fitter = SurfaceFitter()
    held = None
    if truth.taps is not None:
        # the robot taps before it strokes and sends every other recorded tap; the rest are held out
        fitter.push_taps(truth.taps.speeds[0::2], truth.taps.accel[0::2])
        if truth.taps.speeds.size >= 4:
            held = TapSet(truth.taps.speeds[1::2], truth.taps.accel[1::2])
    fitter.push(*free)
    publisher = SurfacePublisher(name)
    orders: tuple[int, int] | None = None
    grid, visited, mu, hybrid_visited = [], [], [], []
    served: list[tuple[float, ...]] = []
    with_silent: list[float] = []
    done = 0
    fit = None

    def scores(model: VibrationModel, upto: int) -> tuple[float, ...]:
        return (
            spectral_distance_db(model, truth),
            _visited(model, truth, traj.speed[:upto], traj.force[:upto]),
            *signal_scores(_normal_stroke(model, operator, seed + 300_000, NOISE_STD), real),
        )

    # the service's cadence: a fit each MIN_INTERVAL_S of stream, offered to the publisher; the study's own fits at
    # the checkpoints
    fit_times = np.arange(MIN_INTERVAL_S, max(CHECKPOINTS_S) + MIN_INTERVAL_S / 2, MIN_INTERVAL_S)
    for t in sorted(set(CHECKPOINTS_S) | set(fit_times.round(6).tolist())):
        stop = int(round(t * 1000))
        _feed(fitter, sig, done, stop)
        done = stop
        if t in fit_times:
            kept = fitter.fit(prior, name, keep_orders=orders)
            if kept.status is FitStatus.ok:
                orders = (int(kept.extra["orders"][0]), int(kept.extra["orders"][1]))
                publisher.offer(kept.model, t)
        if t not in CHECKPOINTS_S:
            continue
        model = prior if t == 0 else fitter.fit(prior, name).model
        upto = max(stop, 2000)
        at = scores(model, upto)
        grid.append(at[0])
        visited.append(at[1])
        signal.append(at[2:])
        with_silent.append(_visited_with_silent(model, truth, traj.speed[:upto], traj.force[:upto]))
        hybrid_visited.append(_visited(prior, truth, traj.speed[:upto], traj.force[:upto]))
        mu.append(abs(model.mu - truth.mu))
        alone = prior if t == 0 else fitter.fit(prior, name, prior_segments=DATA_ONLY_SEGMENTS).model
        data_only.append(scores(alone, upto))
        served.append(scores(publisher.last or prior, upto))
        if t == NOISE_SECONDS:
            fit = model
    first = int(NOISE_SECONDS * 1000)
    noise = []
    for factor in (0.5, 2.0):
        traj_n, sig_n, _ = _robot(truth, NOISE_SECONDS, seed, 0.0)
        told = SurfaceFitter(declared_noise_psd=factor * NOISE_PSD)
        _feed(told, sig_n, 0, sig_n.speed.size)
        noise.append(_visited(told.fit(prior, name).model, truth, traj_n.speed, traj_n.force))
    bump_h = bump_p = float("nan")
    if truth.surface is not None and truth.surface.bump_height_mm > 0 and fit is not None:
        got = fit.surface
        if got is None or got.bump_height_mm <= 0:
            bump_h, bump_p = float("-inf"), float("nan")
        else:
            bump_h = 20.0 * float(np.log10(got.bump_height_mm / truth.surface.bump_height_mm))
            bump_p = got.bump_period_mm / truth.surface.bump_period_mm - 1.0
    return TextureRun(
        texture=name,
        prior=prior_name,
        grid_db=np.array(grid),
        visited_db=np.array(visited),
        mu_diff=np.array(mu),
        hybrid_grid_db=float(spectral_distance_db(prior, truth)),
        hybrid_visited_db=np.array(hybrid_visited),
        hybrid_mu_diff=abs(prior.mu - truth.mu),
        noise_half_db=noise[0],
        noise_double_db=noise[1],
        bump_height_db=bump_h,
        bump_period_rel=bump_p,
        signal_db=np.array([x[0] for x in signal]),
        spqi=np.array([x[1] for x in signal]),
        st_sim=np.array([x[2] for x in signal]),
        hybrid_signal=signal[0],
        floor_signal=signal_scores(_normal_stroke(truth, operator, seed + 300_000, NOISE_STD), real),
        data_only=np.array(data_only),
        served=np.array(served),
        versions=publisher.published,
        floor_visited_db=_visited(representation_floor(truth), truth, traj.speed[:first], traj.force[:first]),
        visited_with_silent_db=np.array(with_silent),
        silent_points=int(np.isnan(visited_distances(prior, truth, traj.speed[:first], traj.force[:first])).sum()),
        visited_measured_db=tuple(
            float(np.nanmean(visited_distances(m, truth, traj.speed[:first], traj.force[:first], NOISE_PSD)))
            for m in (fit if fit is not None else prior, prior)
        ),
        taps_db=float("nan") if held is None or fit is None else tap_scores(fit.taps, held),
        hybrid_taps_db=float("nan") if held is None else tap_scores(prior.taps, held),
        taps_spread_db=float("nan") if held is None else tap_spread(held),
    )


def _ci(values: np.ndarray, seed: int = 0) -> dict:
    r = bootstrap_mean(np.asarray(values, float), seed=seed)
    return {"mean": round(r["mean"], 3), "ci95": [round(r["lo"], 3), round(r["hi"], 3)]}


def _nanmean(values: list[float]) -> float | None:
    v = np.asarray(values, float)
    return round(float(np.nanmean(v)), 4) if np.isfinite(v).any() else None


def _signal_row(triples: list[tuple[float, float, float]]) -> dict:
    db = _ci(np.array([t[0] for t in triples]))
    return {
        "spectral_distance_db": db["mean"],
        "ci95": db["ci95"],
        "spqi": round(float(np.mean([t[1] for t in triples])), 4),
        "st_sim": _nanmean([t[2] for t in triples]),
    }


def _taps_summary(runs: list[TextureRun]) -> dict | None:
    """Held-out recorded taps against the held model's rendering at NOISE_SECONDS, the prior's, and the spread
    between the texture's own taps; each a mean over the textures that have taps, with its interval."""
    have = [r for r in runs if np.isfinite(r.taps_db) and np.isfinite(r.taps_spread_db)]
    if not have:
        return None
    return {
        "textures": len(have),
        "online_db": _ci(np.array([r.taps_db for r in have])),
        "hybrid_db": _ci(np.array([r.hybrid_taps_db for r in have])),
        "spread_db": _ci(np.array([r.taps_spread_db for r in have])),
        "online_minus_spread_db": _ci(np.array([r.taps_db - r.taps_spread_db for r in have])),
        "within_spread": int(sum(r.taps_db <= r.taps_spread_db for r in have)),
    }


def summarise_online(runs: list[TextureRun], models_by_name: dict[str, VibrationModel]) -> dict:
    """The world's `online` entry: the curve, the hybrid baseline, paired differences, noise, per dimension."""
    curve = []
    for k, t in enumerate(CHECKPOINTS_S):
        for scope, values in (
            ("grid", [r.grid_db[k] for r in runs]),
            ("visited", [r.visited_db[k] for r in runs]),
            ("signal", [r.signal_db[k] for r in runs]),
        ):
            s = _ci(np.array(values))
            signal = scope == "signal"
            curve.append(
                {
                    "seconds": t,
                    "scope": scope,
                    "rule": "online+prior",
                    "spectral_distance_db": s["mean"],
                    "ci95": s["ci95"],
                    "st_sim": _nanmean([r.st_sim[k] for r in runs]) if signal else None,
                    "spqi": round(float(np.mean([r.spqi[k] for r in runs])), 4) if signal else None,
                    "spqi_ci95": _ci(np.array([r.spqi[k] for r in runs]))["ci95"] if signal else None,
                }
            )
    for rule, table in (("online", [r.data_only for r in runs]), ("served", [r.served for r in runs])):
        for k, t in enumerate(CHECKPOINTS_S):
            for col, scope in enumerate(("grid", "visited", "signal")):
                s = _ci(np.array([x[k, col] for x in table]))
                signal = scope == "signal"
                curve.append(
                    {
                        "seconds": t,
                        "scope": scope,
                        "rule": rule,
                        "spectral_distance_db": s["mean"],
                        "ci95": s["ci95"],
                        "st_sim": _nanmean([x[k, 4] for x in table]) if signal else None,
                        "spqi": round(float(np.mean([x[k, 3] for x in table])), 4) if signal else None,
                        "spqi_ci95": _ci(np.array([x[k, 3] for x in table]))["ci95"] if signal else None,
                    }
                )
    paired = {}
    for k, t in enumerate(CHECKPOINTS_S):
        paired[str(t)] = {
            "visited_minus_hybrid_db": _ci(np.array([r.visited_db[k] - r.hybrid_visited_db[k] for r in runs])),
            "grid_minus_hybrid_db": _ci(np.array([r.grid_db[k] - r.hybrid_grid_db for r in runs])),
            "signal_minus_hybrid_db": _ci(np.array([r.signal_db[k] - r.hybrid_signal[0] for r in runs])),
            "spqi_minus_hybrid": _ci(np.array([r.spqi[k] - r.hybrid_signal[1] for r in runs])),
        }
    bumps = [r for r in runs if np.isfinite(r.bump_period_rel) or r.bump_height_db == float("-inf")]
    return {
        "textures": [r.texture for r in runs],
        "priors": [r.prior for r in runs],
        "curve": curve,
        "baseline": {
            "rule": "hybrid",
            "grid": _ci(np.array([r.hybrid_grid_db for r in runs])),
            "visited_2s": _ci(np.array([r.hybrid_visited_db[CHECKPOINTS_S.index(2.0)] for r in runs])),
            "visited_10s": _ci(np.array([r.hybrid_visited_db[CHECKPOINTS_S.index(10.0)] for r in runs])),
        },
        "representation_floor_visited_db": _ci(np.array([r.floor_visited_db for r in runs])),
        "visited_with_silent_points_db": {
            str(t): _ci(np.array([r.visited_with_silent_db[k] for r in runs]))
            for k, t in enumerate(CHECKPOINTS_S)
            if t in (2.0, 10.0)
        },
        "silent_points_of_visited": [r.silent_points for r in runs],
        "visited_measured_bins_db": {
            "seconds": NOISE_SECONDS,
            "online+prior": _ci(np.array([r.visited_measured_db[0] for r in runs])),
            "hybrid": _ci(np.array([r.visited_measured_db[1] for r in runs])),
        },
        "versions": [r.versions for r in runs],
        "baseline_signal": {
            "hybrid": {
                "seconds": 0.0,
                "scope": "signal",
                "rule": "hybrid",
                **_signal_row([r.hybrid_signal for r in runs]),
            },
            "floor": {
                "scope": "signal",
                "rule": "the true model rendered",
                **_signal_row([r.floor_signal for r in runs]),
                "minus_hybrid_db": _ci(np.array([r.floor_signal[0] - r.hybrid_signal[0] for r in runs])),
                "spqi_minus_hybrid": _ci(np.array([r.floor_signal[1] - r.hybrid_signal[1] for r in runs])),
            },
        },
        "paired": paired,
        "noise_sensitivity": {
            "seconds": NOISE_SECONDS,
            "declared_half_visited_db": _ci(np.array([r.noise_half_db for r in runs])),
            "declared_double_visited_db": _ci(np.array([r.noise_double_db for r in runs])),
        },
        "friction": {
            str(t): _ci(np.array([r.mu_diff[k] for r in runs])) for k, t in enumerate(CHECKPOINTS_S) if t in (0, 2, 10)
        },
        "friction_hybrid": _ci(np.array([r.hybrid_mu_diff for r in runs])),
        "taps": _taps_summary(runs),
        "bumps": {
            "textures_with_bumps": len(bumps),
            "height_db": [None if not np.isfinite(r.bump_height_db) else round(r.bump_height_db, 2) for r in bumps],
            "period_relative_error": [
                None if not np.isfinite(r.bump_period_rel) else round(r.bump_period_rel, 4) for r in bumps
            ],
        },
        "not_measured": (
            "taps inside the signal scope (its strokes do not tap; taps are scored on their own); the prior as the "
            "service picks it window by window (here one pick, the hybrid rule's most frequent, stands throughout)"
        ),
    }


def run_world(world: World, models: list[VibrationModel], count: int, seed: int = 0) -> dict:
    """The `online` entry of one world: `count` textures (pick_textures), each with its hybrid prior."""
    picks = hybrid_picks(world)
    runs = []
    for i in pick_textures(world.textures, count):
        j = picks[i]
        runs.append(run_texture(models[i], models[j], seed + i, world.textures[i], world.textures[j]))
    return summarise_online(runs, dict(zip(world.textures, models)))


def _taps_line(taps: dict | None) -> str:
    if taps is None:
        return ""
    return (
        f" Taps (every other recorded tap sent, the rest held out; RMS dB of the spectrum, 20–500 Hz): the held "
        f"model's rendering {taps['online_db']['mean']:.2f} {taps['online_db']['ci95']}, the prior's "
        f"{taps['hybrid_db']['mean']:.2f}, between the texture's own taps {taps['spread_db']['mean']:.2f} "
        f"{taps['spread_db']['ci95']} (within the spread on {taps['within_spread']} of {taps['textures']})."
    )


def write_online(out: Path, command: str, entries: dict[str, dict], made_from: dict | None = None) -> Path:
    """results.json's `online` key (the rest kept; with `made_from`, models.offline.provenance's record of what it
    read) and online.md beside README.md."""
    out.mkdir(parents=True, exist_ok=True)
    results = out / "results.json"
    doc = json.loads(results.read_text()) if results.exists() else {}
    doc["online"] = {"command": command, **entries, **({"provenance": made_from} if made_from else {})}
    write_text(results, json.dumps(doc, indent=1) + "\n")
    lines = [
        "# The surface's own model, learnt online: what the operator holds over time",
        "",
        f"Regenerate: `{command}` (fixed seeds). Method: `models/offline/fidelity/online.py` (docstring);",
        "the fit: `models/tactile/surface_fit.py`. The tables: `online+prior` (the fit blended with the served",
        "`hybrid` rule's pick from the other textures); the `online` rule (the data alone) in the line below each.",
        "Brackets: texture-level bootstrap 95 % intervals; differences are paired over the same textures.",
        "",
    ]
    for world, e in entries.items():
        lines += [f"## {world} ({len(e['textures'])} textures, an evenly spaced subsample)", ""]
        lines += [
            "| seconds | grid dB [95 %] | visited dB [95 %] | visited − hybrid | signal dB [95 %] | signal − hybrid "
            "| SPQI | SPQI − hybrid | ST-SIM |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        by = {(c["seconds"], c["scope"]): c for c in e["curve"] if c["rule"] == "online+prior"}
        alone = {(c["seconds"], c["scope"]): c for c in e["curve"] if c["rule"] == "online"}
        for t in CHECKPOINTS_S:
            g, v, sg = by[(t, "grid")], by[(t, "visited")], by[(t, "signal")]
            pv, ps = e["paired"][str(t)]["visited_minus_hybrid_db"], e["paired"][str(t)]["signal_minus_hybrid_db"]
            pq = e["paired"][str(t)]["spqi_minus_hybrid"]
            lines.append(
                f"| {t:g} | {g['spectral_distance_db']:.2f} {g['ci95']} | {v['spectral_distance_db']:.2f} {v['ci95']} "
                f"| {pv['mean']:+.2f} {pv['ci95']} | {sg['spectral_distance_db']:.2f} {sg['ci95']} "
                f"| {ps['mean']:+.2f} {ps['ci95']} | {sg['spqi']:.4f} | {pq['mean']:+.4f} {pq['ci95']} "
                f"| {sg['st_sim']} |"
            )
        hs, fl = e["baseline_signal"]["hybrid"], e["baseline_signal"]["floor"]
        served = {(c["seconds"], c["scope"]): c for c in e["curve"] if c["rule"] == "served"}
        lines += [
            "",
            "The `online` rule (the data alone wherever a segment fell, the prior only where none did), visited / "
            "signal dB at 2, 10 and 30 s: "
            + ", ".join(
                f"{alone[(t, 'visited')]['spectral_distance_db']:.2f} / "
                f"{alone[(t, 'signal')]['spectral_distance_db']:.2f}"
                for t in (2.0, 10.0, 30.0)
            )
            + ".",
            "",
            "As served (`served`: a fit each second of stream keeping its orders unless clearly beaten, offered to "
            "the session's publisher, which sends a version only on a perceptible change; the operator holds the "
            "last version sent, the prior before the first), visited / signal dB at 2, 10 and 30 s: "
            + ", ".join(
                f"{served[(t, 'visited')]['spectral_distance_db']:.2f} {served[(t, 'visited')]['ci95']} / "
                f"{served[(t, 'signal')]['spectral_distance_db']:.2f}"
                for t in (2.0, 10.0, 30.0)
            )
            + f"; versions published in {max(CHECKPOINTS_S):g} s: {e['versions']}.",
            "",
            f"Signal scope, for reference: `hybrid` {hs['spectral_distance_db']:.2f} {hs['ci95']} dB, SPQI "
            f"{hs['spqi']:.4f}; the true model itself rendered along the operator's stroke (the floor: two draws of "
            f"the same surface, each measured with the sensor's noise) {fl['spectral_distance_db']:.2f} "
            f"{fl['ci95']} dB, SPQI {fl['spqi']:.4f}, paired against `hybrid` {fl['minus_hybrid_db']['mean']:+.2f} "
            f"{fl['minus_hybrid_db']['ci95']} dB and SPQI {fl['spqi_minus_hybrid']['mean']:+.4f} "
            f"{fl['spqi_minus_hybrid']['ci95']} (how far SPQI can tell the surface itself from the library pick).",
            "",
            f"`visited` leaves out the points where the true model is silent (zero variance: "
            f"`visited_distances`): {sum(e['silent_points_of_visited'])} of {VISITED_POINTS * len(e['textures'])} "
            f"over the first {NOISE_SECONDS:g} s ({e['silent_points_of_visited']} per texture). With them in, at the "
            "PSD floor, `online+prior` visited at 2 / 10 s: "
            + " / ".join(
                f"{e['visited_with_silent_points_db'][k]['mean']:.2f} {e['visited_with_silent_points_db'][k]['ci95']}"
                for k in ("2.0", "10.0")
            )
            + " dB.",
            "",
            f"Over the bins where the true spectrum reaches the sensor's noise (what a stream can measure), visited at "
            f"{NOISE_SECONDS:g} s: `online+prior` {e['visited_measured_bins_db']['online+prior']['mean']:.2f} "
            f"{e['visited_measured_bins_db']['online+prior']['ci95']}, `hybrid` "
            f"{e['visited_measured_bins_db']['hybrid']['mean']:.2f} {e['visited_measured_bins_db']['hybrid']['ci95']} "
            "dB.",
            "",
            f"Representation floor (the true spectra at the fit's grid points, through its ARMA step, as if without "
            f"limit of data), visited over the first {NOISE_SECONDS:g} s: "
            f"{e['representation_floor_visited_db']['mean']:.2f} {e['representation_floor_visited_db']['ci95']} dB.",
        ]
        b, ns = e["baseline"], e["noise_sensitivity"]
        lines += [
            "",
            f"hybrid (the prior): grid {b['grid']['mean']:.2f} {b['grid']['ci95']}, visited over the first 10 s "
            f"{b['visited_10s']['mean']:.2f} {b['visited_10s']['ci95']} dB. Noise floor declared at ½× / 2× the "
            f"true noise, visited at {ns['seconds']:g} s: {ns['declared_half_visited_db']['mean']:.2f} / "
            f"{ns['declared_double_visited_db']['mean']:.2f} dB. |Δμ| at 0 / 2 / 10 s: "
            + " / ".join(f"{e['friction'][k]['mean']:.3f}" for k in ("0.0", "2.0", "10.0"))
            + f" (hybrid {e['friction_hybrid']['mean']:.3f}). Bumps (textures with a profile, at 10 s): height "
            f"error dB {e['bumps']['height_db']}, period relative error {e['bumps']['period_relative_error']}."
            + _taps_line(e["taps"]),
            "",
        ]
    lines += [f"Not measured yet: {next(iter(entries.values()))['not_measured']}.", ""]
    write_text(out / "online.md", "\n".join(lines))
    return out
