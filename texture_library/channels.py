"""Sensor channels a stroke produces: kinds, units, shapes, sample-rate limits, validation.

The one validator of sensor samples and sample rates (as librosa has util.valid_audio): shared by the
dataset format and the streaming preprocessor (models), the wire format and the sources (drivers) and
the service, so every entry point accepts and refuses exactly the same things.
Canonical units: acceleration m/s², force N, speed mm/s, position mm.
"""

from __future__ import annotations

import math

import numpy as np

#: factor converting a value in the named unit to the canonical (first) unit of its kind
UNIT_SCALE: dict[str, dict[str, float]] = {
    "accel": {"m/s^2": 1.0, "g": 9.80665},
    "force": {"N": 1.0},
    "speed": {"mm/s": 1.0, "m/s": 1000.0},
    "position": {"mm": 1.0, "m": 1000.0},
}
CHANNEL_KINDS: tuple[str, ...] = tuple(UNIT_SCALE)
CANONICAL_UNITS = {kind: next(iter(units)) for kind, units in UNIT_SCALE.items()}
#: accel 3 axes; force normal only or (tangential x, tangential y, normal); position along the stroke or in-plane
CHANNEL_COLUMNS: dict[str, tuple[int, ...]] = {"accel": (3,), "force": (1, 3), "speed": (1,), "position": (1, 2)}
MIN_RATE_HZ = 10.0
MAX_RATE_HZ = 100_000.0
#: Bounds from physics: the largest magnitude a sample of each kind may have, canonical units, one per axis. Each is
#: beyond what a texture-sensing tool can meet and far inside what breaks the features; a sample past it is a sensor
#: fault or a wrong unit (m/s read as mm/s), refused with its block, never computed on (docs/drivers.md, "Bounds"):
#: - acceleration 2000 m/s² (≈ 200 g): the widest MEMS accelerometers (ADXL377, ±200 g); texture sensors are ±3–16 g
#:   and tap transients on the stiffest surfaces peak near 10 g;
#: - force 200 N per axis: a hand presses a tool at most ≈ 50 N, a robot's tool scanning a surface no more than this
#:   without damaging it;
#: - scanning speed 2000 mm/s: a hand strokes at ≤ 500 mm/s (HaTT: ≤ 300), a fast robot arm's tool at ≤ 2 m/s;
#: - position 10⁶ mm (1 km): odometry of a mobile robot; the features read only its differences.
MAX_ABS: dict[str, float] = {"accel": 2000.0, "force": 200.0, "speed": 2000.0, "position": 1e6}
#: the quantity each kind measures, as refusals name it
QUANTITY: dict[str, str] = {
    "accel": "acceleration",
    "force": "force",
    "speed": "scanning speed",
    "position": "position",
}
#: a tap's approach speed, mm/s, [0, MAX_TAP_SPEED]: a tool swung at a surface by hand or arm arrives at ≤ 2 m/s
MAX_TAP_SPEED = 2000.0


def check_array(name: str, x: object, shape: tuple[int | None, ...], dtype: type[np.number] = np.float64) -> np.ndarray:
    """`x` as a `dtype` array (no copy when it already is one) of `shape` (None: any length on that axis),
    real numbers, none NaN or Inf; ValueError naming `name` and the problem otherwise."""
    arr = np.asarray(x)
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{name} must be real numbers, got dtype {arr.dtype}")
    if arr.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, arr.shape, strict=True)):
        want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has {int(np.count_nonzero(~np.isfinite(arr)))} NaN or Inf value(s)")
    return arr.astype(dtype, copy=False)


def check_tap_speeds(speeds: np.ndarray) -> np.ndarray:
    """Tap speeds (k,) mm/s within [0, MAX_TAP_SPEED] (finite); ValueError names the first one outside and the range."""
    bad = ~(np.isfinite(speeds) & (speeds >= 0) & (speeds <= MAX_TAP_SPEED))
    if bad.any():
        value = float(speeds[np.argmax(bad)])
        raise ValueError(
            f"taps: tap speed {value:.4g} mm/s is outside its physical range, 0 to {MAX_TAP_SPEED:g} mm/s: a sensor "
            "fault, or the wrong units"
        )
    return speeds


def check_rate(rate_hz: object, name: str) -> float:
    """A sample rate in Hz: a real number (not a bool, not a string) within [MIN_RATE_HZ, MAX_RATE_HZ], as float.

    ValueError names `name` (the channel, the device, the argument) and the problem."""
    if (
        isinstance(rate_hz, bool)
        or not isinstance(rate_hz, (int, float, np.integer, np.floating))
        or not math.isfinite(rate_hz)
    ):
        raise ValueError(f"{name}: sample rate must be a finite number, got {rate_hz!r}")
    if not MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ:
        raise ValueError(
            f"{name}: sample rate must lie in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}] Hz, got {rate_hz:g} (a sample "
            f"interval of {1e3 / MAX_RATE_HZ:g} to {1e3 / MIN_RATE_HZ:g} ms)"
        )
    return float(rate_hz)


def check_channel(
    kind: str,
    data: object,
    rate_hz: object,
    units: object | None = None,
    dtype: type[np.floating] = np.float64,
    copy: bool = True,
    allow_empty: bool = False,
) -> tuple[np.ndarray, float, str]:
    """Validate one channel: (samples as `dtype`, (n,) or (n, k), in their own units; rate; units).
    copy=False returns `data` itself when it already has `dtype` (e.g. a read-only view of a wire message);
    allow_empty accepts n = 0 (a streaming block may be empty, a recording may not).

    ValueError names the channel and the problem: unknown kind or units, rate not a number or out of
    [MIN_RATE_HZ, MAX_RATE_HZ], non-numeric samples, wrong shape, no samples, NaN/Inf.
    """
    if kind not in UNIT_SCALE:
        raise ValueError(f"unknown channel {kind!r}; expected one of {list(CHANNEL_KINDS)}")
    units = CANONICAL_UNITS[kind] if units is None else units
    if units not in UNIT_SCALE[kind]:
        raise ValueError(f"{kind}: units must be one of {list(UNIT_SCALE[kind])}, got {units!r}")
    rate = check_rate(rate_hz, kind)
    arr = _numbers(np.asarray(data), kind)  # before the shape: text or booleans are refused as such
    if arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]
    cols = 1 if arr.ndim == 1 else (arr.shape[1] if arr.ndim == 2 else -1)
    if cols not in CHANNEL_COLUMNS[kind]:
        allowed = " or ".join("(n,)" if c == 1 else f"(n, {c})" for c in CHANNEL_COLUMNS[kind])
        raise ValueError(f"{kind}: shape must be {allowed}, got {arr.shape}")
    if arr.shape[0] == 0 and not allow_empty:
        raise ValueError(f"{kind}: no samples")
    return check_samples(kind, arr, units, dtype, copy), rate, str(units)


def check_samples(
    kind: str,
    data: np.ndarray,
    units: str | None = None,
    dtype: type[np.floating] = np.float64,
    copy: bool = True,
    name: str | None = None,
) -> np.ndarray:
    """Samples of `kind` in `units` (default canonical; any shape) as `dtype`: numbers, finite, and within
    MAX_ABS[kind] once in canonical units (beyond it: a sensor fault or a wrong unit, never computed on). ValueError
    names `name` (default the kind) and the problem."""
    name = name or kind
    arr = _numbers(data, name).astype(dtype, copy=copy)
    if not arr.size:
        return arr
    # one pass for both checks (this runs per channel of every block): NaN propagates through max, ±Inf is the peak
    peak = float(np.abs(arr).max())
    if not math.isfinite(peak):
        raise ValueError(f"{name}: {int(np.count_nonzero(~np.isfinite(arr)))} sample(s) are NaN or Inf")
    unit = CANONICAL_UNITS[kind]
    peak *= UNIT_SCALE[kind][units or unit]
    if peak > MAX_ABS[kind]:
        raise ValueError(
            f"{name}: {QUANTITY[kind]} {peak:.4g} {unit} is outside its physical range, magnitude at most "
            f"{MAX_ABS[kind]:g} {unit}: a sensor fault, or the wrong units"
        )
    return arr


def _numbers(data: np.ndarray, name: str) -> np.ndarray:
    if data.dtype.kind not in "iuf":
        raise ValueError(f"{name}: samples must be numbers, got dtype {data.dtype}")
    return data
