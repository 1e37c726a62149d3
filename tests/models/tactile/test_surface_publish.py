"""The publication policy of a session's surface model (models.tactile.surface_publish): perceptible
changes only, at most once a second, within the size cap."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import Delaunay

from models.tactile.surface_publish import SurfacePublisher, perceptibly_different
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
