"""The macro surface profile and what the stroke makes of it: bumps felt as position-periodic
acceleration and force, friction as the tangential/normal ratio, and a world whose ratings follow."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.signal import welch

from texture_library.procedural import vibration_model
from texture_library.stroke import TOOL_STIFFNESS_N_PER_MM, stroke
from texture_library.surface import SurfaceProfile
from texture_library.synthesis import render
from texture_library.trajectory import Trajectory, freehand, model_ranges
from texture_library.vibration import VibrationModel


def test_constant_speed_acceleration_is_curvature_times_speed_squared():
    prof = SurfaceProfile(1.0, 8.0)
    rate, v = 1000.0, 120.0
    x = np.arange(2000) * v / rate
    a = prof.normal_accel(x, np.full(x.size, v), rate)
    k = 2 * np.pi / 8.0
    np.testing.assert_allclose(a, -0.5 * k * k * np.cos(k * x) * v * v * 1e-3, rtol=1e-12)
    # the same bumps at twice the speed: the same pattern against position, four times the acceleration
    a2 = prof.normal_accel(x, np.full(x.size, 2 * v), rate)
    np.testing.assert_allclose(a2, 4 * a, rtol=1e-12)


def test_acceleration_matches_the_second_derivative_of_height_along_any_path():
    prof = SurfaceProfile(0.8, 6.0)
    rate = 1000.0
    t = np.arange(4000) / rate
    x = 40 * np.sin(2 * np.pi * 0.7 * t)  # back and forth
    v = np.gradient(x) * rate
    numeric = np.gradient(np.gradient(prof.height(x)) * rate) * rate * 1e-3
    np.testing.assert_allclose(prof.normal_accel(x, v, rate)[5:-5], numeric[5:-5], atol=0.02 * np.abs(numeric).max())


@pytest.mark.parametrize(
    ("h", "p", "match"),
    [(-0.1, 5.0, "bump_height_mm"), (0.5, 0.0, "bump_period_mm"), (float("nan"), 5.0, "bump_height_mm")],
)
def test_bad_profiles(h, p, match):
    with pytest.raises(ValueError, match=match):
        SurfaceProfile(h, p)


def test_profile_round_trips_with_its_model(tmp_path, model):
    with_surface = dataclasses.replace(model, surface=SurfaceProfile(0.7, 12.0))
    loaded = VibrationModel.load(with_surface.save(tmp_path / "m.npz"))
    assert loaded.surface == SurfaceProfile(0.7, 12.0)
    assert VibrationModel.load(model.save(tmp_path / "plain.npz")).surface is None
    with pytest.raises(ValueError, match="surface profile must be"):
        SurfaceProfile.from_dict({"bump_height_mm": 1.0})


def _steady(n=20000, speed=150.0, force=2.0, rate=1000.0):
    # back and forth along 0…300 mm at constant speed
    position = np.abs((np.arange(n) * speed / rate) % 600 - 300)
    return Trajectory(np.full(n, speed), np.full(n, force), position, rate)


def test_a_model_without_profile_strokes_exactly_as_before(model):
    """HaTT models carry no profile: their recordings must not change (no extra random draws)."""
    traj = _steady(3000)
    a = stroke(model, traj, np.random.default_rng(7))
    b = stroke(dataclasses.replace(model, surface=None), traj, np.random.default_rng(7))
    np.testing.assert_array_equal(a.accel, b.accel)
    # and the same generator state afterwards as the pre-profile code (5 draws: 2 renders, rotation, 2 noises)
    rng = np.random.default_rng(7)
    stroke(model, traj, rng)
    ref = np.random.default_rng(7)
    render(model, traj.speed, traj.force, ref)
    render(model, traj.speed, traj.force, ref)
    ref.standard_normal((3, 3)), ref.standard_normal((3000, 3)), ref.standard_normal((3000, 3))
    assert rng.random() == ref.random()


def test_bumps_ride_on_the_normal_axis_and_the_normal_force(model):
    prof = SurfaceProfile(1.0, 10.0)
    traj = _steady()
    s = stroke(
        dataclasses.replace(model, surface=prof),
        traj,
        np.random.default_rng(1),
        rotation=np.eye(3),
        noise_std=0.0,
        force_noise_std=0.0,
    )
    flat = stroke(model, traj, np.random.default_rng(1), rotation=np.eye(3), noise_std=0.0, force_noise_std=0.0)
    bump_accel = s.accel[:, 2] - flat.accel[:, 2]
    f, pxx = welch(bump_accel, fs=1000.0, nperseg=4000)
    assert f[np.argmax(pxx)] == pytest.approx(150.0 / 10.0, abs=0.5)  # v / P
    lift = s.force[:, 2] - flat.force[:, 2]
    assert lift.max() == pytest.approx(TOOL_STIFFNESS_N_PER_MM * 0.5, rel=0.01)
    assert lift.min() == pytest.approx(-TOOL_STIFFNESS_N_PER_MM * 0.5, rel=0.01)
    # Coulomb friction follows the total normal force: the ratio stays μ
    np.testing.assert_allclose(np.abs(s.force[:, 0]) / s.force[:, 2], model.mu, rtol=1e-12)


def test_world_vibration_leaves_the_band_below_20_hz_to_the_bumps(params):
    """Like HaTT's models (fitted to 20 Hz high-passed recordings), texture vibration is ≥ 15 dB
    weaker at 5 Hz than at its strongest, so slow bumps are not buried in it."""
    rough = dataclasses.replace(params, roughness_um=200.0)
    model = vibration_model(rough, "t", np.random.default_rng(0))
    x = render(model, np.full(30000, 150.0), np.full(30000, 2.0), np.random.default_rng(1))
    f, pxx = welch(x, fs=1000.0, nperseg=2000)
    at5 = pxx[np.argmin(np.abs(f - 5.0))]
    assert 10 * np.log10(pxx.max() / at5) > 15.0
    assert model.surface == SurfaceProfile(params.bump_height_mm, params.bump_period_mm)


def test_synthetic_world_bumps_reach_the_sensors_at_any_speed(params):
    """The bump train of a synthetic texture shows up in the recorded normal force against position."""
    bumpy = vibration_model(
        dataclasses.replace(params, bump_height_mm=1.2, bump_period_mm=12.0), "b", np.random.default_rng(0)
    )
    rng = np.random.default_rng(2)
    traj = freehand(20.0, rng, **model_ranges(bumpy.max_speed, bumpy.max_force))
    s = stroke(bumpy, traj, rng)
    # resample the normal force onto travelled distance: the bump period is where the power is
    dist = np.cumsum(traj.speed) / traj.rate_hz
    grid = np.arange(0, dist[-1], 0.5)
    force = np.interp(grid, dist, s.force[:, 2])
    f, pxx = welch(force, fs=2.0, nperseg=512)  # 2 samples per mm
    short = f > 1 / 40.0  # periods under 4 cm: the hand's wander between strokes is longer
    assert 1 / f[short][np.argmax(pxx[short])] == pytest.approx(12.0, rel=0.1)
