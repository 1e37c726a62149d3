"""One stroke recording: sensor channels, each with its own sample rate and units.

Canonical units inside hapticlink: acceleration m/s², force N, speed mm/s,
position mm. Other units named in `UNIT_SCALE` are converted on construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texture_library.channels import CANONICAL_UNITS, UNIT_SCALE, check_channel

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

    def crop(self, start_s: float, stop_s: float) -> "Recording":
        """The part between start_s and stop_s (s from the start), every channel cut at its own rate."""
        if not (0 <= start_s < stop_s):
            raise ValueError(f"crop needs 0 ≤ start < stop, got {start_s}, {stop_s}")

        def cut(c: Channel | None) -> Channel | None:
            if c is None:
                return None
            return Channel(c.data[int(round(start_s * c.rate_hz)) : int(round(stop_s * c.rate_hz))], c.rate_hz)

        return Recording(cut(self.accel), cut(self.force), cut(self.speed), cut(self.position))


def recording_from_stroke(accel: np.ndarray, force: np.ndarray, speed: np.ndarray, rate_hz: float) -> Recording:
    """Wrap 1-rate stroke signals (texture_library.stroke.StrokeSignals fields) as a Recording."""
    return Recording(
        accel=make_channel("accel", accel, rate_hz),
        force=make_channel("force", force, rate_hz),
        speed=make_channel("speed", speed, rate_hz),
    )
