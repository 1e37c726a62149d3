"""benchmarks.rosbag_read: its floors read every message of the bag the source reads, and the bag it writes (the
numeric topics serialised a topic at a time) carries the stroke it was given."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.rosbag_read import read_deserialized, read_raw, read_source, stroke, write
from drivers.rosbag_source import scan_bag


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_the_floors_and_the_source_read_the_same_bag(storage, tmp_path):
    accel, force, speed, jpeg = stroke(2.0)
    bag = write(tmp_path, storage, accel, force, speed, jpeg)
    n = 2000 + 1000 + 200 + 10  # IMU 1 kHz, wrench 500 Hz, twist 100 Hz, camera 5 Hz over 2 s
    assert read_raw(bag) == read_deserialized(bag) == n
    scan = scan_bag(bag)
    np.testing.assert_array_equal(scan.channels["accel"].values, accel)
    np.testing.assert_array_equal(scan.channels["force"].values, force[::2])
    np.testing.assert_allclose(scan.channels["speed"].values[:, 0], speed[::10], rtol=1e-12)
    assert scan.frames is not None and scan.frames.stamps_ns.shape == (10,)
    assert read_source(bag) > 10
