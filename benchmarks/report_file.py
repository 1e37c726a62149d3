"""Where every benchmark's numbers land: one JSON file, its folder made if missing, ending in a newline; its charts, as
PNG files; and what a report says about its run (the command, the machine and how busy it was, the CPU and the
instruction sets an absolute time depends on)."""

from __future__ import annotations

import json
import os
import platform
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from models.offline.host import host
from models.offline.provenance import Input, provenance


def write_report(path: str | Path, report: dict[str, Any], inputs: Sequence[Input] = ()) -> Path:
    """Write `report` as indented JSON to `path` (parents created); returns the path. inputs: the files the run
    read (a dataset, a photo), recorded with their SHA-256 under `provenance` beside the commit that ran
    (`models.offline.provenance`; none: a run on generated input records the commit alone), so the reports'
    staleness test can check them."""
    report = {**report, "host": host(), "provenance": provenance(inputs, report.get("command"))}
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1) + "\n")
    return out


def write_section(path: str | Path, key: str, section: dict[str, Any], inputs: Sequence[Input] = ()) -> Path:
    """Put `section` under `key` in the JSON report at `path`, keeping its other sections (another case's, run at
    another time): the section carries its own `host` and `provenance`, since the file's other sections were made
    elsewhere or at other commits. Returns the path."""
    out = Path(path)
    report = json.loads(out.read_text()) if out.exists() else {}
    report[key] = {**section, "host": host(), "provenance": provenance(inputs, section.get("command"))}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1) + "\n")
    return out


def write_figure(path: str | Path, fig: Any) -> Path:
    """Save a matplotlib figure as a PNG at `path` (parents created) and release it; returns the path."""
    import matplotlib.pyplot as plt

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def command_line(module: str, argv: list[str]) -> str:
    """The command that reproduces a run: `python -m <module>` with its arguments."""
    return " ".join([f"python -m {module}", *argv])


def machine(load_before: tuple[float, float, float]) -> dict[str, Any]:
    """The machine a run used, with its load average before (os.getloadavg() at the start) and now: a number means
    little unless the machine was quiet."""
    return {
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
    }
