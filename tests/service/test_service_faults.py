"""The live service under the robustness study's faults: a real uvicorn, a robot on the real ingest
WebSocket, frames over HTTP and an operator on the events WebSocket. Noisy, clipped, gapped and out-of-range
blocks, invalid blocks, an unreadable frame, an under-exposed frame and then no frame at all: the service keeps
serving, never answers 5xx, flags the windows whose input it was not trained on, and loses no window of an
accepted block. The faults are models/offline/faults' pure functions, as in the offline study."""

from __future__ import annotations

import io
import json
import threading

import httpx
import numpy as np
from PIL import Image
from websockets.sync.client import connect

from drivers.blocks import encode_binary, encode_json
from drivers.source import blocks_from_arrays
from models.offline.datasets.format import Dataset
from models.offline.faults import camera, touch
from models.tactile.stream import StreamContract
from models.visual.image import load_image
from service.events import WindowEvent
from service.live_session import canonical_channels
from service.settings import Settings
from texture_library.attributes import ATTRIBUTES
from texture_library.recording import Recording

TEXTURE = "synth_002"


def _png(gray: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.round(np.clip(gray, 0, 1) * 255).astype(np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def _blocks(rec: Recording, start_s: float, stop_s: float, t0: float, seq0: int, accel=None, force_factor: float = 1.0):
    """Wire blocks of rec[start_s:stop_s] starting at stream time t0 (accel replaced by `accel` if given)."""
    cut = lambda c: c.data[int(start_s * c.rate_hz) : int(stop_s * c.rate_hz)]  # noqa: E731
    channels = {
        "accel": (cut(rec.accel) if accel is None else accel, rec.accel.rate_hz, "m/s^2"),
        "force": (cut(rec.force) * force_factor, rec.force.rate_hz, "N"),
        "speed": (cut(rec.speed), rec.speed.rate_hz, "mm/s"),
    }
    return list(blocks_from_arrays(channels, 0.02, t0=t0, seq0=seq0))


def test_the_live_service_keeps_serving_and_flags_faulty_input(kit, calibrated_visual_model, library_dir):
    m = calibrated_visual_model
    settings = Settings(
        model_path=m.model,
        tactile_model_path=m.tactile,
        library_dir=library_dir,
        backbone_path=m.backbone,
        instance_id="test-faults",
        api_keys=kit.API_KEY,
        session_burst=1000,
        session_queue_windows=64,
        session_idle_s=600,
        session_first_block_s=600,
        interval_level=0.8,
    )  # 8 calibration textures: a finite conformal quantile needs level ≤ 8/9
    rng = np.random.default_rng(kit.FIXED_SEED)
    rec = Dataset(m.dataset).recordings(TEXTURE)[0]  # in distribution by construction: a training stroke
    accel = lambda a, b: rec.accel.data[int(a * 1000) : int(b * 1000)]  # noqa: E731
    # (label, blocks): one second each; the gap drops 150 ms of stream time (a new segment)
    plan = [
        ("clean", _blocks(rec, 0.0, 1.5, 0.0, 0)),
        ("noise_0dB", _blocks(rec, 1.5, 2.5, 1.5, 75, accel=touch.add_noise(accel(1.5, 2.5), 0.0, rng))),
        ("clipped_10pc", _blocks(rec, 2.5, 3.5, 2.5, 125, accel=touch.clip_range(accel(2.5, 3.5), 0.1))),
        ("force_x4", _blocks(rec, 3.5, 4.5, 3.5, 175, force_factor=4.0)),
        ("after_gap", _blocks(rec, 4.65, 7.0, 4.65, 225)),
    ]
    photo = load_image(Dataset(m.dataset).image_paths(TEXTURE)[0])
    statuses: list[int] = []
    acks: list[dict] = []
    events: list[dict] = []
    stop = threading.Event()

    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=30) as client:
        session = kit.create_session(client)
        sid = session["session_id"]
        robot = {"Authorization": f"Bearer {session['robot_token']}"}

        def frame(body: bytes) -> int:
            r = client.post(f"/sessions/{sid}/frames", content=body, headers={**robot, "Content-Type": "image/png"})
            statuses.append(r.status_code)
            return r.status_code

        def operator():
            with connect(kit.socket_url(srv, session, "events")) as sub:
                while not stop.is_set():
                    try:
                        events.append(json.loads(sub.recv(timeout=0.2)))
                    except TimeoutError:
                        continue

        watcher = threading.Thread(target=operator, daemon=True)
        watcher.start()
        kit.wait_for(lambda: any(e.get("event") == "subscribed" for e in events))
        assert frame(_png(photo)) == 202  # a good frame: the scene's embedding
        kit.wait_for(lambda: any(e.get("event") == "visual_updated" for e in events), timeout_s=60)
        accepted = []
        with connect(kit.socket_url(srv, session, "ingest")) as ingest:

            def send(message) -> dict:
                ingest.send(message)
                ack = json.loads(ingest.recv(timeout=20))
                acks.append(ack)
                return ack

            for label, blocks in plan:
                if label == "after_gap":
                    # a bad frame (refused), then an under-exposed one (taken), then no frame at all
                    assert frame(b"\x89PNG\r\n\x1a\n not an image") == 422
                    assert frame(_png(camera.exposure(photo, 0.1))) == 202
                    kit.wait_for(lambda: sum(e.get("event") == "visual_updated" for e in events) >= 2, timeout_s=60)
                for i, block in enumerate(blocks):
                    if i == 3:  # an invalid block (NaN samples) with the next seq: refused, the socket stays open
                        bad = encode_json(block)
                        bad["channels"]["accel"]["data"][0][0] = float("nan")
                        assert send(json.dumps(bad))["ok"] is False  # json.dumps writes NaN, as a broken sender would
                    ack = send(encode_binary(block))
                    assert ack["ok"] is True and ack["duplicate"] is False, ack
                    accepted.append(block)
        # every window the accepted blocks complete, by the stream contract the service enforces
        runtime = srv.app.state.service.runtime
        contract = StreamContract(runtime.tactile_config)
        cursor, expected = contract.start(), 0
        for block in accepted:
            adv = contract.admit(cursor, canonical_channels(block), block.t0)
            cursor, expected = adv.cursor, expected + adv.windows_added
        status = kit.wait_for(
            lambda: (s := kit.session_status(client, session))["counters"]["windows"] >= expected and s, timeout_s=60
        )
        kit.wait_for(lambda: sum(e["type"] == "window" for e in events) >= expected, timeout_s=30)
        stop.set()
        watcher.join(timeout=5)
        assert client.get("/health").status_code == 200

    assert all(s < 500 for s in statuses)
    assert status["counters"]["windows"] == expected and status["windows_ready"] == 0
    assert status["counters"]["pipeline_errors"] == 0
    assert status["counters"]["blocks_accepted"] == len(accepted)
    assert status["segments"] == 2  # the gap started a new segment
    assert sum(1 for a in acks if not a["ok"]) == len(plan)  # each invalid block refused, with a reason
    assert all("NaN" in a["error"] or "finite" in a["error"] for a in acks if not a["ok"])
    windows = [WindowEvent.model_validate(e).model_dump() for e in events if e["type"] == "window"]
    assert [w["window_index"] for w in windows] == list(range(expected))  # none lost, none twice, in order
    assert all(w["interval"] is not None and w["out_of_distribution"] is not None for w in windows)

    def during(a: float, b: float) -> list[dict]:
        return [w for w in windows if a <= w["t_start_s"] and w["t_end_s"] <= b]

    for w in during(3.5, 4.5):  # pressing 4× harder than in training
        assert w["out_of_distribution"] and "force_out_of_range" in w["ood_reasons"], w["ood_reasons"]
    dark = during(4.65, 7.0)
    assert dark and all(w["out_of_distribution"] for w in dark)
    assert all(any(r.startswith("frame_") for r in w["ood_reasons"]) for w in dark[3:]), [
        w["ood_reasons"] for w in dark
    ]
    for w in during(1.5, 3.5):  # noise at 0 dB SNR, a sensor clipping at 10 % of the range
        assert w["out_of_distribution"], (w["t_start_s"], w["ood_reasons"])

    # flagged windows never keep the clean windows' narrow band
    def widths(w: dict) -> np.ndarray:
        return np.array(
            [w["interval"][a]["hi"] - w["interval"][a]["lo"] for a in w["interval"] if a not in ("level", "target")]
        )

    clean = [widths(w) for w in during(0.0, 1.5) if not w["out_of_distribution"]]
    assert clean and all(np.all(c < 200) for c in clean)
    # ... they widen to the hull of their own band and the population band (IntervalCalibration's fallback,
    # clipped to the rating range): never narrower than either, wherever the estimate's centre moved
    cal = runtime.main.calibration
    assert cal.scale == "none"  # the fixture's card: the unflagged band is a function of the estimate alone
    _, prior = cal.quantile(settings.interval_level)
    pop_lo, pop_hi = np.clip(cal.prior_center - prior, -100, 100), np.clip(cal.prior_center + prior, -100, 100)
    widened = False
    for w in during(3.5, 4.5):
        lo = np.array([w["interval"][a]["lo"] for a in ATTRIBUTES])
        hi = np.array([w["interval"][a]["hi"] for a in ATTRIBUTES])
        own_lo, own_hi = cal.interval(np.array([w["ratings"][a] for a in ATTRIBUTES]), None, settings.interval_level)
        assert np.all(lo <= np.minimum(own_lo, pop_lo) + 0.02) and np.all(hi >= np.maximum(own_hi, pop_hi) - 0.02), (
            lo,
            hi,
            own_lo,
            own_hi,
            pop_lo,
            pop_hi,
        )
        widened |= bool(np.any(hi - lo > own_hi - own_lo + 1))
    assert widened, "no flagged window's band grew beyond its own"
