"""Pydantic models at the HTTP boundary: request and response bodies, with the examples OpenAPI shows."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field

from drivers.blocks import BINARY_CONTENT_TYPE

_T = TypeVar("_T")
NonEmpty = Annotated[_T, Field(min_length=1)]

SESSION_ID_EXAMPLE = "replica-a.Xq3v9PzR0kLm"
TOKEN_EXAMPLE = "kY2f0rC4q2mZ1xP9wV7n3bT5hJ8sL6dA0gE4uR2iO1c"


class ErrorOut(BaseModel):
    """Every refusal: a message that names the problem."""

    detail: str = Field(examples=["accel: sample rate must lie in [10, 100000] Hz, got 1e+06"])


#: a robot id: what operators follow across the robot's sessions
ROBOT_ID_PATTERN = r"^[A-Za-z0-9_.:-]{1,64}$"


class SessionCreate(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"name": "robot-7 on fabric"}]})
    name: str | None = Field(None, max_length=200, description="a label shown to operators")
    robot: str | None = Field(
        None,
        pattern=ROBOT_ID_PATTERN,
        description="the robot's own id (1–64 letters, digits, '_', '-', '.', ':'): operators follow the robot by it "
        "across its sessions (GET /robots/{robot}/session), a restart of the service included",
    )
    first_seq: int = Field(
        0,
        ge=0,
        lt=2**63,
        description="seq of the session's first block: a robot that resumes in a new session (its old one was lost) "
        "goes on with its own numbering and resends what was never acknowledged",
    )


#: a session request is a name of at most 200 characters, a robot id and a seq: a body beyond this is refused before it
#: is read
MAX_SESSION_REQUEST_BYTES = 4096
SESSION_REQUEST_BODY = {
    "required": False,
    "description": f"optional (an empty body opens a session with no name); at most {MAX_SESSION_REQUEST_BYTES} bytes",
    "content": {"application/json": {"schema": SessionCreate.model_json_schema()}},
}


class RobotSession(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={"examples": [{"robot": "robot-7", "session_id": SESSION_ID_EXAMPLE, "lost": None}]}
    )
    robot: str
    session_id: str = Field(description="the robot's newest session: follow its events with the fleet API key")
    lost: str | None = Field(
        None, description="why that session is gone (its replica stopped or restarted): its robot opens a new one soon"
    )


class SessionCreated(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"session_id": SESSION_ID_EXAMPLE, "robot_token": TOKEN_EXAMPLE, "operator_token": TOKEN_EXAMPLE[::-1]}
            ]
        }
    )
    session_id: str = Field(description="prefixed with the replica's instance id")
    robot_token: str = Field(description="sends blocks and frames (Authorization: Bearer, or ?token= on WebSockets)")
    operator_token: str = Field(description="reads events and the session's status")


class BlockAck(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"seq": 41, "duplicate": False, "windows_ready": 1}]})
    seq: int
    duplicate: bool = Field(
        description="true: the session already had this seq (or a later one); nothing was processed"
    )
    windows_ready: int = Field(
        ge=0, description="complete windows of the session not yet published (0 when it keeps up)"
    )


class SceneCheck(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={"examples": [{"frame_needed": False, "detail": "the scene is held: no frame needed"}]}
    )
    frame_needed: bool = Field(description="true: send the frame whose thumbnail this was (POST …/frames)")
    detail: str = Field(description="why a frame is needed, or that the scene is held")


class FrameAck(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [{"accepted": True, "used": True, "outcome": "embedding", "width": 448, "height": 448}]
        }
    )
    accepted: bool = True
    used: bool = Field(description="false when the model reads no images (a tactile model ignores frames)")
    outcome: Literal["ignored", "unchanged", "embedding", "superseded"] = Field(
        description="ignored: the model reads no images; unchanged: same scene as the frame last embedded (no new "
        "embedding); embedding: the scene changed, an embedding started; superseded: it replaces a frame waiting "
        "for the running embedding"
    )
    width: int
    height: int


@dataclass
class SessionCounters:
    """A session's counts since it was opened (kept by service.live_session.Session, answered in its status)."""

    blocks_accepted: int = 0
    blocks_duplicate: int = 0
    blocks_rejected: int = 0  # bad blocks (4xx, counted by the routes); nothing of them was taken
    blocks_refused: int = 0  # refused while saturated (429 / 4429); safe to resend
    windows: int = 0
    frames_received: int = 0
    frames_rejected: int = 0
    frames_refused: int = 0  # refused early (429): the visual queue was full or the previous frame was decoding
    frames_unchanged: int = 0  # same scene as the frame last embedded: not embedded again
    frames_embedded: int = 0
    frames_superseded: int = 0  # replaced by a newer frame before being embedded
    pipeline_errors: int = 0
    tap_blocks_used: int = 0  # tap blocks whose features the model reads (taps group)
    tap_blocks_ignored: int = 0  # tap blocks acknowledged and ignored: the model has no taps group


class SurfaceModelStatus(BaseModel):
    """A session's learnt surface model (service/surface_models.py) and what its served version was learnt from."""

    id: str = Field(description="session:<session id>, served at GET /library/{id}/model")
    model_version: str | None = Field(description="the served version; null while none is out")
    versions: int = Field(description="versions sent so far")
    fits: int = Field(description="fits run so far")
    segments: int = Field(description="128-sample contact segments the fitter holds")
    held_gap_fits: int = Field(0, description="fits (ok, with a version out) the two figures below are taken over")
    held_gap_db_mean: float | None = Field(
        None,
        description="mean over those fits of the log-spectral distance (dB, mean over the nine operating points) "
        "between the version operators hold after the fit and the fit itself: what publishing less costs them",
    )
    held_gap_db_max: float | None = Field(None, description="the largest of those distances, dB")
    contact_s: float | None = Field(None, description="seconds of contact the served version was learnt from")
    prior: str | None = Field(None, description="the library entry it was blended with where data were thin")
    noise_source: str | None = Field(None, description="where its noise floor came from")
    learnt_at: float | None = Field(None, description="when the served version was learnt, Unix s")
    ratings: dict[str, float] | None = Field(None, description="the session's smoothed ratings now")


class SessionStatus(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "session_id": SESSION_ID_EXAMPLE,
                    "name": "robot-7 on fabric",
                    "instance": "replica-a",
                    "state": "streaming",
                    "created_at": 1767225600.0,
                    "idle_s": 0.02,
                    "model": "ridge-tactile",
                    "needs_visual": False,
                    "visual_ready": False,
                    "last_seq": 400,
                    "segments": 1,
                    "windows_ready": 0,
                    "pending_blocks": 12,
                    "counters": {
                        "blocks_accepted": 401,
                        "blocks_duplicate": 0,
                        "blocks_rejected": 1,
                        "blocks_refused": 0,
                        "windows": 16,
                        "frames_received": 0,
                        "frames_rejected": 0,
                        "frames_refused": 0,
                        "frames_unchanged": 0,
                        "frames_embedded": 0,
                        "frames_superseded": 0,
                        "pipeline_errors": 0,
                        "tap_blocks_used": 0,
                        "tap_blocks_ignored": 0,
                    },
                }
            ]
        }
    )
    session_id: str
    name: str
    robot: str | None = Field(None, description="the robot's own id, if it gave one (operators follow it by it)")
    instance: str
    state: str = Field(description="open | streaming | waiting_for_frame | waiting_for_taps | saturated | ended")
    created_at: float = Field(description="Unix time, s")
    idle_s: float
    model: str
    needs_visual: bool
    visual_ready: bool
    last_seq: int = Field(description="highest accepted seq (−1: none yet)")
    segments: int = Field(description="continuous stretches of stream (a time gap starts a new one)")
    windows_ready: int
    pending_blocks: int
    counters: SessionCounters
    backbone: BackboneOut | None = Field(None, description="the backbone that embeds this session's frames")
    surface_model: SurfaceModelStatus | None = Field(
        None, description="the session's learnt surface model (HAPTICLINK_SURFACE_MODEL); null when it is off"
    )


class LibraryEntryOut(BaseModel):
    id: str
    name: str
    group: str
    ratings: dict[str, float] = Field(
        examples=[{"rough_smooth": -40.0, "flat_bumpy": 12.5, "sticky_slippery": 8.0, "hard_soft": -60.0}]
    )
    model_version: str | None = Field(
        None, description="the entry's rendering model version (GET /library/{id}/model, its ETag)"
    )


class LibraryOut(BaseModel):
    name: str
    entries: list[LibraryEntryOut]


class HealthOut(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={"examples": [{"status": "ok", "instance": "replica-a", "probe_port": 8081}]}
    )
    status: str
    instance: str
    probe_port: int | None = Field(
        None,
        description="the port orchestrators should probe (HAPTICLINK_PROBE_PORT; absent when none is set): it answers "
        "/health and /ready from a thread of its own, while this answer on the service's port waits behind the event "
        "loop, which a crowd of robots keeps busy",
    )


class BackboneOut(BaseModel):
    """The visual backbone that embeds frames, and how its load-time check went (service.runtime.BackboneStatus)."""

    served: str = Field(description="the backbone that runs")
    configured: str = Field(description="the backbone file configured (HAPTICLINK_BACKBONE_PATH)")
    fallback: bool = Field(description="true: the configured one failed its check on this CPU; its fp32 source runs")
    probe_cosine: float | None = Field(
        None, description="the configured backbone's worst probe frame cosine to fp32 on this CPU (null: unchecked)"
    )
    bound: float | None = Field(None, description="the least probe cosine a backbone must reach to be served")
    detail: str


class ReadyOut(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "ready": True,
                    "detail": "ready",
                    "model": "ridge-tactile",
                    "modality": "tactile",
                    "library": "synthetic-24-s0",
                    "library_entries": 24,
                    "backbone": None,
                }
            ]
        }
    )
    ready: bool
    detail: str
    model: str | None = None
    modality: str | None = None
    tactile_model: str | None = Field(
        None, description="the tactile-only model used until a session's first frame is embedded"
    )
    library: str | None = None
    library_entries: int | None = None
    backbone: str | None = None
    backbone_check: BackboneOut | None = None


class JsonChannel(BaseModel):
    rate_hz: float = Field(ge=10, le=100_000, description="samples per second, 10…100000")
    units: str = Field(description="accel: m/s^2 | g; force: N; speed: mm/s | m/s; position: mm | m")
    data: NonEmpty[list[float]] | NonEmpty[list[NonEmpty[list[float]]]] = Field(
        description="(n,) or (n, k) samples, n ≥ 1"
    )


class JsonBlock(BaseModel):
    """A sample block as JSON (drivers/blocks.py); the binary form carries the same header."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "seq": 0,
                    "t0": 0.0,
                    "channels": {
                        "accel": {"rate_hz": 1000, "units": "m/s^2", "data": [[0.1, -0.2, 9.8], [0.0, 0.1, 9.7]]},
                        "force": {"rate_hz": 1000, "units": "N", "data": [1.5, 1.52]},
                        "speed": {"rate_hz": 1000, "units": "mm/s", "data": [80.0, 80.4]},
                    },
                }
            ]
        }
    )
    seq: int = Field(ge=0, lt=2**63, description="one more per block; required")
    t0: float = Field(description="time of the first sample on the robot's clock, s")
    kind: Literal["samples"] = Field("samples", description="block kind (drivers.blocks.BLOCK_KINDS)")
    channels: dict[Literal["accel", "force", "speed", "position"], JsonChannel] = Field(min_length=1)


class JsonTaps(BaseModel):
    """The taps of a tap block: k taps of n samples each, with their speeds."""

    rate_hz: float = Field(ge=10, le=100_000, description="samples per second, 10…100000")
    units: Literal["m/s^2", "g"] = Field(description="acceleration units")
    speeds: NonEmpty[list[float]] = Field(
        max_length=32, description="each tap's approach speed, mm/s (≥ 0), one per tap"
    )
    data: NonEmpty[list[NonEmpty[list[float]]]] = Field(
        max_length=32, description="k taps × n samples (16 ≤ n ≤ 500): each tap's acceleration transient"
    )


_TAP_BLOCK_EXAMPLE: dict[str, Any] = {
    "seq": 0,
    "t0": 0.0,
    "kind": "taps",
    "taps": {
        "rate_hz": 1000,
        "units": "m/s^2",
        "speeds": [22.5, 41.0],
        "data": [
            [0.0] * 5 + [3.1, -2.4, 1.7, -1.1, 0.6] + [0.0] * 6,
            [0.0] * 5 + [5.8, -4.5, 3.2, -2.0, 1.1] + [0.0] * 6,
        ],
    },
}


class JsonTapBlock(BaseModel):
    """A tap block as JSON (drivers/blocks.py): the tap exploratory procedure on the surface under the tool."""

    model_config = ConfigDict(json_schema_extra={"examples": [_TAP_BLOCK_EXAMPLE]})
    seq: int = Field(ge=0, lt=2**63, description="one more per block (shared with sample blocks); required")
    t0: float = Field(description="time of the first tap on the robot's clock, s")
    kind: Literal["taps"]
    taps: JsonTaps


BLOCK_REQUEST_BODY = {
    "required": True,
    "content": {
        "application/json": {"schema": JsonBlock.model_json_schema(ref_template="#/components/schemas/{model}")},
        BINARY_CONTENT_TYPE: {
            "schema": {
                "type": "string",
                "format": "binary",
                "description": "b'HLB1' | uint32 LE header length | header JSON | float32 LE samples",
            },
        },
    },
}
SCENE_REQUEST_BODY = {
    "required": True,
    "content": {
        "application/octet-stream": {
            "schema": {
                "type": "string",
                "format": "binary",
                "description": "the newest frame's scene thumbnail (drivers/scene_change.py): 2×16×16 float32, "
                "little-endian, 2,048 bytes — block means, then block standard deviations, grey levels in [0, 1]",
            }
        }
    },
}

FRAME_REQUEST_BODY = {
    "required": True,
    "content": {
        "image/png": {
            "schema": {
                "type": "string",
                "format": "binary",
                "description": "at least 224×224 pixels (one patch), at most 4096×4096",
            }
        },
        "image/jpeg": {
            "schema": {
                "type": "string",
                "format": "binary",
                "description": "at least 224×224 pixels (one patch), at most 4096×4096",
            }
        },
    },
}
