"""A compact binary encoding of a rendering model: LSFs quantised the way speech codecs quantise them.

A served model (`texture_library.render_model.RenderModel`, JSON) spends ≈ 20 characters on each float.
This encoding keeps what rendering needs and quantises it:

- LSFs: each row as the gaps between adjacent frequencies (the first from 0), each gap coded on a logarithmic
  scale — step ρ = 2^(3 − bits) relative to the gap (1/256 at 11 bits), from GAP_FLOOR_RAD up — and taken from
  the previous frequency *as decoded* (closed loop), so errors never add up along a row. A close pair of LSFs
  is a root near the unit circle, a sharp resonance or a deep notch whose depth follows the pair's gap: a
  uniform step (the old coding, 2^11 steps over (0, π)) rounded gaps narrower than one step to one step, and
  moved HaTT's notches by up to 1.48 dB at the models' own grid points (textured_metal); coded relative to
  the gap, the depth keeps ≈ ρ/2 of its width. Every decoded row is strictly increasing inside (0, π): a valid,
  minimum-phase LSF set;
- grid speeds and forces as float32: a grid point moved by float16's rounding (1.2328 N → 1.2324 on
  plastic_mesh_2) moves the interpolation near it — 0.75 dB at that model's own point;
- √variance and gain as float16 (0.05 % relative error: ≈ 0.004 dB of level);
- μ and the grid's range as float32; triangles as uint8 (uint16 beyond 255 grid points);
- the whole body deflated (zlib).

Taps (recorded transients, played at a touchdown) travel as f32 speeds and f16 samples (0.05 % relative error);
the surface profile stays. The payload names the JSON document's `model_version` it was made from, so a client caches
what it decodes under the version window events name. Decoding gives a RenderModel whose own
`model_version` is that of the quantised content. What quantisation adds to the spectra is measured by
`python -m benchmarks.bandwidth` (log-spectral distance, texture_library.spectrum).

Layout (little-endian): b"HLM3", then a deflated body (zlib): a 15-byte head — u8 bits, u16 m, u16 p, u16 q,
u16 t, u8 flags (1: surface present, 2: taps present), u8 id length, u8 name length (UTF-8, each cut to 255 bytes),
u8 k taps, u16 n samples per tap — then the sections, each of a length the head gives: id, name, 8 bytes source
version, f64 rate_hz + f32 mu + f32 max_speed + f32 max_force, [f64 bump height, f64 bump period], f32 speeds (m),
f32 forces (m), f16 √variance (m), f16 gain (m), triangles (t × 3, u8, or u16 beyond 255 grid points), f32 tap
speeds (k), f16 tap samples (k × n), AR codes (m × p, u16 gap codes), MA codes (m × q, same). Every array of
multi-byte numbers is stored in byte planes (all first bytes, then all second bytes, …): a refit's small changes
leave the high planes unchanged. b"HLM1" (uniform LSF codes) and b"HLM2" (the layout before: sections not
addressable from a head, taps left out) are refused by name.

A delta (`encode_delta`), for a receiver that holds an earlier payload (a learnt model's previous version, or the
library entry it was learnt from): b"HLD3", the first 8 bytes of the SHA-256 of that base's body (inflated), then,
deflated (zlib), the new body minus the base's section by section, byte by byte (mod 256): the head against the
base's head, each section against the base's same section (read as zeros past its end). So a new ARMA order
shifts nothing else, and what did not change — the grid, the taps a learnt model keeps from its library prior, the
high byte planes — differences to zeros that deflate to almost nothing. Both steps are what a browser has at hand
(DecompressionStream("deflate") and a byte loop; service/static/model-codec.js decodes the same format), unlike a
preset deflate dictionary, which the browser's stream cannot take.
"""

from __future__ import annotations

import hashlib
import struct
import zlib

import numpy as np

from texture_library.render_model import MAX_RENDER_MODEL_BYTES, RenderModel, content_version

MAGIC = b"HLM3"
#: a model sent as a delta against an earlier payload (`encode_delta`)
DELTA_MAGIC = b"HLD3"
#: bytes of a delta before its deflated difference: magic + the base payload's digest
DELTA_HEAD = 4 + 8
#: earlier layouts, refused by name: uniform LSF codes; sections not addressable from a head
OLD_MAGICS = {b"HLM1": "uniform LSF codes", b"HLM2": "no section head, no taps"}
#: bytes of a body's head (see the module's layout)
HEAD = struct.Struct("<BHHHHBBBBH")
CONTENT_TYPE = "application/x-hapticlink-model"
#: default LSF resolution: gaps coded to a relative step of 2^(3 − 11) = 1/256
LSF_BITS = 11
#: the narrowest gap between adjacent LSFs the coding holds, rad (code 0); a narrower one decodes to this
GAP_FLOOR_RAD = 1e-6


def _gap_step(bits: int) -> float:
    """ln(1 + ρ), ρ = 2^(3 − bits): the width of one gap code on the log scale."""
    if not 4 <= bits <= 15:
        raise ValueError(f"bits must lie in [4, 15], got {bits}")
    return float(np.log1p(2.0 ** (3 - bits)))


def quantise_lsf(lsf: np.ndarray, bits: int) -> np.ndarray:
    """(m, p) LSFs in (0, π) → (m, p) int gap codes in [0, 65535] (see the module: log scale, closed loop)."""
    step = _gap_step(bits)
    lsf = np.asarray(lsf, float)
    m, p = lsf.shape
    codes = np.zeros((m, p), np.int64)
    decoded = np.zeros(m)  # the previous frequency as the decoder will have it
    for j in range(p):
        gap = np.maximum(lsf[:, j] - decoded, GAP_FLOOR_RAD)
        code = np.clip(np.rint(np.log(gap / GAP_FLOOR_RAD) / step), 0, 65535).astype(np.int64)
        # the row must stay inside (0, π) with room for the gaps still to come
        room = np.pi - (p - 1 - j) * GAP_FLOOR_RAD
        while True:
            over = decoded + GAP_FLOOR_RAD * np.exp(code * step) >= room
            if not over.any():
                break
            if np.any(code[over] == 0):
                raise ValueError(f"{p} LSFs per row do not fit inside (0, π) at gaps of at least {GAP_FLOOR_RAD} rad")
            code[over] -= 1
        codes[:, j] = code
        decoded = decoded + GAP_FLOOR_RAD * np.exp(code * step)
    return codes


def dequantise_lsf(codes: np.ndarray, bits: int) -> np.ndarray:
    """(m, p) gap codes → (m, p) LSFs, rad: the running sum of the decoded gaps (as `quantise_lsf` decodes them)."""
    step = _gap_step(bits)
    codes = np.asarray(codes, np.int64)
    out = np.zeros(codes.shape)
    decoded = np.zeros(codes.shape[0])
    for j in range(codes.shape[1]):  # the encoder's own order of additions: the same doubles
        decoded = decoded + GAP_FLOOR_RAD * np.exp(codes[:, j] * step)
        out[:, j] = decoded
    return out


def encode(model: RenderModel, bits: int = LSF_BITS) -> bytes:
    """The compact payload of `model` (see the module's layout)."""
    return MAGIC + zlib.compress(_body(model, bits), 9)


def encode_delta(model: RenderModel, base: bytes, bits: int = LSF_BITS) -> bytes:
    """`model` as a delta against `base`, the body (`body`) of a payload the receiver holds (see the module's
    layout): what did not change costs a few bytes."""
    return delta_between(_body(model, bits), base)


def delta_between(new: bytes, base: bytes) -> bytes:
    """A delta that turns the body `base` into the body `new` (both well-formed bodies)."""
    return DELTA_MAGIC + body_digest(base) + zlib.compress(_difference(new, base), 9)


def body(payload: bytes) -> bytes:
    """The inflated body of a compact payload: what a receiver keeps as the base of the next delta. ValueError
    naming the problem."""
    return _inflate(payload)


def body_digest(base: bytes) -> bytes:
    """The 8 bytes a delta names its base by: the first 8 of the SHA-256 of the base's body."""
    return hashlib.sha256(base).digest()[:8]


def delta_base(payload: bytes) -> bytes:
    """The base digest a delta names (ValueError if `payload` is not a delta)."""
    if payload[:4] != DELTA_MAGIC or len(payload) < DELTA_HEAD:
        raise ValueError(f"not a compact rendering model delta (starts {payload[:4]!r}, expected {DELTA_MAGIC!r})")
    return payload[4:DELTA_HEAD]


def decode_delta(payload: bytes, base: bytes) -> tuple[str, RenderModel, bytes]:
    """A delta payload and the body of the base it was made against → (source version, the decoded RenderModel,
    its body: the base of the next delta). ValueError naming the problem, also when the base is not the one the
    delta was made against."""
    if delta_base(payload) != body_digest(base):
        raise ValueError(
            f"the delta was made against base {payload[4:DELTA_HEAD].hex()}, "
            f"not the one held ({body_digest(base).hex()})"
        )
    try:
        diff = zlib.decompressobj().decompress(payload[DELTA_HEAD:], MAX_RENDER_MODEL_BYTES)
    except zlib.error as exc:
        raise ValueError(f"compact rendering model delta: the body does not inflate ({exc})") from None
    try:
        new = _difference(diff, base, add=True)
    except (struct.error, ValueError) as exc:
        raise ValueError(f"compact rendering model delta: malformed ({exc})") from None
    source, doc = _parse_checked(new)
    return source, doc, new


def _sections(head: bytes) -> list[int]:
    """The lengths of a body's sections after its head (see the module's layout), from the head alone."""
    bits, m, p, q, t, flags, id_len, name_len, k, n = HEAD.unpack(head[: HEAD.size])
    width = 1 if m <= 255 else 2
    return [id_len, name_len, 8, 20, 16 if flags & 1 else 0, 4 * m, 4 * m, 2 * m, 2 * m, 3 * t * width, 4 * k,
            2 * k * n, 2 * m * p, 2 * m * q]  # fmt: skip


def _difference(data: bytes, base: bytes, add: bool = False) -> bytes:
    """Section by section (the head first), data − base (or data + base with `add`: data is then a difference and
    the new body's head is read from the sum), byte by byte mod 256; a base section read as zeros past its end."""
    if len(base) < HEAD.size or len(data) < HEAD.size:
        raise ValueError(f"a body is at least {HEAD.size} bytes")

    def combine(a: bytes, b: bytes) -> bytes:
        x = np.frombuffer(a, np.uint8)
        y = np.zeros(x.size, np.uint8)
        y[: min(x.size, len(b))] = np.frombuffer(b, np.uint8, min(x.size, len(b)))
        return (x + y if add else x - y).tobytes()

    head = combine(data[: HEAD.size], base[: HEAD.size])
    new_head = head if add else data[: HEAD.size]
    out = [head]
    at, base_at = HEAD.size, HEAD.size
    for size, base_size in zip(_sections(new_head), _sections(base), strict=True):
        if at + size > len(data):
            raise ValueError(f"the difference ends at byte {len(data)}, its sections need {at + size}")
        out.append(combine(data[at : at + size], base[base_at : base_at + base_size]))
        at, base_at = at + size, base_at + base_size
    if at != len(data):
        raise ValueError(f"{len(data) - at} bytes after the last section")
    return b"".join(out)


def _planes(values: np.ndarray | list[float], dtype: str) -> bytes:
    """An array as byte planes of its little-endian elements (see the module's layout)."""
    a = np.ascontiguousarray(values, dtype=dtype)
    return a.view(np.uint8).reshape(-1, a.itemsize).T.tobytes()


def _unplanes(raw: bytes, dtype: str, count: int) -> np.ndarray:
    width = np.dtype(dtype).itemsize
    return np.frombuffer(raw, np.uint8).reshape(width, count).T.copy().view(dtype).ravel()


def _body(model: RenderModel, bits: int) -> bytes:
    m, p, q = len(model.speeds_mm_s), len(model.ar_lsf[0]), len(model.ma_lsf[0])
    ar = quantise_lsf(np.asarray(model.ar_lsf, float).reshape(m, p), bits)
    ma = quantise_lsf(np.asarray(model.ma_lsf, float).reshape(m, q), bits)
    tri = np.asarray(model.triangles, np.int64)
    ident, name = model.id.encode()[:255], model.name.encode()[:255]
    tap_speeds = np.zeros(0)
    tap_accel = np.zeros((0, 0))
    if model.taps is not None:
        tap_speeds, tap_accel = np.asarray(model.taps.speeds_mm_s, float), np.asarray(model.taps.accel, float)
        if tap_accel.shape[0] > 255 or tap_accel.shape[1] > 65535:
            raise ValueError(f"compact rendering model: at most 255 taps of 65535 samples, got {tap_accel.shape}")
    flags = (1 if model.surface else 0) | (2 if model.taps else 0)
    k, n = tap_accel.shape
    parts = [
        HEAD.pack(bits, m, p, q, tri.shape[0], flags, len(ident), len(name), k, n),
        ident,
        name,
        bytes.fromhex(model.model_version),
        struct.pack("<dfff", model.rate_hz, model.mu, model.max_speed_mm_s, model.max_force_n),
    ]
    if model.surface is not None:
        parts.append(struct.pack("<dd", model.surface.bump_height_mm, model.surface.bump_period_mm))
    parts += [_planes(v, "<f4") for v in (model.speeds_mm_s, model.forces_n)]
    parts += [_planes(v, "<f2") for v in (np.sqrt(model.variance), model.gain)]
    parts.append(_planes(tri.ravel(), "<u1" if m <= 255 else "<u2"))
    parts += [_planes(tap_speeds, "<f4"), _planes(tap_accel.ravel(), "<f2")]
    parts += [_planes(codes.ravel(), "<u2") for codes in (ar, ma)]
    return b"".join(parts)


def decode(payload: bytes) -> tuple[str, RenderModel]:
    """A compact payload → (the source JSON document's model_version, the decoded RenderModel).

    ValueError naming the problem for anything that is not a well-formed payload or model."""
    return _parse_checked(_inflate(payload))


def _inflate(payload: bytes) -> bytes:
    """The body of a compact payload; ValueError naming the problem."""
    if payload[:4] in OLD_MAGICS:
        raise ValueError(
            f"compact rendering model of the old layout {payload[:4]!r} ({OLD_MAGICS[payload[:4]]}); this client "
            f"reads {MAGIC!r}"
        )
    if payload[:4] != MAGIC:
        raise ValueError(f"not a compact rendering model (starts {payload[:4]!r}, expected {MAGIC!r})")
    try:
        return zlib.decompressobj().decompress(payload[4:], MAX_RENDER_MODEL_BYTES)
    except zlib.error as exc:
        raise ValueError(f"compact rendering model: the body does not inflate ({exc})") from None


def _parse_checked(body: bytes) -> tuple[str, RenderModel]:
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

    bits, m, p, q, t, flags, id_len, name_len, k, n = HEAD.unpack(take(HEAD.size))
    if not 4 <= bits <= 15:
        raise ValueError(f"compact rendering model: LSF bits {bits} outside [4, 15]")
    ident = take(id_len).decode()
    name = take(name_len).decode()
    source = take(8).hex()
    rate, mu, max_speed, max_force = struct.unpack("<dfff", take(20))
    surface = None
    if flags & 1:
        h, period = struct.unpack("<dd", take(16))
        surface = {"bump_height_mm": float(h), "bump_period_mm": float(period)}
    speeds, forces = (_unplanes(take(4 * m), "<f4", m).astype(float) for _ in range(2))
    std, gain = (_unplanes(take(2 * m), "<f2", m).astype(float) for _ in range(2))
    width = "<u1" if m <= 255 else "<u2"
    tri = _unplanes(take(3 * t * int(width[-1])), width, 3 * t).astype(np.int64).reshape(t, 3)
    tap_speeds = _unplanes(take(4 * k), "<f4", k).astype(float)
    tap_accel = _unplanes(take(2 * k * n), "<f2", k * n).astype(float).reshape(k, n)
    ar = _unplanes(take(2 * m * p), "<u2", m * p).astype(np.int64).reshape(m, p)
    ma = _unplanes(take(2 * m * q), "<u2", m * q).astype(np.int64).reshape(m, q)
    if pos != len(body):
        raise ValueError(f"compact rendering model: {len(body) - pos} unexpected bytes at the end")
    taps = {"speeds_mm_s": tap_speeds.tolist(), "accel": tap_accel.tolist()} if flags & 2 else None
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
        "taps": taps,
    }
    doc = {"schema": "hapticlink.render-model", "schema_version": 1, "id": ident}
    return source, RenderModel.model_validate({**doc, "model_version": content_version(content), **content})
