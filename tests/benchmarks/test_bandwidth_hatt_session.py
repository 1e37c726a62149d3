"""The HaTT session's byte count (benchmarks.bandwidth.hatt_session): every byte lands in the second it is sent."""

from __future__ import annotations

import numpy as np

from benchmarks.bandwidth import hatt_session
from texture_library import model_codec
from texture_library.procedural import make_world
from texture_library.render_model import RenderModel


def test_every_byte_in_its_second():
    docs = [RenderModel.from_vibration_model(t.model.name, t.model) for t in make_world(2, 0, image_size=32)]
    run = {"stream_s": 20.0, "seconds_per_texture": 10.0, "feed_bytes": 400, "choice_frame_bytes": 30.0,
           "envelope_bytes": 200.0, "entry_fetches": 2}  # fmt: skip
    got = hatt_session(docs, **run, updates_s=(1, 3))
    order = np.random.default_rng(0).permutation(2)
    whole = [len(model_codec.encode(docs[i])) for i in order]
    series = np.array(got["per_second_bytes_whole"])
    assert series.size == 20 and np.allclose(series[[2, 4, 5]], 20.0)  # the feed alone: 400 bytes over 20 s
    # texture k: its library entry fetched whole at 10·k s, its own model at 10·k + 1 s, a refit at 10·k + 3 s
    for k in range(2):
        assert series[10 * k] == 20.0 + 200.0 + whole[k]
        assert series[10 * k + 1] == 20.0 + 30.0 + 200.0 + whole[k]
    assert got["updates"] == 4 and got["bps_whole_models"] == round(8 * series.sum() / 20.0, 1)
    deltas = np.array(got["per_second_bytes_delta"])
    assert deltas[1] == series[1] and deltas[3] < series[3]  # the first is whole either way; a refit is a delta
    shared = hatt_session(docs, **run, updates_s=(1, 3), library_shared=True)
    assert shared["per_second_bytes_whole"][0] == 20.0  # the library is held: no entry fetch
