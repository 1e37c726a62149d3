"""The operator's devices and outputs: a haptic device on a pseudo-terminal (HL1 in, rendered lines out), recorded
motion files, the WAV file, the sound card (skipped without one), and the render feed's format."""

from __future__ import annotations

import asyncio
import json
import os
import select
import threading
import tty
import wave

import numpy as np
import pytest

from drivers import render_feed
from drivers.blocks import ChannelBlock, SampleBlock
from drivers.operator.cli import device_from_spec, output_from_spec
from drivers.operator.devices import RecordedStroke, SerialDevice, motion_of, read_motion_file
from drivers.operator.outputs import SerialOutput, SoundOutput, WavOutput, load_sounddevice
from texture_library.recording import Channel, Recording, save_recording


@pytest.fixture
def pty_port():
    master, slave = os.openpty()
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


def test_a_haptic_device_on_a_serial_port_gives_speed_and_force(pty_port):
    master, port = pty_port
    lines = [b"#HL1 rate=1000 speed=m/s force[3]=N\n"]
    lines += [f"{c},{0.05 + 0.0001 * c:.5f},0.1,0.0,{1.0 + 0.001 * c:.4f}\n".encode() for c in range(300)]

    def board() -> None:
        request = b""
        while b"#?\n" not in request:
            ready, _, _ = select.select([master], [], [], 5.0)
            if not ready:
                return
            request += os.read(master, 64)
        for line in lines:
            os.write(master, line)

    threading.Thread(target=board, daemon=True).start()
    device = SerialDevice(port, block_s=0.05)

    async def main():
        got = []
        async for m in device:
            got.append(m)
            if sum(x.speed.size for x in got) >= 250:
                break
        await device.aclose()
        return got

    got = asyncio.run(asyncio.wait_for(main(), 20))
    speed = np.concatenate([m.speed for m in got])
    force = np.concatenate([m.force for m in got])
    c = np.arange(speed.size)
    np.testing.assert_allclose(speed, (0.05 + 0.0001 * c) * 1000, rtol=1e-5)  # m/s → mm/s
    np.testing.assert_allclose(force, 1.0 + 0.001 * c, rtol=1e-5)  # the normal column of (tx, ty, normal)


def test_a_device_that_reports_position_gives_the_bumps_their_position():
    """Position (m here, 2 axes) → mm along x, passed on to the renderer (which feels the bumps there)."""
    x = np.arange(100) * 1.2e-4  # m: 0.12 mm a sample, 120 mm/s
    block = SampleBlock(
        0.0,
        {
            "force": ChannelBlock(np.ones(100, np.float32), 1000.0, "N"),
            "position": ChannelBlock(np.stack([x, 0 * x], axis=1).astype(np.float32), 1000.0, "m"),
        },
    )
    m = motion_of(block)
    assert m.position is not None
    np.testing.assert_allclose(m.position, x * 1000, rtol=1e-6)
    np.testing.assert_allclose(m.speed[1:-1], 120.0, rtol=1e-3)
    speed_only = SampleBlock(
        0.0, {"force": block.channels["force"], "speed": ChannelBlock(np.ones(100), 1000.0, "mm/s")}
    )
    assert motion_of(speed_only).position is None


def test_a_device_block_without_speed_or_at_another_rate_is_named():
    block = SampleBlock(0.0, {"force": ChannelBlock(np.ones(10, np.float32), 1000.0, "N")})
    with pytest.raises(ValueError, match="force and speed"):
        motion_of(block)
    block = SampleBlock(
        0.0,
        {
            "force": ChannelBlock(np.ones(5, np.float32), 500.0, "N"),
            "speed": ChannelBlock(np.ones(5, np.float32), 500.0, "mm/s"),
        },
    )
    with pytest.raises(ValueError, match="at 1000 Hz, got 500 Hz"):
        motion_of(block)


def test_rendered_samples_go_to_the_device_as_lines(pty_port):
    master, port = pty_port
    out = SerialOutput(port)
    out.write(np.array([0.5, -1.25]), np.array([0.4, 0.41]))
    received = b""
    while received.count(b"\n") < 3:
        ready, _, _ = select.select([master], [], [], 5.0)
        assert ready, received
        received += os.read(master, 4096)
    out.close()
    assert received.decode().splitlines() == [
        SerialOutput.HEADER.decode().strip(),
        "0,0.50000,0.4000",
        "1,-1.25000,0.4100",
    ]


def test_recorded_motion_files(tmp_path):
    n = 2000
    speed = np.linspace(0, 100, n)
    force = np.full((n, 3), [0.1, 0.0, 2.0])
    rec = Recording(
        Channel(np.zeros((n, 3)), 1000.0), Channel(force, 1000.0), Channel(speed, 1000.0), None
    )  # fmt: skip
    save_recording(tmp_path / "stroke.npz", rec)
    s, f = read_motion_file(tmp_path / "stroke.npz")
    np.testing.assert_allclose(s, speed, rtol=1e-6)
    np.testing.assert_allclose(f, 2.0)
    (tmp_path / "stroke.csv").write_text("speed_mm_s,force_n\n" + "".join(f"{v},{1.5}\n" for v in range(10)))
    s, f = read_motion_file(tmp_path / "stroke.csv")
    assert s.tolist() == list(range(10)) and f.tolist() == [1.5] * 10
    (tmp_path / "bad.csv").write_text("v,f\n1,2\n")
    with pytest.raises(ValueError, match="speed_mm_s,force_n"):
        read_motion_file(tmp_path / "bad.csv")

    async def play():
        return [m async for m in RecordedStroke(tmp_path / "stroke.csv", block_s=0.004, realtime=False)]

    assert [m.speed.size for m in asyncio.run(play())] == [4, 4, 2]


def test_the_wav_output_is_16_bit_at_1_khz_and_counts_clipping(tmp_path):
    out = WavOutput(tmp_path / "x.wav", full_scale=10.0)
    out.write(np.array([0.0, 5.0, -10.0, 20.0]), np.zeros(4))
    out.close()
    with wave.open(str(tmp_path / "x.wav")) as w:
        assert (w.getframerate(), w.getsampwidth(), w.getnchannels()) == (1000, 2, 1)
        assert np.frombuffer(w.readframes(4), "<i2").tolist() == [0, 16384, -32767, 32767]
    assert out.clipped == 1


def test_the_sound_card_output_or_a_clear_reason_why_not():
    try:
        sd = load_sounddevice()
        if not sd.query_devices():
            raise RuntimeError("no audio device")
    except RuntimeError as exc:
        with pytest.raises(RuntimeError, match="sounddevice|PortAudio|no audio device"):
            SoundOutput()
        pytest.skip(f"no sound output here: {exc}")
    out = SoundOutput()
    out.write(np.zeros(100), np.zeros(100))
    out.close()


def test_device_and_output_specs_are_checked():
    with pytest.raises(ValueError, match="device spec"):
        device_from_spec("joystick", block_s=0.01, seed=0, loop=False)
    with pytest.raises(ValueError, match="seconds must be > 0"):
        device_from_spec("simulated:-1", block_s=0.01, seed=0, loop=False)
    with pytest.raises(ValueError, match="output spec"):
        output_from_spec("mp3:x", full_scale=40)


def test_the_render_feed_round_trip():
    view = render_feed.RenderView()
    window = {
        "type": "window",
        "window_index": 3,
        "chosen": "synth_001",
        "chosen_model_version": "0123456789abcdef",
        "ratings": {"rough_smooth": -31.4, "flat_bumpy": 8.5, "sticky_slippery": 130.0, "hard_soft": -48.0},
    }
    first = render_feed.parse(view.render(json.dumps(window)))
    assert (first.kind, first.chosen, first.version, first.ratings) == (
        "choice", "synth_001", "0123456789abcdef", (-31, 8, 100, -48)
    )  # fmt: skip
    again = view.render(json.dumps({**window, "window_index": 4}))
    assert isinstance(again, bytes) and len(again) == 4 and render_feed.parse(again).ratings == (-31, 8, 100, -48)
    moved = render_feed.parse(view.render(json.dumps({**window, "chosen": "synth_002"})))
    assert moved.kind == "choice" and moved.chosen == "synth_002"
    assert view.render(json.dumps({"type": "status", "event": "frame_received", "message": ""})) is None
    ended = json.dumps({"type": "status", "event": "session_ended", "message": "bye"})
    assert view.render(ended) == ended
    assert render_feed.parse(render_feed.choice_bytes("x", None, [1, 2, 3, 4])).version is None
    for bad, why in (
        (b"abc", "4 bytes of ratings or a choice"),
        (b"C\x00\x00\x00\x00" + bytes(8), "a choice"),
        (b"C\x00\x00\x00\x00" + bytes(8) + b"\xff", "not UTF-8"),
        ("{", "not JSON"),
        ('{"type": "x"}', "unknown message type"),
        ("[]", "object"),
    ):
        with pytest.raises(ValueError, match=why):
            render_feed.parse(bad)
