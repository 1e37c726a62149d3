"""The JSON events operators receive, as pydantic models (documentation, tests) and fast builders (serving).

Builders produce plain dicts with the same fields as the models and `encode` serialises them
once per publish; tests validate what comes over the wire against the models.
"""

from __future__ import annotations

import json
import time
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from service.pipeline import WindowEstimate
from texture_library.attributes import ATTRIBUTES

StatusKind = Literal[
    "subscribed",  # this connection now receives the session's events
    "session_created",
    "session_ended",
    "frame_received",  # a camera frame arrived (and will be embedded, or is ignored by a tactile model)
    "visual_updated",  # the visual embedding now used for the scene's windows changed
    "waiting_for_frame",  # a visual model without a tactile-only model holds windows until the first frame is embedded
    "robot_disconnected",  # the robot's ingest socket closed (the message says why)
    "robot_refused",  # an ingest connection to this session was refused (a wrong or the operator's token)
    "error",  # something failed inside the pipeline; the message says what
]


class Ratings(BaseModel):
    """The four attributes, bipolar −100…100 (first pole negative)."""

    model_config = ConfigDict(extra="forbid")
    rough_smooth: float
    flat_bumpy: float
    sticky_slippery: float
    hard_soft: float


class Confidence(BaseModel):
    """Per-attribute stability 0…1: 1 − (sd of the last n raw window ratings) / 57.7, clipped."""

    model_config = ConfigDict(extra="forbid")
    rough_smooth: float = Field(ge=0, le=1)
    flat_bumpy: float = Field(ge=0, le=1)
    sticky_slippery: float = Field(ge=0, le=1)
    hard_soft: float = Field(ge=0, le=1)


class MatchOut(BaseModel):
    id: str
    distance: float = Field(ge=0, description="weighted Euclidean distance in bipolar rating space")


class Latency(BaseModel):
    """Milliseconds from the arrival of the block that completed the window: queue (until its batch job
    started), features (this session's preprocessing + window_features of the whole batch), model (the
    batch's inference), lookup (smoothing + nearest + hysteresis of this window), total (until publish)."""

    model_config = ConfigDict(extra="forbid")
    queue: float
    features: float
    model: float
    lookup: float
    total: float


class WindowEvent(BaseModel):
    """One analysed window."""

    model_config = ConfigDict(extra="forbid")
    type: Literal["window"] = "window"
    session_id: str
    window_index: int = Field(ge=0, description="session-wide window counter")
    t_start_s: float = Field(description="window start on the robot's clock, s")
    t_end_s: float
    block_seq: int = Field(description="seq of the block whose samples completed this window")
    ratings: Ratings = Field(description="EMA-smoothed ratings")
    raw_ratings: Ratings = Field(description="this window's model output")
    confidence: Confidence
    matches: list[MatchOut] = Field(description="top-k library entries, nearest first")
    chosen: str = Field(description="the library entry to render (after hysteresis)")
    latency_ms: Latency
    model: str = Field(description="the model that produced raw_ratings")
    inputs: Literal["tactile", "tactile+visual"] = Field(
        description="what the estimate read: tactile+visual, or tactile only (a visual model's session whose first frame "
        "has not been embedded yet, estimated by the tactile-only model)")


class StatusEvent(BaseModel):
    """Something happened to the session."""

    model_config = ConfigDict(extra="allow")
    type: Literal["status"] = "status"
    session_id: str
    event: StatusKind
    message: str
    time: float = Field(description="server wall clock, Unix s")


def _ratings(x: np.ndarray, digits: int = 2) -> dict[str, float]:
    return {a: round(float(v), digits) for a, v in zip(ATTRIBUTES, x, strict=True)}


def window_event(session_id: str, w: WindowEstimate, published_ns: int) -> dict:
    """The window event for `w` (the one place it is built), with its total latency measured to `published_ns`."""
    ms = 1e-6
    return {
        "type": "window",
        "session_id": session_id,
        "window_index": w.index,
        "t_start_s": round(w.t_start_s, 6),
        "t_end_s": round(w.t_end_s, 6),
        "block_seq": w.completed_by,
        "ratings": _ratings(w.smoothed),
        "raw_ratings": _ratings(w.raw),
        "confidence": _ratings(w.confidence, 3),
        "matches": [{"id": m.id, "distance": round(m.distance, 3)} for m in w.matches],
        "chosen": w.chosen,
        "latency_ms": {
            "queue": round(max(0, w.started_ns - w.ingest_ns) * ms, 3),
            "features": round(w.features_ms, 3),
            "model": round(w.model_ms, 3),
            "lookup": round(w.lookup_ms, 3),
            "total": round(max(0, published_ns - w.ingest_ns) * ms, 3),
        },
        "model": w.model,
        "inputs": w.inputs,
    }


def status_event(session_id: str, event: StatusKind, message: str, **extra: object) -> dict:
    return {"type": "status", "session_id": session_id, "event": event, "message": message,
            "time": round(time.time(), 3), **extra}


def encode(event: dict) -> str:
    return json.dumps(event, separators=(",", ":"), allow_nan=False)
