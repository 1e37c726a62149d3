"""`hapticlink serve`: flags override the environment, bad settings are named, and Ctrl-C shuts down cleanly."""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import httpx

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
    assert "port" in capsys.readouterr().err


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
        timeout_s=60,
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
