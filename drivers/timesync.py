"""Device time to host time: the one synchronisation module every driver uses.

A device stamps its data with its own clock (the Kobuki's 16-bit millisecond counter, a
camera driver's buffer time); robotd stamps messages on the injected host clock. Three
small pieces do the mapping, each a function of its own state so it can be tested with
hand-derived numbers:

- :class:`CounterUnwrapper`: a wrapping device counter (``bits`` wide, one tick =
  ``tick_ns``) made monotonic, using the host time elapsed between readings to count the
  wraps a long silence hid.
- :class:`OffsetMapper`: ``host = device + offset``, with ``offset`` the minimum of
  ``receipt - device`` over a sliding window of device time (the reading that travelled
  fastest sets it; transport delay and batching drop out; the window lets the offset
  follow drift), and stamps that never go backwards (clamped, and counted).
- :class:`SkewCheck`: accepts a device stamp that claims to be on the host's time base
  only when it is within a given skew of the host clock.
"""

from __future__ import annotations

import collections

__all__ = ["CounterUnwrapper", "OffsetMapper", "SkewCheck"]


class CounterUnwrapper:
    """Unwraps a ``bits``-wide device time counter that ticks every ``tick_ns`` ns.

    The first reading is taken as it is; each later one advances the unwrapped count by
    the counter's difference modulo ``2**bits`` plus the whole number of wraps that best
    matches the host time elapsed since the previous reading (``round((elapsed - delta)
    / 2**bits)``, never negative). So a silence of several wrap periods is not mistaken
    for a short gap, and a host clock that jitters by less than half a wrap period does
    not add or remove one.
    """

    def __init__(self, bits: int, tick_ns: int) -> None:
        if bits < 1:
            raise ValueError("bits must be >= 1")
        if tick_ns < 1:
            raise ValueError("tick_ns must be >= 1")
        self.modulus = 1 << bits
        """Counter values per wrap (``2**bits``)."""
        self.tick_ns = int(tick_ns)
        self._last_raw: int | None = None
        self._last_host_ns = 0
        self._count = 0
        self.wraps_from_host_time = 0
        """Wraps inferred from elapsed host time beyond the counter's own difference."""

    @property
    def count(self) -> int:
        """The unwrapped counter (ticks) after the last :meth:`unwrap`."""
        return self._count

    def unwrap(self, raw: int, host_ns: int) -> int:
        """The unwrapped device time, ns, of counter value ``raw`` received at host time
        ``host_ns`` (ns)."""
        if self._last_raw is None:
            self._count = raw
        else:
            delta = (raw - self._last_raw) % self.modulus
            elapsed_ticks = (host_ns - self._last_host_ns) / self.tick_ns
            wraps = max(0, round((elapsed_ticks - delta) / self.modulus))
            self.wraps_from_host_time += wraps
            self._count += delta + self.modulus * wraps
        self._last_raw = raw
        self._last_host_ns = host_ns
        return self._count * self.tick_ns


class OffsetMapper:
    """Maps device time to host time by the minimum offset over a window; monotonic.

    :meth:`observe` adds one ``receipt - device`` candidate; :attr:`offset_ns` is the
    smallest candidate whose device time lies within ``window_ns`` of the newest one
    observed. :meth:`stamp` gives ``device + offset`` and :meth:`clamp` (which
    :meth:`stamp` applies) raises a stamp that would go back in time to the previous
    stamp, counting it in :attr:`clamps`. The sliding-window minimum is a deque of
    increasing candidates (Lemire 2006, "Streaming maximum-minimum filter using no more
    than three comparisons per element"), so each observation costs O(1) amortised.
    """

    def __init__(self, window_ns: int) -> None:
        if window_ns < 0:
            raise ValueError("window_ns must be >= 0")
        self.window_ns = int(window_ns)
        self._window: collections.deque[tuple[int, int]] = collections.deque()
        self._last_stamp_ns: int | None = None
        self.clamps = 0
        """Stamps raised to the previous stamp because they would have gone back."""

    @property
    def offset_ns(self) -> int | None:
        """The current offset, ns (host = device + offset); None before any observation."""
        return self._window[0][1] if self._window else None

    def observe(self, device_ns: int, receipt_ns: int) -> None:
        """Add a reading with device time ``device_ns`` received at host ``receipt_ns``.

        Readings must come in non-decreasing device time (the window is cut by the
        newest device time).
        """
        candidate = receipt_ns - device_ns
        w = self._window
        while w and w[-1][1] >= candidate:
            w.pop()
        w.append((device_ns, candidate))
        horizon = device_ns - self.window_ns
        while w[0][0] < horizon:
            w.popleft()

    def stamp(self, device_ns: int) -> int:
        """Host time, ns, of device time ``device_ns``: ``device + offset``, clamped.

        Raises ``RuntimeError`` before the first :meth:`observe`.
        """
        offset = self.offset_ns
        if offset is None:
            raise RuntimeError("no device time observed yet")
        return self.clamp(device_ns + offset)

    def clamp(self, stamp_ns: int) -> int:
        """``stamp_ns``, or the previous stamp if it is earlier (counted in :attr:`clamps`).

        Use it also for readings stamped on the host clock directly (no device time), so
        that every stamp of one driver is non-decreasing.
        """
        if self._last_stamp_ns is not None and stamp_ns < self._last_stamp_ns:
            self.clamps += 1
            stamp_ns = self._last_stamp_ns
        self._last_stamp_ns = stamp_ns
        return stamp_ns


class SkewCheck:
    """Accepts device stamps on the host's time base only within ``max_skew_ns`` of it.

    A camera driver's buffer timestamp is normally ``CLOCK_MONOTONIC``, the same base as
    the host clock; a driver on another base (wall time, a device counter) gives stamps
    far from the clock, which must not be mixed with host-stamped data.
    """

    def __init__(self, max_skew_ns: int) -> None:
        if max_skew_ns < 0:
            raise ValueError("max_skew_ns must be >= 0")
        self.max_skew_ns = int(max_skew_ns)
        self.rejected = 0
        """Stamps refused so far."""
        self.last_skew_ns = 0
        """``stamp - now`` of the last stamp checked, ns."""

    def accept(self, stamp_ns: int, now_ns: int) -> bool:
        """True if ``|stamp_ns - now_ns| <= max_skew_ns`` (both ns); else counts a rejection."""
        self.last_skew_ns = stamp_ns - now_ns
        if abs(self.last_skew_ns) > self.max_skew_ns:
            self.rejected += 1
            return False
        return True
