"""Who may open sessions: fleet API keys (from settings and a key file re-read when it changes) and a
per-client token bucket on session creation.

Keys are kept as SHA-256 digests and compared with `hmac.compare_digest`; a key file holds one key
per line (blank lines and `#` comments ignored). Rotating keys = editing the file: the next request
after its modification time changes sees the new set, no restart.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import math
import time
from collections import OrderedDict
from pathlib import Path

from pydantic import SecretStr

log = logging.getLogger(__name__)

NOT_CONFIGURED = (
    "session creation is disabled: no fleet API key is configured; set HAPTICLINK_API_KEYS "
    "(comma-separated) or HAPTICLINK_API_KEYS_FILE (one key per line) and send "
    "'Authorization: Bearer <key>'"
)


def _digest(key: str) -> bytes:
    return hashlib.sha256(key.encode("utf-8")).digest()


def parse_keys(text: str, sep: str) -> list[str]:
    """Keys from `text` split at `sep`, stripped, without blanks and `#` comments."""
    return [k.strip() for k in text.split(sep) if k.strip() and not k.strip().startswith("#")]


class ApiKeys:
    """The fleet keys that open sessions. `check(key)` → True if valid; `configured` False when there are none."""

    def __init__(self, keys: SecretStr | None, keys_file: Path | None) -> None:
        self._static = [_digest(k) for k in parse_keys(keys.get_secret_value(), ",")] if keys is not None else []
        self._file = keys_file
        self._file_stamp: tuple[float, int] | None = None
        self._from_file: list[bytes] = []
        self._refresh()

    def _refresh(self) -> None:
        if self._file is None:
            return
        try:
            stat = self._file.stat()
            stamp = (stat.st_mtime, stat.st_size)
            if stamp == self._file_stamp:
                return
            keys = parse_keys(self._file.read_text(encoding="utf-8"), "\n")
        except OSError as exc:  # a missing file means no keys from it (and says so once per change)
            if self._file_stamp != (math.nan, -1):
                log.warning("cannot read the API key file %s: %s", self._file, exc.strerror or exc)
            self._file_stamp, self._from_file = (math.nan, -1), []
            return
        if self._file_stamp is not None:
            log.info("API key file changed: %d key(s)", len(keys))
        self._file_stamp, self._from_file = stamp, [_digest(k) for k in keys]

    @property
    def configured(self) -> bool:
        self._refresh()
        return bool(self._static or self._from_file)

    def check(self, key: str | None) -> bool:
        """True if `key` is one of the fleet's keys (every key is compared: constant work)."""
        self._refresh()
        if key is None:
            return False
        given = _digest(key)
        found = False
        for known in (*self._static, *self._from_file):
            found |= hmac.compare_digest(given, known)
        return found


class TokenBucket:
    """Per-client rate limit: `rate` tokens per second, at most `burst` saved; `take(client)` → 0 if allowed,
    else the seconds until a token is there. Remembers at most `max_clients` clients (least recent forgotten)."""

    def __init__(self, rate: float, burst: int, max_clients: int = 10_000, clock=time.monotonic) -> None:
        if not (rate > 0 and burst >= 1 and max_clients >= 1):
            raise ValueError(f"rate must be > 0, burst and max_clients ≥ 1, got {rate}, {burst}, {max_clients}")
        self.rate, self.burst, self.max_clients = float(rate), float(burst), max_clients
        self._clock = clock
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()  # client → (tokens, at)

    def take(self, client: str) -> float:
        now = self._clock()
        tokens, at = self._buckets.pop(client, (self.burst, now))
        tokens = min(self.burst, tokens + (now - at) * self.rate)
        wait = 0.0
        if tokens >= 1.0:
            tokens -= 1.0
        else:
            wait = (1.0 - tokens) / self.rate
        self._buckets[client] = (tokens, now)
        while len(self._buckets) > self.max_clients:
            self._buckets.popitem(last=False)
        return wait

    def refund(self, client: str) -> None:
        """Give back the token `take` just took: what it was taken for was refused before anything was done."""
        if client in self._buckets:
            tokens, at = self._buckets[client]
            self._buckets[client] = (min(self.burst, tokens + 1.0), at)
