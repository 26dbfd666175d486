"""The daemon: source threads, their queues, the main loop, signals and the watchdog.

Threads: one per registered source (the base, the floor camera, a replay, ...), each
reading its driver and putting what it reads into its own bounded queue
(:class:`~robotd.base.queues.BoundedQueue`), which counts what it drops. The main thread
runs :meth:`Daemon.run`: it drains every queue into the :class:`~robotd.app.pipeline.Pipeline`,
which routes each message to the stages that consume it, sends systemd notifications, and
handles SIGTERM/SIGINT (stop) and, when the service gave it a reloader, SIGHUP (reload the
config between two turns of the loop: :attr:`Daemon.on_reload`). The daemon knows nothing
of what the messages are: a new source is a new entry in ``sources``, a new consumer a new
pipeline stage.

Time comes from an injected clock. Live, messages are dropped when a queue is full (fresh
data matters more than old); replaying or simulating, queues block instead
(``lossless=True``) so a run is the same however fast the CPU is.
"""

from __future__ import annotations

import dataclasses
import logging
import signal
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

from robotd.app.pipeline import Pipeline
from robotd.base.clock import Clock, MonotonicClock
from robotd.base.errors import RobotdError
from robotd.base.queues import BoundedQueue

log = logging.getLogger(__name__)

SILENT_AFTER_S = 5.0
"""A source that has sent nothing this long after the start is named in STATUS (and logged
once): the sign of a wrong port, topic or device, or of a base that is switched off."""

_STATUS_FAULTS = ("frames", "unknown_frames", "decode_errors", "error_frames", "bus_off",
                  "bus_errors", "flood_reads", "bus_silent", "stale_left", "stale_right")
"""Driver counters shown in STATUS beside a driver's ``status`` (those that are not 0)."""

_BATCH = 256  # items taken from one queue per turn, so no source starves the others


class Source(Protocol):
    """What a source thread reads: a driver with ``read(timeout_s)`` and ``close()``."""

    def read(self, timeout_s: float) -> Any: ...

    def close(self) -> None: ...


class SourceThread(threading.Thread):
    """Reads a driver in a loop and queues what it returns.

    ``read`` may return ``None``, one message, or a list of messages. The driver owns
    reconnection (:mod:`drivers.base`): one that lost its device returns nothing until it
    has reopened it. So any exception out of ``read`` (a
    :class:`~robotd.base.errors.DriverError` from a driver that cannot go on, a recording
    that cannot be written, a bug) ends the thread and is handed to ``on_fatal``, so the
    daemon stops (and systemd restarts it) instead of running on without the source.
    """

    def __init__(self, name: str, source: Source, out: BoundedQueue[Any], stop: threading.Event,
                 on_fatal: Callable[[str, Exception], None] | None = None) -> None:
        super().__init__(name=f"robotd-{name}", daemon=True)
        self.source_name = name
        self.source = source
        self.out = out
        self.stop = stop
        self.on_fatal = on_fatal
        self.errors = 0
        self.last_error: str | None = None
        self.fatal: Exception | None = None

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                got = self.source.read(0.1)
            except Exception as exc:
                self.errors += 1
                self.last_error = str(exc)
                self.fatal = exc
                if isinstance(exc, RobotdError):  # a known error: the caller reports it
                    log.info("%s: %s; the daemon stops", self.name, exc)
                else:
                    log.exception("%s: unexpected error; the daemon stops", self.name)
                if self.on_fatal is not None:
                    self.on_fatal(self.source_name, exc)
                return
            if got is None:
                continue
            if not (self.out.put_many(got, self.stop) if isinstance(got, list) else self.out.put(got, self.stop)):
                return


def _driver_status(stats: Mapping[str, Any]) -> str:
    """``; name: status ...`` for each driver whose stats carry a ``status`` line (the CAN
    base: its health and fault counters), so they reach STATUS."""
    parts = []
    for name, st in stats.items():
        if not isinstance(st, dict) or "status" not in st:
            continue
        faults = ", ".join(f"{k} {st[k]}" for k in _STATUS_FAULTS if st.get(k))
        parts.append(f"; {name}: {st['status']}" + (f" ({faults})" if faults else ""))
    return "".join(parts)


def gap_text(driver_stats: Mapping[str, Mapping[str, Any]]) -> str:
    """The STATUS fragment of sources that lost their device, ``""`` when none did.

    For each source whose driver counted a loss (:mod:`drivers.base`'s ``losses``):
    ``"floor away 2.1 s"`` while its device is still missing, then the gaps that ended,
    ``"floor gaps 1 (3.400 s, last 3.400 s)"``, e.g.
    ``"floor away 0.5 s, gaps 2 (7.100 s, last 4.000 s)"``.
    """
    parts = []
    for name, st in driver_stats.items():
        if not st.get("losses"):
            continue
        bits = []
        if st.get("away_s"):
            bits.append(f"away {float(st['away_s']):.1f} s")
        if st.get("gaps"):
            bits.append(f"gaps {st['gaps']} ({float(st['gap_s_total']):.3f} s, "
                        f"last {float(st['last_gap_s']):.3f} s)")
        if bits:
            parts.append(f"{name} " + ", ".join(bits))
    return "; ".join(parts)


@dataclass
class DaemonReport:
    """Figures of one run (also the payload of STATUS lines)."""

    wall_s: float
    counters: dict[str, int]
    queue_drops: dict[str, int] = field(default_factory=dict)
    source_errors: dict[str, int] = field(default_factory=dict)
    driver_stats: dict[str, Any] = field(default_factory=dict)
    stopped_by: str = ""

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


class Daemon:
    """One run of the service: owns the source threads and the main loop.

    ``sources`` maps a name to an open driver (``read(timeout_s)``, ``close()``; a driver
    that loses its device reopens it itself); ``queue_sizes`` maps names to their
    queue's capacity (default 64). ``driver_stats`` returns each driver's
    :meth:`~drivers.base.Driver.stats`, for the report and for the STATUS line, which
    names every source that lost its device (see :func:`gap_text`).
    READY is sent when :meth:`run` starts, the drivers being open by then. The caller
    owns the drivers (closes them) and the store; :meth:`run` ends the run in the store.
    """

    def __init__(self, clock: Clock, pipeline: Pipeline, sources: dict[str, Source],
                 notifier: Any, *, store: Any = None, run_id: int | None = None,
                 lossless: bool = False, status_interval_s: float = 5.0,
                 queue_sizes: dict[str, int] | None = None,
                 driver_stats: Callable[[], dict[str, Any]] | None = None,
                 wall_clock: Clock | None = None) -> None:
        self.clock = clock
        # Status lines and the watchdog run on real time even when ``clock`` is a replay's
        # or the virtual robot's (which stops with the input); tests inject a manual one.
        self.wall_clock = wall_clock if wall_clock is not None else MonotonicClock()
        self.pipeline = pipeline
        self.store = store
        self.run_id = run_id
        self.notifier = notifier
        self.status_interval_s = status_interval_s
        self.stop_event = threading.Event()
        self.wakeup = threading.Event()
        self.driver_stats = driver_stats or (lambda: {})
        self.queues: dict[str, BoundedQueue[Any]] = {}
        self.threads: dict[str, SourceThread] = {}
        sizes = queue_sizes or {}
        for name, driver in sources.items():
            q: BoundedQueue[Any] = BoundedQueue(sizes.get(name, 64), lossless=lossless, drop="oldest",
                                           wakeup=self.wakeup, name=name)
            self.queues[name] = q
            self.threads[name] = SourceThread(name, driver, q, self.stop_event,
                                              on_fatal=self._source_failed)
        self._stop_reason = ""
        self._warned_silent: set[str] = set()
        self._fatal: Exception | None = None
        self.on_reload: Callable[[Daemon], None] | None = None
        """Called from the main loop after SIGHUP (set before :meth:`run`); without it
        SIGHUP keeps its default action."""
        self._reload_pending = False
        self._signalled = ""  # set by the signal handler only; see _on_signal
        self.reloads = 0
        self._turns = 0
        self._old_handlers: dict[int, Any] = {}
        self._start_ns = self.wall_clock.now_ns()
        self._next_status_ns = self._start_ns
        self._gate: Any = None

    # -- signals -----------------------------------------------------------------------
    def request_stop(self, reason: str) -> None:
        if not self._stop_reason:
            self._stop_reason = reason
        self.stop_event.set()
        self.wakeup.set()

    def request_reload(self) -> None:
        """Ask the main loop to call :attr:`on_reload` at its next turn (SIGHUP)."""
        self._reload_pending = True

    def signalled(self, name: str) -> None:
        """A stop signal (``"SIGTERM"``, ``"SIGINT"``) arrived: the main loop stops within
        one turn. Safe to call from a signal handler, as :meth:`request_stop` is not."""
        if not self._signalled:
            self._signalled = name

    def _on_signal(self, signum: int, _frame: Any) -> None:
        """The SIGTERM/SIGINT/SIGHUP handler.

        Python runs it in the main thread between two bytecodes, which may be inside
        ``threading.Event.wait()``/``clear()`` of :attr:`wakeup` while that thread holds
        the Event's (non-reentrant) lock. So it only assigns attributes, which the main
        loop reads at least every 50 ms. The former handler called :meth:`request_stop`,
        which sets the Events: a signal landing in that window deadlocked the main thread
        for good (SIGTERM taken, STOPPING=1 never sent, later SIGTERMs ignored: the flaky
        service test).
        """
        if signum == signal.SIGHUP:
            self.request_reload()
        else:
            self.signalled(signal.Signals(signum).name)

    def stopping_requested(self) -> bool:
        """True once a stop was requested or signalled (main thread)."""
        if self._signalled and not self.stop_event.is_set():
            self.request_stop(self._signalled)
        return self.stop_event.is_set()

    def set_status_interval(self, interval_s: float) -> None:
        """Send STATUS every ``interval_s`` from now on (a reloaded config)."""
        self.status_interval_s = interval_s
        self._next_status_ns = min(self._next_status_ns,
                                   self.wall_clock.now_ns() + int(interval_s * 1e9))

    def _reload(self) -> None:
        """SIGHUP: RELOADING=1, the reloader, READY=1. A failing reloader is logged and
        the daemon runs on with what it had: a reload must never stop the robot."""
        self._reload_pending = False
        if self.on_reload is None:
            return
        self.notifier.reloading()
        try:
            self.on_reload(self)
            self.reloads += 1
        except Exception:
            log.exception("reload failed; running on with the previous configuration")
        finally:
            self.notifier.ready()

    def _source_failed(self, name: str, exc: Exception) -> None:
        """A source thread ended on an error its driver cannot mend: stop, and let
        :meth:`run` raise it once the run is closed."""
        if self._fatal is None:
            self._fatal = exc
        self.request_stop(f"{name} failed: {exc}")

    def _install_signal_handlers(self) -> dict[int, Any]:
        old: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                old[sig] = signal.signal(sig, self._on_signal)
            if self.on_reload is not None:
                old[signal.SIGHUP] = signal.signal(signal.SIGHUP, self._on_signal)
        return old

    # -- main loop ---------------------------------------------------------------------
    def progress(self) -> int:
        """A counter that grows while the pipeline does work (feeds the watchdog gate).

        Without sources there is no input to wait for: the main loop turning is then the
        progress, or the watchdog would restart a daemon that only keeps its map open."""
        return self.pipeline.inputs if self.threads else self._turns

    def step(self) -> int:
        """Drain the queues into the pipeline once; returns how many items were handled."""
        handled = 0
        feed = self.pipeline.feed
        for q in self.queues.values():
            items = q.take(_BATCH)  # what is waiting now, in one taking of the queue's lock
            for item in items:
                feed(item)
            handled += len(items)
        handled += self.pipeline.poll()
        return handled

    def status_text(self, elapsed_s: float) -> str:
        """The STATUS line. ``stored N`` acknowledges that this run's first N keyframes are
        committed to the map (the map stage counts a keyframe only after its transaction
        committed), so they survive a kill at any later moment."""
        c = self.pipeline.counters()

        def rate(n: int) -> float:
            return n / elapsed_s if elapsed_s > 0 else 0.0

        drops = sum(q.dropped for q in self.queues.values())
        wheel, frames = c.get("wheel_msgs", 0), c.get("frames", 0)
        text = (f"odometry {rate(wheel):.1f}/s ({wheel}), frames {rate(frames):.1f}/s ({frames}), "
                f"keyframes {c.get('keyframes', 0)}, stored {c.get('keyframes_stored', 0)}, "
                f"loops {c.get('links_loop', 0)}, drops {drops}, "
                f"unsynced {c.get('frames_unsynced', 0)}")
        if "localise_matches_accepted" in c:  # [pose_graph] localise_mapped
            text += (f", mapped ground: {c['keyframes_not_stored']} keyframes not stored, "
                     f"{c.get('localise_matches_accepted', 0)} map matches")
        stats = self._safe_driver_stats()
        gaps = gap_text(stats)
        if gaps:
            text += f", {gaps}"
        silent = self._silent_sources(elapsed_s)
        if silent:
            text += ", " + ", ".join(f"{name} silent (nothing in {elapsed_s:.0f} s)" for name in silent)
        if c.get("odometry_degraded"):
            odo = self.pipeline.stage("odometry")
            text += f", odometry DEGRADED ({getattr(odo, 'degraded_detail', '')})"
        for stage in self.pipeline.stages:  # e.g. the pose graph: "not localised in the stored map"
            fragment = stage.status_fragment() if hasattr(stage, "status_fragment") else ""
            if fragment:
                text += f", {fragment}"
        return text + _driver_status(stats)

    def _silent_sources(self, elapsed_s: float) -> list[str]:
        """The sources that have not sent one message in the run's first ``elapsed_s``
        seconds, once that is :data:`SILENT_AFTER_S` or more; each is logged as a warning
        the first time."""
        if elapsed_s < SILENT_AFTER_S:
            return []
        silent = [name for name, q in self.queues.items() if q.put_count == 0]
        for name in silent:
            if name not in self._warned_silent:
                self._warned_silent.add(name)
                log.warning("%s: no message in the first %.0f s of the run (is the device on, and "
                            "the port, device or topic in the config the right one?)", name, elapsed_s)
        return silent

    def _safe_driver_stats(self) -> dict[str, Any]:
        """The drivers' stats, once per STATUS line ({} when they fail: STATUS must never
        stop the daemon)."""
        try:
            return self.driver_stats()
        except Exception:
            log.debug("driver stats failed", exc_info=True)
            return {}

    def start(self) -> None:
        """Start the source threads and tell systemd the service is ready."""
        self._old_handlers = self._install_signal_handlers()
        for t in self.threads.values():
            t.start()
        self.notifier.ready()
        log.info("robotd running (run %s, sources: %s, stages: %s)", self.run_id,
                 ", ".join(self.threads) or "none", ", ".join(s.name for s in self.pipeline.stages))
        self._start_ns = self.wall_clock.now_ns()
        self._next_status_ns = self._start_ns + int(self.status_interval_s * 1e9)
        self._gate = self.notifier.watchdog_gate(self.wall_clock)

    def turn(self) -> int:
        """One turn of the main loop: drain the queues into the pipeline, feed the watchdog
        if the pipeline made progress, send STATUS when due; first, after SIGHUP, reload.
        Returns items handled."""
        if self._reload_pending:
            self._reload()
        self._turns += 1
        handled = self.step()
        now_ns = self.wall_clock.now_ns()
        self._gate.tick(self.progress())
        if now_ns >= self._next_status_ns:
            text = self.status_text((now_ns - self._start_ns) / 1e9)
            self.notifier.status(text)
            log.info("status: %s", text)
            self._next_status_ns = now_ns + int(self.status_interval_s * 1e9)
        return handled

    def shutdown(self) -> None:
        """Stop the threads, handle whatever was already received (nothing read is lost),
        finish the pipeline and end the run in the map."""
        self.notifier.stopping()
        self.stop_event.set()
        for t in self.threads.values():
            t.join(timeout=5.0)
        while self.step():
            pass
        self.pipeline.finish()
        if self.store is not None and self.run_id is not None:
            self.store.end_run(self.run_id, self.clock.now_ns())
        for sig, h in self._old_handlers.items():
            signal.signal(sig, h)
        log.info("robotd stopped (%s)", self._stop_reason or "stop")

    def run(self, stop_when: Callable[[], bool] | None = None) -> DaemonReport:
        """Run until SIGTERM/SIGINT, :meth:`request_stop`, or ``stop_when()`` is true.

        A source whose driver failed for good (see :class:`SourceThread`) stops the run;
        its exception is raised here after the shutdown, which still handles what was
        read and ends the run in the map.
        """
        self.start()
        try:
            while not self.stopping_requested():
                handled = self.turn()
                if stop_when is not None and stop_when():
                    self.request_stop("finished")
                    break
                if handled == 0:
                    self.wakeup.wait(0.05)
                    self.wakeup.clear()
        finally:
            self.shutdown()
        if self._fatal is not None:
            raise self._fatal
        return self.report()

    def report(self) -> DaemonReport:
        """The figures of the run so far."""
        report = DaemonReport(
            wall_s=(self.wall_clock.now_ns() - self._start_ns) / 1e9,
            counters=self.pipeline.counters(),
            queue_drops={n: q.dropped for n, q in self.queues.items()},
            source_errors={n: t.errors for n, t in self.threads.items()},
            driver_stats=self.driver_stats(),
            stopped_by=self._stop_reason or "stop",
        )
        return report
