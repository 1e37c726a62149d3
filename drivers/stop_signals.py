"""Ctrl-C and SIGTERM as a call on the running event loop, for the long-running commands (robot, operator, demo)."""

from __future__ import annotations

import asyncio
import contextlib
import signal
from collections.abc import Callable, Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def on_stop_signals(handler: Callable[[], None]) -> Iterator[list[signal.Signals]]:
    """Call `handler` on SIGINT or SIGTERM while inside; yields the signals it could take over.

    Where the loop cannot take signals (Windows, a loop outside the main thread, e.g. a test's) the list is
    empty and the signals keep their default meaning. The handlers are removed on the way out.
    """
    loop = asyncio.get_running_loop()
    installed: list[signal.Signals] = []
    for sig in STOP_SIGNALS:
        try:
            loop.add_signal_handler(sig, handler)
            installed.append(sig)
        except (NotImplementedError, RuntimeError, ValueError):
            pass
    try:
        yield installed
    finally:
        for sig in installed:
            loop.remove_signal_handler(sig)
