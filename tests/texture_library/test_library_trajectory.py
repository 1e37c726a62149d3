"""Freehand trajectories and what the tool's sensors record along them."""

from __future__ import annotations

import numpy as np
import pytest

from texture_library.stroke import GRAVITY, random_rotation, stroke
from texture_library.trajectory import Trajectory, freehand, model_ranges


def reversal_lengths(traj: Trajectory) -> np.ndarray:
    """Samples between changes of direction (complete strokes only)."""
    direction = np.sign(np.diff(traj.position, prepend=0.0))
    flips = np.flatnonzero(np.diff(direction) != 0) + 1
    return np.diff(flips)


@pytest.mark.parametrize("speed_range, force_range", [((20.0, 300.0), (0.2, 4.0)), ((5.0, 60.0), (1.0, 1.5))])
def test_freehand_stays_inside_its_ranges(speed_range, force_range):
    traj = freehand(20.0, np.random.default_rng(0), speed_range=speed_range, force_range=force_range)
    assert traj.speed.shape == traj.force.shape == traj.position.shape == (20_000,)
    assert speed_range[0] <= traj.speed.min() and traj.speed.max() <= speed_range[1]
    assert force_range[0] <= traj.force.min() and traj.force.max() <= force_range[1]
    # it uses the ranges, not a corner of them
    assert np.ptp(traj.speed) > 0.5 * (speed_range[1] - speed_range[0])
    assert np.ptp(traj.force) > 0.3 * (force_range[1] - force_range[0])


def test_strokes_go_back_and_forth_with_lengths_in_stroke_s():
    traj = freehand(30.0, np.random.default_rng(1), stroke_s=(0.8, 2.0))
    lengths = reversal_lengths(traj) / traj.rate_hz
    assert lengths.size >= 12
    assert np.all((lengths >= 0.8 - 1e-3) & (lengths <= 2.0))
    # position is the integral of the signed speed
    np.testing.assert_allclose(np.abs(np.diff(traj.position)) * traj.rate_hz, traj.speed[1:], rtol=1e-9)


def test_speed_is_lowest_at_the_turnarounds():
    traj = freehand(10.0, np.random.default_rng(2), speed_range=(20.0, 300.0))
    direction = np.sign(np.diff(traj.position, prepend=0.0))
    flips = np.flatnonzero(np.diff(direction) != 0)
    assert np.all(traj.speed[flips] < 25.0)


def test_freehand_is_deterministic_for_a_seed():
    a, b = (freehand(5.0, np.random.default_rng(3)) for _ in range(2))
    c = freehand(5.0, np.random.default_rng(4))
    for name in ("speed", "force", "position"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.allclose(a.speed, c.speed)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"duration_s": 0.0}, "duration_s must be > 0"),
        ({"rate_hz": -1.0}, "rate_hz must be > 0"),
        ({"speed_range": (300.0, 20.0)}, "speed_range"),
        ({"force_range": (-1.0, 2.0)}, "force_range"),
    ],
)
def test_freehand_rejects_bad_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        freehand(**{"duration_s": 1.0, "rng": np.random.default_rng(0), **kwargs})


def test_model_ranges_keep_inside_the_grid():
    assert model_ranges(200.0, 3.0) == {"speed_range": (20.0, 190.0), "force_range": (0.2, pytest.approx(2.85))}
    assert model_ranges(1000.0, 10.0) == {"speed_range": (20.0, 300.0), "force_range": (0.2, 4.0)}


# ---- stroke ------------------------------------------------------------------------------------
@pytest.fixture
def signals(model):
    traj = freehand(8.0, np.random.default_rng(5), **model_ranges(model.max_speed, model.max_force))
    return traj, stroke(model, traj, np.random.default_rng(6))


def test_stroke_shapes_and_copies(signals):
    traj, s = signals
    assert s.accel.shape == (8000, 3) and s.force.shape == (8000, 3)
    np.testing.assert_array_equal(s.speed, traj.speed)
    np.testing.assert_array_equal(s.position, traj.position)
    assert s.rate_hz == traj.rate_hz


def test_accelerometer_feels_gravity(signals):
    _, s = signals
    assert np.linalg.norm(s.accel.mean(axis=0)) == pytest.approx(GRAVITY, abs=0.05)


def test_force_has_the_normal_force_and_coulomb_friction_against_the_motion(model, signals):
    traj, s = signals
    direction = np.sign(np.diff(traj.position, prepend=0.0))  # motion into each sample
    np.testing.assert_allclose(s.force[:, 2], traj.force, atol=0.06)  # normal, plus 0.01 N noise
    np.testing.assert_allclose(s.force[:, 0], -model.mu * traj.force * direction, atol=0.06)
    assert np.all(np.abs(s.force[:, 1]) < 0.06)  # nothing across the stroke but noise


def test_friction_sign_is_exact_at_every_reversal(model):
    """No force noise: the tangential force is exactly −μ·F_n·direction, turnaround samples included."""
    traj = freehand(6.0, np.random.default_rng(7), **model_ranges(model.max_speed, model.max_force))
    s = stroke(model, traj, np.random.default_rng(8), force_noise_std=0.0)
    direction = np.sign(np.diff(traj.position, prepend=0.0))
    np.testing.assert_array_equal(s.force[:, 0], -model.mu * traj.force * direction)


def test_known_rotation_maps_tool_frame_to_sensor_frame(model):
    """With the identity mounting and no noise, z holds normal vibration + g and y is empty."""
    traj = freehand(3.0, np.random.default_rng(9), **model_ranges(model.max_speed, model.max_force))
    s = stroke(model, traj, np.random.default_rng(10), rotation=np.eye(3), noise_std=0.0)
    np.testing.assert_array_equal(s.accel[:, 1], 0.0)
    assert s.accel[:, 2].mean() == pytest.approx(GRAVITY, abs=0.1)
    assert 0 < s.accel[:, 0].std() < s.accel[:, 2].std()  # along the stroke: weaker (tangential_ratio 0.5)


@pytest.mark.parametrize("seed", range(5))
def test_random_rotation_is_a_proper_rotation(seed):
    r = random_rotation(np.random.default_rng(seed))
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_stroke_is_deterministic_for_a_seed(model):
    traj = freehand(2.0, np.random.default_rng(11), **model_ranges(model.max_speed, model.max_force))
    a, b = (stroke(model, traj, np.random.default_rng(12)) for _ in range(2))
    np.testing.assert_array_equal(a.accel, b.accel)
    np.testing.assert_array_equal(a.force, b.force)


def test_stroke_refuses_a_trajectory_at_another_rate(model):
    traj = freehand(1.0, np.random.default_rng(0), rate_hz=500.0)
    with pytest.raises(ValueError, match="trajectory rate 500.0 Hz differs"):
        stroke(model, traj, np.random.default_rng(0))


def test_strokes_must_last_at_least_two_samples():
    """A zero-sample stroke would never advance the trajectory (it used to hang)."""
    with pytest.raises(ValueError, match="stroke_s must satisfy"):
        freehand(1.0, np.random.default_rng(0), stroke_s=(0.0001, 0.0005))
    with pytest.raises(ValueError, match="stroke_s must satisfy"):
        freehand(1.0, np.random.default_rng(0), stroke_s=(2.0, 1.0))
