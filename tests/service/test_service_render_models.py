"""Rendering models served (GET /library/{id}/model), the chosen model's version in window events, and the lean
render feed (?view=render), on a real server."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from drivers import render_feed
from service.events import WindowEvent
from texture_library import model_codec, render_model
from texture_library.library import Library
from texture_library.render_model import RenderModel, parse_render_model


def _auth(token: str) -> dict:
    return {"Authorization": f"Bearer {token}"}


def test_a_model_is_served_with_its_version_as_a_strong_etag(kit, client, library_dir):
    session = kit.create_session(client)
    url = f"/library/synth_001/model?session={session['session_id']}"
    r = client.get(url, headers=_auth(session["operator_token"]))
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/json"
    served = parse_render_model(r.content)
    want = RenderModel.from_vibration_model("synth_001", Library.load(library_dir).model("synth_001"))
    assert served == want
    assert r.headers["etag"] == f'"{want.model_version}"'
    assert r.headers["cache-control"] == "private, no-cache"
    listed = {e["id"]: e["model_version"] for e in client.get("/library", headers=kit.FLEET).json()["entries"]}
    assert listed["synth_001"] == want.model_version and len(set(listed.values())) == len(listed)

    for tag in (r.headers["etag"], f"W/{r.headers['etag']}", f'"0000000000000000", {r.headers["etag"]}', "*"):
        again = client.get(url, headers={**_auth(session["operator_token"]), "If-None-Match": tag})
        assert again.status_code == 304 and again.content == b"" and again.headers["etag"] == r.headers["etag"]
    stale = client.get(url, headers={**_auth(session["operator_token"]), "If-None-Match": '"0000000000000000"'})
    assert stale.status_code == 200 and stale.content == r.content


def test_the_compact_encoding_is_served_on_request(kit, client):
    session = kit.create_session(client)
    url = f"/library/synth_002/model?session={session['session_id']}"
    headers = {**_auth(session["robot_token"]), "Accept": model_codec.CONTENT_TYPE}
    full = parse_render_model(client.get(url, headers=_auth(session["robot_token"])).content)
    r = client.get(url, headers=headers)
    assert r.status_code == 200 and r.headers["content-type"] == model_codec.CONTENT_TYPE
    source, decoded = model_codec.decode(r.content)
    assert source == full.model_version and decoded.id == "synth_002"
    assert r.headers["etag"] == f'"{full.model_version}.hlm3"' and len(r.content) < len(full.to_json_bytes()) / 10
    assert client.get(url, headers={**headers, "If-None-Match": r.headers["etag"]}).status_code == 304


def test_a_model_needs_a_credential(kit, client):
    session = kit.create_session(client)
    sid = session["session_id"]
    cases = [
        (f"/library/synth_001/model?session={sid}", {}, 401),
        (f"/library/synth_001/model?session={sid}", _auth("not-a-token"), 401),
        ("/library/synth_001/model", _auth(session["operator_token"]), 401),  # a session token needs its session
        ("/library/synth_001/model", {}, 401),
        ("/library/synth_001/model?session=test-a.nope", _auth(session["operator_token"]), 404),
        (f"/library/nope/model?session={sid}", _auth(session["operator_token"]), 404),
        ("/library/synth_001/model", kit.FLEET, 200),  # the fleet's key opens the library too
        (f"/library/synth_001/model?session={sid}", _auth(session["robot_token"]), 200),
    ]
    for url, headers, status in cases:
        r = client.get(url, headers=headers)
        assert r.status_code == status, (url, headers, r.text)
        if status != 200:
            assert r.json()["detail"]


def test_window_events_name_the_chosen_models_version_and_the_render_view_is_lean(kit, server, client, library_dir):
    versions = {e["id"]: e["model_version"] for e in client.get("/library", headers=kit.FLEET).json()["entries"]}
    rec = kit.stroke_recording(library_dir, "synth_003", 6.2)
    session = kit.create_session(client)
    with (
        connect(kit.socket_url(server, session, "events")) as full,
        # models fetched, not pushed (tests/service/test_service_model_push.py): the choices and ratings alone
        connect(kit.socket_url(server, session, "events") + "&view=render&models=fetch") as lean,
    ):
        assert json.loads(full.recv(timeout=5))["event"] == "subscribed"
        assert json.loads(lean.recv(timeout=5))["event"] == "subscribed"
        for block in kit.recording_blocks(rec):
            assert kit.post_block(client, session, block).status_code == 202
        windows = []
        while len(windows) < 10:
            event = json.loads(full.recv(timeout=20))
            if event["type"] == "window":
                windows.append(WindowEvent.model_validate(event))
        raw = [lean.recv(timeout=20) for _ in range(10)]
        feed = [render_feed.parse(m) for m in raw]
    assert all(w.chosen_model_version == versions[w.chosen] for w in windows)
    full_bytes = sum(len(w.model_dump_json()) for w in windows)
    # the feed: a choice whenever the chosen entry changes (the first window's included), 4-byte ratings otherwise
    expect_choice = [i == 0 or windows[i].chosen != windows[i - 1].chosen for i in range(10)]
    assert [m.kind == "choice" for m in feed] == expect_choice
    for w, m in zip(windows, feed, strict=True):
        assert m.ratings == tuple(int(np.rint(getattr(w.ratings, a))) for a in type(w.ratings).model_fields)
        if m.kind == "choice":
            assert (m.chosen, m.version) == (w.chosen, w.chosen_model_version)
    # binary throughout; while the choice holds only the 4 rating bytes travel (the first windows may still
    # switch: the selection rule's pick is taken directly while the smoothed estimate settles)
    assert all(isinstance(m, bytes) for m in raw) and any(m.kind == "ratings" for m in feed)
    assert sum(map(len, raw)) * 50 < full_bytes  # ≥ 50× leaner than the full events


def test_a_library_with_a_model_over_the_size_bound_is_not_served(kit, base_settings, monkeypatch):
    monkeypatch.setattr(render_model, "MAX_RENDER_MODEL_BYTES", 1000)
    with kit.running(base_settings.model_copy(update={"instance_id": "test-big"}), wait_ready=False) as srv:

        def loaded() -> dict | None:
            ready = httpx.get(f"{srv.url}/ready").json()
            return None if ready["detail"].startswith("loading") else ready

        detail = kit.wait_for(loaded)
    assert detail["ready"] is False
    assert "entry 'synth_000'" in detail["detail"] and "at most 1000 are served" in detail["detail"]


def test_the_model_route_is_in_the_openapi_document(client):
    doc = client.get("/openapi.json").json()
    op = doc["paths"]["/library/{entry_id}/model"]["get"]
    assert {"200", "304", "401", "404"} <= set(op["responses"])
    schema = op["responses"]["200"]["content"]["application/json"]["schema"]
    assert schema == {"$ref": "#/components/schemas/RenderModel"}
    assert "model_version" in doc["components"]["schemas"]["RenderModel"]["properties"]
    assert "chosen_model_version" in doc["components"]["schemas"]["WindowEvent"]["properties"]


def test_an_unknown_view_is_refused_at_the_handshake(kit, server, client):
    session = kit.create_session(client)
    with pytest.raises(InvalidStatus) as refused:
        connect(kit.socket_url(server, session, "events") + "&view=bogus")
    assert refused.value.response.status_code == 422
    assert b"view must be one of full, render, got 'bogus'" in refused.value.response.body


@pytest.mark.parametrize(
    ("accept", "compact"),
    [
        (None, False),
        ("application/json", False),
        (model_codec.CONTENT_TYPE, True),
        (f"application/json, {model_codec.CONTENT_TYPE}", True),  # named alike: the one asked for by name
        (f"{model_codec.CONTENT_TYPE};q=0.5, application/json", False),  # JSON preferred
        (f"text/html, {model_codec.CONTENT_TYPE};q=0", False),  # q=0: "not this"
        (f"{model_codec.CONTENT_TYPE}XYZ", False),  # another type that merely contains the name
        (f"{model_codec.CONTENT_TYPE.upper()} ; q=0.9, */*;q=0.1", True),
        (f"{model_codec.CONTENT_TYPE};q=x", False),  # an unreadable weight asks for nothing
    ],
)
def test_the_compact_encoding_is_served_only_when_asked_for_by_name(accept, compact):
    from service.routes.library import wants_compact

    assert wants_compact(accept) is compact
