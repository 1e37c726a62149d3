"""Prometheus metrics, hand-written (text exposition format 0.0.4) so serving needs no extra package.

Counters and gauges are updated on the event loop; histograms also from pool threads,
hence the lock. `render()` is what GET /metrics returns.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterable

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
LATENCY_BUCKETS_S = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


def _labels(names: tuple[str, ...], values: tuple[str, ...], extra: str = "") -> str:
    parts = [f'{n}="{_escape(v)}"' for n, v in zip(names, values, strict=True)]
    if extra:
        parts.append(extra)
    return "{" + ",".join(parts) + "}" if parts else ""


def _escape(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _number(x: float) -> str:
    """A sample value as Prometheus writes it (+Inf, integers without a fraction)."""
    x = float(x)
    if math.isinf(x):
        return "+Inf" if x > 0 else "-Inf"
    if x.is_integer() and abs(x) < 1e15:
        return str(int(x))
    return repr(x)


class _Metric:
    kind = ""

    def __init__(self, name: str, help_text: str, labels: tuple[str, ...] = ()) -> None:
        self.name, self.help, self.label_names = name, help_text, labels
        self._lock = threading.Lock()

    def _key(self, labels: dict[str, str]) -> tuple[str, ...]:
        # on the per-block path: one length check and one lookup per label instead of two sets
        try:
            if len(labels) == len(self.label_names):
                return tuple([str(labels[n]) for n in self.label_names])
        except KeyError:
            pass
        raise ValueError(f"{self.name} takes labels {self.label_names}, got {sorted(labels)}")

    def header(self) -> list[str]:
        return [f"# HELP {self.name} {self.help}", f"# TYPE {self.name} {self.kind}"]

    def lines(self) -> list[str]:
        raise NotImplementedError


class Counter(_Metric):
    """A monotonically increasing count per label set."""

    kind = "counter"

    def __init__(self, name: str, help_text: str, labels: tuple[str, ...] = ()) -> None:
        super().__init__(name, help_text, labels)
        self._values: dict[tuple[str, ...], float] = {} if labels else {(): 0.0}

    def inc(self, amount: float = 1.0, **labels: str) -> None:
        key = self._key(labels)
        with self._lock:
            self._values[key] = self._values.get(key, 0.0) + amount

    def value(self, **labels: str) -> float:
        return self._values.get(self._key(labels), 0.0)

    def lines(self) -> list[str]:
        with self._lock:
            items = sorted(self._values.items())
        return [f"{self.name}{_labels(self.label_names, k)} {_number(v)}" for k, v in items]


class Gauge(Counter):
    """A value that goes up and down (set directly)."""

    kind = "gauge"

    def set(self, value: float, **labels: str) -> None:
        key = self._key(labels)
        with self._lock:
            self._values[key] = float(value)


class Histogram(_Metric):
    """Observations (seconds) counted into cumulative buckets per label set."""

    kind = "histogram"

    def __init__(
        self, name: str, help_text: str, labels: tuple[str, ...] = (), buckets: Iterable[float] = LATENCY_BUCKETS_S
    ) -> None:
        super().__init__(name, help_text, labels)
        self.buckets = tuple(sorted(buckets))
        self._counts: dict[tuple[str, ...], list[int]] = {}
        self._sums: dict[tuple[str, ...], float] = {}

    def observe(self, value: float, **labels: str) -> None:
        key = self._key(labels)
        with self._lock:
            counts = self._counts.setdefault(key, [0] * (len(self.buckets) + 1))
            for i, bound in enumerate(self.buckets):
                if value <= bound:
                    counts[i] += 1
                    break
            else:
                counts[-1] += 1
            self._sums[key] = self._sums.get(key, 0.0) + value

    def lines(self) -> list[str]:
        out = []
        with self._lock:
            items = sorted((k, list(c), self._sums[k]) for k, c in self._counts.items())
        for key, counts, total in items:
            running = 0
            for bound, n in zip((*self.buckets, math.inf), counts, strict=True):
                running += n
                le = 'le="' + _number(bound) + '"'
                out.append(f"{self.name}_bucket{_labels(self.label_names, key, le)} {running}")
            out.append(f"{self.name}_sum{_labels(self.label_names, key)} {total!r}")
            out.append(f"{self.name}_count{_labels(self.label_names, key)} {running}")
        return out


class ServiceMetrics:
    """Every metric the service exports."""

    def __init__(self) -> None:
        self.blocks = Counter("hapticlink_blocks_total", "Sample blocks received, by outcome.", ("outcome",))
        self.windows = Counter("hapticlink_windows_total", "Windows estimated and published.")
        self.windows_admitted = Counter(
            "hapticlink_windows_admitted_total",
            "Windows completed by accepted blocks (each is published, or its loss counted).",
        )
        self.frames = Counter("hapticlink_frames_total", "Camera frames received, by outcome.", ("outcome",))
        self.events_dropped = Counter(
            "hapticlink_events_dropped_total", "Events dropped for slow operator connections (they keep the latest)."
        )
        self.sessions_refused = Counter(
            "hapticlink_sessions_refused_total", "POST /sessions refused, by reason (api_key, rate).", ("reason",)
        )
        self.sessions_reaped = Counter(
            "hapticlink_sessions_reaped_total", "Sessions ended for idling or never streaming."
        )
        self.sockets_refused = Counter(
            "hapticlink_ingest_sockets_refused_total",
            "Ingest WebSocket handshakes refused, by HTTP-equivalent status.",
            ("status",),
        )
        self.robot_disconnects = Counter(
            "hapticlink_robot_disconnects_total", "Ingest WebSockets that closed, by reason.", ("reason",)
        )
        self.publish_errors = Counter("hapticlink_publish_errors_total", "Events the broker failed to publish.")
        self.sessions_active = Gauge("hapticlink_sessions_active", "Open sessions on this replica.")
        self.sessions_lost = Counter(
            "hapticlink_sessions_lost_total",
            "Sessions of another replica found gone (stopped, crashed, restarted) here.",
        )
        self.subscribers = Gauge("hapticlink_subscribers", "Open operator event connections on this replica.")
        self.ready = Gauge("hapticlink_ready", "1 when the model and library are loaded and warmed up.")
        self.latency = Histogram(
            "hapticlink_window_latency_seconds", "Ingest-to-publish latency of windows, by pipeline stage.", ("stage",)
        )
        self.visual_seconds = Histogram(
            "hapticlink_visual_embedding_seconds",
            "Time to embed one camera frame.",
            buckets=(0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10),
        )

    def all(self) -> list[_Metric]:
        return [m for m in vars(self).values() if isinstance(m, _Metric)]

    def render(self) -> str:
        lines: list[str] = []
        for metric in self.all():
            lines += metric.header() + metric.lines()
        return "\n".join(lines) + "\n"
