"""The simulated robot: strokes a library texture by rendering its vibration model.

Chunk after chunk, a seeded freehand trajectory (texture_library.trajectory.freehand) is rendered
into sensor signals (texture_library.stroke.stroke) — the same code that builds the synthetic
datasets — and sent in blocks: accel (n, 3) m/s², force (n, 3) N (tangential x, y, normal),
speed (n,) mm/s, at the model's rate (1 kHz). With taps=True the robot first performs the tap
exploratory procedure: one TapBlock with the texture's tap transients (the model's TapSet: k taps
of n samples at 1 kHz, each with its tap speed), before the stroke begins.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np

from drivers.blocks import ChannelBlock, Frame, TapBlock
from drivers.camera import encode_image, sniff_content_type
from drivers.source import Item, blocks_from_arrays, check_positive, default_block_s, paced
from texture_library.library import Library
from texture_library.stroke import StrokeSignals, random_rotation, stroke
from texture_library.taps import TAP_RATE_HZ
from texture_library.trajectory import Trajectory, freehand, model_ranges
from texture_library.vibration import VibrationModel

MAX_STROKE_S = 2.0  # freehand's longest single stroke: a chunk is rendered this much longer, then cut at a turnaround


def _cut_at_turnaround(traj: Trajectory, min_samples: int) -> Trajectory:
    """The trajectory up to its last direction reversal at or after min_samples (whole strokes only),
    so consecutive chunks meet at a turnaround, where the speed is low anyway, not mid-stroke."""
    step = np.sign(np.diff(traj.position))
    flips = np.nonzero(step[1:] != step[:-1])[0] + 1
    flips = flips[flips >= min_samples]
    if flips.size == 0:
        return traj
    cut = int(flips[-1]) + 1
    return Trajectory(traj.speed[:cut], traj.force[:cut], traj.position[:cut], traj.rate_hz)


def tap_block(model: VibrationModel, t0: float = 0.0, seq: int = 0) -> TapBlock:
    """The tap procedure on a texture: its tap transients as recorded in its model (1 kHz, m/s²).
    ValueError if the model has none."""
    taps = model.taps
    if taps is None:
        raise ValueError(f"model {model.name!r} has no tap transients")
    return TapBlock(
        t0,
        np.asarray(taps.speeds, dtype=np.float64),
        ChannelBlock(np.asarray(taps.accel, dtype=np.float32), TAP_RATE_HZ, "m/s^2"),
        seq,
    )


class SimulatedSource:
    """A robot stroking `model`'s texture: blocks of block_s seconds, generated chunk by chunk.

    image_png: the texture's image (PNG or JPEG bytes), sent as a Frame first and again every
    frame_every_s seconds if set. seed: chunk k draws from np.random.default_rng([seed, k]); the
    accelerometer's mounting orientation is drawn once from seed. chunk_s: seconds of trajectory
    per chunk (each chunk runs to a stroke turnaround, so it is chunk_s to chunk_s + 2 s long);
    the next chunk is rendered in a worker thread while the current one plays. duration_s: stop
    after this much stream time (None: run until closed). taps: tap the surface before stroking
    (a TapBlock at t0 = 0 from the model's tap transients; ValueError if the model has none).
    """

    def __init__(
        self,
        model: VibrationModel,
        image_png: bytes | None = None,
        seed: int = 0,
        block_s: float | None = None,
        realtime: bool = True,
        chunk_s: float = 5.0,
        duration_s: float | None = None,
        frame_every_s: float | None = None,
        speed: float = 1.0,
        name: str | None = None,
        taps: bool = False,
    ) -> None:
        if block_s is None:
            block_s = default_block_s([model.rate_hz])
        check_positive("block_s", block_s)
        if taps and model.taps is None:
            raise ValueError(f"model {model.name!r} has no tap transients to tap with; use taps=False")
        check_positive("chunk_s", chunk_s)
        for label, value in (("duration_s", duration_s), ("frame_every_s", frame_every_s)):
            if value is not None:
                check_positive(label, value)
        if chunk_s < block_s:
            raise ValueError(f"chunk_s ({chunk_s} s) must be at least one block ({block_s} s)")
        self.content_type = None
        if image_png is not None:
            self.content_type = sniff_content_type(image_png)
            if self.content_type is None:
                raise ValueError("image_png must be PNG or JPEG bytes")
        self.model = model
        self.image = image_png
        self.seed = seed
        self.block_s = block_s
        self.realtime = realtime
        self.chunk_s = chunk_s
        self.duration_s = duration_s
        self.frame_every_s = frame_every_s
        self.speed = speed
        self.name = name or f"simulated:{model.name}"
        self.taps = taps
        self._ranges = model_ranges(model.max_speed, model.max_force)
        self._rotation = random_rotation(np.random.default_rng([seed, 2**32]))  # fixed sensor mounting
        self._closed = False

    def chunk(self, k: int) -> StrokeSignals:
        """Sensor signals of chunk k (CPU-bound: a few ms per 5 s; run it off the event loop)."""
        rng = np.random.default_rng([self.seed, k])
        rate = self.model.rate_hz
        traj = freehand(self.chunk_s + MAX_STROKE_S, rng, rate_hz=rate, **self._ranges)
        traj = _cut_at_turnaround(traj, int(round(self.chunk_s * rate)))
        return stroke(self.model, traj, rng, rotation=self._rotation)

    def tap_block(self, t0: float = 0.0, seq: int = 0) -> TapBlock:
        """The tap procedure on this texture (see tap_block)."""
        return tap_block(self.model, t0, seq)

    def _frame(self, t: float) -> Frame:
        assert self.image is not None and self.content_type is not None
        return Frame(t=t, image=self.image, content_type=self.content_type, meta={"texture": self.model.name})

    async def _items(self) -> AsyncIterator[Item]:
        next_frame = math.inf
        if self.image is not None:
            yield self._frame(0.0)
            next_frame = self.frame_every_s or math.inf
        t0, seq, k = 0.0, 0, 0
        if self.taps:
            yield self.tap_block()
            seq = 1
        pending: asyncio.Future | None = asyncio.ensure_future(asyncio.to_thread(self.chunk, 0))
        try:
            while pending is not None and not self._closed:
                signals = await pending
                rate = signals.rate_hz
                n = signals.speed.shape[0]
                if self.duration_s is not None:
                    n = min(n, int(round((self.duration_s - t0) * rate)))
                    if n <= 0:
                        return
                last = self.duration_s is not None and t0 + n / rate >= self.duration_s - 0.5 / rate
                k += 1
                # Render the next chunk in a worker thread while this one plays.
                pending = None if last else asyncio.ensure_future(asyncio.to_thread(self.chunk, k))
                channels = {
                    "accel": (signals.accel[:n], rate, "m/s^2"),
                    "force": (signals.force[:n], rate, "N"),
                    "speed": (signals.speed[:n], rate, "mm/s"),
                }
                for block in blocks_from_arrays(channels, self.block_s, t0=t0, seq0=seq):
                    if self._closed:
                        return
                    while block.t0 >= next_frame:
                        yield self._frame(next_frame)
                        next_frame += self.frame_every_s or math.inf
                    yield block
                    seq = block.seq + 1
                t0 += n / rate
        finally:
            if pending is not None:
                pending.cancel()  # the worker thread finishes its chunk; nobody waits for it

    def __aiter__(self) -> AsyncIterator[Item]:
        return paced(self._items(), self.realtime, self.speed).__aiter__()

    async def aclose(self) -> None:
        self._closed = True

    @classmethod
    def from_library(
        cls, library_dir: str | Path, entry_id: str, image_path: str | Path | None = None, **kwargs
    ) -> SimulatedSource:
        """Stroke library entry `entry_id`; its image (PNG/JPEG/any Pillow format) comes from image_path, or
        else from the entry's own image (`image` in library.json, relative to the library), if it has one."""
        lib = Library.load(library_dir)
        model = lib.model(entry_id)
        if image_path is None:
            rel = lib.entry(entry_id).image_path
            image_path = lib.root / rel if rel else None
        image = None
        if image_path is not None:
            path = Path(image_path)
            if not path.is_file():
                raise ValueError(f"image not found: {path}")
            image, _ = encode_image(path.read_bytes(), str(path))
        kwargs.setdefault("name", f"simulated:{entry_id}")
        return cls(model, image, **kwargs)
