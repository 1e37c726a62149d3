"""The service benchmark as a picture: latency and CPU against the number of robots, per configuration and replicas.

Run from the repository root:  python -m benchmarks.service_chart [reports/bench/service.json]
                                   [--out reports/bench/service.png]

Two panels from one report (written by `python -m benchmarks.service`): the end-to-end window latency p99 against
robots (log scale, the 20 ms target dashed), and the service's CPU per robot-second by accounting (the 10 ms line is
100 robots per core). One line per configuration and replica count; a row that is not valid (its generator fell
behind, or robots were refused: their windows count as lost) is drawn hollow, since it measured something else
than the service serving that load.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from benchmarks.report_file import write_figure  # noqa: E402

DEFAULT_REPORT = Path("reports/bench/service.json")
DEFAULT_OUT = Path("reports/bench/service.png")
E2E_TARGET_MS = 20.0
CPU_TARGET_MS = 10.0  # ms of service CPU per robot-second: 100 robots per core


@dataclass(frozen=True)
class Point:
    robots: int
    e2e_p99_ms: float
    cpu_ms_per_robot_s: float
    valid: bool


def curves(report: dict) -> dict[tuple[str, int], list[Point]]:
    """(config, replicas) → its rows in order of robots, but for rows that measured nothing (refused at set-up: no
    window arrived, so there is no latency to draw). ValueError naming what a report without rows lacks."""
    rows = report.get("results")
    if not rows:
        raise ValueError("the report has no results: write it with python -m benchmarks.service")
    out: dict[tuple[str, int], list[Point]] = {}
    for r in rows:
        if r["e2e_ms"]["p99"] is None:
            continue
        point = Point(int(r["robots"]), float(r["e2e_ms"]["p99"]), float(r["service_cpu_ms_per_robot_s"]), r["valid"])
        out.setdefault((r["config"], int(r["replicas"])), []).append(point)
    return {key: sorted(points, key=lambda p: p.robots) for key, points in out.items()}


def chart(report: dict, out: Path) -> Path:
    fig, (lat, cpu) = plt.subplots(1, 2, figsize=(12, 4.4))
    for (config, replicas), points in curves(report).items():
        label = f"{config}, {replicas} replica{'s' if replicas > 1 else ''}"
        style = {"ls": "-" if config == "served" else "--", "marker": "o" if replicas == 1 else "s"}
        for ax, values in ((lat, [p.e2e_p99_ms for p in points]), (cpu, [p.cpu_ms_per_robot_s for p in points])):
            (line,) = ax.plot([p.robots for p in points], values, label=label, **style)
            hollow = [(p.robots, v) for p, v in zip(points, values, strict=True) if not p.valid]
            if hollow:  # drawn over the filled marker
                ax.plot(*zip(*hollow, strict=True), ls="", marker=style["marker"], mfc="white", mec=line.get_color())
    lat.axhline(E2E_TARGET_MS, color="k", ls=":", lw=0.9, label=f"{E2E_TARGET_MS:g} ms target")
    cpu.axhline(CPU_TARGET_MS, color="k", ls=":", lw=0.9, label="100 robots per core")
    lat.set_yscale("log")
    lat.set_ylabel("window end-to-end p99, ms")
    cpu.set_ylabel("service CPU per robot-second, ms")
    for ax in (lat, cpu):
        ax.set_xscale("log")
        ax.set_xlabel("robots (hollow: row not valid — generator behind or robots refused)")
        ax.grid(alpha=0.3, which="both")
    lat.legend(fontsize=7, loc="upper left")
    machine = report.get("machine", {})
    fig.suptitle(
        f"python -m benchmarks.service — {machine.get('cpus', '?')} cores, load before "
        f"{machine.get('load_average_before', ['?'])[0]}",
        fontsize=9,
    )
    fig.tight_layout()
    return write_figure(out, fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("report", nargs="?", type=Path, default=DEFAULT_REPORT, help="a service.json report")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    try:
        report = json.loads(args.report.read_text())
        print(f"wrote {chart(report, args.out)}")
    except (OSError, ValueError, KeyError) as exc:
        print(f"error: {args.report}: {exc!r}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
