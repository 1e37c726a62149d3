"""benchmarks.block_intake: its floor reads exactly the samples the service's decoder reads."""

from __future__ import annotations

import numpy as np

from benchmarks.block_intake import floor
from drivers.blocks import ChannelBlock, SampleBlock, encode_binary
from service.intake import decode_block


def test_the_floor_parses_the_samples_the_decoder_checks():
    rng = np.random.default_rng(0)
    block = SampleBlock(
        1.5,
        {
            "accel": ChannelBlock(rng.normal(size=(100, 3)).astype(np.float32), 1000.0, "m/s^2"),
            "force": ChannelBlock(rng.random((100, 3)).astype(np.float32), 1000.0, "N"),
            "speed": ChannelBlock((50 + rng.random(100)).astype(np.float32), 1000.0, "mm/s"),
        },
        7,
    )
    payload = encode_binary(block)
    bare, decoded = floor(payload), decode_block(payload, True)
    assert set(bare) == set(decoded.channels) == set(block.channels)
    for kind, ch in decoded.channels.items():
        np.testing.assert_array_equal(bare[kind], np.asarray(ch.data).ravel())
        np.testing.assert_array_equal(bare[kind], block.channels[kind].data.ravel())
