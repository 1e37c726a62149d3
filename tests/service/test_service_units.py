"""The service's small parts on their own: auth, smoothing/steadiness, stream admission, broker queues, metrics,
settings."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest
from fastapi import FastAPI, Request
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from drivers.blocks import ChannelBlock, SampleBlock
from models.tactile.config import TactileConfig
from models.tactile.stream import StreamContract
from service.app import _service_error
from service.auth import EITHER, OPERATOR_ONLY, ROBOT_ONLY, Role, authorize, issue_credentials
from service.broker import InMemoryBroker, LatestQueue
from service.errors import ServiceError
from service.limits import BodySizeLimit, BodyTooLarge, limit_body
from service.live_session import canonical_channels
from service.metrics import ServiceMetrics
from service.settings import Settings, env_name, settings_table
from service.smoothing import SD_UNIFORM, ExponentialSmoother, Steadiness


# ---- auth ------------------------------------------------------------------------------------------
def test_tokens_open_only_their_role_and_session():
    robot, operator, creds = issue_credentials()
    _, other_operator, _ = issue_credentials()
    assert robot != operator and len(robot) >= 40
    assert authorize(creds, robot, ROBOT_ONLY, "s") is Role.ROBOT
    assert authorize(creds, operator, OPERATOR_ONLY, "s") is Role.OPERATOR
    assert authorize(creds, operator, EITHER, "s") is Role.OPERATOR
    for token, allowed, status in (
        (None, ROBOT_ONLY, 401),
        (other_operator, OPERATOR_ONLY, 401),
        (operator, ROBOT_ONLY, 403),
        (robot, OPERATOR_ONLY, 403),
    ):
        with pytest.raises(ServiceError) as err:
            authorize(creds, token, allowed, "s")
        assert err.value.status == status
    # only digests are kept
    assert robot not in repr(creds) and operator not in repr(creds)


# ---- smoothing and steadiness ----------------------------------------------------------------------
def test_ema_passes_the_first_window_then_blends():
    ema = ExponentialSmoother(0.25)
    assert np.allclose(ema.update(np.array([40.0, 0, 0, 0])), [40, 0, 0, 0])
    assert np.allclose(ema.update(np.array([0.0, 80, 0, 0])), [30, 20, 0, 0])
    with pytest.raises(ValueError):
        ExponentialSmoother(0.0)


def test_steadiness_is_one_for_agreement_and_falls_with_spread():
    conf = Steadiness(4)
    assert np.all(conf.update(np.full(4, 10.0)) == 0)  # one window: unknown
    assert np.allclose(conf.update(np.full(4, 10.0)), 1.0)
    spread = Steadiness(2)
    spread.update(np.array([-100.0, 0, 0, 0]))
    c = spread.update(np.array([100.0, 0, 0, 0]))
    assert c[0] == 0.0  # sd 100 > the uniform sd → clipped at 0
    assert np.allclose(c[1:], 1.0)
    mild = Steadiness(2)
    mild.update(np.zeros(4))
    assert np.isclose(mild.update(np.array([20.0, 0, 0, 0]))[0], 1 - 10 / SD_UNIFORM)


# ---- stream admission ------------------------------------------------------------------------------
def _block(t0, n=20, rate=1000.0, seq=0, kinds=("accel", "force", "speed"), accel_units="m/s^2", force_cols=1):
    chans = {}
    if "accel" in kinds:
        chans["accel"] = ChannelBlock(np.ones((n, 3), np.float32), rate, accel_units)
    if "force" in kinds:
        shape = (n,) if force_cols == 1 else (n, force_cols)
        chans["force"] = ChannelBlock(np.ones(shape, np.float32), rate, "N")
    if "speed" in kinds:
        chans["speed"] = ChannelBlock(np.ones(n, np.float32), rate, "mm/s")
    if "position" in kinds:
        chans["position"] = ChannelBlock(np.arange(n, dtype=np.float32), rate, "mm")
    return SampleBlock(t0, chans, seq)


class _Admission:
    """The session's admission step alone: canonical units, then StreamContract.admit."""

    def __init__(self, max_lag_s: float = 5) -> None:
        self.contract = StreamContract(TactileConfig(), max_lag_s=max_lag_s, max_block_s=1.0, max_block_windows=4)
        self.cursor = self.contract.start()

    def admit(self, block: SampleBlock):
        adv = self.contract.admit(self.cursor, canonical_channels(block), block.t0)
        self.cursor = adv.cursor
        return adv


def test_admission_counts_windows_by_stream_time():
    adm = _Admission()
    for k in range(24):
        adv = adm.admit(_block(k * 0.02, seq=k))
    assert adv.windows_after == 0
    adv = adm.admit(_block(24 * 0.02, seq=24))  # 500 samples: the first window is complete
    assert adv.windows_after == 1 and adv.windows_added == 1


def test_admission_converts_units_to_canonical():
    admitted = _Admission().admit(_block(0.0, accel_units="g"))
    assert np.allclose(admitted.channels["accel"].data, 9.80665)


@pytest.mark.parametrize(
    "second, message",
    [
        (_block(0.02, rate=2000.0), "rate changed"),
        (_block(0.02, force_cols=3), "column count changed"),
    ],
)
def test_admission_refuses_contradictions_and_keeps_state(second, message):
    adm = _Admission()
    adm.admit(_block(0.0))
    before = adm.cursor
    with pytest.raises(ValueError, match=message):
        adm.admit(second)
    assert adm.cursor == before
    adm.admit(_block(0.02, seq=1))  # the stream continues


def test_speed_after_position_is_refused_position_after_speed_ignored():
    pos = _Admission()
    pos.admit(_block(0.0, kinds=("accel", "force", "position")))
    with pytest.raises(ValueError, match="speed"):
        pos.admit(_block(0.02, kinds=("accel", "force", "speed")))
    spd = _Admission()
    spd.admit(_block(0.0))
    admitted = spd.admit(_block(0.02, kinds=("accel", "force", "speed", "position")))
    assert "position" not in admitted.channels


def test_a_missing_channel_is_refused_once_it_lags_too_far():
    adm = _Admission(max_lag_s=0.1)
    for k in range(5):
        adm.admit(_block(k * 0.02, kinds=("accel", "speed")))
    with pytest.raises(ValueError, match="force lag"):
        adm.admit(_block(0.1, kinds=("accel", "speed")))


def test_a_time_gap_starts_a_new_segment():
    adm = _Admission()
    a = adm.admit(_block(10.0)).cursor
    b = adm.admit(_block(10.02, seq=1)).cursor
    c = adm.admit(_block(11.0, seq=2))  # 0.96 s missing
    assert a.segment == b.segment == 0 and c.new_segment and c.cursor.segment == 1
    assert c.cursor.origin_t0 == 11.0 and c.cursor.samples["accel"] == 20


# ---- broker ----------------------------------------------------------------------------------------
def test_latest_queue_keeps_the_newest_and_counts_drops():
    async def main():
        q = LatestQueue(3)
        for i in range(10):
            q.offer(str(i))
        q.offer("end", final=True)
        q.offer("after")  # ignored: the subscription ended
        got = []
        while (item := await q.get()) is not None:
            got.append(item)
        return got, q.dropped

    got, dropped = asyncio.run(main())
    assert got == ["8", "9", "end"] and dropped == 8


def test_a_slow_subscriber_never_holds_back_the_others():
    async def main():
        broker = InMemoryBroker(subscriber_queue=4)
        slow = await broker.subscribe("s")
        fast = await broker.subscribe("s")
        received = []

        async def read_fast():
            while (text := await fast.get()) is not None:
                received.append(json.loads(text)["i"])

        reader = asyncio.create_task(read_fast())
        for i in range(100):
            await broker.publish("s", json.dumps({"i": i}))
            await asyncio.sleep(0)  # the fast reader keeps up
        await broker.publish("s", json.dumps({"i": "end"}), final=True)
        await reader
        slow_items = []
        while (text := await slow.get()) is not None:
            slow_items.append(json.loads(text)["i"])
        return received, slow_items, slow.dropped, fast.dropped

    received, slow_items, slow_dropped, fast_dropped = asyncio.run(main())
    assert received == [*range(100), "end"] and fast_dropped == 0
    assert slow_items == [97, 98, 99, "end"] and slow_dropped == 97


class _HeldSession:
    """A stand-in for a live session whose close() waits until `closing` is set (set from the start: closes at once)."""

    def __init__(self, sid: str, closes_at_once: bool) -> None:
        self.id, self.closing = sid, asyncio.Event()
        if closes_at_once:
            self.closing.set()

    def status(self) -> dict:
        return {"counters": {}}

    async def close(self) -> None:
        await self.closing.wait()


def _directory():
    """A SessionDirectory over an in-memory broker, and an open(closes_at_once) that opens a _HeldSession in it."""
    from service.bus import EventBus
    from service.directory import SessionDirectory

    broker = InMemoryBroker(subscriber_queue=4)
    metrics = ServiceMetrics()
    directory = SessionDirectory(Settings(instance_id="here"), broker, EventBus(broker, metrics), metrics)

    async def open_session(closes_at_once: bool = True):
        return await directory.open(None, "test", "m", lambda sid, name, creds: _HeldSession(sid, closes_at_once))

    return directory, open_session


def test_a_session_being_ended_is_not_found_rather_than_elsewhere():
    """DELETE takes the session out of the local table, closes it (awaiting its jobs), then forgets its directory
    entry: in between, its traffic is answered 404 (it ended), not 421 naming this very replica (retry elsewhere)."""

    async def main():
        directory, open_session = _directory()
        session, robot, _ = await open_session(closes_at_once=False)
        ending = asyncio.create_task(directory.end(session.id, "ended by request"))
        await asyncio.sleep(0.01)  # out of the table, closing
        try:
            await directory.local(session.id, robot, ROBOT_ONLY)
        except ServiceError as exc:
            status = exc.status
        session.closing.set()
        await ending
        return status

    assert asyncio.run(main()) == 404


def test_closing_a_robots_socket_never_waits_on_a_client_that_stopped_reading(monkeypatch):
    """A close frame waits behind what the client has not read: awaited inline, one robot that kept sending without
    reading held its DELETE, the idle reaper (every session's), a newer socket's attach and shutdown for ever.
    Closes now run beside the caller, each for at most CLOSE_WAIT_S; and shutdown skips a session the reaper ended
    while it waited (it raised 'no session' out of the shutdown)."""
    from types import SimpleNamespace

    from service import directory as directory_module
    from service.directory import MAX_INGEST_SOCKETS

    monkeypatch.setattr(directory_module, "CLOSE_WAIT_S", 0.2)

    class StalledSocket:  # its client reads nothing: a close never completes
        def __init__(self):
            self.state, self.closes = SimpleNamespace(), []

        async def close(self, code, reason):
            self.closes.append(code)
            await asyncio.Event().wait()

    async def main():
        directory, open_session = _directory()
        a, _, _ = await open_session()
        b, _, _ = await open_session(closes_at_once=False)
        sockets = [StalledSocket() for _ in range(MAX_INGEST_SOCKETS + 1)]
        for socket in sockets:
            directory.attach_ingest(a.id, socket)  # the last replaces the first
        await asyncio.wait_for(directory.end(a.id, "ended by request"), 1.0)
        await asyncio.sleep(0.01)
        tried = [(s.closes, getattr(s.state, "closed_why", None)) for s in sockets]
        await asyncio.sleep(0.3)  # past CLOSE_WAIT_S: the closes gave up
        pending = len(directory._closing)
        c, _, _ = await open_session()
        shutdown = asyncio.create_task(directory.end_all("the replica shut down"))  # b, then c…
        await asyncio.sleep(0.01)
        await directory.end(c.id, "no traffic")  # … but the reaper ends c while shutdown waits on b
        b.closing.set()
        await asyncio.wait_for(shutdown, 1.0)
        return tried, pending

    tried, pending = asyncio.run(main())
    assert tried == [([4409], "replaced"), ([1000], "session ended"), ([1000], "session ended")]
    assert pending == 0


# ---- metrics and settings --------------------------------------------------------------------------
def test_metrics_render_prometheus_text():
    m = ServiceMetrics()
    m.block_outcome["accepted"].inc()
    m.blocks.labels(outcome="accepted").inc(2)
    m.latency.labels(stage="total").observe(0.003)
    text = m.render()
    samples = {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }
    assert samples[("hapticlink_blocks_total", (("outcome", "accepted"),))] == 3
    assert samples[("hapticlink_blocks_total", (("outcome", "refused"),))] == 0
    bucket = "hapticlink_window_latency_seconds_bucket"
    assert samples[(bucket, (("le", "0.002"), ("stage", "total")))] == 0
    assert samples[(bucket, (("le", "0.005"), ("stage", "total")))] == 1
    assert samples[(bucket, (("le", "+Inf"), ("stage", "total")))] == 1
    assert "# TYPE hapticlink_window_latency_seconds histogram" in text
    assert "_created" not in text


def test_settings_come_from_the_environment_and_serialise(monkeypatch, tmp_path):
    monkeypatch.setenv("HAPTICLINK_MODEL_PATH", str(tmp_path / "m.onnx"))
    monkeypatch.setenv("HAPTICLINK_NEAREST_WEIGHTS", "[1, 2, 0, 1]")
    monkeypatch.setenv("HAPTICLINK_BROKER", "redis")
    s = Settings()
    assert s.model_path == tmp_path / "m.onnx" and s.nearest_weights == (1, 2, 0, 1) and s.broker == "redis"
    assert Settings(**s.model_dump()) == s
    json.dumps(s.model_dump(mode="json"))
    monkeypatch.setenv("HAPTICLINK_NEAREST_WEIGHTS", "[0, 0, 0, 0]")
    with pytest.raises(ValueError):
        Settings()
    with pytest.raises(ValueError):
        Settings(instance_id="a.b")  # '.' separates the instance from the session id


def test_every_setting_is_in_the_table():
    table = settings_table()
    for name in Settings.model_fields:
        assert f"`{env_name(name)}`" in table


def test_the_event_bus_bounds_a_sessions_subscriptions_itself_and_releases_them():
    """The bound holds in subscribe itself, not only at the handshake (handshakes answered together all pass the
    route's check before any of them subscribes)."""
    from service.bus import MAX_SUBSCRIBERS_PER_SESSION, EventBus

    async def main() -> None:
        broker = InMemoryBroker(subscriber_queue=4)
        bus = EventBus(broker, ServiceMetrics())
        subs = [await bus.subscribe("s") for _ in range(MAX_SUBSCRIBERS_PER_SESSION)]
        with pytest.raises(ServiceError) as full:
            await bus.subscribe("s")
        assert full.value.status == 429 and full.value.headers == {"Retry-After": "5"}
        other = await bus.subscribe("t")  # another session has its own room
        await bus.unsubscribe(subs.pop())
        subs.append(await bus.subscribe("s"))
        for sub in [*subs, other]:
            await bus.unsubscribe(sub)
        assert bus.subscribers == 0 and bus._per_session == {}

    asyncio.run(main())


# ---- body limits -----------------------------------------------------------------------------------
def test_a_route_tightens_the_body_limit_and_is_refused_as_the_middleware_refuses():
    """One mechanism: BodySizeLimit counts every body; a route may lower its own request's limit (limit_body), and
    either limit refuses 413 with its reason and Connection: close, declared or streamed."""
    app = FastAPI()
    app.add_middleware(BodySizeLimit, max_bytes=64)
    app.add_exception_handler(ServiceError, _service_error)

    @app.post("/small")
    async def small(request: Request) -> int:
        limit_body(request, 16, "a small request holds at most 16 bytes")
        return len(await request.body())

    @app.post("/any")
    async def any_size(request: Request) -> int:
        return len(await request.body())

    def chunks(n: int):  # no Content-Length: counted as it streams in
        yield from (b"x" for _ in range(n))

    with TestClient(app) as client:
        assert client.post("/small", content=b"x" * 16).json() == 16
        assert client.post("/small", content=chunks(16)).json() == 16
        assert client.post("/any", content=b"x" * 64).json() == 64
        for route, body, detail in (
            ("/small", b"x" * 17, "a small request holds at most 16 bytes"),
            ("/small", chunks(17), "a small request holds at most 16 bytes"),
            ("/any", b"x" * 65, "request body too large: at most 64 bytes (HAPTICLINK_MAX_BODY_BYTES)"),
            ("/any", chunks(65), "request body too large: at most 64 bytes (HAPTICLINK_MAX_BODY_BYTES)"),
        ):
            r = client.post(route, content=body)
            assert (r.status_code, r.json()["detail"], r.headers["connection"]) == (413, detail, "close"), route


@pytest.mark.parametrize(
    ("raw", "kept"),
    [
        ("scrape-0123456789\n", "scrape-0123456789"),
        ("  scrape-0123456789 ", "scrape-0123456789"),
        ("", None),
        (" \n", None),
    ],
)
def test_the_metrics_token_is_stripped_as_fleet_keys_are(monkeypatch, raw, kept):
    """A token read from a secret file ends in a newline no Authorization header can carry: kept as is, it could never
    match, and /metrics answered 'not valid' to the right token; blank is no token (compose passes unset as '')."""
    monkeypatch.setenv("HAPTICLINK_METRICS_TOKEN", raw)
    token = Settings().metrics_token
    assert (None if token is None else token.get_secret_value()) == kept


def test_the_body_limit_lets_the_app_judge_the_credential_first_and_reads_only_digit_lengths():
    """Driven as plain ASGI (a server in front may not refuse a length Python's int() reads): a declared length over
    the limit reaches the app, whose first read fails with BodyTooLarge before a byte is taken (the app judged the
    credential first); an answer given without reading (a 401) comes after the body is drained, with Connection: close;
    a Content-Length that is not digits ("1_000", "+13") is no declared length: the body is judged as it streams in."""
    import asyncio

    reached: list[str] = []

    async def app(scope, receive, send):
        reached.append(scope["method"])
        status = 200
        if scope["path"] == "/read":
            try:
                await receive()
            except BodyTooLarge as exc:
                status = exc.status
        else:
            status = 401  # answered without reading the body
        await send({"type": "http.response.start", "status": status, "headers": [(b"connection", b"keep-alive")]})
        await send({"type": "http.response.body", "body": b"ok"})

    def call(path: str, length: bytes, parts: int = 1) -> tuple[list[dict], int]:
        sent: list[dict] = []
        left = [parts]

        async def receive():
            left[0] -= 1
            return {"type": "http.request", "body": b"x" * 10, "more_body": left[0] > 0}

        async def send(message):
            sent.append(message)

        scope = {"type": "http", "method": "POST", "path": path, "headers": [(b"content-length", length)]}
        asyncio.run(BodySizeLimit(app, max_bytes=100)(scope, receive, send))
        return sent, parts - left[0]

    (start, _), taken = call("/read", b"1000", parts=100)
    assert start["status"] == 413 and (b"connection", b"close") in start["headers"]
    assert taken == 100  # nothing read for the app, everything the client sent drained before the answer
    (start, _), taken = call("/other", b"1000", parts=100)
    assert start["status"] == 401 and start["headers"] == [(b"connection", b"close")] and taken == 100
    (start, _), taken = call("/other", b"10")  # within the limit: the app's answer as it is, nothing drained
    assert start["headers"] == [(b"connection", b"keep-alive")] and taken == 0
    for odd in (b"1_000", b"+1000", b"1e3"):
        assert call("/read", odd)[0][0]["status"] == 200  # 10 bytes came: under the limit
    assert reached == ["POST"] * 6
