"""The framework's floor for the service benchmark: a bare uvicorn ASGI app that takes the same blocks and does
nothing else with them.

`python -m benchmarks.service_floor --port P`. WS /sessions/{id}/ingest: every message is decoded with
numpy (drivers.blocks.decode_binary, the service's own decoder) and acknowledged in the protocol's
format (drivers.protocol.ack_ok); POST /sessions answers a fake session so the real RobotClient can
drive it; WS /sessions/{id}/events is greeted and stays silent; GET /health answers. No FastAPI, no
sessions, no windows: what uvicorn + websockets + numpy cost per block on this machine.
"""

from __future__ import annotations

import argparse
import json

import uvicorn

from drivers.blocks import decode_binary
from drivers.protocol import ack_error, ack_ok


async def app(scope, receive, send) -> None:
    if scope["type"] == "lifespan":
        while (await receive())["type"] != "lifespan.shutdown":
            await send({"type": "lifespan.startup.complete"})
        await send({"type": "lifespan.shutdown.complete"})
        return
    path = scope["path"]
    if scope["type"] == "http":
        while (await receive()).get("more_body"):
            pass
        body = (
            {"status": "ok"}
            if path == "/health"
            else {"session_id": "floor.0", "robot_token": "r", "operator_token": "o"}
        )
        data = json.dumps(body).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 201 if path == "/sessions" else 200,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(data)).encode())],
            }
        )
        await send({"type": "http.response.body", "body": data})
        return
    # websocket
    await receive()  # websocket.connect
    await send({"type": "websocket.accept"})
    ingest = path.endswith("/ingest")
    if not ingest:  # an operator: the service greets it, then events would follow
        await send({"type": "websocket.send", "text": '{"type":"status","event":"subscribed"}'})
    while True:
        message = await receive()
        if message["type"] == "websocket.disconnect":
            return
        if not ingest:
            continue
        try:
            block = decode_binary(message["bytes"])
            text = ack_ok(block.seq, False)
        except (ValueError, TypeError) as exc:
            text = ack_error(None, str(exc))
        await send({"type": "websocket.send", "text": text})


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--port", type=int, required=True)
    args = p.parse_args(argv)
    uvicorn.run(app, host="127.0.0.1", port=args.port, log_level="warning", ws_max_size=8 * 1024 * 1024)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
