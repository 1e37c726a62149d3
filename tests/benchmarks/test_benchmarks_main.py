"""`python -m benchmarks` reads its arguments before it starts anything."""

from __future__ import annotations

import pytest

import benchmarks.__main__ as suite


@pytest.mark.parametrize("argv", [["--help"], ["--typo"]])
def test_help_or_a_typo_runs_no_benchmark(argv, monkeypatch, capsys):
    """It ran the whole suite (and rewrote tracked reports) whatever it was given."""
    ran = []
    monkeypatch.setattr(suite.features, "main", lambda a: ran.append("features"))
    with pytest.raises(SystemExit) as stop:
        suite.main(argv)
    assert stop.value.code == (0 if argv == ["--help"] else 2) and ran == []
    out = capsys.readouterr()
    assert "--all" in out.out + out.err
