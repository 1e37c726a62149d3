"""The tactile feature configuration: one frozen, serialisable object for training and serving.

Why ``n_fft=64`` and ``n_mels=26``
----------------------------------
At 1 kHz a 25 ms frame is 25 samples; an FFT of 25 points has only 13 bins, spaced 40 Hz.
The paper's 26 mel bands over 20–500 Hz would then hold many filters with no bin under
them (librosa warns "Empty filters detected"), i.e. constant, information-free MFCC inputs.
Below 1 kHz the Slaney mel scale is linear, so the 28 mel edge points of 26 bands sit
(500 − 20) / 27 ≈ 17.8 Hz apart and each triangular filter is ≈ 35.6 Hz wide. Zero-padding
the 25-sample Hann frame to ``n_fft = 64`` gives 33 bins spaced 15.625 Hz, so every
triangle covers at least two bins (checked: 2–3 non-zero weights per filter). ``n_fft = 32``
or ``48`` still leaves filters with a single bin, so 64 is the smallest power of two that
gives every band ≥ 2 bins. Zero-padding adds no information (the frame's frequency
resolution stays ≈ 40 Hz) but samples the spectrum finely enough that each band gets its
own weighted average instead of nothing. The validator below rejects any configuration
whose mel filterbank has an empty filter.

Frames are taken with ``center=False``: 1 + (500 − 25) // 12 = 40 frames of 25 samples per
0.5 s window, 13 coefficients each → 520 MFCC values, + min/max/mean of speed and of force
= 526 features.

Extra feature groups (``extra_groups``, any of ``EXTRA_GROUPS``, kept in that order) read
physics the MFCC frames cannot see; their columns follow the 6 statistics, group by group:

  "friction" → friction_ratio, friction_ratio_std (models.tactile.friction): 2 values;
               needs 3-column force (the preprocessor derives the tangential magnitude)
  "spatial"  → log mean-square height per band of spatial periods, spatial_max_period_mm down
               to spatial_min_period_mm in spatial_bands geometric bands (models.tactile.spatial),
               from acceleration high-passed at spatial_highpass_hz against integrated speed
  "taps"     → tap_log_peak_per_speed, tap_log_decay_s, tap_centroid_hz (models.tactile.taps):
               3 per-texture values from tap transients, the same on every window of a texture

``hash()`` is stamped into exported models; the service refuses a model whose hash differs
from its own configuration's. It covers every field plus ``FEATURE_CODE_VERSION``, which is
bumped whenever the feature *code* changes meaning for an unchanged configuration. The extra
groups' fields are serialised (and hashed) only when a group is on, so every configuration
from before the groups existed keeps its hash — and its caches and exported models.
"""

from __future__ import annotations

import hashlib
import json
import math
from functools import lru_cache
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, field_validator, model_validator

from texture_library.channels import check_rate

#: bump when the feature definitions change for the same configuration values
FEATURE_CODE_VERSION = 1
#: speed/force statistics appended to every feature set, in this order
STAT_NAMES: tuple[str, ...] = (
    "speed_min",
    "speed_max",
    "speed_mean",
    "force_min",
    "force_max",
    "force_mean",
)
#: per-level DWT statistics, in this order (see models.tactile.dwt)
DWT_STAT_NAMES: tuple[str, ...] = ("log_energy", "mean_abs", "std")
#: optional feature groups, in column order
EXTRA_GROUPS: tuple[str, ...] = ("friction", "spatial", "taps")
ExtraGroup = Literal["friction", "spatial", "taps"]
#: fields that only the extra groups use: left out of to_dict()/hash() while no group is on
EXTRA_FIELDS: tuple[str, ...] = (
    "extra_groups",
    "spatial_highpass_hz",
    "spatial_dx_mm",
    "spatial_n_fft",
    "spatial_min_period_mm",
    "spatial_max_period_mm",
    "spatial_bands",
    "spatial_min_speed",
)


@lru_cache(maxsize=32)
def mel_filter_sizes(rate_hz: float, n_fft: int, n_mels: int, fmin: float, fmax: float) -> tuple[int, ...]:
    """Number of FFT bins with non-zero weight in each mel filter (Slaney mel, librosa)."""
    import warnings

    import librosa

    with warnings.catch_warnings():
        # librosa warns on empty filters; we report them ourselves, precisely
        warnings.simplefilter("ignore", UserWarning)
        basis = librosa.filters.mel(sr=rate_hz, n_fft=n_fft, n_mels=n_mels, fmin=fmin, fmax=fmax)
    return tuple(int(c) for c in np.count_nonzero(basis > 0, axis=1))


def _samples(seconds: float, rate_hz: float, name: str) -> int:
    """seconds → whole samples; ValueError if it is not (close to) an integer."""
    n = seconds * rate_hz
    if abs(n - round(n)) > 1e-6:
        raise ValueError(f"{name}={seconds} s is not a whole number of samples at {rate_hz} Hz ({n} samples)")
    return int(round(n))


class TactileConfig(BaseModel):
    """Tactile preprocessing and feature parameters (rates in Hz, durations in s)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    rate_hz: float = 1000.0
    accel_highpass_hz: float = 20.0
    accel_filter_order: int = 4
    lowpass_hz: float = 25.0
    lowpass_order: int = 2
    window_s: float = 0.5
    hop_s: float = 0.5
    frame_length: int = 25
    frame_hop: int = 12
    n_fft: int = 64
    n_mels: int = 26
    n_mfcc: int = 13
    fmin: float = 20.0
    fmax: float = 500.0
    top_db: float = 80.0
    feature_set: Literal["mfcc", "dwt", "dft"] = "mfcc"
    dwt_wavelet: Literal["db1", "db2", "db3", "db4"] = "db4"
    dwt_levels: int = 5
    dft_bins: int = 32
    extra_groups: tuple[ExtraGroup, ...] = ()
    spatial_highpass_hz: float = 1.0
    spatial_dx_mm: float = 0.25
    spatial_n_fft: int = 1024
    spatial_min_period_mm: float = 1.0
    spatial_max_period_mm: float = 32.0
    spatial_bands: int = 10
    spatial_min_speed: float = 30.0

    @field_validator("extra_groups", mode="before")
    @classmethod
    def _canonical_groups(cls, value: Any) -> Any:
        """Any order in, EXTRA_GROUPS order out (so one set of groups has one hash); no repeats."""
        if isinstance(value, str):
            value = (value,)
        if isinstance(value, (list, tuple)):
            unknown = [g for g in value if g not in EXTRA_GROUPS]
            if unknown:
                raise ValueError(f"unknown feature group(s) {unknown}; expected some of {list(EXTRA_GROUPS)}")
            if len(set(value)) != len(value):
                raise ValueError(f"extra_groups repeats a group: {list(value)}")
            return tuple(g for g in EXTRA_GROUPS if g in value)
        return value

    @model_validator(mode="after")
    def _check(self) -> TactileConfig:
        nyq = self.rate_hz / 2
        check_rate(self.rate_hz, "rate_hz")
        for name in ("accel_highpass_hz", "lowpass_hz"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 < v < nyq):
                raise ValueError(f"{name} must lie in (0, rate_hz/2 = {nyq:g}) Hz, got {v}")
        for name in ("accel_filter_order", "lowpass_order"):
            v = getattr(self, name)
            if not 1 <= v <= 12:
                raise ValueError(f"{name} must lie in [1, 12], got {v}")
        for name in ("window_s", "hop_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0 s, got {v}")
        win = _samples(self.window_s, self.rate_hz, "window_s")
        hop = _samples(self.hop_s, self.rate_hz, "hop_s")
        if hop < 1:
            raise ValueError(f"hop_s={self.hop_s} s is shorter than one sample at {self.rate_hz} Hz")
        if self.frame_length < 2:
            raise ValueError(f"frame_length must be ≥ 2 samples, got {self.frame_length}")
        if self.frame_length > self.n_fft:
            raise ValueError(f"frame_length ({self.frame_length}) must be ≤ n_fft ({self.n_fft})")
        if self.frame_length > win:
            raise ValueError(f"frame_length ({self.frame_length}) must be ≤ the window length ({win} samples)")
        if self.frame_hop < 1:
            raise ValueError(f"frame_hop must be ≥ 1 sample, got {self.frame_hop}")
        if not (math.isfinite(self.fmin) and math.isfinite(self.fmax) and 0 <= self.fmin < self.fmax):
            raise ValueError(f"need 0 ≤ fmin < fmax, got fmin={self.fmin}, fmax={self.fmax}")
        if self.fmax > nyq:
            raise ValueError(f"fmax ({self.fmax} Hz) must be ≤ rate_hz/2 = {nyq:g} Hz")
        if self.n_mels < 1:
            raise ValueError(f"n_mels must be ≥ 1, got {self.n_mels}")
        if not 1 <= self.n_mfcc <= self.n_mels:
            raise ValueError(f"n_mfcc must lie in [1, n_mels={self.n_mels}], got {self.n_mfcc}")
        if not (math.isfinite(self.top_db) and self.top_db > 0):
            raise ValueError(f"top_db must be > 0 dB, got {self.top_db}")
        sizes = mel_filter_sizes(self.rate_hz, self.n_fft, self.n_mels, self.fmin, self.fmax)
        empty = [i for i, s in enumerate(sizes) if s == 0]
        if empty:
            raise ValueError(
                f"mel filterbank has {len(empty)} empty filter(s) (bands {empty}) with n_fft={self.n_fft}, "
                f"n_mels={self.n_mels} over {self.fmin:g}–{self.fmax:g} Hz at {self.rate_hz:g} Hz; "
                "increase n_fft or reduce n_mels"
            )
        if self.dwt_levels < 1:
            raise ValueError(f"dwt_levels must be ≥ 1, got {self.dwt_levels}")
        taps = 2 * int(self.dwt_wavelet[2:])
        max_level = int(math.floor(math.log2(win / (taps - 1)))) if win >= taps else 0
        if self.dwt_levels > max_level:
            raise ValueError(
                f"dwt_levels={self.dwt_levels} is too deep for {win}-sample windows with {self.dwt_wavelet} "
                f"({taps} taps); at most {max_level}"
            )
        if self.dft_bins < 1:
            raise ValueError(f"dft_bins must be ≥ 1, got {self.dft_bins}")
        bin_hz = self.rate_hz / win
        if (self.fmax - self.fmin) / self.dft_bins < bin_hz:
            raise ValueError(
                f"dft_bins={self.dft_bins} bands over {self.fmin:g}–{self.fmax:g} Hz are narrower than the "
                f"{bin_hz:g} Hz DFT bin spacing of a {win}-sample window; some bands would be empty"
            )
        self._check_spatial()
        return self

    def _check_spatial(self) -> None:
        nyq = self.rate_hz / 2
        if not (math.isfinite(self.spatial_highpass_hz) and 0 < self.spatial_highpass_hz < nyq):
            raise ValueError(
                f"spatial_highpass_hz must lie in (0, rate_hz/2 = {nyq:g}) Hz, got {self.spatial_highpass_hz}"
            )
        for name in ("spatial_dx_mm", "spatial_min_period_mm", "spatial_max_period_mm", "spatial_min_speed"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0, got {v}")
        if self.spatial_bands < 1:
            raise ValueError(f"spatial_bands must be ≥ 1, got {self.spatial_bands}")
        if 2 * self.spatial_dx_mm > self.spatial_min_period_mm:
            raise ValueError(
                f"spatial_dx_mm={self.spatial_dx_mm} cannot resolve spatial_min_period_mm="
                f"{self.spatial_min_period_mm} (needs dx ≤ period/2)"
            )
        if not self.spatial_min_period_mm < self.spatial_max_period_mm <= self.spatial_n_fft * self.spatial_dx_mm / 4:
            raise ValueError(
                f"need spatial_min_period_mm < spatial_max_period_mm ≤ spatial_n_fft·spatial_dx_mm/4 = "
                f"{self.spatial_n_fft * self.spatial_dx_mm / 4:g} mm, got {self.spatial_min_period_mm}, "
                f"{self.spatial_max_period_mm}"
            )
        ratio = (self.spatial_max_period_mm / self.spatial_min_period_mm) ** (1 / self.spatial_bands)
        bin_per_mm = 1 / (self.spatial_n_fft * self.spatial_dx_mm)
        if (ratio - 1) / self.spatial_max_period_mm < bin_per_mm:
            raise ValueError(
                f"spatial_bands={self.spatial_bands}: the longest-period band is narrower than one "
                f"bin ({bin_per_mm:g} mm⁻¹) of a {self.spatial_n_fft}-point spectrum at {self.spatial_dx_mm} mm; "
                "use fewer bands or a larger spatial_n_fft"
            )

    # ---- derived sizes -------------------------------------------------------------------
    @property
    def window_length(self) -> int:
        """Samples per analysis window (500 at the defaults)."""
        return int(round(self.window_s * self.rate_hz))

    @property
    def hop_length(self) -> int:
        """Samples between window starts (500 at the defaults: no overlap)."""
        return int(round(self.hop_s * self.rate_hz))

    @property
    def n_frames(self) -> int:
        """MFCC frames per window, center=False: 1 + (window_length − frame_length) // frame_hop."""
        return 1 + (self.window_length - self.frame_length) // self.frame_hop

    @property
    def dwt_taps(self) -> int:
        return 2 * int(self.dwt_wavelet[2:])

    @property
    def n_tactile(self) -> int:
        """Length of the feature-set-specific part (before the 6 speed/force statistics)."""
        if self.feature_set == "mfcc":
            return self.n_frames * self.n_mfcc
        if self.feature_set == "dwt":
            return (self.dwt_levels + 1) * len(DWT_STAT_NAMES)
        return self.dft_bins

    @property
    def n_features(self) -> int:
        """Features per window (526 at the defaults)."""
        return self.n_tactile + len(STAT_NAMES) + sum(len(n) for n in self.group_names().values())

    def group_names(self) -> dict[str, list[str]]:
        """Column names of each extra group that is on, in column order."""
        from models.tactile.friction import FRICTION_NAMES
        from models.tactile.spatial import band_names
        from models.tactile.taps import TAP_NAMES

        names = {
            "friction": list(FRICTION_NAMES),
            "spatial": band_names(self.spatial_min_period_mm, self.spatial_max_period_mm, self.spatial_bands),
            "taps": list(TAP_NAMES),
        }
        return {g: names[g] for g in self.extra_groups}

    def group_slices(self) -> dict[str, slice]:
        """Columns of each feature group: "base" (the feature set and the 6 statistics), then the extra groups."""
        out = {"base": slice(0, self.n_tactile + len(STAT_NAMES))}
        start = out["base"].stop
        for group, names in self.group_names().items():
            out[group] = slice(start, start + len(names))
            start += len(names)
        return out

    @property
    def accel_columns(self) -> int:
        """Columns of a window's accel: 3 axes, + the same 3 high-passed at spatial_highpass_hz with "spatial"."""
        return 6 if "spatial" in self.extra_groups else 3

    @property
    def force_columns(self) -> int:
        """Columns of a window's force: the normal (1, shape (L,)), + the tangential magnitude with "friction"."""
        return 2 if "friction" in self.extra_groups else 1

    @property
    def feature_names(self) -> list[str]:
        """One name per feature column, in column order."""
        if self.feature_set == "mfcc":
            names = [f"mfcc_f{f:02d}_c{c:02d}" for f in range(self.n_frames) for c in range(self.n_mfcc)]
        elif self.feature_set == "dwt":
            bands = [f"d{j}" for j in range(1, self.dwt_levels + 1)] + [f"a{self.dwt_levels}"]
            names = [f"dwt_{b}_{s}" for b in bands for s in DWT_STAT_NAMES]
        else:
            names = [f"dft_b{b:02d}" for b in range(self.dft_bins)]
        return names + list(STAT_NAMES) + [n for group in self.group_names().values() for n in group]

    # ---- serialisation -------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict of the fields (round-trips through ``TactileConfig(**d)``); the extra
        groups' fields only when a group is on (see the module docstring)."""
        d = self.model_dump(mode="json")
        if not self.extra_groups:
            for name in EXTRA_FIELDS:
                d.pop(name)
        return d

    def hash(self) -> str:
        """First 16 hex chars of sha256 over canonical JSON of the fields and FEATURE_CODE_VERSION."""
        payload = {"config": self.to_dict(), "feature_code_version": FEATURE_CODE_VERSION}
        text = json.dumps(payload, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
        return hashlib.sha256(text.encode("ascii")).hexdigest()[:16]
