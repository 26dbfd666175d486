"""Injected clocks: the daemon never reads the wall clock directly.

A replay or the virtual robot drives a :class:`ManualClock`, so the pipeline runs as fast
as the CPU allows and tests never sleep.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol


class Clock(Protocol):
    """Anything that tells the current time in integer nanoseconds."""

    def now_ns(self) -> int:
        """Current time, nanoseconds, monotonic."""
        ...


class MonotonicClock:
    """The host's monotonic clock (``CLOCK_MONOTONIC``), the time base of V4L2 buffers."""

    def now_ns(self) -> int:
        return time.monotonic_ns()


class ManualClock:
    """A clock that moves only when told to; thread-safe, never goes backwards."""

    def __init__(self, start_ns: int = 0) -> None:
        self._now_ns = int(start_ns)
        self._lock = threading.Lock()

    def now_ns(self) -> int:
        with self._lock:
            return self._now_ns

    def set_ns(self, t_ns: int) -> None:
        """Move the clock to ``t_ns``; a time earlier than now raises ``ValueError``."""
        with self._lock:
            if t_ns < self._now_ns:
                raise ValueError(f"clock cannot go backwards ({t_ns} < {self._now_ns})")
            self._now_ns = int(t_ns)

    def advance_ns(self, dt_ns: int) -> None:
        """Move the clock forward by ``dt_ns`` (>= 0)."""
        if dt_ns < 0:
            raise ValueError("dt_ns must be >= 0")
        with self._lock:
            self._now_ns += int(dt_ns)
