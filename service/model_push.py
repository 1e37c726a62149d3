"""Models pushed on an operator's event socket: only what that connection does not hold.

A connection with models pushed (`?models=push`; the render view's default, drivers/render_feed.py) gets, just
before a choice that names a version it does not hold, that version itself, as the smallest of: the whole compact
payload (texture_library.model_codec), a delta against the version of the same id it holds (a learnt
`session:<id>` model's earlier version: what a refit did not move costs nothing), and, for a learnt model, deltas
against the library entry chosen before it (its prior) and against the entry whose recorded taps it carries (its
surface's first prior, `ServedRenderModel.taps_from`: the taps are most of a model's bytes).
A library entry the operator holds — the whole library, shared in advance and named by its digest on connect
(`?library=`), or entries named in a hold message — is named, never sent.

What the connection holds is this object's belief: what it was sent, and what the operator says it holds (a hold
message, drivers/render_feed.parse_hold). A delta the operator cannot apply is answered by its hold saying null
for that id: the whole model goes out again. A hold the service cannot take gets a `refused` status naming why;
after MAX_REFUSALS of them the socket is closed (1008): each costs one bounded parse, and a client cannot make
more of them than it sends messages.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from drivers import render_feed
from service.render_models import RenderCatalog, ServedRenderModel
from service.surface_models import SESSION_PREFIX
from texture_library import model_codec

#: refused hold messages after which the socket is closed (policy violation)
MAX_REFUSALS = 16
#: ids whose held version a connection tracks, at most (a library's entries and a learnt model or two)
MAX_HELD = 4096

#: (id, version or None for the newest) → the served model, or None when this replica cannot serve it
Resolver = Callable[[str, str | None], ServedRenderModel | None]


@dataclass
class Held:
    """A version the connection holds; base: the body a delta is made against (None: look it up when needed)."""

    version: str
    base: bytes | None = None


class ModelPush:
    """One connection's models (see the module docstring).

    resolve: finds a served model by id and version; catalog: the library's served models; own_session: the one
    session whose learnt model this connection may name (None: any, a fleet key's robot feed)."""

    def __init__(self, resolve: Resolver, catalog: RenderCatalog, own_session: str | None) -> None:
        self.resolve, self.catalog, self.own_session = resolve, catalog, own_session
        self.held: dict[str, Held] = {}
        self.current: tuple[str, str | None] | None = None  # the last choice forwarded
        self.last_library: str | None = None  # a learnt model's prior: the window's library_pick, else the last chosen
        self.refusals = 0
        self.sent = {"models": 0, "deltas": 0, "bytes": 0}

    def hold_library(self, digest: str) -> str | None:
        """The operator holds a library with this digest: every entry held if it is this one's; else why not."""
        if digest != self.catalog.digest:
            return (
                f"library digest {digest[:40]!r} is not this service's library ({self.catalog.digest}): its entries "
                "are not taken as held; each is sent whole when chosen"
            )
        for entry_id, served in self.catalog.models.items():
            self.held[entry_id] = Held(served.version)
        return None

    def bring(self, chosen: str, version: str | None, prior: str | None = None) -> bytes | None:
        """The message that brings a choice's model (to send before the choice), or None: held, or not servable
        here (the operator fetches it: GET /library/{id}/model). prior: the library entry a learnt model was
        learnt from (the window event's `library_pick`), when known."""
        self.current = (chosen, version)
        if not chosen.startswith(SESSION_PREFIX):
            self.last_library = chosen
        elif prior is not None and prior in self.catalog.models:
            self.last_library = prior
        held = self.held.get(chosen)
        if version is not None and held is not None and held.version == version:
            return None
        served = self.resolve(chosen, version)
        if served is None:
            return None
        message = render_feed.model_message(served.compact_body, delta=False)
        for base in self._bases(chosen, served.taps_from):  # the smallest: whole, or a delta against what it holds
            delta = render_feed.model_message(model_codec.delta_between(served.body, base), delta=True)
            if len(delta) < len(message):
                message = delta
        self._remember(chosen, Held(served.version, served.body if chosen.startswith(SESSION_PREFIX) else None))
        self.sent["deltas" if message[:1] == render_feed.DELTA_TAG else "models"] += 1
        self.sent["bytes"] += len(message)
        return message

    def take_hold(self, text: str | bytes) -> tuple[list[bytes], str | None]:
        """An operator's hold message → (model messages to send now, a refusal naming why or None). A null for the
        chosen id re-sends its model whole."""
        try:
            models = render_feed.parse_hold(text)
            unknown = [i for i in models if not self._known(i)]
            if unknown:
                raise ValueError(f"no model {unknown[0][:40]!r} here ({len(unknown)} unknown id(s) in the hold)")
        except ValueError as exc:
            self.refusals += 1
            return [], f"hold refused: {exc}"
        stale = []
        for ident, version in models.items():
            self.held.pop(ident, None)
            if version is None:
                continue
            base = self._body(ident, version)
            if base is None:
                stale.append(ident)
                continue
            self._remember(ident, Held(version, base if ident.startswith(SESSION_PREFIX) else None))
        out = []
        if self.current is not None and self.current[0] in models:
            message = self.bring(*self.current)
            if message is not None:
                out.append(message)
            elif self.held.get(self.current[0]) is None:  # not servable here: the operator fetches it
                self.refusals += 1
                return out, (
                    f"model {self.current[0][:40]!r} ({self.current[1]}) cannot be sent on this socket: fetch it "
                    "(GET /library/{id}/model)"
                )
        if stale:
            self.refusals += 1
            return out, (
                f"hold refused for {stale[0][:40]!r} ({len(stale)} id(s)): the version named is not one this service "
                "can make a delta against; the whole model is sent when chosen"
            )
        return out, None

    def _bases(self, chosen: str, taps_from: str | None = None) -> list[bytes]:
        """Bodies the connection holds that a delta for `chosen` may be made against: its earlier version, and (a
        learnt model) its prior (the window's library_pick, else the library entry chosen last) and the entry whose
        taps it carries (taps_from: its surface's first prior, which the window's pick may have moved on from)."""
        out = []
        learnt = chosen.startswith(SESSION_PREFIX)
        idents = (chosen, *((self.last_library, taps_from) if learnt else ()))
        for k, ident in enumerate(idents):
            if ident in idents[:k]:
                continue
            held = None if ident is None else self.held.get(ident)
            if held is not None and ident is not None:
                base = held.base or self._body(ident, held.version)
                if base is not None:
                    out.append(base)
        return out

    @property
    def exhausted(self) -> bool:
        return self.refusals >= MAX_REFUSALS

    def _known(self, ident: str) -> bool:
        if ident.startswith(SESSION_PREFIX):
            session = ident.removeprefix(SESSION_PREFIX)
            return (self.own_session is None or session == self.own_session) and self.resolve(ident, None) is not None
        return ident in self.catalog.models

    def _body(self, ident: str, version: str) -> bytes | None:
        served = self.resolve(ident, version)
        return None if served is None or served.version != version else served.body

    def _remember(self, ident: str, held: Held) -> None:
        self.held.pop(ident, None)
        self.held[ident] = held
        while len(self.held) > MAX_HELD:  # the oldest belief goes: at worst a model is sent once more
            del self.held[next(iter(self.held))]
