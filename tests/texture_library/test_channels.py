"""The one validator of samples, arrays and sample rates (texture_library.channels)."""

import numpy as np
import pytest

from texture_library.channels import check_array, check_channel, check_rate


@pytest.mark.parametrize(
    ("rate", "message"),
    [
        ("100", r"accel: sample rate must be a finite number, got '100'"),
        (True, r"accel: sample rate must be a finite number, got True"),
        (float("inf"), r"accel: sample rate must be a finite number, got inf"),
        (5, r"accel: sample rate must lie in \[10, 100000\] Hz, got 5"),
    ],
)
def test_a_bad_rate_is_named(rate, message):
    with pytest.raises(ValueError, match=message):
        check_rate(rate, "accel")


def test_a_good_rate_comes_back_as_float():
    assert check_rate(np.int64(1000), "accel") == 1000.0 and isinstance(check_rate(10, "x"), float)


def test_arrays_are_checked_for_numbers_shape_and_finiteness():
    x = np.zeros((3, 5), np.float32)
    assert check_array("w", x, (None, 5), dtype=np.float32) is x  # no copy when nothing changes
    assert check_array("w", np.zeros((3, 5), int), (3, 5)).dtype == np.float64
    with pytest.raises(ValueError, match=r"w must have shape \(n, 4\), got \(3, 5\)"):
        check_array("w", x, (None, 4))
    with pytest.raises(ValueError, match=r"w must have shape \(n, 5\), got \(5,\)"):
        check_array("w", x[0], (None, 5))
    with pytest.raises(ValueError, match="w must be real numbers, got dtype <U1"):
        check_array("w", np.array([["a"]]), (None, 1))
    bad = x.copy()
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"w has 1 NaN or Inf value\(s\)"):
        check_array("w", bad, (None, 5))


def test_a_streaming_block_may_be_empty_a_recording_may_not():
    empty = np.zeros((0, 3))
    assert check_channel("accel", empty, 1000.0, allow_empty=True)[0].shape == (0, 3)
    with pytest.raises(ValueError, match="accel: no samples"):
        check_channel("accel", empty, 1000.0)


def test_a_sample_beyond_any_sensors_range_is_refused_in_canonical_units():
    from texture_library.channels import MAX_ABS

    accel = np.zeros((10, 3))
    accel[4, 1] = -2e15  # finite, even in float32, but it would overflow the features
    with pytest.raises(ValueError, match=r"accel: acceleration 2e\+15 m/s\^2 is outside its physical range, magn"):
        check_channel("accel", accel, 1000.0)
    edge = np.full((4, 3), MAX_ABS["accel"])
    assert check_channel("accel", edge, 1000.0)[0].max() == MAX_ABS["accel"]  # the bound itself passes
    in_g = np.full((4, 3), MAX_ABS["accel"] / 9.0)  # within the bound as a number, beyond it in m/s²
    with pytest.raises(ValueError, match="accel: acceleration 2179 m/s\\^2 is outside its physical range"):
        check_channel("accel", in_g, 1000.0, "g")
    with pytest.raises(ValueError, match=r"force: force 1e\+19 N is outside its physical range, magnitude at most 200"):
        check_channel("force", np.array([1.0, 1e19]), 1000.0)


def test_taps_are_bounded_as_accel_is():
    from texture_library.taps import TapSet

    accel = np.zeros((2, 50))
    accel[1, 7] = 3e5
    with pytest.raises(ValueError, match=r"taps: acceleration 3e\+05 m/s\^2 is outside its physical range"):
        TapSet(np.array([20.0, 40.0]), accel)
