"""The service benchmark's chart: rows grouped per configuration and replica count, in order of robots, and a PNG."""

from __future__ import annotations

import pytest

from benchmarks.service_chart import Point, chart, curves, main


def _row(config: str, robots: int, replicas: int, p99: float, cpu: float, valid: bool = True) -> dict:
    return {
        "config": config,
        "robots": robots,
        "replicas": replicas,
        "e2e_ms": {"p50": p99 / 2, "p99": p99},
        "service_cpu_ms_per_robot_s": cpu,
        "valid": valid,
    }


REPORT = {
    "machine": {"cpus": 2, "load_average_before": [0.5, 0.5, 0.5]},
    "results": [
        _row("served", 10, 1, 7.0, 14.0),
        _row("served", 1, 1, 9.0, 26.0),
        _row("served", 200, 2, 115.0, 6.9, valid=False),
        _row("tactile", 1, 2, 6.0, 26.5),
    ],
}


def test_rows_are_grouped_per_configuration_and_replicas_in_order_of_robots():
    c = curves(REPORT)
    assert set(c) == {("served", 1), ("served", 2), ("tactile", 2)}
    assert c["served", 1] == [Point(1, 9.0, 26.0, True), Point(10, 7.0, 14.0, True)]
    assert c["served", 2] == [Point(200, 115.0, 6.9, False)]
    with pytest.raises(ValueError, match="no results"):
        curves({"results": []})


def test_a_row_that_measured_nothing_is_left_off_the_chart(tmp_path):
    # refused at set-up (more robots than a replica's max_sessions): no window, so no latency and no CPU
    empty = {**_row("served", 300, 1, 0.0, 0.0, valid=False), "e2e_ms": {"p50": None, "p99": None, "max": None}}
    empty["service_cpu_ms_per_robot_s"] = 0.0
    report = {**REPORT, "results": [*REPORT["results"], empty]}
    assert curves(report)["served", 1] == [Point(1, 9.0, 26.0, True), Point(10, 7.0, 14.0, True)]
    assert chart(report, tmp_path / "service.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_chart_is_a_png_and_a_report_it_cannot_read_is_named(tmp_path, capsys):
    out = chart(REPORT, tmp_path / "service.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    broken = tmp_path / "broken.json"
    broken.write_text('{"results": [{"config": "served"}]}')
    assert main([str(broken), "--out", str(tmp_path / "x.png")]) == 2
    assert "broken.json" in capsys.readouterr().err
