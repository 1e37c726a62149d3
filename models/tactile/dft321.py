"""DFT321: fold three acceleration axes into one signal with the same spectral energy.

Landin, Romano & Kuchenbecker (2010), "Dimensional reduction of high-frequency
accelerations for haptic rendering". Per frequency bin k of the axes' DFTs A_k^(x,y,z):

    |Â_k| = sqrt(|A_k^x|² + |A_k^y|² + |A_k^z|²)      (energy per bin preserved)
    ∠Â_k  = ∠(A_k^x + A_k^y + A_k^z)                   (phase of the sum)

and the output is the inverse real DFT of Â. A signal on one axis comes back unchanged;
the total energy (Parseval) equals the summed energy of the three axes.
"""

from __future__ import annotations

import numpy as np
import scipy.fft

#: (6, 2): sums the interleaved (re, im) parts of the three axes' spectra
_SUM_AXES = np.array([[1.0, 0.0], [0.0, 1.0]] * 3)


def dft321(x: np.ndarray) -> np.ndarray:
    """Fold axes. x: (..., n, 3) real (e.g. m/s²) → (..., n) real, same units, n ≥ 2."""
    x = np.asarray(x)
    if x.dtype.kind not in "iuf":
        raise ValueError(f"x must be real numbers, got dtype {x.dtype}")
    if x.ndim < 2 or x.shape[-1] != 3:
        raise ValueError(f"x must have shape (..., n, 3), got {x.shape}")
    n = x.shape[-2]
    if n < 2:
        raise ValueError(f"x needs at least 2 samples along axis -2, got {n}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"x has {int(np.count_nonzero(~np.isfinite(x)))} NaN or Inf value(s)")
    spec = np.ascontiguousarray(scipy.fft.rfft(np.asarray(x, dtype=np.float64), axis=-2))  # (..., n//2+1, 3)
    # work on the interleaved float view (re_x, im_x, re_y, im_y, re_z, im_z): reductions over
    # a 3-long complex axis are slow in numpy, small matmuls are not
    parts = spec.view(np.float64)
    magnitude = np.sqrt(np.einsum("...i,...i->...", parts, parts))
    total = parts @ _SUM_AXES  # (..., n//2+1, 2): re, im of A^x + A^y + A^z
    total_mag = np.sqrt(np.einsum("...i,...i->...", total, total))
    scale = np.divide(magnitude, total_mag, out=np.zeros_like(magnitude), where=total_mag > 0)
    folded = total * scale[..., None]
    vanishing = total_mag == 0
    if vanishing.any():  # the sum cancels: angle(0) = 0, as np.angle
        folded[vanishing, 0] = magnitude[vanishing]
    return scipy.fft.irfft(folded.view(np.complex128)[..., 0], n=n, axis=-1)
