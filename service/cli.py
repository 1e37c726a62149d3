"""`hapticlink` — one console script; each part registers its own subcommands.

The parts are found through the `hapticlink.commands` entry points (pyproject.toml), so the
service names no offline module: the offline wing plugs its commands in from above.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from importlib.metadata import EntryPoint, PackageNotFoundError, entry_points, version

COMMAND_GROUP = "hapticlink.commands"
HELP_ORDER = ("service", "demo", "offline", "library", "drivers")  # parts not named here follow, by name


def _help_rank(part: EntryPoint) -> tuple[int, str]:
    return (HELP_ORDER.index(part.name) if part.name in HELP_ORDER else len(HELP_ORDER), part.name)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hapticlink",
        description="Perceptual haptic texture estimation for model-mediated teleoperation.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_installed_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    parts = sorted(entry_points(group=COMMAND_GROUP), key=_help_rank)
    if not parts:
        raise RuntimeError(f"no {COMMAND_GROUP!r} entry points: install hapticlink first (pip install -e .)")
    for part in parts:
        part.load()(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    warnings.formatwarning = _warning_line  # a user reads what went wrong, not the line of code that said so
    try:  # a Ctrl-C while the commands' modules load (the first second) is a stop, not a traceback
        args = build_parser().parse_args(argv)
    except KeyboardInterrupt:
        return 130
    try:
        return int(args.func(args) or 0)
    except ValueError as exc:
        # Bad input named precisely by the code below; no traceback for the user.
        print(f"hapticlink {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a path that cannot be read or written (missing, a file where a folder is due, no access)
        print(f"hapticlink {args.command}: error: {_os_error(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


def _installed_version() -> str:
    try:
        return version("hapticlink")
    except PackageNotFoundError:  # run from a checkout that was never installed
        return "(not installed)"


def _warning_line(message: Warning | str, category: type[Warning], *_: object, **__: object) -> str:
    return f"warning: {message}\n"


def _os_error(exc: OSError) -> str:
    """Which path and what went wrong with it, in one line: "/nope/v.wav: No such file or directory"."""
    where = " → ".join(str(p) for p in (exc.filename, exc.filename2) if p is not None)
    if not where:
        return str(exc)
    return f"{where}: {exc.strerror or type(exc).__name__}"


if __name__ == "__main__":
    sys.exit(main())
