"""SIGINT and SIGTERM while a command starts, before the daemon's own handlers exist.

Loading GTSAM, the simulator and the pipeline takes a second or more on a small computer;
a Ctrl-C then used to interrupt an import (``ImportError: initialization failed``) or kill
the process while it was making a run in the map. The CLI holds the signals from its first
line (:func:`robotd.app.cli.main`) until the command's daemon takes them over, or until it
knows the command does not run one. A light module: no numpy, nothing heavy at import.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from typing import Any

log = logging.getLogger(__name__)


class Interrupted(KeyboardInterrupt):
    """A stop signal held during start-up, raised before anything was written: the CLI
    ends with ``128 + signal`` and one line."""

    def __init__(self, signal_name: str) -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name

    @property
    def exit_status(self) -> int:
        return 128 + signal.Signals[self.signal_name].value


class StartupSignals:
    """SIGTERM/SIGINT that arrive while ``robotd run`` starts (opening the devices and
    the map, assembling the pipeline), before the daemon's own handlers exist.

    Without it such a signal killed the process outright (Python's default action), in
    the middle of making a run in the map; now it is held and handed to the daemon,
    which then starts, stops at once and ends the run cleanly. A context manager: the
    previous handlers come back on exit. Like the daemon's handler, this one only
    assigns attributes (see :meth:`robotd.app.daemon.Daemon._on_signal`).
    """

    def __init__(self) -> None:
        self.received = ""
        self._daemon: Any = None
        self._old: dict[int, Any] = {}

    def __enter__(self) -> StartupSignals:
        if threading.current_thread() is threading.main_thread():
            # SIGINT first: Python catches it from the start (KeyboardInterrupt), so a
            # caught SIGTERM (/proc's SigCgt, what a supervisor or a test can see) must
            # mean that both are held.
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def release(self) -> None:
        """Give the signals back to their previous handlers (once the daemon has stopped,
        a Ctrl-C must interrupt what follows, not be held for a daemon that is gone)."""
        old, self._old = self._old, {}
        for sig, handler in old.items():
            signal.signal(sig, handler)

    def _handler(self, signum: int, _frame: Any) -> None:
        name = signal.Signals(signum).name
        if self._daemon is not None:
            self._daemon.signalled(name)
        elif not self.received:
            self.received = name

    def stop_if_received(self) -> None:
        """:class:`Interrupted` if a signal arrived already: called before anything is
        written, so that a Ctrl-C during start-up leaves the outputs as they were."""
        if self.received and self._daemon is None:
            raise Interrupted(self.received)

    def attach(self, daemon: Any) -> None:
        """From now on signals go to ``daemon``, and one held already is handed over."""
        self._daemon = daemon
        if self.received:
            log.info("%s during start-up: stopping once the run is open", self.received)
            daemon.signalled(self.received)


@contextlib.contextmanager
def held_signals(startup: StartupSignals | None) -> Iterator[StartupSignals]:
    """``startup`` (the CLI's guard, still holding) as it is, or a new guard for the
    ``with`` block when the caller has none (a test, a benchmark)."""
    if startup is not None:
        yield startup
        return
    with StartupSignals() as own:
        yield own
