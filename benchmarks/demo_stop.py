"""One Ctrl-C stops `hapticlink demo`: seconds from the signal to the summary and to the process's exit.

Run from the repository root:  python -m benchmarks.demo_stop [--assets artifacts/demo] [--runs 3]

Each run starts the demo as `hapticlink demo` does once its assets are ready (service + simulated robot + the
terminal feed, logging at WARNING) in a process of its own and sends it one signal:
  streaming       SIGINT once the first probe's report is printed (windows flowing, the robot mid-stroke)
  SIGTERM         the same with SIGTERM (what a process manager sends)
  first frame     SIGINT the moment the robot's session is open: its camera frame is sent first, so the
                  backbone's first embedding is in flight (onnxruntime; Runtime.stop terminates it)
Reported per case: signal → "demo summary" line and signal → exit (median and max over the runs), the exit
codes, and whether anything printed an ERROR line or a traceback. The target is 2 s (demo.run.STOP_S).
Writes reports/bench/demo_stop.json. The assets are read, never written: build them first with
`hapticlink demo` (or pass --assets of a finished build). Timings on a shared machine are upper bounds: say what
else ran.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from benchmarks.report_file import write_report
from demo.run import STOP_S, DemoAssets
from service.launcher import free_port

DEFAULT_OUT = Path("reports/bench/demo_stop.json")
ROOT = Path(__file__).resolve().parents[1]
START_TIMEOUT_S = 300.0  # loading, cross-checking and warming up the models on a busy machine
EXIT_TIMEOUT_S = 60.0


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    sig: signal.Signals
    marker: str  # the signal is sent when the demo prints a line holding this


CASES = (
    Case("streaming", signal.SIGINT, "── "),
    Case("SIGTERM", signal.SIGTERM, "── "),
    Case("first frame", signal.SIGINT, "robot     strokes"),
)


def read_assets(root: Path) -> DemoAssets:
    """The demo's assets under root as `prepare_assets` left them (nothing is built or written here)."""
    from demo.assets import demo_visual
    from models.offline.featurize import backbone_onnx

    assets = DemoAssets(
        root / "dataset",
        root / "model.onnx",
        root / "tactile.onnx",
        backbone_onnx(demo_visual()),
        root / "library",
        root / "probes",
    )
    missing = [str(p) for p in (assets.model, assets.tactile, assets.library, assets.probes) if not p.exists()]
    if missing:
        raise SystemExit(f"demo assets missing ({', '.join(missing)}): run `hapticlink demo --assets {root}` first")
    return assets


def demo_program(assets: DemoAssets, port: int, per_texture_s: float) -> str:
    """What `hapticlink demo` runs once its assets are ready, with its logging."""
    paths = [str(p) for p in dataclasses.astuple(assets)]
    return (
        "import logging\n"
        "from pathlib import Path\n"
        "from demo.run import DemoAssets, demo\n"
        "logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')\n"
        f"assets = DemoAssets(*map(Path, {paths!r}))\n"
        f"raise SystemExit(demo(assets, port={port}, per_texture_s={per_texture_s!r}))\n"
    )


def run_once(assets: DemoAssets, case: Case, per_texture_s: float) -> dict:
    """One demo process, one signal → seconds to the summary and to the exit, exit code, bad lines."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-c", demo_program(assets, free_port(), per_texture_s)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert proc.stdout is not None
    lines: list[tuple[float, str]] = []  # (monotonic time read, line)
    marked = threading.Event()

    def read() -> None:  # a thread of its own: each line is stamped when it arrives
        for line in proc.stdout:  # type: ignore[union-attr]
            lines.append((time.monotonic(), line))
            if case.marker in line:
                marked.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        if not marked.wait(START_TIMEOUT_S):
            raise RuntimeError(f"no line with {case.marker!r} within {START_TIMEOUT_S:g} s:\n{_text(lines)}")
        sent = time.monotonic()
        proc.send_signal(case.sig)
        code = proc.wait(EXIT_TIMEOUT_S)
        exited = time.monotonic()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(5)
    summary = next((t for t, line in lines if t >= sent and line.startswith("demo summary: ")), None)
    out = _text(lines)
    return {
        "exit_s": round(exited - sent, 3),
        "summary_s": None if summary is None else round(summary - sent, 3),
        "code": code,
        "errors": [line.rstrip() for _, line in lines if "ERROR" in line or "Traceback" in line],
        "stopped_line": next((line.strip() for _, line in lines if line.startswith("stopped ")), None),
        "tail": out[-600:] if code != 0 or summary is None else "",
    }


def _text(lines: list[tuple[float, str]]) -> str:
    return "".join(line for _, line in lines)


def _median(values: list[float]) -> float:
    ordered = sorted(values)
    mid = len(ordered) // 2
    return ordered[mid] if len(ordered) % 2 else (ordered[mid - 1] + ordered[mid]) / 2


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--assets", type=Path, default=Path("artifacts/demo"), help="a finished demo asset build")
    parser.add_argument("--runs", type=int, default=3, help="runs per case")
    parser.add_argument("--per-texture", type=float, default=20.0, metavar="S", help="seconds per probe stroke")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    assets = read_assets(args.assets)
    load = os.getloadavg()
    results: dict[str, dict] = {}
    for case in CASES:
        runs = [run_once(assets, case, args.per_texture) for _ in range(args.runs)]
        exits = [r["exit_s"] for r in runs]
        summaries = [r["summary_s"] for r in runs if r["summary_s"] is not None]
        results[case.name] = {
            "signal": case.sig.name,
            "exit_s_median": round(_median(exits), 3),
            "exit_s_max": max(exits),
            "summary_s_median": round(_median(summaries), 3) if summaries else None,
            "summary_s_max": max(summaries) if summaries else None,
            "summaries_printed": len(summaries),
            "codes": sorted({r["code"] for r in runs}),
            "error_lines": sum(len(r["errors"]) for r in runs),
            "runs": runs,
        }
        r = results[case.name]
        print(
            f"{case.name:12s} {case.sig.name:7s} exit {r['exit_s_median']:.2f} s median, {r['exit_s_max']:.2f} s max; "
            f"summary {r['summary_s_median']} s median, {r['summary_s_max']} s max "
            f"({r['summaries_printed']}/{args.runs} printed); exit codes {r['codes']}; "
            f"ERROR/traceback lines {r['error_lines']}",
            flush=True,
        )
        for run in runs:
            if run["tail"]:
                print(f"  a run without a clean stop printed:\n{run['tail']}", flush=True)
    report = {
        "target_s": STOP_S,
        "runs_per_case": args.runs,
        "per_texture_s": args.per_texture,
        "assets": str(args.assets),
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "load_average_before": [round(x, 2) for x in load],
            "load_average_after": [round(x, 2) for x in os.getloadavg()],
        },
        "cases": results,
    }
    write_report(args.out, report)
    print(f"wrote {args.out} (load average {load[0]:.2f} before, {os.getloadavg()[0]:.2f} after)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
