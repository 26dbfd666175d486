"""The odometry filter's late-measurement journal (no I/O).

A floor visual odometry step reaches the filter when it is already past the step's frame
(on the office demo 53 ms at the median, 227 ms at p90, up to half a second). With the
journal, :class:`robotd.odometry.fusion.OdometryFilter` keeps every wheel and gyro message
of its history with a snapshot of the filter after it (:class:`Snapshot`); a step then
goes back to the snapshot after the first message that reached its stamp, is applied
there, and the messages since are run once more (:meth:`Journal.rewind_point`,
:meth:`Journal.tail`), so the fused pose does not depend on the pipeline's timing.
"""

from __future__ import annotations

import collections
from typing import NamedTuple

import numpy as np

from robotd.base.messages import WheelTicks, YawRate
from robotd.odometry.ekf import EkfState
from robotd.odometry.history import HistoryMark
from robotd.odometry.relative import PoseClone

__all__ = ["Journal", "Snapshot"]


class Snapshot(NamedTuple):
    """Everything a wheel or gyro message changes in the fused filter, after that message
    (the wheel-only odometry and the twin excepted: a replay does not touch them)."""

    state: EkfState | None
    wheel_ref: WheelTicks | None
    last_yaw_ns: int | None
    gyro_buf: tuple[YawRate, ...]
    was_still: bool
    clone: PoseClone | None
    map: np.ndarray
    history: HistoryMark
    counters: dict[str, int]  # the FilterCounters' fields (a dict copies in a fraction of the time)


class Journal:
    """Each wheel or gyro message with the filter's :class:`Snapshot` after it, over the
    pose history."""

    def __init__(self) -> None:
        self._entries: collections.deque[tuple[WheelTicks | YawRate, Snapshot]] = collections.deque()

    def __len__(self) -> int:
        return len(self._entries)

    def append(self, msg: WheelTicks | YawRate, snap: Snapshot, oldest_ns: int) -> None:
        """Journal ``msg``; entries whose state is older than ``oldest_ns`` (the oldest
        recorded stamp) are dropped, the newest one always kept."""
        entries = self._entries
        entries.append((msg, snap))
        while len(entries) > 1 and (entries[0][1].state is None or entries[0][1].state.stamp_ns < oldest_ns):
            entries.popleft()

    def rewind_point(self, stamp_ns: int) -> int | None:
        """The index of the first message whose snapshot reached ``stamp_ns``, or None (not
        reached yet, or gone)."""
        entries = self._entries
        at = None
        for i in range(len(entries) - 1, -1, -1):
            state = entries[i][1].state
            if state is None or state.stamp_ns < stamp_ns:
                break
            at = i
        return at

    def snapshot(self, i: int) -> Snapshot:
        return self._entries[i][1]

    def amend(self, i: int, snap: Snapshot) -> None:
        """Replace entry ``i``'s snapshot (a later rewind then keeps what was applied there)."""
        self._entries[i] = (self._entries[i][0], snap)

    def tail(self, i: int) -> list[WheelTicks | YawRate]:
        """Remove and return the messages after entry ``i``, oldest first (to run again)."""
        out = [self._entries.pop()[0] for _ in range(len(self._entries) - i - 1)]
        out.reverse()
        return out
