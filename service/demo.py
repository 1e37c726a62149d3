"""`hapticlink demo`: the whole loop on one machine, from nothing.

1. Prepare assets once (cached in artifacts/demo): a synthetic-world dataset, a model trained on
   it and exported to ONNX, the visual backbone's ONNX, the texture library (the same world), and
   a few *unseen* probe textures (another seed) for the simulated robot to stroke.
2. Start the service, a simulated robot that strokes each probe texture in turn (sending its
   camera frame first), and a terminal subscriber that prints what the operator console shows.
3. Print the console URL; Ctrl-C ends everything cleanly.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import secrets
import time
from collections.abc import AsyncIterator
from pathlib import Path

from drivers.blocks import Frame, SampleBlock
from texture_library.attributes import ATTRIBUTES

log = logging.getLogger("hapticlink.demo")
DEMO_MODEL = "ann"  # reads touch and vision, trains in seconds, best exportable model on the synthetic world (reports/synthetic)
TACTILE_MODEL = "ridge-tactile"  # estimates windows until the session's first frame is embedded
SCENE_GAP_S = 1.0  # the robot lifts the tool between textures: a new stream segment


@dataclasses.dataclass(frozen=True)
class DemoAssets:
    dataset: Path
    model: Path
    tactile: Path
    backbone: Path
    library: Path
    probes: Path


def prepare_assets(root: Path, *, n_textures: int = 24, n_probes: int = 4, seed: int = 0) -> DemoAssets:
    """Build whatever is missing under root (needs the train extra the first time)."""
    from models.datasets.build import build
    from models.featurize import backbone_onnx, featurize_dataset
    from models.train import train_and_export
    from models.visual.config import VisualConfig
    from texture_library.synthetic_library import build_synthetic_library

    root.mkdir(parents=True, exist_ok=True)
    assets = DemoAssets(root / "dataset", root / "model.onnx", root / "tactile.onnx", Path(), root / "library", root / "probes")
    steps = [
        (not (assets.dataset / "dataset.json").is_file(), f"building a synthetic world of {n_textures} textures",
         lambda: build("synthetic", assets.dataset, n_textures=n_textures, seed=seed)),
        (True, "computing features (cached after the first run)", lambda: featurize_dataset(assets.dataset)),
        (not assets.model.is_file(), f"training {DEMO_MODEL} on it and exporting ONNX",
         lambda: train_and_export(assets.dataset, DEMO_MODEL, assets.model, seed=seed)),
        (not assets.tactile.is_file(), f"training {TACTILE_MODEL} (windows before the first frame) and exporting ONNX",
         lambda: train_and_export(assets.dataset, TACTILE_MODEL, assets.tactile, seed=seed)),
        (not (assets.library / "library.json").is_file(), "writing the texture library",
         lambda: build_synthetic_library(assets.library, n_textures=n_textures, seed=seed)),
        (not (assets.probes / "library.json").is_file(), f"making {n_probes} unseen probe textures",
         lambda: build_synthetic_library(assets.probes, n_textures=n_probes, seed=seed + 1)),
    ]
    for needed, what, step in steps:
        if needed:
            print(f"  · {what} …", flush=True)
            step()
    return dataclasses.replace(assets, backbone=backbone_onnx(VisualConfig()))


class ProbeTour:
    """A sensor source that strokes each probe texture for `per_texture_s`, in a loop (or `rounds` times)."""

    def __init__(self, probes: Path, per_texture_s: float, rounds: int | None = None, seed: int = 0):
        from texture_library.library import Library

        self.library = Library.load(probes)
        self.per_texture_s = per_texture_s
        self.rounds = rounds
        self.seed = seed
        self.name = f"probe tour of {probes}"
        self.current: str | None = None
        self._closing = False

    async def _items(self) -> AsyncIterator[SampleBlock | Frame]:
        from drivers.simulated import SimulatedSource

        offset, k = 0.0, 0
        while not self._closing and (self.rounds is None or k < self.rounds * len(self.library.ids)):
            entry = self.library.ids[k % len(self.library.ids)]
            self.current = entry
            source = SimulatedSource(self.library.model(entry), self.library.image(entry), seed=self.seed + k,
                                     duration_s=self.per_texture_s, name=entry)
            try:
                async for item in source:
                    if isinstance(item, SampleBlock):
                        yield dataclasses.replace(item, t0=item.t0 + offset)
                    else:
                        yield item
            finally:
                await source.aclose()
            offset += self.per_texture_s + SCENE_GAP_S
            k += 1

    def __aiter__(self) -> AsyncIterator[SampleBlock | Frame]:
        return self._items()

    async def aclose(self) -> None:
        self._closing = True


def _fmt(ratings: dict) -> str:
    return " ".join(f"{a.split('_')[0][:5]}→{a.split('_')[1][:5]} {ratings[a]:+6.1f}" for a in ATTRIBUTES)


async def print_events(url: str, session: str, token: str, tour: ProbeTour, every_s: float = 2.0) -> None:
    """Subscribe like the console does and print a line every few seconds."""
    import websockets

    ws_url = url.replace("http", "ws", 1) + f"/sessions/{session}/events?token={token}"
    last = 0.0
    async with websockets.connect(ws_url) as ws:
        async for message in ws:
            event = json.loads(message)
            if event.get("type") != "window" or time.monotonic() - last < every_s:
                continue
            last = time.monotonic()
            truth = tour.library.entry(tour.current).ratings if tour.current else None
            print(f"[{event['t_end_s']:6.1f} s] stroking {tour.current}: estimate {_fmt(event['ratings'])}\n"
                  f"{'':10s}truth of {tour.current}: {_fmt(dict(zip(ATTRIBUTES, truth)))}\n"
                  f"{'':10s}nearest library texture: {event['chosen']} "
                  f"(top-{len(event['matches'])}: {', '.join(m['id'] for m in event['matches'])}), "
                  f"pipeline {event['latency_ms']['total']:.1f} ms", flush=True)


async def run_demo(assets: DemoAssets, *, host: str, port: int, per_texture_s: float, duration_s: float | None) -> None:
    import uvicorn

    from drivers.robot import RobotClient
    from service.app import create_app, server_options
    from service.settings import Settings

    api_key = secrets.token_urlsafe(24)  # this run's fleet key: the demo's robot is its only member
    settings = Settings(model_path=assets.model, tactile_model_path=assets.tactile, library_dir=assets.library,
                        backbone_path=assets.backbone, host=host, port=port, log_level="warning", api_keys=api_key)
    server = uvicorn.Server(uvicorn.Config(create_app(settings), **server_options(settings)))
    serving = asyncio.create_task(server.serve())
    while not server.started:
        if serving.done():
            serving.result()  # raises why it could not start (e.g. the port is taken)
            raise RuntimeError("the service stopped while starting")
        await asyncio.sleep(0.05)
    url = f"http://{host}:{port}"
    tour = ProbeTour(assets.probes, per_texture_s)
    robot = RobotClient(url, tour, session_name="demo robot", api_key=api_key)
    info = await robot.open_session()
    print(f"\nservice   {url}  (API docs {url}/docs)\nconsole   {info.console_url}\n"
          f"robot     strokes {len(tour.library.ids)} unseen textures, {per_texture_s:g} s each; Ctrl-C to stop\n", flush=True)
    printer = asyncio.create_task(print_events(url, info.session_id, info.operator_token, tour))
    try:
        await robot.run(duration_s)
    finally:
        printer.cancel()
        server.should_exit = True
        await asyncio.gather(printer, serving, return_exceptions=True)
    print(f"robot stats: {robot.stats.as_dict()}")


def demo(assets_dir: str | Path = "artifacts/demo", *, host: str = "127.0.0.1", port: int = 8000,
         per_texture_s: float = 20.0, duration_s: float | None = None) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    print("hapticlink demo — preparing assets", flush=True)
    t0 = time.perf_counter()
    assets = prepare_assets(Path(assets_dir))
    print(f"  assets ready in {time.perf_counter() - t0:.0f} s: {assets.model}", flush=True)
    try:
        asyncio.run(run_demo(assets, host=host, port=port, per_texture_s=per_texture_s, duration_s=duration_s))
    except KeyboardInterrupt:
        print("\nstopped.")
    return 0
