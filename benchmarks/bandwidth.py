"""What the model-mediated link costs: bits per second from the service to an operator's renderer.

`python -m benchmarks.bandwidth [--minutes 10] [--seconds-per-texture 60] [--hatt-source DIR]`

A real service (child process; a ridge-tactile model trained on a small synthetic world, the synthetic library
of 24 textures) and a scripted robot (the real RobotClient, at 5 × real time) stroking one
library texture after another, `--seconds-per-texture` each (a texture change every minute by default), for
`--minutes` of stream time. Two subscribers record every message the service sends them: the lean render feed
(`?view=render`) and the full event stream (the console's). Models are fetched on demand the way the operator
client fetches them: once per model version, when a choice names a version not yet cached (compact encoding;
the JSON document measured too). Bytes counted are what the service sends: WebSocket payloads plus frame
headers (2 bytes below 126, 4 below 65 536), and for each model fetch the status line, headers and body of
the HTTP answer. Rates are per second of stream time.

Cases: (a) the library shared in advance — only the feed travels; (b) models fetched on demand — the feed plus
the fetches; (c) `hatt_session`: the same session with HaTT-sized models and the surface's own model learnt online
(below). References: raw acceleration (1 kHz × 3 axes × 16 bit = 48 kbit/s) and the perceptual texture
codec anchor ≈ 2.3 kbit/s (Chaudhari et al. 2015). Also the spectral error the compact encoding adds
(texture_library.spectrum, log-spectral distance over 20–500 Hz at the nine operating points) over the
synthetic library and, when at hand, HaTT's 100 models. Writes reports/fidelity/bandwidth.json.

The HaTT session (c), every byte per second of stream time. Measured in this run: the lean feed (its bytes, spread
evenly over the stream), a choice message's frame, an HTTP answer's status line and headers (around a compact
body), the number of library entries fetched. Measured on HaTT's models: their compact payloads (the n-th texture
stroked is HaTT's n-th model in a seeded order). Assumed — the online model's serving is not this benchmark's:
on each texture the service's own model of the surface goes out as a new version at ONLINE_UPDATES_S seconds
into the stroking (at most one per second, only when perceptibly different: a model that converges as data accrue
differs perceptibly ever more rarely), each with a choice message and a fetch; the first is a whole model (the
surface's own grid, not the library entry's), each later one differs from the last in the rows of the (speed,
force) region the robot visits (speed ≤ 200 mm/s, force ≤ 3 N: every such row refitted, LSFs moved by 0.3 % and
variance by 10 % — more change than a converging fit makes). Two ways to send the later ones: whole compact
models (what the service serves today) and deltas against the version the operator holds
(`model_codec.encode_delta`, not yet served).
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
from drivers import render_feed
from drivers.operator.client import OperatorClient
from drivers.operator.devices import SimulatedStroke
from drivers.protocol import bearer, ws_url
from drivers.robot import RobotClient
from drivers.source import blocks_from_arrays
from service.launcher import ServerProcess
from texture_library import atomic_file, model_codec
from texture_library.library import Library
from texture_library.render_model import RenderModel, content_version
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
TARGET_BPS = 230
#: IPv4 (20) + TCP with timestamps (32) per segment: what each message costs below the application
TCP_IP_BYTES = 52
#: how much faster than real time the scripted robot streams
SPEED = 5.0
#: seconds into each texture's stroking at which the online model goes out as a new version (assumed; see above)
ONLINE_UPDATES_S = (1, 2, 3, 5, 8, 13, 21, 34, 55)
#: the HaTT session's target, bit/s
HATT_TARGET_BPS = 500
#: the (speed mm/s, force N) region an online fit refits between versions (the robot's strokes reach it)
VISITED = (200.0, 3.0)
#: other assumptions the HaTT session is also costed under: (update times, rows refitted, library shared)
WHAT_IF: tuple[tuple[tuple[int, ...], int | None, bool], ...] = (
    (ONLINE_UPDATES_S, 3, False),
    (ONLINE_UPDATES_S, 3, True),
    ((1, 5, 21), 3, True),
    ((1, 5, 21), None, True),
    ((1,), None, True),
)


def ws_frame_bytes(payload: int) -> int:
    """A server-to-client WebSocket frame (unmasked): header + payload."""
    return payload + (2 if payload < 126 else 4 if payload < 65536 else 10)


def http_answer_bytes(r: httpx.Response) -> int:
    """Status line + headers + body of an HTTP/1.1 answer, as sent."""
    status = len(f"HTTP/1.1 {r.status_code} {r.reason_phrase}\r\n")
    return status + sum(len(k) + len(v) + 4 for k, v in r.headers.raw) + 2 + len(r.content)


class ScriptedRobot:
    """The robot's sensor: strokes over `textures` in turn, `seconds` each, as one stream of 20 ms blocks."""

    name = "scripted"

    def __init__(self, library: Library, textures: list[str], seconds: float, seed: int = 0) -> None:
        accel, force, speed = [], [], []
        for k, t in enumerate(textures):
            model = library.model(t)
            rng = np.random.default_rng([seed, k])
            traj = freehand(seconds + 0.5, rng, rate_hz=model.rate_hz, **model_ranges(model.max_speed, model.max_force))
            s = stroke(model, traj, rng)
            n = int(round(seconds * s.rate_hz))
            accel.append(s.accel[:n])
            force.append(s.force[:n])
            speed.append(s.speed[:n])
        channels = {
            "accel": (np.concatenate(accel), 1000.0, "m/s^2"),
            "force": (np.concatenate(force), 1000.0, "N"),
            "speed": (np.concatenate(speed), 1000.0, "mm/s"),
        }
        self.blocks = list(blocks_from_arrays(channels, 0.02))

    async def _iterate(self):
        # Paced at SPEED × real time: fast enough for a 10-minute session in a minute, slow enough that the
        # service and both subscribers keep up (a faster robot is refused 4429 and resends: its
        # robot_disconnected events would be counted as feed traffic, and slow subscribers drop events).
        start = time.monotonic()
        for b in self.blocks:
            await asyncio.sleep(max(0.0, start + b.t0 / SPEED - time.monotonic()))
            yield b

    def __aiter__(self):
        return self._iterate()

    async def aclose(self) -> None:
        pass


async def record(url: str, session: dict, view: str, into: list, done: asyncio.Event) -> None:
    """Every message of one subscriber: (kind, payload bytes, message) until the session ends."""
    from websockets.asyncio.client import connect

    target = ws_url(url, session["session_id"], "events", session["operator_token"])
    async with connect(target + ("&view=render" if view == "render" else ""), max_size=1 << 22) as ws:
        async for message in ws:
            size = len(message) if isinstance(message, bytes) else len(message.encode())
            into.append((size, message))
            if done.is_set():
                break


async def session_run(url: str, library: Library, textures: list[str], seconds: float) -> dict:
    async with httpx.AsyncClient(base_url=url, timeout=30) as http:
        r = await http.post("/sessions", json={"name": "bandwidth"}, headers=bearer(API_KEY))
        r.raise_for_status()
        session = r.json()
        lean: list = []
        full: list = []
        done = asyncio.Event()
        subs = [
            asyncio.create_task(record(url, session, "render", lean, done)),
            asyncio.create_task(record(url, session, "full", full, done)),
        ]
        # the operator's client itself, rendering a simulated stroke in real time: each switch's latency
        operator = OperatorClient(
            url,
            session["session_id"],
            session["operator_token"],
            SimulatedStroke(3600.0, seed=1),
            [],
        )
        rendering = asyncio.create_task(operator.run())
        await asyncio.sleep(0.5)
        robot = RobotClient(
            url,
            ScriptedRobot(library, textures, seconds),
            session_id=session["session_id"],
            robot_token=session["robot_token"],
        )
        await robot.run()
        # every window published: none new for 3 s after the robot's last block was acknowledged
        seen, quiet_since = -1, time.monotonic()
        while time.monotonic() - quiet_since < 3.0:
            await asyncio.sleep(0.2)
            if len(full) != seen:
                seen, quiet_since = len(full), time.monotonic()
        await asyncio.sleep(1.0)
        done.set()
        operator.stop()
        await asyncio.wait([rendering], timeout=10)
        await http.delete(f"/sessions/{session['session_id']}", headers=bearer(session["operator_token"]))
        await asyncio.wait(subs, timeout=10)

        # models on demand, as the operator client fetches them: once per version a choice names
        fetched: dict[str, dict] = {}
        choices = []
        for _, message in lean:
            msg = render_feed.parse(message)
            if msg.kind != "choice":
                continue
            choices.append((msg.chosen, msg.version))
            if msg.version in fetched:
                continue
            sizes = {}
            for name, accept in (("compact", model_codec.CONTENT_TYPE), ("json", "application/json")):
                a = await http.get(
                    f"/library/{msg.chosen}/model",
                    params={"session": session["session_id"]},
                    headers={**bearer(session["operator_token"]), "Accept": accept},
                )
                if a.status_code == 410 or a.status_code == 404:  # the session is over: the fleet key opens it too
                    a = await http.get(f"/library/{msg.chosen}/model", headers={**bearer(API_KEY), "Accept": accept})
                a.raise_for_status()
                sizes[name] = http_answer_bytes(a)
                sizes[name + "_envelope"] = http_answer_bytes(a) - len(a.content)
            fetched[str(msg.version)] = sizes
    latencies = [sw.latency_ms for sw in operator.stats.switches if sw.latency_ms is not None]
    return {"lean": lean, "full": full, "choices": choices, "fetched": fetched, "switch_latency_ms": latencies}


def refitted(doc: RenderModel, rng: np.random.Generator, rows: int | None = None) -> RenderModel:
    """`doc` with rows of the VISITED region refitted (see the module): LSFs × (1 + 0.3 % noise), kept sorted
    inside (0, π); variance × 1.1. rows: how many of the region's rows, drawn at random (None: all of them)."""
    content = doc.content()
    region = [i for i, (s, f) in enumerate(zip(doc.speeds_mm_s, doc.forces_n)) if s <= VISITED[0] and f <= VISITED[1]]
    if rows is not None:
        region = list(rng.choice(region, min(rows, len(region)), replace=False)) if region else []
    for i in region:
        for key in ("ar_lsf", "ma_lsf"):
            row = np.asarray(content[key][i], float)
            moved = np.sort(np.clip(row * (1 + 0.003 * rng.standard_normal(row.size)), 1e-4, np.pi - 1e-4))
            content[key][i] = moved.tolist()
        content["variance"][i] *= 1.1
    envelope = {"schema": doc.schema_, "schema_version": doc.schema_version, "id": doc.id}
    return RenderModel.model_validate({**envelope, "model_version": content_version(content), **content})


def hatt_session(
    hatt: list[RenderModel],
    *,
    stream_s: float,
    seconds_per_texture: float,
    feed_bytes: int,
    choice_frame_bytes: float,
    envelope_bytes: float,
    entry_fetches: int,
    seed: int = 0,
    updates_s: tuple[int, ...] = ONLINE_UPDATES_S,
    rows: int | None = None,
    library_shared: bool = False,
) -> dict:
    """Bytes the service sends per second of a HaTT session (the module's case c): (n,) per-second series for the
    whole-model and the delta way of sending updates, their means in bit/s, and what they are made of.

    updates_s: when each texture's online model goes out; rows: rows refitted between versions (None: the whole
    visited region); library_shared: the operator holds the library already (no entry fetches)."""
    n_s = int(np.ceil(stream_s))
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(hatt))
    feed = np.full(n_s, feed_bytes / stream_s)
    whole, delta = feed.copy(), feed.copy()
    n_textures = int(round(stream_s / seconds_per_texture))
    parts = {"feed": float(feed_bytes), "entry_fetches": 0.0, "updates_whole": 0.0, "updates_delta": 0.0}
    fetch_every = max(1, round(n_textures / max(entry_fetches, 1)))  # the run fetched this many library entries
    update_sizes: list[tuple[int, int]] = []
    for k in range(n_textures):
        t0 = int(k * seconds_per_texture)
        doc = hatt[order[k % len(hatt)]]
        # the library entry the camera and the estimate pick, fetched whole
        if not library_shared and k % fetch_every == 0:
            cost = envelope_bytes + len(model_codec.encode(doc))
            whole[t0] += cost
            delta[t0] += cost
            parts["entry_fetches"] += cost
        held: bytes | None = None
        held_doc = doc
        for u in updates_s:
            if u >= seconds_per_texture:
                break
            version = doc if held is None else refitted(held_doc, rng, rows)
            payload = model_codec.encode(version)
            sent = payload if held is None else model_codec.encode_delta(version, held)
            whole[t0 + u] += choice_frame_bytes + envelope_bytes + len(payload)
            delta[t0 + u] += choice_frame_bytes + envelope_bytes + len(sent)
            parts["updates_whole"] += choice_frame_bytes + envelope_bytes + len(payload)
            parts["updates_delta"] += choice_frame_bytes + envelope_bytes + len(sent)
            update_sizes.append((len(payload), len(sent)))
            held, held_doc = payload, version
    sizes = np.array(update_sizes)
    return {
        "assumed_updates_at_s_per_texture": list(updates_s),
        "rows_refitted_per_update": "the whole visited region" if rows is None else rows,
        "library_shared": library_shared,
        "updates": len(update_sizes),
        "update_bytes_whole_mean": round(float(sizes[:, 0].mean()), 1),
        "update_bytes_delta_mean": round(float(sizes[:, 1].mean()), 1),
        "bps_whole_models": round(8 * float(whole.sum()) / stream_s, 1),
        "bps_deltas": round(8 * float(delta.sum()) / stream_s, 1),
        "peak_second_bytes_whole": round(float(whole.max()), 1),
        "peak_second_bytes_delta": round(float(delta.max()), 1),
        "bytes": {k: round(v) for k, v in parts.items()},
        "per_second_bytes_whole": [round(float(v), 1) for v in whole],
        "per_second_bytes_delta": [round(float(v), 1) for v in delta],
        "target_bps": HATT_TARGET_BPS,
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
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hatt-source", type=Path, default=Path("../shared/data/hatt-texnet"))
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    argv = argv if argv is not None else sys.argv[1:]

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        from texture_library.synthetic_library import build_synthetic_library

        print("· a synthetic library of 24 textures and a ridge-tactile model …", flush=True)
        library = build_synthetic_library(root / "library", n_textures=24, seed=args.seed, image_size=64)
        model = train_model(root)
        n = max(1, int(round(args.minutes * 60 / args.seconds_per_texture)))
        order = np.random.default_rng(args.seed).permutation(library.ids)
        textures = [str(order[k % len(order)]) for k in range(n)]
        stream_s = n * args.seconds_per_texture
        print(f"· streaming {stream_s:g} s over {n} textures ({args.seconds_per_texture:g} s each) …", flush=True)
        server = ServerProcess(
            [sys.executable, "-m", "service.cli", "serve", "--model", str(model), "--library", str(library.root),
             "--log-level", "warning"],
            {"HAPTICLINK_API_KEYS": API_KEY, "HAPTICLINK_SESSION_IDLE_S": "600"},
        )  # fmt: skip
        try:
            got = asyncio.run(session_run(server.url, library, textures, args.seconds_per_texture))
        finally:
            server.stop()
        synthetic_models = [(i, library.model(i)) for i in library.ids]

    lean_bytes = sum(ws_frame_bytes(s) for s, _ in got["lean"])
    full_bytes = sum(ws_frame_bytes(s) for s, _ in got["full"])
    compact_fetch = sum(f["compact"] for f in got["fetched"].values())
    json_fetch = sum(f["json"] for f in got["fetched"].values())
    windows = sum(1 for _, m in got["full"] if isinstance(m, str) and '"type":"window"' in m)
    bps = {
        "a_library_shared": 8 * lean_bytes / stream_s,
        "b_models_on_demand": 8 * (lean_bytes + compact_fetch) / stream_s,
        "b_models_on_demand_json": 8 * (lean_bytes + json_fetch) / stream_s,
        "full_event_stream": 8 * full_bytes / stream_s,
        "b_with_tcp_ip_headers": 8
        * (lean_bytes + compact_fetch + TCP_IP_BYTES * (len(got["lean"]) + 2 * len(got["fetched"])))
        / stream_s,  # fmt: skip
    }
    hatt = sorted((args.hatt_source / "models").glob("*.xml")) if args.hatt_source else []
    errors = {"synthetic": encoding_error(synthetic_models)}
    hatt_doc = None
    if hatt:
        from texture_library.hatt_xml import read_model

        hatt_models = [(p.stem, read_model(p)) for p in hatt]
        errors["hatt"] = encoding_error(hatt_models)
        choice_frames = [ws_frame_bytes(size) for size, m in got["lean"] if render_feed.parse(m).kind == "choice"]
        measured = {
            "stream_s": stream_s,
            "seconds_per_texture": args.seconds_per_texture,
            "feed_bytes": lean_bytes,
            "choice_frame_bytes": float(np.mean(choice_frames)) if choice_frames else 0.0,
            "envelope_bytes": float(np.mean([f["compact_envelope"] for f in got["fetched"].values()])),
            "entry_fetches": len(got["fetched"]),
            "seed": args.seed,
        }
        served = [RenderModel.from_vibration_model(name, m) for name, m in hatt_models]
        hatt_doc = {"measured_in_this_run": measured, **hatt_session(served, **measured)}
        bps["c_hatt_session"] = hatt_doc["bps_whole_models"]
        bps["c_hatt_session_deltas"] = hatt_doc["bps_deltas"]
        hatt_doc["what_if"] = [
            {
                k: v
                for k, v in hatt_session(served, **measured, updates_s=u, rows=r, library_shared=shared).items()
                if not k.startswith("per_second")
            }
            for u, r, shared in WHAT_IF
        ]
    load = Path("/proc/loadavg").read_text().split()[0] if Path("/proc/loadavg").exists() else "?"
    doc = {
        "command": "python -m benchmarks.bandwidth " + " ".join(argv),
        "session": {
            "stream_s": stream_s,
            "textures_stroked": n,
            "seconds_per_texture": args.seconds_per_texture,
            "windows": windows,
            "choice_messages": len(got["choices"]),
            "distinct_models_fetched": len(got["fetched"]),
            "lean_messages": len(got["lean"]),
            "lean_bytes": lean_bytes,
            "full_bytes": full_bytes,
            "model_fetch_bytes_compact": compact_fetch,
            "model_fetch_bytes_json": json_fetch,
        },
        "bps": {k: round(v, 1) for k, v in bps.items()},
        "references_bps": {"raw_acceleration": RAW_BPS, "codec_anchor_chaudhari_2015": CODEC_ANCHOR_BPS},
        "target_bps": TARGET_BPS,
        "model_mediated_bps": round(bps["b_models_on_demand"], 1),
        "raw_bps": RAW_BPS,
        "encoding": errors,
        "hatt_session": hatt_doc,
        "switch_latency_ms": {
            "what": "hapticlink operator's client on loopback: from the arrival of the window event that chose an "
            "entry "
            "to the end of the first 10 ms block rendered with it (model fetch included when not cached)",
            "switches": len(got["switch_latency_ms"]),
            "median": round(float(np.median(got["switch_latency_ms"])), 1) if got["switch_latency_ms"] else None,
            "p95": round(float(np.percentile(got["switch_latency_ms"], 95)), 1) if got["switch_latency_ms"] else None,
            "max": round(float(np.max(got["switch_latency_ms"])), 1) if got["switch_latency_ms"] else None,
        },
        "load_average_1min_at_end": load,
        "notes": "bytes the service sends, per second of stream time: WebSocket payloads + frame headers, HTTP "
        "answers (status line, headers, body); b_with_tcp_ip_headers adds 52 bytes per message and two segments per "
        "fetch (ACKs and the operator's requests travel the other way and are not counted)",
    }
    write_report(args.out, doc)
    if args.out == OUT:
        update_fidelity_results(doc, RESULTS, RENDERER_BENCH)
    print(json.dumps({k: doc[k] for k in ("session", "bps", "encoding", "switch_latency_ms")}, indent=1))
    print(
        f"models on demand: {bps['b_models_on_demand']:.0f} bit/s (target ≤ {TARGET_BPS}); library shared: "
        f"{bps['a_library_shared']:.0f} bit/s; full event stream {bps['full_event_stream']:.0f} bit/s; "
        f"raw {RAW_BPS} bit/s; codec anchor {CODEC_ANCHOR_BPS} bit/s. Wrote {args.out}",
        flush=True,
    )
    return 0


def update_fidelity_results(doc: dict, results_path: Path, renderer_path: Path) -> None:
    """Fill results.json's `bandwidth` and `renderer` keys from this run (and the renderer benchmark's last run);
    the other keys — the selection study's, and `renderer.browser_vs_python_db`, which the console's parity test
    measures — are kept as they are."""
    results = json.loads(results_path.read_text()) if results_path.is_file() else {}
    results["bandwidth"] = {
        "model_mediated_bps": doc["model_mediated_bps"],
        "raw_bps": doc["raw_bps"],
        "library_shared_bps": doc["bps"]["a_library_shared"],
        "hatt_session_bps": doc["bps"].get("c_hatt_session"),
        "hatt_session_bps_deltas": doc["bps"].get("c_hatt_session_deltas"),
        "command": doc["command"],
    }
    renderer = dict(results.get("renderer") or {})
    renderer["switch_latency_ms"] = doc["switch_latency_ms"]["p95"]
    renderer["switch_latency_what"] = "p95 over the session's switches: " + doc["switch_latency_ms"]["what"]
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
