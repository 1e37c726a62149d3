"""The texture library: the entries (ids, names, ratings) and each entry's rendering model."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Header, Path, Query
from fastapi.responses import Response

from service.auth import EITHER, OPERATOR_ONLY
from service.deps import ReadyRuntime, State, Token
from service.errors import ServiceError, session_not_found
from service.render_models import ServedRenderModel
from service.routes.common import errors
from service.schemas import LibraryEntryOut, LibraryOut
from service.surface_models import SESSION_PREFIX
from texture_library.model_codec import CONTENT_TYPE as COMPACT_CONTENT_TYPE
from texture_library.model_codec import MAGIC as COMPACT_MAGIC
from texture_library.render_model import MAX_RENDER_MODEL_BYTES, RenderModel

router = APIRouter(tags=["library"])

#: a served model never changes under its version, but the entry behind a URL may (another library after a
#: restart): caches keep it and revalidate every use (If-None-Match → 304, no body)
CACHE_CONTROL = "private, no-cache"


@router.get(
    "/library",
    response_model=LibraryOut,
    responses=errors(401, 403, 404, 410, 422, 503),
    summary="The texture library: ids, names, groups, ratings and each entry's model_version (a session's robot or "
    "operator token with ?session=, or a fleet API key)",
)
async def library(_: LibraryReader, runtime: ReadyRuntime) -> LibraryOut:
    lib = runtime.library
    return LibraryOut(
        name=lib.name,
        entries=[
            LibraryEntryOut(
                id=e.id,
                name=e.name,
                group=e.group,
                ratings=e.to_json()["ratings"],
                model_version=runtime.render_models.version(e.id),
            )
            for e in lib.entries
        ],
    )


@router.get(
    "/library/{entry_id}/model",
    response_model=RenderModel,
    response_model_by_alias=True,
    responses={
        200: {
            "description": f"the entry's rendering model (JSON, at most {MAX_RENDER_MODEL_BYTES} bytes), or with "
            f"`Accept: {COMPACT_CONTENT_TYPE}` its compact LSF-quantised encoding (texture_library/model_codec.py)",
            "headers": {
                "ETag": {"schema": {"type": "string"}, "description": "strong: the model_version (quoted)"},
                "Cache-Control": {"schema": {"type": "string"}},
            },
            "content": {COMPACT_CONTENT_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        },
        304: {"description": "If-None-Match names the current ETag: the cached copy is current"},
        **errors(401, 403, 404, 410, 422, 503),
    },
    summary="An entry's rendering model (a session's robot or operator token with ?session=, or a fleet API key); "
    "session:<session id> is that session's learnt surface model (its operator token, or a fleet API key)",
)
async def render_model(
    _: LibraryReader,
    state: State,
    runtime: ReadyRuntime,
    token: Token,
    entry_id: Annotated[str, Path(max_length=128)],
    # judged by LibraryReader first (the credential before anything else); read here for a learnt model's owner
    session: Annotated[str | None, Query(include_in_schema=False)] = None,
    accept: Annotated[str | None, Header()] = None,
    if_none_match: Annotated[str | None, Header()] = None,
) -> Response:
    if entry_id.startswith(SESSION_PREFIX):
        served = await _learnt_model(state, token, session, entry_id.removeprefix(SESSION_PREFIX))
    else:
        entry = runtime.render_models.models.get(entry_id)
        if entry is None:
            raise ServiceError(404, f"no entry {entry_id!r} in library {runtime.library.name!r}")
        served = entry
    compact = wants_compact(accept)
    # the compact layout's magic in the tag: a copy cached in an older layout is not revalidated as current
    etag = f'"{served.version}.{COMPACT_MAGIC.decode().lower()}"' if compact else f'"{served.version}"'
    headers = {"ETag": etag, "Cache-Control": CACHE_CONTROL, "Vary": "Accept"}
    if if_none_match is not None and _matches(if_none_match, etag):
        return Response(status_code=304, headers=headers)
    if compact:
        return Response(served.compact_body, media_type=COMPACT_CONTENT_TYPE, headers=headers)
    return Response(served.json_body, media_type="application/json", headers=headers)


async def library_reader(
    state: State,
    token: Token,
    session: Annotated[str | None, Query(description="the session whose robot or operator token is sent")] = None,
) -> None:
    """A fleet API key, or a session's robot or operator token with ?session=; else 401/403/404/410.

    A dependency, and the route's first: the credential is judged before anything else of the request (a path or
    query FastAPI would refuse 422, readiness 503). So `session` carries no constraint FastAPI checks first: an
    overlong one is an unknown session (404), once a credential was sent."""
    if state.api_keys.check(token):  # a fleet key reads the library, with or without a session (a follower's)
        return
    if session is None:
        raise ServiceError(
            401,
            "a credential is required: a session's robot or operator token ('Authorization: Bearer <token>' "
            "with ?session=<session id>) or a fleet API key",
            {"WWW-Authenticate": "Bearer"},
        )
    if token is not None and len(session) > MAX_SESSION_PARAM:  # no session has such an id: not looked up
        raise session_not_found(session[:40] + "…")
    await state.directory.authorized(session, token, EITHER)


#: the longest ?session= read (a session id is far shorter)
MAX_SESSION_PARAM = 200
LibraryReader = Annotated[None, Depends(library_reader)]


async def _learnt_model(state: State, token: str | None, session: str | None, session_id: str) -> ServedRenderModel:
    """A session's learnt surface model (service.surface_models): opened by that session's operator token (with
    ?session=<its id>) or a fleet API key, nobody else; 421 when another replica runs the session, 404 while no
    version is out."""
    # the credential itself was judged first (LibraryReader): a fleet key, or some session's token
    if state.api_keys.check(token):
        _, live = await state.directory.credentials(session_id)
        if live is None:
            raise ServiceError(421, f"session {session_id} runs on another replica; route its traffic by session id")
    else:
        if session != session_id:
            raise ServiceError(403, f"only session {session_id}'s operator token opens its learnt surface model")
        live = await state.directory.local(session_id, token, OPERATOR_ONLY)
    served = None if live.surface is None else live.surface.served
    if served is None:
        why = "is not learnt here (surface_model is off)" if live.surface is None else "has no version out yet"
        raise ServiceError(404, f"session {session_id}'s surface model {why}")
    return served


def wants_compact(accept: str | None) -> bool:
    """Whether an Accept header asks for the compact encoding: it names COMPACT_CONTENT_TYPE itself with q > 0, and
    no JSON-serving range (application/json, application/*, */*) with a higher q. A substring is not a name
    (`…-modelXYZ`), and q=0 means "not this" (RFC 9110 §12.5.1)."""
    if not accept:
        return False
    q: dict[str, float] = {}
    for part in accept.split(","):
        kind, *params = (p.strip() for p in part.split(";"))
        weight = 1.0
        for param in params:
            name, _, value = param.partition("=")
            if name.strip().lower() == "q":
                try:
                    weight = float(value)
                except ValueError:
                    weight = 0.0  # an unreadable weight: not a request for this type
        q[kind.lower()] = max(q.get(kind.lower(), 0.0), weight)
    compact = q.get(COMPACT_CONTENT_TYPE, 0.0)
    json_q = max(q.get(k, 0.0) for k in ("application/json", "application/*", "*/*"))
    return compact > 0 and compact >= json_q


def _matches(if_none_match: str, etag: str) -> bool:
    """If-None-Match uses the weak comparison (RFC 9110 §13.1.2): W/"x" matches "x"; * matches anything."""
    tags = [t.strip() for t in if_none_match.split(",")]
    return "*" in tags or any(t.removeprefix("W/") == etag for t in tags)
