"""What every sensor source is, and the pieces sources share.

- `SensorSource`: an async iterator of `SampleBlock | TapBlock | Frame` with a `name` and `aclose()`.
- `blocks_from_arrays`: slice aligned channel arrays into consecutive blocks of `block_s` seconds.
- `paced`: emit items at wall-clock pace (monotonic clock, no drift).
- `ThreadedSource`: a base for sources whose I/O blocks (pyserial, pyusb): a reader thread
  hands items to the event loop through a bounded queue.
- `StreamAssembler`: device rows stamped with a sample counter → blocks, with gap detection.
"""

from __future__ import annotations

import asyncio
import logging
import math
import numbers
import threading
import time
from collections.abc import AsyncIterable, AsyncIterator, Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from drivers.blocks import MAX_BLOCK_SAMPLES, ChannelBlock, Frame, SampleBlock, TapBlock, validate_channel
from texture_library.channels import CHANNEL_COLUMNS, UNIT_SCALE, check_channel, check_rate

log = logging.getLogger(__name__)

Item = SampleBlock | TapBlock | Frame

#: seconds of stream per block that the sources and `hapticlink robot` send unless told otherwise: 250 ms, two
#: blocks per 500 ms window. The service's event loop pays per block (a WebSocket message, its acknowledgement,
#: decoding, admission): 250 ms blocks cost the service about a tenth less CPU per robot-second than 100 ms ones,
#: and a window still completes with the block that ends where it ends (a divisor of the 500 ms hop), so latency
#: does not pay for it (docs/drivers.md, "Block size").
DEFAULT_BLOCK_S = 0.25
#: ... except where a channel runs slower than MODEL_RATE_HZ: resampled up, it holds its last samples back until
#: the next block, so each window completes one block late; short blocks keep that delay short
SLOW_CHANNEL_BLOCK_S = 0.05
#: the rate the project's models resample every channel to, Hz (models.tactile.config.TactileConfig.rate_hz)
MODEL_RATE_HZ = 1000.0


def default_block_s(rates_hz: Iterable[float]) -> float:
    """The block size, s, for a stream whose channels run at `rates_hz` (Hz) when none is asked for:
    DEFAULT_BLOCK_S, or SLOW_CHANNEL_BLOCK_S when one of them is slower than MODEL_RATE_HZ."""
    rates = [float(r) for r in rates_hz]
    if not rates:
        raise ValueError("default_block_s needs the rate of at least one channel")
    return SLOW_CHANNEL_BLOCK_S if min(rates) < MODEL_RATE_HZ else DEFAULT_BLOCK_S


@runtime_checkable
class SensorSource(Protocol):
    """A stream of sample blocks and camera frames, in time order.

    Iterate it once (`async for item in source`); `aclose()` stops it and frees its device,
    and is safe to call more than once or before iterating.
    """

    name: str

    def __aiter__(self) -> AsyncIterator[Item]: ...

    async def aclose(self) -> None: ...


def check_positive(label: str, value: object, what: str = "number of seconds") -> None:
    """ValueError naming `label` unless `value` is a finite real number > 0 (`what` says what it counts)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{label} must be a positive {what}, got {value!r}")
    if not (math.isfinite(value) and float(value) > 0):
        raise ValueError(f"{label} must be a positive {what}, got {value!r}")


# ---- slicing ------------------------------------------------------------------------------------
def _boundary(k: int, block_s: float, rate_hz: float) -> int:
    """Index of the first sample of block k: sample i (at i / rate s) belongs to the block whose
    span [k·block_s, (k+1)·block_s) holds it, rounded to the nearest sample so that a block's first
    sample is never more than half a sample period away from its t0."""
    return int(math.floor(k * block_s * rate_hz + 0.5 + 1e-9))


def blocks_from_arrays(
    channels: Mapping[str, tuple[np.ndarray, float, str]],
    block_s: float | None,
    t0: float = 0.0,
    seq0: int = 0,
) -> Iterator[SampleBlock]:
    """Cut aligned channel arrays into consecutive SampleBlocks of `block_s` seconds (None: default_block_s of
    the channels' rates).

    channels: {kind: (samples (n,) or (n, k), rate Hz, units)}, all starting at t0 (s).
    Block k spans [t0 + k·block_s, t0 + (k+1)·block_s); each channel is cut at its own rate
    at cumulative sample boundaries (round(k·block_s·rate)), so remainders carry over and no
    drift accumulates. Concatenating every block's channel gives back the array (as float32,
    the wire's dtype). The last block takes what is left; a channel with no sample in a block
    is left out of that block, and a block with no samples at all is skipped (seq stays
    consecutive). Samples are validated once (texture_library.channels.check_channel).
    """
    if block_s is not None:
        check_positive("block_s", block_s)
    if not channels:
        raise ValueError("blocks_from_arrays needs at least one channel")
    checked: dict[str, tuple[np.ndarray, float, str]] = {}
    for kind, spec in channels.items():
        if not (isinstance(spec, tuple) and len(spec) == 3):
            raise ValueError(f"{kind}: expected (samples, rate_hz, units), got {type(spec).__name__}")
        checked[kind] = check_channel(kind, spec[0], spec[1], spec[2], dtype=np.float32)
    if block_s is None:
        block_s = default_block_s(rate for _, rate, _ in checked.values())
    for kind, (_, rate, _) in checked.items():
        if math.ceil(block_s * rate) + 1 > MAX_BLOCK_SAMPLES:
            raise ValueError(
                f"{kind}: block_s={block_s} s at {rate:g} Hz exceeds {MAX_BLOCK_SAMPLES} samples per block"
            )
    # Enough blocks that every channel's last sample falls in one.
    n_blocks = 0
    for arr, rate, _ in checked.values():
        k = max(1, math.ceil(arr.shape[0] / (block_s * rate)) - 1)
        while _boundary(k, block_s, rate) < arr.shape[0]:
            k += 1
        n_blocks = max(n_blocks, k)
    seq = seq0
    for k in range(n_blocks):
        last = k == n_blocks - 1
        out: dict[str, ChannelBlock] = {}
        for kind, (arr, rate, units) in checked.items():
            lo = min(_boundary(k, block_s, rate), arr.shape[0])
            hi = arr.shape[0] if last else min(_boundary(k + 1, block_s, rate), arr.shape[0])
            if hi > lo:
                out[kind] = ChannelBlock(arr[lo:hi].copy(), rate, units)
        if out:
            yield SampleBlock(t0=t0 + k * block_s, channels=out, seq=seq)
            seq += 1


def block_end(item: Item) -> float:
    """Time (s, sender's clock) at which an item is complete: a block's last sample period ends,
    a frame is taken, a tap block is sent (at its t0: the taps before it were the procedure)."""
    if isinstance(item, Frame):
        return item.t
    if isinstance(item, TapBlock):
        return item.t0
    return item.t0 + max(c.duration_s for c in item.channels.values())


def _item_start(item: Item) -> float:
    return item.t if isinstance(item, Frame) else item.t0


# ---- pacing -------------------------------------------------------------------------------------
async def paced(
    items: Iterable[Item] | AsyncIterable[Item],
    realtime: bool,
    speed: float = 1.0,
) -> AsyncIterator[Item]:
    """Yield items at wall-clock pace: a block when its span has ended, a frame at its time.

    Each deadline is computed from the first item's time and one monotonic start instant,
    so sleeping late never accumulates drift; a slow consumer gets the overdue items at
    once and is back on schedule. realtime=False yields as fast as the consumer takes them
    (still yielding to the event loop between items). speed > 1 plays faster than real time.
    """
    check_positive("speed", speed, "finite factor")
    origin: float | None = None
    wall0 = 0.0
    async for item in _aiter(items):
        if realtime:
            if origin is None:
                origin, wall0 = _item_start(item), _monotonic()
            delay = wall0 + (block_end(item) - origin) / speed - _monotonic()
            await _sleep(max(0.0, delay))
        else:
            await _sleep(0)
        yield item


# The clock paced() reads and the sleep it awaits (module names, so a test can substitute a fake clock).
_monotonic = time.monotonic
_sleep = asyncio.sleep


async def _aiter(items: Iterable[Item] | AsyncIterable[Item]) -> AsyncIterator[Item]:
    if isinstance(items, AsyncIterable):
        async for item in items:
            yield item
    else:
        for item in items:
            yield item


# ---- blocking I/O in a thread -------------------------------------------------------------------
_END = object()


class ThreadedSource:
    """Base for sources whose device I/O blocks: `_produce` runs in a daemon thread.

    Subclasses implement `_produce(stop, emit)`: open the device, read until `stop` is set
    (reads must time out every ~0.1 s so the thread notices), call `emit(item)` for each block,
    and close the device before returning. Items reach the event loop through a bounded
    asyncio queue; when the consumer falls `queue_size` items behind, the oldest is dropped and
    counted in `overruns` (the reader never blocks, so the device's own buffer never overflows
    unnoticed). An exception in `_produce` is raised from the iterator. `finish()` stops reading the
    device but lets what it already sent (the partial block `_produce` flushes last) come out before
    the iteration ends; `aclose()` (or leaving the iteration) drops it.
    """

    name: str = "threaded"

    def __init__(self, queue_size: int = 256) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be ≥ 1, got {queue_size}")
        self._queue_size = queue_size
        self._stop = threading.Event()  # the reader thread stops reading the device
        self._closed = threading.Event()  # nobody takes items any more: emit drops them
        self._thread: threading.Thread | None = None
        self._started = False
        self.overruns = 0

    def _produce(self, stop: threading.Event, emit: Callable[[Item], None]) -> None:
        raise NotImplementedError

    def __aiter__(self) -> AsyncIterator[Item]:
        if self._started:
            raise RuntimeError(f"{self.name}: a source can be iterated only once")
        self._started = True
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[Item]:
        loop = asyncio.get_running_loop()
        # Bounded by hand: data items beyond queue_size push out the oldest; the end marker always gets in.
        queue: asyncio.Queue = asyncio.Queue()

        def put(item: object) -> None:  # runs on the event loop
            is_data = item is not _END and not isinstance(item, BaseException)
            if is_data and queue.qsize() >= self._queue_size:
                queue.get_nowait()  # data only: the end marker is always the last thing put
                self.overruns += 1
                log.warning("%s: consumer is %d items behind; dropped the oldest block", self.name, self._queue_size)
            queue.put_nowait(item)

        def emit(item: Item) -> None:  # runs in the reader thread
            if not self._closed.is_set():
                loop.call_soon_threadsafe(put, item)

        def run() -> None:
            end: object = _END
            try:
                self._produce(self._stop, emit)
            except BaseException as exc:  # noqa: BLE001 - handed to the consumer, who decides
                end = exc
            try:
                loop.call_soon_threadsafe(put, end)
            except RuntimeError:
                pass  # the loop is closed: nobody is listening any more

        self._thread = threading.Thread(target=run, name=f"hapticlink-{self.name}", daemon=True)
        self._thread.start()
        try:
            while True:
                item = await queue.get()
                if item is _END:
                    return
                if isinstance(item, BaseException):
                    raise item
                yield item
        finally:
            self._stop.set()
            self._closed.set()

    def finish(self) -> None:
        """Stop reading the device; what it already sent still comes out, then the iteration ends."""
        self._stop.set()

    async def aclose(self) -> None:
        """Stop the reader thread and wait (off the event loop) for it to close the device."""
        self._stop.set()
        self._closed.set()
        thread = self._thread
        if thread is not None and thread.is_alive():
            await asyncio.to_thread(thread.join, 5.0)
            if thread.is_alive():
                log.error("%s: reader thread did not stop within 5 s", self.name)


# ---- counter-stamped samples → blocks -----------------------------------------------------------
#: column layout of a device's sample rows: (channel kind, columns, units), in column order
Layout = tuple[tuple[str, int, str], ...]


def device_rate(rate: object, where: str) -> float:
    """A device's declared sample rate, checked against texture_library.channels' limits; ValueError says `where`."""
    return check_rate(rate, where)


def layout_channel(
    layout: Sequence[tuple[str, int, str]], kind: object, columns: object, units: object, where: str
) -> tuple[str, int, str]:
    """One (kind, columns, units) entry a device declares, checked against texture_library.channels (kinds,
    units, column counts) and against the entries before it; ValueError says `where`."""
    if kind not in UNIT_SCALE:
        raise ValueError(f"{where}: channel kind must be one of {list(UNIT_SCALE)}, got {kind!r}")
    if isinstance(columns, bool) or columns not in CHANNEL_COLUMNS[kind]:
        raise ValueError(f"{where}: {kind} has {list(CHANNEL_COLUMNS[kind])} column(s), got {columns!r}")
    if units not in UNIT_SCALE[kind]:
        raise ValueError(f"{where}: {kind} units must be one of {list(UNIT_SCALE[kind])}, got {units!r}")
    if any(k == kind for k, _, _ in layout):
        raise ValueError(f"{where}: channel {kind!r} appears twice")
    return kind, int(columns), units


@dataclass
class StreamStats:
    """What a device stream lost or repaired (counts since the stream started)."""

    samples: int = 0  # samples put into blocks
    blocks: int = 0
    gaps: int = 0  # sample counter jumped forward: data lost on the way
    missing_samples: int = 0  # samples those jumps skipped
    resyncs: int = 0  # counter went backwards or the device restarted: time continues contiguously
    glitches: int = 0  # one packet's counter out of sequence, the sequence going on after it: not a gap (see add)


def _signed(difference: int, wrap: int) -> int:
    """A counter difference mod `wrap` as the signed step it most likely was: in [−wrap/2, wrap/2)."""
    return (difference + wrap // 2) % wrap - wrap // 2


class StreamAssembler:
    """Rows of samples stamped with a device sample counter → SampleBlocks of block_s seconds (None:
    default_block_s of rate_hz).

    Stream time = sample index ÷ rate_hz + time_offset (s); index 0 is the first sample seen.
    Blocks lie on a grid of round(block_s·rate) samples. A forward counter jump (mod `wrap`,
    less than wrap/2) is lost data: the current block ends early, the index skips the missing
    samples, and the next block's t0 is their true time. A backward jump (a counter reset) cannot be
    timed: it is counted as a resync and time continues after the last sample.

    A packet whose counter breaks the sequence is held until the next one says which it was: if the
    next continues *it*, the jump was real (a gap or a reset, as above); if the next continues the old
    sequence, that one counter was the glitch — a corrupted digit (its rows are kept in the slot the
    sequence gave them) or a repeated or swapped packet (dropped) — counted in `glitches`, and time is
    not shifted by it. When the next continues neither exactly (a packet lost right after the odd one),
    it sides with the sequence it lies near (a few packets or a block), the one it lies nearer ahead of
    when near both — a held counter just behind the expected one is garbled, a device never steps back a
    few samples; a held packet that repeats the one before it is dropped; when the next is near neither
    (two garbled counters in a row) the held packet keeps its slot and the next is judged by the one
    after it. The first samples after a real jump thus arrive one packet late. Two counters garbled
    alike, so that the second continues the first, still read as a real jump: that takes a third.
    """

    def __init__(
        self,
        rate_hz: float,
        layout: Layout,
        block_s: float | None,
        *,
        wrap: int = 2**32,
        time_offset: float = 0.0,
        seq0: int = 0,
        stats: StreamStats | None = None,
    ) -> None:
        if block_s is None:
            block_s = default_block_s([rate_hz])
        check_positive("block_s", block_s)
        if not layout:
            raise ValueError("a stream layout needs at least one channel")
        self.rate_hz = rate_hz
        self.layout = layout
        self.columns = sum(cols for _, cols, _ in layout)
        self.per_block = max(1, round(block_s * rate_hz))
        if self.per_block > MAX_BLOCK_SAMPLES:
            raise ValueError(f"block_s={block_s} s at {rate_hz:g} Hz exceeds {MAX_BLOCK_SAMPLES} samples per block")
        self.wrap = wrap
        self.time_offset = time_offset
        self.next_seq = seq0
        self.stats = stats if stats is not None else StreamStats()
        self.next_index = 0  # stream index of the next sample
        self._expected: int | None = None  # device counter expected next
        self._rows: list[np.ndarray] = []
        self._held = 0  # rows held in _rows
        self._block_start = 0
        self._suspect: tuple[int, np.ndarray] | None = None  # a packet that broke the sequence, until the next one
        self._previous: int | None = None  # device counter of the last packet taken

    @property
    def end_time(self) -> float:
        """Stream time just after the last sample seen, s."""
        return self.time_offset + self.next_index / self.rate_hz

    def add(self, counter: int, rows: np.ndarray) -> list[SampleBlock]:
        """Add rows (n, columns) whose first sample carries device counter `counter`; return finished blocks."""
        rows = np.asarray(rows, dtype=np.float64)
        if rows.ndim != 2 or rows.shape[1] != self.columns:
            raise ValueError(f"rows must have shape (n, {self.columns}), got {rows.shape}")
        if self._suspect is not None:
            (held, held_rows), self._suspect = self._suspect, None
            return self._judge(held, held_rows, counter, rows)
        if self._expected is not None and counter != self._expected:
            self._suspect = (counter, rows)
            return []
        return self._take(counter, rows)

    def goes_on(self, counter: int) -> bool:
        """Whether a packet's counter goes on with this stream: the one expected next, or at most a block ahead of it
        (lost packets). False before any packet."""
        if self._expected is None:
            return False
        return 0 <= _signed(counter - self._expected, self.wrap) <= self.per_block

    def _judge(self, held: int, held_rows: np.ndarray, counter: int, rows: np.ndarray) -> list[SampleBlock]:
        """The held packet (its counter broke the sequence), judged by the next one (counter, rows)."""
        assert self._expected is not None
        expected, n, wrap = self._expected, held_rows.shape[0], self.wrap
        side = self._side(held, n, counter)
        if side == "held":  # the jump was real
            return self._take(held, held_rows) + self.add(counter, rows)
        if held == self._previous:  # a repeat of the packet before it (and the one after that lost): dropped
            return self._glitch(held, counter, None) + self.add(counter, rows)
        if side == "neither":  # two garbled counters in a row: the held one keeps its slot, the next is judged next
            return self._glitch(held, counter, held_rows) + self.add(counter, rows)
        if (counter - expected) % wrap < n:  # the old sequence goes on; a repeat or a swap (no room for it): dropped
            return self._glitch(held, counter, None) + self._take(counter, rows)
        return self._glitch(held, counter, held_rows) + self._take(counter, rows)  # its counter garbled

    def _side(self, held: int, n: int, counter: int) -> str:
        """Which sequence the next counter goes on: "old" (the held counter was garbled), "held" (its jump was real)
        or "neither" (the next is garbled too). Near: within a few packets or a block, the most a lost packet or a
        small real gap moves it."""
        assert self._expected is not None
        expected, wrap = self._expected, self.wrap
        continued = (held + n) % wrap
        if counter != expected and counter in (continued, held):  # it continues, or repeats, the held packet
            return "held"
        if counter in (expected, (expected + n) % wrap):  # it continues the old sequence, or one packet after it
            return "old"
        near = max(4 * n, self.per_block)
        near_old = abs(_signed(counter - expected, wrap)) <= near
        near_held = abs(_signed(counter - continued, wrap)) <= near
        if near_old != near_held:
            return "old" if near_old else "held"
        if not near_old:
            return "neither"
        # near both (a small jump): the sequence it lies nearer ahead of; a device never steps back a few samples,
        # so a held counter just behind the expected one was garbled
        ahead = _signed(held - expected, wrap) > 0
        return "held" if ahead and (counter - continued) % wrap <= (counter - expected) % wrap else "old"

    def _glitch(self, held: int, counter: int, rows: np.ndarray | None) -> list[SampleBlock]:
        """Count and say one packet out of sequence; its rows (None: dropped) go in the slot the sequence gives."""
        assert self._expected is not None
        self.stats.glitches += 1
        log.warning(
            "device counter %d out of sequence between %d and %d: one garbled or misplaced packet; time goes on "
            "unshifted",
            held,
            (self._expected - 1) % self.wrap,
            counter,
        )
        return [] if rows is None else self._take(self._expected, rows)

    def _take(self, counter: int, rows: np.ndarray) -> list[SampleBlock]:
        """Rows whose first sample carries `counter`, judged: a jump from the expected counter is a gap or a resync."""
        out: list[SampleBlock] = []
        if self._expected is not None and counter != self._expected:
            jump = (counter - self._expected) % self.wrap
            out += self._close_block()
            if jump < self.wrap // 2:
                self.stats.gaps += 1
                self.stats.missing_samples += jump
                log.warning("%d sample(s) lost before device counter %d", jump, counter)
                self.next_index += jump
            else:
                self.stats.resyncs += 1
                log.warning(
                    "device counter went back to %d (expected %d): time continues after the last sample",
                    counter,
                    self._expected,
                )
        self._expected = (counter + rows.shape[0]) % self.wrap
        self._previous = counter
        i = 0
        while i < rows.shape[0]:
            if self._held == 0:
                self._block_start = self.next_index
            take = min(rows.shape[0] - i, self.per_block - self.next_index % self.per_block)
            self._rows.append(rows[i : i + take])
            self._held += take
            self.next_index += take
            self.stats.samples += take
            i += take
            if self.next_index % self.per_block == 0:
                out += self._close_block()
        return out

    def settle(self) -> list[SampleBlock]:
        """The device went quiet (a read timed out): a packet held for judgement is taken as it came, a real jump,
        since nothing follows to say otherwise; the blocks it completes."""
        if self._suspect is None:
            return []
        (held, held_rows), self._suspect = self._suspect, None
        return self._take(held, held_rows)

    def flush(self) -> list[SampleBlock]:
        """What is held so far, as blocks: a packet held for judgement (taken as it came), then the partial block."""
        return self.settle() + self._close_block()

    def _close_block(self) -> list[SampleBlock]:
        """The partial block held so far, if any."""
        if not self._held:
            return []
        rows = np.concatenate(self._rows)
        self._rows, self._held = [], 0
        channels: dict[str, ChannelBlock] = {}
        col = 0
        for kind, cols, units in self.layout:
            data = rows[:, col] if cols == 1 else rows[:, col : col + cols]
            channels[kind] = validate_channel(kind, data, self.rate_hz, units)
            col += cols
        block = SampleBlock(self.time_offset + self._block_start / self.rate_hz, channels, self.next_seq)
        self.next_seq += 1
        self.stats.blocks += 1
        return [block]
