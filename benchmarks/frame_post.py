"""What a robot's refresh costs the service process, by thread — a posted camera frame, and the scene check that
replaces it — against a `/health` GET in the same run.

    python -m benchmarks.frame_post [--requests 1000] [--rounds 3] [--out FILE.json]

One service process (the `served` configuration of benchmarks/service.py) and one session. Its first frame is
embedded; every later POST of the same photo is what a robot's refresh costs: the body is received, the header
probed, the frame decoded and thumbnailed, the scene found unchanged, the frame_received event published and
the answer sent. The robot client now sends the frame's scene thumbnail instead (`POST …/scene`, 2 kB: no decode)
and the frame only if the session wants it. The floor is the framework's own: a `/health` GET through the same
middleware. Sequential
requests from one client; the service's CPU is read from /proc per thread — the event loop's (the process's
main thread) apart from the rest (the frame decoder above all). Rounds alternate frames, scene checks and health
checks;
medians over rounds, in ms per request. The machine's load average is recorded before and after.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import httpx

from benchmarks.report_file import write_report
from drivers.protocol import SCENE_CONTENT_TYPE
from drivers.robot.frames import frame_thumbnail
from drivers.scene_change import thumbnail_bytes

DEFAULT_OUT = Path("reports") / "bench" / "frame_post.json"
API_KEY = "frame-post-benchmark-key-0123456789"


def thread_cpu_seconds(pid: int) -> dict[int, float]:
    """CPU time (user + system) of each thread of process `pid`, s, by thread id."""
    out = {}
    tick = os.sysconf("SC_CLK_TCK")
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except FileNotFoundError:  # the thread ended meanwhile
            continue
        out[int(task.name)] = (int(fields[11]) + int(fields[12])) / tick
    return out


def split_cpu(pid: int, before: dict[int, float], after: dict[int, float]) -> tuple[float, float]:
    """(the event loop's CPU, every other thread's), s, between two `thread_cpu_seconds` readings."""
    loop = after.get(pid, 0.0) - before.get(pid, 0.0)
    rest = sum(cpu - before.get(tid, 0.0) for tid, cpu in after.items() if tid != pid)
    return loop, rest


def measure(pid: int, send, requests: int) -> dict[str, float]:
    """`requests` sequential calls of send() → ms per request: client wall time, loop CPU, other threads' CPU."""
    before = thread_cpu_seconds(pid)
    started = time.perf_counter()
    for _ in range(requests):
        send()
    wall = time.perf_counter() - started
    loop, rest = split_cpu(pid, before, thread_cpu_seconds(pid))
    return {
        "wall_ms": 1e3 * wall / requests,
        "loop_cpu_ms": 1e3 * loop / requests,
        "other_cpu_ms": 1e3 * rest / requests,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.frame_post", description=__doc__.split("\n")[0])
    p.add_argument("--assets", type=Path, default=Path("artifacts/demo"), help="the demo's assets (built if missing)")
    p.add_argument("--requests", type=int, default=1000, help="requests of each kind per round")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    if args.requests < 1 or args.rounds < 1:
        p.error("--requests and --rounds must be ≥ 1")
    if not sys.platform.startswith("linux"):
        p.error("per-thread CPU is read from /proc: Linux only")

    from benchmarks.service import ServerProcess, prepare_assets

    assets = prepare_assets(args.assets)["served"]
    photo = sorted((assets.library / "images").glob("*.png"))[0]  # robot 0's camera frame in the load benchmark
    image = photo.read_bytes()
    load_before = os.getloadavg()
    server = ServerProcess.service(assets, API_KEY, instance_id="frame-post")
    try:
        with httpx.Client(base_url=server.url, timeout=30) as client:
            created = client.post(
                "/sessions", json={"name": "frame-post"}, headers={"Authorization": f"Bearer {API_KEY}"}
            )
            created.raise_for_status()
            session = created.json()
            frames = f"/sessions/{session['session_id']}/frames"
            headers = {"Authorization": f"Bearer {session['robot_token']}", "Content-Type": "image/png"}

            def post_frame() -> None:
                r = client.post(frames, content=image, headers=headers)
                if r.status_code != 202:
                    raise RuntimeError(f"POST frame: HTTP {r.status_code}: {r.text}")

            scene = f"/sessions/{session['session_id']}/scene"
            thumb = thumbnail_bytes(frame_thumbnail(image))
            scene_headers = {**headers, "Content-Type": SCENE_CONTENT_TYPE}

            def check_scene() -> None:
                r = client.post(scene, content=thumb, headers=scene_headers)
                if r.status_code != 200 or r.json()["frame_needed"]:
                    raise RuntimeError(f"POST scene: HTTP {r.status_code}: {r.text} (the scene should be held)")

            def get_health() -> None:
                client.get("/health").raise_for_status()

            post_frame()  # the first frame is embedded; wait for it, so the rounds measure refreshes alone
            status = f"/sessions/{session['session_id']}"
            deadline = time.monotonic() + 60
            operator = {"Authorization": f"Bearer {session['operator_token']}"}
            while client.get(status, headers=operator).json()["counters"]["frames_embedded"] < 1:
                if time.monotonic() > deadline:
                    raise RuntimeError("the first frame was not embedded within 60 s")
                time.sleep(0.1)
            pid = server.proc.pid
            rows: dict[str, list[dict[str, float]]] = {"frame": [], "scene": [], "health": []}
            for _ in range(args.rounds):
                rows["frame"].append(measure(pid, post_frame, args.requests))
                rows["scene"].append(measure(pid, check_scene, args.requests))
                rows["health"].append(measure(pid, get_health, args.requests))
    finally:
        server.stop()
    medians = {kind: {k: statistics.median(r[k] for r in runs) for k in runs[0]} for kind, runs in rows.items()}
    floor = max(medians["health"]["loop_cpu_ms"], 1e-9)
    ratio, scene_ratio = medians["frame"]["loop_cpu_ms"] / floor, medians["scene"]["loop_cpu_ms"] / floor
    print(f"{'request':<30}{'wall, ms':>10}{'loop CPU, ms':>14}{'other threads, ms':>19}")
    labels = {
        "frame": f"POST frame ({len(image) / 1e3:.0f} kB PNG)",
        "scene": f"POST scene ({len(thumb) / 1e3:.0f} kB thumbnail)",
        "health": "GET /health (the floor)",
    }
    for kind, m in medians.items():
        print(f"{labels[kind]:<30}{m['wall_ms']:>10.2f}{m['loop_cpu_ms']:>14.3f}{m['other_cpu_ms']:>19.3f}")
    print(
        f"the loop's CPU per request: a refresh frame {ratio:.1f} ×, a scene check {scene_ratio:.1f} × a /health GET "
        f"(medians of {args.rounds} rounds)"
    )
    write_report(
        args.out,
        {
            "when": datetime.now(UTC).isoformat(timespec="seconds"),
            "command": "python -m benchmarks.frame_post " + " ".join(argv if argv is not None else sys.argv[1:]),
            "image": {"path": str(photo), "bytes": len(image)},
            "requests_per_round": args.requests,
            "rounds": rows,
            "medians": medians,
            "loop_ratio_frame_to_health": round(ratio, 2),
            "loop_ratio_scene_to_health": round(scene_ratio, 2),
            "load_average_before": load_before,
            "load_average_after": os.getloadavg(),
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
