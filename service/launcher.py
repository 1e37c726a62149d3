"""Start a server in a child process and wait until it answers: the tests, the benchmarks and the local topology.

Nothing here is imported by the running service; it needs the standard library alone.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Sequence
from pathlib import Path


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free on `host` a moment ago (the OS picks it)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def answers(url: str, timeout_s: float = 2.0) -> bool:
    """True when GET url answers 200 within timeout_s."""
    with contextlib.suppress(OSError, urllib.error.URLError):
        with urllib.request.urlopen(url, timeout=timeout_s) as response:
            return response.status == 200
    return False


def wait_until_ready(
    url: str,
    *,
    timeout_s: float = 60.0,
    alive: Callable[[], bool] = lambda: True,
    describe: Callable[[], str] = str,
    every_s: float = 0.1,
) -> None:
    """Poll GET url until it answers 200.

    alive     False once the server has died: stop waiting at once
    describe  what to add to the error (a log tail)
    raises RuntimeError naming the url when the server died or did not answer within timeout_s
    """
    deadline = time.monotonic() + timeout_s
    while not answers(url):
        if not alive():
            raise RuntimeError(f"the server exited before {url} answered{_detail(describe())}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"{url} did not answer 200 within {timeout_s:g} s{_detail(describe())}")
        time.sleep(every_s)


def _detail(text: str) -> str:
    return f":\n{text}" if text else ""


class ServerProcess:
    """A server in a child process on a free loopback port, ready when `ready_path` answers 200.

    argv gets `--port N` appended (port: this one, e.g. a restart's on its predecessor's; default a free one) and env
    is added to this process's environment. capture: stdout and
    stderr together in `proc.stdout` (read it after stopping); else stdout is dropped and stderr kept
    for the error message when the server fails to start.
    """

    def __init__(
        self,
        argv: Sequence[str],
        env: dict[str, str] | None = None,
        *,
        ready_path: str = "/ready",
        timeout_s: float = 180.0,
        cwd: str | Path | None = None,
        capture: bool = False,
        port: int | None = None,
    ) -> None:
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        output = (subprocess.PIPE, subprocess.STDOUT) if capture else (subprocess.DEVNULL, subprocess.PIPE)
        self.proc = subprocess.Popen(
            [*argv, "--port", str(self.port)],
            env={**os.environ, **(env or {})},
            cwd=cwd,
            stdout=output[0],
            stderr=output[1],
            text=True,
        )
        try:
            wait_until_ready(
                self.url + ready_path,
                timeout_s=timeout_s,
                alive=lambda: self.proc.poll() is None,
                describe=self._output_if_dead,
            )
        except RuntimeError:
            self.proc.kill()
            raise

    def _output_if_dead(self) -> str:
        if self.proc.poll() is None:
            return ""
        stream = self.proc.stderr or self.proc.stdout
        return stream.read() if stream else ""

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 20.0) -> int:
        """Ask it to stop (Ctrl-C by default), kill it after timeout_s; its exit code."""
        self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait()
