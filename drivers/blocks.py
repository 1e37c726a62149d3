"""What sensors send: timestamped sample blocks and camera frames, and their wire formats.

A block carries one span of time for every channel it holds; each channel has
its own sample rate, so the spans agree in seconds, not in sample counts.

Wire formats (robot → service), both carrying the same fields:
- JSON: {"seq": int, "t0": float s, ["kind": "samples",] "channels": {"accel": {"rate_hz": f, "units": "m/s^2", "data": [[x, y, z], …]}, …}}
- binary (Content-Type application/x-hapticlink-block, WebSocket binary messages):
    b"HLB1" | uint32 LE header length | header JSON (as above, "shape" instead of "data") |
    the channels' float32 little-endian samples, concatenated in header order

`seq` is required. `kind` names the block's kind (`BLOCK_KINDS`; "samples", the default, is a
SampleBlock); a new kind (e.g. short tap transients) is a new entry there and its dataclass.
What travels around blocks (acknowledgements, close codes, credentials) is `drivers.protocol`.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, field

import numpy as np

from texture_library.channels import check_channel

MAGIC = b"HLB1"
BINARY_CONTENT_TYPE = "application/x-hapticlink-block"
MAX_BLOCK_SAMPLES = 100_000  # per channel: 1 s at 100 kHz; a robot sends blocks far smaller
MAX_HEADER_BYTES = 64 * 1024
#: block kinds the wire carries (header "kind"); absent means "samples"
BLOCK_KINDS = ("samples",)


@dataclass(frozen=True)
class ChannelBlock:
    """data: (n,) or (n, k) float32 samples in `units`, at rate_hz."""

    data: np.ndarray
    rate_hz: float
    units: str

    @property
    def duration_s(self) -> float:
        return self.data.shape[0] / self.rate_hz


@dataclass(frozen=True)
class SampleBlock:
    """t0: time of the first sample, s (sender's clock); seq: per-stream sequence number."""

    t0: float
    channels: dict[str, ChannelBlock]
    seq: int = 0


@dataclass(frozen=True)
class Frame:
    """A camera frame: encoded image bytes (PNG, JPEG, …) taken at time t (s)."""

    t: float
    image: bytes
    content_type: str = "image/png"
    meta: dict = field(default_factory=dict)


def validate_channel(kind: str, data: np.ndarray, rate_hz: object, units: object) -> ChannelBlock:
    """Check one channel (texture_library.channels.check_channel) and keep it as float32 in its own units."""
    if units is None:
        raise ValueError(f"{kind}: units are required")
    # no copy: a binary block's samples stay a read-only view of its message
    arr, rate, units = check_channel(kind, data, rate_hz, units, dtype=np.float32, copy=False)
    if arr.shape[0] > MAX_BLOCK_SAMPLES:
        raise ValueError(f"{kind}: a block holds at most {MAX_BLOCK_SAMPLES} samples per channel, got {arr.shape[0]}")
    return ChannelBlock(arr, rate, units)


def _check_header(header: object) -> tuple[int, float, dict]:
    if not isinstance(header, dict):
        raise ValueError("block must be a JSON object")
    if "seq" not in header:
        raise ValueError("seq is required (an integer ≥ 0, one more per block)")
    kind = header.get("kind", "samples")
    if kind not in BLOCK_KINDS:
        raise ValueError(f"kind must be one of {list(BLOCK_KINDS)}, got {kind!r}")
    seq, t0, channels = header["seq"], header.get("t0"), header.get("channels")
    if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
        raise ValueError(f"seq must be an integer ≥ 0, got {seq!r}")
    if isinstance(t0, bool) or not isinstance(t0, (int, float)) or not math.isfinite(t0):
        raise ValueError(f"t0 must be a finite number (seconds), got {t0!r}")
    if not isinstance(channels, dict) or not channels:
        raise ValueError("channels must be a non-empty object of {kind: {rate_hz, units, data}}")
    for kind, spec in channels.items():
        if not isinstance(spec, dict):
            raise ValueError(f"channel {kind!r} must be an object with rate_hz, units and data")
    return seq, float(t0), channels


def decode_json(obj: object) -> SampleBlock:
    seq, t0, channels = _check_header(obj)
    out = {}
    for kind, spec in channels.items():
        data = spec.get("data")
        if not isinstance(data, list):
            raise ValueError(f"{kind}: data must be a list of samples")
        try:
            arr = np.array(data, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{kind}: data must be a rectangular list of numbers") from None
        out[kind] = validate_channel(kind, arr, spec.get("rate_hz"), spec.get("units"))
    return SampleBlock(t0, out, seq)


def encode_json(block: SampleBlock) -> dict:
    return {
        "seq": block.seq,
        "t0": block.t0,
        "channels": {k: {"rate_hz": c.rate_hz, "units": c.units, "data": c.data.tolist()} for k, c in block.channels.items()},
    }


def encode_binary(block: SampleBlock) -> bytes:
    header = {
        "seq": block.seq,
        "t0": block.t0,
        "channels": {k: {"rate_hz": c.rate_hz, "units": c.units, "shape": list(c.data.shape)} for k, c in block.channels.items()},
    }
    head = json.dumps(header).encode()
    payload = b"".join(np.ascontiguousarray(c.data, dtype="<f4").tobytes() for c in block.channels.values())
    return MAGIC + struct.pack("<I", len(head)) + head + payload


def peek_header(payload: bytes, binary: bool) -> object | None:
    """The header object of a (possibly bad) block without validating it; None if unreadable."""
    try:
        if binary:
            if len(payload) < 8 or payload[:4] != MAGIC:
                return None
            (n,) = struct.unpack_from("<I", payload, 4)
            return json.loads(payload[8 : 8 + min(n, MAX_HEADER_BYTES)])
        return json.loads(payload)
    except (ValueError, RecursionError):
        return None


def decode_binary(buf: bytes) -> SampleBlock:
    if len(buf) < 8 or buf[:4] != MAGIC:
        raise ValueError("binary block must start with the magic bytes b'HLB1'")
    (n,) = struct.unpack_from("<I", buf, 4)
    if n > MAX_HEADER_BYTES or 8 + n > len(buf):
        raise ValueError(f"binary block header length {n} is invalid for a {len(buf)}-byte message")
    try:
        header = json.loads(buf[8 : 8 + n])
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise ValueError("binary block header is not valid JSON") from None
    seq, t0, channels = _check_header(header)
    offset = 8 + n
    out = {}
    for kind, spec in channels.items():
        shape = spec.get("shape")
        if not (isinstance(shape, list) and 1 <= len(shape) <= 2 and all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)):
            raise ValueError(f"{kind}: shape must be [n] or [n, k] with non-negative integers, got {shape!r}")
        count = math.prod(shape)
        if count > 4 * MAX_BLOCK_SAMPLES:
            raise ValueError(f"{kind}: shape {shape} is too large")
        end = offset + 4 * count
        if end > len(buf):
            raise ValueError(f"{kind}: payload too short: need {4 * count} bytes, {len(buf) - offset} left")
        arr = np.frombuffer(buf, dtype="<f4", count=count, offset=offset).reshape(shape)
        out[kind] = validate_channel(kind, arr, spec.get("rate_hz"), spec.get("units"))
        offset = end
    if offset != len(buf):
        raise ValueError(f"binary block has {len(buf) - offset} trailing bytes after the declared channels")
    return SampleBlock(t0, out, seq)
