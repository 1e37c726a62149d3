"""What sensors send: timestamped sample blocks and camera frames, and their wire formats.

A block carries one span of time for every channel it holds; each channel has
its own sample rate, so the spans agree in seconds, not in sample counts.

Wire formats (robot → service), both carrying the same fields:
- JSON: {"seq": int, "t0": float s, ["kind": "samples",]
         "channels": {"accel": {"rate_hz": f, "units": "m/s^2", "data": [[x, y, z], …]}, …}}
- binary (Content-Type application/x-hapticlink-block, WebSocket binary messages):
    b"HLB1" | uint32 LE header length | header JSON (as above, "shape" instead of "data") |
    the channels' float32 little-endian samples, concatenated in header order

`seq` is required. `kind` names the block's kind (`BLOCK_KINDS`; "samples", the default, is a
SampleBlock); a new kind is a new entry there and its dataclass. Kind "taps" (a TapBlock) carries
the tap exploratory procedure — k taps of the tool on the surface, n acceleration samples each —
in "taps" instead of "channels":
- JSON: {"seq", "t0", "kind": "taps", "taps": {"rate_hz": f, "units": "m/s^2" | "g",
         "speeds": [k tap speeds, mm/s], "data": [[n samples] × k]}}
- binary: header {"seq", "t0", "kind": "taps", "taps": {"rate_hz", "units", "speeds", "shape": [k, n]}},
          then k·n float32 samples, tap after tap
Limits: 1 ≤ k ≤ MAX_TAPS taps, MIN_TAP_SAMPLES ≤ n ≤ MAX_TAP_SAMPLES samples each, speeds within
[0, MAX_TAP_SPEED] mm/s; every sample within its kind's MAX_ABS (texture_library.channels: the bounds from physics).
Tap and sample blocks share one seq sequence.
What travels around blocks (acknowledgements, close codes, credentials) is `drivers.protocol`.
"""

from __future__ import annotations

import json
import math
import re
import struct
from dataclasses import dataclass, field

import numpy as np

from texture_library.channels import UNIT_SCALE, check_channel, check_rate, check_samples, check_tap_speeds

MAGIC = b"HLB1"
BINARY_CONTENT_TYPE = "application/x-hapticlink-block"
MAX_BLOCK_SAMPLES = 100_000  # per channel: 1 s at 100 kHz; a robot sends blocks far smaller
#: the largest JSON block, bytes: parsing JSON costs the receiver ≈ 50 µs per kB (a 4.7 MB block held an event loop
#: for ≈ 0.2 s) against ≈ 8 µs per kB for the binary format, so larger blocks go binary. 256 kB holds ≈ 1 s of 1 kHz
#: accel, force and speed as JSON text.
MAX_JSON_BLOCK_BYTES = 256 * 1024
MAX_HEADER_BYTES = 64 * 1024
#: block kinds the wire carries (header "kind"); absent means "samples"
BLOCK_KINDS = ("samples", "taps")
#: the largest camera frame the service decodes (width × height, a 4096×4096 image); a robot never sends a larger one
MAX_FRAME_PIXELS = 4096 * 4096
#: the service's default limit on a request body or WebSocket message (HAPTICLINK_MAX_BODY_BYTES): a robot keeps each
#: encoded frame under it, since a larger one could never arrive
DEFAULT_MAX_BODY_BYTES = 8 * 1024 * 1024
MAX_TAPS = 32  # taps per tap block (HaTT records 9–15 per texture)
MIN_TAP_SAMPLES = 16  # models.tactile.taps.MIN_TAP_SAMPLES: a shorter tap has no ringing to measure
#: per tap: 0.5 s at 1 kHz (HaTT's taps are 100 ms); with MAX_TAPS it bounds the tap features' cost on admission
#: (on the event loop): 32 taps × 500 samples took about 10 ms on the shared 2-core machine, under load
MAX_TAP_SAMPLES = 500


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
class TapBlock:
    """The tap exploratory procedure: k taps on the surface under the tool. t0: time of the first tap, s
    (sender's clock); speeds: (k,) each tap's approach speed, mm/s (float64); accel: (k, n) acceleration of
    each tap in accel.units at accel.rate_hz (float32, one row per tap); seq: shared with sample blocks."""

    t0: float
    speeds: np.ndarray
    accel: ChannelBlock
    seq: int = 0

    @property
    def n_taps(self) -> int:
        return int(self.speeds.shape[0])


Block = SampleBlock | TapBlock


@dataclass(frozen=True)
class Frame:
    """A camera frame: encoded image bytes (PNG, JPEG, …) taken at time t (s)."""

    t: float
    image: bytes
    content_type: str = "image/png"
    meta: dict = field(default_factory=dict)


class FrameTooLarge(ValueError):
    """A frame larger than MAX_FRAME_PIXELS (check_frame_pixels)."""


def check_frame_pixels(width: int, height: int, label: str = "image") -> int:
    """width × height of a frame the service would decode; FrameTooLarge (a ValueError) when larger than
    MAX_FRAME_PIXELS.

    The robot (drivers.camera) and the service (service.runtime) both judge a frame's size here, from its header
    alone, so a frame the robot sends is one the service takes."""
    if width * height > MAX_FRAME_PIXELS:
        raise _too_large(f"{width}×{height} pixels", label)
    return width * height


def frame_bomb(exc: Exception, label: str = "image") -> FrameTooLarge:
    """Pillow's DecompressionBombError — a header declaring more pixels than Pillow opens at all, far past
    MAX_FRAME_PIXELS — as check_frame_pixels' refusal, with the pixel count Pillow's message gives."""
    declared = re.search(r"\((\d+) pixels\)", str(exc))
    return _too_large(f"{declared.group(1)} pixels" if declared else f"over {MAX_FRAME_PIXELS} pixels", label)


def _too_large(size: str, label: str) -> FrameTooLarge:
    return FrameTooLarge(f"{label}: {size}; the service decodes at most {MAX_FRAME_PIXELS} (4096×4096)")


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
    """(seq, t0, channels) of a samples block; a taps block's "taps" object in place of channels."""
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
    if kind == "taps":
        taps = header.get("taps")
        if channels is not None or not isinstance(taps, dict):
            raise ValueError(
                'a taps block carries "taps": {rate_hz, units, speeds, data (JSON) or shape (binary)} and no "channels"'
            )
        return seq, float(t0), taps
    if "taps" in header:
        raise ValueError('"taps" belongs to a block of kind "taps"; this block\'s kind is "samples"')
    if not isinstance(channels, dict) or not channels:
        raise ValueError("channels must be a non-empty object of {kind: {rate_hz, units, data}}")
    for kind, spec in channels.items():
        if not isinstance(spec, dict):
            raise ValueError(f"channel {kind!r} must be an object with rate_hz, units and data")
    return seq, float(t0), channels


def validate_taps(speeds: object, data: np.ndarray, rate_hz: object, units: object) -> tuple[np.ndarray, ChannelBlock]:
    """Check a tap set → (speeds (k,) float64 mm/s, accel (k, n) float32 in its units); ValueError names the problem."""
    if not isinstance(speeds, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in speeds):
        raise ValueError("taps: speeds must be a list of numbers (mm/s), one per tap")
    v = check_tap_speeds(np.array(speeds, dtype=np.float64))
    arr = np.asarray(data)
    if arr.ndim != 2:
        raise ValueError(f"taps: data must be k taps of n samples, shape (k, n), got {arr.shape}")
    k, n = arr.shape
    if not 1 <= k <= MAX_TAPS:
        raise ValueError(f"taps: a block holds 1 to {MAX_TAPS} taps, got {k}")
    if not MIN_TAP_SAMPLES <= n <= MAX_TAP_SAMPLES:
        raise ValueError(f"taps: each tap holds {MIN_TAP_SAMPLES} to {MAX_TAP_SAMPLES} samples, got {n}")
    if v.shape[0] != k:
        raise ValueError(f"taps: {v.shape[0]} speed(s) for {k} tap(s); give one speed per tap")
    if units not in UNIT_SCALE["accel"]:
        raise ValueError(f"taps: units must be one of {list(UNIT_SCALE['accel'])}, got {units!r}")
    rate = check_rate(rate_hz, "taps")
    return v, ChannelBlock(check_samples("accel", arr, units, np.float32, copy=False, name="taps"), rate, units)


def _json_numbers(data: list, message: str) -> np.ndarray:
    """A JSON list of samples as float64; ValueError(message) for a ragged list, strings ("1.5" too: numpy would
    parse them) or booleans alone — what numpy infers without being told a dtype says which it is. (Booleans among
    numbers numpy reads as numbers: the service refuses a block's bytes that hold any, service.intake.)"""
    try:
        arr = np.array(data)
    except (TypeError, ValueError):  # ragged
        raise ValueError(message) from None
    if arr.dtype.kind not in "iuf":
        raise ValueError(message)
    return arr.astype(np.float64, copy=False)


def decode_json(obj: object) -> Block:
    seq, t0, channels = _check_header(obj)
    assert isinstance(obj, dict)  # _check_header refused anything else
    if obj.get("kind") == "taps":
        data = channels.get("data")
        if not isinstance(data, list):
            raise ValueError("taps: data must be a list of taps, each a list of samples")
        arr = _json_numbers(data, "taps: data must be a rectangular list of numbers (k taps × n samples)")
        speeds, accel = validate_taps(channels.get("speeds"), arr, channels.get("rate_hz"), channels.get("units"))
        return TapBlock(t0, speeds, accel, seq)
    out = {}
    for kind, spec in channels.items():
        data = spec.get("data")
        if not isinstance(data, list):
            raise ValueError(f"{kind}: data must be a list of samples")
        arr = _json_numbers(data, f"{kind}: data must be a rectangular list of numbers")
        out[kind] = validate_channel(kind, arr, spec.get("rate_hz"), spec.get("units"))
    return SampleBlock(t0, out, seq)


def encode_json(block: Block) -> dict:
    if isinstance(block, TapBlock):
        a = block.accel
        return {
            "seq": block.seq,
            "t0": block.t0,
            "kind": "taps",
            "taps": {"rate_hz": a.rate_hz, "units": a.units, "speeds": block.speeds.tolist(), "data": a.data.tolist()},
        }
    return {
        "seq": block.seq,
        "t0": block.t0,
        "channels": {
            k: {"rate_hz": c.rate_hz, "units": c.units, "data": c.data.tolist()} for k, c in block.channels.items()
        },
    }


def encode_binary(block: Block) -> bytes:
    if isinstance(block, TapBlock):
        a = block.accel
        header = {
            "seq": block.seq,
            "t0": block.t0,
            "kind": "taps",
            "taps": {
                "rate_hz": a.rate_hz,
                "units": a.units,
                "speeds": block.speeds.tolist(),
                "shape": list(a.data.shape),
            },
        }
        head = json.dumps(header).encode()
        return MAGIC + struct.pack("<I", len(head)) + head + np.ascontiguousarray(a.data, dtype="<f4").tobytes()
    header = {
        "seq": block.seq,
        "t0": block.t0,
        "channels": {
            k: {"rate_hz": c.rate_hz, "units": c.units, "shape": list(c.data.shape)} for k, c in block.channels.items()
        },
    }
    head = json.dumps(header).encode()
    payload = b"".join(np.ascontiguousarray(c.data, dtype="<f4").tobytes() for c in block.channels.values())
    return MAGIC + struct.pack("<I", len(head)) + head + payload


def peek_header(payload: bytes, binary: bool) -> object | None:
    """The header object of a (possibly bad) block without validating it; None if unreadable (or a JSON block too
    large to parse)."""
    try:
        if not binary and len(payload) > MAX_JSON_BLOCK_BYTES:
            return None
        if binary:
            if len(payload) < 8 or payload[:4] != MAGIC:
                return None
            (n,) = struct.unpack_from("<I", payload, 4)
            return json.loads(payload[8 : 8 + min(n, MAX_HEADER_BYTES)])
        return json.loads(payload)
    except (ValueError, RecursionError):
        return None


class UnreadableHeader(ValueError):
    """A binary block whose JSON header Python cannot read (the service answers it as a body that is not JSON)."""


def decode_binary(buf: bytes) -> Block:
    if len(buf) < 8 or buf[:4] != MAGIC:
        raise ValueError("binary block must start with the magic bytes b'HLB1'")
    (n,) = struct.unpack_from("<I", buf, 4)
    if n > MAX_HEADER_BYTES or 8 + n > len(buf):
        raise ValueError(f"binary block header length {n} is invalid for a {len(buf)}-byte message")
    try:
        header = json.loads(buf[8 : 8 + n])
    except (ValueError, RecursionError) as exc:  # its syntax, bytes not UTF-8, a huge integer, nesting too deep
        raise UnreadableHeader(f"the binary block's header: {exc}") from None
    seq, t0, channels = _check_header(header)
    offset = 8 + n
    if header.get("kind") == "taps":
        shape = channels.get("shape")
        if not (
            isinstance(shape, list)
            and len(shape) == 2
            and all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)
        ):
            raise ValueError(f"taps: shape must be [k, n] (k taps of n samples), got {shape!r}")
        if max(shape) > MAX_TAPS * MAX_TAP_SAMPLES or shape[0] * shape[1] > MAX_TAPS * MAX_TAP_SAMPLES:
            raise ValueError(f"taps: shape {shape} is too large")
        if offset + 4 * shape[0] * shape[1] != len(buf):
            raise ValueError(
                f"taps: shape {shape} needs {4 * shape[0] * shape[1]} bytes of samples, the message "
                f"holds {len(buf) - offset}"
            )
        arr = np.frombuffer(buf, dtype="<f4", count=shape[0] * shape[1], offset=offset).reshape(shape)
        speeds, accel = validate_taps(channels.get("speeds"), arr, channels.get("rate_hz"), channels.get("units"))
        return TapBlock(t0, speeds, accel, seq)
    out = {}
    for kind, spec in channels.items():
        shape = spec.get("shape")
        if not (
            isinstance(shape, list)
            and 1 <= len(shape) <= 2
            and all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)
        ):
            raise ValueError(f"{kind}: shape must be [n] or [n, k] with non-negative integers, got {shape!r}")
        count = math.prod(shape)
        if count > 4 * MAX_BLOCK_SAMPLES or max(shape) > 4 * MAX_BLOCK_SAMPLES:  # [2**62, 0] holds 0 samples
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
