"""The crowd case's figures (`python -m benchmarks.hostile --case crowd`, run by hand): known answers for a robot's
longest gap without a window and a histogram's quantile, and the report file keeping the other cases' objects."""

from __future__ import annotations

import json
import math

import pytest

from benchmarks.hostile import histogram_quantile, robot_gap_s
from benchmarks.report_file import write_section


def test_a_robots_longest_gap_counts_from_its_first_windows_due_time_to_its_streams_end():
    # stream from 10 s for 5 s, first window due at 11 s: windows at 11.2, 11.7, 14.5 → gaps 0.2, 0.5, 2.8, then 0.5
    assert robot_gap_s(10.0, [11.7, 11.2, 14.5], 5.0, 1.0) == pytest.approx(2.8)
    assert robot_gap_s(10.0, [11.1, 11.6], 5.0, 1.0) == pytest.approx(15.0 - 11.6)  # the end of the stream counts
    assert robot_gap_s(10.0, [], 5.0, 1.0) == pytest.approx(4.0)  # no window at all: the whole stream
    assert robot_gap_s(10.0, [11.0, 16.0], 5.0, 1.0) == pytest.approx(5.0)  # a late last window


def test_the_histograms_quantile_is_the_first_bucket_holding_that_share():
    text = "\n".join(
        [
            "# HELP hapticlink_readmit_seconds x",
            'hapticlink_readmit_seconds_bucket{le="0.5"} 10.0',
            'hapticlink_readmit_seconds_bucket{le="1.0"} 98.0',
            'hapticlink_readmit_seconds_bucket{le="2.0"} 100.0',
            'hapticlink_readmit_seconds_bucket{le="+Inf"} 100.0',
            "hapticlink_readmit_seconds_count 100.0",
        ]
    )
    assert histogram_quantile(text, "hapticlink_readmit_seconds", 0.5) == (1.0, 100)
    assert histogram_quantile(text, "hapticlink_readmit_seconds", 0.99) == (2.0, 100)
    beyond = text.replace('le="2.0"} 100.0', 'le="2.0"} 98.0')
    assert histogram_quantile(beyond, "hapticlink_readmit_seconds", 0.99) == (math.inf, 100)
    assert histogram_quantile("", "hapticlink_readmit_seconds", 0.99) == (None, 0)


def test_writing_the_crowd_object_keeps_the_other_cases_objects(tmp_path):
    """Each case's section carries its own host and provenance: the file's other sections were run at other times."""
    path = tmp_path / "hostile.json"
    path.write_text(json.dumps({"health_ms": {"p99": 13.0}, "restart": {"robots": 3}}))
    write_section(path, "crowd", {"max_robot_gap_s": 1.5, "command": "python -m benchmarks.hostile --case crowd"})
    report = json.loads(path.read_text())
    assert report["health_ms"] == {"p99": 13.0} and report["restart"] == {"robots": 3}
    crowd = report["crowd"]
    assert crowd["max_robot_gap_s"] == 1.5 and crowd["host"]["model"]
    assert crowd["provenance"]["command"] == "python -m benchmarks.hostile --case crowd"
    assert crowd["provenance"]["inputs"] == []
    write_section(tmp_path / "new.json", "crowd", {"x": 1})
    assert set(json.loads((tmp_path / "new.json").read_text())) == {"crowd"}
