"""Replaying recordings: a recording played back as a driver on a manual clock.

:class:`ReplayDriver` is the replay: one deterministic, lossless
:class:`~drivers.base.Driver` with no thread of its own. :class:`ReplaySource` and its
:class:`ReplayQueue` sub-sources (a reader thread feeding two queues) remain until the
daemon has moved to :class:`ReplayDriver`.
"""

from __future__ import annotations

import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.base import Driver, Message, StatValue
from drivers.recording.reader import RecordingDamage, RecordingReader, RobotdMessage
from robotd.base.clock import ManualClock
from robotd.base.errors import DriverError, RobotdError
from robotd.base.messages import Frame, WheelTicks, YawRate

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------
# Replay
# --------------------------------------------------------------------------------------


class ReplayQueue:
    """One driver-like output of a :class:`ReplaySource` (``replay.base``, ``replay.floor``).

    ``read(timeout_s)`` waits up to ``timeout_s`` for the next item and returns it (a
    camera: one :class:`Frame`), or every item then waiting, up to ``max_batch`` (the
    base: a list of :class:`WheelTicks` and :class:`YawRate`), or None. After the reader
    thread failed and the queue is empty, ``read`` raises its
    :class:`~robotd.base.errors.DriverError`. ``close`` does nothing: the
    :class:`ReplaySource` owns the file and the thread.
    """

    def __init__(self, name: str, maxsize: int, batch: bool, owner: ReplaySource,
                 max_batch: int = 64) -> None:
        self.name = name
        self.batch = batch
        self.max_batch = max_batch
        self._q: queue.Queue[Any] = queue.Queue(maxsize=maxsize)
        self._owner = owner
        self.handed_out = 0
        """Items returned by :meth:`read` so far."""
        self.queued = 0
        """Items the reader thread has queued so far."""

    def read(self, timeout_s: float) -> list[WheelTicks | YawRate] | Frame | None:
        self._owner.start()
        try:
            first = self._q.get(timeout=timeout_s)
        except queue.Empty:
            if self._owner.error is not None and self._owner.finished.is_set():
                raise self._owner.error from None
            return None
        if not self.batch:
            self.handed_out += 1
            return first
        items = [first]
        while len(items) < self.max_batch:
            try:
                items.append(self._q.get_nowait())
            except queue.Empty:
                break
        self.handed_out += len(items)
        return items

    def _put(self, item: Any, stop: threading.Event) -> bool:
        while not stop.is_set():
            try:
                self._q.put(item, timeout=0.1)
                self.queued += 1
                return True
            except queue.Full:
                continue
        return False

    def close(self) -> None:
        pass


class ReplaySource:
    """Feeds a recording back as the daemon's sources, in recorded order, losslessly.

    One reader thread walks the recording in log-time order and hands base messages
    (``/wheel_ticks``, ``/imu``) to :attr:`base` and frames of the cameras in ``cameras``
    to :attr:`floor` (and :meth:`camera` for others), each a bounded blocking queue of
    ``queue_size`` items: nothing is dropped, the thread waits for the daemon. Frames of
    other cameras and every other topic (``/odom``, ``/ground_truth``) are not handed
    out; they are passed to ``on_other(topic, message)`` when given (in the reader
    thread) and counted in :attr:`skipped`.

    ``speed=None`` replays as fast as the consumers take the data; ``speed=s`` paces the
    messages at ``s`` times recorded speed on the wall clock (inside the reader thread
    only). With a :class:`~robotd.base.clock.ManualClock`, the clock is set to each message's
    stamp just before the message is handed out (it never goes backwards), so the daemon
    runs on recorded time.

    The file is opened at construction (:class:`~robotd.base.errors.DriverError` if it is not a
    recording); the thread starts on :meth:`start` or the first ``read``. :attr:`finished`
    is set once every message has been queued (or the thread failed: :attr:`error`);
    :meth:`done` is true once they have also all been read.
    """

    def __init__(self, path: str | os.PathLike[str], clock: ManualClock | None = None,
                 speed: float | None = None, *, cameras: Sequence[str] = ("floor",),
                 queue_size: int = 64,
                 on_other: Callable[[str, RobotdMessage], None] | None = None) -> None:
        if speed is not None and not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"speed must be a positive number or None, got {speed}")
        if queue_size < 1:
            raise ValueError("queue_size must be >= 1")
        self.path = Path(path)
        self.clock = clock
        self.speed = speed
        self.on_other = on_other
        self.reader = RecordingReader(path)
        self.base = ReplayQueue("base", queue_size, batch=True, owner=self)
        self._cameras = {name: ReplayQueue(name, queue_size, batch=False, owner=self) for name in cameras}
        self.floor: ReplayQueue | None = self._cameras.get("floor")
        self.finished = threading.Event()
        self.error: DriverError | None = None
        self.counts: dict[str, int] = {}
        """Messages handed to the sub-sources, per topic."""
        self.skipped: dict[str, int] = {}
        """Messages not handed out, per topic."""
        self._stop = threading.Event()
        self._start_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._closed = False

    @property
    def damage(self) -> RecordingDamage:
        """Damage met in the recording so far."""
        return self.reader.damage

    def camera(self, name: str) -> ReplayQueue:
        """The sub-source of camera ``name`` (one of ``cameras``)."""
        return self._cameras[name]

    def start(self) -> None:
        """Start the reader thread (once; later calls do nothing)."""
        with self._start_lock:
            if self._thread is None and not self._closed:
                self._thread = threading.Thread(target=self._run, name="robotd-replay", daemon=True)
                self._thread.start()

    def done(self) -> bool:
        """True once every message was queued and :meth:`ReplayQueue.read` has returned
        each of them (an item being taken out counts only once ``read`` returns it)."""
        return self.finished.is_set() and all(
            q.handed_out == q.queued for q in (self.base, *self._cameras.values()))

    def _route(self, msg: RobotdMessage) -> ReplayQueue | None:
        if isinstance(msg, (WheelTicks, YawRate)):
            return self.base
        if isinstance(msg, Frame):
            return self._cameras.get(msg.camera)
        return None

    def _run(self) -> None:
        try:
            self._play()
        except RobotdError as exc:
            self.error = exc if isinstance(exc, DriverError) else DriverError(f"{self.path}: {exc}")
            log.warning("replay of %s failed: %s", self.path, exc)
        except OSError as exc:
            self.error = DriverError(f"{self.path}: cannot read the recording: {exc.strerror}")
            log.warning("%s", self.error)
        except Exception as exc:  # reported through read(), never silently lost
            self.error = DriverError(f"{self.path}: replay failed: {exc!r}")
            log.exception("replay of %s failed", self.path)
        finally:
            self.finished.set()

    def _play(self) -> None:
        wall0 = first_ns = None
        for topic, msg in self.reader.messages():
            if self._stop.is_set():
                return
            target = self._route(msg)
            if target is None:
                self.skipped[topic] = self.skipped.get(topic, 0) + 1
                if self.on_other is not None:
                    self.on_other(topic, msg)
                continue
            if self.speed is not None:
                if wall0 is None:
                    wall0, first_ns = time.monotonic(), msg.stamp_ns
                delay = wall0 + (msg.stamp_ns - first_ns) / 1e9 / self.speed - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
            if self.clock is not None:
                now = self.clock.now_ns()
                if msg.stamp_ns > now:
                    self.clock.set_ns(msg.stamp_ns)
            if not target._put(msg, self._stop):
                return
            self.counts[topic] = self.counts.get(topic, 0) + 1

    def close(self) -> None:
        """Stop the reader thread and close the file; safe to call twice."""
        with self._start_lock:
            if self._closed:
                return
            self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
        self.reader.close()

    def __enter__(self) -> ReplaySource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------------------
# ReplayDriver
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReplayConfig:
    """What :func:`open_replay` needs: the recording and the pace.

    ``speed`` is a multiple of recorded time on the wall clock (``1.0``: as recorded),
    or None for as fast as the caller reads.
    """

    path: str
    speed: float | None = None


def open_replay(section: ReplayConfig, clock: ManualClock) -> ReplayDriver:
    """The registry's factory of ``("replay", "mcap")``."""
    return ReplayDriver(section.path, clock, section.speed)


class ReplayDriver(Driver):
    """A recording's :class:`WheelTicks`, :class:`YawRate` and :class:`Frame` messages,
    handed out in log-time order (the order the live daemon received them); lossless
    and deterministic: two replays of one file give the same sequence.

    Each :meth:`read` returns the next messages, at most ``max_batch`` of them and never
    more than one frame. As a message is handed out, ``clock`` is moved to its stamp
    unless it is already later, so the clock never goes backwards and, after a read,
    equals the latest stamp handed out (the base stream's log time), never a time not
    yet handed out. There is no thread: with ``speed=None`` a read returns at once;
    with ``speed=s`` a read waits (up to its timeout, on ``wall_clock``) until the next
    message is due at ``s`` times recorded speed, and returns ``[]`` if it is not due
    within the timeout. Topics that are not driver output (``/odom``,
    ``/ground_truth``) are counted in :attr:`skipped`.

    The file is opened at construction (:class:`~robotd.base.errors.DriverError` if it
    is not a recording). A damaged file is replayed as far as it is intact (see
    :attr:`damage`), then :attr:`done`. ``wall_clock`` (seconds) and ``sleep`` are the
    pacing's time source, replaced in tests.
    """

    def __init__(self, path: str | os.PathLike[str], clock: ManualClock,
                 speed: float | None = None, *, max_batch: int = 64, name: str = "replay",
                 wall_clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        if speed is not None and not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"speed must be a positive number or None, got {speed}")
        if max_batch < 1:
            raise ValueError("max_batch must be >= 1")
        super().__init__(name)
        self.path = Path(path)
        self.clock = clock
        self.speed = speed
        self.max_batch = max_batch
        self._wall_clock = wall_clock
        self._sleep = sleep
        self._reader = RecordingReader(path)
        self._messages: Iterator[tuple[str, RobotdMessage]] = self._reader.messages()
        self._next: tuple[str, Message] | None = None
        self._exhausted = False
        self._pace_origin: tuple[float, int] | None = None  # (wall s, stamp ns) of the first
        self.counts: dict[str, int] = {}
        """Messages handed out, per topic."""
        self.skipped: dict[str, int] = {}
        """Messages of the recording not handed out (not driver output), per topic."""

    @property
    def damage(self) -> RecordingDamage:
        """Damage met in the recording so far (grows while it is replayed)."""
        return self._reader.damage

    @property
    def time_range_ns(self) -> tuple[int, int] | None:
        """``(first, last)`` log time of the intact messages, ns; None for an empty file."""
        return self._reader.time_range_ns

    @property
    def done(self) -> bool:
        """True once the last message was handed out (at once for an empty recording)."""
        if self.closed:
            return self._exhausted and self._next is None
        return self._peek() is None

    def _peek(self) -> tuple[str, Message] | None:
        """The next driver message without handing it out (None at the end)."""
        while self._next is None and not self._exhausted:
            item = next(self._messages, None)
            if item is None:
                self._exhausted = True
            elif isinstance(item[1], WheelTicks | YawRate | Frame):
                self._next = (item[0], item[1])
            else:
                self.skipped[item[0]] = self.skipped.get(item[0], 0) + 1
        return self._next

    def _wait_until_due(self, stamp_ns: int, timeout_s: float) -> bool:
        """With a speed, wait until ``stamp_ns`` is due; False if it is not within
        ``timeout_s`` (the wait then lasted ``timeout_s``)."""
        if self.speed is None:
            return True
        if self._pace_origin is None:
            self._pace_origin = (self._wall_clock(), stamp_ns)
        wall0, stamp0 = self._pace_origin
        wait_s = wall0 + (stamp_ns - stamp0) / 1e9 / self.speed - self._wall_clock()
        if wait_s <= 0:
            return True
        if wait_s > timeout_s:
            if timeout_s > 0:
                self._sleep(timeout_s)
            return False
        self._sleep(wait_s)
        return True

    def _read_internal(self, timeout_s: float) -> list[Message]:
        batch: list[Message] = []
        has_frame = False
        while len(batch) < self.max_batch:
            item = self._peek()
            if item is None:
                break
            topic, msg = item
            if isinstance(msg, Frame) and has_frame:
                break
            if not self._wait_until_due(msg.stamp_ns, 0.0 if batch else timeout_s):
                break
            self._next = None
            if msg.stamp_ns > self.clock.now_ns():
                self.clock.set_ns(msg.stamp_ns)
            batch.append(msg)
            has_frame = has_frame or isinstance(msg, Frame)
            self.counts[topic] = self.counts.get(topic, 0) + 1
        return batch

    def _close_internal(self) -> None:
        self._reader.close()

    def _stats_internal(self) -> dict[str, StatValue]:
        out: dict[str, StatValue] = {"done": int(self._exhausted and self._next is None),
                                     "skipped": sum(self.skipped.values())}
        out.update({k: int(v) for k, v in self.damage.as_dict().items()})
        return out

    def __str__(self) -> str:
        return f"{self.name}: recording {self.path}"
