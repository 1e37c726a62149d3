"""Where the operator's speed (mm/s) and normal force (N) come from, at the renderer's rate (1 kHz).

Each device is an async iterator of `Motion` blocks:
- `SimulatedStroke`: a seeded freehand stroke (texture_library.trajectory.freehand), paced in real time;
- `RecordedStroke`: a recording file (.npz of texture_library.recording, speed or position + force; or a CSV
  with columns speed_mm_s,force_n at 1 kHz), paced in real time, optionally looped;
- `SerialDevice`: a haptic device on a serial port speaking the HL1 line protocol (drivers/serial_board.py) with
  speed (or position) and force columns at 1 kHz.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.blocks import SampleBlock
from drivers.serial_board import SerialBoardSource
from texture_library.channels import UNIT_SCALE
from texture_library.recording import load_recording
from texture_library.trajectory import freehand

RATE_HZ = 1000.0


@dataclass(frozen=True)
class Motion:
    """speed: (n,) mm/s (≥ 0); force: (n,) normal force, N; position: (n,) mm along the surface's x axis (where the
    bumps are felt) or None for a device that reports none; at RATE_HZ."""

    speed: np.ndarray
    force: np.ndarray
    position: np.ndarray | None = None


async def paced(speed: np.ndarray, force: np.ndarray, block_s: float, realtime: bool) -> AsyncIterator[Motion]:
    """Cut aligned arrays into blocks of block_s, each released when its time has come (realtime)."""
    n = max(1, int(round(block_s * RATE_HZ)))
    start = time.monotonic()
    for k, lo in enumerate(range(0, speed.size, n)):
        if realtime:
            await asyncio.sleep(max(0.0, start + k * n / RATE_HZ - time.monotonic()))
        else:
            await asyncio.sleep(0)
        yield Motion(speed[lo : lo + n], force[lo : lo + n])


class SimulatedStroke:
    """`duration_s` of a seeded freehand stroke over speed 20–200 mm/s and force 0.2–3 N."""

    def __init__(self, duration_s: float, seed: int = 0, block_s: float = 0.01, realtime: bool = True) -> None:
        traj = freehand(duration_s, np.random.default_rng(seed), rate_hz=RATE_HZ, speed_range=(20.0, 200.0),
                        force_range=(0.2, 3.0))  # fmt: skip
        self.speed, self.force = np.abs(traj.speed), traj.force
        self.block_s, self.realtime = block_s, realtime
        self.name = f"simulated stroke ({duration_s:g} s, seed {seed})"

    def __aiter__(self) -> AsyncIterator[Motion]:
        return paced(self.speed, self.force, self.block_s, self.realtime)


def read_motion_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(speed (n,) mm/s, normal force (n,) N) at 1 kHz from a recording .npz or a speed_mm_s,force_n CSV."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        try:
            table = np.genfromtxt(path, delimiter=",", names=True)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: {exc}") from None
        names = table.dtype.names or ()
        if "speed_mm_s" not in names or "force_n" not in names:
            raise ValueError(f"{path}: a motion CSV needs the columns speed_mm_s,force_n (at 1 kHz), got {names}")
        speed, force = np.atleast_1d(table["speed_mm_s"]), np.atleast_1d(table["force_n"])
    else:
        rec = load_recording(path)
        force = rec.force.data if rec.force.data.ndim == 1 else rec.force.data[:, -1]  # (tx, ty, normal)
        if rec.speed is not None:
            speed, speed_rate = rec.speed.data.ravel(), rec.speed.rate_hz
        else:
            position = rec.position
            assert position is not None  # a Recording has speed or position
            pos = position.data.reshape(len(position.data), -1)
            speed = np.linalg.norm(np.gradient(pos, axis=0), axis=1) * position.rate_hz
            speed_rate = position.rate_hz
        speed, force = _at_rate(speed, speed_rate), _at_rate(force, rec.force.rate_hz)
        n = min(speed.size, force.size)
        speed, force = speed[:n], force[:n]
    if speed.size == 0 or not (np.all(np.isfinite(speed)) and np.all(np.isfinite(force))):
        raise ValueError(f"{path}: speed and force must be non-empty and finite")
    return np.abs(speed.astype(float)), force.astype(float)


def _at_rate(x: np.ndarray, rate_hz: float) -> np.ndarray:
    """A channel resampled to RATE_HZ by linear interpolation (as is when it is already there)."""
    x = np.asarray(x, float)
    if rate_hz == RATE_HZ:
        return x
    t = np.arange(x.size) / rate_hz
    return np.interp(np.arange(int(t[-1] * RATE_HZ) + 1) / RATE_HZ, t, x)


class RecordedStroke:
    """A recorded operator motion (read_motion_file), paced in real time; `loop` plays it again and again."""

    def __init__(self, path: str | Path, block_s: float = 0.01, realtime: bool = True, loop: bool = False) -> None:
        self.speed, self.force = read_motion_file(path)
        self.block_s, self.realtime, self.loop = block_s, realtime, loop
        self.name = f"recording {path}"

    async def _iterate(self) -> AsyncIterator[Motion]:
        while True:
            async for m in paced(self.speed, self.force, self.block_s, self.realtime):
                yield m
            if not self.loop:
                return

    def __aiter__(self) -> AsyncIterator[Motion]:
        return self._iterate()


def motion_of(block: SampleBlock) -> Motion:
    """A serial board's block → Motion: speed (or |d position/dt|) and the normal force, canonical units, 1 kHz.
    ValueError naming what is missing or not at 1 kHz."""
    ch = block.channels
    if "force" not in ch or ("speed" not in ch and "position" not in ch):
        raise ValueError(f"the operator's device must send force and speed (or position), got {sorted(ch)}")
    for kind, c in ch.items():
        if kind in ("force", "speed", "position") and c.rate_hz != RATE_HZ:
            raise ValueError(f"the operator's device must send {kind} at {RATE_HZ:g} Hz, got {c.rate_hz:g} Hz")
    f = ch["force"]
    force = np.asarray(f.data, float) * UNIT_SCALE["force"][f.units]
    force = force if force.ndim == 1 else force[:, -1]
    position = None
    if "position" in ch:
        p = ch["position"]
        position = np.asarray(p.data, float).reshape(len(p.data), -1)[:, 0] * UNIT_SCALE["position"][p.units]
    if "speed" in ch:
        s = ch["speed"]
        speed = np.abs(np.asarray(s.data, float).ravel()) * UNIT_SCALE["speed"][s.units]
    else:
        p = ch["position"]
        pos = np.asarray(p.data, float).reshape(len(p.data), -1) * UNIT_SCALE["position"][p.units]
        speed = np.linalg.norm(np.gradient(pos, axis=0), axis=1) * RATE_HZ if len(pos) > 1 else np.zeros(len(pos))
    n = min(speed.size, force.size)
    return Motion(speed[:n], force[:n], None if position is None else position[:n])


class SerialDevice:
    """A haptic device on a serial port (HL1: `#HL1 rate=1000 speed=mm/s force=N`, drivers/serial_board.py)."""

    def __init__(self, port: str, baudrate: int = 921_600, block_s: float = 0.01, header: str | None = None) -> None:
        self.source = SerialBoardSource(port, baudrate, block_s=block_s, header=header)
        self.name = f"serial device {port}"

    async def _iterate(self) -> AsyncIterator[Motion]:
        async for block in self.source:
            if isinstance(block, SampleBlock):
                yield motion_of(block)

    def __aiter__(self) -> AsyncIterator[Motion]:
        return self._iterate()

    async def aclose(self) -> None:
        await self.source.aclose()
