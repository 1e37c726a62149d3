"""The entry to render on a real server: the selection rule's reason in every window event, and a steady
stroke that does not flip the choice.

A steady stroke (constant speed and force over one library texture) for a minute, sent in 100 ms blocks;
the choice may settle during the session's first windows (`hysteresis_settle_windows`: the smoothed
estimate is still converging), and from then on it must not change: 0 flips per minute.
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
