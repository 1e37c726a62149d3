"""Pictures are shed before robots: under load camera frames are bounded, sampled less often, then dropped — the
windows of a session without its frame estimated tactile-only and marked — and only then are sessions refused; a
slow visual pool never sheds a robot's windows; refused robots come back in the order they came, told when.

Real uvicorn on loopback where a client meets it (the visual model with its tactile-only fallback, a stalled visual
pool); the guard's decisions in steps with stub sessions, as tests/service/test_service_admission.py does."""

from __future__ import annotations

import json
import logging
import threading
import time
from types import SimpleNamespace

import httpx
import pytest
from websockets.sync.client import connect

from service.capacity import (
    FRAME_SAMPLE_S,
    FRAMES_ALL,
    FRAMES_DROPPED,
    FRAMES_SAMPLED,
    READMIT_EVERY_S,
    SETTLE_S,
    AtCapacity,
    CapacityGuard,
)
from service.metrics import ServiceMetrics
from service.settings import Settings
from service.thread_cpu import ThreadCpu
from service.visual_queue import EmbeddingQueue


# ---- the embedding queue ----------------------------------------------------------------------------------------
def test_the_embedding_queue_measures_each_jobs_wait_for_the_thread_and_the_work_ahead():
    queue = EmbeddingQueue(first_guess_s=0.1)
    a, b = queue.submit(now=0.0), queue.submit(now=0.5)
    assert queue.jobs == 2 and queue.ahead_s() == pytest.approx(0.2)
    assert queue.wait_s(1.0) == pytest.approx(1.0)  # a still waits, for 1 s by now
    a.started = 1.2
    queue.done(a, now=1.5)  # ran 0.3 s: the average moves an eighth of the way
    assert queue.embed_s == pytest.approx(0.1 + (0.3 - 0.1) / 8)
    assert queue.wait_s(1.6) == pytest.approx(1.2)  # a waited 1.2 s (recorded); b has waited 1.1 s
    assert queue.wait_s(1.6) == pytest.approx(1.1)  # the record restarted: b still waits
    queue.done(b, now=2.0)  # cancelled before it started: it waited all along
    assert queue.jobs == 0 and queue.wait_s(2.0) == pytest.approx(1.5) and queue.wait_s(3.0) == 0.0
    assert queue.drain_s(1.0) == 0.0
    with pytest.raises(ValueError, match="first_guess_s"):
        EmbeddingQueue(first_guess_s=0)


# ---- frames before sessions: the guard's steps ------------------------------------------------------------------
class _Robot(SimpleNamespace):
    def touch(self) -> None:
        self.last_activity = self.last_contact = time.monotonic()

    def heard(self) -> None:
        self.last_contact = time.monotonic()


def _guard(n: int, queue: EmbeddingQueue | None = None) -> tuple[CapacityGuard, list[_Robot]]:
    sessions = [
        _Robot(id=f"s{i}", opened_at=float(i), last_activity=0.0, last_contact=0.0, last_seq=0, visual=None)
        for i in range(n)
    ]
    return CapacityGuard(Settings(), ServiceMetrics(), lambda: sessions, visual=queue), sessions


def _update(guard: CapacityGuard, sessions: list[_Robot], now: float) -> None:
    for s in sessions:
        if s.id not in guard._shed:
            s.last_activity = now
    guard.update(now)


def _shed(guard: CapacityGuard, sessions: list[_Robot]) -> list[str]:
    return [s.id for s in sessions if s.id in guard._shed]


def test_over_capacity_with_the_camera_busy_frames_are_sampled_then_dropped_and_only_then_are_sessions_shed():
    queue = EmbeddingQueue()
    guard, sessions = _guard(8, queue)
    job = queue.submit(now=0.0)  # embeddings are queued: the camera path holds CPU
    guard.cpu_share, guard.lag_s = 0.6, 3 * guard.settings.shed_lag_s  # busy and late
    with pytest.raises(AtCapacity, match="its event loop runs"):
        guard.admit_session(len(sessions))  # a late loop is not the camera's doing alone: new sessions wait
    _update(guard, sessions, 0.0)
    assert guard.frame_level == FRAMES_SAMPLED and _shed(guard, sessions) == []
    _update(guard, sessions, SETTLE_S / 2)  # the step's effect has not shown yet: nothing more
    assert guard.frame_level == FRAMES_SAMPLED and _shed(guard, sessions) == []
    _update(guard, sessions, SETTLE_S)
    assert guard.frame_level == FRAMES_DROPPED and _shed(guard, sessions) == []
    with pytest.raises(AtCapacity, match="camera frames are dropped") as refused:
        guard.admit_frame(sessions[1])  # type: ignore[arg-type]
    assert float(refused.value.headers["Retry-After"]) > 0
    guard.admit_frame(sessions[0])  # type: ignore[arg-type]  # the oldest is never shed, nor its frames dropped
    guard._frame_at = -10.0  # (taken on the real clock: back on the test's)
    _update(guard, sessions, 1.5 * SETTLE_S)  # frames dropped, their effect not shown yet
    assert _shed(guard, sessions) == []
    queue.done(job, now=2 * SETTLE_S)
    _update(guard, sessions, 2 * SETTLE_S)  # frames gave what they had and it is still over: robots now
    assert _shed(guard, sessions) == ["s6", "s7"]
    # calm again: the robots come back first, then their frames, a level at a time
    guard.cpu_share, guard.lag_s = 0.3, 0.0
    t = 2 * SETTLE_S + READMIT_EVERY_S
    _update(guard, sessions, t)
    assert _shed(guard, sessions) == ["s7"] and guard.frame_level == FRAMES_DROPPED
    t += READMIT_EVERY_S
    _update(guard, sessions, t)
    assert _shed(guard, sessions) == [] and guard.frame_level == FRAMES_DROPPED
    t += READMIT_EVERY_S
    _update(guard, sessions, t)
    assert guard.frame_level == FRAMES_SAMPLED
    t += READMIT_EVERY_S
    _update(guard, sessions, t)
    assert guard.frame_level == FRAMES_ALL


def test_windows_queued_while_the_camera_is_busy_degrade_frames_and_neither_refuse_nor_shed_robots():
    """The window pool falls behind while embeddings run beside it (on two cores an embedding anywhere makes every
    window dearer): frames give back their CPU first; new robots are not refused for the window queue meanwhile."""
    guard, sessions = _guard(8)
    guard._frame_at = 0.0  # a frame was just taken
    guard.cpu_share, guard.queue_s = 0.6, 3 * guard.settings.shed_queue_s
    _update(guard, sessions, 0.1)
    assert guard.frame_level == FRAMES_SAMPLED and _shed(guard, sessions) == []
    assert guard._why_no_room(0.1) is None


def test_at_sampled_frames_a_robot_with_a_visual_input_gets_a_frame_every_few_seconds_a_first_frame_always():
    guard, sessions = _guard(4)
    guard.frame_level = FRAMES_SAMPLED
    seen, first = sessions[1], sessions[2]
    seen.visual = object()  # has an embedding
    guard.admit_frame(seen)  # type: ignore[arg-type]
    with pytest.raises(AtCapacity, match=f"sampled once every {FRAME_SAMPLE_S:g} s") as refused:
        guard.admit_frame(seen)  # type: ignore[arg-type]
    assert 0 < float(refused.value.headers["Retry-After"]) <= FRAME_SAMPLE_S
    guard.admit_frame(first)  # type: ignore[arg-type]  # no embedding yet: its first frame is not held back
    guard.admit_frame(first)  # type: ignore[arg-type]


def test_frames_beyond_the_embedding_budget_wait_and_are_taken_in_the_order_they_were_refused():
    """The queue is bounded in embedding time before a frame is taken: a fleet's first frames arrive within half a
    second, before any measure could see them. Each refused robot is told when its frame would be taken, later the
    later it came; once there is room, the robot refused first goes first."""
    queue = EmbeddingQueue(first_guess_s=0.4)
    guard, sessions = _guard(6, queue)
    jobs = [queue.submit() for _ in range(3)]  # 1.2 s of embeddings queued, over the budget of 1 s
    retry = []
    for s in sessions[1:4]:
        with pytest.raises(AtCapacity, match="ms of embeddings are queued") as refused:
            guard.admit_frame(s)  # type: ignore[arg-type]
        retry.append(float(refused.value.headers["Retry-After"]))
    assert retry == sorted(retry) and retry[0] < retry[-1]
    queue.done(jobs[0])  # 0.8 s queued: room for one
    with pytest.raises(AtCapacity, match="refused before this one go first"):
        guard.admit_frame(sessions[2])  # type: ignore[arg-type]
    guard.admit_frame(sessions[1])  # type: ignore[arg-type]  # the first refused is taken
    queue.submit()  # its embedding is queued
    queue.done(jobs[1])
    guard.admit_frame(sessions[2])  # type: ignore[arg-type]  # now the next in line


def test_a_robot_whose_windows_wait_for_a_first_frame_always_gets_it():
    """Without a tactile-only model a visual session's windows wait for its first frame: refusing that frame would
    stop its windows, not degrade them."""
    guard, sessions = _guard(3)
    guard.frame_level = FRAMES_DROPPED
    sessions[1].waiting_for_frame = lambda: True
    guard.admit_frame(sessions[1])  # type: ignore[arg-type]
    sessions[2].waiting_for_frame = lambda: False
    with pytest.raises(AtCapacity, match="dropped"):
        guard.admit_frame(sessions[2])  # type: ignore[arg-type]


# ---- on a real uvicorn -------------------------------------------------------------------------------------------
def _visual_settings(kit, visual_model, library_dir, **extra) -> Settings:
    return Settings(
        model_path=visual_model.model,
        tactile_model_path=visual_model.tactile,
        library_dir=library_dir,
        backbone_path=visual_model.backbone,
        api_keys=kit.API_KEY,
        metrics_token=kit.METRICS_TOKEN,
        session_queue_windows=64,
        **extra,
    )


def _post_frame(client: httpx.Client, session: dict, image: bytes) -> httpx.Response:
    return client.post(
        f"/sessions/{session['session_id']}/frames",
        content=image,
        headers={"Authorization": f"Bearer {session['robot_token']}", "Content-Type": "image/png"},
    )


def test_a_slow_visual_pool_sheds_frames_not_tactile_windows_which_are_served_tactile_only_and_marked(
    kit, visual_model, library_dir, caplog
):
    caplog.set_level(logging.INFO)
    image = (library_dir / "images" / "synth_003.png").read_bytes()
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_003", 2.1))  # 4 windows
    settings = _visual_settings(kit, visual_model, library_dir, instance_id="frames-first", shed_visual_queue_s=0.05)
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=30) as client:
        state = srv.app.state.service
        guard = state.capacity
        release = threading.Event()
        stall = state.visual_pool.submit(release.wait, 60)  # the embedder is stuck (a slow visual pool)
        try:
            first, second = kit.create_session(client, "first"), kit.create_session(client, "second")
            with connect(kit.socket_url(srv, second, "events")) as sub:
                assert json.loads(sub.recv(timeout=5))["event"] == "subscribed"
                taken = _post_frame(client, first, image)  # none queued: taken; its embedding waits behind the stall
                assert taken.status_code == 202 and taken.json()["outcome"] == "embedding"
                refused = _post_frame(client, second, image)
                detail = refused.json()["detail"]
                assert refused.status_code == 429 and "at capacity for camera frames" in detail
                assert "tactile-only" in detail and float(refused.headers["retry-after"]) > 0
                for block in blocks:  # the robots' blocks are all taken while frames wait
                    assert kit.post_block(client, second, block).status_code == 202
                    assert kit.post_block(client, first, block).status_code == 202
                events: list[dict] = []
                while sum(e["type"] == "window" for e in events) < 4:
                    events.append(json.loads(sub.recv(timeout=30)))
            told = [e for e in events if e.get("event") == "input_missing"]
            assert len(told) == 1 and told[0]["missing"] == "frame" and "tactile-only" in told[0]["message"]
            windows = [e for e in events if e["type"] == "window"]
            assert [(w["inputs"], w["missing_inputs"]) for w in windows] == [("tactile", ["frame"])] * 4
            # the frames' own wait grows behind the stall: frames are degraded, no robot is shed
            kit.wait_for(lambda: guard.frame_level >= FRAMES_SAMPLED, timeout_s=10)
            assert guard.visual_queue_s > settings.shed_visual_queue_s and guard.shedding == 0
            status = kit.session_status(client, first)
            assert status["counters"]["windows"] == 4 and status["counters"]["blocks_refused"] == 0
        finally:
            release.set()
            stall.result(timeout=10)
        kit.wait_for(lambda: kit.session_status(client, first)["counters"]["frames_embedded"] == 1, timeout_s=60)
        # the embedder caught up: frames come back a level at a time, then the refused robot's frame is taken
        kit.wait_for(lambda: guard.frame_level == FRAMES_ALL, timeout_s=60)
        # read before the next frame: on a busy host its own embedding may wait past the 50 ms bound and degrade again
        assert "hapticlink_frame_level 0.0" in client.get("/metrics", headers=kit.SCRAPER).text
        assert _post_frame(client, second, image).status_code == 202
        kit.wait_for(lambda: kit.session_status(client, second)["counters"]["frames_embedded"] == 1, timeout_s=60)
        metrics = client.get("/metrics", headers=kit.SCRAPER).text
        assert 'hapticlink_windows_degraded_total{missing="frame"} 4.0' in metrics
        assert "hapticlink_visual_queue_seconds" in metrics
        assert "hapticlink_sessions_shed_total 0.0" in metrics
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert "camera frames" in caplog.text  # one WARNING says what was degraded and why


def test_shed_robots_come_back_in_the_order_they_came_told_when_and_the_wait_is_measured(
    kit, base_settings, library_dir
):
    """Over capacity the newest robots are shed (429, Retry-After later the newer they are); once it has caught up
    they are let back oldest first, and the time from their readmission to their next block accepted is measured."""
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_002", 1.0))
    # refusals answered at once, told when (held in line instead: tests/service/test_service_readmission.py)
    settings = base_settings.model_copy(update={"instance_id": "readmit", "readmit_hold_s": 0})
    # about capacity: the service's own CPU meter, the load set through the budget
    with kit.running(settings, cpu_meter=ThreadCpu()) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        guard, sessions = kit.overload(client, srv, settings, blocks[0], robots=3)  # over capacity from now on
        kit.wait_for(lambda: guard.shedding == 2, timeout_s=10)
        retry = []
        for s in sessions[1:]:
            r = kit.post_block(client, s, blocks[1])
            assert r.status_code == 429 and "among its newest" in r.json()["detail"]
            retry.append(float(r.headers["retry-after"]))
        assert 0 < retry[0] < retry[1]  # the older comes back first: it is told sooner
        guard.settings = settings.model_copy(update={"cpu_budget": 1.0})  # caught up
        order = []

        def back() -> bool:
            for i, s in enumerate(sessions[1:], 1):
                if i not in order and kit.post_block(client, s, blocks[1]).status_code == 202:
                    order.append(i)
            return len(order) == 2

        kit.wait_for(back, timeout_s=20)
        assert order == [1, 2]  # in the order they came
        metrics = client.get("/metrics", headers=kit.SCRAPER).text
        assert "hapticlink_readmit_seconds_count 2.0" in metrics


def test_health_on_either_port_names_the_probe_port_orchestrators_should_use(kit, base_settings):
    settings = base_settings.model_copy(update={"instance_id": "probe-named", "probe_port": 0})
    with kit.running(settings) as srv, httpx.Client(timeout=10) as client:
        port = srv.app.state.service.probes.port
        own, main = client.get(f"http://127.0.0.1:{port}/health"), client.get(f"{srv.url}/health")
        assert own.json() == main.json() == {"status": "ok", "instance": "probe-named", "probe_port": port}
