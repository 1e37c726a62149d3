"""One stroke recording: sensor channels, each with its own sample rate and units, and its .npz file.

Canonical units inside hapticlink: acceleration m/s², force N, speed mm/s,
position mm. Other units named in `UNIT_SCALE` are converted on construction.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from texture_library.channels import CANONICAL_UNITS, CHANNEL_KINDS, UNIT_SCALE, check_channel
from texture_library.npzfile import load_npz, save_npz

FILE_FORMAT = "hapticlink-recording"
FILE_VERSION = 1


@dataclass(frozen=True)
class Channel:
    """Samples of one sensor: data (n,) or (n, k) in canonical units, at rate_hz."""

    data: np.ndarray
    rate_hz: float

    @property
    def duration_s(self) -> float:
        return self.data.shape[0] / self.rate_hz


def make_channel(kind: str, data: np.ndarray, rate_hz: float, units: str | None = None) -> Channel:
    """Validate one channel (texture_library.channels.check_channel) and convert it to canonical units."""
    arr, rate, units = check_channel(kind, data, rate_hz, units)
    return Channel(arr * UNIT_SCALE[kind][units], rate)


@dataclass(frozen=True)
class Recording:
    """A stroke over one texture.

    accel: (n, 3) m/s²; force: (n,) normal or (n, 3) (tangential x, tangential y, normal) N;
    speed: (n,) mm/s, or position: (n,) / (n, 2) mm to derive it. Each channel has its own rate.
    """

    accel: Channel
    force: Channel
    speed: Channel | None = None
    position: Channel | None = None

    def __post_init__(self) -> None:
        if self.speed is None and self.position is None:
            raise ValueError("recording needs a speed or a position channel")

    @property
    def duration_s(self) -> float:
        """Length of the span all channels cover, s."""
        return min(c.duration_s for c in self.channels().values())

    def channels(self) -> dict[str, Channel]:
        out = {"accel": self.accel, "force": self.force}
        if self.speed is not None:
            out["speed"] = self.speed
        if self.position is not None:
            out["position"] = self.position
        return out

    def crop(self, start_s: float, stop_s: float) -> Recording:
        """The part between start_s and stop_s (s from the start), every channel cut at its own rate."""
        if not (0 <= start_s < stop_s):
            raise ValueError(f"crop needs 0 ≤ start < stop, got {start_s}, {stop_s}")

        def cut(c: Channel) -> Channel:
            return Channel(c.data[int(round(start_s * c.rate_hz)) : int(round(stop_s * c.rate_hz))], c.rate_hz)

        return Recording(
            cut(self.accel),
            cut(self.force),
            None if self.speed is None else cut(self.speed),
            None if self.position is None else cut(self.position),
        )


def recording_from_stroke(accel: np.ndarray, force: np.ndarray, speed: np.ndarray, rate_hz: float) -> Recording:
    """Wrap 1-rate stroke signals (texture_library.stroke.StrokeSignals fields) as a Recording."""
    return Recording(
        accel=make_channel("accel", accel, rate_hz),
        force=make_channel("force", force, rate_hz),
        speed=make_channel("speed", speed, rate_hz),
    )


# ---- recordings ---------------------------------------------------------------------------------
def save_recording(path: str | Path, recording: Recording) -> Path:
    """Write a recording as .npz: one array per channel plus a JSON header of rates and units."""
    channels = recording.channels()
    header = {"channels": {k: {"rate_hz": c.rate_hz, "units": CANONICAL_UNITS[k]} for k, c in channels.items()}}
    return save_npz(
        path, FILE_FORMAT, FILE_VERSION, header, {k: c.data.astype(np.float32) for k, c in channels.items()}
    )


def load_recording(path: str | Path) -> Recording:
    """Read a recording .npz; ValueError names the file and what is wrong."""
    path = Path(path)
    header, arrays = load_npz(path, FILE_FORMAT, FILE_VERSION)
    specs = header.get("channels")
    if not isinstance(specs, dict) or not all(isinstance(s, dict) for s in specs.values()):
        raise ValueError(f'{path}: header \'channels\' must map each channel to {{"rate_hz": …, "units": …}}')
    chans: dict[str, Channel] = {}
    for kind, spec in specs.items():
        if kind not in CHANNEL_KINDS:
            raise ValueError(f"{path}: unknown channel {kind!r}")
        if kind not in arrays:
            raise ValueError(f"{path}: header lists channel {kind!r} but the array is missing")
        try:
            chans[kind] = make_channel(kind, arrays[kind], spec.get("rate_hz"), spec.get("units"))
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    return recording_from_channels(chans, str(path))


def recording_from_channels(chans: dict[str, Channel], source: str) -> Recording:
    """A Recording from channels by kind; ValueError naming `source` if accel, force or speed/position is missing."""
    for needed in ("accel", "force"):
        if needed not in chans:
            raise ValueError(f"{source}: missing channel {needed!r}")
    try:
        return Recording(chans["accel"], chans["force"], chans.get("speed"), chans.get("position"))
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}") from None
