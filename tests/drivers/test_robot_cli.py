"""`hapticlink robot`: source specs, argument errors, and one run against the fake service."""

from __future__ import annotations

import argparse
import json
import os
import socket

import numpy as np
import pytest

from drivers.camera import WatchedDirectorySource
from drivers.cli import register, source_from_spec
from drivers.serial_board import SerialBoardSource
from drivers.usb_daq import UsbDaqSource
from texture_library.recording import Recording, make_channel, save_recording


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hapticlink")
    register(p.add_subparsers(dest="command", required=True))
    return p


@pytest.mark.parametrize(
    "spec, message",
    [
        ("simulated", "must be one of: simulated:LIBRARY_DIR:ENTRY_ID"),
        ("webcam:0", "unknown source kind 'webcam'"),
        ("simulated:only-a-dir", "expected simulated:DIR:ENTRY_ID"),
        ("replay:/no/such/dir:t1", "'/no/such/dir' is not a directory"),
        ("replay::t1", "both parts non-empty"),
        ("usb:1209", "expected usb:VID:PID"),
        ("usb:12g9:0001", "VID must be hexadecimal"),
        ("usb:1209:10000", "PID must lie in 0000…ffff"),
        ("serial:/dev/ttyUSB0:0", "baud rate must be positive"),
        ("camera-dir:/no/such/dir", "not a directory"),
    ],
)
def test_bad_specs_say_what_is_wrong(spec, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        source_from_spec(spec)


def test_only_the_simulated_source_taps():
    with pytest.raises(ValueError, match="--taps: only the simulated source"):
        source_from_spec("serial:COM3", taps=True)


def test_good_specs_build_their_sources(tmp_path):
    s = source_from_spec("serial:/dev/ttyUSB0:115200")
    assert isinstance(s, SerialBoardSource) and (s.port, s.baudrate) == ("/dev/ttyUSB0", 115200)
    assert source_from_spec("serial:COM3").port == "COM3"
    u = source_from_spec("usb:1209:0x0001", block_s=0.05)
    assert isinstance(u, UsbDaqSource) and (u.vid, u.pid, u.block_s) == (0x1209, 1, 0.05)
    assert isinstance(source_from_spec(f"camera-dir:{tmp_path}"), WatchedDirectorySource)


def test_robot_arguments(tmp_path):
    args = parser().parse_args(
        ["robot", "--source", "serial:COM3", "--url", "http://h:1", "--no-realtime", "--transport", "http"]
    )
    assert (args.realtime, args.transport, args.duration, args.session) == (False, "http", None, None)
    only_session = parser().parse_args(["robot", "--source", "serial:COM3", "--url", "http://h:1", "--session", "s1"])
    with pytest.raises(ValueError, match="--session and --token go together"):
        only_session.func(only_session)
    bad_url = parser().parse_args(["robot", "--source", f"camera-dir:{tmp_path}", "--url", "h:1"])
    with pytest.raises(ValueError, match="url must be http"):
        bad_url.func(bad_url)


def test_robot_command_replays_a_recording_into_a_new_session(kit, fake_service, tmp_path, capsys):
    rng = np.random.default_rng(0)
    rec = Recording(
        accel=make_channel("accel", rng.standard_normal((500, 3)), 1000.0),
        force=make_channel("force", rng.uniform(1, 2, 500), 1000.0),
        speed=make_channel("speed", rng.uniform(20, 80, 500), 1000.0),
    )
    folder = tmp_path / "textures" / "t1"
    folder.mkdir(parents=True)
    save_recording(folder / "recording_000.npz", rec)
    (folder / "meta.json").write_text(json.dumps({"recordings": ["recording_000.npz"], "images": []}))

    # The service runs in its own thread and loop: the command owns the main thread's loop.
    with kit.ServerThread(fake_service.app) as server:
        args = parser().parse_args(
            ["robot", "--source", f"replay:{tmp_path}:t1", "--url", server.url, "--no-realtime", "--transport", "http"]
        )
        status = args.func(args)
    out = capsys.readouterr().out.splitlines()
    sess = fake_service.only_session()
    assert status == 0
    assert (
        out[0].startswith("session s1")
        and out[2] == f"console {server.url}/console?session=s1&token={sess.operator_token}"
    )
    stats = json.loads(out[-1])
    assert stats["acked"] == stats["read"] == 2 and stats["lost"] == stats["unsent"] == 0  # 0.5 s in 250 ms blocks
    np.testing.assert_array_equal(kit.concat(sess.accepted, "speed"), rec.speed.data.astype(np.float32))


OPERATOR = ["operator", "--url", "http://h:1", "--session", "s1", "--token", "t"]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["robot", "--source", "serial:COM3", "--url", "http://h:1", "--seed", "-1"], "--seed must be a whole number"),
        ([*OPERATOR, "--block-s", "0"], "--block-s must lie in (0, 0.1] s"),
        ([*OPERATOR, "--block-s", "5"], "--block-s must lie in (0, 0.1] s"),
        ([*OPERATOR, "--crossfade-s", "-1"], "--crossfade-s must lie in [0, 1] s"),
        ([*OPERATOR, "--full-scale", "0"], "--full-scale must be a positive acceleration"),
        (["robot", "--source", "serial:COM3", "--url", "http://h:1", "--block-s", "0"], "--block-s must be a positive"),
        # a URL without its scheme: the operator rendered silence and exited 0, saying nothing
        (["operator", "--url", "127.0.0.1:8711", "--session", "s1", "--token", "t"], "url must be http://host[:port]"),
    ],
)
def test_bad_numbers_are_named_by_their_flag_before_anything_connects(argv, message):
    """numpy refused a negative seed without naming it; the operator took a zero block and rendered silence, and
    refused a negative crossfade only once connected (never, with the service unreachable)."""
    args = parser().parse_args(argv)
    with pytest.raises(ValueError) as refused:
        args.func(args)
    assert message in str(refused.value)


def test_a_source_that_does_not_open_ends_the_robot_before_it_opens_a_session(kit, fake_service, capsys):
    """It opened a session, printed its tokens and console link, then failed on the device: an orphan session."""
    with kit.ServerThread(fake_service.app) as server:
        args = parser().parse_args(
            ["robot", "--source", "serial:/dev/hapticlink-no-such-port", "--url", server.url, "--api-key", "k"]
        )
        status = args.func(args)
    captured = capsys.readouterr()
    assert status == 1 and "hapticlink-no-such-port" in captured.err
    assert fake_service.sessions == {} and "console" not in captured.out


def _replay_dataset(root, seconds: float = 0.5):
    """A dataset folder holding texture t1 with one recording of `seconds` at 1 kHz → the robot's replay SPEC."""
    rng = np.random.default_rng(0)
    n = int(seconds * 1000)
    rec = Recording(
        accel=make_channel("accel", rng.standard_normal((n, 3)), 1000.0),
        force=make_channel("force", rng.uniform(1, 2, n), 1000.0),
        speed=make_channel("speed", rng.uniform(20, 80, n), 1000.0),
    )
    folder = root / "textures" / "t1"
    folder.mkdir(parents=True)
    save_recording(folder / "recording_000.npz", rec)
    (folder / "meta.json").write_text(json.dumps({"recordings": ["recording_000.npz"], "images": []}))
    return rec, f"replay:{root}:t1"


def test_a_robot_whose_blocks_the_service_rejected_exits_1(kit, fake_service, tmp_path, capsys):
    """Every block rejected (an ERROR line each) and yet exit 0: a script driving the robot could not tell."""
    _, spec = _replay_dataset(tmp_path)
    fake_service.reject_seqs = {0, 1}
    with kit.ServerThread(fake_service.app) as server:
        args = parser().parse_args(
            ["robot", "--source", spec, "--url", server.url, "--no-realtime", "--transport", "http"]
        )
        status = args.func(args)
    stats = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert (stats["rejected"], stats["acked"], status) == (2, 0, 1)


def test_an_operator_that_never_reaches_the_service_says_so_and_exits_1(capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again at once: nothing listens there
    args = parser().parse_args(
        ["operator", "--url", f"http://127.0.0.1:{port}", "--session", "s1", "--token", "t", "--device",
         "simulated:1", "--out", f"wav:{os.devnull}", "--duration", "1"]
    )  # fmt: skip
    assert args.func(args) == 1
    assert "never reached the service's event feed" in capsys.readouterr().out
