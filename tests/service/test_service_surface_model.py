"""A session's learnt surface model on a real server: learnt from the robot's stream, served as `session:<id>` through
the ETag fetch with the session's operator token (or a fleet key) only, named by the window events, a version at most
once a second; bad input keeps the library pick and is told once."""

from __future__ import annotations

import json
import threading
import time
from types import SimpleNamespace

import httpx
import numpy as np
import pytest
from websockets.sync.client import connect

from benchmarks.surface_model import known_texture
from models.tactile.surface_fit import FitStatus
from service import cli
from service.events import StatusEvent, WindowEvent
from service.surface_models import SessionSurface
from texture_library.library import Library
from texture_library.recording import Recording, recording_from_stroke
from texture_library.render_model import RenderModel, parse_render_model
from texture_library.spectrum import spectral_distance_db
from texture_library.stroke import GRAVITY, stroke
from texture_library.trajectory import freehand, model_ranges
from texture_library.vibration import VibrationModel

#: seconds of stroking streamed (kept small: the host is busy)
STROKE_S = 5.0
NOISE_STD = 0.05  # m/s² per axis: the stroke's accelerometer noise (texture_library.stroke's default)


def _auth(token: str) -> dict:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture(scope="module")
def surface_server(kit, base_settings):
    settings = base_settings.model_copy(update={"instance_id": "test-surface", "surface_model": True})
    with kit.running(settings) as srv:
        yield srv


@pytest.fixture(scope="module")
def unseen() -> VibrationModel:
    return known_texture()


def _stroke(model, seconds: float, seed: int = 7, hover_s: float = 0.5) -> Recording:
    """The robot hovering `hover_s` (gravity and the accelerometer's noise: the noise floor), then stroking."""
    rng = np.random.default_rng(seed)
    traj = freehand(seconds, rng, rate_hz=model.rate_hz, **model_ranges(model.max_speed, model.max_force))
    s = stroke(model, traj, rng)
    n = int(hover_s * model.rate_hz)
    hover = np.array([0.0, 0.0, GRAVITY]) + NOISE_STD * rng.standard_normal((n, 3))
    return recording_from_stroke(
        np.concatenate([hover, s.accel]),
        np.concatenate([0.01 * rng.standard_normal((n, 3)), s.force]),
        np.concatenate([np.zeros(n), s.speed]),
        s.rate_hz,
    )


def _stream(kit, client, session, rec: Recording, events, pace: float = 2.0) -> tuple[list, list, float]:
    """Post the recording's blocks at `pace` × real time while a thread reads the session's events; → (window
    events, status events, wall seconds from the first block to the last window)."""
    windows: list[WindowEvent] = []
    statuses: list[StatusEvent] = []
    done = threading.Event()

    def read() -> None:
        while not done.is_set():
            try:
                event = json.loads(events.recv(timeout=0.5))
            except TimeoutError:
                continue
            if event["type"] == "window":
                windows.append(WindowEvent.model_validate(event))
            else:
                statuses.append(StatusEvent.model_validate(event))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    start = time.monotonic()
    try:
        for i, block in enumerate(kit.recording_blocks(rec)):
            assert kit.post_block(client, session, block).status_code == 202
            lag = start + (i + 1) * 0.02 / pace - time.monotonic()
            if lag > 0:
                time.sleep(lag)

        def all_published() -> bool:
            status = kit.session_status(client, session)
            return status["windows_ready"] == 0 and status["counters"]["windows"] == len(windows)

        kit.wait_for(all_published, timeout_s=60, every_s=0.5)
        time.sleep(1.0)  # a status event told after the last window
    finally:
        done.set()
        reader.join(timeout=5)
    return windows, statuses, time.monotonic() - start


@pytest.fixture(scope="module")
def learnt(kit, surface_server, unseen) -> SimpleNamespace:
    """A session that stroked the known texture, its events, and a client of the server."""
    client = httpx.Client(base_url=surface_server.url, timeout=10)
    session = kit.create_session(client, name="robot-7 on the known texture")
    with connect(kit.socket_url(surface_server, session, "events")) as events:
        assert json.loads(events.recv(timeout=5))["event"] == "subscribed"
        windows, statuses, wall_s = _stream(kit, client, session, _stroke(unseen, STROKE_S), events, pace=1.0)
    yield SimpleNamespace(client=client, session=session, windows=windows, statuses=statuses, wall_s=wall_s)
    client.close()


def test_the_session_learns_its_surface_and_serves_it(kit, learnt, unseen, library_dir):
    library = Library.load(library_dir)
    assert all(spectral_distance_db(library.model(e), unseen) > 10.0 for e in library.ids)  # no entry is it
    client, session, windows, statuses = learnt.client, learnt.session, learnt.windows, learnt.statuses
    sid = session["session_id"]
    entry = f"session:{sid}"
    served = [w for w in windows if w.chosen == entry]
    assert served, [w.chosen for w in windows]
    # before the first version the library's pick; beneath every learnt one, too
    first = windows.index(served[0])
    assert first > 0 and all(w.chosen in library.ids and w.library_pick is None for w in windows[:first])
    assert all(w.library_pick in library.ids for w in served)
    assert all(w.chosen == entry for w in windows[first:])  # no scene change: it stays
    versions = list(dict.fromkeys(w.chosen_model_version for w in served))
    assert len(versions) <= 1 + learnt.wall_s  # at most one version a second
    assert not [s for s in statuses if s.event == "surface_model"]  # good input: nothing to tell

    url = f"/library/{entry}/model?session={sid}"
    r = client.get(url, headers=_auth(session["operator_token"]))
    assert r.status_code == 200, r.text
    doc = parse_render_model(r.content)
    assert doc.id == entry and r.headers["etag"] == f'"{doc.model_version}"'
    status = kit.session_status(client, session)["surface_model"]
    assert status["model_version"] == doc.model_version
    # the last window named the served version, unless a fit after the last job sent one more (the next window
    # would name it)
    assert (status["versions"], doc.model_version) == (len(versions), versions[-1]) or (
        status["versions"] == len(versions) + 1 and doc.model_version not in versions
    )
    again = client.get(url, headers={**_auth(session["operator_token"]), "If-None-Match": r.headers["etag"]})
    assert again.status_code == 304
    assert client.get(f"/library/{entry}/model", headers=kit.FLEET).content == r.content  # the fleet's key
    assert status["contact_s"] > 0.0 and status["prior"] in library.ids
    assert status["noise_source"] == "contact-free blocks"  # the robot's hovering
    # every version came from an ok fit, each of which measured what the operators then held against it
    assert status["held_gap_fits"] >= status["versions"]
    assert 0 <= status["held_gap_db_mean"] <= status["held_gap_db_max"]

    # the surface's own model is closer to the stroked texture than the library entry it started from
    model, prior = doc.to_vibration_model(), library.model(status["prior"])
    learnt_db, prior_db = spectral_distance_db(model, unseen), spectral_distance_db(prior, unseen)
    assert learnt_db < prior_db, (learnt_db, prior_db)


def test_only_its_operator_token_or_a_fleet_key_opens_it(kit, learnt):
    client, session = learnt.client, learnt.session
    sid = session["session_id"]
    entry = f"session:{sid}"
    other = kit.create_session(client)
    refused = [
        (f"/library/{entry}/model?session={sid}", {}, 401),
        (f"/library/{entry}/model?session={sid}", _auth("not-a-token"), 401),
        (f"/library/{entry}/model?session={sid}", _auth(session["robot_token"]), 403),
        (f"/library/{entry}/model?session={other['session_id']}", _auth(other["operator_token"]), 403),
        (f"/library/{entry}/model", _auth(session["operator_token"]), 401),  # a session token needs its session
        (f"/library/session:{other['session_id']}/model", kit.FLEET, 404),  # no version out yet
        ("/library/session:test-surface.nope/model", kit.FLEET, 404),  # no such session
    ]
    for u, headers, status in refused:
        got = client.get(u, headers=headers)
        assert got.status_code == status, (u, got.text)
        assert got.json()["detail"]


def test_library_add_from_session_round_trips_with_its_provenance(kit, learnt, surface_server, tmp_path, capsys):
    session = learnt.session
    sid = session["session_id"]
    served = learnt.client.get(f"/library/session:{sid}/model", headers=kit.FLEET)
    doc = parse_render_model(served.content)
    status = kit.session_status(learnt.client, session)["surface_model"]
    out = tmp_path / "learnt-library"
    argv = ["library", "add", "--from-session", surface_server.url, sid, "--library", str(out)]
    assert cli.main([*argv, "--token", session["operator_token"]]) == 0, capsys.readouterr()
    lib = Library.load(out)
    (entry,) = lib.entries
    # the saved model is the served one: the same content hash
    assert RenderModel.from_vibration_model(entry.id, lib.model(entry.id)).model_version == doc.model_version
    assert entry.ratings_source == "predicted" and np.all(np.abs(entry.ratings) <= 100)
    for what in (sid, "robot-7 on the known texture", doc.model_version, f"{status['contact_s']} s of contact"):
        assert what in entry.provenance, (what, entry.provenance)
    assert f"{status['segments']} segments" in entry.provenance and status["prior"] in entry.provenance
    # a second save under the same id is refused, naming it; the robot's token cannot read the model
    assert cli.main([*argv, "--token", session["operator_token"]]) == 2
    assert f"already holds {entry.id!r}" in capsys.readouterr().err
    assert cli.main([*argv, "--id", "other", "--token", session["robot_token"]]) == 2
    assert "403" in capsys.readouterr().err
    assert Library.load(out).ids == [entry.id]


def test_a_clipping_accelerometer_keeps_the_library_pick_and_is_told_once(kit, surface_server, unseen):
    rec = _stroke(unseen, 3.0, seed=8, hover_s=0.0)
    a = rec.accel.data
    lo, hi = np.percentile(a, 20, axis=0), np.percentile(a, 80, axis=0)  # a saturated sensor, every block
    rec = Recording(accel=type(rec.accel)(np.clip(a, lo, hi), rec.accel.rate_hz), force=rec.force, speed=rec.speed)
    with httpx.Client(base_url=surface_server.url, timeout=10) as client:
        session = kit.create_session(client)
        with connect(kit.socket_url(surface_server, session, "events")) as events:
            assert json.loads(events.recv(timeout=5))["event"] == "subscribed"
            windows, statuses, _ = _stream(kit, client, session, rec, events, pace=4.0)
    told = [s for s in statuses if s.event == "surface_model"]
    assert len(told) == 1, [(s.message, s.model_extra) for s in told]
    assert told[0].model_extra["reason"] == "clipping" and "clipping" in told[0].message
    assert windows and not [w for w in windows if w.chosen.startswith("session:")]


def test_a_scene_change_drops_the_served_model_and_is_told_once(unseen, library_dir):
    """SessionSurface alone: a camera frame of another surface takes the served version away at once; a fit that was
    running on the old surface is not served; the fitter restarts from the prior and says so once."""
    prior = Library.load(library_dir).model("synth_000")
    rec = _stroke(unseen, 2.0)
    surface = SessionSurface("test-surface.unit")
    channels = {"accel": rec.accel, "force": rec.force, "speed": rec.speed}
    surface.feed(0, channels)
    outcome = surface.fit(prior, 10.0, "synth_000")
    assert outcome.status is FitStatus.ok and outcome.served is not None
    surface.served = outcome.served
    stale = surface.fit(prior, 20.0, "synth_000")  # (imperceptible or not, it is of this surface)
    surface.scene_changed()
    assert surface.served is None and stale.generation != surface.generation
    after = surface.fit(prior, 30.0, "synth_000")
    assert after.status is FitStatus.scene_change and after.served is None and surface.segments == 0
    assert surface.untold() == [FitStatus.scene_change] and surface.untold() == []
