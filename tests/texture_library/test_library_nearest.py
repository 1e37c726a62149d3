"""Perceptual nearest neighbour and the hysteresis that keeps the rendered texture from flickering."""

from __future__ import annotations

import numpy as np
import pytest

from texture_library.nearest import HysteresisSelector, Match, PerceptualIndex

IDS = ["smooth_hard", "rough_hard", "rough_soft"]
RATINGS = np.array([[80.0, 0.0, 0.0, -60.0], [-80.0, 0.0, 0.0, -60.0], [-70.0, 0.0, 0.0, 60.0]])


def test_query_known_answer():
    index = PerceptualIndex(IDS, RATINGS)
    q = np.array([-60.0, 0.0, 0.0, 0.0])
    # distances: smooth_hard √(140² + 60²), rough_hard √(20² + 60²), rough_soft √(10² + 60²)
    assert index.query(q, k=3) == [
        Match("rough_soft", pytest.approx(np.hypot(10, 60))),
        Match("rough_hard", pytest.approx(np.hypot(20, 60))),
        Match("smooth_hard", pytest.approx(np.hypot(140, 60))),
    ]
    assert [m.id for m in index.query(q, k=1)] == ["rough_soft"]
    assert len(index.query(q, k=10)) == 3


def test_weights_change_the_answer():
    """Roughness alone picks rough_hard (Δ 2 vs 8); weighting hardness ×4 picks rough_soft (Δ hardness 5 vs 115)."""
    q = np.array([-78.0, 0.0, 0.0, 55.0])
    roughness_only = PerceptualIndex(IDS, RATINGS, weights=[1, 0, 0, 0])
    assert roughness_only.query(q, k=1)[0] == Match("rough_hard", pytest.approx(2.0))
    hardness_heavy = PerceptualIndex(IDS, RATINGS, weights=[1, 0, 0, 4])
    best = hardness_heavy.query(q, k=1)[0]
    assert best.id == "rough_soft" and best.distance == pytest.approx(np.sqrt(8**2 + 4 * 5**2))


def test_ties_keep_library_order():
    index = PerceptualIndex(["x", "y"], np.array([[10.0, 0, 0, 0], [-10.0, 0, 0, 0]]))
    assert [m.id for m in index.query(np.zeros(4), k=2)] == ["x", "y"]


@pytest.mark.parametrize(
    "ids, ratings, weights, message",
    [
        (["a"], np.zeros((1, 3)), None, r"ratings must be \(1, 4\)"),
        (["a", "b"], np.zeros((1, 4)), None, r"ratings must be \(2, 4\)"),
        ([], np.zeros((0, 4)), None, r"ratings must be"),
        (["a"], np.zeros((1, 4)), [0, 0, 0, 0], "not all zero"),
        (["a"], np.zeros((1, 4)), [1, -1, 1, 1], "≥ 0"),
        (["a"], np.zeros((1, 4)), [1, 1, 1], "weights must be 4"),
        (["a"], np.zeros((1, 4)), [1, np.nan, 1, 1], "finite"),
    ],
)
def test_index_validation(ids, ratings, weights, message):
    with pytest.raises(ValueError, match=message):
        PerceptualIndex(ids, ratings, weights)


def test_query_validation():
    index = PerceptualIndex(IDS, RATINGS)
    with pytest.raises(ValueError, match="rating must be 4 finite values"):
        index.query(np.zeros(3))
    with pytest.raises(ValueError, match="rating must be 4 finite values"):
        index.query(np.array([0, np.nan, 0, 0]))
    with pytest.raises(ValueError, match="k must be ≥ 1"):
        index.query(np.zeros(4), k=0)


# ---- hysteresis -----------------------------------------------------------------------------------
# Two entries on the roughness axis; the boundary is at 0. Being at x, A is nearer by 2|x| when x < 0.
A_B = PerceptualIndex(["A", "B"], np.array([[-10.0, 0, 0, 0], [10.0, 0, 0, 0]]))


def at(x: float) -> np.ndarray:
    return np.array([x, 0.0, 0.0, 0.0])


def test_no_flicker_when_estimates_wobble_around_the_boundary_within_the_margin():
    sel = HysteresisSelector(margin=5.0, hold=2)
    assert sel.update(A_B, at(-3.0)) == "A"
    # B is nearer every other window, but only by 2·2 = 4 < margin
    picks = [sel.update(A_B, at(x)) for x in [2.0, -2.0] * 10]
    assert picks == ["A"] * 20


def test_switches_after_hold_windows_beyond_the_margin():
    sel = HysteresisSelector(margin=5.0, hold=3)
    sel.update(A_B, at(-5.0))
    assert [sel.update(A_B, at(4.0)) for _ in range(4)] == ["A", "A", "B", "B"]  # nearer by 8 ≥ 5 for 3 windows
    assert sel.current == "B"


def test_an_isolated_excursion_does_not_switch():
    sel = HysteresisSelector(margin=5.0, hold=2)
    sel.update(A_B, at(-5.0))
    picks = [sel.update(A_B, at(x)) for x in [6.0, 1.0, 6.0, -4.0, 6.0, 0.5]]
    assert picks == ["A"] * 6  # every run beyond the margin is one window long


def test_hold_one_switches_at_once_and_margin_zero_follows_the_nearest():
    sel = HysteresisSelector(margin=0.0, hold=1)
    assert [sel.update(A_B, at(x)) for x in [-1.0, 1.0, -1.0]] == ["A", "B", "A"]


def test_a_current_choice_missing_from_a_new_index_is_replaced():
    sel = HysteresisSelector()
    sel.update(A_B, at(-5.0))
    other = PerceptualIndex(["C", "D"], np.array([[-10.0, 0, 0, 0], [10.0, 0, 0, 0]]))
    assert sel.update(other, at(-5.0)) == "C"


def test_selector_validation():
    with pytest.raises(ValueError, match="margin must be ≥ 0 and hold ≥ 1"):
        HysteresisSelector(margin=-1.0)
    with pytest.raises(ValueError, match="margin must be ≥ 0 and hold ≥ 1"):
        HysteresisSelector(hold=0)
