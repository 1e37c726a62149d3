"""A session's learnt surface model saved into a texture library, with where it came from.

`hapticlink library add --from-session URL SESSION --token T --library DIR` reads the session's status
(`GET /sessions/{id}`: the served version, the contact seconds and segments it was learnt from, its prior, the
session's ratings) and its model (`GET /library/session:<id>/model`, the session's operator token), and adds it to
the library at DIR (a new library when DIR holds none). The entry's ratings are the service's estimate
(`ratings_source` "predicted"); its provenance names the service, session, its name (the robot's, as it opened the
session), the version, the time and what the model was learnt from. HTTP lives here, not in texture_library, which
talks to nothing.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

import httpx
import numpy as np

from texture_library.attributes import ATTRIBUTES
from texture_library.library import Library, LibraryEntry, add_entry
from texture_library.render_model import parse_render_model
from texture_library.vibration import VibrationModel

TIMEOUT_S = 10.0


@dataclass(frozen=True)
class SessionModel:
    """What the service says of a session's learnt model: the model, its version, the session's status."""

    model: VibrationModel
    version: str
    status: dict


def fetch_session_model(url: str, session_id: str, token: str, client: httpx.Client | None = None) -> SessionModel:
    """The session's served surface model and status; ValueError naming the problem (no version out yet, the
    surface model off, a refused token, the version changing between the two requests)."""
    own = client is None
    http = client or httpx.Client(base_url=url.rstrip("/"), timeout=TIMEOUT_S)
    headers = {"Authorization": f"Bearer {token}"}
    try:
        for _ in range(3):  # a new version between the two requests: read both again
            status = _get(http, f"/sessions/{quote(session_id, safe='')}", headers).json()
            surface = status.get("surface_model")
            if surface is None:
                raise ValueError(f"session {session_id} learns no surface model (the service runs without it)")
            if surface.get("model_version") is None:
                raise ValueError(f"session {session_id} has no learnt surface model out yet: stroke the surface first")
            r = _get(http, f"/library/{quote(surface['id'], safe='')}/model", headers, {"session": session_id})
            doc = parse_render_model(r.content)
            if doc.model_version == surface["model_version"]:
                return SessionModel(doc.to_vibration_model(), doc.model_version, status)
        raise ValueError(f"session {session_id}'s surface model kept changing while it was read: try again")
    finally:
        if own:
            http.close()


def _get(http: httpx.Client, path: str, headers: dict, params: dict | None = None) -> httpx.Response:
    try:
        r = http.get(path, headers=headers, params=params)
    except httpx.HTTPError as exc:
        raise ValueError(f"GET {path}: the request failed ({type(exc).__name__}: {exc})") from None
    if r.status_code != 200:
        try:
            detail = r.json().get("detail")
        except ValueError:
            detail = r.text[:200]
        raise ValueError(f"GET {path}: the service answered {r.status_code} ({detail})")
    return r


def entry_id_for(session_id: str) -> str:
    """A library id for a session's model: `session-` and the session id with anything else than letters, digits,
    _ . - replaced by -."""
    return "session-" + re.sub(r"[^A-Za-z0-9_.-]", "-", session_id)


def save_to_library(
    fetched: SessionModel,
    library_dir: str | Path,
    url: str,
    entry_id: str | None = None,
    name: str | None = None,
    group: str = "learnt",
) -> LibraryEntry:
    """Add the fetched model to the library at library_dir (created when it holds none); ValueError when the id is
    taken or the session has no ratings yet."""
    root = Path(library_dir)
    status = fetched.status
    surface = status["surface_model"]
    sid = status["session_id"]
    entry_id = entry_id or entry_id_for(sid)
    ratings = surface.get("ratings")
    if not ratings:
        raise ValueError(f"session {sid} has no estimate yet: its entry would have no ratings")
    library = Library.load(root) if (root / "library.json").is_file() else None
    if library is not None and entry_id in library.ids:
        raise ValueError(f"library {library.name!r} already holds {entry_id!r}: name another with --id")
    learnt_at = surface.get("learnt_at")
    when = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(learnt_at if learnt_at is not None else time.time()))
    provenance = (
        f"learnt online by {url.rstrip('/')} in session {sid} (name {status.get('name')!r}), version "
        f"{fetched.version} at {when}, from {surface.get('contact_s')} s of contact ({surface.get('segments')} "
        f"segments of 128 samples), prior {surface.get('prior')!r}, noise floor: {surface.get('noise_source')}"
    )
    entry = add_entry(
        root,
        entry_id,
        fetched.model,
        name=name or f"{status.get('name') or sid} (learnt)",
        group=group,
        ratings=np.array([ratings[a] for a in ATTRIBUTES], float),
        ratings_source="predicted",
        provenance=provenance,
        licence="learnt from the robot's own stream",
    )
    entries = [*(library.entries if library is not None else []), entry]
    Library(root, library.name if library is not None else root.name, entries).save()
    return entry
