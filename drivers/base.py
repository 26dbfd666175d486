"""The base class of every source: what a daemon thread reads, in python-can's style.

The public :meth:`Driver.read` does what every source needs (the closed check, timeout
validation, normalising what the backend returns to a list, counting, logging); a
backend implements only ``_read_internal(timeout_s)``, ``_close_internal()`` and,
optionally, ``_stats_internal()``, like python-can's ``BusABC.recv`` over
``_recv_internal``. Every driver is a context manager and :meth:`Driver.close` is safe
to call twice.

Reconnection lives here, once, for every device that can vanish (a camera unplugged, a
USB serial adapter pulled): a backend that implements ``_open_internal()`` and
``_release_internal()`` and ends its ``__init__`` with :meth:`Driver._start` is reopened
with exponential backoff when its ``_read_internal`` raises
:class:`~robotd.base.errors.DriverError`, and :meth:`Driver.read` then returns ``[]``
instead of raising. The time without data (a *gap*, from the loss to the first message
after it) is logged when it ends, counted, and reported by :meth:`Driver.stats`, from
which the daemon's STATUS line shows it. A backend whose device library reconnects by
itself (DepthAI) reports the loss with :meth:`Driver._device_away` so the gap is counted
the same way. The daemon never reopens a driver: a
:class:`~robotd.base.errors.DriverError` out of :meth:`Driver.read` means the driver
cannot go on.

Reconnection never sleeps on the wall clock unless the clock is the real
:class:`~robotd.base.clock.MonotonicClock`: with any other clock, while the device is away,
``read`` returns ``[]`` at once until the clock reaches the next retry time, so a replay or
a test drives the backoff by moving a :class:`~robotd.base.clock.ManualClock`.
"""

from __future__ import annotations

import logging
import math
import time
from types import TracebackType
from typing import Self

from robotd.base.clock import Clock, MonotonicClock
from robotd.base.errors import DriverError
from robotd.base.messages import BaseStatus, Frame, WheelDrop, WheelTicks, YawRate

__all__ = ["Driver", "Message", "StatValue"]

_log = logging.getLogger(__name__)

Message = WheelTicks | YawRate | Frame | BaseStatus | WheelDrop
"""What a driver hands out."""

StatValue = int | float | str
"""A value of :meth:`Driver.stats` (JSON-ready)."""

_MAX_DISTINCT_ERRORS_LOGGED = 100
"""Distinct error texts remembered for "log once" (bounds memory on a flood of texts)."""


class Driver:
    """Base class of every source (a base, a camera, a replay); a context manager.

    ``name`` is the source's role in the daemon (``"base"``, ``"floor"``, ...), used in
    logs and STATUS lines. Counters kept here, for :meth:`stats`:

    - ``reads``: calls of :meth:`read` that reached the backend;
    - ``messages_out``: messages returned by :meth:`read`;
    - ``empty_reads``: reads that returned no message (timeout, nothing waiting);
    - ``errors``: :class:`~robotd.base.errors.DriverError` raised by the backend.

    A driver that reconnects (see the module; it called :meth:`_start`) adds:

    - ``connected``: 1 while the device is open, 0 while waiting to reconnect;
    - ``losses``: times the device was lost (each begins a gap);
    - ``reopen_failures`` and ``reconnects``: reconnection attempts that failed, succeeded;
    - ``gaps``: gaps that ended (data flowed again); ``gap_s_total`` and ``last_gap_s``
      their summed and latest length, seconds; ``away_s``: the current gap so far (0
      when data flows).

    ``clock`` times the backoff and the gaps (default: the host monotonic clock). After a
    loss, attempts are made ``initial_backoff_s`` later, then at doubling intervals up to
    ``max_backoff_s``.
    """

    def __init__(self, name: str, *, clock: Clock | None = None,
                 initial_backoff_s: float = 0.5, max_backoff_s: float = 8.0) -> None:
        if not 0 < initial_backoff_s <= max_backoff_s:
            raise ValueError("need 0 < initial_backoff_s <= max_backoff_s")
        self.name = name
        self._closed = False
        self._base_counts = {"reads": 0, "messages_out": 0, "empty_reads": 0, "errors": 0}
        self._errors_logged: set[str] = set()
        self._clock: Clock = MonotonicClock() if clock is None else clock
        self._may_sleep = isinstance(self._clock, MonotonicClock)
        self._initial_backoff_ns = int(initial_backoff_s * 1e9)
        self._max_backoff_ns = int(max_backoff_s * 1e9)
        self._backoff_ns = self._initial_backoff_ns
        self._next_attempt_ns = 0
        self._reconnecting = False  # set by _start(): this driver reopens itself
        self._connected = False
        self._gap_start_ns: int | None = None
        self._gap_counts: dict[str, StatValue] = {
            "losses": 0, "reopen_failures": 0, "reconnects": 0, "gaps": 0,
            "gap_s_total": 0.0, "last_gap_s": 0.0}

    # -- what a backend implements ---------------------------------------------------

    def _read_internal(self, timeout_s: float) -> Message | list[Message] | None:
        """Wait up to ``timeout_s`` seconds for data; return None, one message or a list.

        Raise :class:`~robotd.base.errors.DriverError` when the device failed.
        """
        raise NotImplementedError

    def _close_internal(self) -> None:
        """Release the device; called once, by the first :meth:`close`."""

    def _stats_internal(self) -> dict[str, StatValue]:
        """The backend's own counters (flat; names must not clash with the base's)."""
        return {}

    def _open_internal(self) -> None:
        """Open the device (reconnecting drivers only); raise :class:`DriverError` saying
        why if it cannot be."""
        raise NotImplementedError

    def _release_internal(self) -> None:
        """Release the device; called once per successful ``_open_internal``."""
        raise NotImplementedError

    # -- reconnection (drivers that call _start) ---------------------------------------

    def _start(self) -> None:
        """Open the device for the first time and from now on reopen it when it is lost;
        a reconnecting backend's ``__init__`` ends with this.

        A failure here raises: a device that is missing at start-up is a configuration
        or wiring problem to report, not something to wait for.
        """
        self._open_internal()
        self._connected = True
        self._reconnecting = True

    @property
    def connected(self) -> bool:
        """True while the device is open (False while waiting to reconnect, or closed)."""
        return self._connected

    def _device_away(self, reason: str) -> None:
        """The device stopped delivering but is still open (its library is reconnecting
        it): begin a gap, once. The gap ends at the next message."""
        if self._gap_start_ns is None:
            self._gap_start_ns = self._clock.now_ns()
            self._gap_counts["losses"] += 1  # type: ignore[operator]
            _log.warning("%s lost (%s); waiting for it to come back", self, reason)

    def _lose(self, exc: DriverError) -> None:
        """The device failed: release it, begin a gap (unless one is open), and schedule
        the first reconnection attempt."""
        self._connected = False
        try:
            self._release_internal()
        except Exception as close_exc:  # noqa: BLE001 - the device is gone; log and go on
            _log.debug("%s: error while releasing a lost device: %s", self, close_exc)
        if self._gap_start_ns is None:
            self._gap_start_ns = self._clock.now_ns()
            self._gap_counts["losses"] += 1  # type: ignore[operator]
        self._backoff_ns = self._initial_backoff_ns
        self._next_attempt_ns = self._clock.now_ns() + self._backoff_ns
        _log.warning("%s lost (%s); reconnecting in %.1f s", self, exc, self._backoff_ns / 1e9)

    def _reconnect(self, timeout_s: float) -> bool:
        """One reconnection attempt if it is due; True when the device is open again."""
        wait_ns = self._next_attempt_ns - self._clock.now_ns()
        if wait_ns > 0:
            if not (self._may_sleep and timeout_s):
                return False
            # Real clock only: wait inside read() instead of letting the caller spin.
            time.sleep(min(wait_ns / 1e9, timeout_s))
            if self._clock.now_ns() < self._next_attempt_ns:
                return False
        counts = self._gap_counts
        try:
            self._open_internal()
        except DriverError as exc:
            counts["reopen_failures"] += 1  # type: ignore[operator]
            self._backoff_ns = min(2 * self._backoff_ns, self._max_backoff_ns)
            self._next_attempt_ns = self._clock.now_ns() + self._backoff_ns
            log = _log.warning if counts["reopen_failures"] == 1 else _log.debug
            log("%s: reconnection failed (%s); next try in %.1f s", self, exc, self._backoff_ns / 1e9)
            return False
        self._connected = True
        counts["reconnects"] += 1  # type: ignore[operator]
        self._backoff_ns = self._initial_backoff_ns
        _log.warning("%s reconnected", self)
        return True

    def _end_gap(self) -> None:
        assert self._gap_start_ns is not None
        gap_s = (self._clock.now_ns() - self._gap_start_ns) / 1e9
        self._gap_start_ns = None
        counts = self._gap_counts
        counts["gaps"] += 1  # type: ignore[operator]
        counts["last_gap_s"] = gap_s
        counts["gap_s_total"] += gap_s  # type: ignore[operator]
        _log.warning("%s back after %.3f s without data (gap %d; %.3f s in all)", self, gap_s,
                     counts["gaps"], counts["gap_s_total"])

    def _read_reconnecting(self, timeout_s: float) -> Message | list[Message] | None:
        if not self._connected and not self._reconnect(timeout_s):
            return None
        try:
            got = self._read_internal(timeout_s)
        except DriverError as exc:
            self._lose(exc)
            return None
        if got and self._gap_start_ns is not None and self._gap_ends_with(got):
            self._end_gap()
        return got

    def _gap_ends_with(self, got: Message | list[Message]) -> bool:
        """Whether ``got`` (what a read returned during a gap) ends the gap: any message by
        default. A backend with several streams, of which one is the one that matters (the
        ROS 2 base's odometry beside its gyro), says which messages count."""
        return True

    # -- public API ------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        """True once :meth:`close` was called."""
        return self._closed

    def read(self, timeout_s: float) -> list[Message]:
        """The messages that arrived within ``timeout_s`` seconds (>= 0), possibly none.

        Raises :class:`~robotd.base.errors.DriverError` when the driver is closed or the
        device failed (counted in ``errors``, logged once per distinct message), and
        ``ValueError`` for a negative or non-finite timeout.
        """
        if self._closed:
            raise DriverError(f"{self} is closed")
        if not (isinstance(timeout_s, int | float) and math.isfinite(timeout_s)
                and timeout_s >= 0):
            raise ValueError(f"timeout_s must be a finite number >= 0, got {timeout_s}")
        counts = self._base_counts
        counts["reads"] += 1
        try:
            if self._reconnecting:
                got = self._read_reconnecting(timeout_s)
            else:
                got = self._read_internal(timeout_s)
        except DriverError as exc:
            counts["errors"] += 1
            self._log_error(exc)
            raise
        if got is None:
            messages: list[Message] = []
        elif isinstance(got, list):
            messages = got
        else:
            messages = [got]
        if messages:
            counts["messages_out"] += len(messages)
            if _log.isEnabledFor(logging.DEBUG):
                _log.debug("%s: %d messages, last at %d ns", self, len(messages),
                           messages[-1].stamp_ns)
        else:
            counts["empty_reads"] += 1
        return messages

    def _log_error(self, exc: DriverError) -> None:
        text = str(exc)
        if text in self._errors_logged:
            _log.debug("%s: %s (again)", self, text)
            return
        if len(self._errors_logged) < _MAX_DISTINCT_ERRORS_LOGGED:
            self._errors_logged.add(text)
        _log.warning("%s: %s", self, text)

    def stats(self) -> dict[str, StatValue]:
        """Every counter in one flat mapping: ``name``, the base's counters, then the
        backend's (for STATUS lines and JSON)."""
        out: dict[str, StatValue] = {"name": self.name, **self._base_counts}
        if self._reconnecting:
            away_ns = 0 if self._gap_start_ns is None else self._clock.now_ns() - self._gap_start_ns
            out.update(connected=int(self._connected), **self._gap_counts, away_s=away_ns / 1e9)
        out.update(self._stats_internal())
        return out

    def close(self) -> None:
        """Release the device. Safe to call more than once."""
        if self._closed:
            return
        self._closed = True
        if self._reconnecting and self._connected:
            self._connected = False
            self._release_internal()
        self._close_internal()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __str__(self) -> str:
        return f"{self.name} driver"
