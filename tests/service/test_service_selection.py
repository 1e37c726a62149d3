"""The entry to render on a real server: the selection rule's reason in every window event, and a steady
stroke that does not flip the choice.

A steady stroke (constant speed and force over one library texture) for a minute, sent in 100 ms blocks;
the choice may settle during the session's first windows (`hysteresis_settle_windows`: the smoothed
estimate is still converging), and from then on it must not change: 0 flips per minute.

A real surface change (the stream goes on over the library entry furthest away in rating space) switches the
choice with at most 2 windows held by hysteresis (the cumulative lead releases it), and with none when the
camera's frame of the new surface comes first (a new scene: the chooser settles again).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from websockets.sync.client import connect

from service.events import WindowEvent
from texture_library.library import Library
from texture_library.recording import recording_from_stroke
from texture_library.stroke import stroke
from texture_library.trajectory import Trajectory

STROKE_S = 60.0


def steady_recording(library_dir, entry_id: str, seed: int):
    """STROKE_S of stroking one entry at a constant 30 % of its speed range and 40 % of its force range."""
    model = Library.load(library_dir).model(entry_id)
    n = int(STROKE_S * model.rate_hz)
    speed = np.full(n, 0.3 * model.max_speed)
    force = np.full(n, 0.4 * model.max_force)
    trajectory = Trajectory(speed, force, np.cumsum(speed) / model.rate_hz, model.rate_hz)
    s = stroke(model, trajectory, np.random.default_rng(seed))
    return recording_from_stroke(s.accel, s.force, s.speed, s.rate_hz)


def flips_per_minute(windows: list[dict], settle: int) -> float:
    chosen = [w["chosen"] for w in windows[settle:]]
    flips = sum(a != b for a, b in zip(chosen, chosen[1:]))
    return flips / (len(windows) * 0.5 / 60.0)


@pytest.mark.parametrize(("entry", "seed"), [("synth_001", 1), ("synth_004", 2)])
def test_a_steady_stroke_does_not_flip_the_choice(kit, server, client, library_dir, base_settings, entry, seed):
    rec = steady_recording(library_dir, entry, seed)
    blocks = kit.recording_blocks(rec, block_s=0.1)
    session = kit.create_session(client)
    expected = int(STROKE_S / 0.5)
    with connect(kit.socket_url(server, session, "events")) as sub:
        sub.recv(timeout=5)
        windows: list[dict] = []
        for block in blocks:
            assert kit.post_block(client, session, block).status_code == 202
        while len(windows) < expected:
            event = json.loads(sub.recv(timeout=30))
            if event["type"] == "window":
                windows.append(event)
    for w in windows:
        WindowEvent.model_validate(w)
        sel = w["selection"]
        assert sel["rule"] == base_settings.selection_rule
        assert sel["reason"] and sel["switch_margin"] is not None and sel["switch_margin"] >= 0
    settle = base_settings.hysteresis_settle_windows
    assert flips_per_minute(windows, settle) == 0, [w["chosen"] for w in windows]
    # the settling windows follow the rule without hysteresis, and say so
    assert all(not w["selection"]["held_by_hysteresis"] for w in windows[:settle])
    assert all("settling" in w["selection"]["reason"] for w in windows[:settle])


# ---- a real surface change ----------------------------------------------------------------------------
SURFACE_S = 20.0  # each surface is stroked this long, in one stream without a gap


def far_apart(library_dir) -> tuple[str, str]:
    """The two library entries furthest apart in rating space: a surface change the choice must follow."""
    lib = Library.load(library_dir)
    r = np.asarray(lib.ratings, float)
    d = np.linalg.norm(r[:, None] - r[None], axis=-1)
    i, j = np.unravel_index(int(np.argmax(d)), d.shape)
    return lib.ids[i], lib.ids[j]


def held_before_the_switch(windows: list[dict]) -> int:
    """Windows after the surface change held by hysteresis before the choice first reaches the new surface's
    (the choice of the stream's last window)."""
    after = [w for w in windows if w["t_end_s"] > SURFACE_S + 1e-6]
    final = after[-1]["chosen"]
    held = 0
    for w in after:
        if w["chosen"] == final:
            return held
        held += w["selection"]["held_by_hysteresis"]
    return held


@pytest.mark.parametrize("camera", [False, True], ids=["no camera", "a frame at the change"])
def test_a_surface_change_switches_within_two_windows(kit, server, client, library_dir, base_settings, camera):
    first, second = far_apart(library_dir)
    lib = Library.load(library_dir)
    a = kit.recording_blocks(steady_recording(library_dir, first, 3), block_s=0.1)[: int(SURFACE_S / 0.1)]
    b = kit.recording_blocks(steady_recording(library_dir, second, 4), block_s=0.1, t0=SURFACE_S, seq0=len(a))
    b = b[: int(SURFACE_S / 0.1)]
    session = kit.create_session(client)
    robot = {"Authorization": f"Bearer {session['robot_token']}", "Content-Type": "image/png"}
    frames = f"/sessions/{session['session_id']}/frames"
    windows: list[dict] = []

    def collect(sub, until_s: float) -> None:
        while not windows or windows[-1]["t_end_s"] < until_s - 1e-6:
            event = json.loads(sub.recv(timeout=30))
            if event["type"] == "window":
                windows.append(event)

    with connect(kit.socket_url(server, session, "events")) as sub:
        sub.recv(timeout=5)
        if camera:
            assert client.post(frames, content=lib.image(first), headers=robot).status_code == 202
        for block in a:
            assert kit.post_block(client, session, block).status_code == 202
        collect(sub, SURFACE_S)  # every window of the first surface is chosen before the camera shows the second
        before = windows[-1]["chosen"]
        if camera:
            assert client.post(frames, content=lib.image(second), headers=robot).status_code == 202
        for block in b:
            assert kit.post_block(client, session, block).status_code == 202
        collect(sub, 2 * SURFACE_S)
    after = windows[-1]["chosen"]
    assert after != before, [w["chosen"] for w in windows]
    held = held_before_the_switch(windows)
    assert held <= (0 if camera else 2), [(w["chosen"], w["selection"]["reason"]) for w in windows]
    # once switched, the new surface's steady stroke keeps its choice
    tail = [w["chosen"] for w in windows if w["t_end_s"] > SURFACE_S + 5.0]
    assert len(set(tail)) == 1, tail
