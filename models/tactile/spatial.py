"""Spatial spectra: the window's acceleration and normal force against position, per band of spatial periods.

Bumps are a function of *where* the tool is: a bump train of period P stroked at v mm/s rings at
v/P Hz, which wanders with the stroke's speed (and falls below the MFCC frames' resolution and
the 20 Hz high-pass on a slow stroke). Against position it stays at 1/P mm⁻¹. Per window:

  1. resample onto a uniform position grid (step dx mm) using the integrated speed
     x(t) = Σ v/rate: each grid cell takes the mean of the signal over the cell (the exact
     integral of the piecewise-constant samples, which also suppresses aliasing when the tool
     moves slowly);
  2. remove the (Hann-weighted) linear trend, Hann-window the cells the window covered,
     zero-pad to n_fft, and take the one-sided power spectrum normalised so that it sums to the
     mean square (a sinusoid of amplitude A → A²/2), summed over the signal's columns (so the
     accelerometer's mounting orientation does not matter);
  3. sum the bins in each band of spatial periods (geometric bands from max_period down to
     min_period) and take log10(energy + floor).

Two signals, one band set each:

  spatial_accel_*  acceleration (high-passed only against gravity, at `spatial_highpass_hz` ≈ 1 Hz)
                   speed-normalised to curvature — the tip's acceleration over a profile z(x) is
                   z''(x)·v² (+ z'(x)·v̇, small), so the spectrum is divided by the window's
                   position-weighted mean of v⁴ (floored at min_speed⁴: slow samples are not
                   amplified) and by (2πk)⁴ (curvature → height): the band's mean-square height,
                   mm². A bump train z = h·(1 + cos(2πx/P))/2 puts h²/8 mm² into the band holding
                   1/P at any speed (up to the spread of the window's spectral line over
                   neighbouring bands when the window covers only a few periods);
                   floor ENERGY_FLOOR_MM2;
  spatial_force_*  normal force (low-passed at 25 Hz): the hand–tool spring the bumps compress
                   (texture_library.stroke), mean-square force per band, N² — it sees long
                   periods at slow strokes, where the acceleration (∝ v²/P²) is faint;
                   floor FORCE_FLOOR_N2.

and two totals over all bands, linear (a bump train lifts whichever band its period falls in;
their sum is what says "bumpy", and a linear model cannot sum exponentials of log bands):

  spatial_accel_rms_mm  √(Σ accel band energies): the RMS profile height over 1–32 mm periods, mm
  spatial_force_rms_n   √(Σ force band energies): the RMS normal-force fluctuation over them, N

A window in which the tool moved less than MIN_CELLS grid cells has no spatial spectrum: every
band then reads log10(floor) and the totals √(n_bands·floor) (documented fallback, never NaN).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.fft

#: added to every accel band's energy before the log, mm² (a 0.3 µm bump train's energy)
ENERGY_FLOOR_MM2 = 1e-8
#: added to every force band's energy before the log, N² (well below 0.01 N sensor noise)
FORCE_FLOOR_N2 = 1e-8
MIN_CELLS = 4


@lru_cache(maxsize=16)
def band_edges_per_mm(min_period_mm: float, max_period_mm: float, n_bands: int) -> np.ndarray:
    """(n_bands + 1,) spatial-frequency band edges, mm⁻¹, ascending (band 0 holds the longest periods)."""
    if not (0 < min_period_mm < max_period_mm) or n_bands < 1:
        raise ValueError(f"need 0 < min_period < max_period and n_bands ≥ 1, got {min_period_mm}, {max_period_mm}, {n_bands}")
    edges = np.geomspace(1.0 / max_period_mm, 1.0 / min_period_mm, n_bands + 1)
    edges.setflags(write=False)
    return edges


def band_names(min_period_mm: float, max_period_mm: float, n_bands: int) -> list[str]:
    """Feature names: accel bands, force bands (longest periods first: spatial_{accel,force}_<long>-<short>mm),
    then the two totals."""
    edges = band_edges_per_mm(min_period_mm, max_period_mm, n_bands)
    spans = [f"{1 / lo:.3g}-{1 / hi:.3g}mm" for lo, hi in zip(edges[:-1], edges[1:])]
    bands = [f"spatial_{signal}_{span}" for signal in ("accel", "force") for span in spans]
    return bands + ["spatial_accel_rms_mm", "spatial_force_rms_n"]


@lru_cache(maxsize=16)
def _band_weights(n_fft: int, dx_mm: float, edges: tuple[float, ...], power: int) -> np.ndarray:
    """(n_fft//2 + 1, n_bands): 1/(2πk)^power for the bins of each band, 0 elsewhere (and at k = 0)."""
    k = scipy.fft.rfftfreq(n_fft, dx_mm)
    inv = np.zeros_like(k)
    inv[1:] = 1.0 / (2 * np.pi * k[1:]) ** power
    e = np.asarray(edges)
    members = (k[:, None] >= e[None, :-1]) & (k[:, None] < e[None, 1:])
    return members * inv[:, None]


def position_power(signal: np.ndarray, x_edges: np.ndarray, dx_mm: float, n_fft: int) -> np.ndarray | None:
    """One-sided power spectrum over spatial frequency (n_fft//2 + 1,) of a signal against position.

    signal: (L, c), constant over each sample; x_edges: (L + 1,) strictly increasing positions of the
    samples' edges, mm. Spectrum of the cell means on a dx_mm grid (detrended, Hann, zero-padded to
    n_fft), summed over the c columns, normalised to sum to the mean square. None if the samples
    cover fewer than MIN_CELLS cells.
    """
    cells = min(int(x_edges[-1] / dx_mm), n_fft)
    if cells < MIN_CELLS:
        return None
    integral = np.concatenate([np.zeros((1, signal.shape[1])), np.cumsum(signal * np.diff(x_edges)[:, None], axis=0)])
    grid = np.arange(cells + 1) * dx_mm
    at = np.stack([np.interp(grid, x_edges, integral[:, a]) for a in range(signal.shape[1])], axis=1)
    means = np.diff(at, axis=0) / dx_mm  # (cells, c)
    w = np.hanning(cells + 2)[1:-1]  # no zero end points: every covered cell counts
    t = np.linspace(-1.0, 1.0, cells)
    basis = np.stack([w, w * t], axis=1)  # Hann-weighted least-squares line through each column
    coef, *_ = np.linalg.lstsq(basis, w[:, None] * means, rcond=None)
    tapered = w[:, None] * means - basis @ coef
    spec = scipy.fft.rfft(tapered, n=n_fft, axis=0)
    return 2.0 * np.sum(spec.real**2 + spec.imag**2, axis=1) / (n_fft * np.sum(w * w))


def spatial_features(
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
        raise ValueError(f"spatial features need accel (n, L, 3), force (n, L) and speed (n, L), "
                         f"got {accel.shape}, {force.shape} and {speed.shape}")
    if not (rate_hz > 0 and dx_mm > 0 and min_speed > 0):
        raise ValueError(f"rate_hz, dx_mm and min_speed must be > 0, got {rate_hz}, {dx_mm}, {min_speed}")
    if 2 * dx_mm > min_period_mm:
        raise ValueError(f"dx_mm={dx_mm} cannot resolve periods of {min_period_mm} mm (needs dx ≤ period/2)")
    edges = tuple(band_edges_per_mm(min_period_mm, max_period_mm, n_bands))
    height_w = _band_weights(n_fft, dx_mm, edges, 4)
    force_w = _band_weights(n_fft, dx_mm, edges, 0)
    n = accel.shape[0]
    energy = np.empty((n, 2 * n_bands))  # mm² per accel band, N² per force band
    energy[:, :n_bands] = ENERGY_FLOOR_MM2
    energy[:, n_bands:] = FORCE_FLOOR_N2
    v = np.maximum(speed, 0.0)
    step = np.maximum(v, 1e-9) / rate_hz  # mm travelled during each sample (strictly > 0: x increases)
    x = np.concatenate([np.zeros((n, 1)), np.cumsum(step, axis=1)], axis=1)  # (n, L + 1) sample edges
    # position-weighted mean of v⁴ ((mm/s)⁴): the acceleration's power over a profile is |z''|²·v⁴
    v4 = np.maximum(np.sum(v**4 * step, axis=1) / np.maximum(x[:, -1], 1e-12), min_speed**4)
    for i in range(n):
        p_accel = position_power(1e3 * accel[i], x[i], dx_mm, n_fft)  # (mm/s²)² per bin
        if p_accel is None:
            continue
        energy[i, :n_bands] += p_accel @ height_w / v4[i]
        p_force = position_power(force[i][:, None], x[i], dx_mm, n_fft)
        energy[i, n_bands:] += p_force @ force_w
    totals = np.sqrt(np.stack([energy[:, :n_bands].sum(axis=1), energy[:, n_bands:].sum(axis=1)], axis=1))
    return np.concatenate([np.log10(energy), totals], axis=1)
