"""`hapticlink` — one console script; each part registers its own subcommands."""

from __future__ import annotations

import argparse
import sys


def build_parser() -> argparse.ArgumentParser:
    from drivers import cli as drivers_cli
    from models import cli as models_cli
    from service import commands as service_commands
    from texture_library import cli as library_cli

    parser = argparse.ArgumentParser(
        prog="hapticlink",
        description="Perceptual haptic texture estimation for model-mediated teleoperation.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for part in (service_commands, models_cli, library_cli, drivers_cli):
        part.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except ValueError as exc:
        # Bad input named precisely by the code below; no traceback for the user.
        print(f"hapticlink {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
