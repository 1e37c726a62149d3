"""The ordered resend buffer: encoded blocks the service has not acknowledged yet, bounded in seconds of data."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from drivers.source import check_positive


@dataclass(frozen=True)
class Pending:
    """One encoded block waiting for its acknowledgement: seq, wire bytes, seconds of data it holds."""

    seq: int
    payload: bytes
    duration_s: float


class ResendBuffer:
    """Encoded blocks not yet acknowledged, in seq order, holding at most max_s seconds of data.

    Entries leave from the front only (acknowledged, or dropped when full), so the seqs held are
    always one consecutive run.
    """

    def __init__(self, max_s: float) -> None:
        check_positive("max_buffer_s", max_s)
        self.max_s = max_s
        self._items: deque[Pending] = deque()
        self.held_s = 0.0

    def __len__(self) -> int:
        return len(self._items)

    def append(self, entry: Pending) -> list[Pending]:
        """Add the newest block; return the oldest ones dropped to stay within max_s (never the new one)."""
        if self._items and entry.seq != self._items[-1].seq + 1:
            raise ValueError(f"resend buffer: seq {entry.seq} does not follow {self._items[-1].seq}")
        self._items.append(entry)
        self.held_s += entry.duration_s
        dropped = []
        while self.held_s > self.max_s + 1e-9 and len(self._items) > 1:
            old = self._items.popleft()
            self.held_s -= old.duration_s
            dropped.append(old)
        return dropped

    def settle(self, seq: int) -> list[Pending]:
        """Remove and return every entry with seq ≤ `seq` (the service has seen them)."""
        out = []
        while self._items and self._items[0].seq <= seq:
            old = self._items.popleft()
            self.held_s -= old.duration_s
            out.append(old)
        if not self._items:
            self.held_s = 0.0  # no round-off creeping in
        return out

    def first_from(self, seq: int) -> Pending | None:
        """The oldest entry with seq ≥ `seq`, or None."""
        if not self._items:
            return None
        i = max(0, seq - self._items[0].seq)
        return self._items[i] if i < len(self._items) else None

    def count_before(self, seq: int) -> int:
        """Entries with seq < `seq` (sent and waiting for their acknowledgement)."""
        if not self._items:
            return 0
        return max(0, min(seq - self._items[0].seq, len(self._items)))

    @property
    def oldest_seq(self) -> int | None:
        return self._items[0].seq if self._items else None
