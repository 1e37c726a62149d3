"""The embedding queue: what frames wait for the visual pool, measured apart from what windows wait for theirs.

The visual pool is one thread (service/state.py); every session with a frame to embed has one job in it at a time
(its embedder: service/live_session.py). `EmbeddingQueue` follows those jobs from submission to their end:

- `wait_s(now)`: the longest a job waited for the thread (from submission to its start) since the last call, or has
  waited by `now` and still waits — the **visual queue delay** admission reads (service/capacity.py), never mixed with
  the window queue's: a slow visual pool degrades frames, not robots;
- `ahead_s()`: the embedding work, s, that a frame taken now would wait behind (jobs not finished × the measured
  seconds per embedding): what frame admission bounds before it takes a frame, so that a fleet's first frames
  arriving within half a second do not queue seconds of embeddings the measures would only see afterwards.

Jobs are submitted and finished on the event loop; `Job.run` executes on the pool thread and stamps its start there
(one attribute write: no lock needed under the GIL).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

#: seconds per embedding assumed before one is measured (the served int8 backbone takes ≈ 0.03 s on a quiet core, the
#: fp32 7×7 grid ≈ 0.5 s: an overestimate only refuses a few first frames too early, for a second)
FIRST_GUESS_S = 0.1
#: the measured seconds per embedding is an exponential average over about this many embeddings
AVERAGE_OVER = 8


class Job:
    """One embedding submitted to the visual pool. submitted / started / finished: time.monotonic(), s."""

    __slots__ = ("finished", "started", "submitted")

    def __init__(self, submitted: float) -> None:
        self.submitted = submitted
        self.started: float | None = None
        self.finished: float | None = None

    def run(self, fn: Callable[..., T], *args: object) -> T:
        """Pool thread: stamp the start, then run `fn(*args)`."""
        self.started = time.monotonic()
        return fn(*args)


class EmbeddingQueue:
    """See the module docstring."""

    def __init__(self, first_guess_s: float = FIRST_GUESS_S) -> None:
        if not first_guess_s > 0:
            raise ValueError(f"first_guess_s must be > 0 s, got {first_guess_s}")
        self.embed_s = first_guess_s  # seconds per embedding, an exponential average
        self._jobs: set[Job] = set()
        self._waited = 0.0  # the longest wait of the jobs started since the last wait_s call, s

    def submit(self, now: float | None = None) -> Job:
        job = Job(time.monotonic() if now is None else now)
        self._jobs.add(job)
        return job

    def done(self, job: Job, now: float | None = None) -> None:
        """The job ended (embedded, failed or cancelled): its wait is recorded, and its run time when it ran."""
        now = time.monotonic() if now is None else now
        self._jobs.discard(job)
        job.finished = now
        if job.started is not None:
            self._waited = max(self._waited, job.started - job.submitted)
            ran = now - job.started
            if ran > 0:
                self.embed_s += (ran - self.embed_s) / AVERAGE_OVER
        else:  # cancelled before it started: it waited all along
            self._waited = max(self._waited, now - job.submitted)

    @property
    def jobs(self) -> int:
        """Jobs submitted and not finished (running or waiting)."""
        return len(self._jobs)

    def wait_s(self, now: float) -> float:
        """The longest (s) a job waited for the thread since the last call, or has waited at `now` and still waits;
        0 when none did. Resets the record."""
        waiting = (now - j.submitted if j.started is None else j.started - j.submitted for j in self._jobs)
        longest = max([self._waited, *waiting])
        self._waited = 0.0
        return max(0.0, longest)

    def ahead_s(self) -> float:
        """Embedding work (s) a job submitted now would wait behind: every job not finished, at the measured seconds
        per embedding (the running one counted whole: an upper bound)."""
        return len(self._jobs) * self.embed_s

    def drain_s(self, budget_s: float) -> float:
        """Seconds until the work queued is back under `budget_s` (0 when it is), at the measured rate."""
        over = self.ahead_s() - budget_s
        return 0.0 if over <= 0 else math.ceil(over / self.embed_s) * self.embed_s
