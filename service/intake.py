"""What robots send, from bytes to a session: blocks (`BlockIntake`) and camera frames (`FrameIntake`).

Routes read the body (HTTP) or the message (WebSocket) and hand the bytes over, so a block is
decoded and validated once, in one place, whichever way it came, and outcomes are counted here.

    block bytes ─▶ BlockIntake: capacity (shed?) ─▶ decode_block: SampleBlock | TapBlock ─▶ Session.ingest
        (admission) ─▶ acknowledgement
    frame bytes ─▶ FrameIntake: refused early (429) when the visual queue's pixels are spent ─▶ decode + thumbnail
        (frame pool) ─▶ Session.offer_frame (the serving policy: embed it?) ─▶ frame_received event
    scene thumbnail (a robot's refresh) ─▶ FrameIntake.check_scene ─▶ Session.frame_wanted: send the frame?
"""

from __future__ import annotations

import asyncio
import json
from concurrent.futures import Executor

import numpy as np

from drivers.blocks import (
    BINARY_CONTENT_TYPE,
    MAX_JSON_BLOCK_BYTES,
    Block,
    UnreadableHeader,
    decode_binary,
    decode_json,
)
from drivers.scene_change import thumbnail, thumbnail_from_bytes
from service.bus import EventBus
from service.capacity import AtCapacity, CapacityGuard
from service.errors import ServiceError, not_json, saturated, session_not_found
from service.events import status_event
from service.live_session import RETRY_AFTER_S, Session
from service.metrics import ServiceMetrics
from service.runtime import Runtime, frame_pixels
from service.schemas import FrameAck, SceneCheck
from service.settings import Settings

#: what a malformed payload can raise inside the shared decoders (huge ints overflow, deep nesting recurses)
DECODE_ERRORS = (ValueError, TypeError, OverflowError, RecursionError)


# ---- blocks --------------------------------------------------------------------------------------
class BlockIntake:
    """Blocks of every session: the capacity check, decoding, the session's admission, outcomes counted."""

    def __init__(self, metrics: ServiceMetrics, capacity: CapacityGuard) -> None:
        self.metrics = metrics
        self.capacity = capacity

    def receive(self, session: Session, payload: bytes, binary: bool, arrived_ns: int) -> dict:
        """Decode and admit one block → its acknowledgement; ServiceError 400/422 (invalid), 429 (the session's queue
        is full, or the replica is over capacity and sheds this session's blocks) otherwise; 404 when the session
        ended after the request was authorized (a DELETE while its body arrived): no session holds the block."""
        if session.closed:
            raise session_not_found(session.id)
        try:
            self.capacity.admit_block(session)
        except ServiceError:
            self._refused_for_capacity(session)
            raise
        try:
            block = decode_block(payload, binary)
            ack = session.ingest(block, arrived_ns)
        except ServiceError as exc:
            if exc.status == 429:
                self.metrics.block_outcome["refused"].inc()  # the session counted it (its queue is full)
                self.metrics.block_refusal["session_queue"].inc()
            else:
                self.rejected(session)
            raise
        self.metrics.block_outcome["duplicate" if ack["duplicate"] else "accepted"].inc()
        return ack

    async def hold(self, session: Session, hold_s: float) -> None:
        """Before a block's body is read: a robot refused for capacity waits in line up to `hold_s` and goes on the
        moment its turn comes (CapacityGuard.hold); AtCapacity (429, counted as `receive` counts one) otherwise."""
        try:
            await self.capacity.hold(session, hold_s)
        except ServiceError:
            self._refused_for_capacity(session)
            raise

    def _refused_for_capacity(self, session: Session) -> None:
        self.metrics.block_outcome["refused"].inc()
        self.metrics.block_refusal["capacity"].inc()
        session.counters.blocks_refused += 1

    def rejected(self, session: Session) -> None:
        """Count an invalid block (also one refused before decoding, e.g. a wrong Content-Type)."""
        self.metrics.block_outcome["rejected"].inc()
        session.counters.blocks_rejected += 1


def decode_block(payload: bytes, binary: bool) -> Block:
    """Wire bytes → SampleBlock | TapBlock; ServiceError 400 (not JSON), 413 (a JSON block over MAX_JSON_BLOCK_BYTES,
    refused before it is parsed) or 422 (not a valid block) with the decoder's message."""
    try:
        if binary:
            try:
                return decode_binary(payload)
            except UnreadableHeader as exc:
                raise not_json(exc) from None
        if len(payload) > MAX_JSON_BLOCK_BYTES:
            raise ServiceError(
                413,
                f"a JSON block holds at most {MAX_JSON_BLOCK_BYTES} bytes, got {len(payload)}: send larger blocks in "
                f"the binary format ({BINARY_CONTENT_TYPE}), or smaller ones",
            )
        # No field of a block is a boolean; among numbers numpy would read true as 1. On the bytes: a scan in C,
        # where checking every parsed sample would be a Python loop per sample.
        if b"true" in payload or b"false" in payload:
            raise ServiceError(422, "a block holds no booleans (true/false): samples, rates and times are numbers")
        try:
            obj = json.loads(payload, parse_int=_json_int)
        except (ValueError, RecursionError) as exc:
            raise not_json(exc) from None
        return decode_json(obj)
    except DECODE_ERRORS as exc:
        if isinstance(exc, ValueError):
            detail = str(exc)
        elif isinstance(exc, OverflowError):
            detail = f"a number in the block is out of range ({exc})"
        else:
            detail = f"invalid block ({type(exc).__name__}: {exc})"
        raise ServiceError(422, detail) from None


def _json_int(text: str) -> int | float:
    """JSON integers beyond float range become ±inf, so the validators name the field instead of overflowing."""
    value = int(text)
    if abs(value) > 2**1023:
        return float("inf") if value > 0 else float("-inf")
    return value


# ---- frames --------------------------------------------------------------------------------------
FRAME_MESSAGES = {
    "unchanged": "frame received (scene unchanged: the current embedding stays)",
    "embedding": "frame received (scene changed: embedding it)",
    "superseded": "frame received (replaces a frame waiting for the embedder)",
}


class FrameIntake:
    """Camera frames of every session: a visual queue bounded in pixels, decoding on its own pool (a thread that never
    waits behind an embedding), and the frame_received event.

    visual_pixels: pixels of the frames being decoded or embedded, all sessions together (≤ settings.visual_queue_mpx
    megapixels, but for a single frame, which is taken whatever its size when the queue is empty)."""

    def __init__(
        self, settings: Settings, metrics: ServiceMetrics, bus: EventBus, decode_pool: Executor, capacity: CapacityGuard
    ) -> None:
        self.settings = settings
        self.capacity = capacity
        self.metrics = metrics
        self.bus = bus
        self.decode_pool = decode_pool
        self.visual_pixels = 0

    async def receive(self, session: Session, runtime: Runtime, payload: bytes) -> FrameAck:
        """One encoded frame (PNG/JPEG bytes): refused (429) when the session's previous frame is still decoding or
        its pixels would overfill the visual queue; 422 when it cannot be decoded; otherwise offered to the session,
        which embeds it only if the scene changed. A session whose blocks the replica sheds has its frames refused
        too (429): a frame costs more than a second of blocks.

        The queue is bounded in pixels, not frames: what a frame costs to hold and to decode grows with its size,
        and a fleet whose robots all send their first frame at once must not be refused (each refused robot sends
        again, and every resent body costs the loop as much as the first)."""
        try:
            self.capacity.admit_frame(session)
            if session.decoding_frame:
                raise saturated(
                    f"session {session.id} is still decoding its previous frame; send the newest frame later",
                    RETRY_AFTER_S,
                )
            pixels = frame_pixels(payload)
            budget = round(self.settings.visual_queue_mpx * 1e6)
            if self.visual_pixels and self.visual_pixels + pixels > budget:
                raise saturated(
                    f"the visual queue is full ({self.visual_pixels / 1e6:.1f} of {self.settings.visual_queue_mpx:g} "
                    f"megapixels held; this frame has {pixels / 1e6:.2f}); send the newest frame later",
                    RETRY_AFTER_S,
                )
        except AtCapacity:
            self.metrics.frames.labels(outcome="refused").inc()
            session.counters.frames_refused += 1
            await self._frames_shed(session, runtime)
            raise
        except ServiceError:
            self.metrics.frames.labels(outcome="refused").inc()
            session.counters.frames_refused += 1
            raise
        except ValueError as exc:  # its header declares more pixels than are ever decoded
            self.rejected(session)
            raise ServiceError(422, f"frame: {exc}") from None
        session.decoding_frame = True
        self.visual_pixels += pixels
        try:
            loop = asyncio.get_running_loop()
            gray, thumb = await loop.run_in_executor(self.decode_pool, decode_frame, runtime, payload)
        except ValueError as exc:
            self.rejected(session)
            raise ServiceError(422, f"frame: {exc}") from None
        finally:
            session.decoding_frame = False
            self.visual_pixels -= pixels
        if session.closed:  # ended while the frame was decoded
            raise session_not_found(session.id)
        held = session.embedding_pixels
        outcome = session.offer_frame(gray, thumb)
        # a frame the session's embedding job takes (to embed now, or waiting in place of an older one) stays in the
        # queue until the job is done with it: the session gives its pixels back through visual_done
        self.visual_pixels += session.embedding_pixels - held
        self.metrics.frames.labels(outcome=outcome).inc()
        height, width = gray.shape
        used = outcome != "ignored"
        message = FRAME_MESSAGES.get(outcome, f"frame received (ignored: model {runtime.model_name} reads no images)")
        await self.bus.publish(
            session.id,
            status_event(session.id, "frame_received", message, used=used, outcome=outcome, width=width, height=height),
            False,
        )
        return FrameAck(used=used, outcome=outcome, width=width, height=height)

    async def _frames_shed(self, session: Session, runtime: Runtime) -> None:
        """A frame refused under load (the replica degrades frames before robots): until one of its frames is embedded,
        the session's windows are estimated without it, marked; its operators are told once."""
        told, session.frames_shed = session.frames_shed, True
        if told or session.visual is not None or not runtime.needs_visual:
            return  # an embedding it has keeps serving its windows
        await self.bus.publish(
            session.id,
            status_event(
                session.id,
                "input_missing",
                f"the replica is at capacity and refuses camera frames before robots' blocks: model "
                f"{runtime.model_name}'s windows of this session are estimated tactile-only (marked missing_inputs: "
                "frame) until one of its frames is embedded; the robot sends it again after Retry-After",
                missing="frame",
                send="frame",
            ),
            False,
        )

    def check_scene(self, session: Session, payload: bytes) -> SceneCheck:
        """A robot's scene check: its newest frame's thumbnail (drivers/scene_change.thumbnail_bytes) in place of a
        refresh frame → whether the session wants the frame; 422 for a malformed thumbnail. Costs no decode, and the
        robot sends 2 kB instead of the frame."""
        try:
            thumb = thumbnail_from_bytes(payload)
        except ValueError as exc:
            raise ServiceError(422, f"scene check: {exc}") from None
        why = session.frame_wanted(thumb)
        self.metrics.scene_checks.labels(answer="held" if why is None else "frame_needed").inc()
        return SceneCheck(frame_needed=why is not None, detail=why or "the scene is held: no frame needed")

    def rejected(self, session: Session) -> None:
        """Count a frame refused before it reached the intake (e.g. a wrong Content-Type)."""
        session.counters.frames_rejected += 1
        self.metrics.frames.labels(outcome="rejected").inc()

    def visual_done(self, pixels: int) -> None:
        """A session's embedding job is done with frames of these pixels: they leave the visual queue."""
        self.visual_pixels -= pixels


def decode_frame(runtime: Runtime, payload: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Frame pool: frame bytes → (grey image (H, W) in [0, 1], its scene_change thumbnail)."""
    gray = runtime.decode_frame(payload)
    return gray, thumbnail(gray)
