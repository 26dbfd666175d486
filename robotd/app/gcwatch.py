"""Python's garbage collections, timed and counted in the daemon's process.

CPython's cyclic collector runs in whichever thread allocates past a generation's
threshold, holding the GIL: every thread waits for it, and the thread that triggered it
pays for it in its own CPU time. A full collection (generation 2) walks every container
object the process holds, which in the daemon grows with the run (the stages' per-keyframe
lists, the map's rows, the detector's images). :class:`GcWatch` times each collection
through :data:`gc.callbacks` (wall clock, by generation and by thread), so a stage can
take the collector's share out of its own time (the forward stage's ``gc`` part) and the
counters say what the collector cost over the run.
"""

from __future__ import annotations

import gc
import threading
import time
from collections import deque
from typing import Any

# The watch installed in this process (install()/uninstall()); None when none is.
_installed: GcWatch | None = None


class GcWatch:
    """Times Python's garbage collections (:data:`gc.callbacks`) once :meth:`install` ed.

    Per generation: collections, their total and largest duration (wall clock, ms: the
    collector holds the GIL, so every thread waits that long); per thread: the total
    (:meth:`thread_ms`, the calling thread's). ``events`` keeps the last ``keep``
    collections as ``(perf_counter s at the start, thread name, generation, ms,
    objects collected)``."""

    def __init__(self, keep: int = 4096) -> None:
        self.collections = [0, 0, 0]
        self.ms_total = [0.0, 0.0, 0.0]
        self.ms_max = [0.0, 0.0, 0.0]
        self.events: deque[tuple[float, str, int, float, int]] = deque(maxlen=keep)
        self._thread_ms: dict[int, float] = {}
        self._t0 = 0.0  # the running collection's start (the collector is never re-entered)

    def _callback(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._t0 = time.perf_counter()
            return
        t0 = self._t0
        ms = (time.perf_counter() - t0) * 1e3
        g = int(info.get("generation", 0))
        self.collections[g] += 1
        self.ms_total[g] += ms
        self.ms_max[g] = max(self.ms_max[g], ms)
        ident = threading.get_ident()
        self._thread_ms[ident] = self._thread_ms.get(ident, 0.0) + ms
        if g or ms >= 1.0:  # the rare and the long ones: young collections are many and short
            self.events.append((t0, threading.current_thread().name, g, ms, int(info.get("collected", 0))))

    def thread_ms(self) -> float:
        """The collections run in the calling thread so far, wall clock, ms."""
        return self._thread_ms.get(threading.get_ident(), 0.0)

    def counters(self) -> dict[str, Any]:
        """``gc_collections_gen<g>``, ``gc_ms_total_gen<g>`` and ``gc_ms_max_gen<g>`` for
        generations 0-2, and ``gc_frozen_objects`` (:func:`gc.freeze`)."""
        out: dict[str, Any] = {}
        for g in range(3):
            out[f"gc_collections_gen{g}"] = self.collections[g]
            out[f"gc_ms_total_gen{g}"] = round(self.ms_total[g], 1)
            out[f"gc_ms_max_gen{g}"] = round(self.ms_max[g], 2)
        out["gc_frozen_objects"] = gc.get_freeze_count()
        return out

    def install(self) -> GcWatch:
        """Start timing (this process's watch from now on: :func:`installed`)."""
        global _installed
        if _installed is not None and _installed is not self:
            _installed.uninstall()
        if self._callback not in gc.callbacks:
            gc.callbacks.append(self._callback)
        _installed = self
        return self

    def uninstall(self) -> None:
        global _installed
        if self._callback in gc.callbacks:
            gc.callbacks.remove(self._callback)
        if _installed is self:
            _installed = None


def installed() -> GcWatch | None:
    """The watch timing this process's collections, None when none is installed."""
    return _installed
