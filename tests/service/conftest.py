"""Shared pieces of the service tests: real fixtures (library, dataset, ONNX models) and a real uvicorn
server on a random loopback port, run in a background thread with its own event loop.

Helpers are handed out through the `kit` fixture (conftest is not importable under importlib mode).
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace

import httpx
import numpy as np
import pytest
import uvicorn
from PIL import Image

from drivers.blocks import BINARY_CONTENT_TYPE, SampleBlock, encode_binary, encode_json
from drivers.source import blocks_from_arrays, paced
from service.app import create_app, server_options
from service.launcher import free_port
from service.server import SessionEndingServer
from service.settings import Settings
from service.thread_cpu import CpuMeter
from texture_library.library import Library
from texture_library.recording import Recording, recording_from_stroke
from texture_library.stroke import stroke
from texture_library.trajectory import freehand, model_ranges

FIXED_SEED = 1234
API_KEY = "test-fleet-key-0123456789"  # the fleet key every test server accepts
FLEET = {"Authorization": f"Bearer {API_KEY}"}
METRICS_TOKEN = "test-metrics-token-0123456789"  # the scrape credential every test server accepts on /metrics
SCRAPER = {"Authorization": f"Bearer {METRICS_TOKEN}"}


# ---- the real server -----------------------------------------------------------------------------
class QuietCpu:
    """A CPU meter that reads no CPU used: admission (service/capacity.py) then never finds the replica busy, whatever
    else runs on the host. Every test server has it unless its test is about capacity, which passes
    `cpu_meter=ThreadCpu()` (the service's own meter) and sets the load it tests through the settings' budget."""

    def register(self) -> None:
        pass

    def seconds(self) -> float:
        return 0.0

    def loop_seconds(self) -> float:
        return 0.0


QUIET_CPU = QuietCpu()


class ServerThread:
    """uvicorn serving create_app(settings, cpu_meter) on 127.0.0.1:<free port> in a daemon thread; `cpu_meter`:
    QUIET_CPU unless the test is about capacity (ThreadCpu(): what the service measures)."""

    def __init__(self, settings: Settings, log_level: str = "warning", cpu_meter: CpuMeter = QUIET_CPU) -> None:
        self.settings = settings
        self.log_level = log_level
        self.app = create_app(settings, cpu_meter)
        self.port = 0
        self._server: uvicorn.Server | None = None
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"

    def start(self, wait_ready: bool = True, timeout_s: float = 60.0) -> ServerThread:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("127.0.0.1", 0))
        self.port = sock.getsockname()[1]
        config = uvicorn.Config(
            self.app,
            **server_options(
                self.settings, lifespan="on", log_level=self.log_level, access_log=False, timeout_graceful_shutdown=3
            ),
        )
        self._server = SessionEndingServer(config)
        self._thread = threading.Thread(target=self._server.run, kwargs={"sockets": [sock]}, daemon=True)
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self._server.started:
            if not self._thread.is_alive():
                raise RuntimeError("the server thread died during start-up")
            if time.monotonic() > deadline:
                raise TimeoutError("the server did not start")
            time.sleep(0.01)
        if wait_ready:
            self.wait_ready(deadline - time.monotonic())
        return self

    def wait_ready(self, timeout_s: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout_s
        with httpx.Client(base_url=self.url, timeout=5) as client:
            while True:
                r = client.get("/ready")
                if r.status_code == 200:
                    return r.json()
                if time.monotonic() > deadline:
                    raise TimeoutError(f"not ready: {r.text}")
                time.sleep(0.05)

    def stop(self) -> None:
        if self._server is not None and self._thread is not None:
            self._server.should_exit = True
            self._thread.join(timeout=15)
        self._server = self._thread = None


@contextlib.contextmanager
def running(
    settings: Settings, wait_ready: bool = True, log_level: str = "warning", cpu_meter: CpuMeter = QUIET_CPU
) -> Iterator[ServerThread]:
    server = ServerThread(settings, log_level, cpu_meter).start(wait_ready=wait_ready)
    try:
        yield server
    finally:
        server.stop()


# ---- signals -------------------------------------------------------------------------------------
def stroke_recording(library_dir: Path, entry_id: str, seconds: float, seed: int = FIXED_SEED) -> Recording:
    """`seconds` of freehand stroking over a library entry's vibration model (1 kHz, canonical units)."""
    model = Library.load(library_dir).model(entry_id)
    rng = np.random.default_rng(seed)
    traj = freehand(seconds, rng, rate_hz=model.rate_hz, **model_ranges(model.max_speed, model.max_force))
    s = stroke(model, traj, rng)
    return recording_from_stroke(s.accel, s.force, s.speed, s.rate_hz)


def recording_blocks(rec: Recording, block_s: float = 0.02, t0: float = 0.0, seq0: int = 0) -> list[SampleBlock]:
    """The recording cut into consecutive wire blocks (float32, as a robot sends them)."""
    channels = {
        "accel": (rec.accel.data, rec.accel.rate_hz, "m/s^2"),
        "force": (rec.force.data, rec.force.rate_hz, "N"),
        "speed": (rec.speed.data, rec.speed.rate_hz, "mm/s"),
    }
    return list(blocks_from_arrays(channels, block_s, t0=t0, seq0=seq0))


def wait_for(predicate, timeout_s: float = 30.0, every_s: float = 0.02):
    """Poll until predicate() is truthy; returns its value (TimeoutError otherwise)."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError("condition not met in time")
        time.sleep(every_s)


def png(size: int = 256) -> bytes:
    """A size×size RGB PNG (a valid camera frame from 224 px up)."""
    buf = io.BytesIO()
    Image.new("RGB", (size, size), (120, 80, 40)).save(buf, format="PNG")
    return buf.getvalue()


def post_block(
    client: httpx.Client, session: dict, block: SampleBlock | bytes, content_type: str | None = None
) -> httpx.Response:
    """POST one block with the session's robot token: a SampleBlock encoded as `content_type` (binary by default,
    or application/json), raw bytes as they are."""
    content_type = content_type or BINARY_CONTENT_TYPE
    if isinstance(block, SampleBlock):
        block = json.dumps(encode_json(block)).encode() if content_type == "application/json" else encode_binary(block)
    return client.post(
        f"/sessions/{session['session_id']}/blocks",
        content=block,
        headers={"Authorization": f"Bearer {session['robot_token']}", "Content-Type": content_type},
    )


def socket_url(server: ServerThread, session: dict, route: str) -> str:
    """ws:// URL of a session's WebSocket `route` with the token it takes (ingest: robot, events: operator)."""
    token = session["robot_token" if route == "ingest" else "operator_token"]
    return f"{server.ws_url}/sessions/{session['session_id']}/{route}?token={token}"


def create_session(client: httpx.Client, name: str = "test") -> dict:
    r = client.post("/sessions", json={"name": name}, headers=FLEET)
    assert r.status_code == 201, r.text
    return r.json()


def session_status(client: httpx.Client, session: dict) -> dict:
    r = client.get(
        f"/sessions/{session['session_id']}", headers={"Authorization": f"Bearer {session['operator_token']}"}
    )
    assert r.status_code == 200, r.text
    return r.json()


# ---- fixtures ------------------------------------------------------------------------------------
@pytest.fixture(scope="session")
def library_dir(built_once) -> Path:
    from texture_library.synthetic_library import build_synthetic_library

    return built_once.folder("library", lambda root: build_synthetic_library(root, n_textures=6, image_size=256))


@pytest.fixture(scope="session")
def tactile_dataset(built_once) -> Path:
    """A small synthetic world (8 textures, 4 s of stroking each, with tap transients), shared by the tactile
    models below: each trains on its own features of it."""
    from models.offline.datasets.build import build

    return (
        built_once.folder(
            "tactile-dataset", lambda root: build("synthetic", root / "dataset", n_textures=8, duration_s=4)
        )
        / "dataset"
    )


@pytest.fixture(scope="session")
def tactile_model(built_once, tactile_dataset) -> Path:
    """ridge-tactile trained on `tactile_dataset` (needs no visual features: fast)."""
    from models.offline.train import train_and_export

    def fill(root: Path) -> None:
        train_and_export(tactile_dataset, "ridge-tactile", root / "ridge-tactile.onnx")

    return built_once.folder("tactile-model", fill) / "ridge-tactile.onnx"


@pytest.fixture(scope="session")
def taps_model(built_once, tactile_dataset) -> Path:
    """ridge-tactile on MFCC + taps, trained on `tactile_dataset` (its textures carry tap transients). Its
    features without the taps group are `tactile_model`'s: that model is its untapped fallback."""
    from models.offline.train import train_and_export
    from models.tactile.config import TactileConfig

    def fill(root: Path) -> None:
        config = TactileConfig(extra_groups=("taps",))
        train_and_export(tactile_dataset, "ridge-tactile", root / "ridge-tactile-taps.onnx", tactile_config=config)

    return built_once.folder("taps-model", fill) / "ridge-tactile-taps.onnx"


@pytest.fixture(scope="session")
def visual_model(built_once) -> SimpleNamespace:
    """ridge-both on 3 synthetic textures and the EfficientNet backbone ONNX it was trained with.

    Exporting the backbone and embedding 3 × 8 image views takes ~30 s the first time; both are
    cached under ./cache (HAPTICLINK_CACHE) and reused by later runs.
    """
    from models.offline.datasets.build import build
    from models.offline.featurize import backbone_onnx
    from models.offline.train import train_and_export
    from models.visual.config import VisualConfig

    def fill(root: Path) -> None:
        dataset = build("synthetic", root / "dataset", n_textures=3, duration_s=3, image_size=256)
        train_and_export(dataset, "ridge-both", root / "ridge-both.onnx")
        train_and_export(dataset, "ridge-tactile", root / "ridge-tactile.onnx")  # same features: the fallback

    root = built_once.folder("visual-model", fill)
    return SimpleNamespace(
        model=root / "ridge-both.onnx",
        tactile=root / "ridge-tactile.onnx",
        backbone=backbone_onnx(VisualConfig()),
        dataset=root / "dataset",
    )


@pytest.fixture(scope="session")
def calibrated_visual_model(built_once) -> SimpleNamespace:
    """ridge-both on 8 synthetic textures (enough for `hapticlink train` to calibrate intervals and fit the OOD
    detector, frame ranges included), its ridge-tactile fallback, the backbone, and the dataset (8 s of stroking
    per texture: tests stream a texture's own recording as the in-distribution case). It reads the served visual
    configuration (2×2 patches, no GLCM); `visual_model` reads the default one."""
    from models.offline.datasets.build import build
    from models.offline.featurize import SERVED_VISUAL, backbone_onnx
    from models.offline.train import train_and_export

    def fill(root: Path) -> None:
        dataset = build("synthetic", root / "dataset", n_textures=8, duration_s=8, image_size=256)
        train_and_export(dataset, "ridge-both", root / "ridge-both.onnx", visual_config=SERVED_VISUAL)
        train_and_export(dataset, "ridge-tactile", root / "ridge-tactile.onnx")

    root = built_once.folder("calibrated-visual-model", fill)
    return SimpleNamespace(
        model=root / "ridge-both.onnx",
        tactile=root / "ridge-tactile.onnx",
        backbone=backbone_onnx(SERVED_VISUAL),
        dataset=root / "dataset",
    )


@pytest.fixture(scope="session")
def base_settings(tactile_model, library_dir) -> Settings:
    # A generous window bound: tests post blocks as fast as they can, on a machine that may be busy;
    # the backpressure tests set a tight one. For the same reason the loop-lag limits of admission are out of
    # reach (the default tens of milliseconds would shed sessions whenever the machine is busy): the admission
    # tests set what they test.
    return Settings(
        model_path=tactile_model,
        library_dir=library_dir,
        instance_id="test-a",
        session_idle_s=600,
        session_first_block_s=600,
        session_queue_windows=64,
        api_keys=API_KEY,
        metrics_token=METRICS_TOKEN,
        session_burst=10_000,
        session_lag_s=600,
        shed_lag_s=600,
        session_queue_s=600,
        shed_queue_s=600,
    )


@pytest.fixture(scope="session")
def server(base_settings) -> Iterator[ServerThread]:
    """One shared server with the tactile model and default bounds."""
    with running(base_settings) as srv:
        yield srv


@pytest.fixture
def client(server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=10) as c:
        yield c


class BlockList:
    """A SensorSource over prepared blocks (as fast as the client takes them)."""

    name = "blocks"

    def __init__(self, blocks) -> None:
        self.blocks = blocks

    def __aiter__(self):
        return paced(self.blocks, False).__aiter__()

    async def aclose(self) -> None:
        pass


class PoolStall:
    """Occupies one of the server's pools (default: the window pool) until released; the session's jobs queue up
    behind it."""

    def __init__(self, server, pool: str = "window_pool") -> None:
        self.release = threading.Event()
        self.future = getattr(server.app.state.service, pool).submit(self.release.wait, 60)

    def __enter__(self) -> PoolStall:
        return self

    def __exit__(self, *exc) -> None:
        self.release.set()
        self.future.result(timeout=10)

    async def release_when(self, done: Callable[[], bool], then_s: float = 0.5, guard_s: float = 60.0) -> None:
        """Releases the pool then_s after done() first holds (not after a fixed time: on a busy host a robot may take
        longer to fill its session's queue), or after guard_s (a hang guard)."""
        deadline = time.monotonic() + guard_s
        while not done() and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        await asyncio.sleep(then_s)
        self.release.set()


def robot_session(robot) -> dict:
    """The session a RobotClient opened, as the session helpers take it (id and operator token)."""
    return {"session_id": robot.session.session_id, "operator_token": robot.session.operator_token}


def overload(client: httpx.Client, server, settings: Settings, first_block, robots: int):
    """`robots` sessions opened oldest first, each streaming (its first block accepted), then the service over
    capacity from now on (its CPU budget set to nothing): (the capacity guard, the sessions)."""
    guard = server.app.state.service.capacity
    sessions = [create_session(client, f"robot{i}") for i in range(robots)]
    for s in sessions:
        assert post_block(client, s, first_block).status_code == 202
    guard.settings = settings.model_copy(update={"cpu_budget": 1e-6})
    return guard, sessions


@pytest.fixture(scope="session")
def kit() -> SimpleNamespace:
    return SimpleNamespace(
        ServerThread=ServerThread,
        running=running,
        BlockList=BlockList,
        PoolStall=PoolStall,
        robot_session=robot_session,
        overload=overload,
        stroke_recording=stroke_recording,
        recording_blocks=recording_blocks,
        wait_for=wait_for,
        create_session=create_session,
        session_status=session_status,
        post_block=post_block,
        socket_url=socket_url,
        png=png,
        free_port=free_port,
        QUIET_CPU=QUIET_CPU,
        FIXED_SEED=FIXED_SEED,
        API_KEY=API_KEY,
        FLEET=FLEET,
        METRICS_TOKEN=METRICS_TOKEN,
        SCRAPER=SCRAPER,
    )
