"""The service benchmark's verdict on a row: whether it measured the service serving its load, and if not, why."""

from __future__ import annotations

from benchmarks.service import invalid_because


def test_a_row_is_valid_only_when_its_generator_kept_up_and_nothing_failed():
    assert invalid_because(2.5, 10.0, []) is None
    assert invalid_because(10.0, 10.0, []) is None  # at the limit: kept up
    assert invalid_because(12.5, 10.0, []) == "generator send lag p99 12.5 ms > 10 ms"
    assert invalid_because(12.5, 10.0, ["robot 3: closed", "robot 4: closed"]) == (
        "generator send lag p99 12.5 ms > 10 ms; 2 generator failure(s): robot 3: closed"
    )


def test_a_row_refused_at_set_up_says_so_and_not_that_its_generator_lagged():
    # more robots than a replica's max_sessions: the sessions were refused (503) before any block was sent
    why = invalid_because(None, 10.0, ["set-up: 503", "set-up: 503"])
    assert why == "the generator sent no block; 2 generator failure(s): set-up: 503"
    assert "lag" not in why
