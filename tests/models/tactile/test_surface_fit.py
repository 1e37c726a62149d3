"""Known-answer tests of the online surface fit (models.tactile.surface_fit): a stream rendered from a known
model gives back its spectrum, noise floor, μ, bumps and taps; bad input keeps the prior and says why."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import Delaunay

from models.tactile.surface_fit import ORDER_MARGIN_NATS, FitStatus, SurfaceFitter, choose_orders, clipped, constant
from texture_library.lsf import poles_to_poly, poly_to_lsf
from texture_library.spectrum import arma_psd, band_frequencies, log_spectral_distance_db
from texture_library.stroke import GRAVITY, random_rotation, stroke
from texture_library.surface import SurfaceProfile
from texture_library.taps import TapSet
from texture_library.trajectory import freehand
from texture_library.vibration import VibrationModel

NOISE_STD = 0.02  # m/s² per axis: the robot's accelerometer in these tests


def _model(name: str, poles_hz, radii, zeros_hz=(), zero_radii=(), level=0.05, surface=None, mu=0.4, taps=None):
    """An ARMA model with the same spectral shape at every grid point, louder with speed (variance ∝ speed)."""
    speeds, forces = np.meshgrid([0.0, 150.0, 320.0], [0.0, 2.0, 4.5], indexing="ij")
    s, f = speeds.ravel(), forces.ravel()
    tri = Delaunay(np.stack([s / 320, f / 4.5], axis=1)).simplices.astype(np.int64)
    m = s.size
    ar = poly_to_lsf(poles_to_poly(np.array(poles_hz), np.array(radii), 1000.0))
    ma = poly_to_lsf(poles_to_poly(np.array(zeros_hz), np.array(zero_radii), 1000.0)) if zeros_hz else np.zeros(0)
    return VibrationModel(
        name=name,
        speeds=s,
        forces=f,
        triangles=tri,
        ar_lsf=np.tile(ar, (m, 1)),
        ma_lsf=np.tile(ma, (m, 1)),
        variance=level * (0.2 + s / 150.0),
        gain=np.ones(m),
        mu=mu,
        max_speed=320.0,
        max_force=4.5,
        surface=surface,
        taps=taps,
    )


TRUTH = _model("truth", [90.0, 260.0], [0.93, 0.9], zeros_hz=[170.0], zero_radii=[0.8])
PRIOR = _model("prior", [40.0, 380.0], [0.8, 0.95], level=0.2, mu=0.8)


def _stream(model: VibrationModel, seconds: float, seed: int = 0, free_s: float = 0.5):
    """A robot hovering `free_s` s (contact-free: gravity and noise), then stroking `seconds` s."""
    rng = np.random.default_rng(seed)
    traj = freehand(seconds, rng, speed_range=(20.0, 300.0), force_range=(0.2, 4.0))
    rot = random_rotation(rng)
    sig = stroke(model, traj, rng, rotation=rot, noise_std=NOISE_STD)
    n = int(free_s * 1000)
    free_accel = (rot @ np.array([0.0, 0.0, GRAVITY]))[None] + NOISE_STD * rng.standard_normal((n, 3))
    free_force = 0.01 * rng.standard_normal((n, 3))
    return traj, sig, (free_accel, free_force, np.zeros(n), np.zeros(n))


def _feed(fitter: SurfaceFitter, sig, free, block: int = 100) -> None:
    fitter.push(*free)
    for a in range(0, sig.speed.size, block):
        b = a + block
        assert fitter.push(sig.accel[a:b], sig.force[a:b], sig.speed[a:b], sig.position[a:b]) is None


def _visited_db(model: VibrationModel, truth: VibrationModel, traj) -> float:
    keep = np.linspace(0, traj.speed.size - 1, 60).round().astype(int)
    s, f = traj.speed[keep], traj.force[keep]
    freqs = band_frequencies()
    return float(np.mean(log_spectral_distance_db(arma_psd(model, s, f, freqs), arma_psd(truth, s, f, freqs))))


@pytest.fixture(scope="module")
def fitted():
    traj, sig, free = _stream(TRUTH, 10.0)
    fitter = SurfaceFitter()
    _feed(fitter, sig, free)
    return traj, fitter, fitter.fit(PRIOR)


def test_recovers_the_spectrum_where_the_robot_stroked(fitted):
    traj, _, fit = fitted
    assert fit.status is FitStatus.ok
    prior_db = _visited_db(PRIOR, TRUTH, traj)
    fit_db = _visited_db(fit.model, TRUTH, traj)
    assert prior_db > 8.0  # the prior is far off: the test can tell a fit from the prior
    assert fit_db <= 3.0, f"fitted model {fit_db:.2f} dB from the truth over the visited region (prior {prior_db:.2f})"
    assert fit.confidence.max() > 0.8 and fit.confidence.min() >= 0.0


def test_noise_floor_is_measured_from_contact_free_blocks(fitted):
    _, _, fit = fitted
    true_floor = 2.0 * NOISE_STD**2 / 1000.0  # one axis (the normal), one-sided
    assert fit.noise_source == "contact-free blocks"
    assert fit.noise_psd == pytest.approx(true_floor, rel=0.25)


def test_friction_from_tangential_and_normal_force(fitted):
    _, _, fit = fitted
    assert fit.model.mu == pytest.approx(TRUTH.mu, abs=0.03)


def test_declared_noise_when_the_stream_has_no_contact_free_block():
    traj, sig, free = _stream(TRUTH, 3.0, free_s=0.0)
    fitter = SurfaceFitter(declared_noise_psd=1.5e-6)
    for a in range(0, sig.speed.size, 100):
        fitter.push(sig.accel[a : a + 100], sig.force[a : a + 100], sig.speed[a : a + 100], sig.position[a : a + 100])
    fit = fitter.fit(PRIOR)
    assert (fit.noise_source, fit.noise_psd) == ("declared", 1.5e-6)


def test_bump_profile_recovered_from_the_stroke():
    truth = _model("bumpy", [90.0, 260.0], [0.93, 0.9], surface=SurfaceProfile(0.6, 12.0))
    traj, sig, free = _stream(truth, 5.0, seed=3)
    fitter = SurfaceFitter()
    _feed(fitter, sig, free)
    fit = fitter.fit(PRIOR)
    assert fit.model.surface is not None
    assert fit.model.surface.bump_period_mm == pytest.approx(12.0, rel=0.03)
    # the profile's spatial spectrum is its (h/2)² line at 1/P: within 3 dB means 20·log10 of the height ratio
    assert abs(20 * np.log10(fit.model.surface.bump_height_mm / 0.6)) <= 3.0


def test_a_flat_surface_gets_no_bumps(fitted):
    _, _, fit = fitted
    assert fit.model.surface is None


def test_taps_from_tap_blocks_replace_the_priors():
    rng = np.random.default_rng(1)
    t = np.arange(100) / 1000.0
    traces = np.array([v * 0.05 * np.exp(-t / 0.01) * np.sin(2 * np.pi * 150 * t) for v in (50, 80, 120)])
    traces += 1e-3 * rng.standard_normal(traces.shape)
    prior = _model("prior-taps", [40.0], [0.8], taps=TapSet(np.array([60.0]), np.ones((1, 100))))
    fitter = SurfaceFitter()
    assert fitter.push_taps(np.array([50.0, 80.0, 120.0]), traces) is None
    _, sig, free = _stream(TRUTH, 1.0)
    _feed(fitter, sig, free)
    fit = fitter.fit(prior)
    assert fit.model.taps is not None
    np.testing.assert_allclose(fit.model.taps.speeds, [50.0, 80.0, 120.0])
    np.testing.assert_allclose(fit.model.taps.accel, traces)


def test_before_contact_the_prior_stands():
    fitter = SurfaceFitter()
    _, _, free = _stream(TRUTH, 1.0)
    fitter.push(*free)
    fit = fitter.fit(PRIOR)
    assert fit.model is PRIOR and fit.status is FitStatus.no_contact
    assert not fit.confidence.any()


def test_clipping_is_detected_and_the_block_left_out():
    _, sig, free = _stream(TRUTH, 2.0)
    fitter = SurfaceFitter()
    fitter.push(*free)
    block = np.clip(sig.accel[:500], -2.0, 2.0 + GRAVITY)
    assert clipped(block) and not clipped(sig.accel[:500])
    assert fitter.push(block, sig.force[:500], sig.speed[:500], sig.position[:500]) is FitStatus.clipping
    assert fitter.segments == 0
    assert fitter.fit(PRIOR).status is FitStatus.clipping
    assert fitter.fit(PRIOR).model is PRIOR


def test_constant_and_all_zero_signals_are_refused():
    fitter = SurfaceFitter()
    force = np.tile([0.5, 0.0, 1.0], (200, 1))
    speed = np.full(200, 100.0)
    assert constant(np.zeros((200, 3)))
    assert fitter.push(np.zeros((200, 3)), force, speed) is FitStatus.constant
    assert fitter.push(np.tile([0.0, 0.0, GRAVITY], (200, 1)), force, speed) is FitStatus.constant
    assert fitter.segments == 0 and fitter.fit(PRIOR).model is PRIOR


def test_too_short_and_too_slow_strokes_keep_the_prior():
    _, sig, free = _stream(TRUTH, 2.0)
    short = SurfaceFitter()
    short.push(*free)
    short.push(sig.accel[:300], sig.force[:300], sig.speed[:300], sig.position[:300])
    assert short.fit(PRIOR).status is FitStatus.too_short and short.fit(PRIOR).model is PRIOR
    slow = SurfaceFitter()
    slow.push(*free)
    crawl = np.full(1500, 2.0)
    slow.push(sig.accel[:1500], sig.force[:1500], crawl, np.cumsum(crawl) / 1000.0)
    assert slow.fit(PRIOR).status is FitStatus.too_slow


def test_too_noisy_stroke_keeps_the_prior():
    quiet = _model("quiet", [90.0], [0.5], level=1e-7)
    _, sig, free = _stream(quiet, 2.0)
    fitter = SurfaceFitter()
    _feed(fitter, sig, free)
    assert fitter.fit(PRIOR).status is FitStatus.too_noisy


def test_scene_change_restarts_from_the_prior(fitted):
    traj, sig, free = _stream(TRUTH, 2.0)
    fitter = SurfaceFitter()
    _feed(fitter, sig, free)
    assert fitter.fit(PRIOR).status is FitStatus.ok
    assert fitter.scene_change() is FitStatus.scene_change
    fit = fitter.fit(PRIOR)
    assert fit.status is FitStatus.scene_change and fit.model is PRIOR


def test_bad_shapes_name_the_problem():
    with pytest.raises(ValueError, match="accel"):
        SurfaceFitter().push(np.zeros((10, 2)), np.zeros(10), np.zeros(10))
    with pytest.raises(ValueError, match="finite"):
        SurfaceFitter().push(np.full((10, 3), np.nan), np.zeros(10), np.zeros(10))


def test_prior_strength_sets_the_confidence(fitted):
    _, fitter, fit = fitted
    alone = fitter.fit(PRIOR, prior_segments=1e-3)
    touched = fit.confidence > 0
    assert np.all(alone.confidence[touched] > fit.confidence[touched])
    assert np.all(alone.confidence[touched] > 0.99)
    with pytest.raises(ValueError, match="prior_segments"):
        fitter.fit(PRIOR, prior_segments=0.0)


def test_an_earlier_fits_orders_stand_unless_clearly_beaten():
    aic = np.array([100.0, 40.0, 70.0])
    n = 1000.0  # samples behind the grid: the margin is ORDER_MARGIN_NATS × n = 20
    assert choose_orders(aic, n) == 1  # nothing held: the lowest AIC
    assert choose_orders(aic, n, keep=1) == 1
    near = aic[1] + 0.9 * ORDER_MARGIN_NATS * n
    assert choose_orders(np.array([100.0, 40.0, near]), n, keep=2) == 2  # a near-tie: the held pair stays
    far = aic[1] + 1.1 * ORDER_MARGIN_NATS * n
    assert choose_orders(np.array([100.0, 40.0, far]), n, keep=2) == 1  # clearly beaten: the best
    with pytest.raises(ValueError, match="keep"):
        choose_orders(aic, n, keep=3)
    with pytest.raises(ValueError, match="n_samples"):
        choose_orders(aic, 0.0)
    with pytest.raises(ValueError, match="finite"):
        choose_orders(np.array([1.0, np.nan]), n)
