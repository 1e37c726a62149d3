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
from service.uncertainty import Assessment
from texture_library.attributes import ATTRIBUTES

StatusKind = Literal[
    "subscribed",  # this connection now receives the session's events
    "session_created",
    "session_ended",
    "frame_received",  # a camera frame arrived (and will be embedded, or is ignored by a tactile model)
    "visual_updated",  # the visual embedding now used for the scene's windows changed
    "waiting_for_frame",  # a visual model without a tactile-only model holds windows until the first frame is embedded
    "waiting_for_taps",  # a model with tap features holds windows until the surface under the tool is tapped
    "input_missing",  # windows lack an input the model reads (missing: "taps" or "frame"); a fallback estimates them
    "robot_disconnected",  # the robot's ingest socket closed (the message says why)
    "robot_refused",  # an ingest connection to this session was refused (a wrong or the operator's token)
    "error",  # something failed inside the pipeline; the message says what
    "surface_model",  # the session's learnt surface model keeps what it serves: `reason` says why (once per surface)
    "refused",  # an operator's message on its event socket was refused (a hold naming what the service lacks)
]


class Ratings(BaseModel):
    """The four attributes, bipolar −100…100 (first pole negative)."""

    model_config = ConfigDict(extra="forbid")
    rough_smooth: float
    flat_bumpy: float
    sticky_slippery: float
    hard_soft: float


class Steadiness(BaseModel):
    """Per-attribute steadiness 0…1 — how stable the estimate is, not how right: 1 − (sd of the last n raw window
    ratings) / 57.7, clipped. How far to trust the estimate is its `interval`."""

    model_config = ConfigDict(extra="forbid")
    rough_smooth: float = Field(ge=0, le=1)
    flat_bumpy: float = Field(ge=0, le=1)
    sticky_slippery: float = Field(ge=0, le=1)
    hard_soft: float = Field(ge=0, le=1)


class Bounds(BaseModel):
    """One attribute's interval, bipolar −100…100, lo ≤ hi."""

    model_config = ConfigDict(extra="forbid")
    lo: float = Field(ge=-100, le=100)
    hi: float = Field(ge=-100, le=100)


class Interval(BaseModel):
    """Conformal prediction interval of the smoothed `ratings`, per attribute, at nominal coverage `level`
    (models/inference/intervals.py, calibrated by `hapticlink train` inside cross-validation over the training
    textures).
    target: the calibration used — "ema" (of the smoothed estimate at the service's alpha) or "window" (of one
    window's estimate; used when the service smooths with another alpha). Widens to include the population band
    while the estimate is out of distribution."""

    model_config = ConfigDict(extra="forbid")
    level: float = Field(gt=0, lt=1, description="nominal coverage, e.g. 0.9")
    target: Literal["ema", "window"]
    rough_smooth: Bounds
    flat_bumpy: Bounds
    sticky_slippery: Bounds
    hard_soft: Bounds


class MatchOut(BaseModel):
    id: str
    distance: float = Field(ge=0, description="weighted Euclidean distance in bipolar rating space")


class Latency(BaseModel):
    """Milliseconds from the arrival of the block that completed the window: queue (until its batch job
    started), features (this session's preprocessing + window_features of the whole batch, or of this session
    alone when the batch's call failed), model (the batch's inference), lookup (smoothing + nearest + hysteresis
    of this window), total (until publish)."""

    model_config = ConfigDict(extra="forbid")
    queue: float
    features: float
    model: float
    lookup: float
    total: float


class SelectionOut(BaseModel):
    """Why `chosen` is the entry to render."""

    model_config = ConfigDict(extra="forbid")
    rule: str = Field(description="the selection rule: perceptual, physical, physical-lsd or hybrid")
    reason: str = Field(description="one short sentence: why this entry")
    held_by_hysteresis: bool = Field(description="the rule's own pick this window is another entry; hysteresis holds")
    switch_margin: float | None = Field(
        description="how much cheaper than now, in the rule's units, the best other entry must get for the choice "
        "to switch at the next window (by the margin, or by its cumulative lead); null when the library holds one "
        "entry"
    )


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
    interval: Interval | None = Field(
        description="prediction interval of `ratings` per attribute; null when the served model's card carries no "
        "interval calibration (models exported before calibration, or trained on < 8 textures): never a made-up one"
    )
    out_of_distribution: bool | None = Field(
        description="the estimate rests on input unlike the model's training data (a flagged window, or one still "
        "weighing in the smoothed ratings); null when the model's card carries no OOD detector"
    )
    ood_reasons: list[str] = Field(
        description="why: force_out_of_range, speed_out_of_range, tactile_outlier, visual_outlier, no_frame, "
        "frame_underexposed, frame_overexposed, frame_dark_region, frame_low_contrast, frame_blurred; "
        "recent_window_flagged (this window is clean, earlier flagged ones still weigh in the smoothed ratings: their "
        "reasons follow)"
    )
    provisional: bool = Field(
        False,
        description="the smoothed estimate rests on too few windows for its interval's own calibration (the first "
        "windows of a session): the interval is the single window's, wider; show the estimate as provisional",
    )
    steadiness: Steadiness
    matches: list[MatchOut] = Field(description="top-k library entries, nearest first")
    chosen: str = Field(
        description="the entry to render: the library entry (after hysteresis), or the session's learnt surface model "
        "(session:<session id>) once a version of it is out (served like an entry: GET /library/{id}/model)"
    )
    library_pick: str | None = Field(
        None,
        description="when `chosen` is the session's learnt surface model: the library entry the selection rule picked "
        "(the learnt model's prior); null otherwise",
    )
    selection: SelectionOut | None = Field(None, description="why `chosen` was chosen (absent from older servers)")
    chosen_model_version: str | None = Field(
        None,
        description="model_version of `chosen`'s rendering model (GET /library/{id}/model): a client fetches each "
        "version once; absent from older servers",
    )
    latency_ms: Latency
    model: str = Field(
        description="the model that produced raw_ratings (under the adaptive policy: the cheap model, or "
        "the full one where the cheap estimate was not good enough)"
    )
    inputs: Literal["tactile", "tactile+visual"] = Field(
        description="what the estimate read: tactile+visual, or tactile only (a visual model's session whose "
        "first frame has not been embedded yet, estimated by the tactile-only model; or a tactile-only cheap "
        "model's estimate)"
    )
    missing_inputs: list[Literal["taps", "frame"]] = Field(
        default_factory=list,
        description="inputs the served model reads that this window lacked, so a fallback model estimated it: "
        '"taps" (the surface under the tool has not been tapped since the scene changed; send a tap block); "frame" '
        "(the replica, under load, refused the session's camera frames before any robot's blocks, and no frame of it "
        "has been embedded since: estimated tactile-only)",
    )


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


def _interval(a: Assessment) -> dict | None:
    i = a.interval
    if i is None:
        return None
    return {
        "level": i.level,
        "target": i.target,
        **{
            name: {"lo": round(float(lo), 2), "hi": round(float(hi), 2)}
            for name, lo, hi in zip(ATTRIBUTES, i.lo, i.hi, strict=True)
        },
    }


def _selection(w: WindowEstimate) -> dict | None:
    c = w.selection
    if c is None:
        return None
    return {
        "rule": c.rule,
        "reason": c.reason,
        "held_by_hysteresis": c.held_by_hysteresis,
        "switch_margin": None if c.switch_margin is None else round(c.switch_margin, 3),
    }


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
        "interval": _interval(w.assessment),
        "out_of_distribution": w.assessment.out_of_distribution,
        "ood_reasons": list(w.assessment.ood_reasons),
        "provisional": w.assessment.provisional,
        "steadiness": _ratings(w.steadiness, 3),
        "matches": [{"id": m.id, "distance": round(m.distance, 3)} for m in w.matches],
        "chosen": w.chosen,
        "library_pick": w.library_pick,
        "selection": _selection(w),
        "chosen_model_version": w.chosen_model_version,
        "latency_ms": {
            "queue": round(max(0, w.started_ns - w.ingest_ns) * ms, 3),
            "features": round(w.features_ms, 3),
            "model": round(w.model_ms, 3),
            "lookup": round(w.lookup_ms, 3),
            "total": round(max(0, published_ns - w.ingest_ns) * ms, 3),
        },
        "model": w.model,
        "inputs": w.inputs,
        "missing_inputs": list(w.missing),
    }


def status_event(session_id: str, event: StatusKind, message: str, **extra: object) -> dict:
    return {
        "type": "status",
        "session_id": session_id,
        "event": event,
        "message": message,
        "time": round(time.time(), 3),
        **extra,
    }


def encode(event: dict) -> str:
    return json.dumps(event, separators=(",", ":"), allow_nan=False)
