"""The pipeline end to end on a real server: blocks in (HTTP and WebSocket), window events out.

The service must compute exactly what training computes: its raw ratings equal the offline
recording_features + Predictor.predict of the same samples.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from websockets.sync.client import connect

from drivers.blocks import encode_binary, encode_json
from models.inference.predictor import Predictor
from models.tactile.features import recording_features
from models.tactile.preprocess import TactilePreprocessor
from service.events import StatusEvent, WindowEvent
from service.settings import Settings
from texture_library.attributes import ATTRIBUTES
from texture_library.library import Library
from texture_library.nearest import PerceptualIndex
from texture_library.recording import Channel, Recording
from texture_library.selection import HysteresisChooser, SelectionRule, SpectralTable


def read_windows(sub, n: int, timeout_s: float = 20.0) -> tuple[list[dict], list[dict]]:
    windows, statuses = [], []
    while len(windows) < n:
        event = json.loads(sub.recv(timeout=timeout_s))
        (windows if event["type"] == "window" else statuses).append(event)
    return windows, statuses


def float32_recording(rec: Recording) -> Recording:
    """What the service receives: the wire carries float32."""

    def f32(c: Channel) -> Channel:
        return Channel(c.data.astype(np.float32).astype(np.float64), c.rate_hz)

    return Recording(f32(rec.accel), f32(rec.force), f32(rec.speed))


def test_events_equal_the_offline_features_and_model(kit, server, client, library_dir, tactile_model):
    rec = kit.stroke_recording(library_dir, "synth_002", 4.2)
    blocks = kit.recording_blocks(rec, block_s=0.02, t0=100.0)
    session = kit.create_session(client)
    with connect(kit.socket_url(server, session, "events")) as sub:
        first = json.loads(sub.recv(timeout=5))
        StatusEvent.model_validate(first)
        assert first["event"] == "subscribed"
        for i, block in enumerate(blocks):  # JSON and binary blocks mixed
            r = kit.post_block(client, session, block, None if i % 3 else "application/json")
            assert r.status_code == 202, r.text
            assert r.json()["seq"] == block.seq and r.json()["duplicate"] is False
        windows, _ = read_windows(sub, 8)
    for w in windows:
        WindowEvent.model_validate(w)
    assert [w["window_index"] for w in windows] == list(range(8))
    assert [w["t_start_s"] for w in windows] == pytest.approx([100.0 + 0.5 * i for i in range(8)])
    assert [w["block_seq"] for w in windows] == [25 * (i + 1) - 1 for i in range(8)]  # 20 ms blocks, 0.5 s windows

    predictor = Predictor(tactile_model)
    features, t_start = recording_features(float32_recording(rec), predictor.tactile_config)
    offline = predictor.predict(features[:8])
    served = np.array([[w["raw_ratings"][a] for a in ATTRIBUTES] for w in windows])
    assert np.allclose(served, offline, atol=0.011)  # events carry 2 decimals

    # smoothing, the selection rule (hybrid: ratings and the window's vibration) and hysteresis replayed
    # offline from the same samples give the same ratings, choices and reasons
    lib = Library.load(library_dir)
    index = PerceptualIndex(lib.ids, lib.ratings)
    settings = Settings()
    rule = SelectionRule(settings.selection_rule, settings.selection_weight)
    table = SpectralTable(lib.ids, [lib.model(i) for i in lib.ids])
    chooser = HysteresisChooser(
        rule,
        settings.hysteresis_margin,
        settings.hysteresis_hold,
        settings.hysteresis_settle_windows,
        settings.hysteresis_release_lead,
    )
    pre = TactilePreprocessor(predictor.tactile_config, max_buffer_s=None)
    f32 = float32_recording(rec)
    pre.push(accel=f32.accel, force=f32.force, speed=f32.speed)
    batch = pre.take()
    state = mismatch = None
    for i, (w, raw) in enumerate(zip(windows, served, strict=True)):
        state = raw if state is None else 0.5 * raw + 0.5 * state
        assert np.allclose([w["ratings"][a] for a in ATTRIBUTES], state, atol=0.02)
        m = table.mismatch_db(batch.accel[i], float(batch.speed[i].mean()), float(batch.force[i].mean()))
        mismatch = m if mismatch is None else 0.5 * m + 0.5 * mismatch
        choice = chooser.choose(index.ids, rule.costs(index.distances(state), mismatch))
        assert w["chosen"] == choice.id
        assert w["selection"]["rule"] == "hybrid" and w["selection"]["reason"] == choice.reason
        assert w["selection"]["held_by_hysteresis"] == choice.held_by_hysteresis
        assert [m["id"] for m in w["matches"]] == [m.id for m in index.query(state, 3)]
        assert all(v >= 0 for v in w["latency_ms"].values())
        assert w["latency_ms"]["total"] >= w["latency_ms"]["queue"]
        assert w["model"] == "ridge-tactile"


def test_duplicates_are_acknowledged_but_not_processed_again(kit, server, client, library_dir):
    rec = kit.stroke_recording(library_dir, "synth_001", 1.5)
    blocks = kit.recording_blocks(rec)
    session = kit.create_session(client)
    for block in blocks[:60]:
        assert kit.post_block(client, session, block).status_code == 202
    for block in blocks[10:60]:  # a robot resending after an outage
        r = kit.post_block(client, session, block)
        assert r.status_code == 202 and r.json()["duplicate"] is True
    for block in blocks[60:]:
        assert kit.post_block(client, session, block).status_code == 202
    status = kit.wait_for(lambda: (s := kit.session_status(client, session))["counters"]["windows"] == 3 and s)
    assert status["counters"]["blocks_duplicate"] == 50
    assert status["counters"]["blocks_accepted"] == len(blocks)
    assert status["last_seq"] == blocks[-1].seq


def test_any_block_size_gives_the_same_windows(kit, server, client, library_dir):
    rec = kit.stroke_recording(library_dir, "synth_004", 2.0)
    results = []
    for block_s in (0.02, 0.007, 0.5, 1.0):  # up to HAPTICLINK_MAX_BLOCK_S
        session = kit.create_session(client)
        with connect(kit.socket_url(server, session, "events")) as sub:
            sub.recv(timeout=5)
            for block in kit.recording_blocks(rec, block_s=block_s):
                assert kit.post_block(client, session, block).status_code == 202
            windows, _ = read_windows(sub, 4)
        results.append(np.array([[w["raw_ratings"][a] for a in ATTRIBUTES] for w in windows]))
    for other in results[1:]:  # equal up to float32 rounding of the batched features
        assert np.allclose(results[0], other, atol=0.011)


@pytest.mark.parametrize("block_s", [0.1, 0.25])
def test_a_window_completes_with_the_block_that_ends_where_it_ends(kit, server, client, library_dir, block_s):
    """Why a long default block costs no latency: at 1 kHz the block ending at a window's end completes it, whatever
    the block's size (a divisor of the hop)."""
    rec = kit.stroke_recording(library_dir, "synth_004", 2.0)
    blocks = kit.recording_blocks(rec, block_s=block_s)
    ends = {b.seq: b.t0 + block_s for b in blocks}
    session = kit.create_session(client)
    with connect(kit.socket_url(server, session, "events")) as sub:
        sub.recv(timeout=5)
        for block in blocks:
            assert kit.post_block(client, session, block).status_code == 202
        windows, _ = read_windows(sub, 4)
    assert [round(w["t_end_s"], 6) for w in windows] == [0.5, 1.0, 1.5, 2.0]
    assert [round(ends[w["block_seq"]], 6) for w in windows] == [0.5, 1.0, 1.5, 2.0]


def test_a_time_gap_starts_a_new_segment_and_no_window_straddles_it(kit, server, client, library_dir):
    rec = kit.stroke_recording(library_dir, "synth_003", 2.0)
    first = kit.recording_blocks(rec.crop(0, 0.75), t0=0.0)
    second = kit.recording_blocks(rec.crop(0.75, 2.0), t0=5.0, seq0=len(first))  # 4.25 s of data lost
    session = kit.create_session(client)
    with connect(kit.socket_url(server, session, "events")) as sub:
        sub.recv(timeout=5)
        for block in first + second:
            assert kit.post_block(client, session, block).status_code == 202
        windows, _ = read_windows(sub, 3)
    assert [w["t_start_s"] for w in windows] == pytest.approx([0.0, 5.0, 5.5])
    status = kit.session_status(client, session)
    assert status["segments"] == 2 and status["counters"]["windows"] == 3


def test_websocket_ingest_acknowledges_each_block_and_survives_bad_ones(kit, server, client, library_dir):
    rec = kit.stroke_recording(library_dir, "synth_005", 1.0)
    blocks = kit.recording_blocks(rec)
    session = kit.create_session(client)
    with (
        connect(kit.socket_url(server, session, "ingest")) as ws,
        connect(kit.socket_url(server, session, "events")) as sub,
    ):
        sub.recv(timeout=5)
        for i, block in enumerate(blocks):
            if i == 10:  # garbage, then a well-formed block that lies about its rate: both refused, socket stays
                ws.send(b"HLB1garbage")
                bad = json.loads(ws.recv(timeout=5))
                assert bad["seq"] is None and bad["ok"] is False and "header length" in bad["error"]
                lying = json.loads(json.dumps(encode_json(block)))
                lying["channels"]["accel"]["rate_hz"] = 2000.0
                ws.send(json.dumps(lying))
                bad = json.loads(ws.recv(timeout=5))
                assert bad == {
                    "seq": block.seq,
                    "ok": False,
                    "error": "accel: rate changed from 1000 Hz to 2000 Hz mid-stream",
                }
            ws.send(encode_binary(block) if i % 2 else json.dumps(encode_json(block)))
            ack = json.loads(ws.recv(timeout=5))
            assert ack == {"seq": block.seq, "ok": True, "duplicate": False}
        ws.send(encode_binary(blocks[3]))
        assert json.loads(ws.recv(timeout=5)) == {"seq": blocks[3].seq, "ok": True, "duplicate": True}
        windows, _ = read_windows(sub, 2)
    assert [w["window_index"] for w in windows] == [0, 1]


def test_a_backlog_taken_in_capped_jobs_gives_the_windows_of_one_job(kit, base_settings, library_dir):
    """A session's backlog is estimated a few windows per job (the batcher caps a job's windows), oldest first: the
    same windows, in the same order, with the same ratings as one job of it all."""
    import time

    from service.live_session import Session
    from service.metrics import ServiceMetrics
    from service.pipeline import estimate_batch
    from service.runtime import load_runtime

    runtime = load_runtime(base_settings)
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_001", 3.2), block_s=0.05)

    def session() -> Session:
        s = Session("s", "s", None, runtime, base_settings, None, None, ServiceMetrics(), lambda s: None)  # type: ignore[arg-type]
        for b in blocks:
            s.ingest(b, time.perf_counter_ns())
        return s

    whole = session().take_job()
    capped, jobs = session(), []
    while (job := capped.take_job(max_windows=2)) is not None and job.windows:
        jobs.append(job)
    assert whole is not None and whole.windows == 6 and [j.windows for j in jobs] == [2, 2, 2]
    assert sum(len(j.blocks) for j in jobs) <= len(whole.blocks)  # blocks after the last window may stay pending
    one = estimate_batch(runtime, [whole])[0].estimates
    split = [e for j in jobs for e in estimate_batch(runtime, [j])[0].estimates]
    assert [e.index for e in split] == [e.index for e in one] == list(range(6))
    assert [e.completed_by for e in split] == [e.completed_by for e in one]
    np.testing.assert_allclose([e.raw for e in split], [e.raw for e in one], atol=1e-9)


def _sessions_of(kit, base_settings, library_dir):
    """(runtime, job(name, texture)): a session's job over 2.2 s of stroke in 50 ms blocks."""
    import time

    from service.live_session import Session
    from service.metrics import ServiceMetrics
    from service.runtime import load_runtime

    runtime = load_runtime(base_settings)

    def job(name: str, texture: str):
        s = Session(name, name, None, runtime, base_settings, None, None, ServiceMetrics(), lambda s: None)  # type: ignore[arg-type]
        for b in kit.recording_blocks(kit.stroke_recording(library_dir, texture, 2.2), block_s=0.05):
            s.ingest(b, time.perf_counter_ns())
        return s.take_job()

    return runtime, job


@pytest.mark.parametrize("step", ["featurize", "predict", "lookup"])
def test_a_failure_in_one_session_costs_the_other_sessions_of_its_batch_nothing(
    kit, base_settings, library_dir, monkeypatch, step
):
    """Features, the model or the lookup failing on one session's windows: that session alone gets the error (and
    restarts its stream); the other sessions of the batch get the windows they get without it."""
    from service import pipeline

    runtime, job = _sessions_of(kit, base_settings, library_dir)
    alone = pipeline.estimate_batch(runtime, [job("good", "synth_001")])[0]
    good, bad, other = job("good", "synth_001"), job("bad", "synth_002"), job("other", "synth_003")
    real = getattr(pipeline, step)

    def glitch(*args, **kwargs):
        items = args[0] if step == "lookup" else args[-1]
        if any(p.estimator is bad.estimator for p in ([items] if step == "lookup" else items)):
            raise FloatingPointError("a glitch in this session's windows")
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline, step, glitch)
    results = pipeline.estimate_batch(runtime, [good, bad, other])

    assert isinstance(results[1].error, FloatingPointError) and results[1].estimates == []
    assert results[1].windows == bad.windows and bad.estimator.segment == -1  # restarts at the next block
    assert [r.error for r in (results[0], results[2])] == [None, None]
    assert len(results[0].estimates) == len(alone.estimates) == good.windows > 0
    assert len(results[2].estimates) == other.windows > 0
    np.testing.assert_allclose([e.raw for e in results[0].estimates], [e.raw for e in alone.estimates], atol=1e-9)


def test_a_lookup_failing_partway_undoes_what_its_windows_moved_on(kit, base_settings, library_dir):
    """The lookup fails at a session's third window: none of its windows is published, so none may count — the
    window index and the smoothing, steadiness and hysteresis state are as if they had never been."""
    from service import pipeline

    runtime, job = _sessions_of(kit, base_settings, library_dir)
    bad = job("bad", "synth_002")
    est = bad.estimator
    assert bad.windows >= 3 and est.next_index == 0
    real, calls = est.selector.choose, []

    def choose(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise FloatingPointError("a glitch at the third window")
        return real(*args, **kwargs)

    est.selector.choose = choose
    result = pipeline.estimate_batch(runtime, [bad])[0]
    assert isinstance(result.error, FloatingPointError) and result.estimates == [] and len(calls) == 3
    assert est.next_index == 0
    assert est.smoother.state is None and len(est.steadiness.recent) == 0 and est.mismatch is None
    assert est.selector.choose is not choose  # a fresh chooser: no hysteresis from windows nobody saw


def test_a_fault_of_the_batch_alone_is_estimated_and_logged(kit, base_settings, library_dir, monkeypatch, caplog):
    """Features failing for a batch but for none of its sessions alone: every session gets its windows, and one
    WARNING says so (such a job costs twice)."""
    import logging

    from service import pipeline

    runtime, job = _sessions_of(kit, base_settings, library_dir)
    jobs = [job("a", "synth_001"), job("b", "synth_002")]
    real = pipeline.featurize

    def only_alone(runtime, prepared):
        if len({p.estimator for p in prepared}) > 1:
            raise MemoryError("a batch too large")
        return real(runtime, prepared)

    monkeypatch.setattr(pipeline, "featurize", only_alone)
    with caplog.at_level(logging.WARNING, logger="service.pipeline"):
        results = pipeline.estimate_batch(runtime, jobs)
    assert [r.error for r in results] == [None, None]
    assert [len(r.estimates) for r in results] == [j.windows for j in jobs]
    assert [r.levelname for r in caplog.records] == ["WARNING"] and "for none of its sessions" in caplog.text
