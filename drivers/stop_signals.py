"""Ctrl-C and SIGTERM as a call on the running event loop, for the long-running commands (robot, operator, demo)."""

from __future__ import annotations

import asyncio
import contextlib
import signal
import sys
from collections.abc import Callable, Iterator
from typing import Any, Protocol

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


class Stoppable(Protocol):
    """A client that runs until its source ends or `duration_s` passes, and winds down when told to stop."""

    def stop(self) -> None: ...

    async def run(self, duration_s: float | None) -> Any: ...


async def run_until_stopped(client: Stoppable, duration_s: float | None, stopping: str) -> Any:
    """`client.run(duration_s)`; the first Ctrl-C (or SIGTERM) says `stopping` on stderr and stops the client the way
    its duration's end does (what it holds is finished), a second quits at once (the run is cancelled)."""
    main = asyncio.current_task()
    interrupted = False

    def on_signal() -> None:
        nonlocal interrupted
        if interrupted:
            if main is not None:
                main.cancel()
            return
        interrupted = True
        print(f"stopping: {stopping} (Ctrl-C again to quit now)", file=sys.stderr, flush=True)
        client.stop()

    with on_stop_signals(on_signal):
        return await client.run(duration_s)
