"""The base class of every source: what a daemon thread reads, in python-can's style.

The public :meth:`Driver.read` does what every source needs (the closed check, timeout
validation, normalising what the backend returns to a list, counting, logging); a
backend implements only ``_read_internal(timeout_s)``, ``_close_internal()`` and,
optionally, ``_stats_internal()``, like python-can's ``BusABC.recv`` over
``_recv_internal``. Every driver is a context manager and :meth:`Driver.close` is safe
to call twice.
"""

from __future__ import annotations

import logging
import math
from types import TracebackType
from typing import Self

from robotd.base.errors import DriverError
from robotd.base.messages import BaseStatus, Frame, WheelTicks, YawRate

__all__ = ["Driver", "Message", "StatValue"]

_log = logging.getLogger(__name__)

Message = WheelTicks | YawRate | Frame | BaseStatus
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
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._closed = False
        self._base_counts = {"reads": 0, "messages_out": 0, "empty_reads": 0, "errors": 0}
        self._errors_logged: set[str] = set()

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
        out.update(self._stats_internal())
        return out

    def close(self) -> None:
        """Release the device. Safe to call more than once."""
        if self._closed:
            return
        self._closed = True
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
