"""The probe port (service.probes.ProbeServer, real sockets): a dripping request is cut at its deadline, a dropped
link is one rate-limited WARNING without a traceback, and connections beyond the cap are closed at once."""

from __future__ import annotations

import logging
import shutil
import socket
import subprocess
import time

import pytest

from service import probes
from service.probes import ProbeServer, health
from service.schemas import ReadyOut


@pytest.fixture
def probe_port(monkeypatch):
    monkeypatch.setattr(probes, "PROBE_REQUEST_S", 1.0)
    monkeypatch.setattr(probes, "MAX_PROBE_CONNECTIONS", 4)
    server = ProbeServer(lambda: health("t"), lambda: (ReadyOut(ready=True, detail="ok"), 200), "127.0.0.1", 0)
    server.start()
    try:
        yield server.port
    finally:
        server.stop()


def _get(port: int) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        return s.recv(4096)


def test_a_request_dripping_in_is_cut_at_its_deadline(probe_port):
    with socket.create_connection(("127.0.0.1", probe_port), timeout=5) as s:
        s.sendall(b"GET /health HTTP/1.1\r\n")
        t0 = time.monotonic()
        with pytest.raises(OSError):  # each header line well inside the per-read timeout, the whole past the deadline
            for k in range(20):
                time.sleep(0.3)
                s.sendall(b"X-Drip-%d: 1\r\n" % k)
                s.settimeout(0.01)
                try:
                    if s.recv(4096) == b"":
                        raise ConnectionResetError("closed")
                except TimeoutError:
                    pass
                s.settimeout(5)
        assert time.monotonic() - t0 < 3.0
    assert _get(probe_port).startswith(b"HTTP/1.1 200")


def test_dropped_links_are_one_warning_without_a_traceback(probe_port, caplog, capsys):
    caplog.set_level(logging.WARNING, logger="service.probes")
    for _ in range(5):  # half a request, then gone: the answer meets a closed socket
        with socket.create_connection(("127.0.0.1", probe_port), timeout=5) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")  # close: RST
            s.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")
    time.sleep(1.5)
    assert _get(probe_port).startswith(b"HTTP/1.1 200")
    records = [r for r in caplog.records if r.name == "service.probes"]
    assert all(r.levelno == logging.WARNING and r.exc_info is None for r in records), records
    assert len([r for r in records if "ended before its answer" in r.getMessage()]) <= 1
    assert "Traceback" not in capsys.readouterr().err


def test_connections_beyond_the_cap_are_closed_at_once(probe_port):
    held = [socket.create_connection(("127.0.0.1", probe_port), timeout=5) for _ in range(4)]
    try:
        time.sleep(0.2)
        with socket.create_connection(("127.0.0.1", probe_port), timeout=5) as extra:
            t0 = time.monotonic()
            assert extra.recv(4096) == b""  # closed without an answer, before any timeout (1 s here)
            assert time.monotonic() - t0 < 0.5
    finally:
        for s in held:
            s.close()
    time.sleep(0.3)
    assert _get(probe_port).startswith(b"HTTP/1.1 200")  # the slots are free again


@pytest.mark.skipif(shutil.which("ss") is None, reason="needs ss (iproute2) to read a socket's listen backlog")
def test_the_listen_backlog_holds_a_burst_of_connects(probe_port):
    """socketserver listens with a backlog of 5: a client connecting and closing in a loop made 1 s liveness probes
    time out (3 of 120) while the main port, backlog 2048, answered every one."""
    out = subprocess.run(["ss", "-ltnH", f"sport = :{probe_port}"], capture_output=True, text=True, check=True).stdout
    backlog = int(out.split()[2])  # State Recv-Q Send-Q …: a listening socket's Send-Q is its backlog
    assert backlog >= probes.PROBE_LISTEN_BACKLOG >= 128, out
