"""Following a session live in Foxglove: how much of the session arrives, and what it adds to the service's CPU.

Run from the repository root:  python -m benchmarks.foxglove_live [--seconds 60] [--rounds 2]

The demo's service (benchmarks.service's `served` configuration: the demo's model, library and backbone) runs in
a child process. A simulated robot strokes one of the library's textures for --seconds; the stroke is written as
an MCAP ROS 2 bag (drivers/rosbag_writer.py, with the texture's photo as the camera) and streamed in real time by
RosbagSource and the robot client, once per session (after a tap block: the demo's models read taps, and a bag
carries no tap procedure), in rounds of two sessions:

- alone: an operator's event subscriber follows the session (the floor);
- followed: the same, and `hapticlink record --mcap OUT --foxglove PORT` (a child process) follows it too, with a
  Foxglove WebSocket protocol client (this process) subscribed to every channel it advertises.

Reported: the service's CPU (/proc, all threads) per second of session in each, and the ratio (target: following
adds ≤ 5 %); the recorder's own CPU; the fraction of the operator feed's window events the Foxglove client received
(target ≥ 99 %) and whether the MCAP file holds every event the feed carried. Writes reports/bench/foxglove_live.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from benchmarks.report_file import command_line, machine, write_report
from benchmarks.rosbag_read import host
from models.offline.provenance import file_input

DEFAULT_OUT = Path("reports/bench/foxglove_live.json")
API_KEY = "foxglove-live-benchmark-key-0123456789"
QUIET_S = 3.0


async def _feed(url: str, events: list, ready: asyncio.Event) -> None:
    """An operator's subscriber: every event of the session's feed."""
    from websockets.asyncio.client import connect

    async with connect(url, max_size=1 << 20) as ws:
        ready.set()
        async for message in ws:
            events.append(json.loads(message))


async def _foxglove(url: str, received: list, ready: asyncio.Event) -> None:
    """A Foxglove WebSocket protocol client subscribed to every advertised channel (ready once subscribed)."""
    from websockets.asyncio.client import connect

    deadline = time.monotonic() + 240  # until the recorder's server listens
    while True:
        try:
            ws = await connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"])
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)
    async with ws:
        channels: dict = {}
        while not channels:
            msg = json.loads(await ws.recv())
            if msg["op"] == "advertise":
                channels = {c["id"]: c["topic"] for c in msg["channels"]}
        subs = [{"id": k, "channelId": cid} for k, cid in enumerate(channels)]
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        topic_of = {s["id"]: channels[s["channelId"]] for s in subs}
        await asyncio.sleep(0.5)  # the server takes the subscription
        ready.set()
        async for frame in ws:
            if isinstance(frame, bytes) and frame[0] == 1:
                sub_id, log_ns = struct.unpack_from("<IQ", frame, 1)
                received.append((topic_of[sub_id], log_ns, json.loads(frame[13:])))


def _free_port() -> int:
    from service.launcher import free_port

    return free_port()


class TappedBag:
    """The demo's models read the tap features, and a bag carries no tap procedure: the robot taps the surface
    first (the texture model's tap transients, as the simulated robot taps), then the bag streams."""

    name = "tapped-bag"

    def __init__(self, bag: Path, model) -> None:
        from drivers.rosbag_source import RosbagSource

        self.source = RosbagSource(bag, realtime=True)
        self.model = model

    async def _items(self):
        from drivers.simulated import tap_block

        yield tap_block(self.model, t0=self.source.scan.start_ns * 1e-9)
        async for item in self.source:
            yield item

    def __aiter__(self):
        return self._items()

    async def aclose(self) -> None:
        await self.source.aclose()


async def session(server_url: str, bag: Path, model, followed: bool, service_pid: int, tmp: Path) -> dict:
    """One session streamed from the bag in real time; its measurements."""
    from benchmarks.service import process_cpu_seconds
    from drivers.protocol import ws_url
    from drivers.robot.client import RobotClient
    from drivers.rosbag_source import RosbagSource

    async with httpx.AsyncClient(base_url=server_url, timeout=30) as client:
        r = await client.post("/sessions", json={"name": "foxglove"}, headers={"Authorization": f"Bearer {API_KEY}"})
        r.raise_for_status()
        s = r.json()
    events: list = []
    feed_ready = asyncio.Event()
    feed = asyncio.ensure_future(
        _feed(ws_url(server_url, s["session_id"], "events", s["operator_token"]), events, feed_ready)
    )
    await asyncio.wait_for(feed_ready.wait(), 30)
    recorder = fox = None
    received: list = []
    out = tmp / f"estimates-{s['session_id']}.mcap"
    if followed:
        port = _free_port()
        argv = [sys.executable, "-m", "service.cli", "record", "--url", server_url, "--session", s["session_id"]]
        argv += ["--token", s["operator_token"], "--mcap", str(out), "--foxglove", f"127.0.0.1:{port}"]
        recorder = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        fox_ready = asyncio.Event()
        fox = asyncio.ensure_future(_foxglove(f"ws://127.0.0.1:{port}", received, fox_ready))
        deadline = time.monotonic() + 300  # the recorder starts a Python process: slow on a busy host
        while not fox_ready.is_set():
            if recorder.poll() is not None:
                said = recorder.communicate()[0].decode(errors="replace")
                raise RuntimeError(f"hapticlink record exited ({recorder.returncode}): {said}")
            if time.monotonic() > deadline or fox.done():
                recorder.kill()
                raise RuntimeError(f"no Foxglove channels from hapticlink record within 300 s ({fox!r})")
            await asyncio.sleep(0.2)
        await asyncio.sleep(5.0)  # the recorder subscribes to the session's feed right after its server listens
    source = TappedBag(bag, model) if model.taps is not None else RosbagSource(bag, realtime=True)
    cpu0, t0 = process_cpu_seconds(service_pid), time.monotonic()
    robot = RobotClient(server_url, source, session_id=s["session_id"], robot_token=s["robot_token"])
    stats = await robot.run()
    await asyncio.sleep(QUIET_S)
    wall, cpu = time.monotonic() - t0, process_cpu_seconds(service_pid) - cpu0
    row: dict = {
        "followed": followed,
        "session_s": round(wall, 2),
        "service_cpu_s": round(cpu, 3),
        "service_cpu_per_s": round(cpu / wall, 4),
        "blocks_acked": stats.acked,
        "feed_windows": sum(e["type"] == "window" for e in events),
        "feed_statuses": sum(e["type"] == "status" for e in events),
    }
    if followed:
        assert recorder is not None and fox is not None
        recorder_cpu = process_cpu_seconds(recorder.pid)
        fox.cancel()  # the client leaves, then the session ends: the recorder ends with it
        await asyncio.gather(fox, return_exceptions=True)
    async with httpx.AsyncClient(base_url=server_url, timeout=30) as client:  # the session ends: its feed closes
        r = await client.delete(f"/sessions/{s['session_id']}", headers={"Authorization": f"Bearer {s['robot_token']}"})
        r.raise_for_status()
    if followed:
        assert recorder is not None
        output = (await asyncio.to_thread(recorder.communicate, timeout=120))[0].decode(errors="replace")
        windows = [e for e in events if e["type"] == "window"]
        got = [p for t, _, p in received if t == "/hapticlink/window"]
        row["recorder_cpu_s"] = round(recorder_cpu, 3)
        row["foxglove_windows"] = len(got)
        row["foxglove_fraction"] = round(
            len({w["window_index"] for w in got} & {w["window_index"] for w in windows}) / max(1, len(windows)), 4
        )
        row["mcap_holds_every_event"] = _mcap_holds(out, events)
        row["recorder_said"] = output.strip().splitlines()[-1:] if output.strip() else []
    feed.cancel()
    await asyncio.gather(feed, return_exceptions=True)
    return row


def _mcap_holds(path: Path, events: list) -> bool:
    """Whether the recorder's MCAP file opens with the mcap reader and holds every window and status event of the
    operator's feed (its own "subscribed" status aside)."""
    from mcap.reader import make_reader

    with path.open("rb") as fh:
        recorded: dict[str, list] = {}
        for _, channel, message in make_reader(fh).iter_messages(log_time_order=False):
            recorded.setdefault(channel.topic, []).append(json.loads(message.data))
    windows = [e for e in events if e["type"] == "window"]
    statuses = [e for e in events if e["type"] == "status" and e.get("event") != "subscribed"]
    got_statuses = [e for e in recorded.get("/hapticlink/status", []) if e.get("event") != "subscribed"]
    return recorded.get("/hapticlink/window", []) == windows and got_statuses == statuses


def write_bag_from_library(library: Path, seconds: float, out: Path):
    """--seconds of the simulated robot stroking the library's first entry, as an MCAP bag with its photo; → (the
    bag, the entry's vibration model)."""
    from drivers.blocks import SampleBlock
    from drivers.rosbag_writer import stroke_messages, write_bag
    from drivers.simulated import SimulatedSource
    from texture_library.library import Library

    lib = Library.load(library)
    entry = lib.entries[0]
    image = (lib.root / entry.image_path).read_bytes() if entry.image_path else None

    async def take():
        return [i async for i in SimulatedSource(lib.model(entry.id), seed=0, realtime=False, duration_s=seconds)]

    blocks = [i for i in asyncio.run(take()) if isinstance(i, SampleBlock)]
    accel, force, speed = (np.concatenate([b.channels[k].data for b in blocks]) for k in ("accel", "force", "speed"))
    return write_bag(out, stroke_messages(accel, force, speed, 1000.0, image), "mcap"), lib.model(entry.id)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(prog="python -m benchmarks.foxglove_live", description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=60.0, help="seconds of stroking per session (default 60)")
    p.add_argument("--rounds", type=int, default=2, help="rounds of (alone, followed) sessions")
    p.add_argument("--assets", type=Path, default=Path("artifacts/demo"), help="the demo's assets (built if missing)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    if not sys.platform.startswith("linux"):
        p.error("CPU is read from /proc: Linux only")
    from benchmarks.service import ServerProcess, prepare_assets

    assets = prepare_assets(args.assets)["served"]
    load_before = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory(prefix="hapticlink-foxglove-bench-") as tmp:
        bag, model = write_bag_from_library(assets.library, args.seconds, Path(tmp) / "bag")
        server = ServerProcess.service(assets, API_KEY, instance_id="foxglove-live")
        try:
            for k in range(args.rounds):
                for followed in (False, True) if k % 2 == 0 else (True, False):
                    row = asyncio.run(session(server.url, bag, model, followed, server.proc.pid, Path(tmp)))
                    rows.append(row)
                    print(json.dumps(row), flush=True)
        finally:
            server.stop()
    alone = statistics.median(r["service_cpu_per_s"] for r in rows if not r["followed"])
    followed = statistics.median(r["service_cpu_per_s"] for r in rows if r["followed"])
    fractions = [r["foxglove_fraction"] for r in rows if r["followed"]]
    summary = {
        "service_cpu_per_s_alone": alone,
        "service_cpu_per_s_followed": followed,
        "added_cpu_fraction": round(followed / alone - 1, 4),
        "target_added_cpu_fraction": 0.05,
        "foxglove_fraction_min": min(fractions),
        "target_fraction": 0.99,
        "mcap_holds_every_event": all(r["mcap_holds_every_event"] for r in rows if r["followed"]),
    }
    print(json.dumps(summary))
    report = {
        "what": "a session followed live in Foxglove (hapticlink record --mcap --foxglove) against one that is not",
        "command": command_line("benchmarks.foxglove_live", argv),
        "seconds": args.seconds,
        "summary": summary,
        "sessions": rows,
        "host": {k: v for k, v in host().items() if k != "flags"},
        "machine": machine(load_before),
    }
    read = [file_input("model", assets.model), file_input("library", assets.library)]
    read += [
        file_input(role, path)
        for role, path in (("tactile model", assets.tactile), ("backbone", assets.backbone))
        if path is not None
    ]
    print(f"wrote {write_report(args.out, report, read)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
