"""A ROS 2 bag of a simulated stroke, replayed through a real service (uvicorn on loopback, the robot client over
WebSocket), gives the estimates the simulated robot gives streaming the same stroke directly."""

from __future__ import annotations

import asyncio
import json
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from websockets.sync.client import connect

from drivers.blocks import SampleBlock
from drivers.robot.client import RobotClient
from drivers.rosbag_source import RosbagSource
from drivers.rosbag_writer import stroke_messages, write_bag
from drivers.simulated import SimulatedSource
from texture_library.library import Library

SECONDS = 4.0
#: raw ratings (−100…100) of the bag's windows against the simulated robot's: the same accel; force and speed at
#: 500 Hz and 100 Hz in the bag, so their statistics move a little (tests/drivers/test_rosbag_source.py bounds the
#: features)
RATING_ATOL = 1.0
QUIET_S = 5.0


class _Items:
    """The simulated robot's items, captured once, sent again as a source."""

    name = "captured"

    def __init__(self, items) -> None:
        self.items = items

    async def _gen(self):
        for item in self.items:
            await asyncio.sleep(0)
            yield item

    def __aiter__(self):
        return self._gen()

    async def aclose(self) -> None:
        pass


def _windows(kit, server, source) -> list[dict]:
    """Stream `source` into a new session with the robot client; the session's window events, until none has come
    for QUIET_S after the robot has delivered every block."""
    with httpx.Client(base_url=server.url, timeout=10) as client:
        session = kit.create_session(client, "rosbag")
    with connect(kit.socket_url(server, session, "events")) as sub:
        assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"
        robot = RobotClient(
            server.url, source, session_id=session["session_id"], robot_token=session["robot_token"], transport="ws"
        )
        stats = asyncio.run(robot.run())
        assert stats.lost == stats.rejected == stats.unsent == 0
        windows: list[dict] = []
        while True:
            try:
                event = json.loads(sub.recv(timeout=QUIET_S))
            except TimeoutError:
                return windows
            if event["type"] == "window":
                windows.append(event)


@pytest.mark.slow
@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_bag_replayed_through_the_service_gives_the_simulated_robots_estimates(
    kit, server, library_dir, tmp_path, storage
):
    # IMU 1 kHz, wrench 500 Hz, twist 100 Hz and the texture's photo as a CompressedImage at 5 Hz
    items, bag = _stroke_bag(library_dir, "synth_002", 5, SECONDS, tmp_path / "bag", storage, photo=True)
    sim = _windows(kit, server, _Items(items))
    got = _windows(kit, server, RosbagSource(bag, realtime=False))
    assert len(sim) >= 5
    # the last window of the stream ends where the bag ends: the service's resampler holds a slow (100 Hz) channel's
    # last samples back for the block that never comes, so that one window goes unestimated, and only that one
    assert [w["window_index"] for w in got] == list(range(len(sim) - 1))
    assert [w["window_index"] for w in sim] == list(range(len(sim)))
    start = got[0]["t_start_s"]
    assert start == pytest.approx(1_700_000_000.0), "windows on the robot's clock: the bag's header stamps"
    assert [w["t_start_s"] - start for w in got] == pytest.approx([w["t_start_s"] for w in sim[:-1]], abs=1e-6)
    for a, b in zip(got, sim):
        assert a["raw_ratings"] == pytest.approx(b["raw_ratings"], abs=RATING_ATOL), (a["window_index"], a, b)
        assert a["chosen"] == b["chosen"]


async def _take(source) -> list:
    return [item async for item in source]


def _events_until_quiet(sub) -> list[dict]:
    """Every event the feed socket `sub` still sends, until it stays quiet for 1 s."""
    feed = []
    while True:
        try:
            feed.append(json.loads(sub.recv(timeout=1.0)))
        except TimeoutError:
            return feed


async def _stream_bag(server, session: dict, bag) -> None:
    """A robot streams the bag into the session as fast as it is taken, then QUIET_S passes: the last windows are
    estimated and published."""
    await RobotClient(
        server.url,
        RosbagSource(bag, realtime=False),
        session_id=session["session_id"],
        robot_token=session["robot_token"],
    ).run()
    await asyncio.sleep(QUIET_S)


def _stroke_bag(library_dir, texture: str, seed: int, seconds: float, folder, storage: str, photo: bool = False):
    """A simulated robot's stroke of a library texture (its items, as the source yields them) and the bag written
    from it: IMU 1 kHz, wrench 500 Hz, twist 100 Hz, and with `photo` the texture's photo as a CompressedImage at
    5 Hz. → (items, bag path)."""
    library = Library.load(library_dir)
    image = library.image(texture) if photo else None
    assert image is not None or not photo
    items = asyncio.run(_take(SimulatedSource(library.model(texture), seed=seed, realtime=False, duration_s=seconds)))
    blocks = [i for i in items if isinstance(i, SampleBlock)]
    accel, force, speed = (np.concatenate([b.channels[k].data for b in blocks]) for k in ("accel", "force", "speed"))
    return items, write_bag(folder, stroke_messages(accel, force, speed, 1000.0, image), storage)


def test_hapticlink_record_writes_every_event_of_the_feed_as_mcap_on_the_robots_clock(
    kit, server, library_dir, tmp_path
):
    """A bag streamed into a session while `SessionRecorder` (hapticlink record --mcap) and an operator follow its
    feed: the MCAP file opens with the mcap reader, its channels carry JSON schemas, it holds every event the
    operator's feed carried, and each window is logged at its end on the robot's clock (the bag's header stamps)."""
    from mcap.reader import make_reader

    from drivers.estimates_mcap import CHANNELS, EstimatesMcap, SessionRecorder

    _, bag = _stroke_bag(library_dir, "synth_003", 7, SECONDS, tmp_path / "bag", "mcap")
    out = tmp_path / "estimates.mcap"
    with httpx.Client(base_url=server.url, timeout=10) as client:
        session = kit.create_session(client, "record")
    with connect(kit.socket_url(server, session, "events")) as sub:
        assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"

        async def main() -> int:
            fh = out.open("wb")
            recorder = SessionRecorder(
                server.url, session["session_id"], session["operator_token"], [EstimatesMcap(fh)]
            )
            task = asyncio.ensure_future(recorder.run())
            await asyncio.wait_for(recorder.subscribed.wait(), 10)
            await _stream_bag(server, session, bag)
            recorder.stop()
            written = await task
            fh.close()
            return written

        written = asyncio.run(main())
        feed = _events_until_quiet(sub)
    with out.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {s.id: s for s in summary.schemas.values()}
        topics = {c.topic: schemas[c.schema_id] for c in summary.channels.values()}
        assert set(topics) == set(CHANNELS)
        assert all(s.encoding == "jsonschema" and json.loads(s.data)["type"] == "object" for s in topics.values())
        recorded: dict[str, list] = {t: [] for t in CHANNELS}
        for _, channel, message in reader.iter_messages(log_time_order=False):
            recorded[channel.topic].append((message.log_time, json.loads(message.data)))
    windows = [e for e in feed if e["type"] == "window"]
    assert len(windows) >= 5
    assert [e for _, e in recorded["/hapticlink/window"]] == windows, "every window event, whole, in order"
    statuses = [e for e in feed if e["type"] == "status"]
    assert [e for _, e in recorded["/hapticlink/status"]][1:] == statuses, "and every status (after its own hello)"
    assert written == len(windows) + len(statuses) + 1
    for topic in ("/hapticlink/ratings", "/hapticlink/ood", "/hapticlink/model", "/hapticlink/latency"):
        assert [m["window_index"] for _, m in recorded[topic]] == [w["window_index"] for w in windows]
    for (log_ns, ratings), w in zip(recorded["/hapticlink/ratings"], windows):
        assert log_ns == round(w["t_end_s"] * 1e9) and ratings["interval"] == w["interval"]
        assert ratings["ratings"] == w["ratings"] and ratings["raw_ratings"] == w["raw_ratings"]
    assert recorded["/hapticlink/window"][0][0] == pytest.approx(1_700_000_000.5e9, abs=1e3), "the bag's clock"
    models = [m for _, m in recorded["/hapticlink/model"]]
    assert all(
        m["chosen"] == w["chosen"] and m["chosen_model_version"] == w["chosen_model_version"]
        for m, w in zip(models, windows)
    )


async def _foxglove_client(url: str, ready: asyncio.Event, received: list, channels: dict) -> None:
    """A Foxglove WebSocket protocol client: reads serverInfo and the advertised channels, subscribes to every one,
    and keeps each message data frame (opcode 1: subscription id, log time ns, payload) until cancelled."""
    import struct

    from websockets.asyncio.client import connect as connect_async

    async with connect_async(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:
        assert json.loads(await ws.recv())["op"] == "serverInfo"
        advertise = json.loads(await ws.recv())
        assert advertise["op"] == "advertise"
        channels.update({c["id"]: c for c in advertise["channels"]})
        subs = [{"id": k, "channelId": cid} for k, cid in enumerate(channels)]
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        topic_of = {s["id"]: channels[s["channelId"]]["topic"] for s in subs}
        await asyncio.sleep(0.2)  # the server takes the subscription before anything is logged
        ready.set()
        async for frame in ws:
            if isinstance(frame, bytes) and frame[0] == 1:
                sub_id, log_ns = struct.unpack_from("<IQ", frame, 1)
                received.append((topic_of[sub_id], log_ns, json.loads(frame[13:])))


def test_record_publishes_the_same_channels_live_to_a_foxglove_client(kit, server, library_dir, tmp_path):
    """`hapticlink record --foxglove`: a Foxglove WebSocket protocol client sees the channels advertised with their
    JSON schemas and receives every window's messages the operator's feed carried, at the robot's clock."""
    from drivers.estimates_foxglove import FoxgloveLive
    from drivers.estimates_mcap import CHANNELS, SessionRecorder

    _, bag = _stroke_bag(library_dir, "synth_001", 9, SECONDS, tmp_path / "bag", "sqlite3")
    with httpx.Client(base_url=server.url, timeout=10) as client:
        session = kit.create_session(client, "foxglove")
    received: list = []
    channels: dict = {}
    with connect(kit.socket_url(server, session, "events")) as sub:
        assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"

        async def main() -> None:
            live = FoxgloveLive(port=0)
            recorder = SessionRecorder(server.url, session["session_id"], session["operator_token"], [live])
            ready = asyncio.Event()
            client_task = asyncio.ensure_future(_foxglove_client(live.url, ready, received, channels))
            await asyncio.wait_for(ready.wait(), 10)
            task = asyncio.ensure_future(recorder.run())
            await asyncio.wait_for(recorder.subscribed.wait(), 10)
            await _stream_bag(server, session, bag)
            client_task.cancel()
            await asyncio.gather(client_task, return_exceptions=True)
            recorder.stop()
            await task

        asyncio.run(main())
        feed = _events_until_quiet(sub)
    assert {c["topic"]: c["schemaName"] for c in channels.values()} == {t: n for t, (n, _, _) in CHANNELS.items()}
    assert all(c["encoding"] == "json" and c["schemaEncoding"] == "jsonschema" for c in channels.values())
    assert all(json.loads(c["schema"]) == CHANNELS[c["topic"]][1] for c in channels.values())
    windows = [e for e in feed if e["type"] == "window"]
    assert len(windows) >= 5
    by_topic: dict[str, list] = {}
    for topic, log_ns, payload in received:
        by_topic.setdefault(topic, []).append((log_ns, payload))
    assert [p for _, p in by_topic["/hapticlink/window"]] == windows
    for (log_ns, ratings), w in zip(by_topic["/hapticlink/ratings"], windows):
        assert log_ns == round(w["t_end_s"] * 1e9) and ratings["ratings"] == w["ratings"]
    for topic in ("/hapticlink/ood", "/hapticlink/model", "/hapticlink/latency"):
        assert [p["window_index"] for _, p in by_topic[topic]] == [w["window_index"] for w in windows]
    statuses = [e for e in feed if e["type"] == "status"]
    assert [p for _, p in by_topic["/hapticlink/status"]][1:] == statuses


#: how soon `hapticlink record` must exit after Ctrl-C, s: its own bounds are 2 s for the feed's close and 3 s for the
#: Foxglove server's stop; the rest is slack for a busy host
CTRL_C_EXIT_S = 20.0
#: the stroke streamed while one Foxglove client stalls, s: ~40 windows, more than the stalled connection's buffers
#: hold
STALL_SECONDS = 20.0
#: 4 kB messages sent to a stalled client in the server-level test: 32 MB, more than its connection's buffers hold (up
#: to 16 MB of kernel send buffer) and the server's backlog of 1024 messages
STALLED_MESSAGES = 8000
REPO = Path(__file__).resolve().parents[2]
#: a Foxglove WebSocket protocol client in its own process (argv: the port): subscribes to every advertised channel,
#: prints "subscribed", then the topic of each message it receives, then "closed" when the server ends the
#: connection. Its receive buffer is small, so that once it stalls (SIGSTOP) what the server sends it piles up.
FOXGLOVE_CLIENT = """
import json, socket, struct, sys, time
from websockets.sync.client import connect
port = int(sys.argv[1])
deadline = time.monotonic() + 180
while True:
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        sock.connect(("127.0.0.1", port))
        break
    except OSError:
        sock.close()
        if time.monotonic() > deadline:
            raise
        time.sleep(0.2)
with connect(f"ws://127.0.0.1:{port}", sock=sock, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
             max_queue=1) as ws:
    channels = {}
    while not channels:
        m = json.loads(ws.recv())
        if m["op"] == "advertise":
            channels = {c["id"]: c["topic"] for c in m["channels"]}
    subs = [{"id": k, "channelId": c} for k, c in enumerate(channels)]
    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
    topic_of = {s["id"]: channels[s["channelId"]] for s in subs}
    print("subscribed", flush=True)
    try:
        for frame in ws:
            if isinstance(frame, bytes) and frame[0] == 1:
                print(topic_of[struct.unpack_from("<I", frame, 1)[0]], flush=True)
    except Exception as exc:
        print(type(exc).__name__, flush=True)
print("closed", flush=True)
"""


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class _Lines:
    """A child process's output lines, read in a thread as they come."""

    def __init__(self, proc: subprocess.Popen) -> None:
        import queue
        import threading

        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._read, args=(proc,), daemon=True).start()

    def _read(self, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            self.lines.put(line.decode(errors="replace").strip())

    def wait_for(self, text: str, timeout_s: float) -> None:
        import queue

        deadline = time.monotonic() + timeout_s
        while text not in self.seen:
            try:
                self.seen.append(self.lines.get(timeout=max(0.01, deadline - time.monotonic())))
            except queue.Empty:
                raise TimeoutError(f"{text!r} not seen in {timeout_s:g} s; seen {self.seen[-5:]}") from None


def _subscribers(client: httpx.Client, kit) -> int:
    """The operator event connections open on the server (its hapticlink_subscribers gauge)."""
    found = re.search(r"^hapticlink_subscribers (\S+)$", client.get("/metrics", headers=kit.SCRAPER).text, re.M)
    assert found is not None, "no hapticlink_subscribers gauge on /metrics"
    return int(float(found.group(1)))


def test_record_stops_on_ctrl_c_with_foxglove_clients_connected(kit, server, library_dir, tmp_path):
    """A real `hapticlink record --mcap OUT --foxglove PORT` process follows a live session with two Foxglove
    protocol clients (each its own process) subscribed: one keeps reading, one stalls (a viewer's laptop asleep:
    SIGSTOP), so what the server sends it piles up. Ctrl-C (SIGINT) while the session is
    still open ends the recorder promptly with status 0 or 130, the MCAP file finished (it opens with the mcap reader
    and holds every window the feed carried), the reading client told that the connection ended. (The Foxglove
    server's stop waits for ever on the stalled client's unsent messages: the recorder bounds that wait.)"""
    from mcap.reader import make_reader

    from drivers.estimates_mcap import CHANNELS

    _, bag = _stroke_bag(library_dir, "synth_004", 11, STALL_SECONDS, tmp_path / "bag", "mcap")
    with httpx.Client(base_url=server.url, timeout=10) as client:
        session = kit.create_session(client, "ctrl-c")
        before = _subscribers(client, kit)  # the recorder's feed and the test's own come on top
    port, out = _free_port(), tmp_path / "estimates.mcap"
    argv = [sys.executable, "-m", "service.cli", "record", "--url", server.url, "--session", session["session_id"]]
    argv += ["--token", session["operator_token"], "--mcap", str(out), "--foxglove", f"127.0.0.1:{port}"]
    procs = [subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)]
    recorder = procs[0]
    try:
        clients = []
        for _ in range(2):
            procs.append(
                subprocess.Popen(
                    [sys.executable, "-c", FOXGLOVE_CLIENT, str(port)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT
                )
            )
            clients.append(_Lines(procs[-1]))
        reading = clients[0]
        for c in clients:
            c.wait_for("subscribed", 240)  # the recorder's process starts slowly on a busy host
        procs[2].send_signal(signal.SIGSTOP)  # the stalled viewer
        with connect(kit.socket_url(server, session, "events")) as sub:
            assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"
            # the recorder subscribes to the feed right after its Foxglove server listens: stream once it has
            with httpx.Client(base_url=server.url, timeout=10) as client:
                kit.wait_for(lambda: _subscribers(client, kit) >= before + 2, timeout_s=60)

            asyncio.run(_stream_bag(server, session, bag))  # the session stays open
            feed = _events_until_quiet(sub)
        reading.wait_for("/hapticlink/window", 10)
        assert recorder.poll() is None, "only Ctrl-C ends the recorder here"
        t0 = time.monotonic()
        recorder.send_signal(signal.SIGINT)
        try:
            said = recorder.communicate(timeout=CTRL_C_EXIT_S)[0].decode(errors="replace")
        except subprocess.TimeoutExpired:
            pytest.fail(f"hapticlink record still running {CTRL_C_EXIT_S:g} s after Ctrl-C")
        took = time.monotonic() - t0
        reading.wait_for("closed", 10)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    assert recorder.returncode in (0, 130), said
    assert "Traceback" not in said and "recorded" in said, said
    assert took < CTRL_C_EXIT_S
    windows = [e for e in feed if e["type"] == "window"]
    assert len(windows) >= 5
    with out.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None, "the file was finished: its summary written"
        assert {c.topic for c in summary.channels.values()} == set(CHANNELS)
        recorded = [json.loads(m.data) for _, c, m in reader.iter_messages() if c.topic == "/hapticlink/window"]
    assert recorded == windows


def test_a_stalled_foxglove_client_does_not_hold_up_the_recorders_end(caplog):
    """A Foxglove client that stops reading (SIGSTOP) with megabytes sent to it unread: foxglove-sdk's server.stop()
    waits for ever to flush them; FoxgloveLive.close() returns after STOP_WAIT_S, says so, and the server's stop
    completes once the client is gone."""
    import threading

    from drivers.estimates_foxglove import STOP_WAIT_S, FoxgloveLive

    live = FoxgloveLive(port=0)
    client = subprocess.Popen(
        [sys.executable, "-c", FOXGLOVE_CLIENT, str(live.port)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )
    try:
        _Lines(client).wait_for("subscribed", 120)
        client.send_signal(signal.SIGSTOP)
        payload = {"type": "status", "event": "padding", "message": "x" * 4000}
        for k in range(STALLED_MESSAGES):  # more than the socket buffers and the backlog hold
            live.log("/hapticlink/status", payload, k)
        time.sleep(1.0)  # the server's writer fills the socket
        t0 = time.monotonic()
        with caplog.at_level("WARNING", logger="hapticlink.record"):
            live.close()
        took = time.monotonic() - t0
        assert STOP_WAIT_S - 0.1 <= took < STOP_WAIT_S + 5.0, "it waited its bound, then went on"
        assert "did not stop within" in caplog.text
        stopper = next(t for t in threading.enumerate() if t.name == "foxglove-stop")
    finally:
        client.kill()
        client.wait()
    stopper.join(30)
    assert not stopper.is_alive(), "the server's stop completes once the stalled client is gone"
