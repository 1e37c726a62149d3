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
   The robot opens its session once the service's /ready answers 200.
3. Print the console URL; one Ctrl-C (or SIGTERM) stops the robot, the feed and the service within
   STOP_S and prints the summary (each probe's error, windows flagged out of distribution); a
   second one quits at once.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import dataclasses
import json
import logging
import secrets
import threading
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from demo.terminal import (
    Terminal,
    cells,
    heads,
    robot_line,
    status_header,
    status_line,
    summary_table,
    wrapped,
)
from drivers.blocks import Frame, SampleBlock, TapBlock
from drivers.stop_signals import on_stop_signals
from texture_library.attributes import ATTRIBUTES, REPORT_SCALE

if TYPE_CHECKING:
    from fastapi import FastAPI

log = logging.getLogger("hapticlink.demo")
SCENE_GAP_S = 1.0  # the robot lifts the tool between textures: a new stream segment
REPORT_AFTER_S = 5.0  # seconds into each probe's stroke at which its estimate is compared with its truth
READY_TIMEOUT_S = 120.0  # the service loads, cross-checks and warms up its models before /ready answers 200
STOP_S = 2.0  # one Ctrl-C stops robot, feed and service within this
PROBE_LABEL_W = 60  # a probe report's row labels, right-aligned so its ratings sit under their column heads


@dataclasses.dataclass(frozen=True)
class DemoAssets:
    """What the demo runs on; built by `demo.assets.prepare_assets`."""

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
            f"{f'── {probe}, {into:.1f} s into its stroke (an unseen texture)':<{PROBE_LABEL_W}}{heads()}  error",
            f"{'console estimate':>{PROBE_LABEL_W}}{cells(ratings)}  {e_now:5.1f}",
            f"{'mean of windows':>{PROBE_LABEL_W}}{cells(mean)}  {e_mean:5.1f}",
            f"{'truth':>{PROBE_LABEL_W}}{cells(truth)}",
        ]


@dataclasses.dataclass
class FeedCounts:
    """What the terminal feed saw: window events, and those flagged out of distribution (by reason)."""

    windows: int = 0
    flagged: int = 0
    reasons: dict[str, int] = dataclasses.field(default_factory=dict)

    def add(self, event: dict) -> None:
        self.windows += 1
        if event.get("out_of_distribution"):
            self.flagged += 1
            for reason in event.get("ood_reasons") or ():
                self.reasons[reason] = self.reasons.get(reason, 0) + 1

    def summary(self) -> str:
        if not self.windows:
            return "no window estimated"
        why = ", ".join(f"{r} {n}" for r, n in sorted(self.reasons.items(), key=lambda kv: -kv[1]))
        return (
            f"{self.windows} windows estimated, {self.flagged} ({100 * self.flagged / self.windows:.1f} %) flagged out "
            f"of distribution" + (f" ({why})" if why else "")
        )


async def print_events(
    url: str,
    session: str,
    token: str,
    tour: ProbeTour,
    terminal: Terminal,
    report: ProbeReport | None = None,
    counts: FeedCounts | None = None,
) -> None:
    """Subscribe like the console does: every window updates the status line; a change of the rendered entry or of
    hysteresis, of the out-of-distribution flag, and each probe's report get lines of their own."""
    import websockets

    ws_url = url.replace("http", "ws", 1) + f"/sessions/{session}/events?token={token}"
    shown: tuple[str, bool] | None = None  # (rendered entry, held by hysteresis) last said
    flagged = False
    async with websockets.connect(ws_url) as ws:
        async for message in ws:
            event = json.loads(message)
            if event.get("type") != "window":
                continue
            t = event["t_end_s"]
            if counts is not None:
                counts.add(event)
            if report is not None:
                for line in report.add(t, event["ratings"], event["raw_ratings"]):
                    terminal.say(line)
            selection = event.get("selection") or {}
            held = bool(selection.get("held_by_hysteresis"))
            # a line when the rendered entry changes, or when hysteresis starts keeping it; not when it is free again
            if shown is None or event["chosen"] != shown[0] or (held and not shown[1]):
                terminal.say(wrapped(f"{t:7.1f} s rendering {event['chosen']} — {_why(event)}"))
            shown = (event["chosen"], held)
            if bool(event.get("out_of_distribution")) != flagged:
                flagged = not flagged
                reasons = ", ".join(event.get("ood_reasons") or ()) or "no reason given"
                terminal.say(
                    wrapped(
                        f"{t:7.1f} s " + (f"out of distribution: {reasons}" if flagged else "in distribution again")
                    )
                )
            # the probe this window belongs to, from its time (the robot may be ahead, stroking the next)
            current = tour.probe_at(t)
            truth = dict(zip(ATTRIBUTES, map(float, tour.library.entry(current).ratings)))
            terminal.status(
                status_line(
                    t,
                    current,
                    event["ratings"],
                    truth,
                    rating_error(event["ratings"], truth),
                    event["chosen"],
                    held=held,
                    provisional=bool(event.get("provisional")),
                    flagged=flagged,
                ),
                time.monotonic(),
            )


def _why(event: dict) -> str:
    """Why the entry is rendered, as the console says it: 'rule <rule>: <its reason>' (a held choice's reason says
    what keeps it: 'keeping a: b is closer by …'). The rule may read more than the ratings (the hybrid weighs the
    window's vibration against each entry's), so the chosen entry need not be the nearest by ratings."""
    selection = event.get("selection") or {}
    if not selection.get("reason"):
        return "nearest to the smoothed ratings"  # an older server: no reason sent
    return f"rule {selection['rule']}: {selection['reason']}"


class DaemonThreads(concurrent.futures.ThreadPoolExecutor):
    """The demo loop's default executor: one daemon thread per call. The simulated robot renders its next
    stretch of stroke in a thread (seconds of CPU on a busy machine); exiting must not wait for it, and nothing
    the demo runs in a thread holds anything that has to be finished."""

    def submit(self, fn, /, *args, **kwargs):
        future: concurrent.futures.Future = concurrent.futures.Future()

        def run() -> None:
            if not future.set_running_or_notify_cancel():
                return
            try:
                future.set_result(fn(*args, **kwargs))
            except BaseException as exc:  # noqa: BLE001 - handed to whoever awaits the future
                future.set_exception(exc)

        threading.Thread(target=run, name="demo-worker", daemon=True).start()
        return future

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        pass  # daemon threads of their own (the pool's are never started): nothing to wait for


class DemoStopped(Exception):
    """A signal asked the demo to stop before it was streaming."""


async def wait_ready(url: str, serving: asyncio.Task, stop: asyncio.Event, timeout_s: float = READY_TIMEOUT_S) -> None:
    """Poll GET url/ready until 200 (the model and library are loaded and warmed up).

    RuntimeError with /ready's last reason when the service stopped or was not ready within timeout_s;
    DemoStopped when `stop` was set meanwhile."""
    import httpx

    deadline = time.monotonic() + timeout_s
    why = "no answer yet"
    async with httpx.AsyncClient(timeout=2.0) as http:
        while True:
            if serving.done():
                serving.result()  # raises why it could not start (e.g. the port is taken)
                raise RuntimeError("the service stopped while starting")
            try:
                r = await http.get(f"{url}/ready")
                if r.status_code == 200:
                    return
                why = f"HTTP {r.status_code}: {r.text[:300]}"
            except httpx.TransportError as exc:
                why = f"{type(exc).__name__}: {exc}"
            if time.monotonic() > deadline:
                raise RuntimeError(f"the service at {url} was not ready within {timeout_s:g} s: {why}")
            if stop.is_set():
                raise DemoStopped
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), 0.1)


def local_address(host: str) -> str:
    """Where a client on this machine reaches a server listening on `host`: its loopback for every address ("",
    0.0.0.0, ::), the host itself otherwise (IPv6 in brackets, as a URL needs)."""
    if host in ("", "0.0.0.0"):
        return "127.0.0.1"
    if host == "::":
        return "[::1]"
    return f"[{host}]" if ":" in host else host


async def run_demo(
    assets: DemoAssets,
    *,
    host: str,
    port: int,
    per_texture_s: float,
    duration_s: float | None,
    report_after_s: float = REPORT_AFTER_S,
) -> None:
    """Serve, stream and print until duration_s, or until SIGINT / SIGTERM: the first stops the robot, the
    terminal feed and the service within STOP_S and prints the summary; a second quits at once."""
    import uvicorn

    from drivers.robot import RobotClient
    from service.app import create_app, server_options
    from service.server import SessionEndingServer, bind_socket
    from service.settings import Settings

    class DemoServer(SessionEndingServer):
        @contextlib.contextmanager
        def capture_signals(self):  # the demo handles SIGINT/SIGTERM: one stops robot, feed and service together
            yield

    loop = asyncio.get_running_loop()
    loop.set_default_executor(DaemonThreads())
    main = asyncio.current_task()
    stop = asyncio.Event()
    stop_asked: list[float] = []

    def on_signal() -> None:
        if stop.is_set():
            if main is not None:
                main.cancel()  # a second signal: quit now
            return
        stop_asked.append(time.monotonic())
        print("\nstopping (again to quit at once) …", flush=True)  # before the status line stops: a plain print
        stop.set()

    with on_stop_signals(on_signal):  # removed after the service has stopped and the summary is printed
        api_key = secrets.token_urlsafe(24)  # this run's fleet key: the demo's robot is its only member
        # bound here, not by uvicorn: with port 0 (any free port) the robot, the console URL and the summary need
        # the port the system picked before the service starts
        listening = bind_socket(host, port)
        port = listening.getsockname()[1]
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
        app = create_app(settings)
        server = DemoServer(uvicorn.Config(app, **server_options(settings)))
        serving = asyncio.create_task(server.serve(sockets=[listening]))
        url = f"http://{local_address(host)}:{port}"
        tour = ProbeTour(assets.probes, per_texture_s)
        # a short drain: at a stop the service goes too, so what is still unacknowledged after it cannot be delivered
        robot = RobotClient(url, tour, session_name="demo robot", api_key=api_key, drain_timeout_s=STOP_S / 2)
        truth = {i: dict(zip(ATTRIBUTES, map(float, tour.library.entry(i).ratings))) for i in tour.library.ids}
        report = ProbeReport(list(tour.library.ids), truth, per_texture_s, min(report_after_s, per_texture_s))
        counts = FeedCounts()
        terminal = Terminal()
        started = time.monotonic()
        tasks: list[asyncio.Task] = []
        try:
            await wait_ready(url, serving, stop)  # the robot opens its session only once the service can take it
            info = await robot.open_session()
            terminal.say(f"\nservice   {url}  (API docs {url}/docs)")
            terminal.say(f"console   {info.console_url}")  # a URL is never cut: a terminal wraps it
            terminal.say(
                wrapped(
                    "feel it   open the console URL, press Start sound, then stroke its touch pad with a mouse, pen "
                    "or finger: the chosen texture plays in headphones (or a voice-coil on the audio jack)",
                    indent=10,
                )
            )
            terminal.say(
                f"robot     strokes {len(tour.library.ids)} unseen textures, {per_texture_s:g} s each; Ctrl-C to stop\n"
            )
            terminal.say(status_header())
            if info.operator_token is None:
                raise RuntimeError("the service opened the demo's session without an operator token")
            printer = asyncio.create_task(
                print_events(url, info.session_id, info.operator_token, tour, terminal, report=report, counts=counts)
            )
            streaming = asyncio.create_task(robot.run(duration_s))
            stopping = asyncio.create_task(stop.wait())
            tasks = [printer, streaming, stopping]
            await asyncio.wait([streaming, stopping], return_when=asyncio.FIRST_COMPLETED)
            if stop.is_set():
                robot.stop()  # stop reading; deliver what is buffered for at most drain_timeout_s
                await asyncio.wait([streaming], timeout=STOP_S / 2 + 0.2)
            else:
                await asyncio.sleep(0.5)  # the last windows' events are still on their way
            if streaming.done() and not streaming.cancelled() and streaming.exception() is not None:
                raise streaming.exception()  # type: ignore[misc]
        except DemoStopped:
            pass
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            server.should_exit = True
            done, _ = await asyncio.wait([serving], timeout=STOP_S / 4)
            if not done:  # connections still open: close them now
                server.force_exit = True
                done, _ = await asyncio.wait([serving], timeout=STOP_S / 4)
            if not done:
                serving.cancel()
                await asyncio.gather(serving, return_exceptions=True)
            _stop_runtime(app)  # the lifespan's close did, unless serving had to be cancelled before it
            listening.close()  # uvicorn's shutdown closed it, unless serving was cancelled first
            terminal.close()
            terminal.say(f"demo summary: {counts.summary()} in {time.monotonic() - started:.1f} s")
            if report.errors:
                terminal.table(summary_table(report.errors, report.after_s))
            if stop_asked:
                terminal.say(f"stopped {time.monotonic() - stop_asked[0]:.2f} s after the signal")
        terminal.say(robot_line(robot.stats.as_dict()))


def _stop_runtime(app: FastAPI) -> None:
    """Stop the service's runtime (an embedding in flight ends, later ones are refused); nothing if none started."""
    state = getattr(app.state, "service", None)
    if state is not None:
        state.stop_runtime()


def demo(
    assets: DemoAssets,
    *,
    host: str = "127.0.0.1",
    port: int = 8000,
    per_texture_s: float = 20.0,
    duration_s: float | None = None,
) -> int:
    """The `hapticlink demo` entry: run the loop on prepared assets until Ctrl-C (or SIGTERM) or duration_s.

    Returns the exit code (0). The service's shutdown terminates an embedding under way (Runtime.stop), so the
    worker threads the interpreter joins at exit are done within milliseconds: one Ctrl-C is enough."""
    try:
        asyncio.run(run_demo(assets, host=host, port=port, per_texture_s=per_texture_s, duration_s=duration_s))
    except (KeyboardInterrupt, asyncio.CancelledError):
        print("\nstopped.")
    return 0
