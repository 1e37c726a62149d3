"""The online fidelity study (models.offline.fidelity.online): one texture's curve from a known model and a far
prior, and the world entry's shape (the `online` object of reports/fidelity/results.json)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import Delaunay

from models.offline.fidelity.online import (
    CHECKPOINTS_S,
    VISITED_POINTS,
    pick_textures,
    run_texture,
    summarise_online,
    visited_distances,
)
from texture_library.lsf import poles_to_poly, poly_to_lsf
from texture_library.spectrum import arma_psd, band_frequencies
from texture_library.surface import SurfaceProfile
from texture_library.vibration import VibrationModel


def _model(name, poles_hz, radii, level, mu, surface=None):
    speeds, forces = np.meshgrid([0.0, 150.0, 320.0], [0.0, 2.0, 4.5], indexing="ij")
    s, f = speeds.ravel(), forces.ravel()
    tri = Delaunay(np.stack([s / 320, f / 4.5], axis=1)).simplices.astype(np.int64)
    ar = poly_to_lsf(poles_to_poly(np.array(poles_hz), np.array(radii), 1000.0))
    return VibrationModel(
        name=name,
        speeds=s,
        forces=f,
        triangles=tri,
        ar_lsf=np.tile(ar, (s.size, 1)),
        ma_lsf=np.zeros((s.size, 0)),
        variance=level * (0.2 + s / 150.0),
        gain=np.ones(s.size),
        mu=mu,
        max_speed=320.0,
        max_force=4.5,
        surface=surface,
    )


def test_pick_textures_is_a_fixed_even_subsample():
    names = [f"t{i:02d}" for i in range(48)]
    assert pick_textures(names, 8) == pick_textures(names, 8)
    assert pick_textures(names, 8)[0] == 0 and pick_textures(names, 8)[-1] == 47
    assert pick_textures(names[:5], 8) == [0, 1, 2, 3, 4]


def test_curve_moves_from_the_prior_towards_the_surface():
    truth = _model("truth", [90.0, 260.0], [0.93, 0.9], 0.05, 0.35, SurfaceProfile(0.5, 15.0))
    prior = _model("prior", [40.0, 380.0], [0.8, 0.95], 0.2, 0.8)
    run = run_texture(truth, prior, 0, "truth", "prior")
    assert run.visited_db[0] == run.hybrid_visited_db[0]  # 0 s: the camera's pick itself
    assert run.visited_db[CHECKPOINTS_S.index(10.0)] < 0.5 * run.hybrid_visited_db[CHECKPOINTS_S.index(10.0)]
    assert run.mu_diff[CHECKPOINTS_S.index(10.0)] < 0.05 < run.hybrid_mu_diff
    assert abs(run.bump_height_db) <= 3.0 and abs(run.bump_period_rel) <= 0.05
    # along the operator's own stroke, bumps and all, the held model comes to sound like the surface
    assert run.signal_db[0] == run.hybrid_signal[0]
    assert run.signal_db[CHECKPOINTS_S.index(10.0)] < 0.5 * run.hybrid_signal[0]
    assert run.floor_signal[0] < run.signal_db[CHECKPOINTS_S.index(10.0)] + 1.0
    # as served: the prior until the first version (the first fit is a second in), then versions that follow the fit
    ten = CHECKPOINTS_S.index(10.0)
    assert run.served[0, 1] == run.hybrid_visited_db[0] and run.served[CHECKPOINTS_S.index(0.5), 2] == run.signal_db[0]
    assert 1 <= run.versions <= max(CHECKPOINTS_S)
    assert run.served[ten, 1] < 0.5 * run.hybrid_visited_db[ten]
    # the representation floor: perfect data through the fit's grid and ARMA step reproduce this smooth model
    assert run.floor_visited_db < 1.0 and run.floor_visited_db < run.visited_db[ten]
    entry = summarise_online([run, run], {})
    scopes = {(c["seconds"], c["scope"]) for c in entry["curve"]}
    assert scopes == {(t, s) for t in CHECKPOINTS_S for s in ("grid", "visited", "signal")}
    assert {c["rule"] for c in entry["curve"]} == {"online+prior", "online", "served"}
    assert entry["baseline_signal"]["floor"]["minus_hybrid_db"]["mean"] < 0
    assert all(set(c) >= {"seconds", "scope", "spectral_distance_db", "ci95", "st_sim", "spqi"} for c in entry["curve"])


def test_tap_scores_known_answers():
    from models.offline.fidelity.online import rendered_tap, tap_distance_db, tap_scores, tap_spread
    from texture_library.taps import TapSet

    t = np.arange(100) / 1000.0
    ring = np.exp(-t / 0.01) * np.sin(2 * np.pi * 150 * t)
    taps = TapSet(np.array([20.0, 80.0]), np.stack([20.0 * ring, 80.0 * ring]))
    # a tap is rendered from the stored one nearest in speed, scaled by speed: the same ringing at 40 mm/s
    np.testing.assert_allclose(rendered_tap(taps, 40.0), 40.0 * ring)
    assert tap_scores(taps, TapSet(np.array([40.0]), (40.0 * ring)[None])) == 0.0
    assert tap_spread(taps) == 0.0
    other = np.exp(-t / 0.002) * np.sin(2 * np.pi * 400 * t)
    assert tap_distance_db(ring, other) > 10.0
    assert np.isnan(tap_spread(TapSet(np.array([20.0]), ring[None])))


def test_visited_leaves_out_the_points_where_the_surface_is_silent():
    truth = _model("truth", [90.0, 260.0], [0.93, 0.9], 0.05, 0.35)
    other = _model("other", [40.0, 380.0], [0.8, 0.95], 0.2, 0.8)
    # the slowest row silent (zero variance), as HaTT's slowest corners are: a stroke that dwells there
    quiet = replace(truth, variance=np.where(truth.speeds == 0.0, 0.0, truth.variance))
    speed = np.concatenate([np.zeros(50), np.linspace(100.0, 300.0, 50)])
    force = np.full(100, 2.0)
    d = visited_distances(other, quiet, speed, force)
    assert d.shape == (VISITED_POINTS,)
    silent = np.isnan(d)
    assert 0 < silent.sum() < VISITED_POINTS and np.all(np.isfinite(d[~silent]))
    # where the surface is audible, the distance is the plain one: the same model scores 0 there
    np.testing.assert_allclose(visited_distances(quiet, quiet, speed, force)[~silent], 0.0, atol=1e-9)
    assert np.isnan(visited_distances(other, replace(truth, variance=0.0 * truth.variance), speed, force)).all()
    # over the measured bins only (where the truth reaches a given density): the same distance where they are, NaN
    # at the points with none
    freqs = band_frequencies()
    loud = arma_psd(quiet, speed, force, freqs)
    threshold = float(np.quantile(loud[loud > 0], 0.5))
    quieter = replace(quiet, variance=quiet.variance * 1e-3)
    far = visited_distances(quieter, quiet, speed, force)
    near = visited_distances(quieter, quiet, speed, force, measured_above=threshold)
    np.testing.assert_allclose(far[~silent], 30.0, atol=1e-6)  # a uniform 30 dB
    np.testing.assert_allclose(near[np.isfinite(near)], 30.0, atol=1e-6)
    assert np.isnan(near[silent]).all()
    assert np.isnan(visited_distances(quieter, quiet, speed, force, measured_above=10.0 * loud.max())).all()
