"""StreamContract: the stream's rules, and the claim that admission never accepts what the preprocessor refuses."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from models.tactile.config import TactileConfig
from models.tactile.preprocess import TactilePreprocessor
from models.tactile.resample import Resampler, resampled_count
from models.tactile.stream import StreamContract
from texture_library.recording import Channel

RATES = (500.0, 1000.0, 1250.0, 2000.0, 333.0)


def _channels(kinds: dict[str, tuple[int, float, int]], rng: np.random.Generator) -> dict[str, Channel]:
    """{kind: (samples, rate, columns)} → channels of random data."""
    out = {}
    for kind, (n, rate, cols) in kinds.items():
        shape = (n,) if cols == 1 else (n, cols)
        out[kind] = Channel(rng.normal(size=shape), rate)
    return out


def test_resampled_count_is_what_the_resampler_emits():
    rng = np.random.default_rng(0)
    for rate in RATES + (1000.0 / 3, 999.0, 44100.0):
        r, total = Resampler(rate, 1000.0), 0
        for n in rng.integers(0, 97, size=40):
            r.process(rng.normal(size=int(n)))
            total += int(n)
            assert r.n_out == resampled_count(total, rate, 1000.0)


def test_windows_are_counted_by_stream_time_and_segments_split_on_gaps():
    contract = StreamContract(TactileConfig(), max_lag_s=5)
    rng = np.random.default_rng(1)
    cursor = contract.start()
    block = {"accel": (20, 1000.0, 3), "force": (20, 1000.0, 1), "speed": (20, 1000.0, 1)}
    for k in range(25):
        adv = contract.advance(cursor, _channels(block, rng), t0=k * 0.02)
        cursor = adv.cursor
    assert adv.windows_after == 1 and adv.windows_added == 1 and cursor.segment == 0
    adv = contract.advance(cursor, _channels(block, rng), t0=10.0)  # 9.5 s later than expected: a new segment
    assert adv.new_segment and adv.cursor.segment == 1 and adv.windows_before == 0 and adv.windows_after == 0
    assert adv.cursor.origin_t0 == 10.0


def test_a_slow_channel_in_short_blocks_keeps_one_segment():
    """Speed at 10 Hz beside 1 kHz accel and force, in 20 ms blocks: a block holds one speed sample or none, yet the
    blocks follow each other; the stream is one segment with the windows of the same stream in 100 ms blocks."""
    contract = StreamContract(TactileConfig(), max_lag_s=5)
    rng = np.random.default_rng(2)
    windows = {}
    for block_ms in (20, 100):
        cursor, segments = contract.start(), set()
        for k in range(3000 // block_ms):
            speed = (k + 1) * block_ms // 100 - k * block_ms // 100  # 10 Hz samples that fall in this block
            block = {"accel": (block_ms, 1000.0, 3), "force": (block_ms, 1000.0, 1), "speed": (speed, 10.0, 1)}
            cursor = contract.advance(cursor, _channels(block, rng), t0=k * block_ms / 1000).cursor
            segments.add(cursor.segment)
        windows[block_ms] = cursor.windows
        assert segments == {0}, block_ms
    assert windows[20] == windows[100] > 0


def test_each_channel_in_its_own_block_keeps_one_segment_and_a_real_gap_still_opens_one():
    """accel, force and speed each in its own 100 ms block, all three stamped with the same t0: every block continues
    its own channel (the old rule saw each as 100 ms off and opened 81 segments, 0 windows); then a 200 ms gap in
    all three opens exactly one segment."""
    contract = StreamContract(TactileConfig(), max_lag_s=5)
    rng = np.random.default_rng(3)
    kinds = {"accel": (100, 1000.0, 3), "force": (100, 1000.0, 1), "speed": (100, 1000.0, 1)}
    cursor, segments = contract.start(), []
    for k in range(40):
        t0 = k * 0.1 + (0.2 if k >= 20 else 0.0)  # a 200 ms gap before block 20
        for kind, spec in kinds.items():
            cursor = contract.advance(cursor, _channels({kind: spec}, rng), t0=t0).cursor
            segments.append(cursor.segment)
        if k == 19:
            windows_before_gap = cursor.windows
    assert set(segments[:60]) == {0} and set(segments[60:]) == {1}
    assert windows_before_gap == cursor.windows == 4  # 2 s of every channel: four 0.5 s windows, hop 0.5 s


@pytest.mark.parametrize(
    "change, message",
    [
        ({"accel": (20, 2000.0, 3)}, "rate changed"),
        ({"force": (20, 1000.0, 3)}, "column count changed"),
        ({"accel": (20, 1000.0, 2)}, "shape must be"),
        ({"torque": (20, 1000.0, 1)}, "unknown channel"),
    ],
)
def test_contradictions_are_refused_and_the_cursor_kept(change, message):
    contract = StreamContract(TactileConfig(), max_lag_s=5)
    rng = np.random.default_rng(2)
    first = contract.advance(
        contract.start(), _channels({"accel": (20, 1000.0, 3), "force": (20, 1000.0, 1)}, rng), t0=0.0
    )
    with pytest.raises(ValueError, match=message):
        contract.advance(first.cursor, _channels(change, rng), t0=0.02)
    assert first.cursor.samples == {"accel": 20, "force": 20}


def test_block_time_and_windows_per_block_are_bounded():
    contract = StreamContract(TactileConfig(), max_lag_s=60, max_block_s=1.0, max_block_windows=1)
    rng = np.random.default_rng(3)
    # the probe's block: 100 000 samples at 10 Hz is 10 000 s of stream
    with pytest.raises(ValueError, match="at most 1 s of stream time, got 10000 s"):
        contract.admit(contract.start(), _channels({"accel": (100_000, 10.0, 3)}, rng), t0=0.0)
    # accel runs 4 s ahead (a legal lag); the 1 s force+speed block that follows completes 2 windows at once
    cursor = contract.start()
    for k in range(4):
        cursor = contract.advance(cursor, _channels({"accel": (1000, 1000.0, 3)}, rng), t0=float(k)).cursor
    with pytest.raises(ValueError, match="would complete 2 windows; a block may complete at most 1"):
        contract.admit(cursor, _channels({"force": (1000, 1000.0, 1), "speed": (1000, 1000.0, 1)}, rng), t0=4.0)


# ---- the claim: whatever admission accepts, the preprocessor takes, and it emits exactly the windows counted
block_kinds = st.fixed_dictionaries(
    {},
    optional={
        "accel": st.tuples(st.integers(0, 80), st.sampled_from(RATES), st.just(3)),
        "force": st.tuples(st.integers(0, 80), st.sampled_from(RATES), st.sampled_from((1, 3))),
        "speed": st.tuples(st.integers(0, 80), st.sampled_from(RATES), st.just(1)),
        "position": st.tuples(st.integers(0, 80), st.sampled_from(RATES), st.sampled_from((1, 2))),
    },
).filter(bool)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(blocks=st.lists(block_kinds, min_size=1, max_size=40), seed=st.integers(0, 2**16))
def test_admitted_blocks_never_fail_in_the_preprocessor(blocks, seed):
    rng = np.random.default_rng(seed)
    contract = StreamContract(TactileConfig(hop_s=0.05), max_lag_s=0.2, max_block_s=0.1, max_block_windows=2)
    cursor = contract.start()
    pre = TactilePreprocessor(contract=contract)
    emitted, pending, t0 = 0, [], 0.0
    for kinds in blocks:
        channels = _channels(kinds, rng)
        try:
            adv = contract.admit(cursor, channels, t0)
        except ValueError:
            continue  # refused: nothing may change
        cursor, t0 = adv.cursor, adv.cursor.next_t0
        pending.append(adv.channels)
        if len(pending) == 3 or rng.random() < 0.5:  # the service pushes what accumulated, in bulk
            merged = {
                k: Channel(
                    np.concatenate([p[k].data for p in pending if k in p]),
                    next(p[k].rate_hz for p in pending if k in p),
                )
                for k in {k for p in pending for k in p}
            }
            pre.push(**merged)  # must never raise
            pending = []
            assert pre.n_ready + emitted == contract.windows(cursor)
            emitted += len(pre.take())
