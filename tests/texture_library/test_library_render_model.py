"""The served rendering model: round trip through JSON, its version, its size bound, bad documents."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import numpy as np
import pytest

from texture_library.render_model import (
    MAX_RENDER_MODEL_BYTES,
    RenderModel,
    canonical_json,
    content_version,
    parse_render_model,
)
from texture_library.surface import SurfaceProfile
from texture_library.synthesis import render
from texture_library.taps import TapSet


def test_vibration_model_to_json_and_back_renders_identically(model_with_taps):
    model = dataclasses.replace(model_with_taps, surface=SurfaceProfile(0.4, 12.0))
    doc = RenderModel.from_vibration_model("synth_003", model)
    back = parse_render_model(doc.to_json_bytes()).to_vibration_model()
    speed = np.linspace(0, 220, 3000)
    force = np.linspace(4.5, -0.2, 3000)
    np.testing.assert_array_equal(
        render(back, speed, force, np.random.default_rng(4)), render(model, speed, force, np.random.default_rng(4))
    )
    assert back.surface == model.surface and back.mu == model.mu
    np.testing.assert_array_equal(back.taps.accel, model.taps.accel)
    np.testing.assert_array_equal(back.triangles, model.triangles)


def test_the_document_has_the_contracts_fields(model):
    raw = json.loads(RenderModel.from_vibration_model("e1", model).to_json_bytes())
    assert raw["schema"] == "hapticlink.render-model" and raw["schema_version"] == 1 and raw["id"] == "e1"
    assert set(raw) == {
        "schema", "schema_version", "id", "model_version", "name", "rate_hz", "speeds_mm_s", "forces_n",
        "triangles", "ar_lsf", "ma_lsf", "variance", "gain", "mu", "max_speed_mm_s", "max_force_n", "surface", "taps",
    }  # fmt: skip
    assert len(raw["ar_lsf"]) == 9 and len(raw["ar_lsf"][0]) == 4 and raw["taps"] is None


def test_model_version_hashes_the_content_not_the_id(model):
    a = RenderModel.from_vibration_model("a", model)
    b = RenderModel.from_vibration_model("b", model)
    assert a.model_version == b.model_version == content_version(a.content())
    assert a.model_version == hashlib.sha256(canonical_json(a.content())).hexdigest()[:16]
    louder = RenderModel.from_vibration_model("a", dataclasses.replace(model, variance=model.variance * 1.0001))
    assert louder.model_version != a.model_version


def test_a_document_whose_version_does_not_match_its_content_is_refused(model):
    raw = json.loads(RenderModel.from_vibration_model("a", model).to_json_bytes())
    raw["mu"] = 0.41
    with pytest.raises(ValueError, match="model_version .* does not match"):
        parse_render_model(json.dumps(raw))


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d.update(ar_lsf=[list(reversed(r)) for r in d["ar_lsf"]]), "increase strictly"),
        (lambda d: d.update(variance=d["variance"][:-1]), "variance must have shape"),
        (lambda d: d.update(triangles=[[0, 1, 99]]), "triangle indices"),
        (lambda d: d.update(schema="something-else"), "schema"),
        (lambda d: d.update(extra_field=1), "extra_field"),
        (lambda d: d.pop("gain"), "gain"),
        (lambda d: d.update(mu=-1), "mu"),
    ],
)
def test_bad_documents_get_a_clear_error(model, change, message):
    raw = json.loads(RenderModel.from_vibration_model("a", model).to_json_bytes())
    change(raw)
    with pytest.raises(ValueError, match=message):
        parse_render_model(json.dumps(raw))


def test_not_json_and_oversized_payloads_are_refused(model):
    with pytest.raises(ValueError, match="not a valid hapticlink.render-model"):
        parse_render_model(b"{not json")
    with pytest.raises(ValueError, match="bytes; at most"):
        parse_render_model(b" " * (2 * MAX_RENDER_MODEL_BYTES + 1))


def test_a_model_over_the_size_bound_is_refused_when_it_is_built(model):
    huge = dataclasses.replace(model, taps=TapSet(np.arange(40.0), np.full((40, 2000), 0.123456789012345)))
    with pytest.raises(ValueError, match=f"at most {MAX_RENDER_MODEL_BYTES} are served"):
        RenderModel.from_vibration_model("huge", huge)
