"""Bounds from physics, on a real uvicorn: every physical quantity a robot sends has a documented range
(texture_library.channels: MAX_ABS, MAX_TAP_SPEED, MIN/MAX_RATE_HZ; models.tactile.stream: the clock), checked at
admission, refused 422 with the quantity, the value and the range; a clock that runs backwards starts a new segment;
a tap inside the bounds but outside what the model was trained on flags the windows it feeds."""

from __future__ import annotations

import json
import time
from dataclasses import replace

import numpy as np
import pytest
from websockets.sync.client import connect

from drivers.blocks import ChannelBlock, TapBlock, encode_binary, encode_json
from service.settings import Settings


def _block(kit, library_dir, seconds: float = 0.1):
    return kit.recording_blocks(kit.stroke_recording(library_dir, "synth_000", seconds))


def _with(block, kind: str, value: float):
    """`block` with one sample of channel `kind` set to `value` (in the channel's units)."""
    ch = block.channels[kind]
    data = np.array(ch.data, copy=True)
    data.flat[0] = value
    return replace(block, channels={**block.channels, kind: ChannelBlock(data, ch.rate_hz, ch.units)})


@pytest.mark.parametrize(
    ("kind", "value", "message"),
    [
        (
            "speed",
            10_000.0,
            "speed: scanning speed 1e+04 mm/s is outside its physical range, magnitude at most 2000 mm/s",
        ),
        ("force", -500.0, "force: force 500 N is outside its physical range, magnitude at most 200 N"),
        ("accel", 3000.0, "accel: acceleration 3000 m/s^2 is outside its physical range, magnitude at most 2000 m/s^2"),
    ],
)
def test_a_sample_outside_its_physical_range_is_refused_naming_it(kit, client, library_dir, kind, value, message):
    session = kit.create_session(client)
    good = _block(kit, library_dir)
    for content_type in (None, "application/json"):  # binary and JSON blocks alike
        r = kit.post_block(client, session, _with(good[0], kind, value), content_type)
        assert r.status_code == 422 and r.json()["detail"].startswith(message), r.text
    # the bound itself passes, and nothing refused was taken: the stream goes on from seq 0
    assert (
        kit.post_block(client, session, _with(good[0], kind, 2000.0 if kind != "force" else 200.0)).status_code == 202
    )
    assert kit.session_status(client, session)["counters"]["blocks_accepted"] == 1


def test_a_tap_speed_outside_its_physical_range_is_refused_naming_it(kit, client, library_dir, server):
    """The probe: tap speeds of 10,000 and 1,000,000 mm/s were taken, and every later window read hard–soft +100."""
    session = kit.create_session(client)
    accel = ChannelBlock(np.zeros((3, 100), np.float32), 1000.0, "m/s^2")
    for speed in (10_000.0, 1e6, 1e300):
        taps = TapBlock(0.0, np.array([20.0, speed, 30.0]), accel, seq=0)
        for content_type in (None, "application/json"):
            body = encode_binary(taps) if content_type is None else json.dumps(encode_json(taps)).encode()
            r = kit.post_block(client, session, body, content_type)
            assert r.status_code == 422, r.text
            assert r.json()["detail"] == (
                f"taps: tap speed {speed:.4g} mm/s is outside its physical range, 0 to 2000 mm/s: a sensor fault, "
                "or the wrong units"
            )
    with connect(kit.socket_url(server, session, "ingest")) as ws:  # the same over the ingest socket
        ws.send(encode_binary(TapBlock(0.0, np.array([10_000.0]), accel.__class__(accel.data[:1], 1000.0, "m/s^2"))))
        ack = json.loads(ws.recv(timeout=10))
    assert ack["ok"] is False and "tap speed 1e+04 mm/s is outside its physical range" in ack["error"]


def test_a_sample_rate_outside_its_range_names_the_sample_interval(kit, client, library_dir):
    session = kit.create_session(client)
    block = _block(kit, library_dir)[0]
    ch = block.channels["speed"]
    slow = replace(block, channels={**block.channels, "speed": ChannelBlock(ch.data, 5.0, ch.units)})
    r = kit.post_block(client, session, slow)
    assert r.status_code == 422
    assert r.json()["detail"].startswith("speed: sample rate must lie in [10, 100000] Hz, got 5 (a sample interval")


@pytest.mark.parametrize("back_samples", [1, 50])
def test_a_clock_running_backwards_starts_a_new_segment_never_merges(kit, client, library_dir, back_samples):
    """The probe: a clock running backwards by up to 50 ms a block was merged into one stream (1 segment, windows
    stamped 10.0–12.5 s while the robot's clock went from 10 to 7). Back by one sample of the fastest channel, or by
    50 ms: a new segment each time."""
    session = kit.create_session(client)
    blocks = _block(kit, library_dir, 0.2)
    rate = max(c.rate_hz for c in blocks[0].channels.values())
    step = back_samples / rate
    sent = [blocks[0], blocks[1]]  # continuous
    t = blocks[1].t0
    for b in blocks[2:5]:
        t = t - step  # each block starts `step` before the previous one did: the clock runs backwards
        sent.append(replace(b, t0=t))
    for seq, b in enumerate(sent):
        assert kit.post_block(client, session, replace(b, seq=seq)).status_code == 202
    assert kit.session_status(client, session)["segments"] == 4


def test_a_clock_drifting_forward_within_the_tolerance_continues_the_segment(kit, client, library_dir):
    """A sender clock running ahead of its sample count by 10 ms a block (within the 50 ms tolerance) is one stream;
    past the tolerance, a gap: a new segment."""
    session = kit.create_session(client)
    blocks = _block(kit, library_dir, 0.2)
    for seq, b in enumerate(blocks[:6]):
        assert kit.post_block(client, session, replace(b, seq=seq, t0=b.t0 + 0.01 * seq)).status_code == 202
    assert kit.session_status(client, session)["segments"] == 1
    assert kit.post_block(client, session, replace(blocks[6], seq=6, t0=blocks[6].t0 + 0.2)).status_code == 202
    assert kit.session_status(client, session)["segments"] == 2


@pytest.fixture(scope="module")
def taps_server(kit, taps_model, library_dir):
    settings = Settings(
        model_path=taps_model,
        library_dir=library_dir,
        api_keys=kit.API_KEY,
        instance_id="bounds-taps",
        session_idle_s=600,
        session_first_block_s=600,
        session_queue_windows=64,
        session_burst=10_000,
    )
    with kit.running(settings) as srv:
        yield srv


def _windows(kit, server, client, library_dir, speeds: np.ndarray, n: int = 3) -> list[dict]:
    """The first n window events of a session that tapped at `speeds` (the simulated robot's transients) and
    stroked."""
    import asyncio

    from drivers.simulated import SimulatedSource
    from texture_library.library import Library

    async def first():
        src = SimulatedSource(Library.load(library_dir).model("synth_002"), taps=True, realtime=False, duration_s=0.1)
        async for item in src:
            return item

    taps = asyncio.run(first())
    assert isinstance(taps, TapBlock)
    taps = replace(taps, speeds=np.resize(speeds, taps.speeds.shape).astype(float), seq=0)
    session = kit.create_session(client)
    with connect(kit.socket_url(server, session, "events")) as sub:
        assert kit.post_block(client, session, encode_binary(taps)).status_code == 202
        for seq, b in enumerate(_block(kit, library_dir, 1.5), start=1):
            assert kit.post_block(client, session, replace(b, seq=seq)).status_code == 202
        windows: list[dict] = []
        deadline = time.monotonic() + 60
        while len(windows) < n:
            event = json.loads(sub.recv(timeout=max(0.1, deadline - time.monotonic())))
            if event["type"] == "window":
                windows.append(event)
    return windows


def test_a_tap_inside_the_bounds_but_outside_the_training_range_flags_its_windows(kit, taps_server, library_dir):
    """The model was trained on taps at 5–80 mm/s (the synthetic world): taps at 1500 mm/s are physical (admitted)
    but unlike anything it learnt, so every window they feed is flagged out of distribution, saying why; taps
    inside the training range are not flagged for it."""
    import httpx

    with httpx.Client(base_url=taps_server.url, timeout=10) as client:
        fast = _windows(kit, taps_server, client, library_dir, np.array([1500.0]))
        usual = _windows(kit, taps_server, client, library_dir, np.array([30.0, 50.0]))
    assert all(w["out_of_distribution"] and "taps_out_of_range" in w["ood_reasons"] for w in fast), fast
    assert not any("taps_out_of_range" in w["ood_reasons"] for w in usual), [w["ood_reasons"] for w in usual]
