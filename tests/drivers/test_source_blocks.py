"""blocks_from_arrays, paced, ThreadedSource and StreamAssembler."""

from __future__ import annotations

import asyncio
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.blocks import Frame, SampleBlock
from drivers.source import (
    DEFAULT_BLOCK_S,
    SLOW_CHANNEL_BLOCK_S,
    SensorSource,
    StreamAssembler,
    ThreadedSource,
    blocks_from_arrays,
    default_block_s,
    paced,
)

RATES = st.sampled_from([10.0, 100.0, 333.3, 500.0, 1000.0, 1234.5, 2500.0, 10_000.0])


@settings(max_examples=150, deadline=None)
@given(
    rates=st.lists(RATES, min_size=1, max_size=3),
    duration_s=st.floats(0.01, 2.0),
    block_s=st.floats(0.003, 0.5),
    t0=st.floats(-10.0, 1000.0),
    seq0=st.integers(0, 10**6),
    seed=st.integers(0, 2**16),
)
def test_concatenated_blocks_give_back_the_arrays(rates, duration_s, block_s, t0, seq0, seed):
    rng = np.random.default_rng(seed)
    kinds = ["accel", "force", "speed"][: len(rates)]
    channels = {}
    for kind, rate in zip(kinds, rates):
        n = max(1, int(duration_s * rate * rng.uniform(0.9, 1.1)))  # lengths need not agree exactly
        shape = (n, 3) if kind == "accel" else (n,)
        channels[kind] = (
            rng.standard_normal(shape).astype(np.float32),
            rate,
            "m/s^2" if kind == "accel" else "N" if kind == "force" else "mm/s",
        )
    blocks = list(blocks_from_arrays(channels, block_s, t0=t0, seq0=seq0))

    assert [b.seq for b in blocks] == list(range(seq0, seq0 + len(blocks)))
    assert all(b.channels for b in blocks)
    for kind, (data, rate, units) in channels.items():
        parts = [b.channels[kind] for b in blocks if kind in b.channels]
        np.testing.assert_array_equal(np.concatenate([p.data for p in parts]), data)
        assert {p.units for p in parts} == {units} and {p.rate_hz for p in parts} == {rate}
        # each block's first sample lies within half a sample period of the block's t0 (remainders carried, no drift)
        start = 0
        for b in blocks:
            if kind in b.channels:
                assert abs(start / rate - (b.t0 - t0)) <= 0.5 / rate + 1e-6
                assert b.channels[kind].data.shape[0] <= int(np.ceil(block_s * rate)) + 1 or b is blocks[-1]
                start += b.channels[kind].data.shape[0]
    t0s = [b.t0 for b in blocks]
    assert t0s == sorted(t0s)


def test_blocks_at_1khz_are_exactly_20_samples():
    data = np.arange(1000, dtype=np.float32)
    blocks = list(blocks_from_arrays({"speed": (data, 1000.0, "mm/s")}, 0.02, t0=5.0))
    assert [b.channels["speed"].data.shape[0] for b in blocks] == [20] * 50
    assert blocks[3].t0 == pytest.approx(5.06) and blocks[3].channels["speed"].data[0] == 60


def test_the_default_block_is_long_unless_a_channel_is_slower_than_the_models_rate():
    """A channel below 1 kHz is resampled up and completes each window a block late: such a stream gets short
    blocks; a stream at 1 kHz or above gets 250 ms ones (a window completes with its block whatever the size)."""
    assert DEFAULT_BLOCK_S == 0.25 and SLOW_CHANNEL_BLOCK_S == 0.05
    assert default_block_s([1000.0, 1000.0]) == 0.25
    assert default_block_s([10_000.0, 1000.0]) == 0.25
    assert default_block_s([1000.0, 999.0]) == 0.05
    assert default_block_s([250.0]) == 0.05
    with pytest.raises(ValueError, match="at least one channel"):
        default_block_s([])


def test_blocks_from_arrays_chooses_the_block_from_the_channels_rates_when_not_told():
    fast = {"speed": (np.arange(1000, dtype=np.float32), 1000.0, "mm/s")}
    assert [b.t0 for b in blocks_from_arrays(fast, None)] == [0.0, 0.25, 0.5, 0.75]
    slow = {**fast, "force": (np.zeros(250, np.float32), 250.0, "N")}
    blocks = list(blocks_from_arrays(slow, None))
    assert len(blocks) == 20 and blocks[1].t0 == pytest.approx(0.05)
    assert blocks[1].channels["speed"].data.shape[0] == 50 and blocks[1].channels["force"].data.shape[0] == 12
    assert StreamAssembler(250.0, (("force", 1, "N"),), None).per_block == 12  # round(0.05 s × 250 Hz)
    assert StreamAssembler(1000.0, (("force", 1, "N"),), None).per_block == 250


def test_blocks_from_arrays_names_bad_arguments():
    good = (np.zeros(10, np.float32), 1000.0, "N")
    with pytest.raises(ValueError, match="block_s"):
        list(blocks_from_arrays({"force": good}, 0.0))
    with pytest.raises(ValueError, match="at least one channel"):
        list(blocks_from_arrays({}, 0.02))
    with pytest.raises(ValueError, match="units"):
        list(blocks_from_arrays({"force": (good[0], 1000.0, "lbf")}, 0.02))
    with pytest.raises(ValueError, match="shape"):
        list(blocks_from_arrays({"accel": (np.zeros((10, 2)), 1000.0, "g")}, 0.02))
    with pytest.raises(ValueError, match="samples per block"):
        list(blocks_from_arrays({"force": (np.zeros(10), 100_000.0, "N")}, 2.0))


class FakeClock:
    """A monotonic clock that advances only when paced sleeps (or the consumer is slow)."""

    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def monotonic(self) -> float:
        return self.now

    async def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += max(0.0, seconds)


def _block(t0: float, n: int = 20) -> SampleBlock:
    from drivers.blocks import ChannelBlock

    return SampleBlock(t0, {"speed": ChannelBlock(np.zeros(n, np.float32), 1000.0, "mm/s")})


def test_paced_follows_an_absolute_schedule_without_drift(monkeypatch):
    clock = FakeClock()
    monkeypatch.setattr("drivers.source._monotonic", clock.monotonic)
    monkeypatch.setattr("drivers.source._sleep", clock.sleep)
    items = [Frame(0.0, b"png"), *[_block(0.02 * k) for k in range(10)]]

    async def consume():
        emitted = []
        async for _ in paced(items, realtime=True, speed=2.0):
            emitted.append(clock.now - 100.0)
            if len(emitted) == 4:
                clock.now += 0.05  # the consumer is late once: the schedule must not shift
        return emitted

    emitted = asyncio.run(consume())
    # block k completes at 0.02·(k+1) s of stream time; at speed 2 that is 0.01·(k+1) s of wall time
    expected = [0.0] + [0.01 * (k + 1) for k in range(10)]
    for got, want in zip(emitted, expected):
        assert got >= want - 1e-12  # never early
    late_from = 4
    assert emitted[late_from] == pytest.approx(0.08)  # caught up at once after the late consumer
    assert emitted[-1] == pytest.approx(0.1), "no drift: the last block is on its original schedule"


def test_paced_without_realtime_never_sleeps_a_positive_time(monkeypatch):
    clock = FakeClock()
    monkeypatch.setattr("drivers.source._sleep", clock.sleep)

    async def consume():
        return [i async for i in paced([_block(0.02 * k) for k in range(5)], realtime=False)]

    assert len(asyncio.run(consume())) == 5 and set(clock.sleeps) == {0}
    with pytest.raises(ValueError, match="speed"):
        asyncio.run(consume_with(paced([], True, speed=0.0)))


async def consume_with(agen):
    return [i async for i in agen]


class BurstSource(ThreadedSource):
    """Emits n items at once from its thread, then signals and waits to be stopped (or fails)."""

    name = "burst"

    def __init__(self, n: int, queue_size: int, fail: bool = False) -> None:
        super().__init__(queue_size)
        self.n, self.fail = n, fail
        self.emitted = threading.Event()
        self.closed_device = threading.Event()

    def _produce(self, stop, emit):
        try:
            for k in range(self.n):
                emit(_block(0.02 * k))
            self.emitted.set()
            if self.fail:
                raise OSError("device unplugged")
        finally:
            self.closed_device.set()


def test_threaded_source_bounds_its_queue_drops_oldest_and_ends():
    src = BurstSource(10, queue_size=3)
    assert isinstance(src, SensorSource)

    async def consume():
        it = aiter(src)
        first = await anext(it)  # starts the thread; the first item may already be through
        await asyncio.to_thread(src.emitted.wait, 5)
        rest = [b async for b in it]
        await src.aclose()
        return [first, *rest]

    items = asyncio.run(consume())
    t0s = [round(b.t0 / 0.02) for b in items]
    assert t0s[-3:] == [7, 8, 9], "the newest items survive"
    assert src.overruns == 10 - len(items)
    assert src.closed_device.is_set()


def test_threaded_source_raises_the_thread_error():
    src = BurstSource(2, queue_size=8, fail=True)

    async def consume():
        return [b async for b in src]

    with pytest.raises(OSError, match="unplugged"):
        asyncio.run(consume())


LAYOUT = (("accel", 3, "g"), ("force", 1, "N"))


def _rows(counters):
    # the counter in every column: samples within the bounds from physics up to counter 100 (2·100 N)
    return np.array([[c, c + 0.5, -c, 2 * c] for c in counters], float)


def test_assembler_splits_on_the_grid_and_at_gaps_with_true_times():
    asm = StreamAssembler(1000.0, LAYOUT, 0.01)  # 10 samples per block
    out = asm.add(0, _rows(range(25)))  # counters 0..24 in one packet
    out += asm.add(28, _rows(range(28, 40)))  # 25, 26, 27 lost
    out += asm.flush()
    assert [(round(b.t0 * 1000), b.channels["force"].data.shape[0]) for b in out] == [
        (0, 10),
        (10, 10),
        (20, 5),
        (28, 2),
        (30, 10),
    ]
    assert out[3].channels["accel"].data[0].tolist() == [28, 28.5, -28]
    assert asm.stats.gaps == 1 and asm.stats.missing_samples == 3 and asm.stats.samples == 37
    assert [b.seq for b in out] == [0, 1, 2, 3, 4]


def test_assembler_counts_across_the_counter_wrap_and_resyncs_backwards():
    asm = StreamAssembler(100.0, LAYOUT, 0.1, wrap=256)
    out = asm.add(250, _rows(range(6)))  # 250..255
    out += asm.add(0, _rows(range(4)))  # wrapped: contiguous, no gap
    assert asm.stats.gaps == 0
    out += asm.add(10, _rows(range(2)))  # 4..9 lost across nothing but a jump of 6: judged at the next packet
    out += asm.add(12, _rows(range(2)))  # which continues it: the jump was real
    assert asm.stats.gaps == 1 and asm.stats.missing_samples == 6
    out += asm.add(3, _rows(range(2)))  # backwards: a restart
    out += asm.add(5, _rows(range(2)))
    out += asm.flush()
    assert asm.stats.resyncs == 1
    assert out[-1].t0 == pytest.approx((10 + 6 + 4) / 100.0), "after a resync time continues after the last sample"
    assert asm.stats.glitches == 0


def _counters(blocks, rate_hz: float = 1000.0) -> list[tuple[int, list[int]]]:
    """(block start in samples, the counters its rows carry) of each block; _rows puts the counter in column 0."""
    return [(round(b.t0 * rate_hz), b.channels["accel"].data[:, 0].astype(int).tolist()) for b in blocks]


@pytest.mark.parametrize(
    "sequence, kept, glitches",
    [
        # a digit of one counter corrupted on the way: its sample stays where the sequence puts it
        ([*range(0, 12), 4_000_012, *range(13, 20)], list(range(20)), 1),
        # one line sent twice: the repeat is dropped
        ([*range(0, 12), 11, *range(12, 20)], list(range(20)), 1),
        # two lines swapped: the early one is dropped, its place shows as a one-sample gap
        ([*range(0, 12), 13, 12, *range(14, 20)], [c for c in range(20) if c != 13], 1),
        # a real gap is still one
        ([*range(0, 12), *range(15, 20)], [*range(0, 12), *range(15, 20)], 0),
        # a corrupted counter, and the line after it lost: the next counter is nearer the old sequence
        ([*range(0, 12), 4_000_012, *range(14, 20)], [c for c in range(20) if c != 13], 1),
        # a real gap, and the line after it lost: the next counter is nearer the jump's own sequence
        ([*range(0, 12), 90, *range(92, 100)], [*range(0, 12), 90, *range(92, 100)], 0),
        # two corrupted counters in a row: each keeps its slot (the second was judged as a jump of 5 million)
        ([*range(0, 12), 4_000_012, 5_000_013, *range(14, 20)], list(range(20)), 2),
        # a real gap, then its first line repeated: the jump stands (the line went into the slot before the gap)
        ([*range(0, 12), 90, 90, *range(91, 96)], [*range(0, 12), *range(90, 96)], 1),
        # a real gap, then two lines swapped: the early one is dropped, nothing lands before the gap
        ([*range(0, 12), 91, 90, *range(92, 96)], [*range(0, 12), 91, *range(92, 96)], 1),
        # a line repeated and the one after it lost: the repeat is dropped (every later sample was one late)
        ([*range(0, 12), 11, *range(13, 20)], [c for c in range(20) if c != 12], 1),
        # a counter garbled to just behind (9 for 12), and the line after it lost: it keeps its slot
        ([*range(0, 12), (9, 12), *range(14, 20)], [c for c in range(20) if c != 13], 1),
    ],
)
def test_one_counter_out_of_sequence_never_shifts_time(sequence, kept, glitches):
    """A corrupted counter (4 000 012 for 12) used to shift every later block by 4 000 s: a 'gap' of 4 million
    samples, then a 'resync' after it; a repeated line put every later sample one late. A line is its counter, or
    (counter, the sample it really is) where the counter was garbled into another number below 1000."""
    asm = StreamAssembler(1000.0, LAYOUT, 0.005)  # 5 samples per block
    out = []
    for line in sequence:
        c, true = line if isinstance(line, tuple) else (line, line % 1000)
        out += asm.add(c, _rows([true]))
    out += asm.flush()
    got = [c for _, counters in _counters(out) for c in counters]
    assert got == [c % 1000 for c in kept]
    # every block starts at its first sample's true time: sample k at k ms
    for start, counters in _counters(out):
        assert start == counters[0], (start, counters)
    assert asm.stats.glitches == glitches and asm.stats.resyncs == 0


def test_one_frame_size_check_for_the_robot_and_the_service():
    from drivers.blocks import MAX_FRAME_PIXELS, check_frame_pixels

    assert check_frame_pixels(4096, 4096) == MAX_FRAME_PIXELS  # the largest taken
    assert check_frame_pixels(1, 1) == 1
    with pytest.raises(
        ValueError, match=r"^big.png: 4097×4096 pixels; the service decodes at most 16777216 \(4096×4096\)$"
    ):
        check_frame_pixels(4097, 4096, "big.png")
    with pytest.raises(ValueError, match=r"^image: 16777217×1 pixels; the service decodes at most 16777216"):
        check_frame_pixels(MAX_FRAME_PIXELS + 1, 1)
