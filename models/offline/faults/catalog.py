"""The faults of the robustness study by name, each with its strengths ordered from mild to severe.

The apply functions take any strength their fault function accepts (training-time augmentation
uses strengths between the studied ones).

Touch faults act on a recording segment (a `Recording` cut from the dataset's stroke); the
speed and force faults re-render the whole stroke from the texture's vibration model along the
scaled trajectory (the faithful way: the vibration, not just the statistics, changes) and cut
the same segment. Camera faults act on the grayscale image. `no_frame` has no function: the
model gets no visual input at all.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np

from models.offline.faults import camera, touch
from texture_library.recording import Channel, Recording

SEGMENT_EVERY_S = 1.0  # dropouts and gaps recur once a second, so every 0.5 s window meets about half of one


@dataclass(frozen=True)
class Fault:
    """name: key; family: "touch" | "camera"; label and unit for plots; strengths: mild → severe;
    clean: the strength that means no fault (the curves start there)."""

    name: str
    family: str
    label: str
    unit: str
    strengths: tuple[float, ...]
    clean: float


FAULTS: dict[str, Fault] = {
    f.name: f
    for f in (
        Fault("noise", "touch", "additive noise", "SNR dB", (40, 30, 20, 10, 5, 0), math.inf),
        Fault("clipping", "touch", "clipping", "fraction of range kept", (0.5, 0.25, 0.1), 1.0),
        Fault("dropout", "touch", "dropouts (sensor holds its value), one per second", "ms", (10, 20, 50, 100, 200), 0),
        Fault("gap", "touch", "gaps (samples lost), one per second", "ms", (10, 20, 50, 100, 200), 0),
        Fault("rate_fast", "touch", "accelerometer clock fast", "% rate error", (5, 10, 20), 0),
        Fault("rate_slow", "touch", "accelerometer clock slow", "% rate error", (-5, -10, -20), 0),
        Fault("speed_fast", "touch", "strokes faster than in training", "× speed", (2, 4), 1),
        Fault("speed_slow", "touch", "strokes slower than in training", "× speed", (0.5, 0.25), 1),
        Fault("force_high", "touch", "pressing harder than in training", "× force", (2, 4), 1),
        Fault("force_low", "touch", "pressing lighter than in training", "× force", (0.5, 0.25), 1),
        Fault("orientation", "touch", "accelerometer mounted turned", "degrees", (30, 90, 180), 0),
        Fault("bias", "touch", "accelerometer bias", "m/s²", (1, 5, 20, 100), 0),
        Fault("drift", "touch", "accelerometer drift", "m/s² per s", (0.1, 1, 10), 0),
        Fault("blur", "camera", "blur", "σ px", (2, 4, 8, 16), 0),
        Fault("underexposure", "camera", "under-exposure", "gain", (0.5, 0.25, 0.1), 1),
        Fault("overexposure", "camera", "over-exposure", "gain", (2, 4), 1),
        Fault("image_noise", "camera", "sensor noise", "std (of 1)", (0.05, 0.1, 0.2), 0),
        Fault("jpeg", "camera", "JPEG compression", "quality", (20, 10, 5), 100),
        Fault("rotation", "camera", "camera rotation", "degrees", (30, 90), 0),
        Fault("closer", "camera", "camera closer (surface magnified)", "× scale", (1.4, 2.0), 1),
        Fault("farther", "camera", "camera farther (surface shrunk)", "× scale", (0.7, 0.5), 1),
        Fault("occlusion", "camera", "occlusion", "fraction of frame", (0.25, 0.5), 0),
        Fault("no_frame", "camera", "no frame at all (tactile-only fallback)", "", (1,), 0),
    )
}
TRAJECTORY_FAULTS = ("speed_fast", "speed_slow", "force_high", "force_low")
ORIENTATION_AXIS = np.array([1.0, 2.0, 3.0])  # a fixed, generic axis (not a sensor axis)


def fault(name: str) -> Fault:
    if name not in FAULTS:
        raise ValueError(f"unknown fault {name!r}; known: {', '.join(FAULTS)}")
    return FAULTS[name]


def trajectory_transform(name: str, strength: float) -> Callable:
    """The trajectory change of a speed/force fault (for models.offline.datasets.simulate.simulated_recording)."""
    fault(name)
    if name not in TRAJECTORY_FAULTS:
        raise ValueError(f"fault {name!r} does not change the trajectory")
    key = "speed_factor" if name.startswith("speed") else "force_factor"
    return partial(touch.scale_trajectory, **{key: float(strength)})


def _accel_fault(
    name: str, strength: float, rate_hz: float, rng: np.random.Generator
) -> Callable[[np.ndarray], np.ndarray]:
    if name == "noise":
        return lambda a: touch.add_noise(a, strength, rng)
    if name == "clipping":
        return lambda a: touch.clip_range(a, strength)
    if name == "dropout":
        return lambda a: touch.dropout_hold(
            a, touch.periodic_segments(len(a), rate_hz, strength / 1e3, SEGMENT_EVERY_S)
        )
    if name in ("rate_fast", "rate_slow"):
        return lambda a: touch.rate_mismatch(a, strength / 100)
    if name == "orientation":
        return lambda a: touch.rotate_sensor(a, strength, ORIENTATION_AXIS)
    if name == "bias":
        return lambda a: touch.add_bias(a, strength)
    if name == "drift":
        return lambda a: touch.add_drift(a, rate_hz, strength)
    raise ValueError(f"fault {name!r} is not an acceleration fault")


def apply_touch(name: str, strength: float, segment: Recording, rng: np.random.Generator) -> Recording:
    """A recording segment under a touch fault (not the trajectory faults: see trajectory_transform).

    Acceleration faults change the accel channel only; a gap removes the same stretch of time
    from every channel (they are lost together in transit)."""
    f = fault(name)
    if f.family != "touch" or name in TRAJECTORY_FAULTS:
        raise ValueError(f"fault {name!r} is not a segment touch fault")
    accel = segment.accel
    if name == "gap":

        def cut(ch: Channel | None) -> Channel | None:
            if ch is None:
                return None
            mask = touch.periodic_segments(ch.data.shape[0], ch.rate_hz, strength / 1e3, SEGMENT_EVERY_S)
            return Channel(touch.remove_gaps(ch.data, mask), ch.rate_hz)

        return Recording(cut(segment.accel), cut(segment.force), cut(segment.speed), cut(segment.position))
    changed = _accel_fault(name, strength, accel.rate_hz, rng)(accel.data)
    return Recording(Channel(changed, accel.rate_hz), segment.force, segment.speed, segment.position)


def apply_camera(name: str, strength: float, img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The image under a camera fault (every camera fault but no_frame)."""
    f = fault(name)
    if f.family != "camera" or name == "no_frame":
        raise ValueError(f"fault {name!r} is not an image fault")
    if name == "blur":
        return camera.blur(img, strength)
    if name in ("underexposure", "overexposure"):
        return camera.exposure(img, strength)
    if name == "image_noise":
        return camera.sensor_noise(img, strength, rng)
    if name == "jpeg":
        return camera.jpeg(img, int(strength))
    if name == "rotation":
        return camera.rotate(img, strength)
    if name in ("closer", "farther"):
        return camera.distance(img, strength)
    return camera.occlude(img, strength)
