"""The demo's per-probe report: the estimate after REPORT_AFTER_S of each probe's stroke against its truth."""

import pytest

from demo.run import SCENE_GAP_S, ProbeReport, rating_error
from texture_library.attributes import ATTRIBUTES


def _r(*values):
    return dict(zip(ATTRIBUTES, map(float, values)))


def test_rating_error_is_the_mean_over_attributes_on_the_0_100_scale():
    assert rating_error(_r(10, -10, 0, 40), _r(0, 0, 0, 0)) == pytest.approx((5 + 5 + 0 + 20) / 4)


def test_each_probe_is_reported_once_when_its_stroke_passes_the_mark():
    truth = {"a": _r(0, 0, 0, 0), "b": _r(50, 50, 50, 50)}
    report = ProbeReport(["a", "b"], truth, per_texture_s=8.0, after_s=2.0)
    # probe a: windows ending 0.5 … 2.0 s; the console's smoothed estimate and the raw window estimates
    assert report.add(0.5, _r(8, 8, 8, 8), _r(8, 8, 8, 8)) == []
    assert report.add(1.0, _r(6, 6, 6, 6), _r(4, 4, 4, 4)) == []
    assert report.add(1.5, _r(5, 5, 5, 5), _r(4, 4, 4, 4)) == []
    lines = report.add(2.0, _r(4, 4, 4, 4), _r(0, 0, 0, 0))
    assert lines and lines[0].startswith("── a, 2.0 s into its stroke")
    assert "error   2.0" in lines[1]  # console estimate 4 bipolar → 2 points
    assert "error   2.0" in lines[2]  # mean of windows (8 + 4 + 4 + 0) / 4 = 4 → 2 points
    assert report.add(2.5, _r(0, 0, 0, 0), _r(0, 0, 0, 0)) == []  # reported once
    # probe b starts after the first probe's stroke and the gap; its clock restarts there
    start_b = 8.0 + SCENE_GAP_S
    assert report.add(start_b + 1.5, _r(50, 50, 50, 50), _r(50, 50, 50, 50)) == []
    lines = report.add(start_b + 2.0, _r(30, 50, 50, 50), _r(50, 50, 50, 50))
    assert lines[0].startswith("── b") and "error   2.5" in lines[1] and "error   0.0" in lines[2]
    assert report.errors == [("a", 2.0, 2.0), ("b", 2.5, 0.0)]
    assert "2 probe stroke(s): mean error 2.2 (console estimate), 1.0 (mean of windows)" in report.summary()


def test_nothing_to_summarise_before_the_first_report():
    assert ProbeReport(["a"], {"a": _r(0, 0, 0, 0)}, per_texture_s=3.0).summary() is None
