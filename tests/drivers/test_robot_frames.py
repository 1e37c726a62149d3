"""FrameGate: a robot sends a camera frame only when its scene changed (or the refresh is due), and the RobotClient
sends what the gate lets through, against a fake service on loopback."""

from __future__ import annotations

import asyncio
import random

import numpy as np
import pytest

from drivers.blocks import Frame
from drivers.camera import frame_gray, png_bytes
from drivers.robot.frames import FrameGate, frame_thumbnail
from drivers.scene_change import thumbnail, thumbnail_bytes
from drivers.source import blocks_from_arrays

FAST = {"backoff": (0.01, 0.05), "seed": 7}


def _surface(seed: int) -> np.ndarray:
    """A coarse grey texture, (448, 448) float in [0.2, 0.8]."""
    rng = np.random.default_rng(seed)
    return np.kron(rng.uniform(0.2, 0.8, size=(14, 14)), np.ones((32, 32)))


def _photo(surface: np.ndarray, seed: int, noise: float = 0.02) -> bytes:
    """One camera frame of `surface`: sensor noise, 8-bit PNG (bytes differ from frame to frame)."""
    rng = np.random.default_rng(seed)
    return png_bytes(np.clip((surface + rng.normal(0, noise, surface.shape)) * 255, 0, 255).astype(np.uint8))


def test_the_gate_lets_a_new_scene_through_and_holds_back_the_same_one():
    a, other = thumbnail(_surface(0)), thumbnail(_surface(1))
    gate = FrameGate(change=0.015, refresh_s=10.0, jitter=0.0)
    assert gate.admit(a, 0.0), "the first frame goes"
    assert not gate.admit(a, 1.0) and not gate.admit(a + 0.001, 2.0), "the same scene waits"
    assert gate.admit(other, 3.0), "another surface goes"
    assert not gate.admit(other, 12.9)
    assert gate.admit(other, 13.0), "the refresh is due 10 s after the last frame sent"
    assert gate.admit(a, 13.5) and not gate.admit(a, 14.0)
    assert gate.admit(None, 14.5), "an unreadable frame goes: the service says what is wrong with it"
    assert gate.admit(a, 15.0), "and the next readable one too"


def test_robots_started_together_refresh_apart():
    """Each refresh comes 10–12.5 s after the last frame sent, drawn anew: a fleet started at one instant does not
    send its refreshes at one instant."""
    a = thumbnail(_surface(0))
    gates = [FrameGate(change=0.015, refresh_s=10.0, rng=random.Random(k)) for k in range(50)]
    firsts = []
    for gate in gates:
        assert gate.admit(a, 0.0)
        t = next(t for t in np.arange(0.0, 20.0, 0.05) if gate.admit(a, float(t)))
        firsts.append(t)
    assert 10.0 <= min(firsts) and max(firsts) < 12.5 + 0.05
    assert max(firsts) - min(firsts) > 1.5, "the refreshes spread over the jitter's span"
    again = FrameGate(change=0.015, refresh_s=10.0, rng=random.Random(0))
    assert again.admit(a, 0.0) and not again.admit(a, firsts[0] - 0.05) and again.admit(a, firsts[0])  # seeded


def test_the_gate_says_when_the_refresh_is_due():
    a = thumbnail(_surface(0))
    gate = FrameGate(change=0.015, refresh_s=10.0, jitter=0.0)
    assert gate.refresh_at is None, "nothing sent, nothing to refresh"
    assert gate.admit(a, 3.0) and gate.refresh_at == 13.0
    assert not gate.admit(a, 12.999) and gate.admit(a, gate.refresh_at), "due at refresh_at, not a tick later"
    assert gate.refresh_at == 23.0
    jittered = FrameGate(change=0.015, refresh_s=10.0, jitter=0.25, rng=random.Random(3))
    assert jittered.admit(a, 0.0) and 10.0 <= (at := jittered.refresh_at) < 12.5
    assert not jittered.admit(a, at - 1e-6) and jittered.admit(a, at)


def test_change_zero_sends_every_frame_without_reading_it():
    gate = FrameGate(change=0.0)
    assert not gate.reads_frames
    a = thumbnail(_surface(0))
    assert all(gate.admit(a, t) for t in (0.0, 0.1, 0.2)), "even the same frame, again and again"
    assert FrameGate().reads_frames


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"change": -0.1}, "frame change must lie in"),
        ({"change": 2.5}, "frame change"),
        ({"refresh_s": 0}, "refresh"),
        ({"jitter": 1.5}, "jitter"),
    ],
)
def test_the_gate_refuses_bad_settings(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FrameGate(**kwargs)


def test_frame_thumbnail_is_the_thumbnail_of_the_decoded_frame():
    grey = (np.arange(64 * 48, dtype=np.uint32).reshape(48, 64) % 256).astype(np.uint8)
    png = png_bytes(grey)
    np.testing.assert_array_equal(frame_gray(png), grey.astype(np.float32) / 255)
    np.testing.assert_allclose(frame_thumbnail(png), thumbnail(grey.astype(np.float32) / 255), atol=1e-6)
    assert frame_thumbnail(b"\x89PNG\r\n\x1a\nnot an image") is None
    with pytest.raises(ValueError, match="not a readable image"):
        frame_gray(b"nothing")


@pytest.mark.parametrize("change", [0.015, 0.0])
def test_the_robot_sends_a_frame_when_its_scene_changes(kit, fake_service, change):
    a, b = _surface(0), _surface(1)
    photos = [_photo(a, 1), _photo(a, 2), _photo(a, 3), _photo(b, 4), _photo(b, 4), _photo(a, 5)]
    assert len(set(photos[:3])) == 3, "every frame of one surface is its own bytes, as from a camera"
    arrays = kit.stroke_arrays(600, seed=4)
    blocks = list(blocks_from_arrays(arrays, 0.1))
    items = [x for pair in zip(blocks, (Frame(0.1 * i, p, "image/png") for i, p in enumerate(photos))) for x in pair]
    stats = kit.stream(fake_service.app, items, frame_change=change, frame_refresh_s=60, **FAST)
    sent = [body for _, body in fake_service.only_session().frames]
    assert stats.frames_read == 6 and stats.acked == len(blocks)
    if change:
        assert sent == [photos[0], photos[3], photos[5]], "a, then b, then a again"
        assert stats.frames_sent == 3 and stats.frames_unchanged == 3
    else:  # every frame is queued; the source reads faster than the session opens, so older ones are superseded
        assert sent[-1] == photos[-1] and sent == sorted(sent, key=photos.index) and stats.frames_unchanged == 0
        assert stats.frames_sent + stats.frames_dropped == 6


@pytest.mark.parametrize("held", [True, False])
def test_the_refresh_goes_on_time_and_sends_the_frame_only_if_the_service_lacks_its_scene(kit, fake_service, held):
    """A camera that sent one frame and stopped: each time the refresh is due (a timer, not the camera's next frame),
    the client asks the service with that frame's thumbnail, and sends the frame again only when the answer wants it;
    it stops refreshing when the stream ends."""
    from drivers.robot import RobotClient

    fake_service.scene_held = held
    photo = _photo(_surface(0), 1)
    blocks = list(blocks_from_arrays(kit.stroke_arrays(1200, seed=4), 0.05))  # 1.2 s of stream, paced
    items = [Frame(0.0, photo, "image/png"), *blocks]

    async def main():
        server = kit.LoopbackServer(fake_service.app)
        await server.start()
        try:
            client = RobotClient(server.url, kit.ListSource(items, realtime=True), frame_refresh_s=0.2, **FAST)
            return await client.run()
        finally:
            await server.stop()

    stats = asyncio.run(main())
    session = fake_service.only_session()
    sent = [body for _, body in session.frames]
    assert stats.frames_read == 1 and stats.acked == len(blocks)
    # refreshes 0.2–0.25 s apart over 1.2 s: 4–6 (2 fewer leave room for a slow machine); none would mean the
    # refresh waited for a camera frame that never came
    assert 3 <= len(session.scene_checks) <= 6, len(session.scene_checks)
    assert set(session.scene_checks) == {thumbnail_bytes(frame_thumbnail(photo))}
    if held:
        assert sent == [photo] and stats.refreshes_held == len(session.scene_checks)
    else:
        assert sent == [photo] * (1 + len(session.scene_checks)) and stats.refreshes_held == 0
    assert stats.frames_sent == len(sent)
