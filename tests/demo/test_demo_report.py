"""What the demo prints: the per-probe report (the estimate after REPORT_AFTER_S of each probe's stroke against its
truth), the status line, the robot's counters and the summary table, each within 100 columns."""

import io
import re

import pytest

from demo.run import SCENE_GAP_S, ProbeReport, rating_error
from demo.terminal import WIDTH, robot_line, status_header, status_line, summary_table
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
    assert lines[1].endswith("console estimate   +4   +4   +4   +4    2.0")  # 4 bipolar → 2 points
    assert lines[2].endswith("mean of windows   +4   +4   +4   +4    2.0")  # (8 + 4 + 4 + 0) / 4 = 4 → 2 points
    assert lines[3].endswith("truth   +0   +0   +0   +0") and all(len(line) <= WIDTH for line in lines)
    assert lines[0].index("r→s") + 3 == lines[1].index("+4") + 2  # column heads end where their ratings end
    assert report.add(2.5, _r(0, 0, 0, 0), _r(0, 0, 0, 0)) == []  # reported once
    # probe b starts after the first probe's stroke and the gap; its clock restarts there
    start_b = 8.0 + SCENE_GAP_S
    assert report.add(start_b + 1.5, _r(50, 50, 50, 50), _r(50, 50, 50, 50)) == []
    lines = report.add(start_b + 2.0, _r(30, 50, 50, 50), _r(50, 50, 50, 50))
    assert lines[0].startswith("── b") and lines[1].endswith("2.5") and lines[2].endswith("0.0")
    assert report.errors == [("a", 2.0, 2.0), ("b", 2.5, 0.0)]
    table = _rendered(summary_table(report.errors, report.after_s))
    assert "error after 2 s of each probe's stroke" in table
    assert re.search(r"mean\s+│\s+2\.2\s+│\s+1\.0", table), table  # the mean row: (2 + 2.5) / 2, (2 + 0) / 2
    assert max(map(len, table.splitlines())) <= WIDTH


def test_status_lines_fit_100_columns_at_their_widest():
    extreme = _r(-100, -100, -100, -100)
    line = status_line(
        12345.6, "synth_texture_0042", extreme, extreme, 100.0, "a_very_long_library_id_0042",
        held=True, provisional=True, flagged=True,
    )  # fmt: skip
    assert len(line) <= WIDTH, line
    assert all(len(line) <= WIDTH for line in status_header().splitlines())
    plain = status_line(12.5, "synth_000", _r(12, -30, 5, -40), _r(10, -28, 3, -41), 1.8, "synth_003", held=False,
                        provisional=False, flagged=False)  # fmt: skip
    assert plain == "   12.5 s synth_000    +12  -30   +5  -40    +10  -28   +3  -41    1.8  synth_003"
    cut = status_line(0.5, "synth_000", _r(72, -100, -43, 29), _r(53, -32, -57, 35), 13.4, "s", held=False,
                      provisional=False, flagged=False)  # fmt: skip
    assert " +72 -100  -43" in cut, "a -100 keeps a space before it"
    header = status_header().splitlines()
    assert header[1].index("r→s") + 3 == plain.index("+12") + 3  # the heads end where their ratings end
    assert status_line(1.0, "a", extreme, extreme, 0.0, "b", held=True, provisional=True, flagged=False).endswith(
        " b kept provisional"
    )


def test_the_robot_line_names_its_counters_in_words_and_skips_zeros():
    line = robot_line({"read": 131, "acked": 131, "lost": 0, "unsent": 0, "frames_sent": 4, "reconnects": 0})
    assert line == "robot: 131 blocks read, 131 acknowledged, 4 frames sent"
    long = robot_line({k: 123456 for k in ("read", "acked", "resent", "duplicates", "rejected", "lost", "unsent")})
    assert "{" not in long and all(len(x) <= WIDTH for x in long.splitlines()) and len(long.splitlines()) > 1


def _rendered(table) -> str:
    from rich.console import Console

    console = Console(width=WIDTH, record=True, file=io.StringIO())
    console.print(table)
    return console.export_text()
