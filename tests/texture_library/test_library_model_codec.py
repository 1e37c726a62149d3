"""The compact model encoding: round trip, what quantisation costs in spectral distance, bad payloads."""

from __future__ import annotations

import dataclasses
import zlib

import numpy as np
import pytest

from texture_library import model_codec
from texture_library.render_model import RenderModel
from texture_library.spectrum import spectral_distance_db
from texture_library.surface import SurfaceProfile


def test_round_trip_keeps_the_grid_and_names_the_source_version(model):
    doc = RenderModel.from_vibration_model("e7", dataclasses.replace(model, surface=SurfaceProfile(0.3, 9.0)))
    payload = model_codec.encode(doc)
    source, back = model_codec.decode(payload)
    assert source == doc.model_version and back.id == "e7" and back.name == doc.name
    assert back.triangles == doc.triangles and back.taps is None and back.surface == doc.surface
    np.testing.assert_allclose(back.speeds_mm_s, doc.speeds_mm_s, rtol=1e-3)
    np.testing.assert_allclose(back.variance, doc.variance, rtol=2e-3)
    assert np.max(np.abs(np.subtract(back.ar_lsf, doc.ar_lsf))) <= np.pi / 2**model_codec.LSF_BITS
    assert len(payload) < len(doc.to_json_bytes()) / 5


@pytest.mark.parametrize("bits, most_db", [(10, 0.1), (6, 2.0)])
def test_the_spectral_error_it_adds_shrinks_with_the_bits(model, bits, most_db):
    _, back = model_codec.decode(model_codec.encode(RenderModel.from_vibration_model("e", model), bits))
    d = spectral_distance_db(model, back.to_vibration_model())
    assert 0 < d <= most_db


def test_quantised_lsfs_stay_strictly_increasing():
    lsf = np.array([[0.1000, 0.1001, 0.1002, 3.14]])
    codes = model_codec.quantise_lsf(lsf, 8)
    assert np.all(np.diff(codes, axis=1) > 0) and codes.max() <= 255
    with pytest.raises(ValueError, match="bits must lie"):
        model_codec.quantise_lsf(lsf, 2)


def test_bad_payloads_are_named(model):
    good = model_codec.encode(RenderModel.from_vibration_model("e", model))
    with pytest.raises(ValueError, match="not a compact rendering model"):
        model_codec.decode(b"JUNK" + good[4:])
    with pytest.raises(ValueError, match="does not inflate"):
        model_codec.decode(good[:4] + b"\x00\x01garbage")
    body = zlib.decompress(good[4:])
    with pytest.raises(ValueError, match="truncated"):
        model_codec.decode(good[:4] + zlib.compress(body[:-3]))
    with pytest.raises(ValueError, match="unexpected bytes"):
        model_codec.decode(good[:4] + zlib.compress(body + b"xx"))
