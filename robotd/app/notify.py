"""systemd service notifications (``sd_notify(3)``) and a progress-gated watchdog.

Under ``Type=notify`` systemd passes ``NOTIFY_SOCKET`` (an ``AF_UNIX`` datagram socket,
a path or ``@abstract``); with ``WatchdogSec=`` it also passes ``WATCHDOG_USEC`` and
``WATCHDOG_PID``. Outside systemd (tests, a terminal) ``NOTIFY_SOCKET`` is unset and every
notification is a no-op, so the daemon never has to ask where it runs.

The watchdog is only useful if it proves the pipeline works: a timer thread that pings
unconditionally would keep a wedged daemon alive forever. :class:`WatchdogGate` therefore
pings only when a progress counter moved since the previous ping; when the pipeline
stalls, the pings stop and systemd restarts the service (``Restart=on-failure``).
"""

from __future__ import annotations

import logging
import os
import time

import systemd.daemon as daemon

from robotd.base.clock import Clock, MonotonicClock

__all__ = ["Notifier", "WatchdogGate"]

_log = logging.getLogger(__name__)


class Notifier:
    """Sends state changes to systemd over ``NOTIFY_SOCKET``.

    The environment is read once, at construction: ``NOTIFY_SOCKET`` decides
    :attr:`enabled`, ``WATCHDOG_USEC``/``WATCHDOG_PID`` the watchdog timeout. Each method
    returns True if the message was sent and False if notification is disabled or the
    send failed; a failure is logged, never raised, because losing a status line must not
    stop the robot (a lost READY or WATCHDOG makes systemd act, which is what we want).
    """

    def __init__(self) -> None:
        self._socket = os.environ.get("NOTIFY_SOCKET", "")
        self._watchdog_timeout_ns = _parse_watchdog(
            os.environ.get("WATCHDOG_USEC"), os.environ.get("WATCHDOG_PID"), os.getpid()
        )
        if self._socket:
            _log.debug("systemd notification socket %s", self._socket)

    @property
    def enabled(self) -> bool:
        """True when running under systemd with a notification socket."""
        return bool(self._socket)

    def watchdog_timeout_ns(self) -> int | None:
        """The service's watchdog timeout (``WatchdogSec=``) in ns, None when there is
        no watchdog for this process.

        Follows ``sd_watchdog_enabled(3)``: ``WATCHDOG_USEC`` must be a positive integer,
        and if ``WATCHDOG_PID`` is set it must be this process's pid (the variables may be
        inherited by a child that is not the service's main process).
        """
        return self._watchdog_timeout_ns

    def watchdog_interval_ns(self) -> int | None:
        """How often to send ``WATCHDOG=1``: half the timeout, as ``sd_watchdog_enabled(3)``
        recommends, so one late ping is not fatal. None when there is no watchdog."""
        timeout_ns = self._watchdog_timeout_ns
        return None if timeout_ns is None else timeout_ns // 2

    def watchdog_gate(self, clock: Clock | None = None) -> WatchdogGate:
        """A :class:`WatchdogGate` at this service's interval (disabled without a
        watchdog). ``clock`` defaults to the host monotonic clock, which is right even
        when the pipeline runs on simulated time: systemd's watchdog counts real time."""
        return WatchdogGate(self, MonotonicClock() if clock is None else clock)

    def ready(self, status: str | None = None) -> bool:
        """``READY=1``: start-up finished (with ``Type=notify`` systemd waits for this);
        with ``status``, the status line goes in the same datagram."""
        message = "READY=1"
        if status is not None:
            message += "\nSTATUS=" + _one_line(status)
        return self._send(message)

    def status(self, text: str) -> bool:
        """``STATUS=text``: the line ``systemctl status robotd`` shows (newlines become
        spaces, since the protocol separates assignments by newline)."""
        return self._send("STATUS=" + _one_line(text))

    def watchdog(self) -> bool:
        """``WATCHDOG=1``: keep-alive ping. Prefer :class:`WatchdogGate`, which pings only
        when the pipeline made progress."""
        return self._send("WATCHDOG=1")

    def reloading(self) -> bool:
        """``RELOADING=1``: the configuration is being reloaded (SIGHUP); send
        :meth:`ready` when done. ``MONOTONIC_USEC`` (CLOCK_MONOTONIC now) goes with it, as
        ``sd_notify(3)`` asks since systemd 253 (``Type=notify-reload``)."""
        now_us = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        return self._send(f"RELOADING=1\nMONOTONIC_USEC={now_us}")

    def stopping(self) -> bool:
        """``STOPPING=1``: shutdown has begun."""
        return self._send("STOPPING=1")

    def extend_timeout(self, timeout_ns: int) -> bool:
        """``EXTEND_TIMEOUT_USEC``: ask for ``timeout_ns`` more before the start (or stop)
        timeout fires, e.g. while checking a large map file at start-up."""
        if timeout_ns <= 0:
            raise ValueError(f"timeout_ns must be > 0, got {timeout_ns}")
        return self._send(f"EXTEND_TIMEOUT_USEC={-(-int(timeout_ns) // 1000)}")

    def _send(self, message: str) -> bool:
        if not self._socket:
            return False
        try:
            return bool(daemon.notify(message))
        except OSError as exc:
            _log.warning("sd_notify(%r) to %s failed: %s", message, self._socket, exc)
            return False


class WatchdogGate:
    """Sends ``WATCHDOG=1`` at most once per interval, and only after progress.

    The daemon calls :meth:`tick` from its main loop with a counter that grows whenever
    the pipeline does useful work (samples fused, frames processed). If the counter has
    not changed since the previous ping, the ping is withheld; once the stall outlasts
    ``WatchdogSec=``, systemd kills and restarts the service.

    ``clock`` is the daemon's injected clock; ``interval_ns`` defaults to
    ``notifier.watchdog_interval_ns()`` (None disables the gate: :meth:`tick` then only
    tracks progress).
    """

    def __init__(
        self,
        notifier: Notifier,
        clock: Clock,
        interval_ns: int | None = None,
        *,
        progress: int = 0,
    ) -> None:
        self._notifier = notifier
        self._clock = clock
        self._interval_ns = notifier.watchdog_interval_ns() if interval_ns is None else interval_ns
        if self._interval_ns is not None and self._interval_ns <= 0:
            raise ValueError(f"interval_ns must be > 0, got {self._interval_ns}")
        now_ns = clock.now_ns()
        self._last_ping_ns = now_ns
        self._last_progress = progress
        self._last_progress_ns = now_ns
        self._progress_since_ping = False
        self._withheld_logged = False
        self.pings = 0
        """WATCHDOG=1 messages sent so far."""

    @property
    def enabled(self) -> bool:
        """True when there is a watchdog interval to keep."""
        return self._interval_ns is not None

    @property
    def interval_ns(self) -> int | None:
        """Minimum time between two pings, ns."""
        return self._interval_ns

    def stalled_ns(self) -> int:
        """Time since the progress counter last changed, ns."""
        return self._clock.now_ns() - self._last_progress_ns

    def tick(self, progress: int) -> bool:
        """Record ``progress``; ping if an interval has passed since the last ping and
        the counter changed meanwhile. Returns True if a ping was sent."""
        now_ns = self._clock.now_ns()
        if progress != self._last_progress:
            self._last_progress = progress
            self._last_progress_ns = now_ns
            self._progress_since_ping = True
        if self._interval_ns is None or now_ns - self._last_ping_ns < self._interval_ns:
            return False
        if not self._progress_since_ping:
            if not self._withheld_logged:
                _log.warning(
                    "no pipeline progress for %.1f s: withholding the watchdog ping, so"
                    " systemd restarts robotd if this lasts",
                    (now_ns - self._last_progress_ns) / 1e9,
                )
                self._withheld_logged = True
            return False
        if self._withheld_logged:
            _log.info("pipeline progressing again; watchdog pings resumed")
            self._withheld_logged = False
        self._last_ping_ns = now_ns
        self._progress_since_ping = False
        sent = self._notifier.watchdog()
        self.pings += int(sent)
        return sent


def _one_line(text: str) -> str:
    return " ".join(str(text).splitlines())


def _parse_watchdog(usec: str | None, pid: str | None, own_pid: int) -> int | None:
    """``sd_watchdog_enabled(3)`` on the given variable values; timeout in ns or None."""
    if usec is None:
        return None
    try:
        timeout_us = int(usec)
    except ValueError:
        timeout_us = 0
    if timeout_us <= 0:
        _log.warning("ignoring invalid WATCHDOG_USEC=%r", usec)
        return None
    if pid is not None:
        try:
            target_pid = int(pid)
        except ValueError:
            _log.warning("ignoring the watchdog: invalid WATCHDOG_PID=%r", pid)
            return None
        if target_pid != own_pid:
            return None  # meant for another process (we inherited the environment)
    return timeout_us * 1000
