"""A session's estimates live in Foxglove: `hapticlink record --foxglove [HOST:]PORT` (off unless asked for).

The recorder (drivers.estimates_mcap.SessionRecorder) hands each event's messages to this sink too: the same
channels with the same JSON schemas as the MCAP file, published over the Foxglove WebSocket protocol by
`foxglove-sdk`'s server, each message at its robot-clock log time. It runs in the recorder's process, beside the
service, not inside it: the service pays for one more event subscriber, nothing else.
"""

from __future__ import annotations

import logging
from typing import Any

from drivers.estimates_mcap import CHANNELS

log = logging.getLogger("hapticlink.record")

#: the longest the recorder waits for the Foxglove server to stop, s
STOP_WAIT_S = 3.0


class FoxgloveLive:
    """A Foxglove WebSocket server on host:port (port 0: a free one; see `port`) advertising CHANNELS."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "hapticlink") -> None:
        import foxglove

        self._context = foxglove.Context()
        self._channels = {
            topic: foxglove.Channel(
                topic,
                schema=foxglove.Schema(name=schema_name, encoding="jsonschema", data=_json(schema)),
                message_encoding="json",
                context=self._context,
            )
            for topic, (schema_name, schema, _) in CHANNELS.items()
        }
        self._server = foxglove.start_server(name=name, host=host, port=port, context=self._context)
        self.host = host
        self.port = int(self._server.port)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def log(self, topic: str, payload: dict[str, Any], log_ns: int) -> None:
        self._channels[topic].log(payload, log_time=log_ns)

    def close(self) -> None:
        """Stop the server, waiting at most STOP_WAIT_S for it: the recorder must end even if a client holds it up
        (the server's threads end with the process)."""
        import threading

        stopper = threading.Thread(target=self._server.stop, name="foxglove-stop", daemon=True)
        stopper.start()
        stopper.join(STOP_WAIT_S)
        if stopper.is_alive():
            log.warning("the Foxglove server did not stop within %g s; leaving it to the process's exit", STOP_WAIT_S)


def _json(obj: object) -> bytes:
    import json

    return json.dumps(obj).encode()
