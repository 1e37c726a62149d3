"""Classic texture descriptors of one frame: what a photo shows of how a surface feels.

Each is a pure function (arrays in, a fixed-length float64 vector out, ValueError with a precise message on
bad input). `models.visual.embedding.visual_features` appends the ones a `VisualConfig` names, in the order
of DESCRIPTORS, after the backbone and GLCM columns — training and serving compute them the same way.

    lbp        rotation-invariant uniform local binary pattern histograms at several radii
    spectrum   the radially averaged Fourier power spectrum: its log-log slope and octave band energies
    colour     colour statistics (RGB, opponent channels, saturation)
    grids      multi-scale patch grids: how much the mean and the contrast vary between cells, per grid
    scattering wavelet scattering (kymatio), averaged over space and over absolute orientation

Images: gray (H, W) float in [0, 1]; colour (H, W, 3) float in [0, 1].
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import ndimage

DESCRIPTORS = ("lbp", "spectrum", "colour", "grids", "scattering")
EPS = 1e-12


def _check_gray(gray: np.ndarray, min_size: int, name: str = "gray") -> np.ndarray:
    if not isinstance(gray, np.ndarray) or gray.ndim != 2:
        raise ValueError(f"{name} must be a 2-D (H, W) array, got {getattr(gray, 'shape', type(gray).__name__)}")
    if min(gray.shape) < min_size:
        raise ValueError(f"{name} is {gray.shape[1]}×{gray.shape[0]} px; this descriptor needs ≥ {min_size} px a side")
    out = np.asarray(gray, dtype=np.float64)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name} has non-finite values")
    return out


# ---- local binary patterns ----------------------------------------------------------------------
def lbp_codes(gray: np.ndarray, radius: int, points: int = 8) -> np.ndarray:
    """Rotation-invariant uniform LBP code (Ojala et al. 2002, LBP^riu2) of every interior pixel.

    gray     (H, W) float, H, W > 2·radius
    returns  (H − 2r, W − 2r) int codes in 0 … points + 1: for a uniform pattern (≤ 2 transitions
             around the circle) the number of neighbours ≥ the centre; points + 1 for every other pattern.
             Neighbours on the circle of `radius` px are read with bilinear interpolation.
    """
    if radius < 1 or points < 3:
        raise ValueError(f"radius must be ≥ 1 px and points ≥ 3, got radius {radius}, points {points}")
    img = _check_gray(gray, 2 * radius + 1)
    h, w = img.shape
    centre = img[radius : h - radius, radius : w - radius]
    bits = []
    for p in range(points):
        angle = 2.0 * np.pi * p / points
        dy, dx = -radius * np.sin(angle), radius * np.cos(angle)
        y0, x0 = int(np.floor(dy)), int(np.floor(dx))
        fy, fx = dy - y0, dx - x0
        # round away sub-1e-9 fractions so axis-aligned neighbours read exact pixels
        fy, fx = (
            (0.0 if abs(fy) < 1e-9 else 1.0 if abs(fy - 1) < 1e-9 else fy),
            (0.0 if abs(fx) < 1e-9 else 1.0 if abs(fx - 1) < 1e-9 else fx),
        )

        def at(oy: int, ox: int) -> np.ndarray:
            return img[radius + oy : h - radius + oy, radius + ox : w - radius + ox]

        value = (
            (1 - fy) * (1 - fx) * at(y0, x0)
            + (1 - fy) * fx * at(y0, min(x0 + 1, radius))
            + fy * (1 - fx) * at(min(y0 + 1, radius), x0)
            + fy * fx * at(min(y0 + 1, radius), min(x0 + 1, radius))
        )
        bits.append(value >= centre - 1e-12)
    b = np.stack(bits).astype(np.int64)
    transitions = np.abs(np.diff(np.concatenate([b, b[:1]]), axis=0)).sum(axis=0)
    return np.where(transitions <= 2, b.sum(axis=0), points + 1)


def lbp_histograms(gray: np.ndarray, radii: tuple[int, ...] = (1, 2, 4), points: int = 8) -> np.ndarray:
    """Normalised LBP^riu2 histograms, one per radius: (len(radii) · (points + 2),), each histogram sums to 1."""
    if not radii:
        raise ValueError("radii must not be empty")
    out = []
    for r in radii:
        codes = lbp_codes(gray, r, points)
        out.append(np.bincount(codes.ravel(), minlength=points + 2) / codes.size)
    return np.concatenate(out).astype(np.float64)


# ---- radially averaged power spectrum -----------------------------------------------------------
def radial_power_spectrum(gray: np.ndarray, n_bands: int = 6) -> np.ndarray:
    """Slope and octave band energies of the radially averaged power spectrum.

    gray     (H, W) float; the mean is removed and a 2-D Hann window applied before the FFT
    returns  (n_bands + 2,): [slope of log10 power vs log10 frequency over the bands' range,
             log10 total power (per pixel, grey levels²), then the fraction of power in each octave band
             (band k: frequencies in [0.5 / 2^(k+1), 0.5 / 2^k) cycles/px, finest first)]
    """
    if n_bands < 1:
        raise ValueError(f"n_bands must be ≥ 1, got {n_bands}")
    img = _check_gray(gray, 2 ** (n_bands + 1))
    h, w = img.shape
    window = np.outer(np.hanning(h), np.hanning(w))
    power = np.abs(np.fft.fft2((img - img.mean()) * window)) ** 2 / (window**2).sum()
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.fftfreq(w)[None, :]
    radius = np.sqrt(fy**2 + fx**2)
    edges = 0.5 / 2.0 ** np.arange(n_bands + 1)  # 0.5, 0.25, …: finest band first
    band_power = np.array([power[(radius < edges[k]) & (radius >= edges[k + 1])].sum() for k in range(n_bands)])
    total = band_power.sum()
    # slope: least squares of log mean power per band against log band centre
    counts = np.array([((radius < edges[k]) & (radius >= edges[k + 1])).sum() for k in range(n_bands)])
    mean_power = band_power / np.maximum(counts, 1)
    centres = np.sqrt(edges[:-1] * edges[1:])
    slope = np.polyfit(np.log10(centres), np.log10(mean_power + EPS), 1)[0] if n_bands > 1 else 0.0
    fractions = band_power / total if total > 0 else np.zeros(n_bands)
    return np.concatenate([[slope, np.log10(total / img.size + EPS)], fractions]).astype(np.float64)


# ---- colour -------------------------------------------------------------------------------------
COLOUR_DIM = 13


def colour_statistics(rgb: np.ndarray) -> np.ndarray:
    """Colour statistics of a photo.

    rgb      (H, W, 3) float in [0, 1]
    returns  (13,): mean and std of R, G, B; mean and std of the opponent channels
             rg = R − G and yb = (R + G)/2 − B; mean and std of the HSV saturation (max − min) / max
             (0 where max = 0); the mean chroma √(rg² + yb²)
    """
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be an (H, W, 3) array, got {getattr(rgb, 'shape', type(rgb).__name__)}")
    x = np.asarray(rgb, dtype=np.float64)
    if not np.all(np.isfinite(x)) or x.min() < 0 or x.max() > 1:
        raise ValueError("rgb must be finite and lie in [0, 1]")
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    rg, yb = r - g, (r + g) / 2 - b
    hi, lo = x.max(axis=2), x.min(axis=2)
    sat = np.where(hi > 0, (hi - lo) / np.where(hi > 0, hi, 1.0), 0.0)
    return np.array(
        [
            *x.reshape(-1, 3).mean(axis=0),
            *x.reshape(-1, 3).std(axis=0),
            rg.mean(),
            rg.std(),
            yb.mean(),
            yb.std(),
            sat.mean(),
            sat.std(),
            np.sqrt(rg**2 + yb**2).mean(),
        ]
    )


# ---- multi-scale patch grids --------------------------------------------------------------------
def grid_statistics(gray: np.ndarray, scales: tuple[int, ...] = (2, 4, 8, 16)) -> np.ndarray:
    """How a surface's brightness and contrast vary across patch grids of several sizes.

    gray     (H, W) float; for each s in scales the image is cut into s × s equal cells (the remainder
             rows and columns dropped)
    returns  (3 · len(scales),): per scale the std of the cell means (macro structure coarser than a cell),
             the mean of the cell stds (texture finer than a cell) and the std of the cell stds (how
             uneven that fine texture is)
    """
    if not scales or min(scales) < 1:
        raise ValueError(f"scales must be non-empty positive ints, got {scales}")
    img = _check_gray(gray, max(scales))
    out = []
    for s in scales:
        ch, cw = img.shape[0] // s, img.shape[1] // s
        cells = img[: ch * s, : cw * s].reshape(s, ch, s, cw).transpose(0, 2, 1, 3).reshape(s * s, ch * cw)
        means, stds = cells.mean(axis=1), cells.std(axis=1)
        out += [means.std(), stds.mean(), stds.std()]
    return np.array(out, dtype=np.float64)


# ---- wavelet scattering -------------------------------------------------------------------------
_SCATTERING: dict[tuple[int, int, int], Any] = {}  # one kymatio filter bank per (size, J, L): its setup is slow


def scattering_dim(J: int, L: int) -> int:
    """Length of `scattering_features`: 1 + J + L · J(J − 1)/2."""
    return 1 + J + L * J * (J - 1) // 2


def scattering_features(gray: np.ndarray, J: int = 3, L: int = 8) -> np.ndarray:
    """Rotation-invariant wavelet scattering coefficients (kymatio's Scattering2D, numpy frontend).

    gray     (N, N) float, N ≥ 2^J · 4, square (scale the frame first: the filter bank is built per size)
    returns  (1 + J + L · J(J − 1)/2,): log(ε + spatial mean) of the order-0 coefficient; of the order-1
             coefficients per scale j (averaged over the L orientations); of the order-2 coefficients per
             (j1 < j2, relative orientation (θ2 − θ1) mod L) (averaged over θ1). ε = 1e-6.
    """
    img = _check_gray(gray, 2**J * 4)
    if img.shape[0] != img.shape[1]:
        raise ValueError(f"scattering needs a square image, got {img.shape[1]}×{img.shape[0]}")
    if J < 1 or L < 1:
        raise ValueError(f"J and L must be ≥ 1, got J {J}, L {L}")
    key = (img.shape[0], J, L)
    if key not in _SCATTERING:
        # the 2-D frontend itself: kymatio.numpy also imports the 3-D one, which needs scipy.special.sph_harm
        # (removed in SciPy 1.15)
        from kymatio.scattering2d.frontend.numpy_frontend import ScatteringNumPy2D

        _SCATTERING[key] = ScatteringNumPy2D(J=J, shape=img.shape, L=L, max_order=2, out_type="list")
    coeffs = _SCATTERING[key](img.astype(np.float32))
    order0 = []
    order1 = np.zeros((J, L))
    order2 = np.zeros((J, J, L))
    counts2 = np.zeros((J, J, L))
    for c in coeffs:
        value = float(np.mean(c["coef"]))
        j, theta = tuple(c["j"]), tuple(c["theta"])
        if len(j) == 0:
            order0.append(value)
        elif len(j) == 1:
            order1[j[0], theta[0]] = value
        else:
            dt = (theta[1] - theta[0]) % L
            order2[j[0], j[1], dt] += value
            counts2[j[0], j[1], dt] += 1
    pairs = [(a, b) for a in range(J) for b in range(a + 1, J)]
    o2 = [order2[a, b, d] / max(counts2[a, b, d], 1) for a, b in pairs for d in range(L)]
    values = np.array([order0[0], *order1.mean(axis=1), *o2], dtype=np.float64)
    return np.log(1e-6 + np.maximum(values, 0.0))


# ---- an image zoomed for a descriptor -----------------------------------------------------------
def centre_square(img: np.ndarray) -> np.ndarray:
    """The largest centred square of an (H, W[, C]) image."""
    h, w = img.shape[:2]
    s = min(h, w)
    top, left = (h - s) // 2, (w - s) // 2
    return img[top : top + s, left : left + s]


def zoom_to(img: np.ndarray, size: int) -> np.ndarray:
    """(H, W) float → (size, size): its centre square scaled (area-averaged when shrinking by a whole factor,
    else spline order 1), values kept in the input's range."""
    sq = centre_square(np.asarray(img, dtype=np.float64))
    n = sq.shape[0]
    if n == size:
        return sq
    if n % size == 0:
        k = n // size
        return sq.reshape(size, k, size, k).mean(axis=(1, 3))
    return np.clip(ndimage.zoom(sq, size / n, order=1, grid_mode=True, mode="reflect"), sq.min(), sq.max())[
        :size, :size
    ]


def descriptor_vector(gray: np.ndarray, colour: np.ndarray | None, config) -> np.ndarray:
    """The descriptors `config` (a models.visual.config.VisualConfig) names, concatenated in DESCRIPTORS order.

    gray     (H, W) float in [0, 1], the frame as the backbone sees it (any view already applied)
    colour   (h, w, 3) float in [0, 1], the same view in colour; needed only for the colour statistics
    returns  (config.descriptor_dim,) float32
    """
    parts = []
    need_gray = [d for d in config.descriptors if d in ("lbp", "spectrum", "grids")]
    small = zoom_to(gray, min(config.descriptor_size, min(gray.shape))) if need_gray else gray
    for name in config.descriptors:
        if name == "lbp":
            parts.append(lbp_histograms(small, tuple(config.lbp_radii)))
        elif name == "spectrum":
            parts.append(radial_power_spectrum(small, config.spectrum_bands))
        elif name == "grids":
            parts.append(grid_statistics(small, tuple(config.grid_scales)))
        elif name == "scattering":
            size = min(config.scattering_size, min(gray.shape))
            parts.append(scattering_features(zoom_to(gray, size), config.scattering_j, config.scattering_l))
        elif name == "colour":
            if colour is None:
                raise ValueError("the colour descriptor needs the frame in colour (H, W, 3); got grayscale only")
            parts.append(colour_statistics(colour))
    out = np.concatenate(parts).astype(np.float32) if parts else np.zeros(0, np.float32)
    if out.shape != (config.descriptor_dim,):
        raise ValueError(f"descriptors gave {out.shape[0]} values, the configuration says {config.descriptor_dim}")
    return out
