"""Taps over the wire, end to end on a real uvicorn: the simulated robot taps then strokes, the robot client
sends the tap block with the sample blocks, and the service computes the tap features with the one function
the datasets use (models.tactile.taps.tap_features) for a model whose card asks for the taps group.
Models without the group acknowledge and ignore tap blocks; bad tap blocks get a 4xx naming the problem."""

from __future__ import annotations

import asyncio
import json
from dataclasses import replace

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from drivers.blocks import ChannelBlock, SampleBlock, TapBlock, encode_binary, encode_json
from drivers.protocol import SCENE_CONTENT_TYPE
from drivers.robot import RobotClient
from drivers.robot.frames import frame_thumbnail
from drivers.scene_change import thumbnail_bytes
from drivers.simulated import SimulatedSource
from drivers.source import paced
from models.inference.predictor import Predictor
from models.tactile.config import TactileConfig
from models.tactile.features import recording_features
from models.tactile.taps import tap_features
from service.settings import Settings
from texture_library.attributes import ATTRIBUTES
from texture_library.library import Library
from texture_library.recording import Channel, Recording


def _taps_settings(kit, taps_model, library_dir, **changes) -> Settings:
    """A server of the taps model without an untapped fallback (its windows wait for taps)."""
    return Settings(model_path=taps_model, library_dir=library_dir, api_keys=kit.API_KEY, **changes)


@pytest.fixture(scope="module")
def taps_server(kit, taps_model, library_dir):
    settings = _taps_settings(
        kit,
        taps_model,
        library_dir,
        instance_id="test-taps",
        session_idle_s=600,
        session_first_block_s=600,
        session_queue_windows=64,
        session_burst=10_000,
    )
    with kit.running(settings) as srv:
        yield srv


class ItemList:
    """A SensorSource over prepared items (as fast as the client takes them)."""

    name = "items"

    def __init__(self, items) -> None:
        self.items = items

    def __aiter__(self):
        return paced(self.items, False).__aiter__()

    async def aclose(self) -> None:
        pass


def _simulated_items(library_dir, entry: str, seconds: float, seed: int = 5) -> list:
    async def collect():
        src = SimulatedSource(
            Library.load(library_dir).model(entry), taps=True, realtime=False, duration_s=seconds, seed=seed
        )
        return [item async for item in src]

    return asyncio.run(collect())


def _offline(items, cfg: TactileConfig, predictor: Predictor) -> np.ndarray:
    """What training computes from the same float32 samples and taps: recording_features with tap_features."""
    taps = next(i for i in items if isinstance(i, TapBlock))
    blocks = [i for i in items if isinstance(i, SampleBlock)]
    chan = {
        k: Channel(
            np.concatenate([b.channels[k].data for b in blocks]).astype(np.float64), blocks[0].channels[k].rate_hz
        )
        for k in ("accel", "force", "speed")
    }
    features = tap_features(taps.speeds, taps.accel.data.astype(np.float64), taps.accel.rate_hz)
    rows, _ = recording_features(Recording(chan["accel"], chan["force"], chan["speed"]), cfg, taps=features)
    return predictor.predict(rows)


def _windows(sub, n: int, timeout_s: float = 30.0) -> tuple[list[dict], list[dict]]:
    windows, statuses = [], []
    while len(windows) < n:
        event = json.loads(sub.recv(timeout=timeout_s))
        (windows if event["type"] == "window" else statuses).append(event)
    return windows, statuses


def test_the_robot_taps_and_the_service_serves_tap_features(kit, taps_server, taps_model, library_dir):
    """SimulatedSource(taps=True) → RobotClient (binary WebSocket) → service: every window's raw ratings are the
    offline features (tap features from the same tap block) through the same model."""
    items = _simulated_items(library_dir, "synth_002", 3.0)
    assert isinstance(items[0], TapBlock) and items[0].n_taps == 10  # the procedure comes before the stroke
    with httpx.Client(base_url=taps_server.url, timeout=10) as client:
        session = kit.create_session(client)
        with connect(kit.socket_url(taps_server, session, "events")) as sub:
            assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"
            robot = RobotClient(
                taps_server.url,
                ItemList(items),
                session_id=session["session_id"],
                robot_token=session["robot_token"],
                transport="ws",
                binary=True,
            )
            stats = asyncio.run(robot.run())
            assert stats.acked == len(items) and stats.rejected == 0
            windows, _ = _windows(sub, 6)
        status = kit.session_status(client, session)
    assert status["counters"]["tap_blocks_used"] == 1 and status["counters"]["tap_blocks_ignored"] == 0
    predictor = Predictor(taps_model)
    offline = _offline(items, predictor.tactile_config, predictor)
    served = np.array([[w["raw_ratings"][a] for a in ATTRIBUTES] for w in windows])
    assert np.allclose(served, offline[:6], atol=0.011)  # events carry 2 decimals
    # the taps matter: other tap features give other ratings
    other = tap_features(items[0].speeds, 0.2 * items[0].accel.data.astype(np.float64))
    assert not np.allclose(
        predictor.predict(recording_features(_recording(items), predictor.tactile_config, taps=other)[0])[:6],
        offline[:6],
        atol=0.5,
    )


def _recording(items) -> Recording:
    blocks = [i for i in items if isinstance(i, SampleBlock)]
    chan = {
        k: Channel(
            np.concatenate([b.channels[k].data for b in blocks]).astype(np.float64), blocks[0].channels[k].rate_hz
        )
        for k in ("accel", "force", "speed")
    }
    return Recording(chan["accel"], chan["force"], chan["speed"])


def test_windows_of_an_untapped_surface_wait_for_its_taps(kit, taps_server, library_dir):
    """Sample blocks before any tap block: the windows wait (state waiting_for_taps, one status event);
    the tap block, sent late as JSON over HTTP, releases them."""
    items = _simulated_items(library_dir, "synth_001", 2.0)
    taps, blocks = items[0], [i for i in items if isinstance(i, SampleBlock)]
    with httpx.Client(base_url=taps_server.url, timeout=10) as client:
        session = kit.create_session(client)
        with connect(kit.socket_url(taps_server, session, "events")) as sub:
            assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"
            for seq, block in enumerate(blocks):
                r = kit.post_block(client, session, SampleBlock(block.t0, block.channels, seq))
                assert r.status_code == 202, r.text
            waiting = json.loads(sub.recv(timeout=10))
            assert waiting["event"] == "waiting_for_taps" and "tapped" in waiting["message"]
            status = kit.session_status(client, session)
            assert status["state"] == "waiting_for_taps" and status["counters"]["windows"] == 0
            late = TapBlock(taps.t0, taps.speeds, taps.accel, len(blocks))
            r = kit.post_block(client, session, json.dumps(encode_json(late)).encode(), "application/json")
            assert r.status_code == 202, r.text
            windows, _ = _windows(sub, 4)
    assert [w["window_index"] for w in windows] == [0, 1, 2, 3]


def test_models_without_the_taps_group_ignore_tap_blocks(kit, server, client, library_dir):
    """The shared server's model reads no taps: a tap block is acknowledged, counted as ignored, and the
    stroke's windows flow as if it had not come."""
    items = _simulated_items(library_dir, "synth_003", 1.5)
    session = kit.create_session(client)
    for seq, item in enumerate(items):
        r = kit.post_block(client, session, encode_binary(replace(item, seq=seq)))
        assert r.status_code == 202, r.text
    status = kit.wait_for(lambda: (s := kit.session_status(client, session))["counters"]["windows"] == 3 and s)
    assert status["counters"]["tap_blocks_ignored"] == 1 and status["counters"]["tap_blocks_used"] == 0
    assert status["counters"]["blocks_accepted"] == len(items)


def _tap_doc(**taps) -> dict:
    base = {"rate_hz": 1000.0, "units": "m/s^2", "speeds": [20.0, 40.0], "data": [[0.0] * 50, [0.0] * 50]}
    return {"seq": 0, "t0": 0.0, "kind": "taps", "taps": {**base, **taps}}


@pytest.mark.parametrize(
    ("doc", "detail"),
    [
        (_tap_doc(speeds=[20.0]), "1 speed(s) for 2 tap(s)"),
        (_tap_doc(data=[[0.0] * 5, [0.0] * 5]), "each tap holds 16 to"),
        (_tap_doc(units="N"), "units must be one of"),
        (_tap_doc(rate_hz=5.0), "sample rate"),
        (_tap_doc(speeds=[20.0, -1.0]), "tap speed -1 mm/s is outside its physical range, 0 to 2000 mm/s"),
        (_tap_doc(data=[[0.0] * 50] * 33, speeds=[1.0] * 33), "1 to 32 taps"),
        (_tap_doc(data=[[0.0] * 501] * 2), "each tap holds 16 to 500 samples"),
        (
            _tap_doc(data=[[0.0] * 49 + [1e30], [0.0] * 50]),
            "taps: acceleration 1e+30 m/s^2 is outside its physical range",
        ),
        (_tap_doc(data=[[0.0] * 49 + [2e4], [0.0] * 50], units="g"), "taps: acceleration 1.961e+05 m/s^2 is outside"),
        ({"seq": 0, "t0": 0.0, "kind": "taps", "channels": {}}, 'a taps block carries "taps"'),
        ({"seq": 0, "t0": 0.0, "kind": "tap"}, "kind must be one of"),
    ],
)
def test_bad_tap_blocks_get_422_naming_the_problem(kit, taps_server, doc, detail):
    with httpx.Client(base_url=taps_server.url, timeout=10) as client:
        session = kit.create_session(client)
        r = kit.post_block(client, session, json.dumps(doc).encode(), "application/json")
        assert r.status_code == 422 and detail in r.json()["detail"], r.text
        assert kit.session_status(client, session)["counters"]["blocks_rejected"] == 1


def test_taps_the_features_cannot_use_are_refused_over_the_socket_and_the_stream_goes_on(kit, taps_server, library_dir):
    """Taps all slower than the tap function's minimum speed: an error ack naming it (the socket stays open,
    nothing is taken), then good taps and samples are served."""
    items = _simulated_items(library_dir, "synth_000", 1.5)
    slow = TapBlock(0.0, np.full(items[0].n_taps, 0.1), items[0].accel, 0)
    with httpx.Client(base_url=taps_server.url, timeout=10) as client:
        session = kit.create_session(client)
        with connect(kit.socket_url(taps_server, session, "ingest")) as ws:
            ws.send(encode_binary(slow))
            ack = json.loads(ws.recv(timeout=5))
            assert ack["ok"] is False and ack["seq"] == 0 and "no tap is faster" in ack["error"]
            for seq, item in enumerate(items):
                ws.send(encode_binary(replace(item, seq=seq)))
                assert json.loads(ws.recv(timeout=5)) == {"seq": seq, "ok": True, "duplicate": False}
        status = kit.wait_for(lambda: (s := kit.session_status(client, session))["counters"]["windows"] == 3 and s)
    assert status["counters"]["blocks_rejected"] == 1 and status["counters"]["tap_blocks_used"] == 1


def test_a_gap_keeps_the_taps_and_a_new_scene_waits_for_its_own(kit, taps_server, library_dir):
    """A gap in the stream (a new segment) on the same surface keeps its tap features; once the camera shows
    another scene, windows of the new surface wait (no untapped fallback here: state waiting_for_taps, telling
    what to send) until its tap block arrives."""
    items = _simulated_items(library_dir, "synth_004", 1.0)
    taps, blocks = items[0], [i for i in items if isinstance(i, SampleBlock)]
    images = library_dir / "images"

    def frame(client, session, name):
        r = client.post(
            f"/sessions/{session['session_id']}/frames",
            content=(images / name).read_bytes(),
            headers={"Authorization": f"Bearer {session['robot_token']}", "Content-Type": "image/png"},
        )
        assert r.status_code == 202 and r.json()["outcome"] == "ignored", r.text

    with httpx.Client(base_url=taps_server.url, timeout=10) as client:
        session = kit.create_session(client)
        seq = 0

        def send(block):
            nonlocal seq
            r = kit.post_block(client, session, encode_binary(replace(block, seq=seq)))
            assert r.status_code == 202, r.text
            seq += 1

        send(taps)
        frame(client, session, "synth_004.png")  # the tapped surface
        for b in blocks:
            send(b)
        kit.wait_for(lambda: kit.session_status(client, session)["counters"]["windows"] == 2)
        for b in blocks:  # the same stroke 10 s later: a new segment on the same surface
            send(SampleBlock(b.t0 + 10.0, b.channels))
        kit.wait_for(lambda: kit.session_status(client, session)["counters"]["windows"] == 4)
        frame(client, session, "synth_000.png")  # the tool is over another surface now
        for b in blocks:
            send(SampleBlock(b.t0 + 20.0, b.channels))
        status = kit.wait_for(lambda: (s := kit.session_status(client, session))["state"] == "waiting_for_taps" and s)
        assert status["counters"]["windows"] == 4
        send(TapBlock(20.0, taps.speeds, taps.accel))  # tapped late: the waiting windows go
        status = kit.wait_for(lambda: (s := kit.session_status(client, session))["counters"]["windows"] == 6 and s)
    assert status["state"] == "streaming" and status["counters"]["tap_blocks_used"] == 2


def test_a_scene_check_after_taps_asks_for_a_frame_of_the_tapped_surface(kit, taps_server, library_dir):
    """Taps belong to the surface the next frame shows: until a frame after the tap block has come, a robot's scene
    check asks for the frame even when the scene is the one held (else a later scene change would be taken for the
    tapped surface)."""
    taps = _simulated_items(library_dir, "synth_004", 1.0)[0]
    image = (library_dir / "images" / "synth_004.png").read_bytes()
    with httpx.Client(base_url=taps_server.url, timeout=10) as client:
        session = kit.create_session(client)
        robot = {"Authorization": f"Bearer {session['robot_token']}"}

        def check() -> dict:
            r = client.post(
                f"/sessions/{session['session_id']}/scene",
                content=thumbnail_bytes(frame_thumbnail(image)),
                headers={**robot, "Content-Type": SCENE_CONTENT_TYPE},
            )
            assert r.status_code == 200, r.text
            return r.json()

        def frame() -> None:
            r = client.post(
                f"/sessions/{session['session_id']}/frames",
                content=image,
                headers={**robot, "Content-Type": "image/png"},
            )
            assert r.status_code == 202, r.text

        frame()
        assert not check()["frame_needed"], "the scene is held, and no taps wait for a frame"
        assert kit.post_block(client, session, encode_binary(replace(taps, seq=0))).status_code == 202
        answer = check()
        assert answer["frame_needed"] and "tapped surface" in answer["detail"]
        frame()
        assert not check()["frame_needed"]


def test_tap_blocks_round_trip_both_encodings():
    rng = np.random.default_rng(0)
    block = TapBlock(
        3.5, np.array([12.0, 30.5, 44.0]), ChannelBlock(rng.normal(size=(3, 100)).astype(np.float32), 1000.0, "g"), 9
    )
    from drivers.blocks import decode_binary, decode_json

    for back in (decode_binary(encode_binary(block)), decode_json(json.loads(json.dumps(encode_json(block))))):
        assert isinstance(back, TapBlock) and back.seq == 9 and back.t0 == 3.5 and back.accel.units == "g"
        np.testing.assert_array_equal(back.speeds, block.speeds)
        np.testing.assert_allclose(back.accel.data, block.accel.data, rtol=1e-6)


def test_a_robot_refused_while_its_windows_wait_for_taps_is_told_to_send_them(kit, taps_model, library_dir):
    """No untapped fallback and no tap block: the windows wait until the session's queue is full; then the refusal
    itself (the HTTP 429's detail, the ingest socket's 4429 reason) says what to send, not only "saturated"."""
    from drivers.protocol import Close

    settings = _taps_settings(
        kit, taps_model, library_dir, instance_id="test-taps-wait", session_queue_windows=2, max_block_windows=1
    )
    blocks = [i for i in _simulated_items(library_dir, "synth_001", 3.0) if isinstance(i, SampleBlock)]
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        session = kit.create_session(client)
        for k, block in enumerate(blocks):
            refused = kit.post_block(client, session, encode_binary(replace(block, seq=k)))
            if refused.status_code == 429:
                break
        assert refused.status_code == 429, refused.text
        assert "tap block" in refused.json()["detail"] and "saturated" in refused.json()["detail"]
        with connect(kit.socket_url(srv, session, "ingest")) as ws:
            ws.send(encode_binary(replace(block, seq=k)))  # the refused block, resent
            with pytest.raises(ConnectionClosed):
                ws.recv(timeout=5)
        assert ws.close_code == Close.SATURATED and "tap block" in ws.close_reason and "--taps" in ws.close_reason
