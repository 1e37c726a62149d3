"""SerialBoardSource over a real pseudo-terminal pair: a thread plays the board on the master side."""

from __future__ import annotations

import asyncio
import os
import select
import threading
import time
import tty

import numpy as np
import pytest

from drivers.serial_board import BoardDecoder, SerialBoardSource, parse_header

HEADER = "#HL1 rate=1000 accel=g force=N position=mm"


def sample_values(counter: int) -> list[float]:
    """What the fake board measures at sample `counter`: ax, ay, az (g), fx, fy, fz (N), position (mm)."""
    return [0.001 * counter, -0.5, 1.0 + 0.25 * (counter % 4), 0.1, 0.0, 1.5 + 0.01 * counter, 0.2 * counter]


def data_line(counter: int) -> bytes:
    return (f"{counter}," + ",".join(f"{v:.4f}" for v in sample_values(counter)) + "\n").encode()


@pytest.fixture
def pty_port():
    """(master fd, slave device name); the slave is raw so bytes pass untouched."""
    master, slave = os.openpty()
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


def play_board(master: int, lines: list[bytes]) -> tuple[threading.Thread, dict]:
    """The board: wait for the host's header request (it comes right after the port is opened,
    and opening flushes the input), then send the lines."""
    seen = {"request": b""}

    def run() -> None:
        while b"#?\n" not in seen["request"]:
            ready, _, _ = select.select([master], [], [], 5.0)
            if not ready:
                return
            seen["request"] += os.read(master, 64)
        for chunk in lines:
            os.write(master, chunk)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, seen


def test_values_gaps_and_garbled_lines_over_a_pty(kit, pty_port):
    master, port = pty_port
    lost = {30, 31, 32}  # lines lost on the wire
    lines = [b"boot noise without a header\n", (HEADER + "\r\n").encode(), b"# board v1.2 says hello\n"]
    for c in range(100):
        if c in lost:
            continue
        if c == 50:
            lines.append(b"50,0.05,-0.5,1.5,0.1,oops,2.0,10.0\n")  # garbled: its sample is missing
        else:
            lines.append(data_line(c))
        if c == 60:
            lines.append(b"\xff\xfe\x00\n")  # noise between two good lines
        if c == 70:
            lines.append(b"9" * 700)  # a runaway line with no newline in sight...
            lines.append(b"123,4\n")  # ...whose tail must not be parsed as a sample
    expected_counters = [c for c in range(100) if c not in lost and c != 50]

    source = SerialBoardSource(port, block_s=0.02)
    board, seen = play_board(master, lines)

    async def main():
        return await asyncio.wait_for(kit.take(source, samples=len(expected_counters)), 20)

    blocks = asyncio.run(main())
    board.join(5)

    accel = np.concatenate([b.channels["accel"].data for b in blocks])
    force = np.concatenate([b.channels["force"].data for b in blocks])
    position = np.concatenate([b.channels["position"].data for b in blocks])
    truth = np.array([sample_values(c) for c in expected_counters])
    np.testing.assert_allclose(accel, truth[:, 0:3], atol=1e-4)
    np.testing.assert_allclose(force, truth[:, 3:6], atol=1e-4)
    np.testing.assert_allclose(position, truth[:, 6], atol=1e-4)
    assert {(k, c.units) for b in blocks for k, c in b.channels.items()} == {
        ("accel", "g"),
        ("force", "N"),
        ("position", "mm"),
    }
    assert {c.rate_hz for b in blocks for c in b.channels.values()} == {1000.0}

    # time is never shifted: every block starts at its first sample's counter / rate
    starts, i = [], 0
    for b in blocks:
        starts.append(expected_counters[i])
        i += b.channels["accel"].data.shape[0]
    assert [round(b.t0 * 1000) for b in blocks] == starts
    assert 33 in starts and 51 in starts, "a gap starts a new block at the true time"
    assert [b.seq for b in blocks] == list(range(len(blocks)))

    s = source.stats
    assert (s.gaps, s.missing_samples) == (2, 4)
    assert s.garbled == 3  # the bad number, the binary noise, the runaway line
    assert s.skipped == 1 and s.resyncs == 0
    assert not source._thread.is_alive(), "clean shutdown: the reader thread is gone"
    assert seen["request"] == b"#?\n", "the host asked the board for its header when it opened the port"


def test_a_bad_header_is_raised_with_its_reason(kit, pty_port):
    master, port = pty_port
    source = SerialBoardSource(port)
    play_board(master, [b"#HL1 rate=1000 accel=furlongs\n"])

    async def main():
        return await asyncio.wait_for(kit.take(source, samples=1), 10)

    with pytest.raises(ValueError, match="accel units must be one of"):
        asyncio.run(main())


def test_parse_header_names_what_is_wrong():
    h = parse_header("#HL1 rate=500 wrap=65536 accel=m/s^2 force[1]=N position[2]=m")
    assert h.rate_hz == 500 and h.wrap == 65536 and h.n_values == 6
    assert h.layout == (("accel", 3, "m/s^2"), ("force", 1, "N"), ("position", 2, "m"))
    for bad, why in [
        ("HL1 rate=1", "must start with"),
        ("#HL1 accel=g", "rate=<Hz> is required"),
        ("#HL1 rate=5 accel=g", "rate must lie in"),
        ("#HL1 rate=1000", "no channels"),
        ("#HL1 rate=1000 accel[2]=g", "accel has [3] column"),
        ("#HL1 rate=1000 torque=Nm", "unknown key 'torque'"),
        ("#HL1 rate=1000 accel=g accel=g", "appears twice"),
    ]:
        with pytest.raises(ValueError, match=why.replace("[", r"\[")):
            parse_header(bad)


def test_decoder_restart_header_continues_time_and_counts_a_resync():
    dec = BoardDecoder(0.1, parse_header("#HL1 rate=100 force[1]=N speed=mm/s"))
    out = []
    for c in range(5):
        out += dec.feed_line(f"{c},1.0,{c}".encode())
    out += dec.feed_line(b"#HL1 rate=200 force[1]=N speed=mm/s")  # the board restarted at another rate
    out += dec.feed_line(b"0,2.0,7")
    out += dec.flush()
    assert [round(b.t0, 4) for b in out] == [0.0, 0.05]
    assert out[1].channels["force"].rate_hz == 200.0 and dec.stats.resyncs == 1


def _decode(dec: BoardDecoder, lines: list[bytes]) -> list:
    out = []
    for raw in lines:
        out += dec.feed_line(raw.rstrip(b"\n"))
    return out + dec.flush()


def test_a_value_beyond_any_sensor_is_one_lost_sample_not_the_end_of_the_stream():
    dec = BoardDecoder(0.02, parse_header(HEADER))
    lines = [data_line(c) for c in range(60)]
    lines[20] = b"20,1000000.0,-0.5,1.0,0.1,0.0,1.5,4.0\n"  # 10⁶ g: beyond any accelerometer
    lines[40] = b"40,0.04,-0.5,1e39,0.1,0.0,1.9,8.0\n"  # beyond float32 too
    blocks = _decode(dec, lines)
    kept = [c for c in range(60) if c not in (20, 40)]
    accel = np.concatenate([b.channels["accel"].data for b in blocks])
    np.testing.assert_allclose(accel, np.array([sample_values(c) for c in kept])[:, 0:3], atol=1e-4)
    assert [round(b.t0 * 1000) for b in blocks] == [0, 21, 40 + 1]  # time is kept: each hole is where it was
    assert (dec.stats.out_of_range, dec.stats.gaps, dec.stats.missing_samples) == (2, 2, 2)


def test_only_decimal_numbers_in_lines_of_at_most_512_bytes_are_samples():
    """Python's int and float read '1_2_0' as 120 and '1_0.5' as 10.5; a 700-byte line that came with its newline
    in one read was parsed as a sample."""
    dec = BoardDecoder(0.02, parse_header(HEADER))
    lines = [data_line(c) for c in range(30)]
    lines[10] = b"1_0,0.01,-0.5,1.0,0.1,0.0,1.6,2.0\n"
    lines[20] = b"20,0.02,-0.5,1_0.5,0.1,0.0,1.7,4.0\n"
    lines[25] = b"25," + b"0" * 600 + b"1,-0.5,1.0,0.1,0.0,1.75,5.0\n"
    lines[5] = b"5, 0.005, -0.5, 1.25, 0.1, 0.0, 1.55, 1.0\n"  # spaces after the commas: still a sample
    blocks = _decode(dec, lines)
    kept = [c for c in range(30) if c not in (10, 20, 25)]
    accel = np.concatenate([b.channels["accel"].data for b in blocks])
    np.testing.assert_allclose(accel, np.array([sample_values(c) for c in kept])[:, 0:3], atol=1e-4)
    assert (dec.stats.garbled, dec.stats.gaps) == (3, 3)


def test_a_garbled_header_after_a_good_one_is_skipped_and_the_stream_goes_on():
    dec = BoardDecoder(0.02, parse_header(HEADER))
    lines = [data_line(c) for c in range(40)]
    lines.insert(25, b"#HL1 rate=1000 posit\x00on=mm accel=g\n")
    blocks = _decode(dec, lines)
    assert sum(b.channels["accel"].data.shape[0] for b in blocks) == 40
    assert (dec.stats.garbled, dec.stats.resyncs, dec.stats.gaps) == (1, 0, 0)
    with pytest.raises(ValueError, match="is not key=value"):  # before any good header: the board is misconfigured
        BoardDecoder(0.02).feed_line(b"#HL1 rate=1000 posit\x00on=mm accel=g")


def test_a_board_unplugged_and_plugged_back_keeps_the_stream(kit, tmp_path):
    """The port is a symlink (as udev's /dev/serial/by-id names are): the first pty goes away mid-stream, a new one
    takes its name, and the source reopens it; the samples before the unplug arrive, and the counter times the gap."""
    link = tmp_path / "ttyBOARD"
    first_master, first_slave = os.openpty()
    tty.setraw(first_slave)
    link.symlink_to(os.ttyname(first_slave))
    board, _ = play_board(first_master, [(HEADER + "\n").encode(), *[data_line(c) for c in range(50)]])
    source = SerialBoardSource(str(link), block_s=0.02)
    replugged: dict = {}

    def unplug_and_replug() -> None:
        board.join(5)
        time.sleep(0.3)  # the host reads what was sent
        os.close(first_master)  # unplugged: the host's reads fail
        time.sleep(0.5)
        master, slave = os.openpty()
        tty.setraw(slave)
        replugged.update(master=master, slave=slave)
        tmp = tmp_path / "ttyBOARD.new"
        tmp.symlink_to(os.ttyname(slave))
        tmp.replace(link)
        play_board(master, [(HEADER + "\n").encode(), *[data_line(c) for c in range(100, 150)]])

    async def main():
        threading.Thread(target=unplug_and_replug, daemon=True).start()
        return await asyncio.wait_for(kit.take(source, samples=90), 30)

    try:
        blocks = asyncio.run(main())
    finally:
        os.close(first_slave)
        for fd in (replugged.get("master"), replugged.get("slave")):
            if fd is not None:
                os.close(fd)
    counters = [*range(50), *range(100, 140)]  # 140-149: the block still open when the test stops reading
    accel = np.concatenate([b.channels["accel"].data for b in blocks])
    np.testing.assert_allclose(accel, np.array([sample_values(c) for c in counters])[:, 0:3], atol=1e-4)
    assert [round(b.t0 * 1000) for b in blocks] == [0, 20, 40, 100, 120]  # the partial block at 40, then the gap
    s = source.stats
    assert (s.reopened, s.gaps, s.missing_samples, s.resyncs) == (1, 1, 50, 0)


def _in_milli_g(line: bytes) -> bytes:
    """The board sends accel in mg while its header says g: every value 1000× too large, beyond any accelerometer."""
    counter, *values = line.decode().strip().split(",")
    scaled = [f"{float(v) * 1e3 + 20000:.1f}" if i < 3 else v for i, v in enumerate(values)]
    return (",".join([counter, *scaled]) + "\n").encode()


@pytest.mark.parametrize(
    ("wrong", "advice"),
    [
        pytest.param(lambda line: line.replace(b",", b";"), "baud rate 921600", id="semicolons"),
        # one endless 'line'
        pytest.param(lambda line: line.replace(b"\n", b"\r"), "baud rate 921600", id="cr-line-endings"),
        pytest.param(_in_milli_g, "do the header's units match", id="values-in-other-units"),
    ],
)
def test_bytes_that_never_decode_are_said_once(kit, pty_port, caplog, wrong, advice):
    master, port = pty_port
    source = SerialBoardSource(port, block_s=0.02)
    stop = threading.Event()

    def board() -> None:
        play_board(master, [(HEADER + "\n").encode()])[0].join(5)
        c = 0
        while not stop.is_set():  # a board that keeps talking in the wrong format
            os.write(master, wrong(data_line(c)))
            c += 1
            time.sleep(0.01)

    async def main():
        threading.Thread(target=board, daemon=True).start()
        it = source.__aiter__()
        task = asyncio.ensure_future(it.__anext__())
        await asyncio.sleep(3.0)
        task.cancel()
        await source.aclose()

    with caplog.at_level("WARNING", logger="drivers.serial_board"):
        asyncio.run(main())
    stop.set()
    said = [r.getMessage() for r in caplog.records if "no sample decoded" in r.getMessage()]
    assert len(said) == 1, said
    assert advice in said[0] and "out of range" in said[0]
    assert source.stats.samples == 0 and source.stats.garbled + source.stats.out_of_range >= 1


def test_a_robot_stopped_mid_block_delivers_what_the_board_already_sent(kit, fake_service, pty_port):
    """The last 30 of 130 samples (a block not yet full) were read from the board and dropped at the stop."""
    master, port = pty_port
    play_board(master, [(HEADER + "\n").encode(), *[data_line(c) for c in range(130)]])
    source = SerialBoardSource(port, block_s=0.05)  # 50 samples a block: 130 = 2 blocks + 30 held
    # the robot stops at 1 s; the board is quiet long before
    stats = kit.stream_source(fake_service.app, source, 1.0, backoff=(0.01, 0.05), seed=7)
    accepted = fake_service.only_session().accepted
    assert stats.acked == stats.read == 3 and stats.unsent == 0
    np.testing.assert_allclose(
        kit.concat(accepted, "accel"), np.array([sample_values(c) for c in range(130)])[:, 0:3], atol=1e-4
    )


def test_a_long_line_that_fails_at_its_end_is_judged_at_once():
    """Seven 16-digit values and a stray last byte: a number pattern that can split a run of digits in several
    ways backtracks through every split before it gives up (over a minute here). Run apart, so a hang fails the test
    instead of stalling the suite."""
    import subprocess
    import sys

    script = (
        "from drivers.serial_board import BoardDecoder, parse_header\n"
        f"dec = BoardDecoder(0.02, parse_header({HEADER!r}))\n"
        "dec.feed_line(('1,' + ','.join(['1234567890123456'] * 7) + 'x').encode())\n"
        "print(dec.stats.garbled)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["1"]  # one garbled line, nothing else


@pytest.mark.parametrize("boot", [b"", b"\x00"], ids=["silent", "a-boot-byte"])
def test_a_port_that_opens_and_fails_at_once_is_retried_with_backoff_and_said_once(monkeypatch, caplog, boot):
    """A board in a reset loop, or another process on the port: every open succeeds and the first reads fail, at
    most after a boot byte. The port is not back until it delivers samples, so the retries back off (0.25, 0.5,
    1 s …) and it is said to be gone once, not gone and back at every try."""
    import serial

    opens = []

    class FlappingPort:
        in_waiting = 0

        def __init__(self, *args, **kwargs) -> None:
            opens.append(time.monotonic())
            self.pending = boot

        def __enter__(self):
            return self

        def __exit__(self, *exc) -> None:
            pass

        def write(self, data: bytes) -> int:
            return len(data)

        def read(self, n: int) -> bytes:
            if self.pending:
                out, self.pending = self.pending, b""
                return out
            raise serial.SerialException("device reports readiness to read but returned no data")

    monkeypatch.setattr(serial, "Serial", FlappingPort)
    source = SerialBoardSource("/dev/ttyFLAPPING", block_s=0.02)
    stop = threading.Event()
    reader = threading.Thread(target=source._produce, args=(stop, lambda item: None), daemon=True)
    with caplog.at_level("WARNING", logger="drivers.serial_board"):
        reader.start()
        time.sleep(1.5)
        stop.set()
        reader.join(5)
    assert not reader.is_alive()
    gaps = np.diff(opens)
    assert len(opens) == 3 and np.all(gaps > [0.2, 0.45]), gaps  # opened at 0, 0.25, 0.75 s; the next at 1.75 s
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and "went away" in said[0], said
    assert source.stats.reopened == 0  # opened again twice, never back


def test_a_header_garbled_into_another_valid_one_is_skipped_and_time_goes_on():
    """'rate=1000' garbled to 'rate=1800' parses: it was taken as a board restart, and every later block was timed
    at 1.8 kHz from a resync. A board that restarts counts afresh; here the counter goes on, so it was noise."""
    dec = BoardDecoder(0.02, parse_header(HEADER))
    lines = [data_line(c) for c in range(40)]
    lines.insert(20, HEADER.replace("rate=1000", "rate=1800").encode() + b"\n")
    blocks = _decode(dec, lines)
    assert [round(b.t0 * 1000) for b in blocks] == [0, 20]
    assert all(b.channels["accel"].rate_hz == 1000.0 for b in blocks)
    accel = np.concatenate([b.channels["accel"].data for b in blocks])
    np.testing.assert_allclose(accel, np.array([sample_values(c) for c in range(40)])[:, 0:3], atol=1e-4)
    assert (dec.stats.garbled, dec.stats.resyncs, dec.stats.gaps) == (1, 0, 0)
