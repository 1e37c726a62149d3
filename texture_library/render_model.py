"""The served rendering model: a library entry's vibration model as versioned JSON (schema "hapticlink.render-model").

Every renderer — `texture_library.renderer`, the operator client, the browser console — reads this document.
Its fields are exactly a `VibrationModel`'s (speed mm/s, force N, LSFs in radians, variance (m/s²)²) with the
grid's triangles 0-based. `model_version` is the first 16 hex digits of the SHA-256 of the canonical JSON
(keys sorted, no spaces, floats as Python's shortest round-trip repr) of the content fields — every field but
`schema`, `schema_version`, `id` and `model_version` — so two documents with the same version render the same,
and a client caches a model by its version.
"""

from __future__ import annotations

import hashlib
import json
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from texture_library.surface import SurfaceProfile
from texture_library.taps import TapSet
from texture_library.vibration import RENDER_RATE_HZ, VibrationModel

SCHEMA: Literal["hapticlink.render-model"] = "hapticlink.render-model"
SCHEMA_VERSION: Literal[1] = 1
#: the largest canonical JSON a served model may have, bytes: the library refuses a bigger model when it is
#: loaded, and the service never serves one (HaTT's largest models are ≈ 30 kB without taps)
MAX_RENDER_MODEL_BYTES = 512 * 1024
#: fields outside the hashed content
_ENVELOPE = frozenset({"schema", "schema_version", "id", "model_version"})


class Taps(BaseModel):
    """Recorded tap transients: speeds (k,) mm/s; accel (k × n) m/s² at 1 kHz."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    speeds_mm_s: list[float] = Field(min_length=1)
    accel: list[list[float]] = Field(min_length=1)


class Surface(BaseModel):
    """Macro bump profile along the stroke (texture_library.surface.SurfaceProfile)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    bump_height_mm: float = Field(ge=0)
    bump_period_mm: float = Field(gt=0)


class RenderModel(BaseModel):
    """A library entry's vibration model: ARMA models (as LSFs) on a Delaunay grid over (speed, force).

    m grid points; p AR and q MA line spectral frequencies per point (q may be 0). Rendering semantics are
    `texture_library.synthesis.render`'s (docs/service.md, "Rendering models").
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, populate_by_name=True)

    schema_: Literal["hapticlink.render-model"] = Field(SCHEMA, alias="schema")
    schema_version: Literal[1] = SCHEMA_VERSION
    id: str = Field(min_length=1, max_length=128, description="library entry id")
    model_version: str = Field(
        pattern=r"^[0-9a-f]{16}$",
        description="first 16 hex of the SHA-256 of the canonical JSON of the content fields",
    )
    name: str
    rate_hz: float = Field(RENDER_RATE_HZ, gt=0, description="output sample rate, Hz")
    speeds_mm_s: list[float] = Field(min_length=3, description="(m,) grid speeds, mm/s")
    forces_n: list[float] = Field(min_length=3, description="(m,) grid normal forces, N")
    triangles: list[tuple[int, int, int]] = Field(min_length=1, description="Delaunay triangles, 0-based")
    ar_lsf: list[list[float]] = Field(description="(m × p) AR line spectral frequencies, rad, increasing in (0, π)")
    ma_lsf: list[list[float]] = Field(description="(m × q) MA line spectral frequencies, rad (q may be 0)")
    variance: list[float] = Field(description="(m,) excitation variance, (m/s²)²")
    gain: list[float] = Field(description="(m,) MA gain")
    mu: float = Field(ge=0, lt=5, description="kinetic friction coefficient")
    max_speed_mm_s: float = Field(gt=0)
    max_force_n: float = Field(gt=0)
    surface: Surface | None = None
    taps: Taps | None = None

    @model_validator(mode="after")
    def _consistent(self) -> RenderModel:
        # One set of rules: the VibrationModel's own checks (shapes, LSF order, finite values, ranges).
        self.to_vibration_model()
        want = content_version(self.content())
        if self.model_version != want:
            raise ValueError(f"model_version {self.model_version} does not match the content (its hash is {want})")
        return self

    # ---- conversions -----------------------------------------------------------------------------
    def content(self) -> dict:
        """The hashed fields as plain JSON values."""
        doc = self.model_dump(mode="json", by_alias=True)
        return {k: v for k, v in doc.items() if k not in _ENVELOPE}

    def to_json_bytes(self) -> bytes:
        """The document as compact UTF-8 JSON (what GET /library/{id}/model serves)."""
        return canonical_json(self.model_dump(mode="json", by_alias=True))

    @classmethod
    def from_vibration_model(cls, entry_id: str, model: VibrationModel) -> RenderModel:
        """The served document of `model` under library id `entry_id`; ValueError if it is over the size bound."""
        content = {
            "name": model.name,
            "rate_hz": float(model.rate_hz),
            "speeds_mm_s": _floats(model.speeds),
            "forces_n": _floats(model.forces),
            "triangles": np.asarray(model.triangles, dtype=np.int64).tolist(),
            "ar_lsf": _floats(model.ar_lsf),
            "ma_lsf": _floats(model.ma_lsf),
            "variance": _floats(model.variance),
            "gain": _floats(model.gain),
            "mu": float(model.mu),
            "max_speed_mm_s": float(model.max_speed),
            "max_force_n": float(model.max_force),
            "surface": None if model.surface is None else model.surface.to_dict(),
            "taps": None
            if model.taps is None
            else {"speeds_mm_s": _floats(model.taps.speeds), "accel": _floats(model.taps.accel)},
        }
        size = len(canonical_json(content))
        if size > MAX_RENDER_MODEL_BYTES:
            raise ValueError(
                f"rendering model {entry_id!r} is {size} bytes of JSON; at most {MAX_RENDER_MODEL_BYTES} are served"
            )
        envelope = {"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "id": entry_id}
        return cls.model_validate({**envelope, "model_version": content_version(content), **content})

    def to_vibration_model(self) -> VibrationModel:
        """The VibrationModel this document describes (ValueError naming the problem if it is inconsistent)."""
        m = len(self.speeds_mm_s)
        return VibrationModel(
            name=self.name,
            speeds=np.asarray(self.speeds_mm_s, float),
            forces=np.asarray(self.forces_n, float),
            triangles=np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3),
            ar_lsf=_matrix(self.ar_lsf, m, "ar_lsf"),
            ma_lsf=_matrix(self.ma_lsf, m, "ma_lsf"),
            variance=np.asarray(self.variance, float),
            gain=np.asarray(self.gain, float),
            mu=float(self.mu),
            max_speed=float(self.max_speed_mm_s),
            max_force=float(self.max_force_n),
            taps=None if self.taps is None else TapSet(np.asarray(self.taps.speeds_mm_s), _taps(self.taps.accel)),
            rate_hz=float(self.rate_hz),
            surface=None if self.surface is None else SurfaceProfile.from_dict(self.surface.model_dump()),
        )


def canonical_json(doc: dict) -> bytes:
    """Keys sorted, no whitespace, no NaN/Inf, UTF-8."""
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), allow_nan=False, ensure_ascii=False).encode()


def content_version(content: dict) -> str:
    """model_version of a document's content fields: first 16 hex of SHA-256 of their canonical JSON."""
    return hashlib.sha256(canonical_json(content)).hexdigest()[:16]


def library_digest(versions: dict[str, str]) -> str:
    """What names a whole library's rendering models at once: the first 16 hex of the SHA-256 of its
    "<id> <model_version>" lines, sorted. An operator that holds a library (shared in advance) says so with it."""
    lines = "".join(f"{i} {v}\n" for i, v in sorted(versions.items()))
    return hashlib.sha256(lines.encode()).hexdigest()[:16]


def parse_render_model(payload: bytes | str) -> RenderModel:
    """A served document → RenderModel; ValueError naming the problem (not JSON, too large, not the schema)."""
    size = len(payload)
    if size > MAX_RENDER_MODEL_BYTES * 2:  # the envelope and formatting may add a little; never megabytes
        raise ValueError(f"rendering model is {size} bytes; at most {MAX_RENDER_MODEL_BYTES * 2} are read")
    try:
        return RenderModel.model_validate_json(payload)
    except ValidationError as exc:
        parts = [f"{'.'.join(str(p) for p in e['loc']) or 'document'}: {e['msg']}" for e in exc.errors()[:5]]
        raise ValueError("not a valid hapticlink.render-model: " + "; ".join(parts)) from None


def _floats(arr: np.ndarray) -> list:
    return np.asarray(arr, dtype=float).tolist()


def _matrix(rows: list[list[float]], m: int, name: str) -> np.ndarray:
    """(m, order) from a list of rows; an empty order (q = 0) keeps its m rows."""
    if len(rows) != m:
        raise ValueError(f"{name} must have {m} rows (one per grid point), got {len(rows)}")
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        raise ValueError(f"{name} rows must all have the same length, got lengths {sorted(widths)}")
    return np.asarray(rows, float).reshape(m, widths.pop())


def _taps(accel: list[list[float]]) -> np.ndarray:
    widths = {len(r) for r in accel}
    if len(widths) != 1:
        raise ValueError(f"taps.accel rows must all have the same length, got lengths {sorted(widths)}")
    return np.asarray(accel, float)
