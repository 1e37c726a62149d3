"""`hapticlink serve`: flags override the environment, bad settings are named, and Ctrl-C shuts down cleanly."""

from __future__ import annotations

import re
import signal
import socket
import sys
from pathlib import Path

import httpx
import pytest

from service.cli import build_parser, main
from service.commands import settings_from_args
from service.launcher import ServerProcess

REPO = Path(__file__).resolve().parents[2]


def test_flags_override_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("HAPTICLINK_PORT", "9001")
    monkeypatch.setenv("HAPTICLINK_HOST", "0.0.0.0")
    args = build_parser().parse_args(["serve", "--model", str(tmp_path / "m.onnx"), "--port", "9100"])
    settings = settings_from_args(args)
    assert settings.port == 9100 and settings.host == "0.0.0.0" and settings.model_path == tmp_path / "m.onnx"
    assert settings.serving_policy == "adaptive" and settings.cheap_model_path is None  # the defaults
    monkeypatch.setenv("HAPTICLINK_SERVING_POLICY", "adaptive")
    args = build_parser().parse_args(["serve", "--policy", "always-full", "--cheap-model", str(tmp_path / "c.onnx")])
    settings = settings_from_args(args)
    assert settings.serving_policy == "always-full" and settings.cheap_model_path == tmp_path / "c.onnx"
    monkeypatch.setenv("HAPTICLINK_TACTILE_MODEL_PATH", str(tmp_path / "env.onnx"))
    args = build_parser().parse_args(["serve", "--tactile-model", str(tmp_path / "t.onnx")])
    assert settings_from_args(args).tactile_model_path == tmp_path / "t.onnx"


def test_bad_settings_are_named_without_a_traceback(capsys, tmp_path):
    assert main(["serve", "--model", str(tmp_path / "missing.onnx"), "--library", str(tmp_path)]) == 2
    assert "model not found" in capsys.readouterr().err
    assert main(["serve", "--port", "70000"]) == 2
    assert "--port (HAPTICLINK_PORT): Input should be less than or equal to 65535" in capsys.readouterr().err


def test_serve_runs_and_stops_cleanly_on_ctrl_c(kit, tactile_model, library_dir):
    env = {"HAPTICLINK_LOG_LEVEL": "info", "HAPTICLINK_API_KEYS": kit.API_KEY}
    server = ServerProcess(
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
            "cli",
        ],
        env,
        cwd=REPO,
        timeout_s=180,  # a hang guard: on a busy host the child imports and warms up for a minute or more
        capture=True,
    )
    proc, port = server.proc, server.port
    try:
        created = httpx.post(f"http://127.0.0.1:{port}/sessions", json={}, headers=kit.FLEET).json()
        assert created["session_id"].startswith("cli.")
        proc.send_signal(signal.SIGINT)
        output, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, output
    assert "Application shutdown complete" in output and "Traceback" not in output


def test_a_client_cannot_write_a_line_of_its_own_into_the_log(kit, tactile_model, library_dir):
    """A refused handshake whose URL carries line breaks: the served process's log (as an operator reads it)
    holds the refusal on one line, the breaks escaped; no forged ERROR line, no traceback."""
    server = ServerProcess(
        [sys.executable, "-m", "service.cli", "serve", "--model", str(tactile_model), "--library", str(library_dir)],
        {"HAPTICLINK_API_KEYS": kit.API_KEY},
        cwd=REPO,
        timeout_s=180,  # a hang guard: on a busy host the child imports and warms up for a minute or more
        capture=True,
    )
    forged = "x%0A2001-01-01%2000:00:00,000%20ERROR%20service.state:%20forged%0DTraceback%20(most%20recent%20call)"
    try:
        for route in ("ingest", "events"):
            with socket.create_connection(("127.0.0.1", server.port), timeout=10) as raw:
                raw.sendall(
                    # with a token: the credential is judged first, so only then is the forged id looked up (and logged)
                    f"GET /sessions/{forged}/{route}?token=not-a-token HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\n"
                    "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                    "Sec-WebSocket-Version: 13\r\n\r\n".encode()
                )
                assert raw.recv(4096).startswith(b"HTTP/1.1 404"), route
    finally:
        assert server.stop() == 0
    output = server.proc.stdout.read()
    lines = output.splitlines()
    assert not [line for line in lines if line.startswith("2001-01-01") or line.startswith("Traceback")], output
    # no line at ERROR (the service's "<date> <time> ERROR …", uvicorn's "ERROR: …"): the forged one is inside a WARNING
    assert not [line for line in lines if re.match(r"(\S+ \S+ )?ERROR\b", line)], output
    refused = [line for line in lines if "socket for session" in line and "refused: 404" in line]
    assert len(refused) == 2 and all("\\n2001-01-01 00:00:00,000 ERROR" in line for line in refused), output


def test_every_path_serve_reads_is_checked_before_it_starts(capsys, tmp_path, library_dir, tactile_model):
    """A missing backbone or fallback model, or a folder given as the model, left the service running, never ready."""
    model, library = str(tactile_model), str(library_dir)
    cases = {
        ("--backbone", str(tmp_path / "nope.onnx")): "visual backbone not found",
        ("--tactile-model", str(tmp_path / "nope.onnx")): "tactile fallback model not found",
        ("--cheap-model", str(tmp_path / "nope.onnx")): "cheap model not found",
    }
    for (flag, value), why in cases.items():
        assert main(["serve", "--model", model, "--library", library, flag, value]) == 2
        err = capsys.readouterr().err
        assert why in err and f"{flag} or HAPTICLINK_" in err and "Traceback" not in err
    assert main(["serve", "--model", library, "--library", library]) == 2
    assert "model must be a file, got the folder" in capsys.readouterr().err
    assert main(["serve", "--model", model, "--library", model]) == 2
    assert "library must be a folder, got the file" in capsys.readouterr().err


def test_an_os_error_is_one_line_naming_the_path_not_a_traceback(capsys, tmp_path):
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" / "ds"
    status = main(
        ["dataset", "build", "--source", "synthetic", "--n-textures", "3", "--no-features", "--out", str(out)]
    )
    err = capsys.readouterr().err
    assert status == 2 and "Traceback" not in err
    assert (
        err.startswith("hapticlink dataset: error: ") and str(tmp_path / "afile") in err and len(err.splitlines()) == 1
    )


def test_an_unreachable_redis_is_one_line_without_its_password(capsys, tactile_model, library_dir):
    """It ended the service at start-up with a traceback in one enormous log line."""
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    flags = ["--model", str(tactile_model), "--library", str(library_dir), "--broker", "redis"]
    assert main(["serve", *flags, "--redis-url", f"redis://robot:hunter2@127.0.0.1:{port}/0"]) == 2
    err = capsys.readouterr().err
    assert f"cannot reach Redis at redis://robot:***@127.0.0.1:{port}/0" in err and "--redis-url" in err
    assert "hunter2" not in err and "Traceback" not in err and len(err.splitlines()) == 1


def test_a_redis_url_is_said_without_its_password():
    from service.commands import redact_password

    assert redact_password("redis://:s3cret@host:6379/0") == "redis://:***@host:6379/0"
    assert redact_password("rediss://user:p@ss@host/1") == "rediss://user:***@host/1"
    assert redact_password("redis://host:6379/0") == "redis://host:6379/0"
    assert redact_password("unix:///run/redis.sock") == "unix:///run/redis.sock"


def test_version_prints_the_installed_version(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out.strip() == f"hapticlink {version('hapticlink')}"


def test_serve_names_a_bad_host_a_busy_port_or_a_variable_that_is_not_json(capsys, monkeypatch, tactile_model,
                                                                           library_dir):  # fmt: skip
    """A bad host was found after the models loaded (an ERROR naming no host); a list variable that is not JSON got
    pydantic's message, naming neither the variable nor the form."""
    flags = ["--model", str(tactile_model), "--library", str(library_dir)]
    assert main(["serve", *flags, "--host", "nosuch.invalid"]) == 2
    assert "--host 'nosuch.invalid' is no address of this machine" in capsys.readouterr().err
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["serve", *flags, "--port", str(port)]) == 2
    assert f"127.0.0.1:{port} is not free" in capsys.readouterr().err
    monkeypatch.setenv("HAPTICLINK_NEAREST_WEIGHTS", "1,2")
    assert main(["serve", *flags]) == 2
    err = capsys.readouterr().err
    assert "HAPTICLINK_NEAREST_WEIGHTS must be JSON (a list is written [1, 2])" in err and "Traceback" not in err


def test_a_ctrl_c_while_the_commands_load_is_a_quiet_stop(monkeypatch, capsys):
    """A Ctrl-C in the first second of `hapticlink demo` (the commands' modules importing) printed a traceback."""
    import service.cli

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(service.cli, "build_parser", interrupted)
    assert main(["demo"]) == 130
    assert capsys.readouterr().err == ""
