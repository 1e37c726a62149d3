"""`hapticlink demo`: the whole loop on one machine, from nothing.

1. Prepare assets once (cached in artifacts/demo): a synthetic-world dataset, a model trained on
   it with the physics feature groups (DEMO_GROUPS: MFCC + friction + spatial + taps) and
   exported to ONNX, the visual backbone's ONNX, the texture library (the same
   world), and a few *unseen* probe textures (another seed) for the simulated robot to stroke.
   Assets from another world version, model or feature set are rebuilt.
2. Start the service, a simulated robot that taps and then strokes each probe texture in turn
   (sending its camera frame first), and a terminal subscriber that prints what the operator console shows
   and, REPORT_AFTER_S into each probe's stroke, the estimate next to the probe's ground truth
   with the error (0–100 scale, mean over the four attributes).
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

import numpy as np

from drivers.blocks import Frame, SampleBlock, TapBlock
from texture_library.attributes import ATTRIBUTES, REPORT_SCALE

log = logging.getLogger("hapticlink.demo")
SCENE_GAP_S = 1.0  # the robot lifts the tool between textures: a new stream segment
REPORT_AFTER_S = 5.0  # seconds into each probe's stroke at which its estimate is compared with its truth


@dataclasses.dataclass(frozen=True)
class DemoAssets:
    """What the demo runs on; built by `models.offline.demo_assets.prepare_assets`."""

    dataset: Path
    model: Path
    tactile: Path
    backbone: Path
    library: Path
    probes: Path


def probe_clock(t_s: float, per_texture_s: float) -> tuple[int, float]:
    """(k, seconds into probe k's stroke) at stream time t_s: the tour strokes probe k from
    k·(per_texture_s + SCENE_GAP_S) for per_texture_s seconds (a window ending exactly at a
    stroke's end belongs to that stroke)."""
    period = per_texture_s + SCENE_GAP_S
    k = int(max(t_s - 1e-9, 0.0) // period)
    return k, t_s - k * period


class ProbeTour:
    """A sensor source that taps and strokes each probe texture for `per_texture_s`, in a loop (or `rounds` times)."""

    def __init__(self, probes: Path, per_texture_s: float, rounds: int | None = None, seed: int = 0):
        from texture_library.library import Library

        self.library = Library.load(probes)
        self.per_texture_s = per_texture_s
        self.rounds = rounds
        self.seed = seed
        self.name = f"probe tour of {probes}"
        self.current: str | None = None
        self._closing = False

    async def _items(self) -> AsyncIterator[SampleBlock | TapBlock | Frame]:
        from drivers.simulated import SimulatedSource

        offset, k = 0.0, 0
        while not self._closing and (self.rounds is None or k < self.rounds * len(self.library.ids)):
            entry = self.library.ids[k % len(self.library.ids)]
            self.current = entry
            model = self.library.model(entry)
            # the robot taps each probe before stroking it (a model without tap features ignores the taps)
            source = SimulatedSource(
                model,
                self.library.image(entry),
                seed=self.seed + k,
                duration_s=self.per_texture_s,
                name=entry,
                taps=model.taps is not None,
            )
            try:
                async for item in source:
                    if not isinstance(item, Frame):  # sample and tap blocks: onto the tour's clock
                        yield dataclasses.replace(item, t0=item.t0 + offset)
                    else:
                        yield item
            finally:
                await source.aclose()
            offset += self.per_texture_s + SCENE_GAP_S
            k += 1

    def __aiter__(self) -> AsyncIterator[SampleBlock | TapBlock | Frame]:
        return self._items()

    def probe_at(self, t_s: float) -> str:
        """The probe stroked at stream time t_s (e.g. a window's end)."""
        k, _ = probe_clock(t_s, self.per_texture_s)
        return self.library.ids[k % len(self.library.ids)]

    async def aclose(self) -> None:
        self._closing = True


def _fmt(ratings: dict) -> str:
    return " ".join(f"{a.split('_')[0][:5]}→{a.split('_')[1][:5]} {ratings[a]:+6.1f}" for a in ATTRIBUTES)


def _interval(event: dict) -> str:
    """The event's interval and flag in one line (or why there is none)."""
    i = event.get("interval")
    band = (
        "no interval (the model card has no calibration)"
        if i is None
        else f"{round(100 * i['level'])} % interval "
        + " ".join(f"[{i[a]['lo']:+.0f}, {i[a]['hi']:+.0f}]" for a in ATTRIBUTES)
    )
    ood = event.get("out_of_distribution")
    flag = (
        ""
        if ood is None
        else f"; OUT OF DISTRIBUTION ({', '.join(event['ood_reasons'])})"
        if ood
        else "; in distribution"
    )
    return band + flag


def rating_error(estimate: dict, truth: dict) -> float:
    """Mean absolute error over the four attributes on the 0–100 scale (bipolar difference ÷ 2)."""
    return float(np.mean([abs(estimate[a] - truth[a]) for a in ATTRIBUTES]) * REPORT_SCALE)


class ProbeReport:
    """Collects each probe's window estimates over its first `after_s` seconds of stroking (the probe
    and the time into its stroke follow from the window's end on the robot's clock: probe k strokes
    from k·(per_texture_s + SCENE_GAP_S) for per_texture_s) and, once a window ends past `after_s`,
    returns the lines comparing the estimates with the probe's truth. Keeps the errors for a summary."""

    def __init__(self, ids: list[str], truth: dict[str, dict], per_texture_s: float, after_s: float = REPORT_AFTER_S):
        self.ids, self.truth, self.per_texture_s, self.after_s = ids, truth, per_texture_s, after_s
        self.raw: dict[int, list[dict]] = {}
        self.done: set[int] = set()
        self.errors: list[tuple[str, float, float]] = []  # (probe, error of the console estimate, of the mean)

    def add(self, t_end_s: float, ratings: dict, raw_ratings: dict) -> list[str]:
        k, into = probe_clock(t_end_s, self.per_texture_s)
        if k in self.done or into > self.per_texture_s + 1e-6:
            return []
        self.raw.setdefault(k, []).append(raw_ratings)
        if into < self.after_s - 1e-6:
            return []
        self.done.add(k)
        probe = self.ids[k % len(self.ids)]
        truth = self.truth[probe]
        windows = self.raw.pop(k)
        mean = {a: float(np.mean([r[a] for r in windows])) for a in ATTRIBUTES}
        e_now, e_mean = rating_error(ratings, truth), rating_error(mean, truth)
        self.errors.append((probe, e_now, e_mean))
        return [
            f"── {probe}, {into:.1f} s into its stroke (unseen texture; error = mean |estimate − truth| over the "
            f"4 attributes, 0–100 scale)",
            f"{'':10s}console estimate  {_fmt(ratings)}   error {e_now:5.1f}",
            f"{'':10s}mean of windows   {_fmt(mean)}   error {e_mean:5.1f}",
            f"{'':10s}truth             {_fmt(truth)}",
        ]

    def summary(self) -> str | None:
        if not self.errors:
            return None
        now, mean = np.mean([e[1] for e in self.errors]), np.mean([e[2] for e in self.errors])
        return (
            f"after {self.after_s:g} s of each of {len(self.errors)} probe stroke(s): mean error {now:.1f} "
            f"(console estimate), {mean:.1f} (mean of windows) points on 0–100"
        )


async def print_events(
    url: str, session: str, token: str, tour: ProbeTour, every_s: float = 2.0, report: ProbeReport | None = None
) -> None:
    """Subscribe like the console does and print a line every few seconds, and each probe's report."""
    import websockets

    ws_url = url.replace("http", "ws", 1) + f"/sessions/{session}/events?token={token}"
    last = 0.0
    async with websockets.connect(ws_url) as ws:
        async for message in ws:
            event = json.loads(message)
            if event.get("type") != "window":
                continue
            if report is not None:
                lines = report.add(event["t_end_s"], event["ratings"], event["raw_ratings"])
                if lines:
                    print("\n".join(lines), flush=True)
            if time.monotonic() - last < every_s:
                continue
            last = time.monotonic()
            # the probe this window belongs to, from its time (the robot may be ahead, stroking the next)
            current = tour.probe_at(event["t_end_s"])
            truth = tour.library.entry(current).ratings
            print(
                f"[{event['t_end_s']:6.1f} s] stroking {current}: estimate {_fmt(event['ratings'])}\n"
                f"{'':10s}truth of {current}: {_fmt(dict(zip(ATTRIBUTES, truth)))}\n"
                f"{'':10s}{_interval(event)}\n"
                f"{'':10s}nearest library texture: {event['chosen']} "
                f"(top-{len(event['matches'])}: {', '.join(m['id'] for m in event['matches'])}), "
                f"pipeline {event['latency_ms']['total']:.1f} ms",
                flush=True,
            )


async def run_demo(
    assets: DemoAssets,
    *,
    host: str,
    port: int,
    per_texture_s: float,
    duration_s: float | None,
    report_after_s: float = REPORT_AFTER_S,
) -> None:
    import uvicorn

    from drivers.robot import RobotClient
    from service.app import create_app, server_options
    from service.settings import Settings

    api_key = secrets.token_urlsafe(24)  # this run's fleet key: the demo's robot is its only member
    settings = Settings(
        model_path=assets.model,
        tactile_model_path=assets.tactile,
        library_dir=assets.library,
        backbone_path=assets.backbone,
        host=host,
        port=port,
        log_level="warning",
        api_keys=api_key,
    )
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
    print(
        f"\nservice   {url}  (API docs {url}/docs)\nconsole   {info.console_url}\n"
        f"robot     strokes {len(tour.library.ids)} unseen textures, {per_texture_s:g} s each; Ctrl-C to stop\n",
        flush=True,
    )
    truth = {i: dict(zip(ATTRIBUTES, map(float, tour.library.entry(i).ratings))) for i in tour.library.ids}
    report = ProbeReport(list(tour.library.ids), truth, per_texture_s, min(report_after_s, per_texture_s))
    printer = asyncio.create_task(print_events(url, info.session_id, info.operator_token, tour, report=report))
    try:
        await robot.run(duration_s)
        await asyncio.sleep(0.5)  # the last windows' events are still on their way
    finally:
        printer.cancel()
        server.should_exit = True
        await asyncio.gather(printer, serving, return_exceptions=True)
        if report.summary():
            print(report.summary(), flush=True)
    print(f"robot stats: {robot.stats.as_dict()}")


def demo(
    assets: DemoAssets,
    *,
    host: str = "127.0.0.1",
    port: int = 8000,
    per_texture_s: float = 20.0,
    duration_s: float | None = None,
) -> int:
    """Run the loop on prepared assets until Ctrl-C or duration_s."""
    try:
        asyncio.run(run_demo(assets, host=host, port=port, per_texture_s=per_texture_s, duration_s=duration_s))
    except KeyboardInterrupt:
        print("\nstopped.")
    return 0
