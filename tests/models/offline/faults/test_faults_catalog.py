"""The fault catalog: every studied fault applies at every strength, and the trajectory faults
re-render the dataset's own stroke."""

import numpy as np
import pytest

from models.offline.datasets.simulate import simulated_recording, texture_rng
from models.offline.faults.catalog import (
    FAULTS,
    TRAJECTORY_FAULTS,
    apply_camera,
    apply_touch,
    fault,
    trajectory_transform,
)
from texture_library.procedural import sample_params, vibration_model


@pytest.fixture(scope="module")
def vib():
    rng = np.random.default_rng(3)
    return vibration_model(sample_params(rng), "t", rng)


@pytest.fixture(scope="module")
def segment(vib):
    return simulated_recording(vib, 4.0, texture_rng(0, "t"))


def test_strengths_run_from_mild_to_severe_and_exclude_the_clean_value():
    for f in FAULTS.values():
        assert f.family in ("touch", "camera")
        assert f.clean not in f.strengths and len(f.strengths) >= 1
        distance = [abs(np.log(s / f.clean)) if f.clean not in (0, np.inf) and s > 0 else abs(s) for s in f.strengths]
        if f.name == "noise":  # SNR: lower is worse
            assert list(f.strengths) == sorted(f.strengths, reverse=True)
        elif f.name != "no_frame":
            assert distance == sorted(distance), f.name


@pytest.mark.parametrize("name", [n for n, f in FAULTS.items() if f.family == "touch" and n not in TRAJECTORY_FAULTS])
def test_every_segment_touch_fault_changes_the_recording(name, segment):
    for s in FAULTS[name].strengths:
        out = apply_touch(name, s, segment, np.random.default_rng(0))
        assert out.accel.data.shape[1] == 3
        if name == "gap":
            # the same stretch of time is lost from every channel
            lost = segment.accel.data.shape[0] - out.accel.data.shape[0]
            assert lost > 0 and lost == segment.speed.data.shape[0] - out.speed.data.shape[0]
        elif name.startswith("rate"):
            assert out.accel.data.shape[0] != segment.accel.data.shape[0]
        else:
            assert out.accel.data.shape == segment.accel.data.shape
            assert not np.allclose(out.accel.data, segment.accel.data)
            np.testing.assert_array_equal(out.force.data, segment.force.data)


def test_identity_transform_reproduces_the_dataset_stroke_and_scaling_changes_it(vib, segment):
    same = simulated_recording(vib, 4.0, texture_rng(0, "t"), transform=lambda tr: tr)
    np.testing.assert_array_equal(same.accel.data, segment.accel.data)
    fast = simulated_recording(vib, 4.0, texture_rng(0, "t"), transform=trajectory_transform("speed_fast", 4))
    np.testing.assert_allclose(fast.speed.data, 4 * segment.speed.data, rtol=1e-6)
    hard = simulated_recording(vib, 4.0, texture_rng(0, "t"), transform=trajectory_transform("force_high", 2))
    np.testing.assert_allclose(hard.force.data[:, 2].mean(), 2 * segment.force.data[:, 2].mean(), rtol=0.01)
    assert not np.allclose(hard.accel.data, segment.accel.data)  # the vibration itself is re-rendered


@pytest.mark.parametrize("name", [n for n, f in FAULTS.items() if f.family == "camera" and n != "no_frame"])
def test_every_camera_fault_changes_the_image(name):
    rng = np.random.default_rng(0)
    img = np.clip(0.5 + 0.2 * rng.standard_normal((64, 64)), 0, 1).astype(np.float32)
    for s in FAULTS[name].strengths:
        out = apply_camera(name, s, img, np.random.default_rng(1))
        assert out.shape == img.shape and out.dtype == np.float32 and not np.allclose(out, img)


def test_unknown_and_misplaced_faults_are_named():
    with pytest.raises(ValueError, match="unknown fault"):
        fault("lightning")
    with pytest.raises(ValueError, match="not an image fault"):
        apply_camera("noise", 10, np.zeros((8, 8), np.float32), np.random.default_rng())
    with pytest.raises(ValueError, match="trajectory"):
        trajectory_transform("blur", 2)
