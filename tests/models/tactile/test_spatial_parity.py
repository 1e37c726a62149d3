"""Parity: the channel-first spatial spectra equal the straightforward formulation they replaced.

The reference below is the previous implementation (window-major arrays, one np.interp per column, the band
sums as a (bins × bands) product), kept here only to pin the restructured one to the same numbers.
"""

import numpy as np
import pytest
import scipy.fft

from models.tactile.spatial import (
    ENERGY_FLOOR_MM2,
    FORCE_FLOOR_N2,
    MIN_CELLS,
    _band_weights,
    band_edges_per_mm,
    position_power,
    spatial_features,
)
from texture_library.surface import SurfaceProfile

RATE = 1000.0


def reference_position_power(signal: np.ndarray, x_edges: np.ndarray, dx_mm: float, n_fft: int) -> np.ndarray:
    """One-sided power spectra over spatial frequency of signals against position, n windows at once.

    signal: (n, L, c), constant over each sample; x_edges: (n, L + 1) strictly increasing positions of
    the samples' edges, mm, starting at 0. Per window: the cell means on a dx_mm grid over the
    distance it covers (at most n_fft cells), a Hann-weighted least-squares line removed, Hann,
    zero-padded to n_fft → power (n, n_fft//2 + 1, c), normalised to sum to the mean square;
    all zeros for a window covering fewer than MIN_CELLS cells.
    """
    n, length, c = signal.shape
    cells = np.minimum((x_edges[:, -1] / dx_mm).astype(np.int64), n_fft)  # (n,)
    n_grid = int(max(cells.max(initial=0), MIN_CELLS))  # the grid the longest window needs; zero-padded to n_fft
    integral = np.concatenate(
        [np.zeros((n, 1, c)), np.cumsum(signal * np.diff(x_edges, axis=1)[:, :, None], axis=1)], axis=1
    )
    # one np.interp per column for every window: rows are laid end to end, `gap` mm apart
    gap = float(x_edges[:, -1].max(initial=0.0)) + (n_grid + 2) * dx_mm
    offset = (np.arange(n) * gap)[:, None]
    grid = (np.arange(n_grid + 1) * dx_mm)[None, :] + offset  # (n, n_grid + 1) cell edges
    xs = (x_edges + offset).ravel()
    at = np.stack([np.interp(grid.ravel(), xs, integral[:, :, k].ravel()) for k in range(c)], axis=1)
    # float32 from here: the spectra feed log-energies, and it halves the cost of the heavy part
    means = (np.diff(at.reshape(n, n_grid + 1, c), axis=1) / dx_mm).astype(
        np.float32
    )  # (n, n_grid, c); beyond a window's cells: ignored
    j = np.arange(n_grid, dtype=np.float32)[None, :]
    m = np.maximum(cells, 2)[:, None].astype(np.float32)
    inside = j < cells[:, None]
    w = np.where(
        inside, np.sin(np.float32(np.pi) * (j + 1) / (m + 1)) ** 2, np.float32(0)
    )  # Hann without its zero ends
    t = np.where(inside, 2 * j / (m - 1) - 1, np.float32(0))
    # weighted least-squares line a + b·t through each column (weights w²), removed before the taper
    w2 = w * w
    s0, s1, s2 = w2.sum(axis=1), (w2 * t).sum(axis=1), (w2 * t * t).sum(axis=1)
    y0 = np.einsum("nj,njc->nc", w2, means)
    y1 = np.einsum("nj,njc->nc", w2 * t, means)
    det = np.where(s0 * s2 - s1 * s1 > 0, s0 * s2 - s1 * s1, 1.0)
    a = (s2[:, None] * y0 - s1[:, None] * y1) / det[:, None]
    b = (s0[:, None] * y1 - s1[:, None] * y0) / det[:, None]
    tapered = w[:, :, None] * (means - a[:, None, :] - b[:, None, :] * t[:, :, None])
    spec = scipy.fft.rfft(tapered, n=n_fft, axis=1)
    norm = np.where(cells >= MIN_CELLS, 2.0 / (n_fft * np.maximum(w2.sum(axis=1, dtype=np.float64), 1e-300)), 0.0)
    return (spec.real**2 + spec.imag**2).astype(np.float64) * norm[:, None, None]


def reference_spatial_features(
    accel: np.ndarray,
    force: np.ndarray,
    speed: np.ndarray,
    rate_hz: float,
    *,
    dx_mm: float = 0.25,
    n_fft: int = 1024,
    min_period_mm: float = 1.0,
    max_period_mm: float = 32.0,
    n_bands: int = 10,
    min_speed: float = 30.0,
) -> np.ndarray:
    """accel: (n, L, 3) m/s², high-passed only against gravity; force: (n, L) normal force, N; speed:
    (n, L) mm/s ≥ 0 (tool speed along the surface) → (n, 2·n_bands + 2) float64: log10 mean-square
    profile height (mm²) then log10 mean-square normal force (N²) per band of spatial periods,
    longest periods first, then the RMS height (mm) and RMS force (N) over all bands (names:
    band_names; see the module docstring)."""
    accel = np.asarray(accel, dtype=np.float64)
    force = np.asarray(force, dtype=np.float64)
    speed = np.asarray(speed, dtype=np.float64)
    if accel.ndim != 3 or accel.shape[2] != 3 or speed.shape != accel.shape[:2] or force.shape != speed.shape:
        raise ValueError(
            f"spatial features need accel (n, L, 3), force (n, L) and speed (n, L), "
            f"got {accel.shape}, {force.shape} and {speed.shape}"
        )
    if not (rate_hz > 0 and dx_mm > 0 and min_speed > 0):
        raise ValueError(f"rate_hz, dx_mm and min_speed must be > 0, got {rate_hz}, {dx_mm}, {min_speed}")
    if 2 * dx_mm > min_period_mm:
        raise ValueError(f"dx_mm={dx_mm} cannot resolve periods of {min_period_mm} mm (needs dx ≤ period/2)")
    edges = tuple(band_edges_per_mm(min_period_mm, max_period_mm, n_bands))
    height_w = _band_weights(n_fft, dx_mm, edges, 4)
    force_w = _band_weights(n_fft, dx_mm, edges, 0)
    n = accel.shape[0]
    if n == 0:
        return np.empty((0, 2 * n_bands + 2))
    v = np.maximum(speed, 0.0)
    step = np.maximum(v, 1e-9) / rate_hz  # mm travelled during each sample (strictly > 0: x increases)
    x = np.concatenate([np.zeros((n, 1)), np.cumsum(step, axis=1)], axis=1)  # (n, L + 1) sample edges
    # position-weighted mean of v⁴ ((mm/s)⁴): the acceleration's power over a profile is |z''|²·v⁴
    v4 = np.maximum(np.sum(v**4 * step, axis=1) / np.maximum(x[:, -1], 1e-12), min_speed**4)
    power = reference_position_power(np.concatenate([1e3 * accel, force[:, :, None]], axis=2), x, dx_mm, n_fft)
    energy = np.concatenate(
        [
            power[:, :, :3].sum(axis=2) @ height_w / v4[:, None] + ENERGY_FLOOR_MM2,
            power[:, :, 3] @ force_w + FORCE_FLOOR_N2,
        ],
        axis=1,
    )  # mm² per accel band, N² per force band
    totals = np.sqrt(np.stack([energy[:, :n_bands].sum(axis=1), energy[:, n_bands:].sum(axis=1)], axis=1))
    return np.concatenate([np.log10(energy), totals], axis=1)


def _windows(n: int, length: int, seed: int):
    """n windows of noisy bumps stroked at speeds that vary within and between windows, a few at rest."""
    rng = np.random.default_rng(seed)
    speed = rng.uniform(0, 320, (n, 1)) * (1 + 0.5 * np.sin(np.linspace(0, rng.uniform(1, 9), length)))[None]
    speed[: max(1, n // 8)] *= 0.001  # nearly at rest: fewer than MIN_CELLS cells
    x = np.cumsum(speed, axis=1) / RATE
    profile = SurfaceProfile(0.3, 3.0)
    accel = rng.standard_normal((n, length, 3))
    accel[:, :, 2] += np.stack([profile.normal_accel(x[i], speed[i], RATE) for i in range(n)])
    force = 2.0 + 0.4 * np.sin(2 * np.pi * x / 7.0) + 0.01 * rng.standard_normal((n, length))
    return accel, force, speed


@pytest.mark.parametrize(("n", "length", "seed"), [(1, 500, 0), (7, 500, 1), (64, 500, 2), (5, 333, 3)])
def test_spatial_features_equal_the_reference(n, length, seed):
    accel, force, speed = _windows(n, length, seed)
    new = spatial_features(accel, force, speed, RATE)
    old = reference_spatial_features(accel, force, speed, RATE)
    np.testing.assert_allclose(new, old, rtol=1e-12, atol=1e-12)


def test_spatial_features_equal_the_reference_with_other_bands():
    accel, force, speed = _windows(9, 500, 4)
    options = {"dx_mm": 0.1, "n_fft": 512, "min_period_mm": 0.5, "max_period_mm": 8.0, "n_bands": 6, "min_speed": 10}
    np.testing.assert_allclose(
        spatial_features(accel, force, speed, RATE, **options),
        reference_spatial_features(accel, force, speed, RATE, **options),
        rtol=1e-12,
        atol=1e-12,
    )


def test_position_power_equals_the_reference():
    rng = np.random.default_rng(5)
    signal = rng.standard_normal((6, 400, 2))
    x_edges = np.concatenate([np.zeros((6, 1)), np.cumsum(rng.uniform(0.01, 0.3, (6, 400)), axis=1)], axis=1)
    np.testing.assert_allclose(
        position_power(signal, x_edges, 0.25, 1024),
        reference_position_power(signal, x_edges, 0.25, 1024),
        rtol=1e-12,
        atol=1e-15,
    )
