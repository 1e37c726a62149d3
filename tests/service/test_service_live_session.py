"""A session's answer to a robot's scene check agrees with what the frame would have done: `frame_wanted` is None
exactly when `offer_frame` with that frame would change nothing in the session (its three scene memories — the
chosen entry's, the tapped surface's, the pooled views' —, its tap features, its embedding queue). Random
sequences of frames drifting across the scene-change threshold, between two scenes, with tap blocks among them,
for a taps model and for a visual one."""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest

from drivers.scene_change import FRAME_CHANGE, THUMBNAIL_SIZE
from drivers.simulated import tap_block
from service.auth import SessionCredentials
from service.live_session import Session
from service.metrics import ServiceMetrics
from service.runtime import load_runtime
from service.settings import Settings
from texture_library.library import Library

STEPS = 60


def _memory(s: Session) -> tuple:
    """What a frame may change in a session."""

    def raw(x: np.ndarray | None) -> bytes | None:
        return None if x is None else x.tobytes()

    return (
        raw(s._chosen_scene),
        raw(s._tapped_scene),
        raw(s._taps),
        raw(s._scene._scene),
        s._scene._taken,
        s.counters.frames_superseded,
    )


def _thumbnails(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """Two scenes; the camera drifts by steps of ⅓ of the threshold (a uniform shift of both halves of a thumbnail
    counts twice in frame_difference) and now and then moves to the other scene."""
    scenes = [rng.uniform(0.2, 0.8, (2, THUMBNAIL_SIZE, THUMBNAIL_SIZE)).astype(np.float32) for _ in range(2)]
    out, k, drift = [], 0, 0.0
    for _ in range(n):
        if rng.random() < 0.1:
            k = 1 - k
        drift = float(np.clip(drift + rng.choice([-1.0, 0.0, 1.0]) * FRAME_CHANGE / 6, -0.1, 0.1))
        out.append(scenes[k] + np.float32(drift))
    return out


async def _replay(settings: Settings, library_dir, seed: int) -> tuple[int, int]:
    """Offer a random sequence to a real session; after each check, assert the parity. (frames wanted, held)."""
    runtime = load_runtime(settings)
    pool = ThreadPoolExecutor(1)

    async def publish(channel: str, event: dict, important: bool) -> None:
        pass

    session = Session(
        "s", "parity", SessionCredentials("r", "o"), runtime, settings, pool, publish, ServiceMetrics(), lambda s: None
    )
    rng = np.random.default_rng(seed)
    library = Library.load(library_dir)
    taps = tap_block(library.model(library.ids[0]))
    gray = rng.uniform(0, 1, (64, 64))
    wanted = held = 0
    for i, thumb in enumerate(_thumbnails(rng, STEPS)):
        if runtime.needs_taps and rng.random() < 0.15:
            session.ingest(replace(taps, seq=i), 0)
        why = session.frame_wanted(thumb)
        before = _memory(session)
        outcome = session.offer_frame(gray, thumb)
        changed = _memory(session) != before or outcome in ("embedding", "superseded")
        assert (why is not None) == changed, f"step {i}: scene check {why!r}, offer_frame {outcome!r}"
        wanted += why is not None
        held += why is None
        await asyncio.sleep(0)  # let an embedding job start, as the loop would between requests
    if session._embedder is not None:
        await session._embedder
    pool.shutdown()
    return wanted, held


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_scene_check_of_a_taps_session_answers_as_its_frame_would_act(taps_model, library_dir, seed):
    settings = Settings(model_path=taps_model, library_dir=library_dir, api_keys="k")
    wanted, held = asyncio.run(_replay(settings, library_dir, seed))
    assert wanted > 3 and held > 3  # both answers were put to the test


def test_the_scene_check_of_a_visual_session_answers_as_its_frame_would_act(calibrated_visual_model, library_dir):
    m = calibrated_visual_model
    paths = {"model_path": m.model, "tactile_model_path": m.tactile, "backbone_path": m.backbone}
    settings = Settings(**paths, library_dir=library_dir, api_keys="k")
    wanted, held = asyncio.run(_replay(settings, library_dir, 0))
    assert wanted > 3 and held > 3
