"""What a refused request costs the service: CPU per request, against /health answered before the middleware stack.

Run from the repository root:  python -m benchmarks.refusals [--requests 1000] [--assets artifacts/demo]

One service process (the `served` configuration of benchmarks/service.py) and one session. Each case sends
`--requests` requests one after another from this process and reads the service's CPU time before and after:
  health              GET /health (the probe answers it in front of the middleware stack: the floor here)
  ingest_bad_token    the ingest WebSocket's handshake with a wrong robot token (the service closes it)
  frame_bad_token     the texture's photo POSTed as a camera frame with a wrong robot token (401)
  session_bad_key     POST /sessions with a wrong fleet key (401)
/health runs first and last: the spread between the two says how steady the machine was. Reported per case:
the service's CPU per request (µs) and the answers seen. A robot that may not start yet sends a handshake and a
frame every Retry-After; their cost bounds what refusing them can save. Writes reports/bench/refusals.json.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import secrets
import sys
import time
from collections import Counter
from collections.abc import Awaitable, Callable
from pathlib import Path

import httpx
import websockets

from benchmarks.loadgen import frame_of
from benchmarks.report_file import command_line, machine, write_report
from benchmarks.service import DEFAULT_ASSETS, ServerProcess, prepare_assets
from drivers.protocol import ws_url

DEFAULT_OUT = Path("reports/bench/refusals.json")
CASES = ("health", "ingest_bad_token", "frame_bad_token", "session_bad_key", "health")


async def _ingest_handshake(url: str, session_id: str) -> str:
    """Open the ingest socket with a wrong token → how it ended: the HTTP status, or the close code."""
    try:
        async with websockets.connect(ws_url(url, session_id, "ingest", "wrong-token")) as ws:
            await ws.recv()
    except websockets.InvalidStatus as exc:
        return f"HTTP {exc.response.status_code}"
    except websockets.ConnectionClosed as exc:
        return f"close {exc.rcvd.code if exc.rcvd else 'none'}"
    return "open"  # never: recv() returns only a message, and the service sends none to a refused robot


async def measure(server: ServerProcess, api_key: str, frame: bytes, requests: int) -> list[dict]:
    """Each case's service CPU per request (µs) and its answers, in CASES order."""
    async with httpx.AsyncClient(base_url=server.url, timeout=30.0) as client:
        r = await client.post("/sessions", json={}, headers={"Authorization": f"Bearer {api_key}"})
        r.raise_for_status()
        session_id = r.json()["session_id"]
        wrong = {"Authorization": "Bearer wrong-key"}

        async def health() -> str:
            return f"HTTP {(await client.get('/health')).status_code}"

        async def frame_post() -> str:
            headers = {**wrong, "Content-Type": "image/png"}
            r = await client.post(f"/sessions/{session_id}/frames", content=frame, headers=headers)
            return f"HTTP {r.status_code}"

        async def session_post() -> str:
            return f"HTTP {(await client.post('/sessions', json={}, headers=wrong)).status_code}"

        calls: dict[str, Callable[[], Awaitable[str]]] = {
            "health": health,
            "ingest_bad_token": lambda: _ingest_handshake(server.url, session_id),
            "frame_bad_token": frame_post,
            "session_bad_key": session_post,
        }
        rows = []
        for name in CASES:
            answers: Counter[str] = Counter()
            cpu0, wall0 = server.cpu_seconds(), time.perf_counter()
            for _ in range(requests):
                answers[await calls[name]()] += 1
            cpu, wall = server.cpu_seconds() - cpu0, time.perf_counter() - wall0
            rows.append(
                {
                    "case": name,
                    "requests": requests,
                    "service_cpu_us_per_request": round(1e6 * cpu / requests, 1),
                    "wall_ms_per_request": round(1e3 * wall / requests, 3),
                    "answers": dict(answers),
                }
            )
            print(f"  {name:<18} {rows[-1]['service_cpu_us_per_request']:8.1f} µs of service CPU  {dict(answers)}")
        return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--requests", type=int, default=1000, help="requests per case (default 1000)")
    p.add_argument(
        "--assets",
        type=Path,
        default=DEFAULT_ASSETS,
        help=f"the demo's assets, built there when missing (default {DEFAULT_ASSETS})",
    )
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    if args.requests < 1:
        p.error("--requests must be ≥ 1")
    load_before = os.getloadavg()
    assets = prepare_assets(args.assets)["served"]
    api_key = secrets.token_urlsafe(24)
    frame = frame_of(assets.library, 0)
    server = ServerProcess.service(assets, api_key)
    try:
        print(f"service CPU per request, {args.requests} requests per case:", flush=True)
        rows = asyncio.run(measure(server, api_key, frame, args.requests))
    finally:
        server.stop()
    report = {
        "benchmark": "refusals",
        "command": command_line("benchmarks.refusals", argv if argv is not None else sys.argv[1:]),
        "machine": machine(load_before),
        "frame_bytes": len(frame),
        "results": rows,
    }
    write_report(args.out, report)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
