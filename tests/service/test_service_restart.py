"""A restart of the service, with the real processes: `hapticlink serve`, `hapticlink robot` and `hapticlink operator`
(following the robot by its id), a SIGTERM and a new process on the same port. The robot never exits because of
the restart: it opens a new session and resends what was never acknowledged; the operator follows it there with no
action; the old session is answered 410 with the reason; no ERROR line in the service's log. Once the new session's
windows flow, a Ctrl-C each ends the robot and the operator, as a user stops them."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

from service.launcher import ServerProcess, free_port

REPO = Path(__file__).resolve().parents[2]
ROBOT = "robot-7"
API_KEY = "test-fleet-key-0123456789"  # conftest's fleet key


def _serve(kit, tactile_model, library_dir, port: int) -> ServerProcess:
    return ServerProcess(
        [
            sys.executable,
            "-m",
            "service.cli",
            "serve",
            "--model",
            str(tactile_model),
            "--library",
            str(library_dir),
            "--instance-id",
            "replica-r",
        ],
        {"HAPTICLINK_LOG_LEVEL": "info", "HAPTICLINK_API_KEYS": kit.API_KEY, "HAPTICLINK_SESSION_BURST": "100"},
        cwd=REPO,
        timeout_s=120,
        capture=True,
        port=port,
    )


def _robot_session(url: str, kit) -> dict | None:
    try:
        r = httpx.get(f"{url}/robots/{ROBOT}/session", headers=kit.FLEET, timeout=5)
    except httpx.HTTPError:
        return None
    return r.json() if r.status_code == 200 else None


def _wait(predicate, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise TimeoutError(what)


class Lines:
    """A child process's output, line by line, read by a thread as it comes (so the test can wait for a line)."""

    def __init__(self, stream) -> None:
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        for line in stream:
            self.lines.append(line.rstrip("\n"))

    def text(self) -> str:
        self._thread.join(timeout=30)
        return "\n".join(self.lines)

    def has(self, needle: str) -> bool:
        return any(needle in line for line in list(self.lines))


class RobotFeed:
    """`WS /robots/{id}/events` with the fleet key, reconnected after the restart: the windows it carried."""

    def __init__(self, url: str) -> None:
        self.feed = f"{url.replace('http', 'ws', 1)}/robots/{ROBOT}/events?token={API_KEY}"
        self.windows: list[tuple[str, float]] = []
        self.stopped = threading.Event()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        from websockets.sync.client import connect

        while not self.stopped.is_set():
            try:
                with connect(self.feed, open_timeout=5) as ws:
                    while not self.stopped.is_set():
                        try:
                            event = json.loads(ws.recv(timeout=0.5))
                        except TimeoutError:
                            continue
                        if event["type"] == "window":
                            self.windows.append((event["session_id"], event["t_start_s"]))
            except Exception:  # noqa: BLE001 - the service restarting: connect again
                time.sleep(0.1)


def _streamed_on(windows: list[tuple[str, float]], old: str, new: str) -> float:
    """Seconds the new session's windows reach past the old session's last (-inf before both have one)."""
    starts = {sid: [t for s, t in windows if s == sid] for sid in (old, new)}
    return max(starts[new]) - max(starts[old]) if starts[old] and starts[new] else float("-inf")


def _hapticlink(*argv: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "service.cli", *argv],
        env={**os.environ, "HAPTICLINK_API_KEY": API_KEY},
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["ws", "http"])
def test_a_restart_on_the_same_port_is_resumed_by_the_robot_and_followed_by_the_operator(
    kit, tactile_model, library_dir, tmp_path, transport
):
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    first = _serve(kit, tactile_model, library_dir, port)
    source = f"simulated:{library_dir}:synth_000"
    robot = _hapticlink(
        "robot", "--source", source, "--url", url, "--robot-id", ROBOT, "--transport", transport, "--duration", "90"
    )
    wav = f"wav:{tmp_path / 'out.wav'}"
    operator = _hapticlink(
        "operator", "--url", url, "--robot", ROBOT, "--device", "simulated", "--out", wav, "--duration", "90"
    )
    robot_out, robot_err, operator_err = Lines(robot.stdout), Lines(robot.stderr), Lines(operator.stderr)
    operator_out = Lines(operator.stdout)
    feed = RobotFeed(url)
    second = None
    try:
        before = _wait(lambda: _robot_session(url, kit), 60, "the robot opened no session")
        old = before["session_id"]
        assert old.startswith("replica-r.")
        _wait(lambda: operator_err.has(f"in its session {old}"), 60, "the operator did not follow the robot")
        time.sleep(1.0)  # it streams; its operator renders
        first_code = first.stop(signal.SIGTERM)
        first_log = first.proc.stdout.read()
        second = _serve(kit, tactile_model, library_dir, port)
        ready_at = time.monotonic()
        after = _wait(
            lambda: (s := _robot_session(url, kit)) and s["session_id"] != old and s["lost"] is None and s,
            30,
            "the robot opened no new session after the restart",
        )
        resumed_s = time.monotonic() - ready_at
        new = after["session_id"]
        # the old session is answered 410 with the reason, to a caller with a credential
        with httpx.Client(base_url=url, timeout=10) as client:
            r = client.get(f"/sessions/{old}", headers={"Authorization": "Bearer any-token"})
            assert r.status_code == 410 and "replica-r restarted" in r.json()["detail"], r.text
            assert client.get(f"/sessions/{old}").status_code == 401  # the credential first
        _wait(lambda: operator_err.has(f"in its session {new}"), 30, "the operator did not follow the new session")
        # both go on in the new session until its windows reach 2 s past the old one's last on the robot's feed (what
        # was resent comes first); then a Ctrl-C each (the --duration above only bounds a run that goes wrong)
        _wait(lambda: _streamed_on(feed.windows, old, new) >= 2.0, 30, "the new session's windows did not flow on")
        robot.send_signal(signal.SIGINT)  # it stops reading, delivers what is buffered and exits
        robot.wait(timeout=90)
        operator.send_signal(signal.SIGINT)  # it stops at the next block, finishes the WAV and says what it rendered
        operator.wait(timeout=90)
        time.sleep(1.0)  # the last windows reach the robot's feed
    finally:
        feed.stopped.set()
        for proc in (robot, operator):
            if proc.poll() is None:
                proc.kill()
        if first.proc.poll() is None:
            first.proc.kill()
    second_code = second.stop(signal.SIGTERM)
    second_log = second.proc.stdout.read()
    # the robot never exited because of the restart: it resumed once and delivered everything
    assert robot.returncode == 0, robot_err.text()[-3000:]
    stats = json.loads(robot_out.text().strip().splitlines()[-1])
    assert stats["resumed"] == 1 and stats["lost"] == 0 and stats["unsent"] == 0 and stats["rejected"] == 0, stats
    assert re.findall(r"^session (\S+)$", robot_out.text(), re.M) == [old, new]
    assert "opening a new session and resending" in robot_err.text()
    assert resumed_s < 5.0, resumed_s
    # the operator followed it with no action, and rendered on
    assert operator.returncode == 0, operator_err.text()[-3000:]
    assert "rendered" in operator_out.text()
    # the robot's feed carried both sessions' windows, none twice, with no gap at the restart but the last window the
    # old process could not complete (at most one hop: 0.5 s)
    starts = [t for _, t in feed.windows]
    assert {sid for sid, _ in feed.windows} == {old, new}
    assert len(starts) == len(set(starts)), sorted(starts)
    ordered = sorted(starts)
    assert max(b - a for a, b in zip(ordered, ordered[1:])) <= 1.0 + 1e-6, ordered
    # a graceful shutdown each time (uvicorn exits by the signal it handled, once it has shut down)
    assert first_code in (0, -signal.SIGTERM) and second_code in (0, -signal.SIGTERM)
    for log in (first_log, second_log):
        assert "Application shutdown complete" in log
        assert not [line for line in log.splitlines() if " ERROR " in line or line.startswith("Traceback")], log
        assert API_KEY not in log
