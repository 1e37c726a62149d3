"""Data-driven vibration models: ARMA filters over a (speed, normal force) grid.

A model holds one ARMA model per grid point, stored as line spectral
frequencies, plus the Delaunay triangles that tile the grid. Rendering at a
(speed, force) clamps to the grid's range, finds the enclosing triangle,
interpolates LSFs, excitation variance and gain barycentrically, turns the
LSFs back into coefficients and filters white noise — one output sample per
millisecond (Culbertson et al., IEEE Haptics Symposium 2014; IEEE ToH 2014).

Units: speed mm/s, force N, acceleration m/s², rate 1000 Hz.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from texture_library.npzfile import load_npz, save_npz
from texture_library.surface import SurfaceProfile
from texture_library.taps import TapSet

RENDER_RATE_HZ = 1000.0
FILE_FORMAT = "hapticlink-vibration-model"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class VibrationModel:
    """ARMA vibration models on a Delaunay grid over (speed, force).

    speeds, forces: (m,) grid points, mm/s and N.
    triangles: (t, 3) int, 0-based indices into the grid points.
    ar_lsf: (m, p) radians; ma_lsf: (m, q) radians (q may be 0: pure AR).
    variance: (m,) excitation variance, (m/s²)²; gain: (m,) MA gain.
    mu: kinetic friction coefficient; max_speed / max_force: the grid's range.
    taps: recorded tap transients (a hardness cue), if any.
    surface: the macro bump profile the tool rides over (texture_library.surface), if any: rendered
    by texture_library.stroke on top of the ARMA vibration. HaTT models have none (their bumps live
    in the ARMA spectra they were fitted to); the synthetic world's textures have one.
    """

    name: str
    speeds: np.ndarray
    forces: np.ndarray
    triangles: np.ndarray
    ar_lsf: np.ndarray
    ma_lsf: np.ndarray
    variance: np.ndarray
    gain: np.ndarray
    mu: float
    max_speed: float
    max_force: float
    taps: TapSet | None = None
    rate_hz: float = RENDER_RATE_HZ
    provenance: str = ""
    extra: dict = field(default_factory=dict)
    surface: SurfaceProfile | None = None

    def __post_init__(self) -> None:
        m = np.asarray(self.speeds).shape[0] if np.ndim(self.speeds) == 1 else -1
        problems = []
        if m < 3:
            problems.append(f"speeds must be 1-D with at least 3 grid points, got shape {np.shape(self.speeds)}")
        else:
            for name in ("forces", "variance", "gain"):
                if np.shape(getattr(self, name)) != (m,):
                    problems.append(f"{name} must have shape ({m},), got {np.shape(getattr(self, name))}")
            for name in ("ar_lsf", "ma_lsf"):
                arr = np.asarray(getattr(self, name))
                if arr.ndim != 2 or arr.shape[0] != m:
                    problems.append(f"{name} must have shape ({m}, order), got {arr.shape}")
            tri = np.asarray(self.triangles)
            if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] < 1:
                problems.append(f"triangles must have shape (t, 3), got {tri.shape}")
            elif tri.dtype.kind not in "iu":
                problems.append(f"triangles must be integer indices, got dtype {tri.dtype}")
            elif tri.min() < 0 or tri.max() >= m:
                problems.append(f"triangle indices must lie in [0, {m - 1}] (0-based), got [{tri.min()}, {tri.max()}]")
        for name in ("speeds", "forces", "ar_lsf", "ma_lsf", "variance", "gain"):
            if not np.all(np.isfinite(np.asarray(getattr(self, name), dtype=float))):
                problems.append(f"{name} contains NaN or Inf")
        if not problems:
            if np.any(np.asarray(self.variance) < 0):
                problems.append("variance must be ≥ 0")
            for name in ("ar_lsf", "ma_lsf"):
                arr = np.asarray(getattr(self, name))
                if arr.size and (arr.min() <= 0 or arr.max() >= np.pi or np.any(np.diff(arr, axis=1) <= 0)):
                    problems.append(f"{name} must increase strictly inside (0, π) in every row")
            if not (self.max_speed > 0 and self.max_force > 0):
                problems.append(f"max_speed and max_force must be > 0, got {self.max_speed}, {self.max_force}")
            if not (0 <= self.mu < 5):
                problems.append(f"mu must lie in [0, 5), got {self.mu}")
            if not self.rate_hz > 0:
                problems.append(f"rate_hz must be > 0, got {self.rate_hz}")
            if self.surface is not None and not isinstance(self.surface, SurfaceProfile):
                problems.append(f"surface must be a SurfaceProfile or None, got {type(self.surface).__name__}")
        if problems:
            raise ValueError(f"vibration model {self.name!r}: " + "; ".join(problems))

    @property
    def ar_order(self) -> int:
        return int(np.asarray(self.ar_lsf).shape[1])

    @property
    def ma_order(self) -> int:
        return int(np.asarray(self.ma_lsf).shape[1])

    # ---- storage: one .npz of arrays with a JSON header ------------------------------------
    def save(self, path: str | Path) -> Path:
        path = Path(path)
        header = {
            "name": self.name,
            "mu": float(self.mu),
            "max_speed": float(self.max_speed),
            "max_force": float(self.max_force),
            "rate_hz": float(self.rate_hz),
            "provenance": self.provenance,
            "units": {"speed": "mm/s", "force": "N", "accel": "m/s^2", "lsf": "rad"},
            "extra": self.extra,
        }
        if self.surface is not None:
            header["surface"] = self.surface.to_dict()
        arrays = {
            "speeds": np.asarray(self.speeds, float),
            "forces": np.asarray(self.forces, float),
            "triangles": np.asarray(self.triangles, np.int32),
            "ar_lsf": np.asarray(self.ar_lsf, float),
            "ma_lsf": np.asarray(self.ma_lsf, float),
            "variance": np.asarray(self.variance, float),
            "gain": np.asarray(self.gain, float),
        }
        if self.taps is not None:
            arrays["tap_speeds"] = self.taps.speeds
            arrays["tap_accel"] = self.taps.accel
        return save_npz(path, FILE_FORMAT, FORMAT_VERSION, header, arrays)

    @classmethod
    def load(cls, path: str | Path) -> VibrationModel:
        path = Path(path)
        header, arrays = load_npz(path, FILE_FORMAT, FORMAT_VERSION)
        missing = [k for k in ("name", "mu", "max_speed", "max_force", "rate_hz") if k not in header]
        missing += [
            k for k in ("speeds", "forces", "triangles", "ar_lsf", "ma_lsf", "variance", "gain") if k not in arrays
        ]
        if missing:
            raise ValueError(f"{path}: missing {missing}")
        try:
            taps = TapSet(arrays["tap_speeds"], arrays["tap_accel"]) if "tap_speeds" in arrays else None
            surface = SurfaceProfile.from_dict(header["surface"]) if "surface" in header else None
            return cls(
                name=header["name"],
                speeds=arrays["speeds"],
                forces=arrays["forces"],
                triangles=arrays["triangles"].astype(np.int64),
                ar_lsf=arrays["ar_lsf"],
                ma_lsf=arrays["ma_lsf"],
                variance=arrays["variance"],
                gain=arrays["gain"],
                mu=header["mu"],
                max_speed=header["max_speed"],
                max_force=header["max_force"],
                taps=taps,
                rate_hz=header["rate_hz"],
                provenance=header.get("provenance", ""),
                extra=header.get("extra", {}),
                surface=surface,
            )
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{path}: {exc}") from None
