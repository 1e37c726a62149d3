"""`hapticlink operator` end to end: a real server, a real robot stream (RobotClient) over two textures, and the
operator's client following the render feed, fetching models and writing a WAV; its feed cut and reopened
through a TCP proxy; a corrupt model on the server; a device that stops sending."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
import wave
from itertools import combinations

import numpy as np

from drivers.operator.client import OperatorClient
from drivers.operator.devices import SimulatedStroke
from drivers.operator.outputs import WavOutput
from drivers.robot import RobotClient
from drivers.source import blocks_from_arrays
from texture_library.library import Library


class BlockSource:
    """The robot's sensor: prepared blocks, paced at `speed` × real time."""

    name = "scripted"

    def __init__(self, blocks, speed: float = 4.0) -> None:
        self.blocks, self.speed = blocks, speed

    async def _iterate(self):
        start = asyncio.get_running_loop().time()
        for b in self.blocks:
            await asyncio.sleep(max(0.0, start + b.t0 / self.speed - asyncio.get_running_loop().time()))
            yield b

    def __aiter__(self):
        return self._iterate()

    async def aclose(self) -> None:
        pass


def scripted_blocks(kit, library_dir, textures: list[str], seconds: float) -> list:
    """`seconds` of stroking over each texture in turn, as one stream of 20 ms blocks."""
    recs = [kit.stroke_recording(library_dir, t, seconds, seed=k) for k, t in enumerate(textures)]
    channels = {
        kind: (np.concatenate([getattr(r, kind).data for r in recs]), getattr(recs[0], kind).rate_hz, unit)
        for kind, unit in (("accel", "m/s^2"), ("force", "N"), ("speed", "mm/s"))
    }
    return list(blocks_from_arrays(channels, 0.02))


def far_apart(library_dir) -> tuple[str, str]:
    lib = Library.load(library_dir)
    return max(
        combinations(lib.ids, 2), key=lambda p: np.linalg.norm(lib.entry(p[0]).ratings - lib.entry(p[1]).ratings)
    )


class Proxy:
    """A TCP proxy on loopback whose connections can be cut (an operator's network dropping)."""

    def __init__(self, port: int) -> None:
        self.target = port
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.conns: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            upstream = socket.create_connection(("127.0.0.1", self.target))
            self.conns += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(a: socket.socket, b: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := a.recv(65536):
                b.sendall(data)
        with contextlib.suppress(OSError):
            b.shutdown(socket.SHUT_WR)

    def cut(self) -> None:
        for c in self.conns:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)
                c.close()
        self.conns = []

    def close(self) -> None:
        self.cut()
        self.listener.close()


def test_the_operator_renders_the_robots_textures_to_a_wav(kit, server, client, library_dir, tmp_path):
    a, b = far_apart(library_dir)
    versions = {e["id"]: e["model_version"] for e in client.get("/library", headers=kit.FLEET).json()["entries"]}
    session = kit.create_session(client)
    wav = WavOutput(tmp_path / "operator.wav")
    operator = OperatorClient(
        server.url, session["session_id"], session["operator_token"], SimulatedStroke(8.0, seed=1), [wav]
    )
    robot = RobotClient(
        server.url,
        BlockSource(scripted_blocks(kit, library_dir, [a, b], 8.0), speed=4.0),
        session_id=session["session_id"],
        robot_token=session["robot_token"],
    )

    async def main():
        run = asyncio.create_task(operator.run(duration_s=7.0))
        await asyncio.sleep(0.3)  # the operator is listening before the robot starts
        await robot.run()
        return await run

    stats = asyncio.run(main())
    wav.close()
    entries = [s.entry for s in stats.switches]
    assert entries and entries[-1] == b and a in entries, entries  # the robot's textures, in the order it stroked
    assert all(s.version == versions[s.entry] for s in stats.switches)
    assert all(0 < s.latency_ms < 1000 for s in stats.switches), [s.latency_ms for s in stats.switches]
    assert stats.model_errors == [] and stats.stalls == 0 and stats.connects == 1
    # the lean feed: a few bytes per window, besides the models pushed on it (each entry once: none was held)
    assert stats.feed_bytes - stats.model_bytes < 40 * stats.feed_messages
    assert stats.model_counts.get("pushed_models") == len(set(entries)) and "fetched" not in stats.model_counts
    with wave.open(str(tmp_path / "operator.wav")) as w:
        assert w.getframerate() == 1000 and w.getnchannels() == 1
        pcm = np.frombuffer(w.readframes(w.getnframes()), "<i2")
    assert pcm.size == stats.samples and 6500 <= pcm.size <= 7100  # 7 s at 1 kHz, paced in real time
    assert np.count_nonzero(pcm[-3000:]) > 2500  # the texture plays (silence only before the first model)


def test_the_operator_reconnects_and_keeps_the_last_good_model(kit, server, client, library_dir, caplog):
    a, b = far_apart(library_dir)
    session = kit.create_session(client)
    proxy = Proxy(server.port)
    rt = server.app.state.service.runtime
    collected = []

    class Keep:
        def write(self, accel, friction):
            collected.append(accel)

    operator = OperatorClient(
        f"http://127.0.0.1:{proxy.port}",
        session["session_id"],
        session["operator_token"],
        SimulatedStroke(12.0, seed=2),
        [Keep()],
    )
    blocks = scripted_blocks(kit, library_dir, [a, b], 6.0)
    half = len(blocks) // 2

    def robot(part):
        return RobotClient(
            server.url,
            BlockSource(part, speed=8.0),
            session_id=session["session_id"],
            robot_token=session["robot_token"],
            start_seq=part[0].seq,
        )

    served = rt.render_models.models[b]
    try:

        async def main():
            run = asyncio.create_task(operator.run(duration_s=9.0))
            await asyncio.sleep(0.3)
            await robot(blocks[:half]).run()
            await asyncio.sleep(0.5)
            assert operator.current is not None and operator.current[0] == a
            proxy.cut()  # the network drops the feed
            # ...and the next texture's model on the server is corrupt: its version no longer matches
            rt.render_models.models[b] = type(served)(served.model, served.json_body, served.compact_body[:-7])
            await robot(blocks[half:]).run()
            await asyncio.sleep(1.0)
            rt.render_models.models[b] = served
            return await run

        with caplog.at_level(logging.WARNING, logger="hapticlink.operator"):
            stats = asyncio.run(main())
    finally:
        rt.render_models.models[b] = served
        proxy.close()
    assert stats.connects >= 2  # reconnected after the cut
    assert stats.model_errors and stats.model_errors[0].startswith(
        f"model {b!r} ({served.version}) is unusable: compact"
    )
    refused = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert refused and "; rendering goes on with synth_" in refused[0]  # the entry it rendered then
    assert a in [s.entry for s in stats.switches]
    # the corrupt model was refused; the texture was fetched again when a later window chose it again (or never)
    assert all(s.entry != b or s.version == served.version for s in stats.switches)
    assert np.count_nonzero(np.concatenate(collected)[-2000:]) > 1500  # rendering went on


def test_a_device_that_stops_sending_is_reported_and_rendering_resumes(kit, server, client, library_dir, caplog):
    session = kit.create_session(client)

    async def hiccup():
        stroke = SimulatedStroke(4.0, seed=3)
        async for k, m in _enumerate(stroke):
            if k == 100:  # after 1 s the device goes quiet for 1.2 s
                await asyncio.sleep(1.2)
            yield m

    operator = OperatorClient(server.url, session["session_id"], session["operator_token"], hiccup(), [], stall_s=0.3)
    with caplog.at_level(logging.WARNING, logger="hapticlink.operator"):
        stats = asyncio.run(operator.run(duration_s=6.0))
    assert stats.stalls == 1
    assert any("sent nothing for 0.3 s" in r.getMessage() for r in caplog.records)
    assert any("sends again" in r.getMessage() for r in caplog.records)
    assert stats.samples >= 4000  # every block of the stroke, and silence in the gap


async def _enumerate(source):
    k = 0
    async for m in source:
        yield k, m
        k += 1


def test_an_unknown_session_ends_the_operator_with_the_reason(server):
    operator = OperatorClient(server.url, "test-a.nope", "x", SimulatedStroke(5.0), [])
    stats = asyncio.run(operator.run(duration_s=5.0))
    assert stats.ended is not None and "HTTP 404: no session 'test-a.nope'" in stats.ended and stats.samples < 2000
    assert stats.refused


def test_the_command_line_renders_to_a_wav_and_says_what_it_did(kit, server, client, library_dir, tmp_path):
    import os
    import subprocess
    import sys

    session = kit.create_session(client)
    out = tmp_path / "cli.wav"
    cmd = [sys.executable, "-m", "service.cli", "operator", "--url", server.url, "--session", session["session_id"],
           "--token", session["operator_token"], "--device", "simulated:2", "--out", f"wav:{out}",
           "--duration", "120"]  # fmt: skip
    # the device's 2 s stroke ends the run: on a busy host a 2 s --duration ended it after 1.8 s of samples
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr
    assert "rendered 2.0 s (2.0 s silent), 0 switch(es)" in done.stdout  # no robot: silence, said so
    with wave.open(str(out)) as w:
        assert w.getnframes() >= 1900
    bad = subprocess.run([*cmd[:-2], "--out", "mp3:x"], capture_output=True, text=True, timeout=60, env=env)
    assert bad.returncode != 0 and "output spec 'mp3:x'" in bad.stderr
    # an output that cannot open (here a serial port that is not there; on a headless machine, sound) beside a WAV:
    # said, and the session is rendered into the WAV anyway; with nothing that opens, exit 2
    missing = "serial:/dev/hapticlink-no-such-port"
    out.unlink()
    partial = subprocess.run([*cmd, "--out", missing], capture_output=True, text=True, timeout=120, env=env)
    assert partial.returncode == 0, partial.stderr
    assert "hapticlink-no-such-port" in partial.stderr and f"rendering to wav:{out} only" in partial.stderr
    with wave.open(str(out)) as w:
        assert w.getnframes() >= 1900
    nothing = subprocess.run([*cmd[:-4], "--out", missing], capture_output=True, text=True, timeout=60, env=env)
    assert nothing.returncode == 2 and "hapticlink-no-such-port" in nothing.stderr
    # a WAV that cannot be written: one line naming it, no traceback from a half-built writer
    unwritable = subprocess.run([*cmd[:-4], "--out", f"wav:{tmp_path}/no/such/dir/x.wav"], capture_output=True,
                                text=True, timeout=60, env=env)  # fmt: skip
    assert unwritable.returncode == 2 and "no/such/dir/x.wav" in unwritable.stderr
    assert "Traceback" not in unwritable.stderr
    # a library to hold in advance that is not one: named, exit 2
    no_library = subprocess.run([*cmd, "--library", str(tmp_path / "nowhere")], capture_output=True, text=True,
                                timeout=60, env=env)  # fmt: skip
    assert no_library.returncode == 2 and f"--library {tmp_path / 'nowhere'}" in no_library.stderr
    assert "Traceback" not in no_library.stderr
    # the service refusing the feed (a wrong token): the reason, and a failed exit
    token = cmd.index("--token") + 1
    refused = subprocess.run([*cmd[:token], "not-the-token", *cmd[token + 1 :]], capture_output=True, text=True,
                             timeout=60, env=env)  # fmt: skip
    assert refused.returncode == 1 and "refused the event feed: HTTP 401" in refused.stdout
    assert "never reached" not in refused.stdout  # it was reached, and it refused
