"""The lean render feed: what an operator's renderer receives (`WS /sessions/{id}/events?view=render`).

The full event stream is the console's diagnostics (≈ 1 kB per window: intervals, matches, latencies). A
renderer needs the entry to render, its model version and the ratings, so this view sends:

- a **choice** (binary) on the session's first window and whenever the chosen entry or its model version
  changes: `b"C"`, the 4 ratings as int8, the 8 bytes of the model version (16 hex digits; zeros when the
  server names none), then the entry id in UTF-8 (the rest of the message; at least 1 byte);
- a **ratings** frame (binary, exactly 4 bytes) on every other window;
- the status events a renderer acts on (`RENDER_STATUSES`), unchanged (JSON text);
- with models pushed (`models=push`, this view's default), the chosen model itself, just before the choice that
  names a version the connection does not hold: `b"M"` + a compact payload (texture_library/model_codec.py), or
  `b"D"` + a delta against a body the connection holds (a learnt model's previous version, or its library prior),
  named by that body's digest.

What the connection holds, the service learns from the operator: `?library=<library_digest>` on connect (it holds
every entry of that library, shared in advance; texture_library.render_model.library_digest), and the **hold**
message (JSON text, operator → service) at any time: `{"type": "hold", "models": {"<id>": "<model_version>" or
null, …}}` (at most MAX_HOLD_ENTRIES ids). A null says it holds no usable version of that id: a delta it could not
apply (a missing base, a digest that does not match) is answered with the whole model, if that id is the one chosen.
A hold the service cannot take (malformed, an id it does not know) is answered with a status event `refused`
naming why; the feed goes on.

Ratings are the smoothed ratings rounded to int8 (−100…100) in `texture_library.attributes.ATTRIBUTES` order.

The service encodes it (`RenderView`, from the full events it publishes), the operator client decodes it
(`parse`), so the format lives here once.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass

import numpy as np

#: status events a renderer's view carries; the rest (frames, visual updates) are the console's business
RENDER_STATUSES = frozenset({"subscribed", "session_ended", "error", "refused"})
RATINGS_BYTES = 4
CHOICE_TAG = b"C"
#: a choice: tag + ratings + version, then the id
CHOICE_HEAD = 1 + RATINGS_BYTES + 8
NO_VERSION = bytes(8)
MODEL_TAG = b"M"
DELTA_TAG = b"D"
#: ids one hold message may name
MAX_HOLD_ENTRIES = 1024
#: the longest hold message read, bytes (1024 ids of 128 characters and their versions fit)
MAX_HOLD_BYTES = 192 * 1024
_HEX16 = re.compile(r"[0-9a-f]{16}")


def ratings_bytes(ratings: list[float]) -> bytes:
    """4 bipolar ratings → 4 int8 bytes (rounded, clipped to −100…100)."""
    return np.clip(np.rint(np.asarray(ratings, float)), -100, 100).astype(np.int8).tobytes()


class RenderView:
    """Turns one subscriber's full events (JSON text, as published) into the lean render feed, in order.

    `render(text)` → the message to send (str or bytes), or None to send nothing."""

    def __init__(self) -> None:
        self._sent: tuple[str, str | None] | None = None  # (chosen, version) the subscriber renders now
        #: the newest window's `library_pick`: the library entry beneath a learnt model (its prior), else None
        self.library_pick: str | None = None

    def render(self, text: str) -> str | bytes | None:
        event = json.loads(text)
        kind = event.get("type")
        if kind == "status":
            return text if event.get("event") in RENDER_STATUSES else None
        if kind != "window":
            return None
        ratings = [event["ratings"][k] for k in event["ratings"]]
        self.library_pick = event.get("library_pick")
        now = (event["chosen"], event.get("chosen_model_version"))
        if now == self._sent:
            return ratings_bytes(ratings)
        self._sent = now
        return choice_bytes(now[0], now[1], ratings)


def choice_bytes(chosen: str, version: str | None, ratings: list[float]) -> bytes:
    """A choice message (see the module docstring)."""
    ident = chosen.encode()
    if not ident:
        raise ValueError("a choice needs a non-empty entry id")
    return CHOICE_TAG + ratings_bytes(ratings) + (NO_VERSION if version is None else bytes.fromhex(version)) + ident


def model_message(payload: bytes, delta: bool) -> bytes:
    """A pushed model: a compact payload (delta=False) or a delta (see the module docstring)."""
    return (DELTA_TAG if delta else MODEL_TAG) + payload


def hold_message(models: dict[str, str | None]) -> str:
    """The operator's hold message: the version it holds of each id (None: none usable)."""
    return json.dumps({"type": "hold", "models": models}, separators=(",", ":"))


def parse_hold(message: str | bytes) -> dict[str, str | None]:
    """An operator's hold message → {id: version or None}; ValueError naming the problem (its size is judged
    before it is read)."""
    if isinstance(message, bytes):
        raise ValueError("an operator's message is JSON text (a hold), not binary")
    if len(message) > MAX_HOLD_BYTES:
        raise ValueError(f"a hold message is at most {MAX_HOLD_BYTES} bytes, got {len(message)}")
    try:
        doc = json.loads(message)
    except json.JSONDecodeError as exc:
        raise ValueError(f"a hold message must be JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("type") != "hold" or not isinstance(doc.get("models"), dict):
        raise ValueError('an operator\'s message is {"type": "hold", "models": {"<id>": "<model_version>" or null}}')
    models = doc["models"]
    if len(models) > MAX_HOLD_ENTRIES:
        raise ValueError(f"a hold message names at most {MAX_HOLD_ENTRIES} ids, got {len(models)}")
    for ident, version in models.items():
        if not 1 <= len(ident) <= 128:
            raise ValueError(f"a held id is 1–128 characters, got {len(ident)} ({ident[:40]!r})")
        if version is not None and not (isinstance(version, str) and _HEX16.fullmatch(version)):
            raise ValueError(
                f"the version held of {ident[:40]!r} must be 16 hex digits or null, got {str(version)[:40]!r}"
            )
    return models


@dataclass(frozen=True)
class FeedMessage:
    """One decoded message: kind "choice" (chosen, version, ratings), "ratings" (ratings), "status" (event), or
    "model" / "delta" (payload: the compact payload or delta, texture_library.model_codec)."""

    kind: str
    chosen: str | None = None
    version: str | None = None
    ratings: tuple[int, ...] | None = None
    window_index: int | None = None
    event: dict | None = None
    payload: bytes | None = None


def parse(message: str | bytes) -> FeedMessage:
    """A message of the render feed (or of the full event stream: its window events read as choices) →
    FeedMessage; ValueError naming the problem. A choice of the render feed carries no window index."""
    if isinstance(message, bytes):
        if len(message) == RATINGS_BYTES:
            return FeedMessage("ratings", ratings=tuple(np.frombuffer(message, np.int8).tolist()))
        if message[:1] == CHOICE_TAG and len(message) > CHOICE_HEAD:
            version = message[1 + RATINGS_BYTES : CHOICE_HEAD]
            try:
                chosen = message[CHOICE_HEAD:].decode()
            except UnicodeDecodeError:
                raise ValueError("render feed: a choice's entry id is not UTF-8") from None
            return FeedMessage(
                "choice",
                chosen,
                None if version == NO_VERSION else version.hex(),
                tuple(np.frombuffer(message[1 : 1 + RATINGS_BYTES], np.int8).tolist()),
            )
        if message[:1] in (MODEL_TAG, DELTA_TAG) and len(message) > 5:
            return FeedMessage("delta" if message[:1] == DELTA_TAG else "model", payload=message[1:])
        raise ValueError(
            f"a binary render-feed message is {RATINGS_BYTES} bytes of ratings or a choice (b'C' + at least "
            f"{CHOICE_HEAD} bytes) or a model (b'M' or b'D' + a payload), got {len(message)} bytes starting "
            f"{message[:1]!r}"
        )
    try:
        event = json.loads(message)
    except json.JSONDecodeError as exc:
        raise ValueError(f"render feed: not JSON ({exc})") from None
    if not isinstance(event, dict):
        raise ValueError("render feed: a message must be a JSON object")
    kind = event.get("type")
    if kind == "window":
        name, named_version = event.get("chosen"), event.get("chosen_model_version")
        if not isinstance(name, str) or not (named_version is None or isinstance(named_version, str)):
            raise ValueError("render feed: a window event needs a string `chosen` and `chosen_model_version`")
        raw = event.get("ratings")
        ratings = tuple(raw.values()) if isinstance(raw, dict) else tuple(raw or ())
        return FeedMessage("choice", name, named_version, ratings, event.get("window_index"))
    if kind == "status":
        return FeedMessage("status", event=event)
    raise ValueError(f"render feed: unknown message type {kind!r}")
