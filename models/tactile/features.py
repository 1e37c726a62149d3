"""Per-window tactile features: THE function training and serving both call.

window_features(accel, speed, force, config), per window:
  1. DFT321 folds the high-passed 3-axis acceleration into one signal;
  2. the configured feature set of that signal:
       "mfcc" → (n_frames × n_mfcc) MFCC, frame-major (mfcc_f00_c00, mfcc_f00_c01, …), 520 values;
       "dwt"  → per-band DWT statistics (models.tactile.dwt), 18 values;
       "dft"  → log band-mean DFT magnitudes (models.tactile.dft), 32 values;
  3. then min, max, mean of speed (mm/s) and of normal force (N): 6 values;
  4. then each extra group of ``config.extra_groups`` (columns per ``config.group_slices()``):
       "friction" → models.tactile.friction on force[..., 0] (normal) and force[..., 1] (tangential);
       "spatial"  → models.tactile.spatial on accel[..., 3:6] (high-passed against gravity only), the
                    normal force and speed;
       "taps"     → the texture's tap features (models.tactile.taps.tap_features), given per window
                    as ``taps`` (n, 3): a per-texture block, the same on each of its windows.
Returned as float32, columns named by ``config.feature_names``. The MFCC/DWT/DFT columns and
the statistics do not depend on the extra groups.

recording_features runs the streaming TactilePreprocessor over a whole recording (one
block, then ``flush`` since the recording's end is known; the same code serving runs block by
block) and applies window_features.
"""

from __future__ import annotations

import math

import numpy as np

from models.tactile.config import TactileConfig
from models.tactile.dft import dft_features
from models.tactile.dft321 import dft321
from models.tactile.dwt import dwt_features
from models.tactile.friction import friction_features
from models.tactile.mfcc import mfcc
from models.tactile.preprocess import TactilePreprocessor
from models.tactile.spatial import spatial_features
from models.tactile.taps import TAP_NAMES
from texture_library.channels import check_array
from texture_library.recording import Recording

#: windows per block inside window_features (keeps temporaries in cache; results equal up to float32 rounding)
CHUNK = 64


def speed_force_stats(speed: np.ndarray, force: np.ndarray) -> np.ndarray:
    """(n, L) mm/s and (n, L) N → (n, 6): speed min, max, mean, force min, max, mean."""
    both = np.stack([speed, force], axis=1)  # (n, 2, L)
    stats = np.stack([both.min(axis=2), both.max(axis=2), both.mean(axis=2)], axis=2)  # (n, 2, 3)
    return stats.reshape(-1, 6)


def window_features(
    accel: np.ndarray, speed: np.ndarray, force: np.ndarray, config: TactileConfig, taps: np.ndarray | None = None
) -> np.ndarray:
    """Features of n windows. accel: (n, L, 3) m/s² — (n, L, 6) with the spatial group; speed: (n, L)
    mm/s; force: (n, L) N — (n, L, 2) (normal, tangential) with the friction group; taps: (n, 3) per
    window with the taps group, else None; L = config.window_length → (n, config.n_features) float32.
    The preprocessor's windows (models.tactile.preprocess) have exactly these shapes for `config`."""
    L = config.window_length
    accel = check_array("accel", accel, (None, L, config.accel_columns))
    n = accel.shape[0]
    speed = check_array("speed", speed, (n, L))
    force = check_array("force", force, (n, L) if config.force_columns == 1 else (n, L, config.force_columns))
    if ("taps" in config.extra_groups) != (taps is not None):
        raise ValueError(
            "this configuration has the taps group: pass taps (n, 3) from tap_features"
            if taps is None
            else "taps given, but this configuration has no taps group"
        )
    normal = force if force.ndim == 2 else force[:, :, 0]
    out = np.empty((n, config.n_features), dtype=np.float32)
    for lo in range(0, n, CHUNK):  # blocks of windows keep the temporaries in cache
        hi = min(n, lo + CHUNK)
        folded = dft321(accel[lo:hi, :, :3])  # (m, L)
        if config.feature_set == "mfcc":
            out[lo:hi, : config.n_tactile] = mfcc(folded, config).reshape(hi - lo, -1)
        elif config.feature_set == "dwt":
            out[lo:hi, : config.n_tactile] = dwt_features(folded, config)
        else:
            out[lo:hi, : config.n_tactile] = dft_features(folded, config)
    groups = config.group_slices()
    out[:, config.n_tactile : groups["base"].stop] = speed_force_stats(speed, normal)
    if "friction" in groups:
        out[:, groups["friction"]] = friction_features(normal, force[:, :, 1])
    if "spatial" in groups:
        out[:, groups["spatial"]] = spatial_features(
            accel[:, :, 3:],
            normal,
            speed,
            config.rate_hz,
            dx_mm=config.spatial_dx_mm,
            n_fft=config.spatial_n_fft,
            min_period_mm=config.spatial_min_period_mm,
            max_period_mm=config.spatial_max_period_mm,
            n_bands=config.spatial_bands,
            min_speed=config.spatial_min_speed,
        )
    if taps is not None:  # exactly when the configuration has the taps group (checked above)
        out[:, groups["taps"]] = check_array("taps", taps, (n, len(TAP_NAMES)))
    return out


def recording_features(
    recording: Recording,
    config: TactileConfig,
    skip_s: float = 0.0,
    stop_s: float | None = None,
    taps: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Features of every window of a recording → (features (n_win, n_features) float32, t_start (n_win,) s).

    Windows start at skip_s + i·hop_s and must end by stop_s (s from the recording start;
    None = its end). taps: (3,) the texture's tap features, needed with the taps group.
    ValueError if no complete window fits.
    """
    if not isinstance(recording, Recording):
        raise ValueError(f"recording must be a texture_library.recording.Recording, got {type(recording).__name__}")
    if stop_s is not None and not (math.isfinite(stop_s) and stop_s > skip_s):
        raise ValueError(f"stop_s must be a finite time > skip_s = {skip_s} s, got {stop_s!r}")
    pre = TactilePreprocessor(config, skip_s=skip_s, max_buffer_s=None)
    pre.push(accel=recording.accel, force=recording.force, speed=recording.speed, position=recording.position)
    pre.flush()  # the recording ends here: its last samples are known
    batch = pre.take()
    keep = np.ones(len(batch), dtype=bool)
    if stop_s is not None:
        keep = batch.t_start_s + config.window_s <= stop_s + 0.5 / config.rate_hz
    if not keep.any():
        end = recording.duration_s if stop_s is None else min(stop_s, recording.duration_s)
        raise ValueError(
            f"recording: {max(0.0, end - skip_s):g} s between skip_s={skip_s:g} s and {end:g} s holds no "
            f"complete {config.window_s:g} s window"
        )
    tap_rows = None if taps is None else np.tile(np.asarray(taps, np.float64).reshape(1, -1), (int(keep.sum()), 1))
    feats = window_features(batch.accel[keep], batch.speed[keep], batch.force[keep], config, tap_rows)
    return feats, batch.t_start_s[keep]
