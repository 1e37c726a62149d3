"""Spatial spectra: a bump train of period P puts its energy at 1/P mm⁻¹ at any stroke speed."""

import numpy as np
import pytest

from models.tactile.spatial import (
    ENERGY_FLOOR_MM2,
    FORCE_FLOOR_N2,
    band_edges_per_mm,
    band_names,
    position_power,
    spatial_features,
)
from texture_library.stroke import random_rotation
from texture_library.surface import SurfaceProfile

RATE = 1000.0
L = 500
N_BANDS = 10
EDGES = band_edges_per_mm(1.0, 32.0, N_BANDS)
CENTRES_MM = 1.0 / np.sqrt(EDGES[:-1] * EDGES[1:])  # the period at the geometric centre of each band


def stroke_over(
    profile: SurfaceProfile, speed: np.ndarray, rotation: np.ndarray | None = None, force_per_mm: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Accel (1, L, 3) m/s² and normal force (1, L) N of a tip riding `profile` at `speed` (L,) mm/s."""
    x = np.cumsum(speed) / RATE
    a = profile.normal_accel(x, speed, RATE)
    tool = np.zeros((L, 3))
    tool[:, 2] = a
    accel = tool if rotation is None else tool @ rotation.T
    force = 2.0 + force_per_mm * (profile.height(x) - profile.bump_height_mm / 2)
    return accel[None], force[None]


@pytest.mark.parametrize("band", [3, 5, 7])
@pytest.mark.parametrize("speed_mm_s", [90.0, 180.0, 300.0])
def test_bump_train_energy_sits_at_its_period_at_any_speed(band, speed_mm_s):
    """Known answer: z = h(1 + cos 2πx/P)/2 → h²/8 mm² in the band of 1/P, whatever the speed.
    Slower strokes cover fewer periods per window, so the line spreads into the neighbours."""
    period, h = CENTRES_MM[band], 0.4
    speed = np.full(L, speed_mm_s)
    accel, force = stroke_over(SurfaceProfile(h, period), speed)
    f = spatial_features(accel, force, speed[None], RATE)[0]
    energy = 10 ** f[:N_BANDS] - ENERGY_FLOOR_MM2
    assert int(np.argmax(energy)) == band
    assert energy[band - 1 : band + 2].sum() == pytest.approx(h**2 / 8, rel=0.25)
    far = np.delete(energy, np.arange(band - 1, band + 2))
    assert far.max() < 0.02 * energy[band]


def test_varying_speed_and_sensor_orientation_do_not_move_the_line():
    """Speed rising from 60 to 260 mm/s within the window, sensor mounted at a random orientation."""
    band, h = 5, 0.3
    speed = np.linspace(60.0, 260.0, L)
    rot = random_rotation(np.random.default_rng(3))
    accel, force = stroke_over(SurfaceProfile(h, CENTRES_MM[band]), speed, rot)
    f = spatial_features(accel, force, speed[None], RATE)[0]
    energy = 10 ** f[:N_BANDS]
    assert int(np.argmax(energy)) == band
    assert energy[band - 1 : band + 2].sum() == pytest.approx(h**2 / 8, rel=0.25)


def test_force_bands_see_the_bumps_the_hand_spring_feels():
    """Normal force 2 N + k·(z − h/2): (k·h/2)²/2 N² in the band of 1/P; the RMS totals follow."""
    band, h, k = 4, 0.6, 0.5
    speed = np.full(L, 80.0)  # slowish: the acceleration is faint (∝ v²), the force is not
    accel, force = stroke_over(SurfaceProfile(h, CENTRES_MM[band]), speed, force_per_mm=k)
    f = spatial_features(accel, force, speed[None], RATE)[0]
    force_energy = 10 ** f[N_BANDS : 2 * N_BANDS] - FORCE_FLOOR_N2
    assert int(np.argmax(force_energy)) == band
    expected = (k * h / 2) ** 2 / 2
    assert force_energy[band - 1 : band + 2].sum() == pytest.approx(expected, rel=0.25)
    assert f[-1] == pytest.approx(np.sqrt(expected), rel=0.15)  # spatial_force_rms_n
    height_energy = 10 ** f[:N_BANDS] - ENERGY_FLOOR_MM2
    assert f[-2] == pytest.approx(np.sqrt(height_energy.sum() + N_BANDS * ENERGY_FLOOR_MM2))


def test_position_power_sums_to_the_mean_square():
    """Normalisation: a sinusoid of amplitude A against position → total power A²/2."""
    x_edges = np.arange(801) * 0.2  # 160 mm in 0.2 mm samples
    centres = x_edges[:-1] + 0.1
    signal = 3.0 * np.cos(2 * np.pi * centres / 7.0)[:, None]
    short = np.arange(801) * 0.001  # 0.8 mm: fewer than MIN_CELLS cells
    power = position_power(np.stack([signal, signal]), np.stack([x_edges, short]), 0.25, 1024)
    assert power.shape == (2, 513, 1)
    assert power[0].sum() == pytest.approx(4.5, rel=0.05)
    assert np.all(power[1] == 0.0)


def test_position_power_refuses_positions_that_do_not_start_at_zero_or_do_not_fit_the_signal():
    signal = np.ones((2, 100, 1))
    x_edges = np.tile(np.arange(101) * 0.3, (2, 1))
    with pytest.raises(ValueError, match="starting at 0 mm"):
        position_power(signal, x_edges + 1.0, 0.25, 1024)
    with pytest.raises(ValueError, match=r"x_edges must be \(n, L \+ 1\)"):
        position_power(signal, x_edges[:, :50], 0.25, 1024)


def test_a_tool_at_rest_reads_the_floor_not_nan():
    speed = np.zeros((2, L))
    f = spatial_features(np.ones((2, L, 3)), np.full((2, L), 2.0), speed, RATE)
    assert np.all(np.isfinite(f))
    np.testing.assert_allclose(f[:, :N_BANDS], np.log10(ENERGY_FLOOR_MM2))
    np.testing.assert_allclose(f[:, N_BANDS : 2 * N_BANDS], np.log10(FORCE_FLOOR_N2))
    np.testing.assert_allclose(f[:, -2], np.sqrt(N_BANDS * ENERGY_FLOOR_MM2))


def test_names_follow_the_bands():
    names = band_names(1.0, 32.0, N_BANDS)
    assert len(names) == 2 * N_BANDS + 2
    assert names[0] == "spatial_accel_32-22.6mm" and names[N_BANDS - 1] == "spatial_accel_1.41-1mm"
    assert names[N_BANDS] == "spatial_force_32-22.6mm"
    assert names[-2:] == ["spatial_accel_rms_mm", "spatial_force_rms_n"]


@pytest.mark.parametrize(
    ("accel", "force", "speed", "kwargs", "match"),
    [
        (np.zeros((1, L, 2)), np.zeros((1, L)), np.zeros((1, L)), {}, r"accel \(n, L, 3\)"),
        (np.zeros((1, L, 3)), np.zeros((1, L - 1)), np.zeros((1, L)), {}, r"force \(n, L\)"),
        (np.zeros((1, L, 3)), np.zeros((1, L)), np.zeros((1, L)), {"dx_mm": 0.6}, "cannot resolve"),
        (np.zeros((1, L, 3)), np.zeros((1, L)), np.zeros((1, L)), {"min_speed": 0.0}, "must be > 0"),
    ],
)
def test_bad_arguments(accel, force, speed, kwargs, match):
    with pytest.raises(ValueError, match=match):
        spatial_features(accel, force, speed, RATE, **kwargs)
