"""Selection rules: the window's spectrum, the likelihood against precomputed library spectra, the hysteresis
that keeps the rendered entry from flickering, and the vibrotactile weighting."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from texture_library.selection import (
    HysteresisChooser,
    SelectionRule,
    SpectralTable,
    band_mask,
    lsd_mismatch_db,
    sensor_noise_psd,
    welch_frequencies,
    whittle_mismatch_db,
    window_psd,
)
from texture_library.spectrum import arma_psd
from texture_library.synthesis import render
from texture_library.vibrotactile import detection_threshold_db, sensitivity_weights

from .conftest import square_model


def shifted(model, hz: float, name: str):
    """The square model with its first AR pole moved by `hz` (another texture, a known distance away)."""
    from texture_library.lsf import poles_to_poly, poly_to_lsf

    ar = [
        poly_to_lsf(poles_to_poly(np.array([60.0 + s / 2 + hz, 300.0]), np.array([0.9, 0.8]), 1000.0))
        for s in model.speeds
    ]
    return dataclasses.replace(model, name=name, ar_lsf=np.array(ar))


# ---- the window's spectrum --------------------------------------------------------------------------
def test_white_noise_on_three_axes_has_three_times_two_sigma_squared_over_the_rate():
    rng = np.random.default_rng(0)
    accel = 0.3 * rng.standard_normal((200_000, 3))
    psd = window_psd(accel)
    f = welch_frequencies()
    inside = (f > 10) & (f < 490)
    np.testing.assert_allclose(psd[inside].mean(), 3 * 2 * 0.09 / 1000.0, rtol=0.02)
    assert sensor_noise_psd(0.3) == pytest.approx(3 * 2 * 0.09 / 1000.0)


def test_window_psd_equals_scipy_welch_summed_over_axes():
    from scipy.signal import welch

    accel = np.random.default_rng(1).standard_normal((500, 6))
    _, ref = welch(accel[:, :3], fs=1000.0, window="hann", nperseg=128, noverlap=64, axis=0)
    np.testing.assert_allclose(window_psd(accel), ref.sum(axis=1), rtol=1e-10)


def test_window_psd_refuses_short_or_non_finite_windows():
    with pytest.raises(ValueError, match="L ≥ 128"):
        window_psd(np.zeros((100, 3)))
    bad = np.zeros((500, 3))
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        window_psd(bad)


# ---- mismatch ---------------------------------------------------------------------------------------
def test_mismatch_is_zero_for_a_perfect_fit_and_the_rms_db_for_a_level_offset():
    s = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0]])
    p = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(lsd_mismatch_db(p, s), [0.0, 10 * np.log10(2)], atol=1e-12)
    w = whittle_mismatch_db(p, s)
    assert w[0] == pytest.approx(0.0, abs=1e-9)
    r = 0.5  # P/S for the second model: per bin r − ln r − 1
    assert w[1] == pytest.approx(10 / np.log(10) * np.sqrt(2 * (r - np.log(r) - 1)))
    with pytest.raises(ValueError, match="same bins"):
        whittle_mismatch_db(p, s[:, :2])


def test_the_table_reads_the_exact_spectra_at_grid_points_with_noise_and_high_pass():
    m = square_model()
    table = SpectralTable(["a"], [m], n_speeds=5, n_forces=5, noise_psd=1e-4, highpass_hz=20.0)
    speed, force = table.speeds[2], table.forces[3]  # a grid point: no interpolation
    exact = arma_psd(m, [speed], [force], table.freqs_hz)[0] + 1e-4
    response = 1 / (1 + (20.0 / table.freqs_hz) ** 8)
    np.testing.assert_allclose(table.at(speed, force)[0], exact * response, rtol=1e-5)
    assert table.freqs_hz.min() >= 20.0 and table.freqs_hz.max() < 500.0
    with pytest.raises(ValueError, match="finite"):
        table.at(float("nan"), 1.0)


def test_a_rendered_window_is_most_likely_under_its_own_model():
    m = square_model()
    library = [shifted(m, -40.0, "lower"), m, shifted(m, 40.0, "higher")]
    table = SpectralTable(["lower", "own", "higher"], library, highpass_hz=None, noise_psd=0.0)
    rng = np.random.default_rng(3)
    wins = 0
    for _ in range(20):
        accel = render(m, np.full(500, 120.0), np.full(500, 1.5), rng)
        for kind in ("whittle", "lsd"):
            wins += int(np.argmin(table.mismatch_db(accel, 120.0, 1.5, kind)) == 1)
    assert wins == 40


def _reference_mismatch_db(
    table: SpectralTable, accel: np.ndarray, speed: float, force: float, kind: str
) -> np.ndarray:
    """The straightforward formulation the table's per-window path must equal: Welch spectrum, the table read
    with np.searchsorted and 10**x, then the checked public mismatch."""
    psd = window_psd(accel, table.rate_hz)[band_mask(welch_frequencies(table.rate_hz))]  # the table's default bins
    weights = []
    for grid, x in ((table.speeds, speed), (table.forces, force)):
        x = float(np.clip(x, grid[0], grid[-1]))
        i = min(int(np.searchsorted(grid, x, side="right")) - 1, grid.size - 2)
        weights.append((i, (x - grid[i]) / (grid[i + 1] - grid[i])))
    (i, a), (j, b) = weights
    t = table.log_psd
    mixed = (
        (1 - a) * (1 - b) * t[:, i, j]
        + a * (1 - b) * t[:, i + 1, j]
        + (1 - a) * b * t[:, i, j + 1]
        + a * b * t[:, i + 1, j + 1]
    )
    models = 10.0 ** mixed.astype(np.float64)
    return whittle_mismatch_db(psd, models) if kind == "whittle" else lsd_mismatch_db(psd, models)


def test_mismatch_equals_the_straightforward_formulation_on_and_off_the_grid():
    """The per-window path (cached Welch plan, unchecked table spectra, 10^x as e^(x ln 10)) changes no result
    beyond rounding: on grid points, between them, and clamped outside the grid, for both kinds."""
    m = square_model()
    library = [shifted(m, -40.0, "lower"), m, shifted(m, 40.0, "higher")]
    table = SpectralTable(["lower", "own", "higher"], library)
    rng = np.random.default_rng(7)
    points = [(table.speeds[3], table.forces[2]), (37.3, 1.234), (0.0, 0.0), (250.0, -1.0), (199.99, 4.0)]
    for speed, force in points:
        accel = render(m, np.full(500, max(speed, 10.0)), np.full(500, max(force, 0.5)), rng)
        accel = np.column_stack([accel, 0.1 * rng.standard_normal((500, 5))])  # derived columns: ignored
        for kind in ("whittle", "lsd"):
            np.testing.assert_allclose(
                table.mismatch_db(accel, speed, force, kind),
                _reference_mismatch_db(table, accel, speed, force, kind),
                rtol=1e-12,
                atol=1e-12,
            )


def test_a_table_with_non_finite_spectra_still_refuses_to_score_a_window():
    """The per-window path skips the spectra's checks only for a finite table; a non-finite one fails as before."""
    m = square_model()
    table = SpectralTable(["a"], [m], freqs_hz=np.array([50.0, np.nan, 100.0]))
    accel = render(m, np.full(500, 120.0), np.full(500, 1.5), np.random.default_rng(0))
    with pytest.raises(ValueError, match="finite"):
        table.mismatch_db(accel, 120.0, 1.5)


def test_window_psd_is_the_same_for_every_window_length_it_has_planned():
    """The Welch plan is cached per window length: a later window of another length gets its own."""
    from scipy.signal import welch

    rng = np.random.default_rng(2)
    for length in (500, 300, 500, 128, 1000):
        accel = rng.standard_normal((length, 3))
        _, ref = welch(accel, fs=1000.0, window="hann", nperseg=128, noverlap=64, axis=0)
        np.testing.assert_allclose(window_psd(accel), ref.sum(axis=1), rtol=1e-10)


# ---- rules ------------------------------------------------------------------------------------------
def test_rules_combine_rating_distance_and_mismatch():
    d, mm = np.array([1.0, 5.0]), np.array([10.0, 2.0])
    np.testing.assert_allclose(SelectionRule("perceptual").costs(d, None), d)
    np.testing.assert_allclose(SelectionRule("physical").costs(None, mm), mm)
    np.testing.assert_allclose(SelectionRule("hybrid", 0.5).costs(d, mm), [6.0, 6.0])
    assert not SelectionRule("hybrid", 0.0).needs_spectrum and SelectionRule("hybrid", 1.0).needs_spectrum
    with pytest.raises(ValueError, match="one of"):
        SelectionRule("loudest")
    with pytest.raises(ValueError, match="≥ 0"):
        SelectionRule("hybrid", -1.0)
    with pytest.raises(ValueError, match="spectral mismatch"):
        SelectionRule("hybrid", 1.0).costs(d, None)


# ---- hysteresis -------------------------------------------------------------------------------------
def test_hysteresis_holds_until_a_challenger_wins_by_the_margin_for_hold_windows():
    ids = ["a", "b"]
    ch = HysteresisChooser(SelectionRule("perceptual"), margin=3.0, hold=2)
    first = ch.choose(ids, np.array([1.0, 5.0]))
    assert first.id == "a" and not first.held_by_hysteresis and first.switch_margin == pytest.approx(7.0)
    small = ch.choose(ids, np.array([4.0, 2.0]))  # b nearer by 2 < 3: held
    assert small.id == "a" and small.held_by_hysteresis and small.switch_margin == pytest.approx(1.0)
    assert small.reason == "keeping a: b is closer by 2.0; it must be closer by 3 (2 windows in a row) to take over"
    once = ch.choose(ids, np.array([6.0, 2.0]))  # nearer by 4, first window of the streak
    assert once.id == "a" and once.held_by_hysteresis and once.switch_margin == 0.0
    assert once.reason.endswith("closer by 3 (2 windows in a row, 1 so far) to take over")
    twice = ch.choose(ids, np.array([6.0, 2.0]))
    assert twice.id == "b" and not twice.held_by_hysteresis
    assert twice.reason.startswith("nearest to the estimated ratings")


def test_settling_windows_follow_the_rule_and_say_so():
    ch = HysteresisChooser(SelectionRule("physical"), margin=100.0, hold=5, settle=2)
    assert ch.choose(["a", "b"], np.array([1.0, 2.0])).id == "a"
    c = ch.choose(["a", "b"], np.array([2.0, 1.0]))
    assert c.id == "b" and not c.held_by_hysteresis and "settling" in c.reason
    assert ch.choose(["a", "b"], np.array([2.0, 1.5])).id == "b"
    held = ch.choose(["a", "b"], np.array([1.0, 2.0]))  # settled: the margin applies now
    assert held.id == "b" and held.held_by_hysteresis


def test_a_cumulative_lead_releases_a_challenger_that_never_beats_the_margin():
    ids = ["a", "b"]
    ch = HysteresisChooser(SelectionRule("perceptual"), margin=10.0, hold=4, release_lead=12.0)
    assert ch.choose(ids, np.array([1.0, 5.0])).id == "a"
    first = ch.choose(ids, np.array([5.0, 0.0]))  # b cheaper by 5 < 10: held, lead 5 of 12
    assert first.id == "a" and first.held_by_hysteresis
    assert first.reason == (
        "keeping a: b is closer by 5.0; it must be closer by 10 (4 windows in a row), or by 7.0 more in all, "
        "to take over"
    )
    # next window: by the margin b needs 10 − 5 = 5 more; by the lead 12 − 5 − 5 = 2 more
    assert first.switch_margin == pytest.approx(2.0)
    second = ch.choose(ids, np.array([5.0, 0.0]))  # lead 10: one window short
    assert second.id == "a" and second.switch_margin == 0.0  # the same advantage once more switches
    third = ch.choose(ids, np.array([5.0, 0.0]))  # lead 15 ≥ 12, no window ever beat the margin
    assert third.id == "b" and not third.held_by_hysteresis


def test_a_pick_that_alternates_between_near_equal_entries_never_flips_the_choice():
    ids = ["a", "b", "c"]
    ch = HysteresisChooser(SelectionRule("perceptual"), margin=10.0, hold=4, release_lead=12.0)
    assert ch.choose(ids, np.array([1.0, 2.0, 9.0])).id == "a"
    for i in range(200):  # b and c take turns, each 8 cheaper than a: the lead restarts at every change
        costs = np.array([9.0, 1.0, 9.0]) if i % 2 else np.array([9.0, 9.0, 1.0])
        assert ch.choose(ids, costs).id == "a"
    # without the lead, a steady sub-margin challenger sticks for ever
    stuck = HysteresisChooser(SelectionRule("perceptual"), margin=10.0, hold=4)
    stuck.choose(["a", "b"], np.array([1.0, 2.0]))
    assert all(stuck.choose(["a", "b"], np.array([9.0, 1.0])).id == "a" for _ in range(100))


def test_release_settles_again_after_a_scene_change():
    ids = ["a", "b"]
    ch = HysteresisChooser(SelectionRule("perceptual"), margin=100.0, hold=5, settle=2, release_lead=1000.0)
    for _ in range(3):
        ch.choose(ids, np.array([1.0, 2.0]))
    assert ch.choose(ids, np.array([2.0, 1.0])).id == "a"  # settled: held
    ch.release()
    for _ in range(2):  # max(settle, 1) windows follow the rule
        c = ch.choose(ids, np.array([2.0, 1.0]))
        assert c.id == "b" and not c.held_by_hysteresis and "the scene changed" in c.reason and "settling" in c.reason
    assert ch.choose(ids, np.array([1.0, 2.0])).held_by_hysteresis  # then hysteresis again
    no_settle = HysteresisChooser(SelectionRule("perceptual"), margin=100.0, hold=5)
    no_settle.choose(ids, np.array([1.0, 2.0]))
    no_settle.release()
    assert no_settle.choose(ids, np.array([2.0, 1.0])).id == "b"  # at least the next window
    assert no_settle.choose(ids, np.array([1.0, 2.0])).held_by_hysteresis
    with pytest.raises(ValueError, match="release_lead"):
        HysteresisChooser(SelectionRule("perceptual"), release_lead=0.0)


def test_one_entry_has_no_switch_margin_and_bad_costs_are_refused():
    ch = HysteresisChooser(SelectionRule("perceptual"))
    assert ch.choose(["only"], np.array([3.0])).switch_margin is None
    with pytest.raises(ValueError, match="one per id"):
        ch.choose(["a", "b"], np.array([1.0, np.inf]))
    with pytest.raises(ValueError, match="hold ≥ 1"):
        HysteresisChooser(SelectionRule("perceptual"), margin=1.0, hold=0)


# ---- the vibrotactile weighting ---------------------------------------------------------------------
def test_the_threshold_is_lowest_near_250_hz_and_the_weights_sum_to_one():
    f = np.array([20.0, 40.0, 125.0, 250.0, 500.0])
    t = detection_threshold_db(f)
    assert np.argmin(t) == 3 and t[3] == pytest.approx(-20.0)
    assert t[2] == pytest.approx(-8.0) and t[4] == pytest.approx(-8.0)  # one octave either side: +12 dB
    assert t[0] == pytest.approx(-20.0 + 12.0 * np.log2(250.0 / 20.0))
    w = sensitivity_weights(f)
    assert w.sum() == pytest.approx(1.0) and np.argmax(w) == 3
    with pytest.raises(ValueError, match="> 0 Hz"):
        detection_threshold_db(np.array([0.0, 10.0]))
