"""Wall-clock seconds between the steps of a run (its ``timings``)."""

from __future__ import annotations

import time


class Stopwatch:
    """Seconds between consecutive laps.

    >>> clock = Stopwatch()
    >>> clock.lap() >= 0.0
    True
    """

    __slots__ = ("_last",)

    def __init__(self):
        self._last = time.perf_counter()

    def lap(self) -> float:
        """Seconds since the last lap (or since the stopwatch was made)."""
        now = time.perf_counter()
        seconds, self._last = now - self._last, now
        return seconds
