"""Models pushed on the operator's event socket (service/model_push.py): only what the connection lacks — a library
held in advance is named, never sent; a learnt model's new version goes as a delta against the one held; a delta
that cannot apply gets the whole model; bad holds are refused by name, bounded, without an ERROR line. End to end:
a real server, the operator's client, a session learning its surface."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import threading
import time

import httpx
import numpy as np
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from benchmarks.surface_model import known_texture
from drivers import render_feed
from drivers.operator.client import OperatorClient
from drivers.operator.devices import SimulatedStroke
from service.model_push import MAX_REFUSALS, ModelPush
from service.render_models import RenderCatalog, ServedRenderModel
from texture_library import model_codec
from texture_library.library import Library
from texture_library.recording import recording_from_stroke
from texture_library.render_model import RenderModel, content_version
from texture_library.stroke import GRAVITY, stroke
from texture_library.trajectory import freehand, model_ranges

SESSION = "session:test-a.s1"


def _served(doc: RenderModel) -> ServedRenderModel:
    return ServedRenderModel(doc, doc.to_json_bytes(), model_codec.encode(doc))


def _refit(doc: RenderModel, row: int, factor: float = 0.99) -> RenderModel:
    """`doc` with one grid point's AR LSFs scaled (a refit that new data moved there)."""
    content = doc.content()
    content["ar_lsf"][row] = (np.asarray(content["ar_lsf"][row]) * factor).tolist()
    envelope = {"schema": doc.schema_, "schema_version": doc.schema_version, "id": doc.id}
    return RenderModel.model_validate({**envelope, "model_version": content_version(content), **content})


class Receiver:
    """The operator's side of the messages, with the Python decoder: the bodies it holds, by id."""

    def __init__(self) -> None:
        self.bodies: dict[str, bytes] = {}

    def take(self, message: bytes) -> tuple[str, RenderModel, bool]:
        msg = render_feed.parse(message)
        assert msg.kind in ("model", "delta") and msg.payload is not None
        if msg.kind == "model":
            source, doc = model_codec.decode(msg.payload)
            body = model_codec.body(msg.payload)
        else:
            named = model_codec.delta_base(msg.payload)
            held = [b for b in self.bodies.values() if model_codec.body_digest(b) == named]
            source, doc, body = model_codec.decode_delta(msg.payload, held[0])
        self.bodies[doc.id] = body
        return source, doc, msg.kind == "delta"


@pytest.fixture
def catalog(library_dir) -> RenderCatalog:
    return RenderCatalog.from_library(Library.load(library_dir))


@pytest.fixture
def learnt(catalog) -> list[ServedRenderModel]:
    """Three versions of a learnt model (each a refit of the last) under the session's id."""
    first = RenderModel.from_vibration_model(SESSION, catalog.models["synth_003"].model.to_vibration_model())
    return [_served(first), _served(_refit(first, 4)), _served(_refit(_refit(first, 4), 7, 1.01))]


def _push(catalog, learnt, own: str | None = "test-a.s1") -> ModelPush:
    by_version = {s.version: s for s in learnt}

    def resolve(chosen: str, version: str | None) -> ServedRenderModel | None:
        if chosen == SESSION:
            return learnt[-1] if version is None else by_version.get(version)
        entry = catalog.models.get(chosen)
        return entry if entry is not None and version in (None, entry.version) else None

    return ModelPush(resolve, catalog, own)


def test_only_what_the_connection_lacks_goes_out(catalog, learnt):
    push, op = _push(catalog, learnt), Receiver()
    entry = next(iter(catalog.models.values()))
    message = push.bring(entry.model.id, entry.version)
    assert message is not None and message == b"M" + entry.compact_body  # a library entry it lacks: whole
    op.take(message)
    assert push.bring(entry.model.id, entry.version) is None  # held now: named only
    sizes = []
    for served in learnt:  # the learnt model: whole once, then deltas against the version held
        message = push.bring(SESSION, served.version)
        assert message is not None
        source, doc, delta = op.take(message)
        assert source == served.version and doc == model_codec.decode(served.compact_body)[1]
        sizes.append((len(message), delta))
    # the first version against the library entry chosen before it (its likely prior), the next ones against it
    assert [d for _, d in sizes] == [True, True, True]
    assert sizes[0][0] < len(learnt[0].compact_body)
    assert all(size < len(learnt[0].compact_body) / 4 for size, _ in sizes[1:]), sizes
    assert push.sent == {"models": 1, "deltas": 3, "bytes": push.sent["bytes"]}


def test_a_library_held_in_advance_is_named_never_sent(catalog, learnt):
    push = _push(catalog, learnt)
    assert push.hold_library(catalog.digest) is None
    assert all(push.bring(i, s.version) is None for i, s in catalog.models.items())
    assert push.sent["bytes"] == 0
    other = _push(catalog, learnt)
    why = other.hold_library("0123456789abcdef")
    assert why is not None and "is not this service's library" in why and catalog.digest in why
    entry = next(iter(catalog.models))
    assert other.bring(entry, catalog.version(entry)) is not None  # not taken as held: sent


def test_a_delta_that_cannot_apply_gets_the_whole_model(catalog, learnt):
    push = _push(catalog, learnt)
    push.bring(SESSION, learnt[0].version)
    delta = push.bring(SESSION, learnt[1].version)
    assert delta is not None and delta[:1] == render_feed.DELTA_TAG
    # the operator lost its base (a restart of its client): the delta does not apply, it says so
    with pytest.raises(ValueError, match="made against base"):
        model_codec.decode_delta(delta[1:], model_codec.body(learnt[2].compact_body))
    again, why = push.take_hold(render_feed.hold_message({SESSION: None}))
    assert why is None and again == [b"M" + learnt[1].compact_body]
    # a hold naming an earlier version it holds: the chosen one comes as a delta against it, and the next one
    # against the chosen one
    base = model_codec.body(learnt[0].compact_body)
    (delta,), why = push.take_hold(render_feed.hold_message({SESSION: learnt[0].version}))
    assert why is None and delta[:1] == render_feed.DELTA_TAG
    source, _, base = model_codec.decode_delta(delta[1:], base)
    assert source == learnt[1].version
    delta = push.bring(SESSION, learnt[2].version)
    assert delta is not None and delta[:1] == render_feed.DELTA_TAG
    assert model_codec.decode_delta(delta[1:], base)[0] == learnt[2].version


@pytest.mark.parametrize(
    ("hold", "says"),
    [
        ("not json", "must be JSON"),
        (b"\x00binary", "JSON text"),
        ('{"type": "need"}', '{"type": "hold"'),
        ('{"type": "hold", "models": {"synth_999": null}}', "no model 'synth_999' here"),
        ('{"type": "hold", "models": {"session:test-a.other": null}}', "no model 'session:test-a.other'"),
        ('{"type": "hold", "models": {"synth_000": "xyz"}}', "16 hex digits or null"),
        ('{"type": "hold", "models": {"synth_000": "0000000000000000"}}', "not one this service can make a delta"),
        (json.dumps({"type": "hold", "models": {f"e{i}": None for i in range(2000)}}), "at most 1024 ids"),
        ("x" * 300_000, "at most 196608 bytes"),
    ],
)
def test_a_bad_hold_is_refused_by_name(catalog, learnt, hold, says):
    push = _push(catalog, learnt)
    messages, why = push.take_hold(hold)
    assert messages == [] and why is not None and says in why, why
    assert push.refusals == 1 and not push.exhausted


def test_refusals_are_bounded(catalog, learnt):
    push = _push(catalog, learnt)
    for _ in range(MAX_REFUSALS):
        push.take_hold("{}")
    assert push.exhausted


# ---- on a real server --------------------------------------------------------------------------------------------
def test_the_socket_takes_holds_and_refuses_bad_ones_without_an_error_line(kit, server, client, library_dir, caplog):
    session = kit.create_session(client)
    url = kit.socket_url(server, session, "events") + "&view=render"
    for query, says in (
        ("&library=nope", b"library must be a library digest (16 hex digits), got 'nope'"),
        ("&models=sometimes", b"models must be one of push, fetch, got 'sometimes'"),
        ("&models=fetch&library=0123456789abcdef", b"it needs models=push"),
    ):
        with pytest.raises(InvalidStatus) as refused:
            connect(url + query, open_timeout=10)
        assert refused.value.response.status_code == 422 and says in refused.value.response.body
    digest = RenderCatalog.from_library(Library.load(library_dir)).digest
    with caplog.at_level(logging.WARNING), connect(url + f"&library={digest}", open_timeout=10) as ws:
        assert json.loads(ws.recv(timeout=10))["event"] == "subscribed"  # the digest is this library's: no refusal
        ws.send('{"type": "hold", "models": {"synth_999": null}}')
        event = json.loads(ws.recv(timeout=10))
        assert event["event"] == "refused" and "no model 'synth_999' here" in event["message"]
        for _ in range(MAX_REFUSALS - 1):
            ws.send("{}")
        messages = [ws.recv(timeout=10) for _ in range(MAX_REFUSALS - 1)]
        assert all(json.loads(m)["event"] == "refused" for m in messages)
        with pytest.raises(Exception):  # noqa: B017, PT011 - closed: the 17th message is never answered
            ws.recv(timeout=10)
        assert ws.close_code == 1008 and "too many refused" in (ws.close_reason or "")
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


def _stroke(model, seconds: float, seed: int = 7, hover_s: float = 0.5):
    rng = np.random.default_rng(seed)
    traj = freehand(seconds, rng, rate_hz=model.rate_hz, **model_ranges(model.max_speed, model.max_force))
    s = stroke(model, traj, rng)
    n = int(hover_s * model.rate_hz)
    hover = np.array([0.0, 0.0, GRAVITY]) + 0.05 * rng.standard_normal((n, 3))
    return recording_from_stroke(
        np.concatenate([hover, s.accel]),
        np.concatenate([0.01 * rng.standard_normal((n, 3)), s.force]),
        np.concatenate([np.zeros(n), s.speed]),
        s.rate_hz,
    )


def test_a_learnt_model_reaches_the_operator_as_deltas(kit, base_settings, library_dir):
    """A session learning its surface: the operator client (holding the library in advance) gets no library model
    and the learnt model's versions as deltas, each decoded to the version the window events name (the client
    checks it), and renders on."""
    settings = base_settings.model_copy(update={"instance_id": "test-push", "surface_model": True})
    texture = dataclasses.replace(known_texture(), rate_hz=1000.0)
    with kit.running(settings) as srv, httpx.Client(base_url=srv.url, timeout=10) as client:
        session = kit.create_session(client, "push")
        operator = OperatorClient(
            srv.url,
            session["session_id"],
            session["operator_token"],
            SimulatedStroke(60.0, seed=1),
            [],
            library=Library.load(library_dir),
        )
        got: dict = {}
        runner = threading.Thread(target=lambda: got.update(stats=asyncio.run(operator.run(duration_s=30.0))))
        runner.start()
        kit.wait_for(lambda: operator.stats.connects == 1, timeout_s=20)
        start = time.monotonic()
        for i, block in enumerate(kit.recording_blocks(_stroke(texture, 8.0))):
            assert kit.post_block(client, session, block).status_code == 202
            time.sleep(max(0.0, start + (i + 1) * 0.02 - time.monotonic()))
        versions = kit.session_status(client, session)["surface_model"]["versions"]
        kit.wait_for(lambda: operator.current is not None and operator.current[0].startswith("session:"), 20)
        time.sleep(2.0)
        operator.stop()
        runner.join(timeout=20)
    stats = got["stats"]
    counts = stats.model_counts
    assert stats.model_errors == [] and stats.deltas_unusable == 0
    learnt = [s for s in stats.switches if s.entry.startswith("session:")]
    # the library picks before the first learnt version: named and held, never sent; every learnt version pushed,
    # as a delta against what the client holds — the first against its library prior (held in advance: its body made
    # by the client when the delta named it), the later ones against the version before — or whole where no delta
    # is smaller
    assert counts.get("held", 0) == len(stats.switches) - len(learnt) >= 1, counts
    assert counts.get("pushed_models", 0) + counts.get("pushed_deltas", 0) == len(learnt) >= 1, counts
    assert counts.get("pushed_deltas", 0) >= 1, (versions, counts)
    assert "fetched" not in counts
    assert stats.samples > 0 and stats.silent_samples < stats.samples


def test_a_learnt_model_goes_as_a_delta_against_its_prior_the_window_names(catalog, learnt):
    """The window's library_pick (the learnt model's prior, held with the library) is a base: the first version of a
    surface costs what it changed from its prior, not a whole model."""
    push = _push(catalog, learnt)
    push.hold_library(catalog.digest)
    assert push.bring("synth_000", catalog.version("synth_000")) is None  # the library pick: named only
    message = push.bring(SESSION, learnt[0].version, prior="synth_003")
    assert message is not None and message[:1] == render_feed.DELTA_TAG
    assert model_codec.delta_base(message[1:]) == model_codec.body_digest(catalog.models["synth_003"].body)
    source, doc, _ = model_codec.decode_delta(message[1:], catalog.models["synth_003"].body)
    assert source == learnt[0].version and doc == model_codec.decode(learnt[0].compact_body)[1]
    assert len(message) < len(learnt[0].compact_body) / 4  # it is synth_003's model under another id


def test_a_learnt_model_goes_as_a_delta_against_the_entry_whose_taps_it_carries(catalog, learnt):
    """The surface's versions keep its first prior's taps (models.tactile.surface_fit) while the window's pick moves
    on: that entry (taps_from), held with the library, is a base too."""
    push = _push(catalog, learnt)
    push.hold_library(catalog.digest)
    version = dataclasses.replace(learnt[0], taps_from="synth_003")
    push.resolve = lambda chosen, v: version if chosen == SESSION else catalog.models.get(chosen)
    message = push.bring(SESSION, version.version, prior="synth_000")  # the window's pick is another entry now
    assert message is not None and message[:1] == render_feed.DELTA_TAG
    assert model_codec.delta_base(message[1:]) == model_codec.body_digest(catalog.models["synth_003"].body)
    assert len(message) < len(learnt[0].compact_body) / 4
    # without it the same version goes whole or against the pick, larger
    other = _push(catalog, learnt)
    other.hold_library(catalog.digest)
    plain = other.bring(SESSION, learnt[0].version, prior="synth_000")
    assert plain is not None and len(plain) > 2 * len(message)
