"""Intervals and out-of-distribution flags in window events, on a real server: they are exactly what the model
card's calibration and detector give offline, they widen when the input leaves the training range, and a model
without them says so (null) instead of inventing one."""

from __future__ import annotations

import json

import numpy as np
import pytest
from websockets.sync.client import connect

from models.inference.intervals import EmaUncertainty, calibrations_from_card
from models.inference.ood import OODDetector
from models.inference.predictor import Predictor
from models.tactile.features import recording_features
from service.events import WindowEvent
from service.uncertainty import RECENT_FLAGGED, ServedModel, SessionUncertainty, ema_variance_ratio
from texture_library.attributes import ATTRIBUTES
from texture_library.recording import Channel, Recording


def _windows(kit, server, client, blocks, n: int) -> list[dict]:
    session = kit.create_session(client)
    with connect(kit.socket_url(server, session, "events")) as sub:
        assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"
        for block in blocks:
            r = kit.post_block(client, session, block)
            assert r.status_code == 202, r.text
        windows = []
        while len(windows) < n:
            event = json.loads(sub.recv(timeout=20))
            if event["type"] == "window":
                windows.append(WindowEvent.model_validate(event).model_dump())
    return windows


def _f32(rec: Recording) -> Recording:
    def f(c: Channel) -> Channel:
        return Channel(c.data.astype(np.float32).astype(np.float64), c.rate_hz)

    return Recording(f(rec.accel), f(rec.force), f(rec.speed))


def _bounds(w: dict) -> tuple[np.ndarray, np.ndarray]:
    return (
        np.array([w["interval"][a]["lo"] for a in ATTRIBUTES]),
        np.array([w["interval"][a]["hi"] for a in ATTRIBUTES]),
    )


def test_the_card_carries_what_the_service_needs(tactile_model):
    card = Predictor(tactile_model).card
    assert set(calibrations_from_card(card.intervals)) == {"window", "ema", "texture"}
    assert card.ood is not None


@pytest.mark.parametrize("force_factor", [1.0, 4.0])
def test_intervals_and_flags_equal_the_card_replayed_offline(
    kit, server, client, library_dir, tactile_model, force_factor
):
    """Clean stroking and a tool pressed 4× harder than in training: every event's interval and flag equal
    the card's detector + EMA state + calibration replayed on the same samples."""
    rec = kit.stroke_recording(library_dir, "synth_001", 4.2)
    if force_factor != 1.0:
        rec = Recording(rec.accel, Channel(rec.force.data * force_factor, rec.force.rate_hz), rec.speed)
    windows = _windows(kit, server, client, kit.recording_blocks(rec), 8)

    predictor = Predictor(tactile_model)
    cals = calibrations_from_card(predictor.card.intervals)
    detector = OODDetector.from_dict(predictor.card.ood)
    features, _ = recording_features(_f32(rec), predictor.tactile_config)
    check = detector.check(features[:8])
    state = EmaUncertainty(0.5)
    for k, w in enumerate(windows):
        flagged, distance = state.update(bool(check.flags[k]), float(check.distance[k]))
        smoothed = np.array([w["ratings"][a] for a in ATTRIBUTES])
        target = "window" if k < 2 else "ema"  # the first two (provisional) carry the single window's band
        lo, hi = cals[target].interval(smoothed, None, 0.9, ood=np.array([flagged]))
        assert w["interval"]["level"] == 0.9 and w["interval"]["target"] == target
        assert w["provisional"] is (k < 2)
        got_lo, got_hi = _bounds(w)
        assert np.allclose(got_lo, lo, atol=0.02) and np.allclose(got_hi, hi, atol=0.02)
        assert np.all(got_lo <= smoothed + 0.01) and np.all(smoothed - 0.01 <= got_hi)
        assert w["out_of_distribution"] is bool(flagged)
        if check.flags[k]:
            assert w["ood_reasons"] == check.reasons[k]
        elif flagged:
            assert w["ood_reasons"][0] == RECENT_FLAGGED
        else:
            assert w["ood_reasons"] == []
    if force_factor == 1.0:
        assert sum(w["out_of_distribution"] for w in windows) <= 1  # the detector's limits: ~0.5 % of clean windows
    else:
        assert all(w["out_of_distribution"] for w in windows)
        assert all("force_out_of_range" in w["ood_reasons"] for w in windows)
        # flagged: the band includes the population band, so it is at least as wide as that
        _, prior = cals["ema"].quantile(0.9)
        for w in windows:
            lo, hi = _bounds(w)
            assert np.all(hi - lo >= np.minimum(2 * prior, 200) - 0.05)


def test_the_flag_outlives_a_flagged_window_while_it_weighs_in_the_ema():
    """Unit: one flagged window taints the smoothed estimate while its weight exceeds 0.1 (α 0.5: it and the next
    two windows)."""
    ratings = np.zeros(4)
    cal = _tiny_calibration()
    model = ServedModel(predictor=None, calibration=cal, window_calibration=cal, detector=None)  # type: ignore[arg-type]
    state = SessionUncertainty(0.5, 0.9)
    flags = [False, True, False, False, False, False]
    got = [state.update(model, ratings, f, ["tactile_outlier"] if f else [], 1.0) for f in flags]
    assert [a.out_of_distribution for a in got] == [
        False,
        True,
        True,
        True,
        False,
        False,
    ]  # weight .5, .25, .125, .0625
    assert got[2].ood_reasons == (RECENT_FLAGGED, "tactile_outlier")
    widths = [float(np.max(a.interval.hi - a.interval.lo)) for a in got]  # type: ignore[union-attr]
    assert widths[1] > widths[0] and widths[4] == pytest.approx(widths[0])


def test_the_ema_variance_ratio_matches_a_simulated_ema():
    """Known answer: 3 at the first window (one window's variance over α/(2 − α) = 1/3 at α 0.5), 1.5 at the second,
    → 1; and what an EMA of white noise gives over 200,000 streams."""
    assert [ema_variance_ratio(0.5, n) for n in (1, 2, 3)] == pytest.approx([3.0, 1.5, 1.125])
    assert ema_variance_ratio(1.0, 1) == 1.0 and ema_variance_ratio(0.5, 60) == pytest.approx(1.0)
    x = np.random.default_rng(0).normal(size=(200_000, 6))
    s = x[:, 0].copy()
    for n in range(1, 6):
        s = 0.3 * x[:, n] + 0.7 * s
        assert np.var(s) / (0.3 / 1.7) == pytest.approx(ema_variance_ratio(0.3, n + 1), rel=0.02)
    with pytest.raises(ValueError, match="n ≥ 1"):
        ema_variance_ratio(0.5, 0)


def test_the_first_windows_are_provisional_with_the_single_windows_band():
    """A session's first estimate is one window's: its steady-state EMA band would under-cover it. The first two
    windows at α 0.5 carry the wider per-window band and say they are provisional; then the EMA's own band."""
    ema = _tiny_calibration()
    window = _tiny_calibration(noise=15.0, target="window")
    model = ServedModel(predictor=None, calibration=ema, window_calibration=window, detector=None)  # type: ignore[arg-type]
    state = SessionUncertainty(0.5, 0.9)
    got = [state.update(model, np.zeros(4), None, None, None) for _ in range(4)]
    assert [a.provisional for a in got] == [True, True, False, False]
    assert [a.interval.target for a in got] == ["window", "window", "ema", "ema"]  # type: ignore[union-attr]
    widths = [float(np.max(a.interval.hi - a.interval.lo)) for a in got]  # type: ignore[union-attr]
    assert widths[0] == widths[1] > widths[2] == widths[3]
    unsmoothed = SessionUncertainty(1.0, 0.9).update(model, np.zeros(4), None, None, None)
    assert not unsmoothed.provisional


def test_no_calibration_and_no_detector_give_null_never_a_made_up_interval():
    model = ServedModel(predictor=None, calibration=None, window_calibration=None, detector=None)  # type: ignore[arg-type]
    a = SessionUncertainty(0.5, 0.9).update(model, np.zeros(4), None, None, None)
    assert a.interval is None and a.out_of_distribution is None and a.ood_reasons == ()
    with pytest.raises(ValueError, match="level"):
        SessionUncertainty(0.5, 1.5)


def test_the_smoothed_interval_uses_the_window_calibration_when_alphas_differ(tactile_model):
    predictor = Predictor(tactile_model)
    assert ServedModel.load(predictor, 0.5).calibration.target == "ema"  # type: ignore[union-attr]
    assert ServedModel.load(predictor, 0.3).calibration.target == "window"  # type: ignore[union-attr]
    assert ServedModel.load(predictor, 1.0).calibration.target == "window"  # type: ignore[union-attr]


def test_the_openapi_schema_shows_interval_and_flag(server):
    import httpx

    schemas = httpx.get(f"{server.url}/openapi.json").json()["components"]["schemas"]
    props = schemas["WindowEvent"]["properties"]
    assert {"interval", "out_of_distribution", "ood_reasons", "steadiness"} <= set(props)
    assert "confidence" not in props
    assert {"lo", "hi"} == set(schemas["Bounds"]["properties"])
    assert set(ATTRIBUTES) <= set(schemas["Interval"]["properties"])


def _tiny_calibration(noise: float = 5.0, target: str = "ema"):
    from models.inference.intervals import IntervalCalibration

    rng = np.random.default_rng(0)
    truth = rng.uniform(-60, 60, size=(40, 4))
    pred = truth + rng.normal(0, noise, size=(40, 4))
    alpha = 0.5 if target == "ema" else None
    return IntervalCalibration.fit(pred, truth, prior_ratings=truth, target=target, ema_alpha=alpha)
