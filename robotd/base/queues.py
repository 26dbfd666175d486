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

import collections
import threading
import time
from collections.abc import Iterable
from typing import Generic, Literal, TypeVar

T = TypeVar("T")

_POLL_S = 0.1  # how often a blocked lossless put looks at its stop event


class BoundedQueue(Generic[T]):
    """A thread-safe FIFO of at most ``maxsize`` items, lossy or lossless (see the module).

    ``wakeup`` (optional) is set after every successful put, so a consumer serving several
    queues can sleep on one event. Counters: ``put_count`` (items accepted), ``dropped``
    (items lost to a full lossy queue).

    A lossless put that found the queue full resumes once the consumer has taken it down
    to half (``maxsize // 2``), not after every item: a producer much faster than its
    consumer (a replay read ahead of the pipeline) then hands over half a queue per
    wake-up instead of waking, and taking the interpreter's lock from the consumer, for
    each item.
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
        self._items: collections.deque[T] = collections.deque()
        self._lock = threading.Lock()
        self._not_empty = threading.Condition(self._lock)
        self._room = threading.Condition(self._lock)
        self._resume_at = maxsize // 2  # a blocked lossless put resumes at this many items
        self._putters_waiting = 0
        self._getters_waiting = 0
        self._wakeup = wakeup
        self.put_count = 0
        self.dropped = 0

    def put(self, item: T, stop: threading.Event | None = None) -> bool:
        """Queue ``item``. Returns False when it was not queued: a lossless put whose
        ``stop`` was set while it waited, or a lossy ``drop="newest"`` put on a full queue."""
        with self._lock:
            if self._make_room(stop) <= 0:
                return False
            self._items.append(item)
            self.put_count += 1
            if self._getters_waiting:
                self._not_empty.notify()
        wakeup = self._wakeup
        if wakeup is not None and not wakeup.is_set():
            wakeup.set()
        return True

    def _make_room(self, stop: threading.Event | None) -> int:
        """With the lock held, before one item goes in: room made as the queue's mode says
        when it is full (a lossless put waits until the consumer has taken it down to half, a
        lossy one drops the oldest). 1: the item may go in; 0: refused by a full
        ``drop="newest"`` queue (counted); -1: a lossless wait stopped by ``stop``."""
        items = self._items
        if len(items) < self.maxsize:
            return 1
        if self.lossless:
            while len(items) > self._resume_at:
                if stop is not None and stop.is_set():
                    return -1
                self._putters_waiting += 1
                try:
                    self._room.wait(_POLL_S)
                finally:
                    self._putters_waiting -= 1
            return 1
        self.dropped += 1
        if self.drop == "newest":
            return 0
        items.popleft()
        return 1

    def put_many(self, items: Iterable[T], stop: threading.Event | None = None) -> bool:
        """Queue ``items`` in order, each as :meth:`put` would (the same waits, drops and
        counts), under one taking of the lock and with one wake-up of the consumer instead
        of one per item (a driver's read gives several messages at once: a replay up to
        64). Returns False when one was not queued (see :meth:`put`): refused by a full
        ``drop="newest"`` queue (the others are still offered, each counted), or a lossless
        put stopped while it waited (the items after it are not queued)."""
        queued = 0
        ok = True
        with self._lock:
            queue = self._items
            for item in items:
                if queued and self.lossless and len(queue) >= self.maxsize:
                    self._wake(queued)  # the consumer makes the room we wait for
                    queued = 0
                room = self._make_room(stop)
                if room < 0:
                    ok = False
                    break
                if room == 0:
                    ok = False
                    continue
                queue.append(item)
                self.put_count += 1
                queued += 1
            if queued:
                self._wake(queued)
        return ok

    def _wake(self, queued: int) -> None:
        """With the lock held: tell waiting getters and the consumer's wake-up event that
        ``queued`` items came."""
        if self._getters_waiting:
            self._not_empty.notify(queued)
        wakeup = self._wakeup
        if wakeup is not None and not wakeup.is_set():
            wakeup.set()

    def get(self, timeout_s: float | None = None) -> T | None:
        """The next item, waiting up to ``timeout_s`` (None: forever, 0: not at all);
        None when there is none by then."""
        with self._lock:
            items = self._items
            if not items:
                if timeout_s is not None and timeout_s <= 0:
                    return None
                deadline = None if timeout_s is None else time.monotonic() + timeout_s
                self._getters_waiting += 1
                try:
                    while not items:
                        if deadline is None:
                            self._not_empty.wait()
                        else:
                            remaining = deadline - time.monotonic()
                            if remaining <= 0:
                                return None
                            self._not_empty.wait(remaining)
                finally:
                    self._getters_waiting -= 1
            item = items.popleft()
            if self._putters_waiting and len(items) <= self._resume_at:
                self._room.notify()
            return item

    def get_nowait(self) -> T | None:
        """The next item, or None at once when the queue is empty."""
        return self.get(0)

    def take(self, max_items: int) -> list[T]:
        """Up to ``max_items`` of the items waiting now, oldest first, without waiting (an
        empty list when there are none): one taking of the lock for all of them."""
        with self._lock:
            queue = self._items
            n = min(max_items, len(queue))
            if n == 0:
                return []
            items = [queue.popleft() for _ in range(n)]
            if self._putters_waiting and len(queue) <= self._resume_at:
                self._room.notify()
            return items

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
        return len(self._items)
