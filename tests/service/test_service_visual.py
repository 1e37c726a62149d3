"""A visual model: windows wait for the first camera frame, whose embedding is computed once and reused."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
from websockets.sync.client import connect

from drivers.protocol import SCENE_CONTENT_TYPE
from drivers.robot.frames import frame_thumbnail
from drivers.scene_change import thumbnail_bytes
from models.inference.predictor import Predictor
from models.tactile.features import recording_features
from models.visual.embedding import part_columns, visual_features, visual_layout
from models.visual.image import load_image
from models.visual.onnx_backbone import OnnxBackbone
from service.settings import Settings
from texture_library.attributes import ATTRIBUTES
from texture_library.recording import Channel, Recording


def test_windows_wait_for_a_frame_then_use_its_embedding(kit, visual_model, library_dir):
    settings = Settings(
        model_path=visual_model.model,
        library_dir=library_dir,
        backbone_path=visual_model.backbone,
        instance_id="visual",
        api_keys=kit.API_KEY,
        session_idle_s=600,  # the reaper is not this test's subject: on a busy host an embedding takes over 15 s
        session_first_block_s=600,
    )
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
            r = client.post(
                f"/sessions/{session['session_id']}/frames",
                content=image,
                headers={**robot, "Content-Type": "image/png"},
            )
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
    features, _ = recording_features(
        Recording(f32(rec.accel), f32(rec.force), f32(rec.speed)), predictor.tactile_config
    )
    backbone = OnnxBackbone(visual_model.backbone)
    config = predictor.visual_config
    vector = visual_features(load_image(image), config, backbone)
    columns, _ = part_columns(visual_layout(backbone.dim, config), predictor.card.visual["visual_part"])
    vector = vector[columns]
    offline = predictor.predict(features[:3], np.repeat(vector[None], 3, axis=0))
    served = np.array([[w["raw_ratings"][a] for a in ATTRIBUTES] for w in windows])
    assert np.allclose(served, offline, atol=0.02)


def test_a_visual_model_without_a_backbone_is_not_ready_and_says_why(kit, visual_model, library_dir):
    settings = Settings(
        model_path=visual_model.model, library_dir=library_dir, instance_id="no-backbone", api_keys=kit.API_KEY
    )
    with kit.running(settings, wait_ready=False) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        r = kit.wait_for(lambda: (r := client.get("/ready")).json()["model"] and r)
        assert r.status_code == 503 and r.json()["ready"] is False
        assert "HAPTICLINK_BACKBONE_PATH" in r.json()["detail"] and "efficientnet_lite0" in r.json()["detail"]
        head = client.head("/ready")  # a load balancer's HEAD hears the same
        assert head.status_code == 503 and head.content == b""
        assert client.get("/health").status_code == 200
        refused = client.post("/sessions", json={}, headers=kit.FLEET)
        assert refused.status_code == 503 and "not ready" in refused.json()["detail"]


def test_the_wrong_backbone_is_named_with_the_one_the_model_was_trained_on(visual_model, library_dir, tmp_path):
    """A model trained on the fp32 backbone given the int8 one: the answer named two config hashes, no backbone."""
    import onnx

    from models.visual.onnx_backbone import META_PREFIX
    from service.runtime import load_runtime

    other = onnx.load(str(visual_model.backbone))
    for prop in other.metadata_props:  # another backbone's export: its name and its visual configuration
        if prop.key == META_PREFIX + "backbone":
            prop.value = "efficientnet_lite0_int8"
        elif prop.key == META_PREFIX + "config_hash":
            prop.value = "0123456789abcdef"
    onnx.save(other, str(tmp_path / "int8.onnx"))
    settings = Settings(model_path=visual_model.model, library_dir=library_dir, backbone_path=tmp_path / "int8.onnx")
    with pytest.raises(ValueError) as refused:
        load_runtime(settings)
    why = str(refused.value)
    assert "was trained on efficientnet_lite0 features" in why and "is efficientnet_lite0_int8" in why
    assert "0123456789abcdef" in why and "HAPTICLINK_BACKBONE_PATH" in why


def _visual_settings(kit, visual_model, library_dir, **extra) -> Settings:
    return Settings(
        model_path=visual_model.model,
        tactile_model_path=visual_model.tactile,
        library_dir=library_dir,
        backbone_path=visual_model.backbone,
        api_keys=kit.API_KEY,
        metrics_token=kit.METRICS_TOKEN,
        session_queue_windows=64,
        # the reaper is not these tests' subject: on a busy host an embedding takes longer than its 15 s default, and
        # a session that sent only a frame was ended as abandoned while it waited
        session_idle_s=600,
        session_first_block_s=600,
        # nor is the shedding of frames for load (test_service_shedding.py's): on a busy host the embedder takes more
        # than the 1 s default behind a stalled decoder, frames were degraded a level, and the queue test's last
        # frame was refused 429 for load where it tests the queue's pixels
        shed_visual_queue_s=600,
        **extra,
    )


@contextlib.contextmanager
def _visual_server(kit, visual_model, library_dir, **extra) -> Iterator[tuple[Any, httpx.Client]]:
    """A running service with the visual model (settings as _visual_settings, plus `extra`) and a client of it."""
    with (
        kit.running(_visual_settings(kit, visual_model, library_dir, **extra)) as srv,
        httpx.Client(base_url=srv.url, timeout=30) as client,
    ):
        yield srv, client


def test_windows_are_tactile_only_until_the_embedding_lands_and_say_so(kit, visual_model, library_dir):
    image = (library_dir / "images" / "synth_003.png").read_bytes()
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_003", 3.1))  # 6 windows
    with _visual_server(kit, visual_model, library_dir, instance_id="fallback") as (srv, client):
        assert client.get("/ready").json()["tactile_model"] == "ridge-tactile"
        session = kit.create_session(client)
        robot = {"Authorization": f"Bearer {session['robot_token']}"}
        with connect(kit.socket_url(srv, session, "events")) as sub:
            assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"
            for block in blocks[:80]:  # 1.6 s: 3 windows, no frame yet
                assert kit.post_block(client, session, block).status_code == 202
            before = [json.loads(sub.recv(timeout=30)) for _ in range(3)]
            assert [(e["type"], e["inputs"], e["model"]) for e in before] == [
                ("window", "tactile", "ridge-tactile")
            ] * 3
            r = client.post(
                f"/sessions/{session['session_id']}/frames",
                content=image,
                headers={**robot, "Content-Type": "image/png"},
            )
            assert r.status_code == 202 and r.json()["outcome"] == "embedding"
            events = []
            while not any(e.get("event") == "visual_updated" for e in events):
                events.append(json.loads(sub.recv(timeout=60)))
            for block in blocks[80:]:
                assert kit.post_block(client, session, block).status_code == 202
            after = []
            while len(after) < 3:
                e = json.loads(sub.recv(timeout=30))
                if e["type"] == "window":
                    after.append(e)
        assert [(e["inputs"], e["model"]) for e in after] == [("tactile+visual", "ridge-both")] * 3
        assert [e["window_index"] for e in before + after] == list(range(6))


def test_the_same_scene_is_embedded_once(kit, visual_model, library_dir):
    image = (library_dir / "images" / "synth_003.png").read_bytes()
    other = (library_dir / "images" / "synth_001.png").read_bytes()
    with _visual_server(kit, visual_model, library_dir, instance_id="scene") as (srv, client):
        session = kit.create_session(client)
        headers = {"Authorization": f"Bearer {session['robot_token']}", "Content-Type": "image/png"}
        url = f"/sessions/{session['session_id']}/frames"
        assert client.post(url, content=image, headers=headers).json()["outcome"] == "embedding"
        kit.wait_for(lambda: kit.session_status(client, session)["counters"]["frames_embedded"] == 1, timeout_s=60)
        outcomes = [client.post(url, content=image, headers=headers).json()["outcome"] for _ in range(5)]
        assert outcomes == ["unchanged"] * 5  # a camera at 1–10 fps on one surface: one embedding
        assert client.post(url, content=other, headers=headers).json()["outcome"] == "embedding"
        status = kit.wait_for(
            lambda: (s := kit.session_status(client, session))["counters"]["frames_embedded"] == 2 and s, timeout_s=60
        )
        assert status["counters"]["frames_unchanged"] == 5 and status["counters"]["frames_received"] == 7


def test_a_scene_check_asks_for_the_frame_only_when_the_session_lacks_its_scene(kit, visual_model, library_dir):
    """A robot's refresh sends its newest frame's thumbnail (2 kB) first: the frame goes only if the session wants it
    (no frame yet, another scene), and a held scene costs no decode."""
    image = (library_dir / "images" / "synth_003.png").read_bytes()
    other = (library_dir / "images" / "synth_001.png").read_bytes()
    with _visual_server(kit, visual_model, library_dir, instance_id="check") as (srv, client):
        session = kit.create_session(client)
        robot = {"Authorization": f"Bearer {session['robot_token']}"}
        scene_url = f"/sessions/{session['session_id']}/scene"

        def check(thumb_bytes: bytes, content_type: str = SCENE_CONTENT_TYPE) -> httpx.Response:
            return client.post(scene_url, content=thumb_bytes, headers={**robot, "Content-Type": content_type})

        first = check(thumbnail_bytes(frame_thumbnail(image)))
        assert first.status_code == 200 and first.json()["frame_needed"] and "no frame" in first.json()["detail"]
        assert _post_frame(srv.url, session, image).json()["outcome"] == "embedding"
        kit.wait_for(lambda: kit.session_status(client, session)["counters"]["frames_embedded"] == 1, timeout_s=60)
        held = check(thumbnail_bytes(frame_thumbnail(image)))
        assert held.status_code == 200 and held.json() == {
            "frame_needed": False,
            "detail": "the scene is held: no frame needed",
        }, "the robot's thumbnail of a frame matches the service's own"
        changed = check(thumbnail_bytes(frame_thumbnail(other)))
        assert changed.json()["frame_needed"] and "scene changed" in changed.json()["detail"]
        assert kit.session_status(client, session)["counters"]["frames_received"] == 1, "checks decode nothing"

        short = check(b"\x00" * 100)
        assert short.status_code == 422 and "2048 bytes" in short.json()["detail"]
        large = check(image)  # a whole frame posted as a thumbnail: refused by its declared length
        assert large.status_code == 422 and f"got {len(image)}" in large.json()["detail"]
        # the same without a declared length (chunked): cut where a thumbnail ends, not read to the service's 8 MiB
        chunked = client.post(
            scene_url, content=iter([image[i : i + 4096] for i in range(0, len(image), 4096)]),
            headers={**robot, "Content-Type": SCENE_CONTENT_TYPE},
        )  # fmt: skip
        assert chunked.status_code == 413 and chunked.json()["detail"] == "scene check: a scene thumbnail is 2048 bytes"
        assert chunked.headers["connection"] == "close"
        not_grey = check(thumbnail_bytes(np.full((2, 16, 16), np.nan, np.float32)))
        assert not_grey.status_code == 422 and "finite grey levels" in not_grey.json()["detail"]
        assert check(image, "image/png").status_code == 415
        metrics = client.get("/metrics", headers=kit.SCRAPER).text
        assert 'hapticlink_scene_checks_total{answer="held"} 1.0' in metrics
        assert 'hapticlink_scene_checks_total{answer="frame_needed"} 2.0' in metrics


def _post_frame(url: str, session: dict, image: bytes) -> httpx.Response:
    with httpx.Client(base_url=url, timeout=30) as client:
        return client.post(
            f"/sessions/{session['session_id']}/frames",
            content=image,
            headers={"Authorization": f"Bearer {session['robot_token']}", "Content-Type": "image/png"},
        )


def test_the_visual_queue_takes_frames_up_to_its_pixels_refuses_beyond_and_gives_them_back(
    kit, visual_model, library_dir
):
    import threading

    from service.runtime import frame_pixels

    image = (library_dir / "images" / "synth_003.png").read_bytes()
    pixels = frame_pixels(image)
    room = 2.5 * pixels / 1e6  # two frames fit, a third does not
    with _visual_server(kit, visual_model, library_dir, instance_id="vqueue", visual_queue_mpx=room) as (srv, client):
        state = srv.app.state.service
        release = threading.Event()
        stall = state.frame_pool.submit(release.wait, 60)  # the frame decoder is busy
        sessions = [kit.create_session(client, name) for name in ("first", "second", "third")]
        answers: list[httpx.Response] = []
        waiting = [
            threading.Thread(target=lambda s=s: answers.append(_post_frame(srv.url, s, image))) for s in sessions[:2]
        ]
        for thread in waiting:
            thread.start()
        kit.wait_for(lambda: state.frames.visual_pixels == 2 * pixels, timeout_s=10)
        refused = _post_frame(srv.url, sessions[2], image)
        assert refused.status_code == 429 and "visual queue is full" in refused.json()["detail"]
        assert refused.headers["retry-after"] == "1"
        release.set()
        stall.result(timeout=10)
        for thread in waiting:
            thread.join(timeout=30)
        assert [a.status_code for a in answers] == [202, 202]
        assert all(a.json()["outcome"] == "embedding" for a in answers)
        kit.wait_for(lambda: state.frames.visual_pixels == 0, timeout_s=60)  # both embeddings gave their pixels back
        assert kit.session_status(client, sessions[2])["counters"]["frames_refused"] == 1
        assert 'hapticlink_frames_total{outcome="refused"} 1' in client.get("/metrics", headers=kit.SCRAPER).text
        # the queue is free again: the refused robot's newest frame goes through
        assert _post_frame(srv.url, sessions[2], image).status_code == 202


def test_a_frame_waiting_for_the_embedder_holds_its_pixels_in_the_visual_queue(kit, visual_model, library_dir):
    """While a session's embedding job runs, a frame of another scene waits for it (superseded by a newer one): the
    waiting frame is charged to the visual queue, a newer one in its place is charged instead of it, and every
    pixel comes back once the job is done."""
    import threading

    from service.runtime import frame_pixels

    images = [(library_dir / "images" / f"synth_00{k}.png").read_bytes() for k in (1, 2, 3)]
    first = frame_pixels(images[0])
    with _visual_server(kit, visual_model, library_dir, instance_id="vwait") as (srv, client):
        state = srv.app.state.service
        release = threading.Event()
        stall = state.visual_pool.submit(release.wait, 60)  # the embedder is busy: the first frame's job waits
        session = kit.create_session(client)
        outcomes = []
        for image, held in zip(images, [first, first + frame_pixels(images[1]), first + frame_pixels(images[2])]):
            outcomes.append(_post_frame(srv.url, session, image).json()["outcome"])
            assert state.frames.visual_pixels == held, outcomes
        assert outcomes == ["embedding", "superseded", "superseded"]
        release.set()
        stall.result(timeout=10)
        # hang guards: the embedder's thread runs at visual_nice (+15), last in line on a busy host
        kit.wait_for(lambda: kit.session_status(client, session)["counters"]["frames_embedded"] == 2, timeout_s=300)
        kit.wait_for(lambda: state.frames.visual_pixels == 0, timeout_s=60)


def test_a_frame_larger_than_the_visual_queue_is_taken_when_none_is_held(kit, visual_model, library_dir):
    from service.runtime import frame_pixels

    image = (library_dir / "images" / "synth_003.png").read_bytes()
    tiny = 0.5 * frame_pixels(image) / 1e6
    with _visual_server(kit, visual_model, library_dir, instance_id="vbig", visual_queue_mpx=tiny) as (srv, client):
        answer = _post_frame(srv.url, kit.create_session(client), image)
        assert answer.status_code == 202 and answer.json()["outcome"] == "embedding"
        kit.wait_for(lambda: srv.app.state.service.frames.visual_pixels == 0, timeout_s=60)
