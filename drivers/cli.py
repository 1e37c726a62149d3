"""Subcommands of the drivers part: robot."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    """Registered once the robot client exists."""
