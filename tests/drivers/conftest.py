"""Shared pieces of the drivers tests: a fake hapticlink service on loopback, and small sources.

The fake service implements just the robot-facing contract (sessions, blocks over HTTP and
WebSocket, frames) with switches that misbehave on purpose: reject a seq, answer 429 / close
4429 / refuse a handshake with 429 and Retry-After, process a block and then fail before acknowledging
it, answer 503, restart the whole server, lose the session (410 / close 4410, as when the replica
that held it is gone).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import socket
import threading
import time
from collections import Counter
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest
import uvicorn
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect

from drivers.blocks import BINARY_CONTENT_TYPE, SampleBlock, decode_binary, decode_json
from drivers.protocol import SESSION_LOST, Close, ack_error, ack_ok, peek_seq
from drivers.source import blocks_from_arrays, paced

# ---- the fake service --------------------------------------------------------------------------
LOST_DETAIL = (
    "session s-fixed is lost: its replica replica-z is gone (stopped, crashed or restarted); open a new session"
)


@dataclass
class FakeSession:
    robot_token: str
    operator_token: str
    last_seq: int = -1
    accepted: list[SampleBlock] = field(default_factory=list)
    deliveries: Counter = field(default_factory=Counter)  # seq → times it reached the server
    frames: list[tuple[str, bytes]] = field(default_factory=list)
    scene_checks: list[bytes] = field(default_factory=list)  # thumbnails of the robot's refreshes


class FakeService:
    """State and misbehaviour switches of the fake service (survives server restarts)."""

    def __init__(self) -> None:
        self.sessions: dict[str, FakeSession] = {}
        self._ids = itertools.count(1)
        self.reject_seqs: set[int] = set()  # 400 / ok:false for these seqs
        self.saturate: int = 0  # answer 429 (HTTP) or close 4429 (WS connect) this many times
        self.shed_handshakes: int = 0  # refuse this many ingest handshakes with HTTP 429, Retry-After: 0.3
        self.handshakes: list[float] = []  # time.monotonic() of every ingest handshake
        self.frame_posts: list[float] = []  # time.monotonic() of every frame request
        self.scene_held = True  # a scene check's answer: the scene is held (no frame needed), or not
        self.block_answers: list[tuple[float, int]] = []  # (time.monotonic(), status) of every block POST answered
        self.fail_after_accept: set[int] = set()  # process the block, then 503 / close 1011 without the ack
        self.fail_at: dict[int, list[int]] = {}  # seq → HTTP statuses to answer (one per try) before processing it
        self.ws_kill_every: int = 0  # close 1011 after processing every n-th message of a connection
        self.on_accept = None  # callback(seq) after a block is accepted
        self.lose_after: int | None = None  # the session is lost once this many blocks were accepted
        self.lost_answers = 0  # 410 answers and 4410 closes sent since
        self.app = Starlette(
            routes=[
                Route("/sessions", self.create_session, methods=["POST"]),
                Route("/sessions/{sid}/blocks", self.post_block, methods=["POST"]),
                Route("/sessions/{sid}/frames", self.post_frame, methods=["POST"]),
                Route("/sessions/{sid}/scene", self.post_scene, methods=["POST"]),
                WebSocketRoute("/sessions/{sid}/ingest", self.ingest),
            ]
        )

    def add_session(self, sid: str = "s-fixed", robot_token: str = "robot-secret") -> FakeSession:
        self.sessions[sid] = FakeSession(robot_token, f"operator-{sid}")
        return self.sessions[sid]

    def only_session(self) -> FakeSession:
        (sess,) = self.sessions.values()
        return sess

    async def create_session(self, request: Request) -> Response:
        sid = f"s{next(self._ids)}"
        sess = self.add_session(sid, f"robot-{sid}")
        return JSONResponse(
            {"session_id": sid, "robot_token": sess.robot_token, "operator_token": sess.operator_token}, status_code=201
        )

    def _ingest(self, sess: FakeSession, payload: bytes, content_type: str) -> tuple[int, dict]:
        """(HTTP status, body) for one block, as the real service would treat it."""
        try:
            block = decode_binary(payload) if content_type == BINARY_CONTENT_TYPE else decode_json(json.loads(payload))
        except ValueError as exc:
            return 400, {"detail": str(exc)}
        sess.deliveries[block.seq] += 1
        if block.seq in self.reject_seqs:
            return 400, {"detail": f"block {block.seq} refused on purpose", "seq": block.seq}
        if block.seq <= sess.last_seq:
            return 202, {"seq": block.seq, "duplicate": True}
        sess.last_seq = block.seq
        sess.accepted.append(block)
        if self.on_accept is not None:
            self.on_accept(block.seq)
        return 202, {"seq": block.seq, "duplicate": False}

    def _session(self, sid: str, token: str | None) -> FakeSession | int:
        sess = self.sessions.get(sid)
        if sess is None:
            return 404
        if token != sess.robot_token:
            return 401
        if self.lose_after is not None and len(sess.accepted) >= self.lose_after:
            self.lost_answers += 1
            return SESSION_LOST
        return sess

    async def post_block(self, request: Request) -> Response:
        auth = request.headers.get("authorization", "")
        sess = self._session(request.path_params["sid"], auth.removeprefix("Bearer "))
        if isinstance(sess, int):
            return JSONResponse({"detail": LOST_DETAIL if sess == SESSION_LOST else "no"}, status_code=sess)
        if self.saturate > 0:
            self.saturate -= 1
            self.block_answers.append((time.monotonic(), 429))
            return JSONResponse({"detail": "saturated"}, status_code=429, headers={"Retry-After": "0.02"})
        self.block_answers.append((time.monotonic(), 202))
        payload = await request.body()
        seq = peek_seq(payload, request.headers.get("content-type", "") == BINARY_CONTENT_TYPE)
        if self.fail_at.get(seq):
            return JSONResponse({"detail": "not now"}, status_code=self.fail_at[seq].pop(0))
        status, body = self._ingest(sess, payload, request.headers.get("content-type", ""))
        if seq in self.fail_after_accept:
            self.fail_after_accept.discard(seq)
            return JSONResponse({"detail": "processed, but the answer is lost"}, status_code=503)
        return JSONResponse(body, status_code=status)

    async def post_frame(self, request: Request) -> Response:
        self.frame_posts.append(time.monotonic())
        auth = request.headers.get("authorization", "")
        sess = self._session(request.path_params["sid"], auth.removeprefix("Bearer "))
        if isinstance(sess, int):
            return JSONResponse({"detail": LOST_DETAIL if sess == SESSION_LOST else "no"}, status_code=sess)
        ctype = request.headers.get("content-type", "")
        if ctype not in ("image/png", "image/jpeg"):
            return JSONResponse({"detail": f"unsupported {ctype}"}, status_code=415)
        sess.frames.append((ctype, await request.body()))
        return JSONResponse({"ok": True}, status_code=202)

    async def post_scene(self, request: Request) -> Response:
        auth = request.headers.get("authorization", "")
        sess = self._session(request.path_params["sid"], auth.removeprefix("Bearer "))
        if isinstance(sess, int):
            return JSONResponse({"detail": LOST_DETAIL if sess == SESSION_LOST else "no"}, status_code=sess)
        sess.scene_checks.append(await request.body())
        return JSONResponse({"frame_needed": not self.scene_held, "detail": "fake"})

    async def ingest(self, ws: WebSocket) -> None:
        self.handshakes.append(time.monotonic())
        if self.shed_handshakes > 0:  # the replica sheds this session: refused before the upgrade
            self.shed_handshakes -= 1
            await ws.send_denial_response(
                JSONResponse({"detail": "at capacity"}, status_code=429, headers={"Retry-After": "0.3"})
            )
            return
        await ws.accept()
        sess = self._session(ws.path_params["sid"], ws.query_params.get("token"))
        if isinstance(sess, int):
            await ws.close(
                code=Close.LOST if sess == SESSION_LOST else Close.POLICY,
                reason=LOST_DETAIL if sess == SESSION_LOST else "bad token",
            )
            return
        if self.saturate > 0:
            self.saturate -= 1
            await ws.close(code=Close.SATURATED, reason="saturated")
            return
        n = 0
        try:
            while True:
                message = await ws.receive()
                if message["type"] == "websocket.disconnect":
                    return
                binary = message.get("bytes") is not None
                payload = message["bytes"] if binary else message["text"].encode()
                n += 1
                if self.lose_after is not None and len(sess.accepted) >= self.lose_after:
                    self.lost_answers += 1
                    await ws.close(code=Close.LOST, reason=LOST_DETAIL)
                    return
                status, body = self._ingest(sess, payload, BINARY_CONTENT_TYPE if binary else "application/json")
                seq = body.get("seq")
                if (self.ws_kill_every and n % self.ws_kill_every == 0) or seq in self.fail_after_accept:
                    self.fail_after_accept.discard(seq)
                    await ws.close(code=Close.SERVER_ERROR, reason="server error after processing")
                    return
                if status == 202:
                    await ws.send_text(ack_ok(seq, body["duplicate"]))
                else:
                    # like the real service when it cannot read the seq: the client matches answers by order
                    await ws.send_text(ack_error(None, body["detail"]))
        except WebSocketDisconnect:
            return


class LoopbackServer:
    """uvicorn serving an app on 127.0.0.1 inside the test's event loop; stop/start keep the port."""

    def __init__(self, app) -> None:
        self.app = app
        self.port = 0
        self._server: uvicorn.Server | None = None
        self._task: asyncio.Task | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    async def start(self) -> None:
        # proto IPPROTO_TCP, so asyncio sets TCP_NODELAY on accepted connections (as uvicorn's own sockets get).
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("127.0.0.1", self.port))
        sock.listen(128)
        self.port = sock.getsockname()[1]
        config = uvicorn.Config(
            self.app, log_level="critical", lifespan="off", access_log=False, timeout_graceful_shutdown=2
        )
        self._server = uvicorn.Server(config)
        self._server.capture_signals = contextlib.nullcontext  # the test owns signals
        self._task = asyncio.create_task(self._server.serve(sockets=[sock]))
        while not self._server.started:
            if self._task.done():
                self._task.result()
            await asyncio.sleep(0.01)

    async def stop(self) -> None:
        if self._server is not None and self._task is not None:
            self._server.should_exit = True
            await self._task
        self._server = self._task = None

    def restart_soon(self, down_s: float) -> asyncio.Task:
        """Take the server down now and bring it back after down_s seconds (a real outage: connections refused)."""

        async def bounce() -> None:
            await self.stop()
            await asyncio.sleep(down_s)
            await self.start()

        return asyncio.create_task(bounce())


class ServerThread:
    """A LoopbackServer on its own event loop in a thread, for code that runs asyncio.run itself."""

    def __init__(self, app) -> None:
        self.server = LoopbackServer(app)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._up = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._main()), daemon=True)

    async def _main(self) -> None:
        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        await self.server.start()
        self._up.set()
        await self._stop.wait()
        await self.server.stop()

    @property
    def url(self) -> str:
        return self.server.url

    def __enter__(self) -> ServerThread:
        self._thread.start()
        if not self._up.wait(10):
            raise RuntimeError("the fake service did not start")
        return self

    def __exit__(self, *exc) -> None:
        self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(10)


@pytest.fixture
def fake_service() -> FakeService:
    return FakeService()


# ---- sources -----------------------------------------------------------------------------------
def stroke_arrays(n_samples: int, seed: int = 0) -> dict[str, tuple[np.ndarray, float, str]]:
    """Random accel (n, 3) m/s², force (n,) N, speed (n,) mm/s at 1 kHz (float32-exact)."""
    rng = np.random.default_rng(seed)
    return {
        "accel": (rng.standard_normal((n_samples, 3)).astype(np.float32), 1000.0, "m/s^2"),
        "force": (rng.uniform(0.5, 3.0, n_samples).astype(np.float32), 1000.0, "N"),
        "speed": (rng.uniform(20, 300, n_samples).astype(np.float32), 1000.0, "mm/s"),
    }


class ListSource:
    """A SensorSource over prepared items; realtime paces them; records that it was closed."""

    def __init__(self, items, realtime: bool = False, speed: float = 1.0, name: str = "list") -> None:
        self.items = list(items)
        self.realtime = realtime
        self.speed = speed
        self.name = name
        self.closed = False

    def __aiter__(self) -> AsyncIterator:
        return paced(self.items, self.realtime, self.speed).__aiter__()

    async def aclose(self) -> None:
        self.closed = True


class EndlessSource:
    """Blocks of 20 ms forever, paced in real time (speed×); records that it was closed."""

    name = "endless"

    def __init__(self, speed: float = 1.0) -> None:
        self.speed = speed
        self.closed = False

    def _blocks(self):
        for k in itertools.count():
            arrays = stroke_arrays(20, seed=k)
            yield from blocks_from_arrays(arrays, 0.02, t0=k * 0.02, seq0=k)

    def __aiter__(self) -> AsyncIterator:
        return paced(self._blocks(), True, self.speed).__aiter__()

    async def aclose(self) -> None:
        self.closed = True


def concat(blocks: list[SampleBlock], kind: str) -> np.ndarray:
    return np.concatenate([b.channels[kind].data for b in blocks if kind in b.channels])


async def take(source, n: int | None = None, *, samples: int | None = None) -> list:
    """Items of `source` until `n` items or `samples` accel samples have come (None: to its end), then aclose() it."""
    out, got = [], 0
    async for item in source:
        out.append(item)
        if isinstance(item, SampleBlock) and "accel" in item.channels:
            got += item.channels["accel"].data.shape[0]
        if (n is not None and len(out) >= n) or (samples is not None and got >= samples):
            break
    await source.aclose()
    return out


def stream(app, items, **options):
    """Serve `app` on loopback and stream `items` to it with a RobotClient(**options) → its stats."""
    return stream_source(app, ListSource(items), **options)


def stream_source(app, source, duration_s: float | None = None, **options):
    """Serve `app` on loopback and stream `source` to it with a RobotClient(**options) for `duration_s` (None: until
    the source ends; 60 s at most) → its stats."""
    from drivers.robot import RobotClient

    async def main():
        server = LoopbackServer(app)
        await server.start()
        try:
            return await asyncio.wait_for(RobotClient(server.url, source, **options).run(duration_s=duration_s), 60)
        finally:
            await server.stop()

    return asyncio.run(main())


@pytest.fixture
def kit() -> SimpleNamespace:
    """The helpers above, for test modules (conftest is not importable under --import-mode=importlib)."""
    return SimpleNamespace(
        FakeService=FakeService,
        LOST_DETAIL=LOST_DETAIL,
        LoopbackServer=LoopbackServer,
        ServerThread=ServerThread,
        ListSource=ListSource,
        EndlessSource=EndlessSource,
        stroke_arrays=stroke_arrays,
        concat=concat,
        take=take,
        stream=stream,
        stream_source=stream_source,
    )
