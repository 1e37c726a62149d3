"""Waiting between attempts: capped exponential backoff with jitter, and the service's Retry-After."""

from __future__ import annotations

import email.utils
import json
import math
import random
import time
from typing import Any, Protocol

import httpx

MAX_RETRY_AFTER_S = 60.0


class Backoff:
    """Capped exponential backoff with jitter: attempt k waits uniform(½, 1)·min(cap, base·2^k) s.

    The jitter spreads out robots that lost the service at the same moment; reset() after progress.
    """

    def __init__(self, base_s: float, cap_s: float, rng: random.Random | None = None) -> None:
        if not (math.isfinite(base_s) and math.isfinite(cap_s) and 0 < base_s <= cap_s):
            raise ValueError(f"backoff must be (base, cap) seconds with 0 < base ≤ cap, got ({base_s!r}, {cap_s!r})")
        self.base_s, self.cap_s = base_s, cap_s
        self._rng = rng or random.Random()
        self._attempt = 0

    def next(self, retry_after_s: float | None = None) -> float:
        """Seconds to wait before the next attempt; with the service's Retry-After, at least that, spread over up to
        half as much again: robots it refused together must not all come back at the same instant."""
        ceiling = min(self.cap_s, self.base_s * 2.0 ** min(self._attempt, 62))
        self._attempt += 1
        wait = ceiling * self._rng.uniform(0.5, 1.0)
        if retry_after_s:
            wait = max(wait, retry_after_s * self._rng.uniform(1.0, 1.5))
        return wait

    def reset(self) -> None:
        self._attempt = 0


class _Answer(Protocol):
    """An HTTP answer: httpx's response, or the one a refused WebSocket handshake carries (websockets')."""

    @property
    def headers(self) -> Any: ...


def retry_after(response: _Answer) -> float | None:
    """Seconds from a Retry-After header (delta-seconds, fractional accepted, or an HTTP date), capped."""
    value = response.headers.get("retry-after")
    if not value:
        return None
    try:
        seconds = float(value)
    except ValueError:
        try:
            seconds = email.utils.parsedate_to_datetime(value).timestamp() - time.time()
        except (TypeError, ValueError):
            return None
    return min(max(seconds, 0.0), MAX_RETRY_AFTER_S) if math.isfinite(seconds) else None


def detail(response: httpx.Response) -> str:
    """The service's `detail` message of a refusal (or the start of the body)."""
    return body_detail(response.content)


def body_detail(content: bytes | bytearray | None) -> str:
    """The `detail` of a JSON error body (an HTTP answer, or a refused WebSocket handshake's), else its first
    200 characters."""
    try:
        body = json.loads(content or b"")
        return str(body.get("detail", body)) if isinstance(body, dict) else str(body)
    except ValueError:
        return (content or b"")[:200].decode(errors="replace")
