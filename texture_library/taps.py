"""Tap transients: short acceleration recordings of the tool tapping the surface (a hardness cue)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texture_library.channels import check_samples

#: sample rate of every TapSet's accel (HaTT's taps and the synthetic world's), Hz
TAP_RATE_HZ = 1000.0


@dataclass(frozen=True)
class TapSet:
    """speeds: (k,) tap speed, mm/s; accel: (k, n) acceleration, m/s², at 1 kHz."""

    speeds: np.ndarray
    accel: np.ndarray

    def __post_init__(self) -> None:
        speeds = np.asarray(self.speeds)
        accel = np.asarray(self.accel)
        if speeds.ndim != 1 or accel.ndim != 2 or accel.shape[0] != speeds.shape[0] or speeds.shape[0] == 0:
            raise ValueError(
                f"taps: need speeds (k,) and accel (k, n) with k ≥ 1, got {speeds.shape} and {accel.shape}"
            )
        if not np.all(np.isfinite(speeds)):
            raise ValueError("taps: speeds contain NaN or Inf")
        check_samples("accel", accel, copy=False, name="taps")
