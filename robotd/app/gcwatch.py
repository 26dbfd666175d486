"""Python's garbage collections, timed and counted in the daemon's process.

CPython's cyclic collector runs in whichever thread allocates past a generation's
threshold, holding the GIL: every thread waits for it, and the thread that triggered it
pays for it in its own CPU time. A full collection (generation 2) walks every container
object the process holds, which in the daemon grows with the run (the stages' per-keyframe
lists, the map's rows, the detector's images). :class:`GcWatch` times each collection
through :data:`gc.callbacks` (wall clock and CPU time, by generation and by thread), so a
stage can tell the collector's share of its own time (the forward stage's ``gc`` part) and
the counters say what the collector cost over the run. :func:`freeze_startup` takes the
objects alive after the start-up out of the collections (``[daemon] gc_freeze``;
docs/performance.md, "The garbage collector").

A full collection lands in whichever message's work allocates when one is due, and on a
forward keyframe it was the costliest keyframe of a run (docs/forward.md, "The p99 in
the daemon now"). :meth:`GcWatch.defer_full` (``[daemon] gc_full_between_messages``) moves them out
of the stages' work: CPython's automatic full collection is turned off (its generation-2
threshold set out of reach) and the watch, the pipeline's last stage, runs one in its
:meth:`GcWatch.poll` (after the pipeline has handed on a batch of messages, never inside a
stage's handling of one) once :data:`FULL_AFTER` collections of generation 1 have run since
the last full one: CPython's own count, without its second condition (that the objects
promoted since the last full collection exceed a quarter of those it kept), so no fewer
full collections than CPython's. The collections' work is the same; it runs between
messages.
"""

from __future__ import annotations

import gc
import logging
import threading
import time
from collections import deque
from typing import Any

log = logging.getLogger(__name__)

# The watch installed in this process (install()/uninstall()); None when none is.
_installed: GcWatch | None = None

#: Collections of generation 1 after which a deferred full collection runs (CPython's default
#: generation-2 threshold; :meth:`GcWatch.defer_full`).
FULL_AFTER = 10

# The generation-2 threshold while full collections are deferred: never reached by the
# count of generation-1 collections since the last full one.
_OUT_OF_REACH = 1 << 30


class GcWatch:
    """Times Python's garbage collections (:data:`gc.callbacks`) once :meth:`install` ed.

    Per generation: collections, their total and largest duration (wall clock, ms: the
    collector holds the GIL, so every thread waits that long; on a loaded machine it also
    counts the time the collecting thread was not scheduled) and their total in the
    collecting thread's CPU time (ms); per thread: the CPU total (:meth:`thread_cpu_ms`, the
    calling thread's). ``events`` keeps the last ``keep`` collections of generation 1 or 2
    or of at least 1 ms as ``(perf_counter s at the start, thread name, generation, wall
    ms, CPU ms, objects collected)``."""

    name = "gc"  # a pipeline stage with no inputs: its counters join the daemon's

    def __init__(self, keep: int = 4096) -> None:
        self.collections = [0, 0, 0]
        self.ms_total = [0.0, 0.0, 0.0]
        self.ms_max = [0.0, 0.0, 0.0]
        self.cpu_ms_total = [0.0, 0.0, 0.0]
        self.events: deque[tuple[float, str, int, float, float, int]] = deque(maxlen=keep)
        self._thread_cpu_ms: dict[int, float] = {}
        self._t0 = 0.0  # the running collection's start (the collector is never re-entered)
        self._c0 = 0.0  # ... in the thread's CPU time
        self.frozen_at_start = 0  # objects frozen by freeze_startup() for this daemon (gc_frozen_at_start)
        self.deferred_full = 0  # full collections run by poll() (gc_deferred_full)
        self._thresholds: tuple[int, int, int] | None = None  # gc.get_threshold() before defer_full()

    def _callback(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._t0, self._c0 = time.perf_counter(), time.thread_time()
            return
        t0 = self._t0
        cpu = (time.thread_time() - self._c0) * 1e3
        ms = (time.perf_counter() - t0) * 1e3
        g = int(info.get("generation", 0))
        self.collections[g] += 1
        self.ms_total[g] += ms
        self.ms_max[g] = max(self.ms_max[g], ms)
        self.cpu_ms_total[g] += cpu
        ident = threading.get_ident()
        self._thread_cpu_ms[ident] = self._thread_cpu_ms.get(ident, 0.0) + cpu
        if g or ms >= 1.0:  # the rare and the long ones: young collections are many and short
            self.events.append((t0, threading.current_thread().name, g, ms, cpu, int(info.get("collected", 0))))

    def subscriptions(self) -> dict[type, Any]:
        return {}

    def defer_full(self) -> None:
        """Turn CPython's automatic full collection off for the daemon (module notes):
        :meth:`poll` runs them between messages; :meth:`finish` turns it back on."""
        if self._thresholds is None:
            self._thresholds = gc.get_threshold()
            t0, t1, _ = self._thresholds
            gc.set_threshold(t0, t1, _OUT_OF_REACH)

    def poll(self) -> int:
        """With :meth:`defer_full`: a full collection when :data:`FULL_AFTER` collections of
        generation 1 have run since the last one (``gc.get_count()[2]``). Returns 0 (no
        message handled)."""
        if self._thresholds is not None and gc.get_count()[2] >= FULL_AFTER:
            gc.collect(2)
            self.deferred_full += 1
        return 0

    def thread_cpu_ms(self) -> float:
        """The collections run in the calling thread so far, in its CPU time, ms."""
        return self._thread_cpu_ms.get(threading.get_ident(), 0.0)

    def counters(self) -> dict[str, Any]:
        """``gc_collections_gen<g>``, ``gc_ms_total_gen<g>``, ``gc_ms_max_gen<g>`` (wall
        clock) and ``gc_cpu_ms_total_gen<g>`` (the collecting threads' CPU) for generations
        0-2, ``gc_frozen_objects`` (:func:`gc.get_freeze_count` now) and
        ``gc_frozen_at_start`` (:meth:`freeze`)."""
        out: dict[str, Any] = {}
        for g in range(3):
            out[f"gc_collections_gen{g}"] = self.collections[g]
            out[f"gc_ms_total_gen{g}"] = round(self.ms_total[g], 1)
            out[f"gc_ms_max_gen{g}"] = round(self.ms_max[g], 2)
            out[f"gc_cpu_ms_total_gen{g}"] = round(self.cpu_ms_total[g], 1)
        out["gc_frozen_objects"] = gc.get_freeze_count()
        out["gc_frozen_at_start"] = self.frozen_at_start
        out["gc_deferred_full"] = self.deferred_full
        return out

    def freeze(self) -> int:
        """:func:`freeze_startup` for the daemon this watch is a stage of, undone at its
        :meth:`finish` (another daemon in the same process, a test's or a benchmark's,
        then collects this one's objects as usual)."""
        self.frozen_at_start = freeze_startup()
        return self.frozen_at_start

    def finish(self) -> int:
        """End of the daemon's input: the collections of the run logged; what :meth:`freeze`
        froze goes back to the collector, and the automatic full collection that
        :meth:`defer_full` turned off comes back."""
        log.info("garbage collections over the run (generation: count, CPU ms, largest wall ms): %s; "
                 "%d objects frozen at start; %d full collections run between messages", ", ".join(
                     f"{g}: {self.collections[g]}, {self.cpu_ms_total[g]:.0f}, {self.ms_max[g]:.1f}" for g in range(3)),
                 self.frozen_at_start, self.deferred_full)
        if self.frozen_at_start:
            gc.unfreeze()
        if self._thresholds is not None:
            gc.set_threshold(*self._thresholds)
            self._thresholds = None
        return 0

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


def freeze_startup() -> int:
    """Collect, then move every object the process holds now out of the collector's reach
    (:func:`gc.freeze`): the daemon's start-up (its imports, the stages, the map's load)
    makes most of the objects a full collection would otherwise walk again and again over
    the run, although they live as long as the process. Garbage they become while frozen
    is not collected if it is a cycle (reference counting still frees the rest) until
    :func:`gc.unfreeze` (:meth:`GcWatch.finish`). Returns the objects frozen, logged."""
    gc.collect()
    gc.freeze()
    n = gc.get_freeze_count()
    log.info("garbage collector: %d objects made at start-up frozen out of its collections", n)
    return n
