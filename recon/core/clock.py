"""Wall time per named stage, summed over however many blocks a stage runs in (the streamed
pipeline enters each stage once per batch or window; the one-shot pipeline once). A stage's
end is also where its temporary arrays have just been dropped: the memory they held is
handed back to the OS there (recon.memory), so that stages do not stack their peaks."""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Iterator

from ..memory import release_memory


class StageClock:
    """Wall seconds per stage name, summed over every block timed under it; ``marks``: the
    seconds from ``started`` (the clock's creation, or a given start) to named moments. A
    stage timed inside another (the prior of a frame the front end asks for while it tracks)
    counts for itself alone: the outer stage's seconds leave it out."""

    def __init__(self, started: float | None = None):
        self.seconds: dict[str, float] = {}
        self.started = time.perf_counter() if started is None else started
        self.marks: dict[str, float] = {}
        self._inner: list[float] = []  # per open stage: the seconds of the stages inside it

    def mark(self, name: str) -> None:
        """Record the seconds since ``started`` under ``name``, the first time only."""
        self.marks.setdefault(name, time.perf_counter() - self.started)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        self._inner.append(0.0)
        try:
            yield
        finally:
            release_memory()
            elapsed = time.perf_counter() - start
            inner = self._inner.pop()
            if self._inner:
                self._inner[-1] += elapsed
            self.seconds[name] = self.seconds.get(name, 0.0) + elapsed - inner
