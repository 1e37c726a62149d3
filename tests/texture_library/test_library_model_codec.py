"""The compact model encoding: round trip, what quantisation costs in spectral distance (at every grid point: close
LSF pairs kept), bad payloads."""

from __future__ import annotations

import dataclasses
import zlib

import numpy as np
import pytest

from texture_library import model_codec
from texture_library.lsf import poles_to_poly, poly_to_lsf
from texture_library.render_model import RenderModel
from texture_library.spectrum import arma_psd, band_frequencies, log_spectral_distance_db, spectral_distance_db
from texture_library.surface import SurfaceProfile
from texture_library.vibration import VibrationModel


def test_round_trip_keeps_the_grid_and_names_the_source_version(model):
    doc = RenderModel.from_vibration_model("e7", dataclasses.replace(model, surface=SurfaceProfile(0.3, 9.0)))
    payload = model_codec.encode(doc)
    source, back = model_codec.decode(payload)
    assert source == doc.model_version and back.id == "e7" and back.name == doc.name
    assert back.triangles == doc.triangles and back.taps is None and back.surface == doc.surface
    np.testing.assert_allclose(back.speeds_mm_s, doc.speeds_mm_s, rtol=1e-3)
    np.testing.assert_allclose(back.variance, doc.variance, rtol=2e-3)
    # closed loop: each LSF is off by at most half a step of its own gap from the previous one as decoded
    rho = 2.0 ** (3 - model_codec.LSF_BITS)
    for sent, got in ((doc.ar_lsf, back.ar_lsf), (doc.ma_lsf, back.ma_lsf)):
        sent, got = np.asarray(sent), np.asarray(got)
        gap = sent - np.concatenate([np.zeros((sent.shape[0], 1)), got[:, :-1]], axis=1)
        assert np.all(np.abs(got - sent) <= (np.sqrt(1 + rho) - 1) * gap + 1e-12)
    assert len(payload) < len(doc.to_json_bytes()) / 5


@pytest.mark.parametrize("bits, most_db", [(10, 0.1), (6, 2.0)])
def test_the_spectral_error_it_adds_shrinks_with_the_bits(model, bits, most_db):
    _, back = model_codec.decode(model_codec.encode(RenderModel.from_vibration_model("e", model), bits))
    d = spectral_distance_db(model, back.to_vibration_model())
    assert 0 < d <= most_db


def test_quantised_lsfs_stay_strictly_increasing_inside_0_pi():
    lsf = np.array([[0.1000, 0.1001, 0.1002, np.pi - 1e-7], [1e-9, 2e-9, 1.0, 2.0]])
    back = model_codec.dequantise_lsf(model_codec.quantise_lsf(lsf, 8), 8)
    assert np.all(np.diff(back, axis=1) > 0) and np.all(back > 0) and np.all(back < np.pi)
    np.testing.assert_allclose(back[0, :3], lsf[0, :3], rtol=0.07)  # gaps of 1e-4 rad kept to ρ/2 = 6 %
    with pytest.raises(ValueError, match="bits must lie"):
        model_codec.quantise_lsf(lsf, 2)


def _notch_model() -> VibrationModel:
    """A 2×2 grid whose MA holds eight deep notches, 50–400 Hz on the spectral distance's 2 Hz grid (zeros at radius
    0.9995: each pair of LSFs about 0.001 rad apart, 0.65 of the old uniform step π/2048), behind a resonance at
    60 + s/4 Hz."""
    speeds, forces = np.array([0.0, 200.0, 0.0, 200.0]), np.array([0.0, 0.0, 4.0, 4.0])
    ar = [poly_to_lsf(poles_to_poly(np.array([60.0 + s / 4]), np.array([0.95]), 1000.0)) for s in speeds]
    notches = np.arange(50.0, 401.0, 50.0)  # on the distance's 2 Hz grid, so each notch's depth is sampled
    ma = poly_to_lsf(poles_to_poly(notches, np.full(notches.size, 0.9995), 1000.0))
    assert np.diff(ma).min() < np.pi / 2**11
    return VibrationModel(
        name="notch", speeds=speeds, forces=forces, triangles=np.array([[0, 1, 2], [1, 3, 2]]),
        ar_lsf=np.array(ar), ma_lsf=np.tile(ma, (4, 1)), variance=np.array([0.5, 1.0, 0.7, 2.0]), gain=np.ones(4),
        mu=0.3, max_speed=200.0, max_force=4.0,
    )  # fmt: skip


def _worst_grid_point_db(model: VibrationModel, back: VibrationModel) -> float:
    """The largest log-spectral distance over the model's own grid points, dB."""
    f = band_frequencies()
    a = arma_psd(model, model.speeds, model.forces, f)
    return float(log_spectral_distance_db(a, arma_psd(back, model.speeds, model.forces, f)).max())


def test_a_close_lsf_pair_keeps_its_notch_at_every_grid_point():
    """Known answer: a notch's depth follows its pair's gap. Rounded to the old uniform step (π/2048, a collision
    pushed one step up) the gaps move by up to half their width and the spectrum by 0.89 dB; coded relative to the
    gap, it stays within 0.5 dB (0.44) at every grid point. Deeper notches still (radius 0.9998, pairs a quarter of
    the old step) come back 0.98 dB off at their centres, against 2.3 dB uniform: the bound is kept for notches as
    deep as HaTT's (the next test), not for every notch."""
    model = _notch_model()
    levels = 1 << 11
    uniform = np.rint(model.ma_lsf / np.pi * levels)
    for j in range(1, uniform.shape[1]):
        uniform[:, j] = np.maximum(uniform[:, j], uniform[:, j - 1] + 1)
    old = dataclasses.replace(model, ma_lsf=uniform * np.pi / levels)
    assert _worst_grid_point_db(model, old) > 0.5  # the counterfactual: the uniform step fails this test
    _, back = model_codec.decode(model_codec.encode(RenderModel.from_vibration_model("n", model)))
    assert _worst_grid_point_db(model, back.to_vibration_model()) <= 0.5


@pytest.mark.shared
def test_every_hatt_model_within_half_a_db_at_every_grid_point(hatt_dir):
    """All 100 of HaTT's models, each at each of its own grid points (textured_metal was 1.49 dB off)."""
    from texture_library.hatt_xml import read_model

    paths = sorted((hatt_dir / "models").glob("*.xml"))
    assert len(paths) == 100
    worst = {}
    for path in paths:
        model = read_model(path)
        _, back = model_codec.decode(model_codec.encode(RenderModel.from_vibration_model(path.stem, model)))
        worst[path.stem] = _worst_grid_point_db(model, back.to_vibration_model())
    top = max(worst, key=lambda k: worst[k])
    assert worst[top] <= 0.5, (top, worst[top])


def test_bad_payloads_are_named(model):
    good = model_codec.encode(RenderModel.from_vibration_model("e", model))
    with pytest.raises(ValueError, match="not a compact rendering model"):
        model_codec.decode(b"JUNK" + good[4:])
    with pytest.raises(ValueError, match="old layout"):
        model_codec.decode(b"HLM1" + good[4:])
    with pytest.raises(ValueError, match="does not inflate"):
        model_codec.decode(good[:4] + b"\x00\x01garbage")
    body = zlib.decompress(good[4:])
    with pytest.raises(ValueError, match="truncated"):
        model_codec.decode(good[:4] + zlib.compress(body[:-3]))
    with pytest.raises(ValueError, match="unexpected bytes"):
        model_codec.decode(good[:4] + zlib.compress(body + b"xx"))


def _with_row_moved(doc: RenderModel, row: int) -> RenderModel:
    """`doc` with one grid point's AR LSFs moved by 1 % (a refit where new data arrived)."""
    from texture_library.render_model import content_version

    content = doc.content()
    content["ar_lsf"][row] = (np.asarray(content["ar_lsf"][row]) * 0.99).tolist()
    envelope = {"schema": doc.schema_, "schema_version": doc.schema_version, "id": doc.id}
    return RenderModel.model_validate({**envelope, "model_version": content_version(content), **content})


def test_a_delta_round_trips_and_costs_what_changed(model):
    doc = RenderModel.from_vibration_model("e", model)
    base = model_codec.body(model_codec.encode(doc))
    new = _with_row_moved(doc, 4)
    delta = model_codec.encode_delta(new, base)
    source, back, body = model_codec.decode_delta(delta, base)
    _, whole = model_codec.decode(model_codec.encode(new))
    assert source == new.model_version and back == whole  # the same model as the whole payload decodes to
    assert body == model_codec.body(model_codec.encode(new))  # the base of the next delta
    assert len(delta) < len(model_codec.encode(new)) / 2
    # a delta made against another base is refused by name, not decoded into a wrong model
    other = model_codec.body(model_codec.encode(_with_row_moved(doc, 2)))
    with pytest.raises(ValueError, match="made against base"):
        model_codec.decode_delta(delta, other)
    with pytest.raises(ValueError, match="not a compact rendering model delta"):
        model_codec.decode_delta(model_codec.encode(doc), base)
    with pytest.raises(ValueError, match="does not inflate"):
        model_codec.decode_delta(delta[:12] + b"garbage", base)
    # a base of another layout (a longer or shorter body) still decodes exactly: the difference covers every byte
    far = model_codec.body(model_codec.encode(RenderModel.from_vibration_model("a-longer-id", model)))
    assert model_codec.decode_delta(model_codec.encode_delta(new, far), far)[1] == whole


def test_taps_travel_in_half_precision(model):
    from texture_library.taps import TapSet

    taps = TapSet(np.array([12.0, 80.0]), np.sin(np.arange(240.0) / 7).reshape(2, 120) * 30.0)
    doc = RenderModel.from_vibration_model("t", dataclasses.replace(model, taps=taps))
    _, back = model_codec.decode(model_codec.encode(doc))
    assert back.taps is not None and back.taps.speeds_mm_s == [12.0, 80.0]
    np.testing.assert_allclose(back.taps.accel, taps.accel, rtol=1e-3, atol=30.0 * 2**-11)
    assert back.to_vibration_model().taps is not None
