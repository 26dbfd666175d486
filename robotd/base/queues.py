"""The one bounded queue between a producer thread and a consumer.

Every hand-over in robotd (a source thread to the pipeline, the virtual robot's camera to
its reader, a recording's reader thread to the replay driver) is this queue in one of two
modes:

- lossy (live hardware): a full queue never blocks the producer. ``drop="oldest"`` throws
  the oldest item away to make room, so the consumer always sees the freshest data (the
  daemon's source queues); ``drop="newest"`` refuses the new item, as a camera does whose
  reader is late (its driver buffers are full). Every drop is counted in ``dropped``.
- lossless (replay, the virtual robot as fast as the CPU allows): ``put`` waits until there
  is room, or until the ``stop`` event it is given is set, so a run gives the same result
  however fast the CPU is.
"""

from __future__ import annotations

import queue
import threading
from typing import Generic, Literal, TypeVar

T = TypeVar("T")

_POLL_S = 0.1  # how often a blocked lossless put looks at its stop event


class BoundedQueue(Generic[T]):
    """A thread-safe FIFO of at most ``maxsize`` items, lossy or lossless (see the module).

    ``wakeup`` (optional) is set after every successful put, so a consumer serving several
    queues can sleep on one event. Counters: ``put_count`` (items accepted), ``dropped``
    (items lost to a full lossy queue).
    """

    def __init__(self, maxsize: int, *, lossless: bool, drop: Literal["oldest", "newest"] = "oldest",
                 wakeup: threading.Event | None = None, name: str = "") -> None:
        if maxsize < 1:
            raise ValueError(f"maxsize must be at least 1, got {maxsize}")
        if drop not in ("oldest", "newest"):
            raise ValueError(f"drop must be 'oldest' or 'newest', got {drop!r}")
        self.name = name
        self.maxsize = maxsize
        self.lossless = lossless
        self.drop = drop
        self._q: queue.Queue[T] = queue.Queue(maxsize=maxsize)
        self._wakeup = wakeup
        self._lock = threading.Lock()
        self.put_count = 0
        self.dropped = 0

    def put(self, item: T, stop: threading.Event | None = None) -> bool:
        """Queue ``item``. Returns False when it was not queued: a lossless put whose
        ``stop`` was set while it waited, or a lossy ``drop="newest"`` put on a full queue."""
        if self.lossless:
            while True:
                try:
                    self._q.put(item, timeout=_POLL_S)
                    break
                except queue.Full:
                    if stop is not None and stop.is_set():
                        return False
        elif self.drop == "newest":
            try:
                self._q.put_nowait(item)
            except queue.Full:
                with self._lock:
                    self.dropped += 1
                return False
        else:
            while True:
                try:
                    self._q.put_nowait(item)
                    break
                except queue.Full:
                    try:
                        self._q.get_nowait()
                        with self._lock:
                            self.dropped += 1
                    except queue.Empty:
                        pass
        with self._lock:
            self.put_count += 1
        if self._wakeup is not None:
            self._wakeup.set()
        return True

    def get(self, timeout_s: float | None = None) -> T | None:
        """The next item, waiting up to ``timeout_s`` (None: forever, 0: not at all);
        None when there is none by then."""
        try:
            if timeout_s is not None and timeout_s <= 0:
                return self._q.get_nowait()
            return self._q.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def get_nowait(self) -> T | None:
        """The next item, or None at once when the queue is empty."""
        return self.get(0)

    def get_batch(self, first_timeout_s: float, max_items: int) -> list[T]:
        """Up to ``max_items`` items: waits up to ``first_timeout_s`` for the first, then
        takes what is already waiting. An empty list when nothing came."""
        first = self.get(first_timeout_s)
        if first is None:
            return []
        items = [first]
        while len(items) < max_items and (nxt := self.get_nowait()) is not None:
            items.append(nxt)
        return items

    def qsize(self) -> int:
        """Items waiting now (a snapshot)."""
        return self._q.qsize()
