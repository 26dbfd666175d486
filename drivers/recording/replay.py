"""Replaying recordings: a recording played back as a driver on a manual clock.

:class:`ReplayDriver` is the replay: one deterministic, lossless
:class:`~drivers.base.Driver` with no thread of its own, which the daemon registers as one
source (``robotd replay``, the loop-curve training).
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from drivers.base import Driver, Message, StatValue
from drivers.recording.reader import RecordingDamage, RecordingReader, RobotdMessage
from robotd.base.clock import ManualClock
from robotd.base.messages import Frame, WheelTicks, YawRate

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------
# Replay
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
    yet handed out. There is no thread: with ``speed=None`` a read returns at once
    (once the recording is over, after its timeout: nothing more will come);
    with ``speed=s`` a read waits (up to its timeout, on ``wall_clock``) until the next
    message is due at ``s`` times recorded speed, and returns ``[]`` if it is not due
    within the timeout. Topics that are not driver output (``/odom``,
    ``/ground_truth``) are counted in :attr:`skipped`.

    The file is opened at construction (:class:`~robotd.base.errors.DriverError` if it
    is not a recording). A damaged file is replayed as far as it is intact (see
    :attr:`damage`), then :attr:`done`. ``wall_clock`` (seconds) and ``sleep`` are the
    pacing's time source, replaced in tests. ``on_other(topic, message)``, when given, is
    called with each message that is not driver output (a calibration run keeps the
    virtual robot's ``/ground_truth`` this way), from the thread that reads.

    Thread safety: one thread reads; another may watch :attr:`finished` and
    :attr:`handed_out` (plain attributes), never :attr:`done`, which reads ahead.
    """

    def __init__(self, path: str | os.PathLike[str], clock: ManualClock,
                 speed: float | None = None, *, max_batch: int = 64, name: str = "replay",
                 wall_clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep,
                 on_other: Callable[[str, RobotdMessage], None] | None = None) -> None:
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
        # Without on_other, what is not driver output is not even decoded.
        self._messages: Iterator[tuple[str, RobotdMessage]] = self._reader.messages(
            None if on_other is not None else (WheelTicks, YawRate, Frame), lazy_images=True)
        self._next: tuple[str, Message] | None = None
        self._exhausted = False
        self._pace_origin: tuple[float, int] | None = None  # (wall s, stamp ns) of the first
        self.counts: dict[str, int] = {}
        """Messages handed out, per topic."""
        self._skipped: dict[str, int] = {}
        self.on_other = on_other
        self.handed_out = 0
        """Messages handed out so far, all topics."""
        self.finished = False
        """Set by the reading thread once the last message was handed out."""

    @property
    def skipped(self) -> dict[str, int]:
        """Messages of the recording not handed out (not driver output), per topic."""
        out = dict(self._skipped)
        for topic, n in self._reader.unwanted.items():
            out[topic] = out.get(topic, 0) + n
        return out

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

    def peek(self) -> tuple[str, Message] | None:
        """The first driver message not yet handed out, or None when the recording has none
        left (reads on past messages of other types and undecodable ones, counting them)."""
        return self._peek()

    def describe_contents(self) -> str:
        """The recording's topics and types in words, with its damage, for a message that
        says why it cannot be replayed."""
        topics = self._reader.topics
        if not topics:
            return "no topics"
        shown = ", ".join(f"{t} [{k or 'no schema'}]" for t, k in sorted(topics.items())[:6])
        more = f" and {len(topics) - 6} more" if len(topics) > 6 else ""
        damage = self._reader.damage
        bad = (f"; {damage.undecodable_messages} messages of robotd's types did not decode"
               if damage.undecodable_messages else "")
        return f"{len(topics)} topics: {shown}{more}{bad}"

    def _peek(self) -> tuple[str, Message] | None:
        """The next driver message without handing it out (None at the end)."""
        while self._next is None and not self._exhausted:
            item = next(self._messages, None)
            if item is None:
                self._exhausted = True
            elif isinstance(item[1], WheelTicks | YawRate | Frame):
                self._next = (item[0], item[1])
            else:
                self._skipped[item[0]] = self._skipped.get(item[0], 0) + 1
                if self.on_other is not None:
                    self.on_other(item[0], item[1])
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
        if self._peek() is None:
            # Nothing will come: wait out the timeout as a live driver would, so that the
            # source thread reading in a loop does not spin on empty reads until the daemon
            # stops (a replay read ahead into a large queue spun for the rest of the run).
            self.finished = True
            if timeout_s > 0:
                self._sleep(timeout_s)
            return []
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
        self.handed_out += len(batch)
        if self._peek() is None:
            self.finished = True
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
