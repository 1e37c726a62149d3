"""Prometheus metrics of one service process, with prometheus_client.

Each `ServiceMetrics` has its own `CollectorRegistry` (several app instances may share a process:
tests, benchmarks); `render()` is what GET /metrics returns, in the text exposition format 0.0.4.
Metric names and labels are the ones dashboards read; changing one breaks them.
"""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, disable_created_metrics, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4

# The *_created series (a timestamp per counter and label set) double the page and no dashboard reads them.
disable_created_metrics()

CONTENT_TYPE = CONTENT_TYPE_PLAIN_0_0_4  # what generate_latest writes
LATENCY_BUCKETS_S = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)
BLOCK_OUTCOMES = ("accepted", "duplicate", "rejected", "refused")
#: why a block was refused (429 / close 4429): the replica sheds its session, or the session's own queue is full
REFUSAL_REASONS = ("capacity", "session_queue")


class ServiceMetrics:
    """Every metric the service exports. Counters and gauges are updated on the event loop, histograms also from
    pool threads (prometheus_client's metrics are thread-safe)."""

    def __init__(self) -> None:
        self.registry = registry = CollectorRegistry(auto_describe=True)
        self.blocks = Counter(
            "hapticlink_blocks_total", "Sample blocks received, by outcome.", ("outcome",), registry=registry
        )
        # on the per-block path: bound once, not looked up per block
        self.block_outcome = {outcome: self.blocks.labels(outcome=outcome) for outcome in BLOCK_OUTCOMES}
        self.blocks_refused = Counter(
            "hapticlink_blocks_refused_total",
            "Blocks refused (429 / close 4429; nothing of them taken), by reason (capacity, session_queue).",
            ("reason",),
            registry=registry,
        )
        self.block_refusal = {reason: self.blocks_refused.labels(reason=reason) for reason in REFUSAL_REASONS}
        self.sessions_shed = Counter(
            "hapticlink_sessions_shed_total",
            "Streaming sessions whose blocks the replica began refusing to keep up with its older sessions.",
            registry=registry,
        )
        self.windows = Counter("hapticlink_windows_total", "Windows estimated and published.", registry=registry)
        self.windows_admitted = Counter(
            "hapticlink_windows_admitted_total",
            "Windows completed by accepted blocks (each is published, or its loss counted).",
            registry=registry,
        )
        self.windows_degraded = Counter(
            "hapticlink_windows_degraded_total",
            "Windows estimated by a fallback model because an input the served model reads was missing, by input.",
            ("missing",),
            registry=registry,
        )
        self.frames = Counter(
            "hapticlink_frames_total", "Camera frames received, by outcome.", ("outcome",), registry=registry
        )
        self.scene_checks = Counter(
            "hapticlink_scene_checks_total",
            "Robots' scene checks (a thumbnail in place of a refresh frame), by answer: held or frame_needed.",
            ("answer",),
            registry=registry,
        )
        self.events_dropped = Counter(
            "hapticlink_events_dropped_total",
            "Events dropped for slow operator connections (they keep the latest).",
            registry=registry,
        )
        self.sessions_refused = Counter(
            "hapticlink_sessions_refused_total",
            "POST /sessions refused, by reason (api_key, rate, capacity).",
            ("reason",),
            registry=registry,
        )
        self.sessions_reaped = Counter(
            "hapticlink_sessions_reaped_total", "Sessions ended for idling or never streaming.", registry=registry
        )
        self.sockets_refused = Counter(
            "hapticlink_ingest_sockets_refused_total",
            "Ingest WebSocket handshakes refused, by HTTP-equivalent status.",
            ("status",),
            registry=registry,
        )
        self.robot_disconnects = Counter(
            "hapticlink_robot_disconnects_total",
            "Ingest WebSockets that closed, by reason.",
            ("reason",),
            registry=registry,
        )
        self.publish_errors = Counter(
            "hapticlink_publish_errors_total", "Events the broker failed to publish.", registry=registry
        )
        self.sessions_active = Gauge("hapticlink_sessions_active", "Open sessions on this replica.", registry=registry)
        self.sessions_lost = Counter(
            "hapticlink_sessions_lost_total",
            "Sessions of another replica found gone (stopped, crashed, restarted) here.",
            registry=registry,
        )
        self.subscribers = Gauge(
            "hapticlink_subscribers", "Open operator event connections on this replica.", registry=registry
        )
        self.ready = Gauge(
            "hapticlink_ready", "1 when the model and library are loaded and warmed up.", registry=registry
        )
        self.loop_lag = Gauge(
            "hapticlink_loop_lag_seconds",
            "How late the event loop runs a timer (smoothed): the queue delay every request and block waits.",
            registry=registry,
        )
        self.window_queue = Gauge(
            "hapticlink_window_queue_seconds",
            "The longest a session's complete windows waited for the window pool (its peak, decaying over ~1 s).",
            registry=registry,
        )
        self.protected_window_queue = Gauge(
            "hapticlink_protected_window_queue_seconds",
            "The same of the sessions admission protects (served well before an overload); over twice "
            "HAPTICLINK_SHED_QUEUE_S, their protection lapses.",
            registry=registry,
        )
        self.visual_queue = Gauge(
            "hapticlink_visual_queue_seconds",
            "The longest a camera frame waited for the embedder (its peak, decaying over ~1 s); apart from the window "
            "queue: over HAPTICLINK_SHED_VISUAL_QUEUE_S, frames are degraded, never sessions.",
            registry=registry,
        )
        self.frame_level = Gauge(
            "hapticlink_frame_level",
            "How far camera frames are degraded under load: 0 every frame taken, 1 sampled less often, 2 dropped.",
            registry=registry,
        )
        self.readmit_seconds = Histogram(
            "hapticlink_readmit_seconds",
            "From the moment the replica had room again for a refused robot (its shed session readmitted, or room to "
            "start) to that robot's next block accepted.",
            buckets=(0.1, 0.25, 0.5, 1.0, 2.0, 3.0, 5.0, 10.0, 30.0),
            registry=registry,
        )
        self.robots_held = Gauge(
            "hapticlink_robots_held",
            "Robots refused for capacity whose connection waits in line for room (readmit_hold_s).",
            registry=registry,
        )
        self.cpu_share = Gauge(
            "hapticlink_loop_cpu_share",
            "Share of one core the event-loop thread used (smoothed; 1 = always busy).",
            registry=registry,
        )
        self.process_cpu_share = Gauge(
            "hapticlink_process_cpu_share",
            "Cores the service's threads used together, the event loop and its pools (smoothed).",
            registry=registry,
        )
        self.latency = Histogram(
            "hapticlink_window_latency_seconds",
            "Ingest-to-publish latency of windows, by pipeline stage.",
            ("stage",),
            buckets=LATENCY_BUCKETS_S,
            registry=registry,
        )
        self.visual_seconds = Histogram(
            "hapticlink_visual_embedding_seconds",
            "Time to embed one camera frame.",
            buckets=(0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10),
            registry=registry,
        )

    def render(self) -> str:
        return generate_latest(self.registry).decode()
