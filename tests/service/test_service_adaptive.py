"""The serving policy: what it embeds, how it pools, when the full model runs — as pure objects, through the
pipeline with real ONNX models, and on a live server."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest
from websockets.sync.client import connect

from drivers.scene_change import thumbnail
from service.adaptive import SceneViews, ServingPolicy
from texture_library.nearest import PerceptualIndex, decision_margin


# ---- the policy on its own -----------------------------------------------------------------------
def test_always_full_embeds_every_frame_and_uses_the_newest():
    scene = SceneViews(ServingPolicy("always-full"), 0.05)
    same = np.full((16, 16), 0.5, np.float32)
    assert [scene.offer(same) for _ in range(3)] == [(True, True), (True, False), (True, False)]
    scene.add(np.ones(3, np.float32), True)
    assert np.array_equal(scene.add(np.full(3, 3.0, np.float32), False), np.full(3, 3.0))  # no pooling
    assert scene.views == 1


def test_adaptive_embeds_a_new_scene_and_its_first_pool_frames_then_nothing():
    scene = SceneViews(ServingPolicy("adaptive", pool_frames=2), 0.05)
    a, b = np.full((16, 16), 0.2, np.float32), np.full((16, 16), 0.8, np.float32)
    assert [scene.offer(a) for _ in range(4)] == [(True, True), (True, False), (False, False), (False, False)]
    scene.add(np.zeros(3, np.float32), True)
    pooled = scene.add(np.full(3, 2.0, np.float32), False)
    assert np.allclose(pooled, 1.0) and scene.views == 2  # the mean of the scene's two views
    assert scene.offer(b) == (True, True)  # the scene changed
    assert np.allclose(scene.add(np.full(3, 5.0, np.float32), True), 5.0)  # a new scene starts a new pool
    scene.forget()
    assert scene.offer(b) == (True, True)  # after a failed embedding the next frame is tried


def test_wants_answers_what_offer_would_do_and_takes_nothing():
    """A robot's scene check asks `wants` in place of sending the frame: the same answer as offer's, no view taken."""
    scene = SceneViews(ServingPolicy("adaptive", pool_frames=2), 0.05)
    a, b = np.full((16, 16), 0.2, np.float32), np.full((16, 16), 0.8, np.float32)
    assert scene.wants(a) and scene.wants(a), "no scene yet; asking twice takes nothing"
    assert scene.offer(a) == (True, True)
    assert scene.wants(a) and scene.offer(a) == (True, False), "the second view is still wanted"
    assert not scene.wants(a) and scene.offer(a) == (False, False), "both views taken"
    assert scene.wants(b), "another scene"
    scene.forget()
    assert scene.wants(a), "after a failed embedding the scene is wanted again"


def test_the_full_model_runs_where_the_interval_is_wide_a_boundary_is_near_or_the_input_is_flagged():
    policy = ServingPolicy("adaptive", full_model_width=30, full_model_margin=5)
    width = np.array([[10, 10, 10, 10], [10, 40, 10, 10], [10, 10, 10, 10], [10, 10, 10, 10]], float)
    margin = np.array([20.0, 20.0, 2.0, 20.0])
    flagged = np.array([False, False, False, True])
    assert policy.needs_full(width, margin, flagged).tolist() == [False, True, True, True]
    assert policy.needs_full(None, margin, flagged).all()  # no calibration: never trusted alone
    assert ServingPolicy("always-full").needs_full(width, margin, None).all()
    with pytest.raises(ValueError, match="serving policy"):
        ServingPolicy("sometimes")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="pool_frames"):
        ServingPolicy("adaptive", pool_frames=0)


def test_decision_margin_is_the_gap_between_the_two_nearest():
    index = PerceptualIndex(["a", "b", "c"], np.array([[0, 0, 0, 0], [10, 0, 0, 0], [50, 0, 0, 0]], float))
    d = index.distances_many(np.array([[0, 0, 0, 0], [5, 0, 0, 0], [9, 0, 0, 0]], float))
    assert np.allclose(d[1], index.distances(np.array([5.0, 0, 0, 0])))
    assert decision_margin(d).tolist() == pytest.approx([10.0, 0.0, 8.0])
    assert decision_margin(np.array([3.0])) == np.inf
    with pytest.raises(ValueError):
        decision_margin(np.zeros((2, 2, 2)))


# ---- on a live server ----------------------------------------------------------------------------
def _frame(kit, level: int) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    rng = np.random.default_rng(level)
    Image.fromarray(np.clip(level + rng.normal(0, 2, (256, 256)), 0, 255).astype(np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


@pytest.mark.parametrize("policy", ["always-full", "adaptive"])
def test_a_live_server_embeds_what_its_policy_says(kit, visual_model, library_dir, policy):
    """Four frames of one scene, then one of another: always-full embeds all five, adaptive (pool 2) the first
    two of each scene; windows report the visual input either way."""
    from service.settings import Settings

    settings = Settings(
        model_path=visual_model.model,
        tactile_model_path=visual_model.tactile,
        library_dir=library_dir,
        backbone_path=visual_model.backbone,
        instance_id="test-adaptive",
        api_keys=kit.API_KEY,
        session_burst=1000,
        session_queue_windows=64,
        serving_policy=policy,
        pool_frames=2,
        session_idle_s=600,  # the reaper is not this test's subject: on a busy host an embedding takes over 15 s
        session_first_block_s=600,
    )
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=30) as client:
        session = kit.create_session(client)
        robot = {"Authorization": f"Bearer {session['robot_token']}", "Content-Type": "image/png"}
        with connect(kit.socket_url(srv, session, "events")) as sub:
            sub.recv(timeout=5)
            for level in (100, 100, 100, 100, 200):
                r = client.post(f"/sessions/{session['session_id']}/frames", content=_frame(kit, level), headers=robot)
                assert r.status_code == 202, r.text
                # one at a time, so none is superseded while the previous is embedded
                kit.wait_for(
                    lambda: (
                        kit.session_status(client, session)["counters"]["frames_received"]
                        == kit.session_status(client, session)["counters"]["frames_embedded"]
                        + kit.session_status(client, session)["counters"]["frames_unchanged"]
                    ),
                    timeout_s=60,
                )
            updates = []
            while len(updates) < (5 if policy == "always-full" else 3):
                event = json.loads(sub.recv(timeout=30))
                if event.get("event") == "visual_updated":
                    updates.append(event)
        counters = kit.session_status(client, session)["counters"]
    if policy == "always-full":
        assert counters["frames_embedded"] == 5 and counters["frames_unchanged"] == 0
        assert [u["views"] for u in updates] == [1] * 5
    else:
        assert counters["frames_embedded"] == 3 and counters["frames_unchanged"] == 2
        assert [u["views"] for u in updates] == [1, 2, 1]


def test_thumbnail_of_a_frame_is_what_scene_views_compare():
    gray = np.random.default_rng(0).uniform(0, 1, (64, 64)).astype(np.float32)
    scene = SceneViews(ServingPolicy("adaptive"), 0.05)
    assert scene.offer(thumbnail(gray)) == (True, True)
    assert scene.offer(thumbnail(np.clip(gray + 0.01, 0, 1))) == (False, False)  # same scene, slightly brighter


# ---- through the pipeline with real models -------------------------------------------------------
@pytest.mark.parametrize("width, expect", [(200.0, "cheap"), (0.0, "full")])
def test_the_cheap_model_answers_unless_the_policy_sends_the_window_to_the_full_one(
    kit, visual_model, tactile_model, library_dir, width, expect
):
    """Main ridge-both (with an embedding), cheap ridge-tactile with a calibrated card: with a generous width
    bound and no margin the cheap estimate stands (except flagged windows); with width 0 every window goes to
    the full model. Either way raw_ratings are exactly that model's prediction of the window's features."""
    from models.tactile.features import recording_features
    from service.live_session import canonical_channels, stream_contract
    from service.pipeline import AdmittedBlock, SessionEstimator, SessionJob, estimate_batch
    from service.runtime import load_runtime
    from service.settings import Settings

    settings = Settings(
        model_path=visual_model.model,
        cheap_model_path=tactile_model,
        library_dir=library_dir,
        backbone_path=visual_model.backbone,
        instance_id="t",
        api_keys=kit.API_KEY,
        full_model_width=width,
        full_model_margin=0.0,
    )
    rt = load_runtime(settings)
    assert rt.cheap is not None and rt.cheap.window_calibration is not None
    gray = np.random.default_rng(1).uniform(0, 1, (256, 256)).astype(np.float32)
    visual, reasons = rt.embed_and_inspect(gray)
    checks = rt.frame_checks(reasons, visual)
    rec = kit.stroke_recording(library_dir, "synth_002", 3.0)
    contract = stream_contract(rt, settings)
    cursor, blocks, windows = contract.start(), [], 0
    for b in kit.recording_blocks(rec):
        adv = contract.admit(cursor, canonical_channels(b), b.t0)
        cursor, windows = adv.cursor, windows + adv.windows_added
        blocks.append(AdmittedBlock(b.seq, cursor.segment, cursor.origin_t0, adv.channels, adv.windows_after, 0))
    est = SessionEstimator.from_settings(rt, contract, settings)
    (result,) = estimate_batch(rt, [SessionJob(est, blocks, visual, windows, checks)])
    assert result.error is None and len(result.estimates) == 6
    features, _ = recording_features(rec, rt.tactile_config)
    full_raw = rt.main.predictor.predict(features[:6], np.repeat(visual[None], 6, axis=0))
    cheap_raw = rt.cheap.predictor.predict(features[:6])
    for k, w in enumerate(result.estimates):
        flagged_input = bool(rt.cheap.detector.check(features[k : k + 1]).flags[0])
        uses_full = expect == "full" or flagged_input
        assert w.model == (rt.main.name if uses_full else rt.cheap.name)
        assert np.allclose(w.raw, full_raw[k] if uses_full else cheap_raw[k], atol=1e-3)
    if expect == "cheap":
        assert any(w.model == rt.cheap.name for w in result.estimates)
