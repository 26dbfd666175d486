"""The one bounded queue: lossy (drop oldest / drop newest, counted) and lossless."""

from __future__ import annotations

import threading

import pytest

from robotd.base.queues import BoundedQueue


def test_lossy_drop_oldest_keeps_the_freshest_and_counts():
    wake = threading.Event()
    q: BoundedQueue[int] = BoundedQueue(3, lossless=False, drop="oldest", wakeup=wake)
    for i in range(5):
        assert q.put(i)
    assert wake.is_set()
    assert (q.dropped, q.put_count, q.qsize()) == (2, 5, 3)
    assert [q.get_nowait() for _ in range(4)] == [2, 3, 4, None]


def test_lossy_drop_newest_refuses_what_does_not_fit():
    q: BoundedQueue[int] = BoundedQueue(2, lossless=False, drop="newest")
    assert [q.put(i) for i in range(4)] == [True, True, False, False]
    assert (q.dropped, q.put_count) == (2, 2)
    assert q.get_batch(0, 10) == [0, 1]


def test_lossless_put_waits_for_room_and_loses_nothing():
    q: BoundedQueue[str] = BoundedQueue(1, lossless=True)
    stop = threading.Event()
    assert q.put("a", stop)
    done: list[bool] = []
    t = threading.Thread(target=lambda: done.append(q.put("b", stop)))
    t.start()
    # Whenever the thread runs, "b" cannot be in the queue before "a" leaves it.
    assert q.put_count == 1 and q.dropped == 0
    assert q.get(timeout_s=10.0) == "a"
    t.join(10.0)
    assert done == [True] and q.get_nowait() == "b" and q.dropped == 0


def test_lossless_put_gives_up_when_stopped_instead_of_hanging():
    q: BoundedQueue[str] = BoundedQueue(1, lossless=True)
    stop = threading.Event()
    assert q.put("c", stop)
    stop.set()
    assert q.put("d", stop) is False
    assert q.put_count == 1 and q.get_nowait() == "c"


def test_batches_and_bad_arguments():
    q: BoundedQueue[int] = BoundedQueue(10, lossless=False)
    for i in range(7):
        q.put(i)
    assert q.get_batch(0, 3) == [0, 1, 2]
    assert q.get_batch(0, 10) == [3, 4, 5, 6]
    assert q.get_batch(0, 10) == []
    with pytest.raises(ValueError, match="maxsize"):
        BoundedQueue(0, lossless=True)
    with pytest.raises(ValueError, match="drop"):
        BoundedQueue(1, lossless=False, drop="middle")  # type: ignore[arg-type]


def test_put_many_is_puts_one_by_one():
    """A batch is queued as the same items put one at a time would be: the same order,
    drops and counts in each mode, the consumer woken."""
    for lossless, drop, size in ((False, "oldest", 3), (False, "newest", 3), (True, "oldest", 10)):
        one: BoundedQueue[int] = BoundedQueue(size, lossless=lossless, drop=drop)
        wake = threading.Event()
        many: BoundedQueue[int] = BoundedQueue(size, lossless=lossless, drop=drop, wakeup=wake)
        singles = [one.put(i) for i in range(5)]
        assert many.put_many(range(5)) is all(singles)
        assert wake.is_set()
        assert (many.dropped, many.put_count, many.qsize()) == (one.dropped, one.put_count, one.qsize())
        assert many.take(100) == one.get_batch(0, 100) != []
    assert many.put_many([]) and many.take(5) == []


def test_put_many_waits_for_room_in_a_lossless_queue_and_gives_up_when_stopped():
    q: BoundedQueue[int] = BoundedQueue(4, lossless=True)
    stop = threading.Event()
    done: list[bool] = []
    t = threading.Thread(target=lambda: done.append(q.put_many(range(10), stop)))
    t.start()
    got: list[int] = []
    while len(got) < 10:
        got += q.take(3) or ([x] if (x := q.get(timeout_s=10.0)) is not None else [])
    t.join(10.0)
    assert done == [True] and got == list(range(10)) and q.dropped == 0
    assert q.put_many(range(4), stop)
    stop.set()
    assert q.put_many([4, 5], stop) is False  # full and stopped: not queued, not hanging
    assert q.put_count == 14 and q.take(10) == [0, 1, 2, 3]
