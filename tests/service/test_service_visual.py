"""A visual model: windows wait for the first camera frame, whose embedding is computed once and reused."""

from __future__ import annotations

import json

import httpx
import numpy as np
from websockets.sync.client import connect

from models.predictor import Predictor
from models.tactile.features import recording_features
from models.visual.config import VisualConfig
from models.visual.embedding import visual_features, visual_slice
from models.visual.image import load_image
from models.visual.onnx_backbone import OnnxBackbone
from texture_library.attributes import ATTRIBUTES
from service.settings import Settings
from texture_library.recording import Channel, Recording


def test_windows_wait_for_a_frame_then_use_its_embedding(kit, visual_model, library_dir):
    settings = Settings(model_path=visual_model.model, library_dir=library_dir, backbone_path=visual_model.backbone,
                        instance_id="visual", api_keys=kit.API_KEY)
    image = (library_dir / "images" / "synth_003.png").read_bytes()
    rec = kit.stroke_recording(library_dir, "synth_003", 1.6)
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=30) as client:
        ready = client.get("/ready").json()
        assert ready["backbone"] == "efficientnet_lite0" and ready["modality"] == "both"
        session = kit.create_session(client)
        robot = {"Authorization": f"Bearer {session['robot_token']}"}
        with connect(kit.socket_url(srv, session, "events")) as sub:
            assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"
            for block in kit.recording_blocks(rec):
                assert kit.post_block(client, session, block).status_code == 202
            waiting = json.loads(sub.recv(timeout=10))
            assert waiting["event"] == "waiting_for_frame" and "needs a camera frame" in waiting["message"]
            status = kit.session_status(client, session)
            assert status["state"] == "waiting_for_frame" and status["counters"]["windows"] == 0
            assert status["windows_ready"] == 3
            r = client.post(f"/sessions/{session['session_id']}/frames", content=image,
                            headers={**robot, "Content-Type": "image/png"})
            assert r.status_code == 202 and r.json()["used"] is True
            events = []
            while sum(e["type"] == "window" for e in events) < 3:
                events.append(json.loads(sub.recv(timeout=60)))
        kinds = [e.get("event", e["type"]) for e in events]
        assert kinds[:2] == ["frame_received", "visual_updated"] and kinds[2:] == ["window"] * 3
        windows = events[2:]
        assert kit.session_status(client, session)["counters"]["frames_embedded"] == 1

    predictor = Predictor(visual_model.model)
    f32 = lambda c: Channel(c.data.astype(np.float32).astype(np.float64), c.rate_hz)  # noqa: E731 - the wire's float32
    features, _ = recording_features(Recording(f32(rec.accel), f32(rec.force), f32(rec.speed)), predictor.tactile_config)
    backbone = OnnxBackbone(visual_model.backbone)
    vector = visual_features(load_image(image), VisualConfig(), backbone)
    vector = vector[visual_slice(vector.shape[0], predictor.card.visual["visual_part"])]
    offline = predictor.predict(features[:3], np.repeat(vector[None], 3, axis=0))
    served = np.array([[w["raw_ratings"][a] for a in ATTRIBUTES] for w in windows])
    assert np.allclose(served, offline, atol=0.02)


def test_a_visual_model_without_a_backbone_is_not_ready_and_says_why(kit, visual_model, library_dir):
    settings = Settings(model_path=visual_model.model, library_dir=library_dir, instance_id="no-backbone", api_keys=kit.API_KEY)
    with kit.running(settings, wait_ready=False) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        r = kit.wait_for(lambda: (r := client.get("/ready")).json()["model"] and r)
        assert r.status_code == 503 and r.json()["ready"] is False
        assert "HAPTICLINK_BACKBONE_PATH" in r.json()["detail"] and "efficientnet_lite0" in r.json()["detail"]
        assert client.get("/health").status_code == 200
        refused = client.post("/sessions", json={}, headers=kit.FLEET)
        assert refused.status_code == 503 and "not ready" in refused.json()["detail"]
