"""`hapticlink serve`: flags override the environment, bad settings are named, and Ctrl-C shuts down cleanly."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

from service.cli import build_parser, main
from service.commands import settings_from_args

REPO = Path(__file__).resolve().parents[2]


def test_flags_override_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("HAPTICLINK_PORT", "9001")
    monkeypatch.setenv("HAPTICLINK_HOST", "0.0.0.0")
    args = build_parser().parse_args(["serve", "--model", str(tmp_path / "m.onnx"), "--port", "9100"])
    settings = settings_from_args(args)
    assert settings.port == 9100 and settings.host == "0.0.0.0" and settings.model_path == tmp_path / "m.onnx"


def test_bad_settings_are_named_without_a_traceback(capsys, tmp_path):
    assert main(["serve", "--model", str(tmp_path / "missing.onnx"), "--library", str(tmp_path)]) == 2
    assert "model not found" in capsys.readouterr().err
    assert main(["serve", "--port", "70000"]) == 2
    assert "port" in capsys.readouterr().err


def test_serve_runs_and_stops_cleanly_on_ctrl_c(kit, tactile_model, library_dir):
    port = kit.free_port()
    env = {**os.environ, "HAPTICLINK_LOG_LEVEL": "info", "HAPTICLINK_API_KEYS": kit.API_KEY}
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--model", str(tactile_model), "--library", str(library_dir),
         "--port", str(port), "--instance-id", "cli"],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/ready", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert proc.poll() is None, proc.stdout.read()
            assert time.monotonic() < deadline, "the server did not become ready"
            time.sleep(0.1)
        created = httpx.post(f"http://127.0.0.1:{port}/sessions", json={}, headers=kit.FLEET).json()
        assert created["session_id"].startswith("cli.")
        proc.send_signal(signal.SIGINT)
        output, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, output
    assert "Application shutdown complete" in output and "Traceback" not in output
