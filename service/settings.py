"""The service's configuration: one pydantic `Settings`, read from HAPTICLINK_* environment variables.

Flags of `hapticlink serve` override the environment; the object is serialisable
(`settings.model_dump(mode="json")`) and `settings_table()` renders the documentation table
that docs/service.md carries (a test keeps the two equal).
"""

from __future__ import annotations

import re
import socket
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from drivers.blocks import DEFAULT_MAX_BODY_BYTES
from drivers.scene_change import FRAME_CHANGE

ENV_PREFIX = "HAPTICLINK_"
_INSTANCE_ID = re.compile(r"^[A-Za-z0-9_-]{1,40}$")


def default_instance_id() -> str:
    """The host name reduced to the characters a session id may carry (containers: the container id)."""
    name = re.sub(r"[^A-Za-z0-9_-]", "-", socket.gethostname())[:40].strip("-")
    return name or "local"


class Settings(BaseSettings):
    """Everything the service reads at start-up. Durations in s, sizes in bytes, ratings bipolar."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="forbid", frozen=True)

    # ---- what to serve --------------------------------------------------------------------------
    model_path: Path | None = Field(None, description="exported perceptual model (.onnx with a hapticlink card)")
    library_dir: Path | None = Field(None, description="texture library directory (library.json + models/)")
    backbone_path: Path | None = Field(
        None,
        description="visual backbone ONNX (models/offline/featurize.py backbone_onnx); needed only by visual models",
    )
    backbone_fallback_path: Path | None = Field(
        None,
        description="the fp32 backbone a quantized (int8) backbone was made from: served in its place when the "
        "int8 one fails its load-time check on this CPU (onnxruntime's int8 kernels saturate without VNNI)",
    )
    tactile_model_path: Path | None = Field(
        None,
        description="optional tactile-only fallback model: trained on the same features, it estimates a visual "
        'model\'s windows until the session\'s first frame is embedded (events say `"inputs": "tactile"`); trained on '
        "them without the taps group, it estimates a taps model's windows of a surface not tapped (events say "
        '`"missing_inputs": ["taps"]`); without it those windows wait',
    )
    cheap_model_path: Path | None = Field(
        None,
        description="optional cheap model (same feature configuration; if it reads images, the same visual features) "
        "the adaptive policy asks first; the full model then runs only where the cheap estimate is not good enough",
    )
    serving_policy: Literal["adaptive", "always-full"] = Field(
        "adaptive",
        description="`adaptive`: embed a frame only when the scene changes (and pool_frames of each scene), "
        "the cheap model first; `always-full`: embed every frame, the full model on every window (service/adaptive.py)",
    )
    pool_frames: int = Field(
        1, ge=1, le=32, description="adaptive: embeddings of one scene pooled (mean) into its visual input"
    )
    full_model_width: float = Field(
        40.0,
        ge=0,
        le=200,
        description="adaptive: the full model runs on a window whose cheap estimate's interval is wider "
        "than this on some attribute (bipolar; at interval_level)",
    )
    full_model_margin: float = Field(
        5.0,
        ge=0,
        le=400,
        description="adaptive: the full model runs on a window whose cheap estimate lies within this "
        "distance margin (bipolar) of a library decision boundary",
    )
    interval_level: float = Field(
        0.9, ge=0.5, le=0.99, description="nominal coverage of the intervals in window events"
    )
    # ---- network ----------------------------------------------------------------------------------
    host: str = Field("127.0.0.1", description="address to listen on")
    port: int = Field(8000, ge=0, le=65535, description="TCP port (0: any free port)")
    instance_id: str = Field(
        default_factory=default_instance_id,
        description="this replica's name; prefixes its session ids so a load balancer can pin sessions",
    )
    # ---- credentials and admission ------------------------------------------------------------------
    api_keys: SecretStr | None = Field(
        None,
        description="fleet API keys, comma-separated, any of which opens sessions (`POST /sessions` with "
        "`Authorization: Bearer <key>`); with neither this nor api_keys_file, session creation is refused (503)",
    )
    api_keys_file: Path | None = Field(
        None,
        description="file of fleet API keys, one per line (# comments); re-read when it changes, so keys rotate "
        "without a restart",
    )
    metrics_token: SecretStr | None = Field(
        None,
        description="the read-only credential of `GET /metrics` (`Authorization: Bearer <token>`), for the "
        "scraper; without it /metrics refuses every request (403)",
    )
    session_rate_per_s: float = Field(
        0.5,
        gt=0,
        description="sessions a client (IP address) may open per second, sustained; "
        "beyond it `POST /sessions` answers 429 with Retry-After",
    )
    session_burst: int = Field(
        10, ge=1, description="sessions a client may open at once before session_rate_per_s applies"
    )
    forwarded_allow_ips: str = Field(
        "127.0.0.1",
        description="proxies whose X-Forwarded-For names the client (comma-separated IPs, or *), so the "
        "session-creation rate applies per real client behind nginx",
    )
    cors_origins: tuple[str, ...] = Field(
        (), description="origins allowed to call the API from a browser (JSON list; default none: no CORS headers)"
    )
    # ---- estimation -------------------------------------------------------------------------------
    hop_s: float = Field(
        0.5, gt=0, le=10, description="window hop for serving; the model's TactileConfig fixes the rest"
    )
    smoothing_alpha: float = Field(0.5, gt=0, le=1, description="EMA weight of the newest window (1: no smoothing)")
    steadiness_windows: int = Field(5, ge=2, le=100, description="recent windows whose spread gives the steadiness")
    top_k: int = Field(3, ge=1, le=50, description="library matches per window event")
    nearest_weights: tuple[float, float, float, float] = Field(
        (1.0, 1.0, 1.0, 1.0),
        description="per-attribute weights of the perceptual distance (JSON list in the environment)",
    )
    selection_rule: Literal["perceptual", "physical", "physical-lsd", "hybrid"] = Field(
        "hybrid",
        description="how the entry to render is chosen (texture_library.selection; docs/models.md, fidelity): "
        "nearest to the estimated ratings, the library model the window's vibration fits best, or both",
    )
    selection_weight: float = Field(
        4.0,
        ge=0,
        le=1000,
        description="hybrid: bipolar rating distance per dB of vibration mismatch (hapticlink fidelity tunes it)",
    )
    selection_sensor_noise: float = Field(
        0.05,
        ge=0,
        le=10,
        description="the robots' accelerometer white noise, m/s² RMS per axis (the vibration fit's noise floor)",
    )
    hysteresis_margin: float = Field(
        12.0, ge=0, description="cost a challenger must gain to replace the choice, in the selection rule's units"
    )
    hysteresis_hold: int = Field(4, ge=1, description="windows in a row a challenger must win")
    # 72 = 6 windows' worth of the margin: on steady one-minute strokes over the tests' library the largest lead a
    # challenger reached was 55 (36 and 48 flipped such strokes), and after a change to the entry furthest away
    # at most 2 windows are held (python -m benchmarks.hysteresis; docs/service.md, Events)
    hysteresis_release_lead: float = Field(
        72.0,
        ge=0,
        description="a challenger whose cost advantage summed over the consecutive windows it is the rule's pick "
        "reaches this replaces the choice even if no window beat the margin, in the rule's units (0: off)",
    )
    hysteresis_settle_windows: int = Field(
        6, ge=0, le=1000, description="a session's first windows, while its smoothed estimate settles: no hysteresis"
    )
    # ---- bounds -----------------------------------------------------------------------------------
    session_queue_windows: int = Field(
        8, ge=1, description="complete windows a session may have waiting; beyond it ingest answers 429 / closes 4429"
    )
    session_queue_blocks: int = Field(
        1024, ge=1, description="blocks a session may hold unprocessed (guards against tiny blocks)"
    )
    max_lag_s: float = Field(
        5.0, gt=0, description="how far one channel may run ahead of another before blocks are refused"
    )
    subscriber_queue: int = Field(
        16, ge=1, description="events buffered per operator connection; older ones are dropped"
    )
    max_body_bytes: int = Field(
        DEFAULT_MAX_BODY_BYTES, ge=1024, description="largest request body or WebSocket message (413 / close 1009)"
    )
    max_sessions: int = Field(256, ge=1, description="open sessions per replica; POST /sessions answers 503 beyond it")
    surface_model: bool = Field(
        False,
        description="learn each session's surface model from its stream and serve it (id session:<session id>) as "
        "the window events' `chosen` once a version is out (service/surface_models.py); off by default: "
        "each streaming session then costs a fit (≈ 0.3 s of thread CPU) every few seconds and ≈ 0.8 MB, which the "
        "capacity limits were not measured with",
    )
    session_idle_s: float = Field(60.0, gt=0, description="a session with no traffic for this long is ended")
    session_first_block_s: float = Field(
        15.0,
        gt=0,
        description="a session that has received no block this long after its creation, or its robot's last try (a "
        "frame, or a first block refused for capacity), is ended (abandoned)",
    )
    max_block_s: float = Field(1.0, gt=0, le=60, description="stream time one block may span, s (422 beyond it)")
    max_block_windows: int = Field(
        4, ge=1, description="windows one block may complete (422 beyond it); at most session_queue_windows"
    )
    max_seq_gap: int = Field(
        1_000_000,
        ge=1,
        description="largest jump of seq over the last accepted one (≈ 5.5 h of 20 ms blocks); a larger "
        "jump is refused (422) instead of making every later block a duplicate",
    )
    visual_queue_mpx: float = Field(
        32.0,
        gt=0,
        le=4096,
        description="megapixels of camera frames being decoded or embedded, all sessions together (4 bytes each while "
        "decoded: 32 = 128 MB, the first frames of 160 robots at 448 × 448); a frame beyond it answers 429, and a "
        "single frame is taken whatever its size when none is held",
    )
    frame_change: float = Field(
        FRAME_CHANGE,
        ge=0,
        le=2,
        description="a new scene (embedded) when a frame's thumbnail — block means and block standard "
        "deviations — differs from the scene's first frame by more than this (mean absolute grey difference of "
        "each, summed; drivers/scene_change.py)",
    )
    timeout_keep_alive_s: float = Field(5.0, gt=0, description="idle keep-alive connections are closed after this, s")
    request_read_timeout_s: float = Field(
        10.0,
        gt=0,
        description="a request's headers and body must arrive within this, s (half-open requests are closed)",
    )
    # ---- admission: what the process can serve ------------------------------------------------------
    cpu_budget: float = Field(
        0.85,
        gt=0,
        le=1,
        description="share of one core the event-loop thread may use (smoothed over ~1 s) before the replica refuses "
        "new sessions (429) and sheds the blocks of its newest sessions (429 / close 4429); a new session, or a "
        "robot's start, is also refused when one more at the measured CPU per session would take the service's "
        "threads together over it; service/capacity.py",
    )
    session_lag_s: float = Field(
        0.015,
        gt=0,
        description="event-loop lag, s (the queue delay every request and block waits, smoothed), above which new "
        "sessions are refused (429 + Retry-After) while the process is busy",
    )
    shed_lag_s: float = Field(
        0.02,
        gt=0,
        description="event-loop lag, s (smoothed), above which, while the process is busy, a quarter of the sessions "
        "still served is shed, newest first, every 0.25 s while it gets worse and every 1 s while it gets no better "
        "(their blocks and frames refused: 429 / close 4429 + Retry-After); they stream again oldest first, a tenth "
        "of those served every 2 s once the loop has caught up",
    )
    session_queue_s: float = Field(
        0.03,
        gt=0,
        description="window queue delay, s (the longest complete windows waited for the window pool, its peak held "
        "over ~1 s), above which new sessions are refused (429 + Retry-After) while the process is busy",
    )
    shed_queue_s: float = Field(
        0.05,
        gt=0,
        description="window queue delay, s (its peak), above which, while the process is busy, sessions are shed as "
        "for shed_lag_s: the loop keeps up with the blocks but the window pool, sharing its GIL, does not",
    )
    readmit_hold_s: float = Field(
        5.0,
        ge=0,
        le=30,
        description="a robot refused for capacity (its session shed, or it has not streamed yet and there is no room) "
        "is held this long, s, before its ingest socket's handshake or its block is answered: once a token is "
        "accepted it waits in line, arrival order, costing no CPU, one wait per session, and is let in the moment "
        "room comes back; still no room then: 429 with a short Retry-After, and it keeps its place. A robot whose "
        "session's own backlog of windows is full waits as long for the pool to drain it (its connection unread) "
        "before 429 / close 4429. Below the robot client's request timeout (10 s); 0: answer 429 at once",
    )
    shed_visual_queue_s: float = Field(
        1.0,
        gt=0,
        description="embedding work, s, a camera frame may find queued ahead of it (the measured seconds per "
        "embedding × the embeddings queued); beyond it the frame is refused (429 + Retry-After: when it would be "
        "taken, in the order frames were refused) and the session's windows are estimated tactile-only, marked. Frames "
        "that wait longer than this for the embedder degrade frames a level (sampled less often, then dropped); "
        "they never shed a session",
    )
    probe_port: int | None = Field(
        None,
        ge=0,
        le=65535,
        description="also answer GET (and HEAD) /health and /ready on this port from a thread of their own, which a "
        "blocked event loop cannot delay (a busy one still can, through the GIL) (None: off; 0: any free port)",
    )
    # ---- compute ----------------------------------------------------------------------------------
    pool_threads: int = Field(
        2, ge=1, le=64, description="threads estimating windows, each running one batch of sessions at a time"
    )
    pool_spill_s: float = Field(
        0.01,
        ge=0,
        le=1,
        description="a window job starts beside a running one only once a session's windows have waited this long "
        "for it (s): two jobs at once slow each other down through the GIL; 0: whenever a thread is free",
    )
    visual_threads: int = Field(
        1, ge=1, le=64, description="onnxruntime threads of the visual backbone (one frame at a time)"
    )
    visual_nice: int = Field(
        15,
        ge=0,
        le=19,
        description="how much lower the visual threads' OS priority (decoding, embedding) is than the loop's and the "
        "window threads' (Linux nice): a burst of frames then takes the CPU the windows leave; 0: the same",
    )
    gil_switch_interval_s: float = Field(
        0.0005,
        gt=0,
        le=0.1,
        description="Python's GIL switch interval (sys.setswitchinterval); short keeps the event loop's socket "
        "writes from waiting behind pool threads",
    )
    # ---- fan-out ----------------------------------------------------------------------------------
    broker: Literal["memory", "redis"] = Field(
        "memory", description="event fan-out: in-process, or Redis pub/sub across replicas"
    )
    redis_url: str = Field("redis://localhost:6379/0", description="Redis for broker=redis")
    log_level: Literal["critical", "error", "warning", "info", "debug"] = Field("info", description="log verbosity")

    @model_validator(mode="after")
    def _block_fits_the_queue(self) -> Settings:
        if self.max_block_windows > self.session_queue_windows:
            raise ValueError(
                f"max_block_windows ({self.max_block_windows}) must be ≤ session_queue_windows "
                f"({self.session_queue_windows}): such a block could never be admitted"
            )
        return self

    @field_validator("metrics_token")
    @classmethod
    def _token_is_stripped(cls, value: SecretStr | None) -> SecretStr | None:
        # stripped as fleet keys are: a header value never carries the newline a secret file ends with, so an unstripped
        # token could never match; and compose's `${HAPTICLINK_METRICS_TOKEN:-}` hands an unset variable on as "",
        # which must not be a token
        token = "" if value is None else value.get_secret_value().strip()
        return SecretStr(token) if token else None

    @field_validator("instance_id")
    @classmethod
    def _instance_id_is_a_name(cls, value: str) -> str:
        if not _INSTANCE_ID.match(value):
            raise ValueError(f"instance_id must be 1–40 letters, digits, '_' or '-', got {value!r}")
        return value

    @field_validator("nearest_weights")
    @classmethod
    def _weights_usable(cls, value: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        if any(w < 0 for w in value) or not any(w > 0 for w in value):
            raise ValueError(f"nearest_weights must be ≥ 0 and not all zero, got {value}")
        return value

    @field_validator("redis_url")
    @classmethod
    def _redis_scheme(cls, value: str) -> str:
        if not value.startswith(("redis://", "rediss://", "unix://")):
            raise ValueError(f"redis_url must start with redis://, rediss:// or unix://, got {value!r}")
        return value


def env_name(field: str) -> str:
    """The environment variable that sets `field`."""
    return ENV_PREFIX + field.upper()


def settings_table() -> str:
    """Markdown table of every setting: variable, default, meaning (docs/service.md embeds it)."""
    rows = ["| variable | default | meaning |", "|---|---|---|"]
    for name, info in Settings.model_fields.items():
        if info.default_factory is not None:
            default = "host name"
        elif info.default is None:
            default = "—"
        elif isinstance(info.default, tuple):
            default = "`" + "[" + ", ".join(f"{v:g}" if isinstance(v, float) else repr(v) for v in info.default) + "]`"
        else:
            default = f"`{info.default}`"
        rows.append(f"| `{env_name(name)}` | {default} | {info.description} |")
    return "\n".join(rows)
