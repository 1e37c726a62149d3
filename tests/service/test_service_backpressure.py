"""Bounded queues: a saturated session refuses ingest (429 + Retry-After, close 4429) without taking
anything, a resend then succeeds, and the drivers' RobotClient rides it out losing nothing.

Saturation is produced deterministically: the server runs in this process, so the test occupies
its one window-pool thread (as a slow CPU would) and releases it later.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import time

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from drivers.blocks import encode_binary
from drivers.protocol import Close
from drivers.robot import RobotClient

QUEUE_WINDOWS = 2


@pytest.fixture
def tight_server(kit, base_settings):
    settings = base_settings.model_copy(
        # refused at once (a saturated session's robot held instead: tests/service/test_service_readmission.py)
        update={"pool_threads": 1, "session_queue_windows": QUEUE_WINDOWS, "max_block_windows": 1, "readmit_hold_s": 0}
    )
    with kit.running(settings) as srv:
        yield srv


def test_http_ingest_answers_429_when_saturated_and_a_resend_succeeds(kit, tight_server, library_dir):
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_002", 4.0))  # 200 blocks, 8 windows
    with httpx.Client(base_url=tight_server.url, timeout=10) as client:
        session = kit.create_session(client)
        with kit.PoolStall(tight_server):
            sent = 0
            for block in blocks:
                r = kit.post_block(client, session, block)
                if r.status_code == 429:
                    break
                assert r.status_code == 202, r.text
                sent += 1
            assert r.status_code == 429, "the session never saturated"
            assert r.headers["retry-after"] == "1"
            assert "saturated" in r.json()["detail"] and f"resend block {blocks[sent].seq}" in r.json()["detail"]
            # Saturation comes from the window bound, counted before admission: QUEUE_WINDOWS complete windows
            # are waiting, so the block that would complete one more is refused (blocks that complete none are taken).
            assert sent == 25 * (QUEUE_WINDOWS + 1) - 1
            status = kit.session_status(client, session)
            assert status["last_seq"] == blocks[sent - 1].seq  # nothing of the refused block was taken
            assert status["state"] == "saturated" and status["counters"]["blocks_refused"] == 1
        for block in blocks[sent:]:  # the robot resends from the refused block
            while (r := kit.post_block(client, session, block)).status_code == 429:
                time.sleep(0.01)  # drains within milliseconds once the pool is free
            assert r.status_code == 202 and r.json()["duplicate"] is False
        final = kit.wait_for(lambda: (s := kit.session_status(client, session))["counters"]["windows"] >= 8 and s)
        assert final["counters"]["windows"] == 8 and final["counters"]["blocks_accepted"] == len(blocks)


def test_websocket_ingest_closes_4429_when_saturated(kit, tight_server, library_dir):
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_002", 2.0))
    with httpx.Client(base_url=tight_server.url, timeout=10) as client:
        session = kit.create_session(client)
        url = kit.socket_url(tight_server, session, "ingest")
        with kit.PoolStall(tight_server), connect(url) as ws:
            acked = 0
            with pytest.raises(ConnectionClosed):
                for block in blocks:
                    ws.send(encode_binary(block))
                    assert json.loads(ws.recv(timeout=5))["ok"] is True
                    acked += 1
            assert ws.close_code == Close.SATURATED and "saturated" in ws.close_reason
            assert acked == 25 * (QUEUE_WINDOWS + 1) - 1  # the block that would complete one window too many is refused
            assert kit.session_status(client, session)["last_seq"] == blocks[acked - 1].seq
        kit.wait_for(lambda: kit.session_status(client, session)["windows_ready"] == 0)
        with connect(url) as ws:  # reconnect and resend from the first unacknowledged block
            for block in blocks[acked:]:
                ws.send(encode_binary(block))
                assert json.loads(ws.recv(timeout=5)) == {"seq": block.seq, "ok": True, "duplicate": False}
        kit.wait_for(lambda: kit.session_status(client, session)["counters"]["windows"] == 4)


@pytest.mark.parametrize("transport", ["ws", "http"])
def test_the_robot_client_rides_out_saturation_and_loses_nothing(kit, tight_server, library_dir, transport):
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_004", 3.0))

    async def main():
        robot = RobotClient(
            tight_server.url,
            kit.BlockList(blocks),
            transport=transport,
            backoff=(0.05, 0.2),
            seed=1,
            api_key=kit.API_KEY,
        )
        stall = kit.PoolStall(tight_server)
        # the slow spell lasts until the robot has been refused, and half a second more of its retries
        spell = asyncio.create_task(stall.release_when(lambda: robot.stats.saturated > 0))
        stats = await robot.run()
        await spell
        return robot, stats

    robot, stats = asyncio.run(main())
    assert stats.saturated >= 1, "the client never saw the session saturated"
    assert stats.acked == len(blocks) and stats.lost == 0 and stats.rejected == 0 and stats.unsent == 0
    session = kit.robot_session(robot)
    with httpx.Client(base_url=tight_server.url, timeout=10) as client:
        status = kit.wait_for(lambda: (s := kit.session_status(client, session))["counters"]["windows"] >= 6 and s)
    assert status["counters"]["windows"] == 6
    assert status["counters"]["blocks_accepted"] == len(blocks)


def test_a_subscriber_that_never_reads_does_not_hold_back_another(kit, server, client, library_dir):
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_001", 20.0), block_s=0.5)
    session = kit.create_session(client)
    url = kit.socket_url(server, session, "events")
    # the idle client buffers one message and then stops reading its socket
    with connect(url, max_queue=1, close_timeout=0.2) as idle, connect(url) as reader:
        assert '"subscribed"' in idle.recv(timeout=5) and '"subscribed"' in reader.recv(timeout=5)
        for block in blocks:  # each block completes a window; sent as fast as the service takes them
            while (r := kit.post_block(client, session, block)).status_code == 429:
                time.sleep(0.02)
            assert r.status_code == 202
        windows = []
        while len(windows) < 40:
            event = json.loads(reader.recv(timeout=10))
            if event["type"] == "window":
                windows.append(event["window_index"])
    assert windows == list(range(40))


def test_a_frame_sent_while_the_previous_one_is_decoded_is_refused(kit, tight_server):
    with (
        httpx.Client(base_url=tight_server.url, timeout=10) as client,
        httpx.Client(base_url=tight_server.url, timeout=10) as other,
    ):
        session = kit.create_session(client)
        url = f"/sessions/{session['session_id']}/frames"
        headers = {"Authorization": f"Bearer {session['robot_token']}", "Content-Type": "image/png"}
        state = tight_server.app.state.service.sessions[session["session_id"]]
        with concurrent.futures.ThreadPoolExecutor(1) as sender:
            with kit.PoolStall(tight_server, "frame_pool"):  # frames are decoded in the frame pool
                first = sender.submit(other.post, url, content=kit.png(), headers=headers)  # waits behind the stall
                kit.wait_for(lambda: state.decoding_frame)
                second = client.post(url, content=kit.png(), headers=headers)
                assert second.status_code == 429 and "still decoding" in second.json()["detail"], second.text
                assert second.headers["retry-after"] == "1"
            assert first.result(timeout=10).status_code == 202
        assert client.post(url, content=kit.png(), headers=headers).status_code == 202  # and the next one is taken
