"""Who may do what: robot tokens write, operator tokens read, no token reaches another session."""

from __future__ import annotations

import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from drivers.blocks import BINARY_CONTENT_TYPE, encode_binary
from drivers.protocol import SCENE_CONTENT_TYPE, Close
from drivers.scene_change import THUMBNAIL_BYTES


@pytest.fixture
def two_sessions(kit, client):
    return kit.create_session(client, "a"), kit.create_session(client, "b")


def _requests(kit, library_dir, sid):
    block = encode_binary(kit.recording_blocks(kit.stroke_recording(library_dir, "synth_000", 0.1))[0])
    return {
        "blocks": (
            "POST",
            f"/sessions/{sid}/blocks",
            {"content": block, "headers": {"Content-Type": BINARY_CONTENT_TYPE}},
        ),
        "frames": ("POST", f"/sessions/{sid}/frames", {"content": kit.png(), "headers": {"Content-Type": "image/png"}}),
        "scene": (
            "POST",
            f"/sessions/{sid}/scene",
            {"content": bytes(THUMBNAIL_BYTES), "headers": {"Content-Type": SCENE_CONTENT_TYPE}},
        ),
        "status": ("GET", f"/sessions/{sid}", {}),
    }


def _call(client, request, token):
    method, path, kwargs = request
    headers = dict(kwargs.get("headers", {}))
    if token is not None:
        headers["Authorization"] = f"Bearer {token}"
    return client.request(method, path, content=kwargs.get("content"), headers=headers)


@pytest.mark.parametrize(
    "what, allowed_role", [("blocks", "robot"), ("frames", "robot"), ("scene", "robot"), ("status", "operator")]
)
def test_each_route_opens_only_to_its_role(kit, client, library_dir, two_sessions, what, allowed_role):
    a, b = two_sessions
    request = _requests(kit, library_dir, a["session_id"])[what]
    other_role = "operator" if allowed_role == "robot" else "robot"
    ok = _call(client, request, a[f"{allowed_role}_token"])
    assert ok.status_code in (200, 202), ok.text
    missing = _call(client, request, None)
    assert missing.status_code == 401 and "missing token" in missing.json()["detail"]
    assert missing.headers["www-authenticate"] == "Bearer"
    wrong_role = _call(client, request, a[f"{other_role}_token"])
    article = "an" if other_role == "operator" else "a"
    assert wrong_role.status_code == 403 and f"{article} {other_role} token cannot" in wrong_role.json()["detail"]
    for token in (b["robot_token"], b["operator_token"], "not-a-token"):  # another session's tokens
        r = _call(client, request, token)
        assert r.status_code == 401 and "not valid for session" in r.json()["detail"]
    unknown = _call(client, _requests(kit, library_dir, "test-a.nosuchsession")[what], a[f"{allowed_role}_token"])
    assert unknown.status_code == 404 and "no session" in unknown.json()["detail"]


def test_delete_takes_either_token_of_its_own_session(kit, client, two_sessions):
    a, b = two_sessions
    assert client.delete(f"/sessions/{a['session_id']}").status_code == 401
    assert (
        client.delete(
            f"/sessions/{a['session_id']}", headers={"Authorization": f"Bearer {b['robot_token']}"}
        ).status_code
        == 401
    )
    r = client.delete(f"/sessions/{a['session_id']}", headers={"Authorization": f"Bearer {a['robot_token']}"})
    assert r.status_code == 200 and r.json()["state"] == "ended"
    r = client.delete(f"/sessions/{b['session_id']}", headers={"Authorization": f"Bearer {b['operator_token']}"})
    assert r.status_code == 200
    gone = client.get(f"/sessions/{a['session_id']}", headers={"Authorization": f"Bearer {a['operator_token']}"})
    assert gone.status_code == 404


def test_event_socket_refuses_robot_and_foreign_tokens_at_the_handshake(server, two_sessions):
    a, b = two_sessions
    base = f"{server.ws_url}/sessions/{a['session_id']}/events"
    for query, status in (("", 401), (f"?token={a['robot_token']}", 403), (f"?token={b['operator_token']}", 401)):
        with pytest.raises(InvalidStatus) as err:
            connect(base + query)
        assert err.value.response.status_code == status
    with pytest.raises(InvalidStatus) as err:
        connect(f"{server.ws_url}/sessions/test-a.nosuchsession/events?token={a['operator_token']}")
    assert err.value.response.status_code == 404
    with connect(f"{base}?token={a['operator_token']}") as ok:
        assert '"subscribed"' in ok.recv(timeout=5)


def test_ingest_socket_closes_1008_on_a_bad_token(server, two_sessions):
    a, b = two_sessions
    base = f"{server.ws_url}/sessions/{a['session_id']}/ingest"
    for query in ("", f"?token={a['operator_token']}", f"?token={b['robot_token']}"):
        with connect(base + query) as ws:
            with pytest.raises(ConnectionClosed):
                ws.recv(timeout=5)
            assert ws.close_code == Close.POLICY
    with pytest.raises(InvalidStatus) as err:  # unknown session: refused at the handshake
        connect(f"{server.ws_url}/sessions/test-a.nosuchsession/ingest?token={a['robot_token']}")
    assert err.value.response.status_code == 404


def test_a_token_never_begins_with_a_dash(monkeypatch):
    """`hapticlink operator --token -abc…` would be read as an option: such a draw is drawn again."""
    import secrets

    from service.auth import new_token

    draws = iter(["-starts-with-a-dash", "fine-token"])
    monkeypatch.setattr(secrets, "token_urlsafe", lambda n: next(draws))
    assert new_token() == "fine-token"


def test_metrics_open_only_to_the_metrics_token(kit, client, two_sessions):
    """GET /metrics answered anyone: session counts, refusals and load, to any client that could reach the port. The
    scraper's token reads it; nothing else does, not even the fleet key (it opens sessions, a scraper needs not)."""
    a, _ = two_sessions
    for method in ("GET", "HEAD"):
        ok = client.request(method, "/metrics", headers=kit.SCRAPER)
        assert ok.status_code == 200, (method, ok.text)
        missing = client.request(method, "/metrics")
        assert missing.status_code == 401 and missing.headers["www-authenticate"] == "Bearer", method
        for token in (kit.API_KEY, a["robot_token"], a["operator_token"], "not-a-token"):
            refused = client.request(method, "/metrics", headers={"Authorization": f"Bearer {token}"})
            assert refused.status_code == 401, (method, token)
    assert "HAPTICLINK_METRICS_TOKEN" in client.get("/metrics").json()["detail"]
    assert "not valid" in client.get("/metrics", headers=kit.FLEET).json()["detail"]
    assert "hapticlink_sessions_active" in client.get("/metrics", headers=kit.SCRAPER).text


def test_metrics_are_closed_while_no_metrics_token_is_configured(kit, base_settings):
    """Secure by default: with no token set, no credential opens /metrics, and the refusal says which setting to set."""
    import httpx

    settings = base_settings.model_copy(update={"metrics_token": None, "instance_id": "no-scrape"})
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        for headers in (None, kit.SCRAPER, kit.FLEET):
            for method in ("GET", "HEAD"):
                r = client.request(method, "/metrics", headers=headers)
                assert r.status_code == 403, (method, headers, r.text)
        assert "HAPTICLINK_METRICS_TOKEN" in client.get("/metrics").json()["detail"]
