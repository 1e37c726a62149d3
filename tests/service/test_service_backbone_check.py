"""The load-time self-checks: a backbone that drifts from fp32 on this CPU is not served (its fp32 source is, and the
service says so once, in /ready and in each session's status); a model whose card probe fails is refused."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import httpx
import onnx
import pytest

from models.inference import jsonarrays
from models.inference.modelfile import read_metadata, write_metadata
from models.visual.onnx_backbone import MIN_PROBE_COSINE, PROBE_KEY, OnnxBackbone, decode_array, encode_array
from service.runtime import load_runtime
from service.settings import Settings


def _drifted_backbone(src: Path, folder: Path) -> Path:
    """A copy of the backbone at `src`, in `folder`, whose probe's fp32 reference it no longer reproduces (negated:
    cosine −1, further than any kernel drifts), so its check fails on every CPU."""
    model = onnx.load(str(src))
    for prop in model.metadata_props:
        if prop.key == PROBE_KEY:
            probe = json.loads(prop.value)
            reference = decode_array(probe["reference"], "reference")
            prop.value = json.dumps({**probe, "reference": encode_array(-reference)})
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / src.name
    onnx.save(model, str(out))
    return out


@pytest.fixture(scope="module")
def served(calibrated_visual_model) -> tuple[Path, Path]:
    """(the int8 backbone the model was trained with, the fp32 file it was quantized from)."""
    int8 = OnnxBackbone(calibrated_visual_model.backbone)
    assert int8.source is not None and int8.source_file is not None
    fp32 = calibrated_visual_model.backbone.parent / int8.source_file
    assert fp32.is_file()
    return calibrated_visual_model.backbone, fp32


def _settings(model: Path, library: Path, backbone: Path, **kw) -> Settings:
    return Settings(model_path=model, library_dir=library, backbone_path=backbone, **kw)


def test_the_served_backbone_passes_its_check_or_its_fp32_source_is_served(
    calibrated_visual_model, library_dir, served
):
    """On a CPU with VNNI the int8 copy holds and is served; without, the fp32 file beside it is, found by itself:
    either way the features served are within the bound of fp32's on the probe frames."""
    rt = load_runtime(_settings(calibrated_visual_model.model, library_dir, served[0]))
    status = rt.backbone_status
    assert rt.problem is None and rt.backbone is not None and status is not None and status.check is not None
    assert status.configured == "efficientnet_lite0_int8"
    if status.check.passed:
        assert rt.backbone.name == "efficientnet_lite0_int8" and not status.fallback
    else:
        assert rt.backbone.name == "efficientnet_lite0" and status.fallback
        assert status.fallback_check is not None and status.fallback_check.passed


def test_a_drifted_backbone_falls_back_to_fp32_says_so_once_and_reports_it(
    kit, calibrated_visual_model, library_dir, served, tmp_path, caplog
):
    drifted = _drifted_backbone(served[0], tmp_path / "beside")
    shutil.copy(served[1], drifted.parent / served[1].name)  # its fp32 source beside it, as the cache keeps them
    with caplog.at_level(logging.INFO, logger="service.runtime"):
        rt = load_runtime(_settings(calibrated_visual_model.model, library_dir, drifted))
    assert rt.problem is None and rt.backbone is not None and rt.backbone.name == "efficientnet_lite0"
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and warnings[0].levelno == logging.WARNING
    line = warnings[0].getMessage()
    assert "efficientnet_lite0_int8 failed its load-time check on this CPU" in line and "serving its fp32" in line
    assert kit.API_KEY not in line
    rt.stop()

    settings = _settings(
        calibrated_visual_model.model, library_dir, drifted, instance_id="fallback", api_keys=kit.API_KEY
    )
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=30) as client:
        ready = client.get("/ready")
        assert ready.status_code == 200
        body = ready.json()
        assert body["backbone"] == "efficientnet_lite0"
        check = body["backbone_check"]
        assert check["configured"] == "efficientnet_lite0_int8" and check["served"] == "efficientnet_lite0"
        assert check["fallback"] is True and check["probe_cosine"] < check["bound"] == MIN_PROBE_COSINE
        assert "failed its check on this CPU" in check["detail"]
        session = kit.create_session(client)
        status = kit.session_status(client, session)
        assert status["backbone"] == check


def test_a_drifted_backbone_without_its_fp32_source_is_not_served_and_says_what_to_give(
    kit, calibrated_visual_model, library_dir, served, tmp_path
):
    drifted = _drifted_backbone(served[0], tmp_path / "alone")
    rt = load_runtime(_settings(calibrated_visual_model.model, library_dir, drifted))
    assert rt.backbone is None and rt.problem is not None
    assert "failed its load-time check" in rt.problem and "HAPTICLINK_BACKBONE_FALLBACK_PATH" in rt.problem
    # given explicitly, from anywhere, it is served
    explicit = load_runtime(
        _settings(calibrated_visual_model.model, library_dir, drifted, backbone_fallback_path=served[1])
    )
    assert explicit.problem is None and explicit.backbone is not None and explicit.backbone.name == "efficientnet_lite0"
    explicit.stop()
    settings = _settings(calibrated_visual_model.model, library_dir, drifted, instance_id="alone", api_keys=kit.API_KEY)
    with kit.running(settings, wait_ready=False) as srv, httpx.Client(base_url=srv.url, timeout=30) as client:
        body = kit.wait_for(lambda: (r := client.get("/ready")).json().get("backbone_check") and r, 60).json()
        assert body["ready"] is False and "HAPTICLINK_BACKBONE_FALLBACK_PATH" in body["detail"]
        assert body["backbone_check"]["fallback"] is False and body["backbone"] is None


def test_a_fallback_that_is_not_the_int8_source_is_refused(
    calibrated_visual_model, visual_model, library_dir, tmp_path
):
    drifted = _drifted_backbone(OnnxBackbone(calibrated_visual_model.backbone).path, tmp_path / "other")
    with pytest.raises(ValueError, match="must be the file it was quantized from"):
        load_runtime(
            _settings(calibrated_visual_model.model, library_dir, drifted, backbone_fallback_path=visual_model.backbone)
        )


def test_the_service_refuses_a_model_whose_card_probe_fails_on_this_cpu(tactile_model, library_dir, tmp_path):
    meta = read_metadata(tactile_model)
    probe = json.loads(meta["probe"])
    ratings = jsonarrays.decode(probe["ratings"])
    meta["probe"] = json.dumps({**probe, "ratings": jsonarrays.encode(ratings + 0.25)})
    drifted = tmp_path / "drifted.onnx"
    drifted.write_bytes(tactile_model.read_bytes())
    write_metadata(drifted, meta)
    assert load_runtime(Settings(model_path=tactile_model, library_dir=library_dir)).predictor.probe_error is not None
    with pytest.raises(ValueError, match=r"by up to 0\.25 bipolar points .* refusing it"):
        load_runtime(Settings(model_path=drifted, library_dir=library_dir))
