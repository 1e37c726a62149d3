"""`hapticlink demo` end to end, at a small size: assets from nothing, service, robot, printed estimates, and a
clean stop on one signal."""

import asyncio
import dataclasses
import os
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from models.offline.demo_assets import prepare_assets
from service.demo import run_demo

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def small_assets(tmp_path_factory):
    return prepare_assets(tmp_path_factory.mktemp("demo") / "assets", n_textures=5, n_probes=2)


def test_demo_builds_its_assets_and_streams_estimates(small_assets, kit, capsys):
    assets = small_assets
    for path in (assets.model, assets.backbone, assets.library / "library.json", assets.probes / "library.json"):
        assert path.is_file(), path
    asyncio.run(run_demo(assets, host="127.0.0.1", port=kit.free_port(), per_texture_s=3.0, duration_s=7.0))
    out = capsys.readouterr().out
    assert "/console?session=" in out and "token=" in out
    assert "stroking synth_000: estimate" in out and "rendering model:" in out
    assert "rough→smooth" in out and "sticky→slippery" in out, "labels are whole"
    assert "demo summary: " in out and "flagged out of distribution" in out
    assert "'lost': 0" in out and "'unsent': 0" in out


def _read_until(proc: subprocess.Popen, marker: str, timeout_s: float) -> str:
    """Everything the process printed until a line holding `marker` (AssertionError if it exits or times out)."""
    out: list[str] = []
    selector = selectors.DefaultSelector()
    selector.register(proc.stdout, selectors.EVENT_READ)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not selector.select(timeout=0.5):
            continue
        line = proc.stdout.readline()
        if not line:
            break
        out.append(line)
        if marker in line:
            return "".join(out)
    raise AssertionError(f"no line with {marker!r}; printed:\n{''.join(out)}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_one_signal_stops_robot_feed_and_service_within_two_seconds_with_the_summary(small_assets, kit, sig):
    paths = [str(p) for p in dataclasses.astuple(small_assets)]
    program = (  # what `hapticlink demo` runs once its assets are ready, with its logging
        "import logging\n"
        "from pathlib import Path\n"
        "from service.demo import DemoAssets, demo\n"
        "logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')\n"
        f"assets = DemoAssets(*map(Path, {paths!r}))\n"
        f"raise SystemExit(demo(assets, port={kit.free_port()}, per_texture_s=2.0, duration_s=300.0))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-c", program], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    try:
        before = _read_until(proc, "── synth_000", timeout_s=240)  # streaming: the first probe's report is out
        sent = time.monotonic()
        proc.send_signal(sig)
        rest, _ = proc.communicate(timeout=30)
        took = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    out = before + rest
    assert proc.returncode == 0, out
    assert took <= 2.0, f"stopped {took:.2f} s after the signal:\n{out}"
    assert "demo summary: " in rest and "robot stats: " in rest, out
    assert "error" in rest.split("demo summary: ")[0], "the probes' closing summary is printed"
    for never in ("HTTP 503", "resend buffer full", "Traceback", "ERROR"):
        assert never not in out, f"{never!r} printed:\n{out}"
