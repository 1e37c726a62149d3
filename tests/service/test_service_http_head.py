"""HEAD on a real uvicorn: every GET route answers it with the GET's status and headers and no body, behind the
same credentials; a route without GET still says which methods it has."""

from __future__ import annotations

import httpx

from tests.service.conftest import FLEET, SCRAPER, create_session


def _same_head(client: httpx.Client, path: str, headers: dict[str, str] | None = None) -> httpx.Response:
    """HEAD `path` beside its GET: the same status and content type, no body, and a Content-Length that is the
    GET's (a live document — a session's status, the metrics — may change by a few bytes between the two)."""
    got = client.get(path, headers=headers)
    head = client.head(path, headers=headers)
    assert head.status_code == got.status_code, path
    assert head.content == b"", path
    assert head.headers.get("content-type") == got.headers.get("content-type"), path
    if "content-length" in got.headers:
        assert abs(int(head.headers["content-length"]) - len(got.content)) <= 16, path
    return head


def test_every_get_route_answers_head_without_a_body(client):
    session = create_session(client)
    operator = {"Authorization": f"Bearer {session['operator_token']}"}
    entry = client.get("/library", headers=FLEET).json()["entries"][0]["id"]
    for path, headers in [
        ("/library", FLEET),
        (f"/library/{entry}/model", FLEET),
        ("/metrics", SCRAPER),
        (f"/sessions/{session['session_id']}", operator),
        ("/console", None),
        ("/console/render-worklet.js", None),
    ]:
        assert _same_head(client, path, headers).status_code == 200, path


def test_head_needs_the_credential_its_get_needs(client):
    session = create_session(client)
    path = f"/sessions/{session['session_id']}"
    for headers in (None, {"Authorization": f"Bearer {session['robot_token']}"}):  # none, the wrong role
        head = _same_head(client, path, headers)
        assert head.status_code in (401, 403), headers
    assert _same_head(client, path, {"Authorization": f"Bearer {session['operator_token']}"}).status_code == 200


def test_head_on_a_route_without_get_is_405_naming_its_methods(client):
    head = client.head("/sessions", headers=FLEET)
    assert head.status_code == 405 and head.content == b""
    assert "POST" in head.headers["allow"]
