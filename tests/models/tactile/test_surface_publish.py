"""The publication policy of a session's surface model (models.tactile.surface_publish): perceptible
changes only, at most once a second, within the size cap."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import Delaunay

from models.tactile.surface_fit import GRID_FORCES, GRID_SPEEDS
from models.tactile.surface_publish import SurfacePublisher, perceptibly_different, point_distances_db
from texture_library import model_codec
from texture_library.lsf import poles_to_poly, poly_to_lsf
from texture_library.render_model import RenderModel
from texture_library.surface import SurfaceProfile
from texture_library.taps import TapSet
from texture_library.vibration import VibrationModel


def _model(name: str, poles_hz: list[float], radii: list[float], mu: float) -> VibrationModel:
    speeds, forces = np.meshgrid([0.0, 150.0, 320.0], [0.0, 2.0, 4.5], indexing="ij")
    s, f = speeds.ravel(), forces.ravel()
    ar = poly_to_lsf(poles_to_poly(np.array(poles_hz), np.array(radii), 1000.0))
    return VibrationModel(
        name=name,
        speeds=s,
        forces=f,
        triangles=Delaunay(np.stack([s / 320, f / 4.5], axis=1)).simplices.astype(np.int64),
        ar_lsf=np.tile(ar, (s.size, 1)),
        ma_lsf=np.zeros((s.size, 0)),
        variance=0.05 * (0.2 + s / 150.0),
        gain=np.ones(s.size),
        mu=mu,
        max_speed=320.0,
        max_force=4.5,
    )


TRUTH = _model("truth", [90.0, 260.0], [0.93, 0.9], 0.4)
PRIOR = _model("prior", [40.0, 380.0], [0.8, 0.95], 0.8)


def test_first_offer_goes_out_as_a_render_model():
    pub = SurfacePublisher("session-abc")
    doc = pub.offer(TRUTH, 0.0)
    assert isinstance(doc, RenderModel) and doc.id == "session-abc"
    assert doc.model_version == RenderModel.from_vibration_model("session-abc", TRUTH).model_version
    assert pub.published == 1 and pub.last_refusal is None


def test_at_most_once_per_interval_and_only_when_perceptible():
    pub = SurfacePublisher("s", min_interval_s=1.0)
    assert pub.offer(TRUTH, 0.0) is not None
    assert pub.offer(PRIOR, 0.5) is None and pub.last_refusal == "too soon"
    louder = replace(TRUTH, variance=TRUTH.variance * 10 ** (0.3 / 10))  # +0.3 dB: below the threshold
    assert pub.offer(louder, 2.0) is None and pub.last_refusal == "imperceptible"
    assert pub.offer(PRIOR, 2.0) is not None and pub.published == 2


def test_what_counts_as_perceptible():
    assert perceptibly_different(TRUTH, TRUTH) is None
    assert perceptibly_different(TRUTH, replace(TRUTH, variance=TRUTH.variance * 10 ** (1.5 / 10))) == "vibration"
    assert perceptibly_different(TRUTH, replace(TRUTH, mu=TRUTH.mu + 0.1)) == "friction"
    bumpy = replace(TRUTH, surface=SurfaceProfile(0.5, 10.0))
    assert perceptibly_different(TRUTH, bumpy) == "bumps"
    assert perceptibly_different(bumpy, replace(TRUTH, surface=SurfaceProfile(0.51, 10.1))) is None
    assert perceptibly_different(bumpy, replace(TRUTH, surface=SurfaceProfile(0.5, 11.0))) == "bumps"
    taps = TapSet(np.array([50.0]), np.ones((1, 100)))
    assert perceptibly_different(TRUTH, replace(TRUTH, taps=taps)) == "taps"


def test_a_model_over_the_size_cap_is_not_sent():
    pub = SurfacePublisher("s")
    huge = replace(TRUTH, taps=TapSet(np.full(700, 50.0), np.random.default_rng(0).standard_normal((700, 100))))
    assert pub.offer(huge, 0.0) is None
    assert "bytes of JSON" in (pub.last_refusal or "") and pub.published == 0


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="threshold_db"):
        SurfacePublisher("s", threshold_db=0.0)
    with pytest.raises(ValueError, match="min_interval_s"):
        SurfacePublisher("s", min_interval_s=float("nan"))
    with pytest.raises(ValueError, match="point_db"):
        SurfacePublisher("s", point_db=-1.0)


# ---- publishing point by point ------------------------------------------------------------------------------
def _nudged(model: VibrationModel, rng: np.random.Generator, db: float, rad: float) -> VibrationModel:
    """Every grid point's level moved by up to ±db and its LSFs by up to ±rad: a refit's imperceptible drift."""
    m = model.speeds.size
    return replace(
        model,
        ar_lsf=model.ar_lsf + rng.uniform(-rad, rad, model.ar_lsf.shape),
        variance=model.variance * 10 ** (rng.uniform(-db, db, m) / 10),
        mu=model.mu + 0.01,
    )


def _learnt_sized() -> VibrationModel:
    """A model of a learnt model's size: the fitter's 6 × 5 grid, AR(12) and MA(4) at every point."""
    speeds, forces = np.meshgrid(GRID_SPEEDS, GRID_FORCES, indexing="ij")
    s, f = speeds.ravel(), forces.ravel()
    poles = np.array([40.0, 90.0, 160.0, 260.0, 330.0, 420.0]), np.array([0.9, 0.93, 0.85, 0.9, 0.8, 0.85])
    ar = poly_to_lsf(poles_to_poly(*poles, 1000.0))
    ma = poly_to_lsf(poles_to_poly(np.array([120.0, 300.0]), np.array([0.7, 0.6]), 1000.0))
    return VibrationModel(
        name="learnt",
        speeds=s,
        forces=f,
        triangles=Delaunay(np.stack([s / max(GRID_SPEEDS), f / max(GRID_FORCES)], axis=1)).simplices.astype(np.int64),
        ar_lsf=np.tile(ar, (s.size, 1)),
        ma_lsf=np.tile(ma, (s.size, 1)),
        variance=0.05 * (0.2 + s / 150.0),
        gain=np.ones(s.size),
        mu=0.4,
        max_speed=max(GRID_SPEEDS),
        max_force=max(GRID_FORCES),
    )


LEARNT = _learnt_sized()
CENTRE = 12  # (80 mm/s, 1.5 N), amid the nine operating points: the grid point the refit moves perceptibly


def _refit(rng: np.random.Generator) -> VibrationModel:
    """LEARNT refitted: the centre point's LSFs scaled by 1.15 (its resonances 15 % higher), every point's LSFs
    moved by up to ±3 mrad (a few code steps) and its level by up to ±0.05 dB, μ by 0.01."""
    fit = replace(
        LEARNT,
        ar_lsf=LEARNT.ar_lsf + rng.uniform(-3e-3, 3e-3, LEARNT.ar_lsf.shape),
        ma_lsf=LEARNT.ma_lsf + rng.uniform(-3e-3, 3e-3, LEARNT.ma_lsf.shape),
        variance=LEARNT.variance * 10 ** (rng.uniform(-0.05, 0.05, LEARNT.speeds.size) / 10),
        mu=LEARNT.mu + 0.01,
    )
    ar = fit.ar_lsf.copy()
    ar[CENTRE] *= 1.15
    return replace(fit, ar_lsf=ar)


def test_a_refit_moving_one_point_publishes_only_that_point():
    fit = _refit(np.random.default_rng(1))
    distances = point_distances_db(LEARNT, fit)
    assert distances[CENTRE] > 3 and np.all(np.delete(distances, CENTRE) < 0.25)  # the premise
    assert perceptibly_different(LEARNT, fit) == "vibration"
    pub = SurfacePublisher("s")
    pub.offer(LEARNT, 0.0)
    doc = pub.offer(fit, 2.0)
    assert doc is not None and pub.last is not None
    out = pub.last
    others = np.arange(LEARNT.speeds.size) != CENTRE
    for name in ("ar_lsf", "ma_lsf", "variance", "gain"):
        np.testing.assert_array_equal(getattr(out, name)[others], getattr(LEARNT, name)[others])
        np.testing.assert_array_equal(getattr(out, name)[CENTRE], getattr(fit, name)[CENTRE])
    assert out.mu == LEARNT.mu  # μ moved by 0.01 < MU_STEP: the published one stays
    assert doc.model_version == RenderModel.from_vibration_model("s", out).model_version


def test_the_delta_of_a_one_point_version_is_small():
    fit = _refit(np.random.default_rng(2))
    pub = SurfacePublisher("s")
    first = pub.offer(LEARNT, 0.0)
    second = pub.offer(fit, 2.0)
    assert first is not None and second is not None
    base = model_codec.body(model_codec.encode(first))  # what the operator holds
    sparse = model_codec.encode_delta(second, base)
    whole = model_codec.encode_delta(RenderModel.from_vibration_model("s", fit), base)
    assert model_codec.decode_delta(sparse, base)[0] == second.model_version  # names the version it carries
    # one row of 12 AR codes, the source version and the head differ: ≈ 70 bytes; the whole refit's delta, where
    # every code moved a few steps, ≈ 390 (a refit of a real learnt model: 300–600)
    assert len(sparse) <= 100, len(sparse)
    assert len(whole) >= 3 * len(sparse), (len(whole), len(sparse))


def test_the_published_model_stays_within_the_point_threshold_of_the_fit():
    rng = np.random.default_rng(3)
    pub = SurfacePublisher("s")
    fit, kept_rows = TRUTH, 0
    for step in range(40):
        fit = _nudged(fit, rng, 0.6, 3e-3)
        if step % 7 == 6:  # now and then one point jumps
            i = int(rng.integers(fit.speeds.size))
            ar = fit.ar_lsf.copy()
            ar[i] = PRIOR.ar_lsf[i]
            fit = replace(fit, ar_lsf=ar)
        if pub.offer(fit, 2.0 * step) is None:
            continue
        out = pub.last
        assert out is not None
        distances = point_distances_db(out, fit)
        assert np.all(distances < pub.point_db), distances
        assert perceptibly_different(out, fit) is None
        kept_rows += int(np.sum(~np.all(out.ar_lsf == fit.ar_lsf, axis=1)))
    assert pub.published >= 3 and kept_rows > 0  # the walk published several versions, some rows kept


def test_a_fit_of_other_arma_orders_goes_out_whole():
    pub = SurfacePublisher("s")
    pub.offer(TRUTH, 0.0)
    ar = poly_to_lsf(poles_to_poly(np.array([60.0, 200.0, 400.0]), np.array([0.9, 0.9, 0.9]), 1000.0))
    other = replace(TRUTH, ar_lsf=np.tile(ar, (TRUTH.speeds.size, 1)))
    assert pub.offer(other, 2.0) is not None and pub.last is other
    with pytest.raises(ValueError, match="same grid"):
        point_distances_db(TRUTH, other)


def test_kept_rows_that_add_up_to_a_perceptible_difference_go_out_whole():
    louder = replace(TRUTH, variance=TRUTH.variance * 10 ** (0.45 / 10))  # +0.45 dB at every point, < POINT_DB
    pub = SurfacePublisher("s", threshold_db=0.4)  # … but over this gate
    pub.offer(TRUTH, 0.0)
    assert pub.offer(louder, 2.0) is not None and pub.last is louder
