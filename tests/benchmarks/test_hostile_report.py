"""The hostile-client probe's report helpers: its timeline bins and its chart (the probe itself is a benchmark, run
by hand: `python -m benchmarks.hostile`)."""

from __future__ import annotations

import json

import pytest

from benchmarks.hostile_chart import chart, parse_report
from benchmarks.service import timeline


def test_the_timeline_bins_windows_by_arrival_with_their_percentiles():
    t0 = 100.0
    e2e = [(100.5, 10.0), (101.9, 30.0), (102.0, 1000.0), (107.1, 7.0)]  # (arrival, ms)
    bins = timeline(e2e, t0, bin_s=2.0)
    assert [b["t_s"] for b in bins] == [0.0, 2.0, 4.0, 6.0]  # 102.0 opens the second bin
    assert [b["windows"] for b in bins] == [2, 1, 0, 1]  # a bin no window reached stays, empty
    assert bins[0]["e2e_p50"] == pytest.approx(20.0) and bins[1]["e2e_p99"] == pytest.approx(1000.0)
    assert bins[2]["e2e_p50"] is None and timeline([], t0) == []


def _report() -> dict:
    return {
        "robots": 2,
        "health_ms": {"p50": 2.0, "p99": 30.0, "max": 120.0},
        "phases_s": {"attacks": [3.0, 6.0], "burst_streaming": [12.0, 32.0]},
        "well_behaved": {"robot_counts": {"reconnects": 0}},
        "well_behaved_timeline": [
            {"t_s": 0.0, "windows": 4, "e2e_p50": 8.0, "e2e_p99": 30.0},
            {"t_s": 2.0, "windows": 0, "e2e_p50": None, "e2e_p99": None},
            {"t_s": 4.0, "windows": 4, "e2e_p50": 9.0, "e2e_p99": 150.0},
        ],
    }


def test_the_chart_draws_one_panel_per_report_and_names_a_report_it_cannot_draw(tmp_path):
    good = tmp_path / "hostile.json"
    good.write_text(json.dumps(_report()))
    out = chart([parse_report(f"before={good}"), parse_report(str(good))], tmp_path / "chart.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert parse_report(str(good))[0] == "hostile"  # unlabelled: the file's name
    old = tmp_path / "old.json"
    old.write_text(json.dumps({k: v for k, v in _report().items() if k != "well_behaved_timeline"}))
    with pytest.raises(ValueError, match="old.json has no well_behaved_timeline"):
        parse_report(str(old))
