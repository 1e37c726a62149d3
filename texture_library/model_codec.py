"""A compact binary encoding of a rendering model: LSFs quantised the way speech codecs quantise them.

A served model (`texture_library.render_model.RenderModel`, JSON) spends ≈ 20 characters on each float.
This encoding keeps what rendering needs and quantises it:

- LSFs: each row's frequencies as integer codes on a uniform grid of 2^bits steps over (0, π), strictly
  increasing (a collision is pushed one step up, so every decoded row is a valid, minimum-phase LSF set),
  then stored as first differences (small numbers, alike from one grid point to the next);
- grid speeds and forces, √variance and gain as float16 (0.05 % relative error: ≈ 0.004 dB of level);
- μ and the grid's range as float32; triangles as uint8 (uint16 beyond 255 grid points);
- the whole body deflated (zlib).

Taps are left out (the vibration renderer does not read them; the JSON document carries them); the surface
profile stays. The payload names the JSON document's `model_version` it was made from, so a client caches
what it decodes under the version window events name. Decoding gives a RenderModel whose own
`model_version` is that of the quantised content. What quantisation adds to the spectra is measured by
`python -m benchmarks.bandwidth` (log-spectral distance, texture_library.spectrum).

Layout (little-endian): b"HLM1", then a deflated body: u8 bits, u16 m, u16 p, u16 q, u16 t, u8 flags
(1: surface present), u8 len + id, u8 len + name (UTF-8, cut to 255 bytes), 8 bytes source version,
f64 rate_hz, f32 mu, f32 max_speed, f32 max_force, [f64 bump height, f64 bump period],
f16 speeds (m), f16 forces (m), f16 √variance (m), f16 gain (m), triangles (t × 3, u8 or u16),
AR codes (m × p, u16 first differences), MA codes (m × q, same).
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from texture_library.render_model import MAX_RENDER_MODEL_BYTES, RenderModel, content_version

MAGIC = b"HLM1"
CONTENT_TYPE = "application/x-hapticlink-model"
#: default LSF resolution: 2^11 steps over (0, π) (≈ 0.24 Hz at 1 kHz): ≤ 0.31 dB added on each HaTT model at the
#: nine operating points of texture_library.spectrum (not measured elsewhere on its grid), where 10 bits added up
#: to 0.97 dB (4 of 100 over 0.5 dB)
LSF_BITS = 11


def quantise_lsf(lsf: np.ndarray, bits: int) -> np.ndarray:
    """(m, p) LSFs in (0, π) → (m, p) int codes in [1, 2^bits − 1], strictly increasing along each row."""
    if not 4 <= bits <= 16:
        raise ValueError(f"bits must lie in [4, 16], got {bits}")
    levels = 1 << bits
    lsf = np.asarray(lsf, float)
    codes = np.clip(np.rint(lsf / np.pi * levels), 1, levels - 1).astype(np.int64)
    for j in range(1, codes.shape[1]):  # keep the order: a collision moves one step up
        codes[:, j] = np.maximum(codes[:, j], codes[:, j - 1] + 1)
    if codes.size and codes.max() > levels - 1:
        raise ValueError(f"{lsf.shape[1]} LSFs per row do not fit {bits}-bit codes with distinct values")
    return codes


def dequantise_lsf(codes: np.ndarray, bits: int) -> np.ndarray:
    return np.asarray(codes, float) * np.pi / (1 << bits)


def encode(model: RenderModel, bits: int = LSF_BITS) -> bytes:
    """The compact payload of `model` (see the module's layout)."""
    m, p, q = len(model.speeds_mm_s), len(model.ar_lsf[0]), len(model.ma_lsf[0])
    ar = quantise_lsf(np.asarray(model.ar_lsf, float).reshape(m, p), bits)
    ma = quantise_lsf(np.asarray(model.ma_lsf, float).reshape(m, q), bits)
    tri = np.asarray(model.triangles, np.int64)
    ident, name = model.id.encode()[:255], model.name.encode()[:255]
    parts = [
        struct.pack("<BHHHHB", bits, m, p, q, tri.shape[0], 1 if model.surface else 0),
        bytes([len(ident)]) + ident,
        bytes([len(name)]) + name,
        bytes.fromhex(model.model_version),
        struct.pack("<dfff", model.rate_hz, model.mu, model.max_speed_mm_s, model.max_force_n),
    ]
    if model.surface is not None:
        parts.append(struct.pack("<dd", model.surface.bump_height_mm, model.surface.bump_period_mm))
    for values in (model.speeds_mm_s, model.forces_n, np.sqrt(model.variance), model.gain):
        parts.append(np.asarray(values, "<f2").tobytes())
    parts.append(tri.astype("<u1" if m <= 255 else "<u2").tobytes())
    for codes in (ar, ma):
        parts.append(np.diff(codes, axis=1, prepend=0).astype("<u2").tobytes())
    return MAGIC + zlib.compress(b"".join(parts), 9)


def decode(payload: bytes) -> tuple[str, RenderModel]:
    """A compact payload → (the source JSON document's model_version, the decoded RenderModel).

    ValueError naming the problem for anything that is not a well-formed payload or model."""
    if payload[:4] != MAGIC:
        raise ValueError(f"not a compact rendering model (starts {payload[:4]!r}, expected {MAGIC!r})")
    try:
        body = zlib.decompressobj().decompress(payload[4:], MAX_RENDER_MODEL_BYTES)
    except zlib.error as exc:
        raise ValueError(f"compact rendering model: the body does not inflate ({exc})") from None
    try:
        return _parse(body)
    except (struct.error, IndexError, UnicodeDecodeError) as exc:
        raise ValueError(f"compact rendering model: truncated or malformed ({exc})") from None


def _parse(body: bytes) -> tuple[str, RenderModel]:
    pos = 0

    def take(n: int) -> bytes:
        nonlocal pos
        if pos + n > len(body):
            raise ValueError(f"compact rendering model: truncated at byte {pos} (needs {n} more)")
        pos += n
        return body[pos - n : pos]

    bits, m, p, q, t, flags = struct.unpack("<BHHHHB", take(10))
    ident = take(take(1)[0]).decode()
    name = take(take(1)[0]).decode()
    source = take(8).hex()
    rate, mu, max_speed, max_force = struct.unpack("<dfff", take(20))
    surface = None
    if flags & 1:
        h, period = struct.unpack("<dd", take(16))
        surface = {"bump_height_mm": float(h), "bump_period_mm": float(period)}
    speeds, forces, std, gain = (np.frombuffer(take(2 * m), "<f2").astype(float) for _ in range(4))
    width = 1 if m <= 255 else 2
    tri = np.frombuffer(take(3 * t * width), "<u1" if width == 1 else "<u2").astype(np.int64).reshape(t, 3)
    ar = np.cumsum(np.frombuffer(take(2 * m * p), "<u2").astype(np.int64).reshape(m, p), axis=1)
    ma = np.cumsum(np.frombuffer(take(2 * m * q), "<u2").astype(np.int64).reshape(m, q), axis=1)
    if pos != len(body):
        raise ValueError(f"compact rendering model: {len(body) - pos} unexpected bytes at the end")
    content = {
        "name": name,
        "rate_hz": float(rate),
        "speeds_mm_s": speeds.tolist(),
        "forces_n": forces.tolist(),
        "triangles": tri.tolist(),
        "ar_lsf": dequantise_lsf(ar, bits).tolist(),
        "ma_lsf": dequantise_lsf(ma, bits).tolist(),
        "variance": (std * std).tolist(),
        "gain": gain.tolist(),
        "mu": float(mu),
        "max_speed_mm_s": float(max_speed),
        "max_force_n": float(max_force),
        "surface": surface,
        "taps": None,
    }
    doc = {"schema": "hapticlink.render-model", "schema_version": 1, "id": ident}
    return source, RenderModel.model_validate({**doc, "model_version": content_version(content), **content})
