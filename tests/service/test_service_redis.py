"""Two replicas sharing a real redis-server: a window processed on A reaches an operator connected to B."""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
import time

import httpx
import pytest
import redis
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

REDIS = shutil.which("redis-server")
pytestmark = pytest.mark.skipif(REDIS is None, reason="redis-server is not installed (apt-get install redis-server)")


@pytest.fixture(scope="module")
def redis_url(kit):
    port = kit.free_port()
    proc = subprocess.Popen([REDIS, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"redis://127.0.0.1:{port}/0"
    try:
        deadline = time.monotonic() + 10
        while True:
            try:
                redis.Redis.from_url(url).ping()
                break
            except redis.ConnectionError:
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError("redis-server did not start") from None
                time.sleep(0.05)
        yield url
    finally:
        proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=5)


def test_events_cross_replicas_through_redis(kit, base_settings, redis_url, library_dir):
    common = {"broker": "redis", "redis_url": redis_url}
    settings_a = base_settings.model_copy(update={**common, "instance_id": "replica-a"})
    settings_b = base_settings.model_copy(update={**common, "instance_id": "replica-b"})
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_002", 2.0))
    with kit.running(settings_a) as a, kit.running(settings_b) as b, \
            httpx.Client(base_url=a.url, timeout=10) as client_a, httpx.Client(base_url=b.url, timeout=10) as client_b:
        session = kit.create_session(client_a)
        sid = session["session_id"]
        assert sid.startswith("replica-a.")

        # B knows the session through the shared directory, and sends its traffic to its owner
        misdirected = kit.post_block(client_b, session, blocks[0])
        assert misdirected.status_code == 421 and "replica-a" in misdirected.json()["detail"]
        with pytest.raises(InvalidStatus) as err:
            connect(f"{b.ws_url}/sessions/{sid}/events?token={session['robot_token']}")
        assert err.value.response.status_code == 403

        with connect(kit.socket_url(b, session, "events")) as on_b, connect(kit.socket_url(a, session, "events")) as on_a:
            assert json.loads(on_b.recv(timeout=5))["instance"] == "replica-b"
            assert json.loads(on_a.recv(timeout=5))["instance"] == "replica-a"
            for block in blocks:
                assert kit.post_block(client_a, session, block).status_code == 202
            received = {}
            for name, sub in (("a", on_a), ("b", on_b)):
                windows = []
                while len(windows) < 4:
                    event = json.loads(sub.recv(timeout=10))
                    if event["type"] == "window":
                        windows.append(event)
                received[name] = windows
            assert [w["window_index"] for w in received["b"]] == [0, 1, 2, 3]
            assert received["a"] == received["b"]  # the same events, byte for byte, on both replicas

            ended = client_a.delete(f"/sessions/{sid}", headers={"Authorization": f"Bearer {session['operator_token']}"})
            assert ended.status_code == 200
            last = json.loads(on_b.recv(timeout=10))
            assert last["event"] == "session_ended"
        gone = client_b.get(f"/sessions/{sid}", headers={"Authorization": f"Bearer {session['operator_token']}"})
        assert gone.status_code == 404  # the directory entry went with the session
