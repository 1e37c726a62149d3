"""What the model-mediated link costs: every byte the service sends an operator's renderer, per second.

`python -m benchmarks.bandwidth [--minutes 10] [--seconds-per-texture 60] [--speed 1] [--hatt-source DIR]`

A HaTT session, measured on the wire. A real service (child process) serves a library of HaTT's rated models
(`hapticlink library import-hatt`: 79 textures, 1.1–1.3 kB each in the compact encoding) with the surface's own model
learnt online (HAPTICLINK_SURFACE_MODEL=1: a new `session:<id>` version whenever it differs perceptibly, at most one a
second), estimating with a ridge-tactile model trained on a small synthetic world. A scripted robot (the real
RobotClient, `--speed` × real time; 1 by default, so the fits run at their real-time cadence) strokes one library
texture after another, `--seconds-per-texture` each, for `--minutes`; at each texture change its camera sends a frame
of the new texture (HaTT's photo), so the service sees the scene change and learns the new surface afresh.

Three operators (the real `hapticlink operator` client, each rendering a simulated stroke in real time) follow the
session, each through its own TCP proxy on loopback that counts every byte the service sends on that connection —
the WebSocket upgrade, every frame as it travels (headers and any compression included) and every HTTP answer (status
line, headers, body) — not an estimate:

- `library_shared` (**the default served**: models pushed on the feed, `?models=push`): the operator holds the
  library in advance (`?library=<digest>`: shared beforehand, as a model-mediated system installs its texture
  library); library entries are named, never sent; the learnt model goes whole once per surface and then as deltas;
- `library_not_shared`: the same feed, the operator holding nothing in advance: each library entry chosen is sent
  once (whole), the learnt model as above;
- `whole_models_fetched`: the feed without models (`?models=fetch`), each version fetched whole over HTTP (compact
  encoding, `GET /library/{id}/model`): how models travelled before.

Rates are bytes × 8 per second of stream time (the robot's). Below the application, IP and TCP headers (52 bytes per
segment with timestamps) come on top: `tcp_ip_estimate_bps` adds them for one segment per message received.
References: raw acceleration (1 kHz × 3 axes × 16 bit = 48 kbit/s) and the perceptual texture codec anchor
≈ 2.3 kbit/s (Chaudhari et al. 2015). Also the spectral error the compact encoding adds on HaTT's 100 models
(texture_library.spectrum, log-spectral distance over 20–500 Hz at the nine operating points). Writes
reports/fidelity/bandwidth.json (with the SHA-256 of the HaTT source it read) and the `bandwidth` and `renderer` keys
of reports/fidelity/results.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from benchmarks.report_file import write_report
from drivers.blocks import Frame
from drivers.operator.client import OperatorClient
from drivers.operator.devices import SimulatedStroke
from drivers.protocol import bearer
from drivers.robot import RobotClient
from drivers.source import blocks_from_arrays
from models.offline.provenance import file_input, provenance
from service.launcher import ServerProcess
from texture_library import atomic_file, model_codec
from texture_library.library import Library
from texture_library.render_model import RenderModel
from texture_library.spectrum import spectral_distance_db
from texture_library.stroke import stroke
from texture_library.trajectory import freehand, model_ranges

OUT = Path("reports/fidelity/bandwidth.json")
#: the fidelity report's results.json: this benchmark fills its `bandwidth` and `renderer` keys
RESULTS = Path("reports/fidelity/results.json")
#: the renderer benchmark's output (python -m benchmarks.renderer): its real-time factor at 10 ms blocks
RENDERER_BENCH = Path("reports/bench/renderer.json")
API_KEY = "bandwidth-bench-key-0123456789"
RAW_BPS = 1000 * 3 * 16
CODEC_ANCHOR_BPS = 2300
#: the HaTT session's target, bit/s (what is served by default: models pushed, library shared in advance)
HATT_TARGET_BPS = 500
#: IPv4 (20) + TCP with timestamps (32) per segment: what each message costs below the application
TCP_IP_BYTES = 52
#: the operators, by the way models reach them: (push, library held in advance)
OPERATORS = {
    "library_shared": (True, True),
    "library_not_shared": (True, False),
    "whole_models_fetched": (False, False),
}
DEFAULT_OPERATOR = "library_shared"


class CountingProxy:
    """A TCP proxy on loopback in front of the service: every byte the service sends through it (`down`, with its
    arrival times for the per-second series) and every byte sent to it (`up`)."""

    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self.down = 0
        self.up = 0
        self.arrivals: list[tuple[float, int]] = []  # (time.monotonic(), bytes) of the service's sends
        self.port = 0
        self._server: asyncio.Server | None = None

    async def start(self) -> CountingProxy:
        self._server = await asyncio.start_server(self._connection, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()

    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
        except OSError:
            writer.close()
            return
        await asyncio.gather(self._pipe(reader, up_writer, False), self._pipe(up_reader, writer, True))

    async def _pipe(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, down: bool) -> None:
        try:
            while data := await reader.read(65536):
                if down:
                    self.down += len(data)
                    self.arrivals.append((time.monotonic(), len(data)))
                else:
                    self.up += len(data)
                writer.write(data)
                await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            writer.close()


def per_second(arrivals: list[tuple[float, int]], start: float, seconds: int, speed: float) -> list[int]:
    """Bytes in each second of stream time (arrivals before the start land in the first, after the end in the last)."""
    out = np.zeros(seconds, np.int64)
    for t, n in arrivals:
        out[min(max(int((t - start) * speed), 0), seconds - 1)] += n
    return out.tolist()


class ScriptedRobot:
    """The robot's sensors: strokes over `textures` in turn, `seconds` each, as one stream of 20 ms blocks at `speed`
    × real time, and at each texture's start a camera frame of it (its PNG), so the service sees the scene change."""

    name = "scripted"

    def __init__(
        self, library: Library, textures: list[str], seconds: float, images: Path | None, speed: float, seed: int = 0
    ) -> None:
        accel, force, speed_mm_s = [], [], []
        self.frames: list[Frame] = []
        rate = 0.0
        for k, t in enumerate(textures):
            model = library.model(t)
            rate = model.rate_hz
            rng = np.random.default_rng([seed, k])
            traj = freehand(seconds + 0.5, rng, rate_hz=model.rate_hz, **model_ranges(model.max_speed, model.max_force))
            s = stroke(model, traj, rng)
            n = int(round(seconds * s.rate_hz))
            accel.append(s.accel[:n])
            force.append(s.force[:n])
            speed_mm_s.append(s.speed[:n])
            image = None if images is None else images / f"{t}.png"
            if image is not None and image.is_file():
                self.frames.append(Frame(k * seconds, image.read_bytes()))
        channels = {
            "accel": (np.concatenate(accel), rate, "m/s^2"),
            "force": (np.concatenate(force), rate, "N"),
            "speed": (np.concatenate(speed_mm_s), rate, "mm/s"),
        }
        self.blocks = list(blocks_from_arrays(channels, 0.02))
        self.speed = speed

    async def _iterate(self):
        # paced at `speed` × real time; each frame just before the first block of its texture
        start = time.monotonic()
        frames = list(self.frames)
        for b in self.blocks:
            await asyncio.sleep(max(0.0, start + b.t0 / self.speed - time.monotonic()))
            while frames and frames[0].t <= b.t0:
                yield frames.pop(0)
            yield b

    def __aiter__(self):
        return self._iterate()

    async def aclose(self) -> None:
        pass


async def session_run(
    url: str, server_port: int, library: Library, textures: list[str], seconds: float, images: Path | None,
    speed: float,
) -> dict:  # fmt: skip
    """The session: the robot's stream, the three operators through their proxies; what each received."""
    robot_source = ScriptedRobot(library, textures, seconds, images, speed)
    stream_s = len(textures) * seconds
    async with httpx.AsyncClient(base_url=url, timeout=30) as http:
        r = await http.post("/sessions", json={"name": "bandwidth"}, headers=bearer(API_KEY))
        r.raise_for_status()
        session = r.json()
        proxies = {name: await CountingProxy(server_port).start() for name in OPERATORS}
        operators = {
            name: OperatorClient(
                proxies[name].url,
                session["session_id"],
                session["operator_token"],
                SimulatedStroke(stream_s / speed + 120.0, seed=1),
                [],
                push=push,
                library=library if held else None,
            )
            for name, (push, held) in OPERATORS.items()
        }
        running = [asyncio.create_task(op.run()) for op in operators.values()]
        await asyncio.sleep(1.0)
        start = time.monotonic()
        robot = RobotClient(
            url, robot_source, session_id=session["session_id"], robot_token=session["robot_token"], frame_change=0.02
        )
        robot_stats = await robot.run()
        # every window published: none new for 3 s after the robot's last block was acknowledged
        seen, quiet_since = -1, time.monotonic()
        while time.monotonic() - quiet_since < 3.0:
            await asyncio.sleep(0.2)
            windows = sum(op.stats.feed_messages for op in operators.values())
            if windows != seen:
                seen, quiet_since = windows, time.monotonic()
        operator = bearer(session["operator_token"])
        status = (await http.get(f"/sessions/{session['session_id']}", headers=operator)).json()
        await http.delete(f"/sessions/{session['session_id']}", headers=operator)
        await asyncio.wait(running, timeout=15)
        for op in operators.values():
            op.stop()
        await asyncio.wait(running, timeout=10)
        for p in proxies.values():
            await p.close()
    seconds_n = int(np.ceil(stream_s))
    out = {}
    for name, op in operators.items():
        st, proxy = op.stats, proxies[name]
        series = per_second(proxy.arrivals, start, seconds_n, speed)
        latencies = [sw.latency_ms for sw in st.switches if sw.latency_ms is not None]
        out[name] = {
            "push": OPERATORS[name][0],
            "library_held_in_advance": OPERATORS[name][1],
            "bytes_sent_by_service": proxy.down,
            "bytes_sent_by_operator": proxy.up,
            "bps": round(8 * proxy.down / stream_s, 1),
            "tcp_ip_estimate_bps": round(8 * (proxy.down + TCP_IP_BYTES * st.feed_messages) / stream_s, 1),
            "peak_second_bytes": int(max(series)),
            "feed_messages": st.feed_messages,
            "model_bytes": st.model_bytes,
            "models": st.model_counts,
            "deltas_unusable": st.deltas_unusable,
            "model_errors": st.model_errors,
            "switches": len(st.switches),
            "learnt_versions_rendered": len({s.version for s in st.switches if s.entry.startswith("session:")}),
            "switch_latency_ms": {
                "median": round(float(np.median(latencies)), 1) if latencies else None,
                "p95": round(float(np.percentile(latencies, 95)), 1) if latencies else None,
                "max": round(float(np.max(latencies)), 1) if latencies else None,
            },
            "per_second_bytes": series,
        }
    return {
        "operators": out,
        "surface_model": status.get("surface_model"),
        "windows": status.get("counters", {}).get("windows"),
        "robot": {
            "blocks_acked": robot_stats.acked,
            "blocks_rejected": robot_stats.rejected,
            "frames_sent": robot_stats.frames_sent,
            "saturated": robot_stats.saturated,
        },
    }


def train_model(root: Path) -> Path:
    from models.offline.datasets.build import build
    from models.offline.train import train_and_export

    dataset = build("synthetic", root / "dataset", n_textures=12, duration_s=6)
    return train_and_export(dataset, "ridge-tactile", root / "ridge-tactile.onnx")


def encoding_error(models: list[tuple[str, object]]) -> dict:
    d, sizes, json_sizes = [], [], []
    for entry_id, model in models:
        doc = RenderModel.from_vibration_model(entry_id, model)
        payload = model_codec.encode(doc)
        _, back = model_codec.decode(payload)
        d.append(spectral_distance_db(model, back.to_vibration_model()))
        sizes.append(len(payload))
        json_sizes.append(len(doc.to_json_bytes()))
    return {
        "models": len(d),
        "lsf_bits": model_codec.LSF_BITS,
        "spectral_error_db_mean": round(float(np.mean(d)), 3),
        "spectral_error_db_max": round(float(np.max(d)), 3),
        "compact_bytes_mean": round(float(np.mean(sizes)), 1),
        "json_bytes_mean": round(float(np.mean(json_sizes)), 1),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0, help="stream time of the session")
    ap.add_argument("--seconds-per-texture", type=float, default=60.0)
    ap.add_argument("--speed", type=float, default=1.0, help="the robot's pace, × real time (fits run in real time)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hatt-source", type=Path, default=Path("../shared/data/hatt-texnet"))
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    argv = argv if argv is not None else sys.argv[1:]
    if not (args.hatt_source / "models").is_dir():
        print(f"benchmarks.bandwidth: no HaTT models under {args.hatt_source} (--hatt-source)", file=sys.stderr)
        return 2

    from texture_library.hatt_library import import_hatt
    from texture_library.hatt_xml import read_model

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        print("· HaTT's rated models as a library, and a ridge-tactile model …", flush=True)
        library, _ = import_hatt(args.hatt_source, root / "hatt-library")
        model = train_model(root)
        n = max(1, int(round(args.minutes * 60 / args.seconds_per_texture)))
        order = np.random.default_rng(args.seed).permutation(library.ids)
        textures = [str(order[k % len(order)]) for k in range(n)]
        stream_s = n * args.seconds_per_texture
        print(f"· streaming {stream_s:g} s over {n} HaTT textures ({args.seconds_per_texture:g} s each, "
              f"{args.speed:g} × real time) …", flush=True)  # fmt: skip
        server = ServerProcess(
            [sys.executable, "-m", "service.cli", "serve", "--model", str(model), "--library", str(library.root),
             "--log-level", "warning"],
            {"HAPTICLINK_API_KEYS": API_KEY, "HAPTICLINK_SESSION_IDLE_S": "900", "HAPTICLINK_SURFACE_MODEL": "1"},
        )  # fmt: skip
        try:
            got = asyncio.run(
                session_run(
                    server.url,
                    server.port,
                    library,
                    textures,
                    args.seconds_per_texture,
                    args.hatt_source / "images",
                    args.speed,
                )  # fmt: skip
            )
        finally:
            server.stop()
        served = {e: RenderModel.from_vibration_model(e, library.model(e)) for e in library.ids}
    compact = [len(model_codec.encode(d)) for d in served.values()]
    hatt_models = [(p.stem, read_model(p)) for p in sorted((args.hatt_source / "models").glob("*.xml"))]
    ops = got["operators"]
    bps = {name: ops[name]["bps"] for name in OPERATORS}
    load = Path("/proc/loadavg").read_text().split()[0] if Path("/proc/loadavg").exists() else "?"
    doc = {
        "command": "python -m benchmarks.bandwidth " + " ".join(argv),
        "session": {
            "stream_s": stream_s,
            "textures_stroked": textures,
            "seconds_per_texture": args.seconds_per_texture,
            "robot_speed_x_real_time": args.speed,
            "windows": got["windows"],
            "surface_model": got["surface_model"],
            "robot": got["robot"],
            "library_entries": len(library.ids),
            "library_compact_bytes_mean": round(float(np.mean(compact)), 1),
        },
        "bps": bps,
        "served_by_default": DEFAULT_OPERATOR,
        "hatt_session_bps": bps[DEFAULT_OPERATOR],
        "target_bps": HATT_TARGET_BPS,
        "assumptions": {
            "library_shared": "the operator holds the library before the session (installed with the operator "
            "station; named on the feed by its digest), so library entries are named, never sent",
            "library_not_shared": "the operator holds nothing: each library entry chosen is sent once, whole",
            "whole_models_fetched": "no models on the feed; each version fetched whole (compact) over HTTP",
            "updates": "the service's own learnt model (HAPTICLINK_SURFACE_MODEL=1) at its own cadence: a version "
            "when perceptibly different (≥ 1 dB, |Δμ| ≥ 0.05, …), at most one a second; a frame at each texture "
            "change tells the service the surface changed",
        },
        "operators": ops,
        "references_bps": {"raw_acceleration": RAW_BPS, "codec_anchor_chaudhari_2015": CODEC_ANCHOR_BPS},
        "raw_bps": RAW_BPS,
        "encoding": {"hatt": encoding_error(hatt_models)},
        "load_average_1min_at_end": load,
        "notes": "bytes the service sends, per second of stream time, counted by a TCP proxy in front of each "
        "operator: every byte of its WebSocket (upgrade, frames) and HTTP answers; tcp_ip_estimate_bps adds 52 bytes "
        "per message received for the IP and TCP headers below",
    }
    inputs = [file_input("hatt source", args.hatt_source)]
    write_report(args.out, doc, inputs)
    if args.out == OUT:
        update_fidelity_results(doc, RESULTS, RENDERER_BENCH, inputs)
    print(json.dumps({k: doc[k] for k in ("session", "bps", "encoding")}, indent=1))
    print(
        f"HaTT session, every byte the service sends per second: {bps['library_shared']:.0f} bit/s with the library "
        f"shared in advance (served by default; target ≤ {HATT_TARGET_BPS}), {bps['library_not_shared']:.0f} without, "
        f"{bps['whole_models_fetched']:.0f} with whole models fetched; raw {RAW_BPS} bit/s; codec anchor "
        f"{CODEC_ANCHOR_BPS} bit/s. Wrote {args.out}",
        flush=True,
    )
    return 0


def update_fidelity_results(doc: dict, results_path: Path, renderer_path: Path, inputs: list | None = None) -> None:
    """Fill results.json's `bandwidth` and `renderer` keys from this run (and the renderer benchmark's last run);
    the other keys — the selection study's, and `renderer.browser_vs_python_db`, which the console's parity test
    measures — are kept as they are. The bandwidth key records what it was made from (`provenance`)."""
    results = json.loads(results_path.read_text()) if results_path.is_file() else {}
    ops = doc["operators"]
    results["bandwidth"] = {
        "hatt_session_bps": doc["hatt_session_bps"],
        "hatt_session_what": f"{DEFAULT_OPERATOR}: models pushed on the feed, library held in advance",
        "hatt_session_bps_library_not_shared": doc["bps"]["library_not_shared"],
        "hatt_session_bps_whole_models_fetched": doc["bps"]["whole_models_fetched"],
        "target_bps": doc["target_bps"],
        "raw_bps": doc["raw_bps"],
        "command": doc["command"],
        "provenance": provenance(inputs or [], doc["command"]),
    }
    renderer = dict(results.get("renderer") or {})
    renderer["switch_latency_ms"] = ops[DEFAULT_OPERATOR]["switch_latency_ms"]["p95"]
    renderer["switch_latency_what"] = (
        "p95 over the HaTT session's switches of hapticlink operator on loopback (library held, models pushed): "
        "from the arrival of the window event that chose a model to the end of the first 10 ms block rendered with it"
    )
    if renderer_path.is_file():
        rows = json.loads(renderer_path.read_text())["rows"]
        factors = [s["realtime_factor"] for row in rows for s in row["streaming"] if s["block_ms"] == 10]
        if factors:
            renderer["realtime_factor"] = min(factors)
            renderer["realtime_factor_what"] = f"slowest model, 10 ms blocks, one core ({renderer_path})"
    results["renderer"] = renderer
    atomic_file.write_text(results_path, json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    sys.exit(main())
