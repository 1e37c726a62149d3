"""Refuse early, answer always, on a real uvicorn: admission by what the process can serve, and probes that
answer from a thread of their own. Behaviour only (what is refused, how it is explained); speeds are measured
by `python -m benchmarks.admission`."""

from __future__ import annotations

import json
from dataclasses import replace

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from drivers.blocks import encode_binary


@pytest.fixture(scope="module")
def over_budget(kit, base_settings):
    """A replica whose event-loop CPU budget is below what even an idle loop uses: it is always over capacity (its
    lag limits out of reach: the machine's own load must not decide what this test sees)."""
    settings = base_settings.model_copy(
        update={"instance_id": "tight", "cpu_budget": 1e-6, "session_lag_s": 600, "shed_lag_s": 600}
    )
    with kit.running(settings) as srv:
        yield srv


def test_over_capacity_new_sessions_and_the_newest_sessions_blocks_are_refused_with_a_reason(
    kit, over_budget, library_dir
):
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_002", 1.0))
    with httpx.Client(base_url=over_budget.url, timeout=10) as client:
        oldest, newest = kit.create_session(client, "oldest"), kit.create_session(client, "newest")

        def refused_session() -> httpx.Response | None:
            for session in (oldest, newest):  # both stream, so both count as load
                kit.post_block(client, session, blocks[0])
            r = client.post("/sessions", json={"name": "one more"}, headers=kit.FLEET)
            return r if r.status_code == 429 else None

        r = kit.wait_for(refused_session, timeout_s=20)
        assert "at capacity" in r.json()["detail"] and "over its budget" in r.json()["detail"]
        assert float(r.headers["retry-after"]) > 0
        # the newest session's blocks are shed (nothing taken), the oldest streams on
        shed = kit.wait_for(lambda: (r := kit.post_block(client, newest, blocks[1])).status_code == 429 and r)
        assert "newest" in shed.json()["detail"] and float(shed.headers["retry-after"]) > 0
        for block in blocks[1:10]:
            assert kit.post_block(client, oldest, block).status_code == 202
        assert kit.session_status(client, newest)["counters"]["blocks_refused"] >= 1
        # over WebSocket: close 4429 with the reason, as for a saturated session
        with connect(kit.socket_url(over_budget, newest, "ingest")) as ws:
            ws.send(encode_binary(replace(blocks[2], seq=2)))
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=5)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 4429
        assert "capacity" in closed.value.rcvd.reason
        metrics = client.get("/metrics").text
        assert 'hapticlink_sessions_refused_total{reason="capacity"}' in metrics
        assert "hapticlink_loop_lag_seconds" in metrics and "hapticlink_loop_cpu_share" in metrics


def test_the_first_session_is_always_admitted(kit, base_settings):
    """Nothing to shed for: a replica without sessions admits one even over its budget."""
    settings = base_settings.model_copy(update={"instance_id": "tight-empty", "cpu_budget": 1e-6})
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        guard = srv.app.state.service.capacity
        kit.wait_for(lambda: guard.cpu_share > settings.cpu_budget, timeout_s=10)
        assert client.post("/sessions", json={"name": "first"}, headers=kit.FLEET).status_code == 201


def test_probes_answer_on_their_own_port_as_on_the_service_port(kit, base_settings):
    settings = base_settings.model_copy(update={"instance_id": "probed", "probe_port": 0})
    with kit.running(settings) as srv, httpx.Client(timeout=10) as client:
        port = srv.app.state.service.probes.port
        assert port and port != srv.port
        for path in ("/health", "/ready"):
            own, main = client.get(f"http://127.0.0.1:{port}{path}"), client.get(f"{srv.url}{path}")
            assert own.status_code == main.status_code == 200
            assert own.json() == main.json() and own.headers["content-type"] == "application/json"
        assert json.loads(client.get(f"http://127.0.0.1:{port}/ready").text)["ready"] is True
        assert client.get(f"http://127.0.0.1:{port}/sessions").status_code == 404
