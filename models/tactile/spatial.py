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
from typing import NamedTuple

import numba
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
        raise ValueError(
            f"need 0 < min_period < max_period and n_bands ≥ 1, got {min_period_mm}, {max_period_mm}, {n_bands}"
        )
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


class _BandBins(NamedTuple):
    """The bands as runs of consecutive bins (bands are contiguous in k, so a band's energy is a sum over a
    slice, np.add.reduceat, rather than a (bins × bands) product, which BLAS spreads over threads even at this
    size): the first bin; per-bin weights 1/(2πk)^power from it to the last band's end; where each band's
    run starts (clipped into the run, as reduceat needs); the bands that hold no bin, which read 0."""

    first: int
    weights: np.ndarray
    starts: np.ndarray
    empty: np.ndarray

    @property
    def stop(self) -> int:
        """One past the last bin any band holds."""
        return self.first + self.weights.size


@lru_cache(maxsize=16)
def _band_bins(n_fft: int, dx_mm: float, edges: tuple[float, ...], power: int) -> _BandBins:
    """The bands of `edges` (mm⁻¹) over the bins of an n_fft-point spectrum at dx_mm, weighted 1/(2πk)^power;
    made once per configuration."""
    weights = _band_weights(n_fft, dx_mm, edges, power)
    k = scipy.fft.rfftfreq(n_fft, dx_mm)
    bounds = np.searchsorted(k, np.asarray(edges), side="left")  # band b holds bins bounds[b] … bounds[b+1] − 1
    first, stop = int(bounds[0]), int(bounds[-1])
    run = weights[first:stop].sum(axis=1)  # each bin is in at most one band
    starts = bounds[:-1] - first
    empty = np.diff(bounds) == 0
    starts = np.minimum(starts, max(run.size - 1, 0))
    for array in (run, starts, empty):
        array.setflags(write=False)
    return _BandBins(first, run, starts, empty)


@lru_cache(maxsize=16)
def _feature_bands(
    n_fft: int, dx_mm: float, min_period_mm: float, max_period_mm: float, n_bands: int
) -> tuple[_BandBins, _BandBins]:
    """spatial_features' two band sets, made once per configuration: height (weights 1/(2πk)⁴), force (1)."""
    edges = tuple(float(e) for e in band_edges_per_mm(min_period_mm, max_period_mm, n_bands))
    return _band_bins(n_fft, dx_mm, edges, 4), _band_bins(n_fft, dx_mm, edges, 0)


def _band_sums(power: np.ndarray, bins: _BandBins) -> np.ndarray:
    """(n, n_bins) power → (n, n_bands): Σ over each band's bins of power × weight (0 for a band with no bin)."""
    if bins.weights.size == 0:
        return np.zeros((power.shape[0], bins.starts.size))
    weighted = power[:, bins.first : bins.stop] * bins.weights
    sums = np.add.reduceat(weighted, bins.starts, axis=1)
    if bins.empty.any():
        sums[:, bins.empty] = 0.0
    return sums


@numba.njit(cache=True)
def _cell_means(signal: np.ndarray, x_edges: np.ndarray, dx_mm: float, n_grid: int, gap: float) -> np.ndarray:
    """Cell means on a dx_mm position grid: signal (c, n, L) float64, constant over each sample, whose
    samples' edges lie at x_edges (n, L + 1) mm (strictly increasing, from 0) → (n, n_grid, c) float32,
    the mean of each channel over grid cell k = [k·dx, (k + 1)·dx).

    Each mean is the difference of the signal's running integral, linearly interpolated at the cell's
    edges, over dx. The arithmetic is that of one np.interp over all windows laid end to end `gap` mm
    apart (window i at i·gap, searched together), operation for operation, so the float64 means round
    to the same float32 values; cells past a window's end read the segment to the next window's start
    (the last window: its own last segment, extended) — values the taper zeroes. Compiled: one walk per
    window replaces a cumulative sum, a sorted search and six array passes over the grid."""
    c, n, length = signal.shape
    out = np.empty((n, n_grid, c), np.float32)
    integral = np.zeros(c)  # running integral of each channel up to edges[s]
    before = np.zeros(c)  # … up to edges[s − 1]
    at_last = np.zeros(c)
    for i in range(n):
        offset = i * gap
        edges = x_edges[i]
        s = 0  # the sample holding the current grid edge: edges[s] + offset ≤ grid < edges[s + 1] + offset
        integral[:] = 0.0
        before[:] = 0.0
        for k in range(n_grid + 1):
            grid = k * dx_mm + offset
            while s < length and edges[s + 1] + offset <= grid:
                step = edges[s + 1] - edges[s]
                for ch in range(c):
                    before[ch] = integral[ch]
                    integral[ch] = integral[ch] + signal[ch, i, s] * step
                s += 1
            if s < length:
                x0, x1 = edges[s] + offset, edges[s + 1] + offset
            elif i < n - 1:  # past the end: towards the next window's first edge, where its integral is 0
                x0, x1 = edges[length] + offset, (i + 1) * gap
            else:  # past the end of the last window: its last segment, extended
                x0, x1 = edges[length - 1] + offset, edges[length] + offset
            for ch in range(c):
                if s < length:
                    y0, y1 = integral[ch], integral[ch] + signal[ch, i, s] * (edges[s + 1] - edges[s])
                elif i < n - 1:
                    y0, y1 = integral[ch], 0.0
                else:
                    y0, y1 = before[ch], integral[ch]
                at = (y1 - y0) / (x1 - x0) * (grid - x0) + y0
                if k > 0:
                    out[i, k - 1, ch] = np.float32((at - at_last[ch]) / dx_mm)
                at_last[ch] = at
    return out


def position_power(signal: np.ndarray, x_edges: np.ndarray, dx_mm: float, n_fft: int) -> np.ndarray:
    """One-sided power spectra over spatial frequency of signals against position, n windows at once.

    signal: (n, L, c), constant over each sample; x_edges: (n, L + 1) strictly increasing positions of
    the samples' edges, mm, starting at 0. Per window: the cell means on a dx_mm grid over the
    distance it covers (at most n_fft cells), a Hann-weighted least-squares line removed, Hann,
    zero-padded to n_fft → power (n, n_fft//2 + 1, c), normalised to sum to the mean square;
    all zeros for a window covering fewer than MIN_CELLS cells.
    """
    channels = np.ascontiguousarray(np.asarray(signal, dtype=np.float64).transpose(2, 0, 1))
    x_edges = np.asarray(x_edges, dtype=np.float64)
    if x_edges.ndim != 2 or np.any(x_edges[:, 0] != 0):
        raise ValueError(f"x_edges must be (n, L + 1) positions starting at 0 mm, got shape {x_edges.shape}")
    power, norm = _raw_power(channels, x_edges, dx_mm, n_fft)
    return (power.astype(np.float64) * norm[:, None]).transpose(1, 2, 0)


def _raw_power(
    signal: np.ndarray, x_edges: np.ndarray, dx_mm: float, n_fft: int, n_bins: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """position_power before its normalisation, channel-first: signal (c, n, L) float64 and x_edges (n, L + 1) mm →
    |spectrum|² (c, n, n_bins) float32 over the first n_bins bins (default all n_fft//2 + 1; the band sums
    need only those up to the shortest period's), and each window's normalisation (n,) float64 (0 for a
    window covering fewer than MIN_CELLS cells). Channel-first, so the taper and the FFT run along contiguous
    rows; the normalisation is left to the caller, which applies it to a handful of band sums instead of
    every bin."""
    c, n, length = signal.shape
    if x_edges.shape != (n, length + 1):
        raise ValueError(
            f"x_edges must be (n, L + 1) = {(n, length + 1)} for signal {signal.shape}, got {x_edges.shape}"
        )
    cells = np.minimum((x_edges[:, -1] / dx_mm).astype(np.int64), n_fft)  # (n,)
    n_grid = int(max(cells.max(initial=0), MIN_CELLS))  # the grid the longest window needs; zero-padded to n_fft
    # the windows sit end to end, `gap` mm apart, as they did for one np.interp over all of them: the offsets
    # set the rounding of every position, and with it the float32 means
    gap = float(x_edges[:, -1].max(initial=0.0)) + (n_grid + 2) * dx_mm
    # float32 from here: the spectra feed log-energies, and it halves the cost of the heavy part. The means'
    # memory stays window-major with the channel innermost: the einsum sums below add in an order set by that
    # layout, and this is the layout the straightforward formulation had (a parity test pins it)
    means = _cell_means(np.ascontiguousarray(signal), np.ascontiguousarray(x_edges), dx_mm, n_grid, gap).transpose(
        2, 0, 1
    )  # (c, n, n_grid)
    taper = _one_taper(int(cells[0]), n_grid, n_fft) if n == 1 else _tapers(cells, n_grid, n_fft)
    # the least-squares line a + b·t through each row (weights w²), removed before the taper
    y0s = np.einsum("nj,cnj->cn", taper.w2, means)
    y1s = np.einsum("nj,cnj->cn", taper.w2t, means)
    a = (taper.s2 * y0s - taper.s1 * y1s) / taper.det
    b = (taper.s0 * y1s - taper.s1 * y0s) / taper.det
    # the taper is written straight into the zero-padded FFT input (rfft's own padding would copy it again)
    padded = np.zeros((c, n, n_fft), np.float32)
    tapered = padded[:, :, :n_grid]
    np.subtract(means, a[:, :, None], out=tapered)
    tapered -= b[:, :, None] * taper.t
    tapered *= taper.w
    spec = scipy.fft.rfft(padded, axis=2)
    n_bins = spec.shape[2] if n_bins is None else n_bins
    # |X|² as float32 squares of the interleaved (re, im) pairs: the same roundings as re² + im², in two passes
    squares = spec.view(np.float32)[:, :, : 2 * n_bins] ** 2
    power = squares[:, :, 0::2] + squares[:, :, 1::2]
    return power, taper.norm


class _Taper(NamedTuple):
    """Per-window constants of the taper and the least-squares line, float32 except norm: w (n, n_grid), the
    Hann window over each window's cells (0 beyond); t (n, n_grid), the cells' positions in [−1, 1] (0
    beyond); w2 = w², w2t = w²·t; s0, s1, s2 (n,), Σw², Σw²t, Σw²t²; det (n,), s0·s2 − s1² (1 where not
    > 0); norm (n,) float64, what scales |X|² to a one-sided spectrum summing to the mean square (0 for a
    window under MIN_CELLS cells)."""

    w: np.ndarray
    t: np.ndarray
    w2: np.ndarray
    w2t: np.ndarray
    s0: np.ndarray
    s1: np.ndarray
    s2: np.ndarray
    det: np.ndarray
    norm: np.ndarray


def _tapers(cells: np.ndarray, n_grid: int, n_fft: int) -> _Taper:
    """The _Taper of windows covering `cells` (n,) grid cells each, on a grid of n_grid cells zero-padded to
    n_fft. Each row depends on its own cells and on n_grid only (the sums add in blocks set by the row's
    length), so one window's row is the same alone or in a batch."""
    k = np.arange(n_grid, dtype=np.float32)[None, :]
    m = np.maximum(cells, 2)[:, None].astype(np.float32)
    inside = k < cells[:, None]
    w = np.where(
        inside, np.sin(np.float32(np.pi) * (k + 1) / (m + 1)) ** 2, np.float32(0)
    )  # Hann without its zero ends
    t = np.where(inside, 2 * k / (m - 1) - 1, np.float32(0))
    w2 = w * w
    w2t = w2 * t
    s0, s1, s2 = w2.sum(axis=1), w2t.sum(axis=1), (w2t * t).sum(axis=1)
    det = np.where(s0 * s2 - s1 * s1 > 0, s0 * s2 - s1 * s1, 1.0)
    norm = np.where(cells >= MIN_CELLS, 2.0 / (n_fft * np.maximum(w2.sum(axis=1, dtype=np.float64), 1e-300)), 0.0)
    return _Taper(w, t, w2, w2t, s0, s1, s2, det, norm)


@lru_cache(maxsize=256)
def _one_taper(cells: int, n_grid: int, n_fft: int) -> _Taper:
    """_tapers of a single window, kept: with one window per call (the serving case) n_grid is max(cells,
    MIN_CELLS), so the window's cell count alone is the key — at most n_fft + 1 of them, ≤ 16 kB each — and
    strokes at similar speeds repeat it."""
    taper = _tapers(np.array([cells]), n_grid, n_fft)
    for array in taper:
        array.setflags(write=False)
    return taper


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
        raise ValueError(
            f"spatial features need accel (n, L, 3), force (n, L) and speed (n, L), "
            f"got {accel.shape}, {force.shape} and {speed.shape}"
        )
    if not (rate_hz > 0 and dx_mm > 0 and min_speed > 0):
        raise ValueError(f"rate_hz, dx_mm and min_speed must be > 0, got {rate_hz}, {dx_mm}, {min_speed}")
    if 2 * dx_mm > min_period_mm:
        raise ValueError(f"dx_mm={dx_mm} cannot resolve periods of {min_period_mm} mm (needs dx ≤ period/2)")
    height_bins, force_bins = _feature_bands(n_fft, dx_mm, min_period_mm, max_period_mm, n_bands)
    n, length = speed.shape
    if n == 0:
        return np.empty((0, 2 * n_bands + 2))
    v = np.maximum(speed, 0.0)
    step = np.maximum(v, 1e-9) / rate_hz  # mm travelled during each sample (strictly > 0: x increases)
    x = np.zeros((n, length + 1))
    np.cumsum(step, axis=1, out=x[:, 1:])  # (n, L + 1) sample edges
    # position-weighted mean of v⁴ ((mm/s)⁴): the acceleration's power over a profile is |z''|²·v⁴
    v2 = v * v
    v4 = np.maximum(np.einsum("nl,nl,nl->n", v2, v2, step) / np.maximum(x[:, -1], 1e-12), min_speed**4)
    signal = np.empty((4, n, length))  # channels first: accel x, y, z in mm/s², then normal force, N
    np.multiply(accel.transpose(2, 0, 1), 1e3, out=signal[:3])
    signal[3] = force
    n_bins = max(height_bins.stop, force_bins.stop)
    power, norm = _raw_power(signal, x, dx_mm, n_fft, n_bins)  # (4, n, bins up to the last band's), (n,)
    height = power[0].astype(np.float64)  # the three axes' power summed (orientation-free), in float64
    height += power[1]
    height += power[2]
    energy = np.empty((n, 2, n_bands))  # mm² per accel band, N² per force band
    np.multiply(_band_sums(height, height_bins), (norm / v4)[:, None], out=energy[:, 0])
    np.multiply(_band_sums(power[3].astype(np.float64), force_bins), norm[:, None], out=energy[:, 1])
    energy[:, 0] += ENERGY_FLOOR_MM2
    energy[:, 1] += FORCE_FLOOR_N2
    out = np.empty((n, 2 * n_bands + 2))
    np.log10(energy.reshape(n, 2 * n_bands), out=out[:, : 2 * n_bands])
    np.sqrt(energy.sum(axis=2), out=out[:, 2 * n_bands :])
    return out
