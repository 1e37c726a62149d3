"""The hostile-client probe as a picture: the well-behaved robots' window latency through the run.

Run from the repository root:  python -m benchmarks.hostile_chart REPORT.json [LABEL=REPORT.json ...]
                                   [--out reports/bench/hostile.png]

Each report (written by `python -m benchmarks.hostile`) gives one panel: the well-behaved robots' end-to-end
p50 and p99 per 2 s (log scale), with the attacks and the burst robots' streaming shaded, and the 100 ms target.
Several reports (e.g. this code and the code before, run the same day) sit side by side on one y scale.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from benchmarks.report_file import write_figure  # noqa: E402

DEFAULT_OUT = Path("reports/bench/hostile.png")
TARGET_MS = 100.0


def parse_report(arg: str) -> tuple[str, dict]:
    """`LABEL=path` or `path` (labelled by its file name) → (label, report)."""
    label, _, path = arg.rpartition("=")
    report = json.loads(Path(path).read_text())
    if "well_behaved_timeline" not in report:
        raise ValueError(f"{path} has no well_behaved_timeline: write it with this version of benchmarks.hostile")
    return label or Path(path).stem, report


def chart(reports: list[tuple[str, dict]], out: Path) -> Path:
    fig, axes = plt.subplots(1, len(reports), figsize=(6 * len(reports), 4.2), sharey=True, squeeze=False)
    for ax, (label, r) in zip(axes[0], reports):
        bins = r["well_behaved_timeline"]
        t = [b["t_s"] + 1.0 for b in bins]  # bin centres
        ax.plot(t, [b["e2e_p50"] for b in bins], marker="o", ms=3, label="p50")
        ax.plot(t, [b["e2e_p99"] for b in bins], marker="^", ms=3, label="p99")
        phases = r["phases_s"]
        ax.axvspan(*phases["attacks"], color="tab:red", alpha=0.12, label="attacks (huge blocks, session flood)")
        ax.axvspan(*phases["burst_streaming"], color="tab:orange", alpha=0.12, label="burst robots streaming")
        ax.axhline(TARGET_MS, color="k", ls="--", lw=0.8, label=f"{TARGET_MS:g} ms target")
        wb, health = r["well_behaved"], r["health_ms"]
        ax.set_title(
            f"{label}\n/health p99 {health['p99']:.0f} ms (max {health['max']:.0f}), "
            f"reconnects {wb['robot_counts']['reconnects']}",
            fontsize=9,
        )
        ax.set_yscale("log")
        ax.set_xlabel("s since the well-behaved robots started")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(f"well-behaved robots' window e2e, ms ({reports[0][1]['robots']} robots)")
    axes[0][0].legend(fontsize=7, loc="upper left")
    return write_figure(out, fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("reports", nargs="+", help="hostile.json reports, each optionally LABEL=path")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    try:
        reports = [parse_report(a) for a in args.reports]
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {chart(reports, args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
