"""Line spectral frequencies (LSF) ⇄ polynomial coefficients, batched.

For a monic polynomial A(z) = 1 + a₁z⁻¹ + … + a_p z⁻ᵖ the symmetric and
antisymmetric sum/difference polynomials
    P(z) = A(z) + z^-(p+1) A(1/z),   Q(z) = A(z) − z^-(p+1) A(1/z)
have all roots on the unit circle; their angles, interlaced in (0, π), are the
LSFs. A is minimum phase exactly when they interlace strictly, which is why
the HaTT renderer interpolates LSFs (a convex combination of sorted sequences
stays sorted) rather than coefficients.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def _expand(cos_terms: np.ndarray) -> np.ndarray:
    """∏ (1 − 2cos ωᵢ z⁻¹ + z⁻²) for each row: (n, k) → (n, 2k+1).

    Compiled: the real-time renderer converts LSFs per sample. Each factor updates the coefficients in place
    from the highest down, new[j] = (old[j] + c·old[j−1]) + old[j−2], in the order numpy's slices would."""
    n, k = cos_terms.shape
    poly = np.zeros((n, 2 * k + 1))
    for r in range(n):
        poly[r, 0] = 1.0
        for i in range(k):
            length = 2 * i + 1
            c = -2.0 * cos_terms[r, i]
            for j in range(length + 1, 0, -1):
                v = poly[r, j]
                if j <= length:
                    v = v + c * poly[r, j - 1]
                if j >= 2:
                    v = v + poly[r, j - 2]
                poly[r, j] = v
    return poly


def lsf_to_poly(lsf: np.ndarray) -> np.ndarray:
    """Monic polynomial coefficients from LSFs.

    lsf: (..., p) float, radians, strictly increasing in (0, π).
    Returns (..., p + 1) with a leading 1.
    """
    w = np.asarray(lsf, dtype=float)
    if w.ndim == 0:
        raise ValueError("lsf must have at least one axis (..., p)")
    batch = w.shape[:-1]
    p = w.shape[-1]
    if p == 0:
        return np.ones(batch + (1,))
    if not np.all(np.isfinite(w)):
        raise ValueError("lsf contains NaN or Inf")
    if w.min() <= 0.0 or w.max() >= np.pi:
        raise ValueError(f"lsf must lie strictly inside (0, π), got [{w.min():.4g}, {w.max():.4g}]")
    if p > 1 and np.any(np.diff(w, axis=-1) <= 0.0):
        # Unsorted input would silently pair the wrong roots with P and Q.
        raise ValueError("lsf must increase strictly along the last axis")
    return poly_from_checked_lsf(w)


def poly_from_checked_lsf(lsf: np.ndarray) -> np.ndarray:
    """`lsf_to_poly` without its checks, for LSFs already known to be valid: a barycentric blend of a
    VibrationModel's rows (each validated when the model was made; a convex combination of increasing rows in
    (0, π) is one too). The real-time renderer's per-block path. lsf: (..., p) float → (..., p + 1)."""
    w = np.asarray(lsf, dtype=float)
    batch, p = w.shape[:-1], w.shape[-1]
    if p == 0:
        return np.ones(batch + (1,))
    return _poly_from_cos(np.cos(w.reshape(-1, p))).reshape(batch + (p + 1,))


@numba.njit(cache=True)
def _poly_from_cos(flat: np.ndarray) -> np.ndarray:
    """(n, p) cos ωᵢ of sorted LSFs → (n, p + 1) monic coefficients: A = (P + Q) / 2.

    The roots of P are ω₁, ω₃, …; of Q ω₂, ω₄, …. Even p: P also has the root z = −1 (P·(1 + z⁻¹)) and Q the root
    z = +1 (Q·(1 − z⁻¹)); odd p: Q has both (Q·(1 − z⁻²)). Sums run in the order of the earlier numpy slices,
    so the coefficients are the same to the bit."""
    n, p = flat.shape
    p_poly = _expand(flat[:, 0::2])
    q_poly = _expand(flat[:, 1::2])
    a = np.empty((n, p + 1))
    for r in range(n):
        for j in range(p + 1):
            if p % 2 == 0:
                pf = 0.0 + p_poly[r, j]
                if j >= 1:
                    pf = pf + p_poly[r, j - 1]
                qf = 0.0 + q_poly[r, j]
                if j >= 1:
                    qf = qf - q_poly[r, j - 1]
            else:
                pf = p_poly[r, j]
                qf = 0.0
                if j <= p - 1:
                    qf = qf + q_poly[r, j]
                if j >= 2:
                    qf = qf - q_poly[r, j - 2]
            a[r, j] = 0.5 * (pf + qf)
    return a


def poly_to_lsf(a: np.ndarray) -> np.ndarray:
    """LSFs of one monic minimum-phase polynomial a: (p + 1,) → (p,) radians, sorted."""
    a = np.asarray(a, dtype=float)
    if a.ndim != 1 or a.size < 1:
        raise ValueError(f"a must be 1-D (p + 1,), got shape {a.shape}")
    if not np.isclose(a[0], 1.0):
        raise ValueError(f"a must be monic (a[0] == 1), got a[0] = {a[0]:g}")
    p = a.size - 1
    if p == 0:
        return np.zeros(0)
    if np.any(np.abs(np.roots(a)) >= 1.0):
        raise ValueError("a is not minimum phase (a root lies on or outside the unit circle)")
    ext = np.concatenate([a, [0.0]])
    rev = ext[::-1]
    angles = []
    for poly in (ext + rev, ext - rev):
        ang = np.angle(np.roots(poly))
        angles.append(ang[(ang > 1e-9) & (ang < np.pi - 1e-9)])
    lsf = np.sort(np.concatenate(angles))
    if lsf.size != p or np.any(np.diff(lsf) <= 0):
        raise ValueError(
            f"LSFs of a could not be resolved numerically (found {lsf.size} of {p}); a is too close to instability"
        )
    return lsf


def poles_to_poly(freqs_hz: np.ndarray, radii: np.ndarray, rate_hz: float) -> np.ndarray:
    """Monic real polynomial with conjugate pole pairs at the given frequencies and radii.

    freqs_hz: (k,) in (0, rate/2); radii: (k,) in [0, 1). Returns (2k + 1,).
    """
    freqs = np.asarray(freqs_hz, dtype=float)
    radii = np.asarray(radii, dtype=float)
    if freqs.shape != radii.shape or freqs.ndim != 1:
        raise ValueError(f"freqs_hz and radii must be 1-D of equal length, got {freqs.shape} and {radii.shape}")
    if np.any((freqs <= 0) | (freqs >= rate_hz / 2)):
        raise ValueError(f"pole frequencies must lie in (0, {rate_hz / 2:g}) Hz")
    if np.any((radii < 0) | (radii >= 1)):
        raise ValueError("pole radii must lie in [0, 1)")
    poly = np.array([1.0])
    for f, r in zip(freqs, radii):
        w = 2 * np.pi * f / rate_hz
        poly = np.convolve(poly, [1.0, -2 * r * np.cos(w), r * r])
    return poly
