"""Subcommands of the texture library: library import-hatt, render, list."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    """Registered once the library commands exist."""
