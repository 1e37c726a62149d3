"""Macro surface profile: the bumps a stroking tool rides over, felt as position-periodic acceleration.

A texture's vibration model (ARMA noise) renders its micro-texture; bumps of millimetres to
centimetres are a *deterministic* function of where the tool is, not of time. Along the stroke
line the surface height is

    z(x) = bump_height_mm · (1 + cos(2π x / bump_period_mm)) / 2          (mm)

and a tool tip that follows it accelerates along the surface normal by

    z̈ = z''(x) · v² + z'(x) · v̇                                         (mm/s², × 1e-3 → m/s²)

with v the signed velocity along the line (mm/s) and v̇ its derivative. So a bump train of
period P stroked at speed v rings at v / P Hz: the same bumps are a low hum on a slow stroke
and a buzz on a fast one, and only against position (acceleration resampled onto a uniform
position grid, models.tactile.spatial) do they sit at one place, 1/P mm⁻¹, at every speed.

The tip (radius ≈ 0.5 mm) follows the profile as long as its curvature stays below 1/radius:
(h/2)(2π/P)² ≤ 2 mm⁻¹, which holds for the synthetic world's ranges (h ≤ 1.5 mm, P ≥ 5 mm).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

MM_TO_M = 1e-3


@dataclass(frozen=True)
class SurfaceProfile:
    """bump_height_mm: peak-to-valley height (≥ 0); bump_period_mm: spatial period (> 0)."""

    bump_height_mm: float
    bump_period_mm: float

    def __post_init__(self) -> None:
        h, p = self.bump_height_mm, self.bump_period_mm
        if not (isinstance(h, (int, float)) and math.isfinite(h) and h >= 0):
            raise ValueError(f"surface profile: bump_height_mm must be a finite number ≥ 0, got {h!r}")
        if not (isinstance(p, (int, float)) and math.isfinite(p) and p > 0):
            raise ValueError(f"surface profile: bump_period_mm must be a finite number > 0, got {p!r}")

    def to_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: object) -> SurfaceProfile:
        if not isinstance(d, dict) or set(d) != {"bump_height_mm", "bump_period_mm"}:
            raise ValueError(f"surface profile must be {{'bump_height_mm': …, 'bump_period_mm': …}}, got {d!r}")
        return cls(float(d["bump_height_mm"]), float(d["bump_period_mm"]))

    def height(self, x: np.ndarray) -> np.ndarray:
        """z(x) (n,) mm at positions x (n,) mm."""
        k = 2 * np.pi / self.bump_period_mm
        return 0.5 * self.bump_height_mm * (1.0 + np.cos(k * np.asarray(x, float)))

    def normal_accel(self, position: np.ndarray, velocity: np.ndarray, rate_hz: float) -> np.ndarray:
        """Tip acceleration along the surface normal (n,) m/s².

        position: (n,) mm along the line; velocity: (n,) signed mm/s (d position / dt); rate_hz: their rate.
        """
        x = np.asarray(position, float)
        v = np.asarray(velocity, float)
        if x.ndim != 1 or x.shape != v.shape:
            raise ValueError(f"position and velocity must be 1-D of equal length, got {x.shape} and {v.shape}")
        if x.size < 2:
            return np.zeros(x.size)
        return self.accel_at(x, v, np.gradient(v) * rate_hz)

    def accel_at(self, position: np.ndarray, velocity: np.ndarray, dvelocity: np.ndarray) -> np.ndarray:
        """z''(x)·v² + z'(x)·v̇ (n,) m/s² from position (n,) mm, velocity (n,) mm/s and its derivative (n,) mm/s².

        The one formula of the bump train: `normal_accel` (the robot's stroke, derivatives by central differences)
        and the operator's renderer (texture_library.renderer, backward differences carried across blocks) both
        evaluate it."""
        x, v, dv = (np.asarray(a, float) for a in (position, velocity, dvelocity))
        k = 2 * np.pi / self.bump_period_mm
        half = 0.5 * self.bump_height_mm
        dz = -half * k * np.sin(k * x)  # z'(x), mm/mm
        d2z = -half * k * k * np.cos(k * x)  # z''(x), 1/mm
        return (d2z * v * v + dz * dv) * MM_TO_M
