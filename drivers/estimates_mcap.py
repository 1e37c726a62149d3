"""A session's estimates as MCAP, beside the robot's own bag: `hapticlink record --mcap OUT`.

The recorder follows the session's event feed (`WS /sessions/{id}/events`, the operator console's full view) and
writes every event it carries into an MCAP file, as JSON messages with JSON schemas (the `mcap` package), on the
robot's clock: a window's messages are logged at the window's end (t_end_s, the clock the robot stamped its blocks
with — header.stamp for a ROS 2 bag, drivers.rosbag_source), so Foxglove or the `mcap` tools show them beside the
robot's topics. Channels:

- /hapticlink/window: each window event whole, as the feed carried it;
- /hapticlink/ratings: the smoothed and raw ratings (−100…100) with their prediction interval;
- /hapticlink/ood: the out-of-distribution flag and its reasons;
- /hapticlink/model: the chosen rendering model and its version, the estimating model, what it read;
- /hapticlink/latency: the window's per-stage latency, ms;
- /hapticlink/status: status events (the service's own wall clock in `time`), logged at the robot time of the last
  window before them (0 before the first).

Why a separate recorder rather than an option of `hapticlink operator`: it needs no haptic device or sound card, it
can run on the lab machine that holds the robot's bag, and it follows the full feed (the operator's default feed is
the lean render view, which carries no intervals, OOD reasons or latencies).
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any, BinaryIO, Protocol

from drivers.protocol import FATAL_CLOSES, check_service_url, ws_url
from drivers.robot.backoff import Backoff, body_detail

log = logging.getLogger("hapticlink.record")

#: how long the recorder waits for the service to answer the feed's close, s (as the robot client does)
FEED_CLOSE_S = 2.0

ATTRIBUTE_NAMES = ("rough_smooth", "flat_bumpy", "sticky_slippery", "hard_soft")
_RATINGS = {
    "type": "object",
    "properties": {a: {"type": "number", "minimum": -100, "maximum": 100} for a in ATTRIBUTE_NAMES},
}
_TIMES = {
    "window_index": {"type": "integer", "description": "the session's window number"},
    "t_start_s": {"type": "number", "description": "window start, s, robot's clock"},
    "t_end_s": {"type": "number", "description": "window end, s, robot's clock"},
}
#: topic → (schema name, JSON schema, the fields of a window event it carries; None: the whole event)
CHANNELS: dict[str, tuple[str, dict[str, Any], tuple[str, ...] | None]] = {
    "/hapticlink/window": (
        "hapticlink.WindowEvent",
        {
            "type": "object",
            "description": "a window event as the session's event feed carried it (docs/service.md)",
            "properties": {"type": {"const": "window"}, "session_id": {"type": "string"}, **_TIMES},
            "required": ["type", "window_index", "t_start_s", "t_end_s"],
        },
        None,
    ),
    "/hapticlink/ratings": (
        "hapticlink.Ratings",
        {
            "type": "object",
            "properties": {
                **_TIMES,
                "ratings": {**_RATINGS, "description": "smoothed ratings, bipolar −100…100"},
                "raw_ratings": {**_RATINGS, "description": "the window's own ratings before smoothing"},
                "interval": {
                    "type": ["object", "null"],
                    "description": "prediction interval: level, target, and {lo, hi} per attribute",
                },
            },
        },
        ("window_index", "t_start_s", "t_end_s", "ratings", "raw_ratings", "interval"),
    ),
    "/hapticlink/ood": (
        "hapticlink.OutOfDistribution",
        {
            "type": "object",
            "properties": {
                **_TIMES,
                "out_of_distribution": {"type": "boolean"},
                "ood_reasons": {"type": "array", "items": {"type": "string"}},
            },
        },
        ("window_index", "t_start_s", "t_end_s", "out_of_distribution", "ood_reasons"),
    ),
    "/hapticlink/model": (
        "hapticlink.ChosenModel",
        {
            "type": "object",
            "properties": {
                **_TIMES,
                "chosen": {"type": ["string", "null"], "description": "the library entry rendered"},
                "chosen_model_version": {"type": ["string", "null"]},
                "selection": {"type": ["object", "null"]},
                "model": {"type": "string", "description": "the model that estimated the ratings"},
                "inputs": {"type": "string"},
            },
        },
        ("window_index", "t_start_s", "t_end_s", "chosen", "chosen_model_version", "selection", "model", "inputs"),
    ),
    "/hapticlink/latency": (
        "hapticlink.Latency",
        {
            "type": "object",
            "properties": {
                **_TIMES,
                "latency_ms": {
                    "type": "object",
                    "properties": {k: {"type": "number"} for k in ("queue", "features", "model", "lookup", "total")},
                },
            },
        },
        ("window_index", "t_start_s", "t_end_s", "latency_ms"),
    ),
    "/hapticlink/status": (
        "hapticlink.StatusEvent",
        {
            "type": "object",
            "properties": {
                "type": {"const": "status"},
                "event": {"type": "string"},
                "message": {"type": "string"},
                "time": {"type": "number", "description": "the service's wall clock, Unix s"},
            },
            "required": ["type", "event"],
        },
        None,
    ),
}


def event_messages(event: dict[str, Any], robot_ns: int) -> tuple[list[tuple[str, dict[str, Any], int]], int]:
    """The messages (topic, payload, log time ns) one feed event makes, and the robot time (ns) after it: a window's
    end, or `robot_ns` unchanged. A window without a usable t_end_s, or an event of another type, makes none."""
    kind = event.get("type")
    if kind == "status":
        return [("/hapticlink/status", event, robot_ns)], robot_ns
    if kind != "window":
        return [], robot_ns
    t_end = event.get("t_end_s")
    if not isinstance(t_end, (int, float)) or isinstance(t_end, bool) or not 0 <= t_end < 2**63 / 1e9:
        log.warning("window event without a usable t_end_s (%r): not recorded", t_end)
        return [], robot_ns
    log_ns = int(round(float(t_end) * 1e9))
    out = [
        (topic, event if fields is None else {k: event.get(k) for k in fields}, log_ns)
        for topic, (_, _, fields) in CHANNELS.items()
        if topic != "/hapticlink/status"
    ]
    return out, max(robot_ns, log_ns)


class EstimatesMcap:
    """Writes the channels' messages into an MCAP stream, each channel with its JSON schema."""

    def __init__(self, stream: BinaryIO) -> None:
        from mcap.writer import Writer

        self._writer = Writer(stream)
        self._writer.start(profile="", library="hapticlink")
        self._channels: dict[str, int] = {}
        for topic, (name, schema, _) in CHANNELS.items():
            sid = self._writer.register_schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode())
            self._channels[topic] = self._writer.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        self._sequence = 0

    def log(self, topic: str, payload: dict[str, Any], log_ns: int) -> None:
        self._sequence += 1
        data = json.dumps(payload, separators=(",", ":")).encode()
        self._writer.add_message(self._channels[topic], log_ns, data, log_ns, self._sequence)

    def close(self) -> None:
        """Write the summary (channel and schema index, statistics); the file is complete after this."""
        self._writer.finish()


class EventSink(Protocol):
    """Where the recorder's messages go: an MCAP file (EstimatesMcap), a Foxglove server (FoxgloveLive)."""

    def log(self, topic: str, payload: dict[str, Any], log_ns: int) -> None: ...

    def close(self) -> None: ...


class SessionRecorder:
    """Follows a session's event feed and hands each event's messages to every sink (an MCAP file, a Foxglove
    server) until the session ends or `stop()` is called; reconnects after a drop (the events in between are lost,
    and the log says so). The sinks are closed when it returns."""

    def __init__(self, url: str, session_id: str, token: str, sinks: list[EventSink]) -> None:
        check_service_url(url)
        if not sinks:
            raise ValueError("a recorder needs somewhere to write: an MCAP file, a Foxglove server, or both")
        self.url, self.session_id, self.token, self.sinks = url.rstrip("/"), session_id, token, sinks
        self._done = asyncio.Event()
        self.connects = 0
        self.events = 0
        self.robot_ns = 0  # the robot time of the last window, ns
        self.subscribed = asyncio.Event()

    def stop(self) -> None:
        self._done.set()

    async def run(self, duration_s: float | None = None) -> int:
        """Record; → the number of events written."""
        follow = asyncio.ensure_future(self._follow())
        stop = asyncio.ensure_future(self._done.wait())
        try:
            await asyncio.wait([follow, stop], timeout=duration_s, return_when=asyncio.FIRST_COMPLETED)
        finally:
            follow.cancel()
            stop.cancel()
            # the feed's close handshake is bounded (FEED_CLOSE_S); so is the wait for it
            await asyncio.wait([follow, stop], timeout=FEED_CLOSE_S + 1.0)
            self._close_sinks()
        return self.events

    def _close_sinks(self) -> None:
        """Each sink closed, files first (a file is complete whatever a live server does), each whatever the others
        raised."""
        for sink in sorted(self.sinks, key=lambda s: not isinstance(s, EstimatesMcap)):
            try:
                sink.close()
            except Exception:  # noqa: BLE001 - one sink's failure must not leave the others open
                log.exception("closing %s failed", type(sink).__name__)

    def write(self, event: dict[str, Any]) -> None:
        """One event of the feed, to every sink."""
        messages, self.robot_ns = event_messages(event, self.robot_ns)
        for topic, payload, log_ns in messages:
            for sink in self.sinks:
                sink.log(topic, payload, log_ns)
        self.events += bool(messages)

    async def _follow(self) -> None:
        from websockets.asyncio.client import connect  # noqa: PLC0415 - as drivers/robot/ws.py
        from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus  # noqa: PLC0415

        backoff = Backoff(0.1, 5.0)
        url = ws_url(self.url, self.session_id, "events", self.token)
        while True:
            try:
                async with connect(url, open_timeout=10, close_timeout=FEED_CLOSE_S, max_size=1 << 20) as ws:
                    self.connects += 1
                    if self.connects > 1:
                        log.warning("event feed reconnected: events sent while it was down are not recorded")
                    backoff.reset()
                    async for message in ws:
                        try:
                            event = json.loads(message)
                        except ValueError:
                            log.error("an event the service sent is not JSON; skipped")
                            continue
                        if isinstance(event, dict) and event.get("event") == "subscribed":
                            self.subscribed.set()
                        if isinstance(event, dict):
                            self.write(event)
                    code = ws.close_code
            except InvalidStatus as exc:
                status = exc.response.status_code
                if status in (401, 403, 404, 410):
                    log.error("the service refused the event feed: HTTP %d: %s", status, body_detail(exc.response.body))
                    return
                code = None
            except ConnectionClosed as exc:
                code = exc.rcvd.code if exc.rcvd is not None else None
            except (TimeoutError, OSError, InvalidHandshake) as exc:
                log.warning("event feed unreachable (%s); retrying", type(exc).__name__)
                code = None
            if code is not None and code in FATAL_CLOSES:
                log.info("the event feed closed (%s): the session is over", code)
                return
            await asyncio.sleep(backoff.next())
