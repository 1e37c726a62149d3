"""The extra feature groups (friction, spatial, taps) in the one feature implementation:
configuration, the preprocessor's derived columns, window_features' layout, and the promise that
the default configuration (and its hash, caches and exported models) does not change."""

import json

import numpy as np
import pytest

from models.tactile.config import EXTRA_GROUPS, TactileConfig
from models.tactile.features import recording_features, window_features
from models.tactile.friction import friction_features
from models.tactile.preprocess import TactilePreprocessor
from models.tactile.spatial import spatial_features
from models.tactile.stream import StreamContract
from models.tactile.taps import TAP_NAMES
from texture_library.recording import Channel

ALL = TactileConfig(extra_groups=EXTRA_GROUPS)
#: TactileConfig().hash() before the extra groups existed: caches and exported models key on it
DEFAULT_HASH = "ad3c9b668f454d02"


def test_default_configuration_keeps_its_hash_and_fields():
    c = TactileConfig()
    assert c.hash() == DEFAULT_HASH
    assert "extra_groups" not in c.to_dict() and "spatial_dx_mm" not in c.to_dict()
    assert c.n_features == 526 and c.accel_columns == 3 and c.force_columns == 1


def test_groups_are_kept_in_canonical_order_and_hash_as_one():
    a = TactileConfig(extra_groups=("taps", "friction"))
    b = TactileConfig(extra_groups=["friction", "taps"])
    assert a.extra_groups == b.extra_groups == ("friction", "taps")
    assert a.hash() == b.hash() != TactileConfig().hash()
    assert TactileConfig(**json.loads(json.dumps(a.to_dict()))) == a
    assert (
        TactileConfig(extra_groups=("spatial",), spatial_bands=8).hash()
        != TactileConfig(extra_groups=("spatial",)).hash()
    )


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"extra_groups": ("friction", "texture")}, "unknown feature group"),
        ({"extra_groups": ("friction", "friction")}, "repeats a group"),
        ({"spatial_dx_mm": 0.6}, "cannot resolve"),
        ({"spatial_max_period_mm": 100.0}, "spatial_max_period_mm ≤"),
        ({"spatial_bands": 0}, "spatial_bands must be ≥ 1"),
        ({"spatial_bands": 40}, "narrower than one bin"),
        ({"spatial_highpass_hz": 0.0}, "spatial_highpass_hz"),
    ],
)
def test_bad_group_settings_name_the_problem(kwargs, message):
    with pytest.raises(ValueError, match=message):
        TactileConfig(**kwargs)


def test_layout_names_and_slices():
    names = ALL.feature_names
    slices = ALL.group_slices()
    assert len(names) == len(set(names)) == ALL.n_features == 526 + 2 + 22 + 3
    assert list(slices) == ["base", "friction", "spatial", "taps"]
    assert names[slices["friction"]] == ["friction_ratio", "friction_ratio_std"]
    assert names[slices["taps"]] == list(TAP_NAMES)
    assert (
        names[slices["spatial"]][0] == "spatial_accel_32-22.6mm"
        and names[slices["spatial"]][-1] == "spatial_force_rms_n"
    )
    assert slices["taps"].stop == ALL.n_features and (ALL.accel_columns, ALL.force_columns) == (6, 2)


def _stroke(make_recording, duration=2.2):
    return make_recording(duration, 2000.0, 1000.0, 500.0, force_axes=3, seed=5)


def test_derived_columns_and_unchanged_base_columns(make_recording):
    """Derived streams appear only as extra columns; the MFCC columns and the statistics are
    bit-identical with and without the groups."""
    rec = _stroke(make_recording)
    taps = np.array([0.1, -2.3, 150.0])
    base, t0 = recording_features(rec, TactileConfig())
    full, t1 = recording_features(rec, ALL, taps=taps)
    np.testing.assert_array_equal(full[:, :526], base)
    np.testing.assert_array_equal(t0, t1)
    np.testing.assert_allclose(full[:, ALL.group_slices()["taps"]], np.tile(taps, (len(full), 1)), rtol=1e-6)

    pre = TactilePreprocessor(ALL, max_buffer_s=None)
    pre.push(**rec.channels())
    pre.flush()
    batch = pre.take()
    assert batch.accel.shape == (len(full), 500, 6) and batch.force.shape == (len(full), 500, 2)
    plain = TactilePreprocessor(TactileConfig(), max_buffer_s=None)
    plain.push(**rec.channels())
    plain.flush()
    ref = plain.take()
    np.testing.assert_array_equal(batch.accel[:, :, :3], ref.accel)
    np.testing.assert_array_equal(batch.force[:, :, 0], ref.force)
    # the friction and spatial columns are exactly the pure functions on the derived columns
    np.testing.assert_allclose(
        full[:, ALL.group_slices()["friction"]],
        friction_features(batch.force[:, :, 0], batch.force[:, :, 1]),
        rtol=1e-6,
    )
    np.testing.assert_allclose(
        full[:, ALL.group_slices()["spatial"]],
        spatial_features(batch.accel[:, :, 3:], batch.force[:, :, 0], batch.speed, 1000.0),
        rtol=1e-5,
    )


def test_tangential_magnitude_and_slow_accel_streams(make_recording):
    """Tangential = √(fx² + fy²) (low-passed like the normal force); the spatial accel keeps the
    slow content the 20 Hz high-pass removes, and loses gravity."""
    n = 3000
    t = np.arange(n) / 1000.0
    accel = np.zeros((n, 3))
    accel[:, 2] = 9.81 + 1.0 * np.sin(2 * np.pi * 4.0 * t)  # gravity + a 4 Hz bump hum (2 cycles a window)
    force = np.column_stack([np.full(n, 0.3), np.full(n, -0.4), np.full(n, 1.0)])
    pre = TactilePreprocessor(TactileConfig(extra_groups=("friction", "spatial")), max_buffer_s=None)
    pre.push(accel=Channel(accel, 1000.0), force=Channel(force, 1000.0), speed=Channel(np.full(n, 100.0), 1000.0))
    pre.flush()
    b = pre.take()
    np.testing.assert_allclose(b.force[:, :, 1], 0.5, atol=1e-9)
    last = b.accel[-1]
    assert np.std(last[:, 2]) < 0.1  # 20 Hz high-pass: the hum is gone
    assert np.std(last[:, 5]) == pytest.approx(1 / np.sqrt(2), rel=0.1)  # spatial stream: it stays
    assert abs(np.mean(last[:, 5])) < 0.1  # … and gravity does not


def test_friction_needs_three_column_force(make_recording):
    rec = make_recording(1.2, force_axes=1)
    pre = TactilePreprocessor(TactileConfig(extra_groups=("friction",)))
    with pytest.raises(ValueError, match="friction features need 3-column force"):
        pre.push(**rec.channels())
    # the stream contract says so, so service admission refuses the block before the preprocessor sees it
    contract = StreamContract(TactileConfig(extra_groups=("friction",)))
    cursor = contract.start()
    with pytest.raises(ValueError, match="friction features need 3-column force"):
        contract.admit(cursor, rec.channels(), 0.0)
    assert (
        contract.admit(cursor, {**rec.channels(), "force": Channel(np.zeros((1200, 3)), 1000.0)}, 0.0).windows_added
        == 2
    )
    # without the friction group 1-column force is fine, with spatial or taps alike
    assert recording_features(rec, TactileConfig(extra_groups=("spatial",)))[0].shape == (2, 526 + 22)


def test_window_features_checks_the_groups_inputs():
    L = 500
    rng = np.random.default_rng(0)
    accel6, force2, speed = rng.standard_normal((2, L, 6)), 1 + rng.random((2, L, 2)), 50 + rng.random((2, L))
    cfg = TactileConfig(extra_groups=("friction", "spatial"))
    assert window_features(accel6, speed, force2, cfg).shape == (2, cfg.n_features)
    with pytest.raises(ValueError, match=r"accel must have shape \(n, 500, 6\)"):
        window_features(accel6[:, :, :3], speed, force2, cfg)
    with pytest.raises(ValueError, match=r"force must have shape \(2, 500, 2\)"):
        window_features(accel6, speed, force2[:, :, 0], cfg)
    with pytest.raises(ValueError, match="pass taps"):
        window_features(accel6, speed, force2, ALL)
    with pytest.raises(ValueError, match="no taps group"):
        window_features(accel6, speed, force2, cfg, np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"taps must have shape \(2, 3\)"):
        window_features(accel6, speed, force2, ALL, np.zeros((1, 3)))
