"""An accelerometer/force board on a serial port, speaking the HL1 line protocol (docs/drivers.md).

    #HL1 rate=1000 accel=g force=N position=mm          header: rate, then channels in column order
    17,0.01,-0.02,1.00,0.10,0.00,1.52,12.5               one sample: counter, then the columns

The host writes `#?\n` on open and the board answers with its header (it also sends it at boot).
Values are sent in the board's own units; converting them is the service's job. A counter gap
ends the current block early and the next block starts at the right time; garbled lines are
counted and skipped, never parsed into shifted samples.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from drivers.blocks import SampleBlock
from drivers.source import (
    Item,
    StreamAssembler,
    StreamStats,
    ThreadedSource,
    check_positive,
    device_rate,
    layout_channel,
)
from texture_library.channels import MAX_ABS, UNIT_SCALE

log = logging.getLogger(__name__)

HEADER_TAG = "#HL1"
HEADER_REQUEST = b"#?\n"
DEFAULT_COLUMNS = {"accel": 3, "force": 3, "speed": 1, "position": 1}
MAX_LINE_BYTES = 512
#: seconds between tries to reopen a port that went away (doubling from the first to the last)
REOPEN_S = (0.25, 4.0)
#: seconds of bytes arriving with no sample decoded before the source says the line format or baud rate is wrong
UNDECODED_WARN_S = 2.0
_TOKEN = re.compile(r"^(?P<kind>[a-z]+)(?:\[(?P<cols>\d+)\])?=(?P<value>\S+)$")
#: a data line: a decimal counter, then decimal numbers (Python's int and float alone would take "1_2_0" as 120).
#: Each number matches one way only: "\d+\.?\d*" split a run of digits between its two parts in as many ways as it
#: had digits, so a long line failing at its end backtracked through their product (seconds per line)
_NUMBER = r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"


@dataclass(frozen=True)
class BoardHeader:
    """What an HL1 header declares: sample rate (Hz), counter wrap, and (kind, columns, units) in column order."""

    rate_hz: float
    wrap: int
    layout: tuple[tuple[str, int, str], ...]

    @property
    def n_values(self) -> int:
        """Numbers per data line after the counter."""
        return sum(cols for _, cols, _ in self.layout)


def parse_header(line: str) -> BoardHeader:
    """Parse `#HL1 rate=<Hz> [wrap=<N>] <kind>[<cols>]=<units> …`; ValueError names the bad token."""
    tokens = line.strip().split()
    if not tokens or tokens[0] != HEADER_TAG:
        raise ValueError(f"serial header must start with {HEADER_TAG!r}, got {line.strip()[:40]!r}")
    rate: float | None = None
    wrap = 2**32
    layout: list[tuple[str, int, str]] = []
    for tok in tokens[1:]:
        m = _TOKEN.match(tok)
        if not m:
            raise ValueError(f"serial header token {tok!r} is not key=value or kind[cols]=units")
        kind, cols, value = m["kind"], m["cols"], m["value"]
        if kind == "rate" and cols is None:
            try:
                number = float(value)
            except ValueError:
                raise ValueError(f"serial header: rate must be a number (Hz), got {value!r}") from None
            rate = device_rate(number, "serial header")
        elif kind == "wrap" and cols is None:
            if not value.isdigit() or int(value) < 2:
                raise ValueError(f"serial header: wrap must be an integer ≥ 2, got {value!r}")
            wrap = int(value)
        elif kind in UNIT_SCALE:
            n = DEFAULT_COLUMNS[kind] if cols is None else int(cols)
            layout.append(layout_channel(layout, kind, n, value, "serial header"))
        else:
            raise ValueError(f"serial header: unknown key {kind!r} (expected rate, wrap or one of {list(UNIT_SCALE)})")
    if rate is None:
        raise ValueError("serial header: rate=<Hz> is required")
    if not layout:
        raise ValueError("serial header declares no channels")
    return BoardHeader(rate, wrap, tuple(layout))


@dataclass
class BoardStats(StreamStats):
    """StreamStats plus what the line protocol saw (written by the reader thread only)."""

    lines: int = 0  # data lines read, good or not
    garbled: int = 0  # lines that could not be decoded (skipped; the counter shows the hole)
    out_of_range: int = 0  # lines with a value beyond any sensor's range (skipped, as garbled ones)
    skipped: int = 0  # data lines before any header (layout unknown)
    reopened: int = 0  # times the port went away and came back (delivered samples again)


def undecoded_advice(stats: BoardStats, baudrate: int) -> str:
    """What to check when bytes arrive and no sample decodes from them: the line's counts, then the likeliest cause —
    values beyond their sensors' ranges (the header's units), or else the baud rate and the line format."""
    counts = (
        f"{stats.lines} line(s), {stats.garbled} garbled, {stats.out_of_range} out of range, "
        f"{stats.skipped} before a header"
    )
    if stats.out_of_range > stats.garbled + stats.skipped:
        cause = (
            "the lines decode, but their values lie beyond the sensors' ranges: do the header's units match what "
            "the board sends (e.g. accel in g, not mg)?"
        )
    else:
        cause = f"is the baud rate {baudrate} the board's, and does each line end in \\n with comma-separated fields?"
    return (
        f"bytes for {UNDECODED_WARN_S:.0f} s and no sample decoded from them ({counts}): {cause} (docs/drivers.md, HL1)"
    )


class BoardDecoder:
    """Turns HL1 lines into SampleBlocks of block_s seconds; no I/O, one thread.

    Timing and gap handling: drivers.source.StreamAssembler (stream time = sample index ÷ rate).
    A new, different header mid-stream means the board restarted: counted as a resync, and
    stream time continues after the last sample — unless the next data line's counter goes on with the
    old stream (a restarted board counts afresh): then the header was garbled, and is skipped.
    """

    def __init__(self, block_s: float | None = None, header: BoardHeader | None = None) -> None:
        if block_s is not None:  # None: chosen from the header's rate (drivers.source.default_block_s)
            check_positive("block_s", block_s)
        self.block_s = block_s
        self.stats = BoardStats()
        self._header: BoardHeader | None = None
        self._pending: BoardHeader | None = None  # a new header, until the next data line says whether it was one
        self._assembler: StreamAssembler | None = None
        self._limits: list[float] = []  # largest |value| per column, in the board's units
        if header is not None:
            self._set_header(header)

    @property
    def header(self) -> BoardHeader | None:
        return self._header

    def _set_header(self, header: BoardHeader) -> None:
        old = self._assembler
        self._header = header
        self._line = re.compile(r"\d+\s*" + rf"(?:,\s*{_NUMBER}\s*)" * header.n_values)
        self._limits = [
            MAX_ABS[kind] / UNIT_SCALE[kind][units] for kind, cols, units in header.layout for _ in range(cols)
        ]
        self._assembler = StreamAssembler(
            header.rate_hz,
            header.layout,
            self.block_s,
            wrap=header.wrap,
            time_offset=0.0 if old is None else old.end_time,
            seq0=0 if old is None else old.next_seq,
            stats=self.stats,
        )

    def count_garbled(self) -> None:
        """Count a line that was lost before it could be decoded (e.g. too long)."""
        self.stats.lines += 1
        self.stats.garbled += 1

    def feed_line(self, raw: bytes) -> list[SampleBlock]:
        """Decode one line (without its newline); return the blocks it completes."""
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            self.count_garbled()
            return []
        if not line:
            return []
        if len(raw) > MAX_LINE_BYTES:  # however it arrived: noise, never a sample
            self.count_garbled()
            return []
        if line.startswith("#"):
            return self._on_comment(line)
        self.stats.lines += 1
        if self._assembler is None:
            if self.stats.skipped == 0:
                log.warning("serial board: data before any %s header; waiting for one", HEADER_TAG)
            self.stats.skipped += 1
            return []
        if self._pending is not None:
            return self._judge_header(line)
        return self._sample(line)

    def _judge_header(self, line: str) -> list[SampleBlock]:
        """The data line after a new header: a board that restarted counts afresh, so a line that goes on with the
        old counter says the header was garbled into another valid one (a digit of its rate, say) — skipped, the
        stream unchanged. Otherwise the board restarted, and the line is its first sample."""
        assert self._assembler is not None and self._pending is not None
        header, self._pending = self._pending, None
        parsed = self._parse_sample(line)
        if parsed is not None and self._assembler.goes_on(parsed[0]):
            log.warning("serial board: a header unlike the board's, and the stream went on after it: garbled, skipped")
            self.count_garbled()
            return self._sample(line)
        return self._restart(header) + self._sample(line)

    def _sample(self, line: str) -> list[SampleBlock]:
        """One data line under the current header: its sample added, or counted as garbled or out of range."""
        assert self._assembler is not None
        parsed = self._parse_sample(line)
        if parsed is None:
            self.stats.garbled += 1
            return []
        counter, values = parsed
        if any(abs(v) > limit for v, limit in zip(values, self._limits)):
            # a sensor fault or a corrupted digit: one sample lost (its counter shows the hole), never the stream
            if self.stats.out_of_range == 0:
                log.warning(
                    "serial board: sample %d has a value beyond its sensor's range; such lines are skipped", counter
                )
            self.stats.out_of_range += 1
            return []
        return self._assembler.add(counter, np.asarray([values]))

    def _on_comment(self, line: str) -> list[SampleBlock]:
        if not line.startswith(HEADER_TAG):
            log.debug("serial board says: %s", line)
            return []
        try:
            header = parse_header(line)
        except ValueError as exc:
            if self._header is None:
                raise  # before any good header it is a configuration error: say so
            # after one, it is a line garbled on the way: the board has not changed
            log.warning("serial board: a header line that does not parse, skipped (%s)", exc)
            self.count_garbled()
            return []
        if header == self._header:
            self._pending = None  # the board's own header again: one that differed before it was garbled
            return []  # the answer to our request, or a repeat: nothing changes
        if self._header is None:
            return self._restart(header)
        self._pending = header  # a restart, or a header garbled into another valid one: the next data line says
        return []

    def _restart(self, header: BoardHeader) -> list[SampleBlock]:
        """The board (re)started with `header`: what the old one held goes out; from the second header on, how long
        the board was away is unknown, so stream time continues after the last sample (a resync)."""
        out = self.flush()
        if self._header is not None:
            self.stats.resyncs += 1
            log.warning("serial board sent a new header (restart?): stream time continues after the last sample")
        self._set_header(header)
        return out

    def _parse_sample(self, line: str) -> tuple[int, list[float]] | None:
        assert self._header is not None
        fields = line.split(",")
        if len(fields) != 1 + self._header.n_values or self._line.fullmatch(line) is None:
            return None
        try:
            counter = int(fields[0])
            values = [float(f) for f in fields[1:]]
        except ValueError:
            return None
        if counter < 0 or counter >= self._header.wrap or not all(math.isfinite(v) for v in values):
            return None
        return counter, values

    def settle(self) -> list[SampleBlock]:
        """A read timed out: StreamAssembler.settle."""
        return [] if self._assembler is None else self._assembler.settle()

    def flush(self) -> list[SampleBlock]:
        """What is held so far (if any), as blocks."""
        return [] if self._assembler is None else self._assembler.flush()


class SerialBoardSource(ThreadedSource):
    """Sample blocks from an HL1 board on a serial port, read in a background thread.

    port: device name (/dev/ttyACM0, COM3, or a pty); block_s: seconds per block (None: from the board's rate,
    drivers.source.default_block_s);
    header: an HL1 header line to assume for boards that never send one.
    Decoding counts live in `stats` (BoardStats). A port that does not open raises at once; one that goes away
    once open (unplugged, a board resetting its USB link) is reopened until it is back, every REOPEN_S, the
    samples it sent before going away delivered first.
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 921_600,
        block_s: float | None = None,
        header: str | None = None,
        queue_size: int = 256,
    ) -> None:
        super().__init__(queue_size)
        if not port:
            raise ValueError("serial port name is empty")
        if baudrate <= 0:
            raise ValueError(f"baudrate must be positive, got {baudrate}")
        self.port = port
        self.baudrate = baudrate
        self.name = f"serial:{port}"
        self._decoder = BoardDecoder(block_s, parse_header(header) if header else None)

    @property
    def stats(self) -> BoardStats:
        return self._decoder.stats

    def _produce(self, stop: threading.Event, emit: Callable[[Item], None]) -> None:
        import serial  # pyserial: imported here so the rest of drivers loads without it

        opened = gone = False
        wait = REOPEN_S[0]

        def back() -> None:
            # the port delivers samples again: only now is it back, and the next loss starts the backoff afresh (a
            # port that opens and fails its first reads — a board in a reset loop, another process on it — backs off)
            nonlocal gone, wait
            if gone:
                self.stats.reopened += 1
                log.warning("serial board %s is back; reading again", self.port)
            gone, wait = False, REOPEN_S[0]

        while not stop.is_set():
            try:
                # timeout: a read returns at least every 0.1 s so the stop flag is seen promptly.
                with serial.Serial(self.port, self.baudrate, timeout=0.1) as ser:
                    opened = True
                    self._read(ser, stop, emit, back)
            except (serial.SerialException, OSError) as exc:
                if stop.is_set():
                    break
                if not opened:
                    raise  # it never opened: a wrong port, said at once
                # unplugged, or the board reset its USB link: what it sent so far goes, then the port is reopened
                for block in self._decoder.flush():
                    emit(block)
                if not gone:
                    gone = True
                    log.warning("serial board %s went away (%s); reopening it until it is back", self.port, exc)
                stop.wait(wait)
                wait = min(2 * wait, REOPEN_S[1])
        for block in self._decoder.flush():
            emit(block)

    def _read(self, ser, stop: threading.Event, emit: Callable[[Item], None], delivering: Callable[[], None]) -> None:
        """Read lines from the open port `ser` until `stop` (SerialException when the port goes away); `delivering()`
        is called once, at the first sample decoded."""
        ser.write(HEADER_REQUEST)
        pending = b""
        discarding = False  # inside an over-long line: drop bytes up to the next newline
        undecoded_since: float | None = None  # when bytes began arriving with no sample decoded from them
        warned = False
        first = True
        while not stop.is_set():
            chunk = ser.read(max(1, ser.in_waiting))
            if not chunk:  # 0.1 s of silence: a sample held to see what follows it is judged as it came
                for block in self._decoder.settle():
                    emit(block)
                continue
            samples = self.stats.samples
            pending += chunk
            if discarding:
                end = pending.find(b"\n")
                if end < 0:
                    pending = b""
                else:
                    pending, discarding = pending[end + 1 :], False
            if not discarding:
                *lines, pending = pending.split(b"\n")
                for raw in lines:
                    for block in self._decoder.feed_line(raw):
                        emit(block)
                if len(pending) > MAX_LINE_BYTES:
                    # No newline in sight: noise on the line. Count it once and resynchronise on the next newline.
                    self._decoder.count_garbled()
                    pending, discarding = b"", True
            if self.stats.samples > samples:
                undecoded_since = None
                if first:  # a sample decoded: the board delivers (a boot byte from a board in a reset loop does not)
                    first = False
                    delivering()
            elif undecoded_since is None:
                undecoded_since = time.monotonic()
            elif not warned and time.monotonic() - undecoded_since > UNDECODED_WARN_S:
                warned = True
                log.warning("serial board %s: %s", self.port, undecoded_advice(self.stats, self.baudrate))
