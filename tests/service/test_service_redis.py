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
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

REDIS = shutil.which("redis-server")
pytestmark = pytest.mark.skipif(REDIS is None, reason="redis-server is not installed (apt-get install redis-server)")


@pytest.fixture(scope="module")
def redis_url(kit):
    port = kit.free_port()
    proc = subprocess.Popen(
        [REDIS, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
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
    with (
        kit.running(settings_a) as a,
        kit.running(settings_b) as b,
        httpx.Client(base_url=a.url, timeout=10) as client_a,
        httpx.Client(base_url=b.url, timeout=10) as client_b,
    ):
        session = kit.create_session(client_a)
        sid = session["session_id"]
        assert sid.startswith("replica-a.")

        # B knows the session through the shared directory, and sends its traffic to its owner
        misdirected = kit.post_block(client_b, session, blocks[0])
        assert misdirected.status_code == 421 and "replica-a" in misdirected.json()["detail"]
        with pytest.raises(InvalidStatus) as err:
            connect(f"{b.ws_url}/sessions/{sid}/events?token={session['robot_token']}")
        assert err.value.response.status_code == 403

        with (
            connect(kit.socket_url(b, session, "events")) as on_b,
            connect(kit.socket_url(a, session, "events")) as on_a,
        ):
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

            ended = client_a.delete(
                f"/sessions/{sid}", headers={"Authorization": f"Bearer {session['operator_token']}"}
            )
            assert ended.status_code == 200
            last = json.loads(on_b.recv(timeout=10))
            assert last["event"] == "session_ended"
        gone = client_b.get(f"/sessions/{sid}", headers={"Authorization": f"Bearer {session['operator_token']}"})
        assert gone.status_code == 404  # the directory entry went with the session


# ---- a replica that is gone -------------------------------------------------------------------------------
def _foreign_session(url: str, instance: str, incarnation: str, alive: bool) -> dict:
    """A directory entry as replica `instance` (process `incarnation`) writes it; its heartbeat key if alive."""
    from dataclasses import asdict

    from service.auth import issue_credentials
    from service.broker import ALIVE_PREFIX, DIRECTORY_PREFIX

    robot, operator, creds = issue_credentials()
    sid = f"{instance}.{incarnation}x"
    r = redis.Redis.from_url(url)
    r.hset(
        DIRECTORY_PREFIX + sid, mapping={"name": sid, "instance": instance, "incarnation": incarnation, **asdict(creds)}
    )
    if alive:
        r.set(ALIVE_PREFIX + instance, incarnation, px=600_000)
    return {"session_id": sid, "robot_token": robot, "operator_token": operator}


def _robot_error(url: str, session: dict, transport: str, library_dir) -> Exception:
    import asyncio

    from drivers.robot import RobotClient
    from drivers.simulated import SimulatedSource

    source = SimulatedSource.from_library(library_dir, "synth_001", realtime=False, duration_s=1.0)
    client = RobotClient(
        url,
        source,
        session_id=session["session_id"],
        robot_token=session["robot_token"],
        transport=transport,
        backoff=(0.01, 0.05),
        seed=1,
    )
    with pytest.raises(Exception) as err:
        asyncio.run(client.run())
    return err.value


@pytest.mark.slow
def test_when_a_replicas_heartbeat_lapses_its_sessions_are_lost_for_operators_and_robots(
    kit, base_settings, redis_url, library_dir
):
    settings = base_settings.model_copy(update={"broker": "redis", "redis_url": redis_url, "instance_id": "replica-b"})
    session = _foreign_session(redis_url, "replica-z", "cafe01", alive=True)
    sid, auth = session["session_id"], {"Authorization": f"Bearer {session['operator_token']}"}
    with kit.running(settings) as b, httpx.Client(base_url=b.url, timeout=10) as client:
        assert client.get(f"/sessions/{sid}", headers=auth).status_code == 421  # alive elsewhere: route it there
        with connect(kit.socket_url(b, session, "events")) as operator:
            assert json.loads(operator.recv(timeout=5))["event"] == "subscribed"
            from service.broker import ALIVE_PREFIX

            redis.Redis.from_url(redis_url).delete(ALIVE_PREFIX + "replica-z")  # replica-z stops beating
            ended = json.loads(operator.recv(timeout=30))  # replica-b's watcher notices within a heartbeat or two
            assert ended["event"] == "session_ended" and ended["lost"] is True and "replica-z" in ended["message"]
        gone = client.get(f"/sessions/{sid}", headers=auth)
        assert gone.status_code == 410 and "replica-z is gone" in gone.json()["detail"]
        assert "open a new session" in gone.json()["detail"]
        with pytest.raises(InvalidStatus) as refused:
            connect(kit.socket_url(b, session, "ingest"))
        assert refused.value.response.status_code == 410
        assert "hapticlink_sessions_lost_total 1" in client.get("/metrics", headers=kit.SCRAPER).text
        for transport in ("ws", "http"):  # the robot client stops with the reason instead of retrying forever
            error = _robot_error(b.url, session, transport, library_dir)
            assert type(error).__name__ == "SessionLostError" and "open a new session" in str(error), repr(error)


def test_a_restarted_replica_answers_410_for_its_previous_processs_sessions(kit, base_settings, redis_url):
    """Same instance id, new process: the old sessions' state died with the old process (it used to answer 421,
    naming itself as the owner)."""
    settings = base_settings.model_copy(update={"broker": "redis", "redis_url": redis_url, "instance_id": "replica-c"})
    session = _foreign_session(redis_url, "replica-c", "0ld0ld", alive=False)
    with kit.running(settings) as c, httpx.Client(base_url=c.url, timeout=10) as client:
        r = client.get(
            f"/sessions/{session['session_id']}", headers={"Authorization": f"Bearer {session['operator_token']}"}
        )
        assert r.status_code == 410 and "replica-c is gone" in r.json()["detail"]


def test_a_replica_whose_heartbeat_lapsed_ends_the_sessions_others_marked_lost(
    kit, base_settings, redis_url, library_dir
):
    from drivers.blocks import encode_binary
    from drivers.protocol import Close

    settings = base_settings.model_copy(update={"broker": "redis", "redis_url": redis_url, "instance_id": "replica-d"})
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_001", 0.2))
    with kit.running(settings) as a, httpx.Client(base_url=a.url, timeout=10) as client:
        session = kit.create_session(client)
        restored = kit.create_session(client)
        from service.broker import ALIVE_PREFIX, DIRECTORY_PREFIX

        with connect(kit.socket_url(a, session, "ingest")) as robot:
            robot.send(encode_binary(blocks[0]))
            assert json.loads(robot.recv(timeout=10))["ok"] is True
            r = redis.Redis.from_url(redis_url)
            # replica-d was silent past its heartbeat's TTL: another replica marked its session lost (and told its
            # operators), and Redis restarted in between, losing another session's entry
            r.delete(ALIVE_PREFIX + "replica-d", DIRECTORY_PREFIX + restored["session_id"])
            r.hset(DIRECTORY_PREFIX + session["session_id"], "lost", "its replica replica-d is gone (test)")
            # its next beat sees the lapse: it ends the session marked lost, and re-enters the one Redis forgot
            auth = {"Authorization": f"Bearer {session['operator_token']}"}
            kit.wait_for(lambda: client.get(f"/sessions/{session['session_id']}", headers=auth).status_code == 410)
            kit.wait_for(lambda: r.exists(DIRECTORY_PREFIX + restored["session_id"]))
            assert kit.session_status(client, restored)["instance"] == "replica-d"  # still served
            # the robot still connected learns it on its next block: close 4410 with the reason (not 1000 "ended")
            robot.send(encode_binary(blocks[1]))
            with pytest.raises(ConnectionClosed) as closed:
                robot.recv(timeout=10)
        assert closed.value.rcvd.code == Close.LOST, closed.value.rcvd
        assert "is lost: its replica replica-d is gone" in closed.value.rcvd.reason


def test_a_replica_shutting_down_tells_robots_and_operators_on_other_replicas_to_start_over(
    kit, base_settings, redis_url
):
    common = {"broker": "redis", "redis_url": redis_url}
    settings_a = base_settings.model_copy(update={**common, "instance_id": "replica-f"})
    settings_b = base_settings.model_copy(update={**common, "instance_id": "replica-g"})
    with kit.running(settings_b) as b, httpx.Client(base_url=b.url, timeout=10) as client_b:
        a = kit.ServerThread(settings_a).start()
        try:
            with httpx.Client(base_url=a.url, timeout=10) as client_a:
                session = kit.create_session(client_a)
            with connect(kit.socket_url(b, session, "events")) as operator:
                assert json.loads(operator.recv(timeout=5))["event"] == "subscribed"
                a.stop()  # graceful (SIGTERM in a container): its sessions end with it
                ended = json.loads(operator.recv(timeout=10))
                assert (
                    ended["event"] == "session_ended"
                    and ended["lost"] is True
                    and "replica-f shut down" in ended["message"]
                )
        finally:
            a.stop()
        r = client_b.get(
            f"/sessions/{session['session_id']}", headers={"Authorization": f"Bearer {session['operator_token']}"}
        )
        assert r.status_code == 410 and "replica-f shut down; open a new session" in r.json()["detail"]
