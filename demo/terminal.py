"""What the demo prints: one status line that updates in place on a terminal (plain lines, one per update, when
stdout is a file or a pipe), lines for what changed (the rendered entry, hysteresis, the out-of-distribution flag,
each probe's report) and the closing summary as a table. Every line fits WIDTH columns."""

from __future__ import annotations

import textwrap
from collections.abc import Mapping, Sequence

from rich.console import Console
from rich.table import Table

from texture_library.attributes import ATTRIBUTES

WIDTH = 100  # columns: every line the demo prints fits
TIME_W, PROBE_W, ID_W = 9, 10, 12  # '  12.5 s ', probe ids, the rendered entry's id (longer ones are cut)
#: two-letter names of the attributes' poles, in ATTRIBUTES order, for the status line's column heads
SHORT = {"rough_smooth": "r→s", "flat_bumpy": "f→b", "sticky_slippery": "s→s", "hard_soft": "h→s"}


def _cut(text: str, width: int) -> str:
    return text if len(text) <= width else text[: width - 1] + "…"


CELL_W = 5  # one rating's column: '-100' and a space before it


def cells(ratings: Mapping[str, float]) -> str:
    """Four bipolar ratings as 5-column cells, in ATTRIBUTES order: '  +12  -30   +5 -100'."""
    return "".join(f"{ratings[a]:+{CELL_W}.0f}" for a in ATTRIBUTES)


def heads() -> str:
    """The four attributes' short names over their cells: '  r→s  f→b  s→s  h→s'."""
    return "".join(f"{SHORT[a]:>{CELL_W}}" for a in ATTRIBUTES)


def status_header() -> str:
    """The column heads of the status line (printed once)."""
    group = 4 * CELL_W
    return (
        f"{'':{TIME_W + PROBE_W + 2}}{'estimate':>{group}}  {'truth':>{group}}\n"
        f"{'time':>{TIME_W}} {'stroking':<{PROBE_W}} {heads()}  {heads()}  error  rendering\n"
        f"{'':{TIME_W + 1}}ratings bipolar −100…100; error: mean |estimate − truth| on 0–100"
    )


def status_line(
    t_s: float,
    probe: str,
    estimate: Mapping[str, float],
    truth: Mapping[str, float],
    error: float,
    chosen: str,
    *,
    held: bool,
    provisional: bool,
    flagged: bool,
) -> str:
    """One update: time, the probe stroked, estimate and truth, their error, the rendered entry and its marks."""
    marks = [m for m, on in (("kept", held), ("provisional", provisional), ("OOD", flagged)) if on]
    line = (
        f"{t_s:{TIME_W - 2}.1f} s {_cut(probe, PROBE_W):<{PROBE_W}} {cells(estimate)}  {cells(truth)}  "
        f"{error:5.1f}  {_cut(chosen, ID_W)}"
    )
    return _cut(line + (" " + " ".join(marks) if marks else ""), WIDTH)


def wrapped(text: str, indent: int = TIME_W + 1) -> str:
    """A long sentence over lines of at most WIDTH columns, continuation lines indented."""
    return "\n".join(textwrap.wrap(text, WIDTH, subsequent_indent=" " * indent, break_on_hyphens=False))


class Terminal:
    """The demo's output: `say` prints lines for good; `status` updates the one status line (in place on a terminal,
    else a plain line at most every `every_s`); `close` ends the status line before the summary."""

    def __init__(self, every_s: float = 2.0) -> None:
        self.console = Console(highlight=False, markup=False, emoji=False, width=WIDTH)
        self.live = self.console.is_terminal
        self.every_s = every_s
        self._last = float("-inf")
        self._status = self.console.status("waiting for the first window …") if self.live else None
        if self._status is not None:
            self._status.start()

    def say(self, text: str) -> None:
        self.console.print(text, soft_wrap=True)

    def status(self, text: str, now_s: float) -> None:
        if self._status is not None:
            self._status.update(text)
        elif now_s - self._last >= self.every_s:
            self._last = now_s
            self.say(text)

    def close(self) -> None:
        if self._status is not None:
            self._status.stop()
            self._status = None

    def table(self, table: Table) -> None:
        self.console.print(table)


def summary_table(errors: Sequence[tuple[str, float, float]], after_s: float) -> Table:
    """Each probe's error after `after_s` seconds of its stroke: the console's estimate and the mean of its
    windows (0–100), with their mean."""
    table = Table(  # as wide as its title, so the title stays on one line
        title=f"error after {after_s:g} s of each probe's stroke (mean |estimate − truth|, 0–100)", min_width=78
    )
    table.add_column("probe (unseen)")
    table.add_column("console estimate", justify="right")
    table.add_column("mean of windows", justify="right")
    for probe, now, mean in errors:
        table.add_row(probe, f"{now:.1f}", f"{mean:.1f}")
    if len(errors) > 1:
        table.add_row(
            "mean",
            f"{sum(e[1] for e in errors) / len(errors):.1f}",
            f"{sum(e[2] for e in errors) / len(errors):.1f}",
            style="bold",
        )
    return table


def robot_line(stats: Mapping[str, int | float]) -> str:
    """The robot's counters that are not zero, in words ('robot: 131 blocks read, 131 acknowledged, …')."""
    words = {
        "read": "blocks read",
        "acked": "acknowledged",
        "resent": "resent",
        "duplicates": "duplicates",
        "rejected": "rejected",
        "lost": "lost",
        "unsent": "unsent at the end",
        "reconnects": "reconnects",
        "saturated": "times saturated",
        "frames_sent": "frames sent",
        "frames_unchanged": "frames unchanged (not sent)",
        "frames_refused": "frames refused",
        "frames_rejected": "frames rejected",
    }
    parts = [f"{stats[k]:g} {w}" for k, w in words.items() if stats.get(k)]
    return wrapped("robot: " + (", ".join(parts) if parts else "nothing sent"), indent=7)
