"""The operator's client: the session's render feed in, the chosen texture's vibration out.

Two tasks share one renderer:
- the feed: `WS /sessions/{id}/events?view=render` (drivers/render_feed.py). A choice names an entry and its
  model version. With models pushed (the default) the service sends, just before the choice, what this client
  lacks: a compact model, or a delta against the version of the same id it holds (a learnt model's new version);
  a library held in advance (`library`) is named on connect by its digest and never sent. A delta whose base is
  not held is answered with a hold message (null for that id) and the service sends the whole model. A model
  that was not pushed (a replica that cannot serve it, or push off) is fetched once per version
  (`GET /library/{id}/model`, compact encoding by default). Then it is handed to the render loop. The socket is
  reopened after a drop (backoff), and given up only
  when the session is over (closed 1000, lost 4410, refused 401/403/404/410).
- the render loop: each block of the operator's device (speed, force) is rendered by
  `texture_library.renderer.StreamRenderer` with the latest good model (a switch is crossfaded) and written to
  every output. Before the first model, and while the device is silent, it writes silence.

Bad input never stops rendering: a model that fails its schema or its version, or cannot be fetched, is
reported and the last good model plays on; a device that stops sending for `stall_s` is reported, silence is
written in its place, and rendering resumes when it sends again. Each switch reports its latency: from the
arrival of the window event that chose the entry to the end of the first block rendered with it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterable, AsyncIterator, Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol
from urllib.parse import quote

import httpx
import numpy as np

from drivers import render_feed
from drivers.operator.devices import RATE_HZ, Motion
from drivers.protocol import FATAL_CLOSES, bearer, check_service_url, ws_url
from drivers.robot.backoff import Backoff, body_detail
from texture_library import model_codec
from texture_library.library import Library
from texture_library.render_model import RenderModel, library_digest, parse_render_model
from texture_library.renderer import CROSSFADE_S, StreamRenderer
from texture_library.vibration import VibrationModel

log = logging.getLogger("hapticlink.operator")

#: compact bodies a client keeps as the bases of deltas (a library's entries and a learnt model's versions)
MAX_BASES = 512
#: HTTP statuses of the event socket's handshake after which retrying cannot help
FATAL_HANDSHAKES = frozenset({401, 403, 404, 410})
#: how often an operator following a robot asks for the robot's next session while it has none
FOLLOW_POLL_S = 0.25


@dataclass
class Switch:
    """A model switch: the entry and version; when its window event arrived (monotonic s); how long the model
    took to fetch (0 when cached) and how long until the first block with it was rendered, ms."""

    entry: str
    version: str | None
    received: float
    fetch_ms: float
    latency_ms: float | None = None


@dataclass
class OperatorStats:
    """What happened: switches, samples rendered, problems reported, reconnections, bytes received."""

    switches: list[Switch] = field(default_factory=list)
    samples: int = 0
    silent_samples: int = 0
    model_errors: list[str] = field(default_factory=list)
    stalls: int = 0
    connects: int = 0
    feed_messages: int = 0
    feed_bytes: int = 0
    model_bytes: int = 0
    #: how the models switched to came: pushed_models, pushed_deltas (on the feed), fetched (GET …/model), held (in
    #: advance); only kinds that occurred
    model_counts: dict[str, int] = field(default_factory=dict)
    deltas_unusable: int = 0  # deltas whose base was not held: the whole model was asked for
    ratings: tuple[int, ...] | None = None
    ended: str | None = None
    refused: bool = False  # the service refused the event feed (token, session): nothing was ever rendered for it
    sessions_followed: int = 0  # following a robot: its sessions followed (more than one: a restart, a loss)


class WebSocketLike(Protocol):
    """What the client sends on its feed socket (websockets' connection)."""

    async def send(self, message: str) -> None: ...


class ModelCache:
    """Rendering models by version: pushed on the feed (a whole compact payload, or a delta against the body held
    of the same id), held in advance (`hold`: a library shared beforehand), or fetched (GET /library/{id}/model).
    `get` → VibrationModel; ValueError naming the problem (DeltaUnusable: a delta whose base is not held)."""

    def __init__(self, http: httpx.AsyncClient, session_id: str, token: str, compact: bool = True) -> None:
        self.http, self.session_id, self.token, self.compact = http, session_id, token, compact
        self.models: dict[str, VibrationModel] = {}
        # compact bodies held, by their digest (model_codec.body_digest): the bases deltas name (the newest MAX_BASES)
        self.bases: dict[bytes, bytes] = {}
        self._held_docs: dict[str, RenderModel] = {}  # the library held in advance, its bodies made when first named
        self.pushed: tuple[str, bytes] | None = None  # ("model" or "delta", payload) waiting for its choice
        self.received_bytes = 0
        self.counts = {"pushed_models": 0, "pushed_deltas": 0, "fetched": 0, "held": 0}
        self._held: set[str] = set()

    def hold(self, models: dict[str, VibrationModel], docs: dict[str, RenderModel] | None = None) -> None:
        """Models held in advance, by version (docs: their served documents, whose compact bodies a delta may
        name as its base)."""
        self.models.update(models)
        self._held = set(models)
        self._held_docs = dict(docs or {})

    def push(self, kind: str, payload: bytes) -> None:
        """A model the feed pushed ("model" or "delta"): decoded when the choice that names it arrives."""
        self.pushed = (kind, payload)
        self.received_bytes += len(payload) + 1

    async def get(self, entry: str, version: str | None) -> tuple[VibrationModel, str]:
        """(the model, how it came: "cached", "pushed" or "fetched")."""
        pushed, self.pushed = self.pushed, None
        if version is not None and version in self.models:
            self.counts["held"] += version in self._held
            return self.models[version], "cached"
        if pushed is not None:
            kind, payload = pushed
            try:
                if kind == "delta":
                    base = self._base(model_codec.delta_base(payload))
                    if base is None:
                        raise DeltaUnusable(f"model {entry!r}: a delta against a base this client does not hold")
                    try:
                        source, doc, body = model_codec.decode_delta(payload, base)
                    except ValueError as exc:
                        raise DeltaUnusable(f"model {entry!r}: the delta does not apply ({exc})") from None
                else:
                    source, doc = model_codec.decode(payload)
                    body = model_codec.body(payload)
            except DeltaUnusable:
                raise
            except ValueError as exc:
                raise ValueError(f"model {entry!r} ({version}) is unusable: {exc}") from None
            model = self._keep(entry, version, source, doc, body)
            self.counts["pushed_deltas" if kind == "delta" else "pushed_models"] += 1
            return model, "pushed"
        headers = bearer(self.token)
        if self.compact:
            headers["Accept"] = model_codec.CONTENT_TYPE
        try:
            r = await self.http.get(
                f"/library/{quote(entry, safe='')}/model", params={"session": self.session_id}, headers=headers
            )
        except httpx.HTTPError as exc:
            raise ValueError(f"model {entry!r}: the request failed ({type(exc).__name__}: {exc})") from None
        self.received_bytes += len(r.content) + sum(len(k) + len(v) + 4 for k, v in r.headers.items())
        if r.status_code != 200:
            raise ValueError(f"model {entry!r}: the service answered {r.status_code} ({_detail(r)})")
        whole: bytes | None = None
        try:
            if r.headers.get("content-type", "").startswith(model_codec.CONTENT_TYPE):
                source, doc = model_codec.decode(r.content)
                whole = model_codec.body(r.content)
            else:
                doc = parse_render_model(r.content)
                source = doc.model_version
        except ValueError as exc:
            raise ValueError(f"model {entry!r} ({version}) is unusable: {exc}") from None
        self.counts["fetched"] += 1
        return self._keep(entry, version, source, doc, whole), "fetched"

    def _keep(self, entry: str, version: str | None, source: str, doc, body: bytes | None) -> VibrationModel:
        if version is not None and source != version:
            raise ValueError(f"model {entry!r}: the service sent version {source}, the window event named {version}")
        if doc.id != entry:
            raise ValueError(f"model {entry!r}: the service sent the model of {doc.id!r}")
        model = doc.to_vibration_model()
        self.models[source] = model
        if body is not None:
            self._remember(body)
        return model

    def _remember(self, body: bytes) -> None:
        self.bases[model_codec.body_digest(body)] = body
        while len(self.bases) > MAX_BASES:
            del self.bases[next(iter(self.bases))]

    def _base(self, digest: bytes) -> bytes | None:
        """The body a delta names: one received, or (made once, when first needed) one of the library held."""
        if digest not in self.bases and self._held_docs:
            docs, self._held_docs = self._held_docs, {}
            for doc in docs.values():
                self._remember(model_codec.body(model_codec.encode(doc)))
        return self.bases.get(digest)


class DeltaUnusable(ValueError):
    """A pushed delta whose base this client does not hold (or holds another version of): the whole model is asked
    for (a hold message saying null for the id)."""


def _detail(r: httpx.Response) -> str:
    try:
        return str(r.json().get("detail", r.text[:200]))
    except ValueError:
        return r.text[:200]


class OperatorClient:
    """Renders a session's chosen textures from `device` to `outputs` (see the module docstring).

    url: the service (http://host:port); session_id / token: the session and its operator (or robot) token; or
    robot / token: the robot to follow across its sessions (a restart of the service included) and the fleet API key
    (session_id is then found, and may be None);
    view: "render" (the lean feed) or "full" (the console's events); compact: fetch the compact model encoding;
    push: models come on the feed (only what this client lacks; deltas for a learnt model's new versions), else
    each is fetched; library: a library this client holds in advance (its entries are named on the feed, never
    sent);
    crossfade_s: switch crossfade; stall_s: a device silent this long is reported; seed: the excitation's seed;
    on_switch: called with each Switch once rendered (the CLI prints it).
    """

    def __init__(
        self,
        url: str,
        session_id: str | None,
        token: str,
        device: AsyncIterable[Motion],
        outputs: Sequence[object],
        *,
        view: str = "render",
        compact: bool = True,
        crossfade_s: float = CROSSFADE_S,
        stall_s: float = 0.5,
        block_s: float = 0.01,
        seed: int = 0,
        on_switch: Callable[[Switch], None] | None = None,
        robot: str | None = None,
        push: bool = True,
        library: Library | None = None,
    ) -> None:
        check_service_url(url)
        if view not in ("render", "full"):
            raise ValueError(f"view must be 'render' or 'full', got {view!r}")
        if not stall_s > 0:
            raise ValueError(f"stall_s must be > 0, got {stall_s}")
        if (session_id is None) == (robot is None):
            raise ValueError("give a session to follow, or a robot (and the fleet API key as the token), not both")
        self.url, self.session_id, self.token = url.rstrip("/"), session_id, token
        self.device, self.outputs = device, list(outputs)
        self.view, self.compact, self.crossfade_s, self.stall_s = view, compact, crossfade_s, stall_s
        self.block_n = max(1, int(round(block_s * RATE_HZ)))
        self.rng = np.random.default_rng(seed)
        self.on_switch = on_switch
        self.stats = OperatorStats()
        self.renderer: StreamRenderer | None = None
        self.current: tuple[str, str | None] | None = None  # (entry, version) rendered or about to be
        self._pending: tuple[VibrationModel, Switch] | None = None
        self._done = asyncio.Event()
        # following a robot: its current session is over (go on to the next), and the id of the one that was
        self.robot = robot
        self._over = False
        self._gone: str | None = None
        self.push = push
        # the library held in advance: its models by served version, and the digest that names them all
        self.held: dict[str, VibrationModel] = {}
        self.held_docs: dict[str, RenderModel] = {}
        self.library_digest: str | None = None
        if library is not None:
            for entry_id in library.ids:
                model = library.model(entry_id)
                doc = RenderModel.from_vibration_model(entry_id, model)
                self.held[doc.model_version], self.held_docs[entry_id] = model, doc
            self.library_digest = library_digest({i: d.model_version for i, d in self.held_docs.items()})
        # a choice waiting for its whole model (asked for after a delta that did not apply): (entry, version, at)
        self._awaiting: tuple[str, str | None, float] | None = None

    # ---- the feed --------------------------------------------------------------------------------
    async def follow(self, http: httpx.AsyncClient) -> None:
        """Receive the feed until the session is over, reconnecting after drops; with `robot`, go on to the robot's
        next session each time one is over (found with GET /robots/{robot}/session), until stopped."""
        while not self._done.is_set():
            if self.robot is not None and not await self._find_session(http):
                return
            self._over = False
            assert self.session_id is not None  # given, or found
            cache = ModelCache(http, self.session_id, self.token, self.compact)
            cache.hold(self.held, self.held_docs)
            self._cache = cache
            await self._follow_session(cache)
            if self.robot is None:
                return

    async def _find_session(self, http: httpx.AsyncClient) -> bool:
        """Wait for the robot's newest session that is live and not the one just over; False when refused (the key)
        or stopped. Polled every FOLLOW_POLL_S: a restarted service knows the robot again once it opens a session."""
        assert self.robot is not None
        said = False
        while not self._done.is_set():
            try:
                r = await http.get(f"/robots/{quote(self.robot, safe='')}/session", headers=bearer(self.token))
            except httpx.HTTPError as exc:
                why = f"{type(exc).__name__}"
            else:
                if r.status_code in (401, 403):
                    self.stats.refused = True
                    self._end(f"the service refused to say robot {self.robot!r}'s session: HTTP {r.status_code}")
                    return False
                doc = r.json() if r.status_code == 200 else {}
                sid = doc.get("session_id")
                if sid and doc.get("lost") is None and sid != self._gone:
                    self.stats.sessions_followed += 1
                    log.info("following robot %s in its session %s", self.robot, sid)
                    self.session_id = sid
                    return True
                why = f"HTTP {r.status_code}" if r.status_code != 200 else "its session is over"
            if not said:
                log.info("waiting for robot %s's next session (%s)", self.robot, why)
                said = True
            await asyncio.sleep(FOLLOW_POLL_S)
        return False

    def _session_over(self, why: str) -> None:
        """The followed session is over: the end of the run, or (following a robot) of this session only."""
        if self.robot is None:
            self._end(why)
            return
        if not self._over:
            log.info("%s; following robot %s to its next session", why, self.robot)
        self._over, self._gone = True, self.session_id

    async def _follow_session(self, cache: ModelCache) -> None:
        """Receive one session's feed until it is over (or the run stops), reconnecting after drops."""
        from websockets.asyncio.client import connect  # noqa: PLC0415 - as drivers/robot/ws.py
        from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus  # noqa: PLC0415

        backoff = Backoff(0.1, 5.0)
        url = ws_url(self.url, cache.session_id, "events", self.token)
        if self.view == "render":
            url += "&view=render"
        url += "&models=" + ("push" if self.push else "fetch")
        if self.push and self.library_digest is not None:
            url += "&library=" + self.library_digest
        while not self._done.is_set() and not self._over:
            opened = False
            try:
                async with connect(url, open_timeout=10, max_size=1 << 20) as ws:
                    opened = True
                    self.stats.connects += 1
                    if self.stats.connects > 1:
                        log.warning("event feed reconnected (connection %d)", self.stats.connects)
                    backoff.reset()
                    async for message in ws:
                        await self._on_message(message, time.monotonic(), cache, ws)
                        if self._over:
                            return
                    code = ws.close_code
            except InvalidStatus as exc:
                status = exc.response.status_code
                if status in FATAL_HANDSHAKES:
                    if self.robot is None or status in (401, 403):
                        self.stats.refused = True
                        self._end(
                            f"the service refused the event feed: HTTP {status}: {body_detail(exc.response.body)}"
                        )
                        return
                    self._session_over(f"session {self.session_id} is over (HTTP {status})")
                    return
                log.warning("event feed refused (HTTP %d); retrying", status)
                code = None
            except ConnectionClosed as exc:
                code = exc.rcvd.code if exc.rcvd is not None else None
            except (TimeoutError, OSError, InvalidHandshake) as exc:
                log.warning("event feed unreachable (%s); retrying", type(exc).__name__)
                code = None
            if code is not None and code in FATAL_CLOSES:
                self._session_over(f"the event feed closed ({code}): the session is over")
                return
            if not self._done.is_set():
                if opened:
                    log.warning("event feed dropped (close code %s); reconnecting", code)
                await asyncio.sleep(backoff.next())

    async def _on_message(
        self, message: str | bytes, received: float, cache: ModelCache, ws: WebSocketLike | None = None
    ) -> None:
        self.stats.feed_messages += 1
        self.stats.feed_bytes += len(message) if isinstance(message, bytes) else len(message.encode())
        try:
            msg = render_feed.parse(message)
        except ValueError as exc:
            log.error("bad event from the service: %s; rendering goes on", exc)
            return
        if msg.ratings:
            self.stats.ratings = tuple(int(round(r)) for r in msg.ratings)
        if msg.kind in ("model", "delta") and msg.payload is not None:
            cache.push(msg.kind, msg.payload)
            if self._awaiting is not None:  # the whole model asked for
                await self._choose(*self._awaiting, cache, ws)
            return
        if msg.kind == "status" and msg.event is not None and msg.event.get("event") == "refused":
            log.warning("the service refused a message of this client: %s", msg.event.get("message", ""))
            if self._awaiting is not None:  # it cannot send the whole model on the feed: fetch it
                await self._choose(*self._awaiting, cache, None)
            return
        if msg.kind == "status" and msg.event is not None and msg.event.get("event") == "session_ended":
            self._session_over(f"session ended: {msg.event.get('message', '')}")
            return
        if msg.kind != "choice" or msg.chosen is None or (msg.chosen, msg.version) == self.current:
            return
        await self._choose(msg.chosen, msg.version, received, cache, ws)

    async def _choose(
        self, chosen: str, version: str | None, received: float, cache: ModelCache, ws: WebSocketLike | None
    ) -> None:
        """Get a choice's model (held, pushed or fetched) and hand it to the render loop."""
        self._awaiting = None
        started = time.monotonic()
        try:
            model, how = await cache.get(chosen, version)
        except DeltaUnusable as exc:
            self.stats.deltas_unusable += 1
            if ws is not None:  # say so: the service sends the whole model (or refuses, and it is fetched)
                log.warning("%s; asking the service for the whole model", exc)
                self._awaiting = (chosen, version, received)
                await ws.send(render_feed.hold_message({chosen: None}))
                return
            await self._choose(chosen, version, received, cache, None)  # nothing pushed now: fetched
            return
        except ValueError as exc:
            self.stats.model_errors.append(str(exc))
            now = self.current[0] if self.current else "silence"
            log.error("%s; rendering goes on with %s", exc, now)
            return
        self.stats.model_bytes = cache.received_bytes
        self.stats.model_counts = {k: v for k, v in cache.counts.items() if v}
        self.current = (chosen, version)
        fetch_ms = (time.monotonic() - started) * 1e3 if how == "fetched" else 0.0
        self._pending = (model, Switch(chosen, version, received, fetch_ms))

    def stop(self) -> None:
        """End `run` at the next block (from the same event loop)."""
        self._done.set()

    def _end(self, why: str) -> None:
        if self.stats.ended is None:
            self.stats.ended = why
            log.info("%s", why)
        self._done.set()

    # ---- the render loop ---------------------------------------------------------------------------
    async def render(self) -> None:
        """Render the device's blocks until it ends or the session is over."""
        it: AsyncIterator[Motion] = aiter(self.device)
        nxt: asyncio.Future | None = None
        stalled = False
        stop = asyncio.ensure_future(self._done.wait())
        try:
            while not self._done.is_set():
                if nxt is None:
                    nxt = asyncio.ensure_future(anext(it))
                done, _ = await asyncio.wait({nxt, stop}, timeout=self.stall_s, return_when=asyncio.FIRST_COMPLETED)
                if stop in done:
                    return
                if nxt not in done:  # the device is silent: say so once, keep the output fed with silence
                    if not stalled:
                        stalled = True
                        self.stats.stalls += 1
                        log.error("the device sent nothing for %.1f s; writing silence until it resumes", self.stall_s)
                    self._emit(np.zeros(int(self.stall_s * RATE_HZ)), np.zeros(int(self.stall_s * RATE_HZ)), True)
                    continue
                try:
                    motion = nxt.result()
                except StopAsyncIteration:
                    return
                finally:
                    nxt = None
                if stalled:
                    stalled = False
                    log.warning("the device sends again; rendering resumes")
                self._render_block(motion)
        finally:
            stop.cancel()
            if nxt is not None:
                nxt.cancel()

    def _render_block(self, motion: Motion) -> None:
        pending, self._pending = self._pending, None
        if pending is not None:
            model, switch = pending
            if self.renderer is None:
                self.renderer = StreamRenderer(model, self.rng, crossfade_s=self.crossfade_s)
            else:
                self.renderer.switch(model)
        if self.renderer is None:
            self._emit(np.zeros(motion.speed.size), np.zeros(motion.speed.size), True)
            return
        try:
            out = self.renderer.process(motion.speed, motion.force, position=motion.position)
        except ValueError as exc:  # a glitch in the device's data: this block is silent, the next one renders
            log.error("the device sent a bad block (%s); it is rendered as silence", exc)
            self._emit(np.zeros(motion.speed.size), np.zeros(motion.speed.size), True)
            return
        self._emit(out.accel, out.friction, False)
        if pending is not None:
            switch = pending[1]
            switch.latency_ms = (time.monotonic() - switch.received) * 1e3
            self.stats.switches.append(switch)
            if self.on_switch is not None:
                self.on_switch(switch)

    def _emit(self, accel: np.ndarray, friction: np.ndarray, silent: bool) -> None:
        for out in self.outputs:
            out.write(accel, friction)  # type: ignore[attr-defined]
        self.stats.samples += accel.size
        if silent:
            self.stats.silent_samples += accel.size

    # ---- both --------------------------------------------------------------------------------------
    async def run(self, duration_s: float | None = None) -> OperatorStats:
        """Follow the feed and render until the device ends, the session is over, or duration_s has passed."""
        async with httpx.AsyncClient(base_url=self.url, timeout=10) as http:
            feed = asyncio.create_task(self.follow(http))
            try:
                await asyncio.wait_for(self.render(), duration_s) if duration_s else await self.render()
            except TimeoutError:
                pass
            finally:
                self._done.set()
                feed.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await feed
                closer = getattr(self.device, "aclose", None)
                if closer is not None:
                    with contextlib.suppress(Exception):
                        await closer()
        return self.stats
