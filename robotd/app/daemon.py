"""The daemon: wires drivers, odometry, keyframe selection and the map store together.

Threads: one per source (base serial, floor camera), each reading its driver and putting
samples into its own bounded :class:`SourceQueue`, which counts what it drops. The main
thread runs :meth:`Daemon.run`: it drains the queues into the :class:`Pipeline`, sends
systemd notifications, and handles SIGTERM/SIGINT. This is the only module that knows
both the drivers and the algorithms.

Time comes from an injected clock. Live, frames and samples are dropped when a queue is
full (fresh data matters more than old); replaying or simulating, queues block instead
(``lossless=True``) so a run is the same however fast the CPU is.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import queue
import signal
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import cv2
import numpy as np

from robotd.base.clock import Clock
from robotd.base.config import Config, to_toml
from robotd.base.errors import DriverError
from robotd.base.geometry import between
from robotd.base.messages import Frame, PoseStamped, WheelTicks, YawRate

log = logging.getLogger(__name__)


class SourceQueue:
    """A bounded FIFO between a source thread and the pipeline.

    Live (``lossless=False``) a full queue drops its *oldest* item to make room, so the
    pipeline always sees the freshest data; every drop is counted. Lossless, ``put``
    blocks until there is room or ``stop`` is set.
    """

    def __init__(self, name: str, maxsize: int, lossless: bool, wakeup: threading.Event) -> None:
        self.name = name
        self.lossless = lossless
        self._q: queue.Queue = queue.Queue(maxsize=maxsize)
        self._wakeup = wakeup
        self.put_count = 0
        self.dropped = 0

    def put(self, item: Any, stop: threading.Event) -> bool:
        """Queue ``item``; returns False if ``stop`` was set while waiting (lossless only)."""
        if self.lossless:
            while not stop.is_set():
                try:
                    self._q.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            else:
                return False
        else:
            while True:
                try:
                    self._q.put_nowait(item)
                    break
                except queue.Full:
                    try:
                        self._q.get_nowait()
                        self.dropped += 1
                    except queue.Empty:
                        pass
        self.put_count += 1
        self._wakeup.set()
        return True

    def get_nowait(self) -> Any | None:
        try:
            return self._q.get_nowait()
        except queue.Empty:
            return None

    def qsize(self) -> int:
        return self._q.qsize()


class Source(Protocol):
    """What a source thread reads: a driver with ``read(timeout_s)`` and ``close()``."""

    def read(self, timeout_s: float) -> Any: ...

    def close(self) -> None: ...


class SourceThread(threading.Thread):
    """Reads a driver in a loop and queues what it returns.

    ``read`` may return ``None``, one message, or a list of messages. A
    :class:`~robotd.base.errors.DriverError` is logged and counted; the thread then calls
    ``reopen`` (if given) so a vanished device is retried rather than ending the service.
    """

    def __init__(self, name: str, source: Source, out: SourceQueue, stop: threading.Event,
                 reopen: Callable[[], Source] | None = None, retry_s: float = 1.0) -> None:
        super().__init__(name=f"robotd-{name}", daemon=True)
        self.source = source
        self.out = out
        self.stop = stop
        self.reopen = reopen
        self.retry_s = retry_s
        self.errors = 0
        self.reopens = 0
        self.last_error: str | None = None

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                got = self.source.read(0.1)
            except DriverError as exc:
                self.errors += 1
                self.last_error = str(exc)
                log.warning("%s: %s", self.name, exc)
                if not self._reopen():
                    return
                continue
            if got is None:
                continue
            for item in got if isinstance(got, list) else (got,):
                if not self.out.put(item, self.stop):
                    return

    def _reopen(self) -> bool:
        if self.reopen is None:
            return False
        try:
            self.source.close()
        except Exception:  # closing a broken device must not stop the retry
            log.debug("%s: close failed during reopen", self.name, exc_info=True)
        while not self.stop.wait(self.retry_s):
            try:
                self.source = self.reopen()
                self.reopens += 1
                log.info("%s: reopened", self.name)
                return True
            except DriverError as exc:
                self.errors += 1
                self.last_error = str(exc)
                log.debug("%s: reopen failed: %s", self.name, exc)
        return False


@dataclass
class KeyframeSelector:
    """Chooses keyframes by distance or rotation travelled since the last one."""

    distance_m: float
    rotation_rad: float
    last_pose: np.ndarray | None = None

    def offer(self, pose_xyyaw: np.ndarray) -> bool:
        """True (and remember the pose) when ``pose_xyyaw`` should become a keyframe."""
        if self.last_pose is None:
            self.last_pose = pose_xyyaw.copy()
            return True
        rel = between(self.last_pose, pose_xyyaw)
        if math.hypot(rel[0], rel[1]) >= self.distance_m or abs(rel[2]) >= self.rotation_rad:
            self.last_pose = pose_xyyaw.copy()
            return True
        return False


class PipelineObserver(Protocol):
    """Optional hooks (the demo uses them to write trajectories)."""

    def on_odometry(self, fused: PoseStamped, wheel: PoseStamped) -> None: ...

    def on_keyframe(self, keyframe_id: int, frame: Frame, pose: PoseStamped) -> None: ...

    def on_floor_query(self, query: Any) -> None: ...


@dataclass
class PipelineCounters:
    """What the pipeline has done, for STATUS lines and the demo summary."""

    wheel_msgs: int = 0
    yaw_msgs: int = 0
    frames: int = 0
    keyframes: int = 0
    frames_unsynced: int = 0
    frames_without_odometry: int = 0
    odometry_rejected: int = 0
    floor_queries: int = 0
    floor_candidates: int = 0
    loops_declared: int = 0


class Pipeline:
    """Odometry, frame/pose association, keyframe selection and storage.

    Frames are held until the odometry has reached their timestamp (or
    ``max_sync_wait_s`` of clock time has passed, then dropped and counted), so every
    keyframe pose is interpolated, never extrapolated.
    """

    def __init__(self, config: Config, clock: Clock, odometry: Any, store: Any, run_id: int,
                 observers: list[PipelineObserver] | None = None, floor: Any = None) -> None:
        kf = config.keyframes
        self.config = config
        self.clock = clock
        self.odometry = odometry
        self.store = store
        self.run_id = run_id
        self.observers = list(observers or [])
        self.selector = KeyframeSelector(kf.distance_m, math.radians(kf.rotation_deg))
        self.pending: collections.deque[Frame] = collections.deque()
        self.counters = PipelineCounters()
        self.has_base = config.base.driver != "none"
        self.floor = floor  # a FloorLoopDetector, or None
        self._max_wait_ns = int(kf.max_sync_wait_s * 1e9)

    def on_base(self, msg: WheelTicks | YawRate) -> None:
        if isinstance(msg, WheelTicks):
            self.counters.wheel_msgs += 1
            accepted = self.odometry.on_wheels(msg)
            if accepted is False:
                self.counters.odometry_rejected += 1
                return
            if self.observers:
                fused, wheel = self.odometry.pose(), self.odometry.wheel_pose()
                for o in self.observers:
                    o.on_odometry(fused, wheel)
        elif isinstance(msg, YawRate):
            self.counters.yaw_msgs += 1
            if self.odometry.on_yaw_rate(msg) is False:
                self.counters.odometry_rejected += 1

    def on_frame(self, frame: Frame) -> None:
        self.counters.frames += 1
        self.pending.append(frame)

    def process_pending(self) -> int:
        """Handle every held frame whose pose is now known; returns how many were handled."""
        done = 0
        while self.pending:
            frame = self.pending[0]
            if not self.has_base:
                self.pending.popleft()
                self.counters.frames_without_odometry += 1
                done += 1
                continue
            settled = self.odometry.settled_stamp_ns()
            if settled is None or settled < frame.stamp_ns:
                if self.clock.now_ns() - frame.stamp_ns > self._max_wait_ns:
                    self.pending.popleft()
                    self.counters.frames_unsynced += 1
                    done += 1
                    continue
                break
            self.pending.popleft()
            pose = self.odometry.pose_at(frame.stamp_ns)
            if pose is None:
                self.counters.frames_unsynced += 1
            else:
                self._maybe_keyframe(frame, pose)
            done += 1
        return done

    def finish(self) -> int:
        """End of input: nothing more will arrive, so the newest pose is final as well.

        Held frames stamped up to the newest odometry sample take their pose now; frames
        after it can never have one and are counted in ``frames_unsynced``. Without this a
        run whose clock stops with the input (the virtual robot, a replay) would wait for a
        settled pose forever. Returns how many frames were handled.
        """
        done = 0
        while self.pending:
            frame = self.pending.popleft()
            done += 1
            pose = self.odometry.pose_at(frame.stamp_ns) if self.has_base else None
            if pose is None:
                if self.has_base:
                    self.counters.frames_unsynced += 1
                else:
                    self.counters.frames_without_odometry += 1
            else:
                self._maybe_keyframe(frame, pose)
        return done

    def _maybe_keyframe(self, frame: Frame, pose: PoseStamped) -> None:
        xyyaw = np.array([pose.x_m, pose.y_m, pose.yaw_rad])
        if not self.selector.offer(xyyaw):
            return
        image = downsample(frame.image, self.config.keyframes.image_width_px)
        descriptor = mode = None
        if self.floor is not None:
            descriptor = self.floor.describe(frame.image)
            mode = self.floor.params.mode
        kf_id = self.store.add_keyframe(
            self.run_id, frame.stamp_ns, xyyaw, pose.covariance, image,
            descriptor=descriptor, descriptor_mode=mode,
        )
        self.counters.keyframes += 1
        for o in self.observers:
            o.on_keyframe(kf_id, frame, pose)
        if descriptor is not None:
            query = self.floor.query_and_add(kf_id, frame.stamp_ns, descriptor)
            self.counters.floor_queries += 1
            self.counters.floor_candidates += len(query.candidates)
            for loop in query.loops:
                self.store.add_link("loop", loop.from_id, loop.to_id, loop.delta, loop.information)
                self.counters.loops_declared += 1
            for o in self.observers:
                o.on_floor_query(query)


def downsample(image: np.ndarray, width_px: int) -> np.ndarray | None:
    """Grey image resized to ``width_px`` wide (aspect kept), or None when width is 0."""
    if width_px <= 0:
        return None
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    h, w = grey.shape
    if w <= width_px:
        return grey
    height = max(1, round(h * width_px / w))
    return cv2.resize(grey, (width_px, height), interpolation=cv2.INTER_AREA)


@dataclass
class DaemonReport:
    """Figures of one run (also the payload of STATUS lines)."""

    wall_s: float
    counters: PipelineCounters
    queue_drops: dict[str, int] = field(default_factory=dict)
    source_errors: dict[str, int] = field(default_factory=dict)
    driver_stats: dict[str, Any] = field(default_factory=dict)
    stopped_by: str = ""

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        return d


class Daemon:
    """One run of the service: owns the threads and the main loop.

    ``sources`` maps a name (``"base"``, ``"floor"``) to ``(driver, reopen)``; the driver
    is already open (READY is sent after construction, when the drivers are open).
    """

    def __init__(self, config: Config, clock: Clock, sources: dict[str, tuple[Source, Any]],
                 odometry: Any, store: Any, notifier: Any, *, lossless: bool = False,
                 observers: list[PipelineObserver] | None = None,
                 driver_stats: Callable[[], dict[str, Any]] | None = None,
                 floor: Any = None) -> None:
        self.config = config
        self.clock = clock
        self.store = store
        self.notifier = notifier
        self.stop_event = threading.Event()
        self.wakeup = threading.Event()
        self.run_id = store.begin_run(to_toml(config))
        self.pipeline = Pipeline(config, clock, odometry, store, self.run_id, observers, floor)
        self.driver_stats = driver_stats or (lambda: {})
        self.queues: dict[str, SourceQueue] = {}
        self.threads: dict[str, SourceThread] = {}
        sizes = {"base": config.base.queue_size, "floor": config.floor_camera.queue_size}
        for name, (driver, reopen) in sources.items():
            q = SourceQueue(name, sizes.get(name, 64), lossless, self.wakeup)
            self.queues[name] = q
            self.threads[name] = SourceThread(name, driver, q, self.stop_event, reopen)
        self._stop_reason = ""

    # -- signals -----------------------------------------------------------------------
    def request_stop(self, reason: str) -> None:
        if not self._stop_reason:
            self._stop_reason = reason
        self.stop_event.set()
        self.wakeup.set()

    def _install_signal_handlers(self) -> dict[int, Any]:
        old = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                old[sig] = signal.signal(sig, lambda s, _f: self.request_stop(signal.Signals(s).name))
        return old

    # -- main loop ---------------------------------------------------------------------
    def progress(self) -> int:
        """A counter that grows while the pipeline does work (feeds the watchdog gate)."""
        c = self.pipeline.counters
        return c.wheel_msgs + c.yaw_msgs + c.frames

    def step(self) -> int:
        """Drain the queues into the pipeline once; returns how many items were handled."""
        handled = 0
        base = self.queues.get("base")
        if base is not None:
            while (msg := base.get_nowait()) is not None:
                self.pipeline.on_base(msg)
                handled += 1
        floor = self.queues.get("floor")
        if floor is not None:
            # Take frames only while the pending list is short: the rest wait in the queue,
            # where drops are counted (live) or the producer blocks (lossless).
            while len(self.pipeline.pending) < 4 and (frame := floor.get_nowait()) is not None:
                self.pipeline.on_frame(frame)
                handled += 1
        handled += self.pipeline.process_pending()
        return handled

    def status_text(self, elapsed_s: float) -> str:
        c = self.pipeline.counters
        rate = lambda n: n / elapsed_s if elapsed_s > 0 else 0.0  # noqa: E731
        drops = sum(q.dropped for q in self.queues.values())
        return (f"odometry {rate(c.wheel_msgs):.1f}/s, frames {rate(c.frames):.1f}/s, "
                f"keyframes {c.keyframes}, drops {drops}, unsynced {c.frames_unsynced}")

    def run(self, stop_when: Callable[[], bool] | None = None) -> DaemonReport:
        """Run until SIGTERM/SIGINT, :meth:`request_stop`, or ``stop_when()`` is true."""
        old_handlers = self._install_signal_handlers()
        for t in self.threads.values():
            t.start()
        self.notifier.ready()
        log.info("robotd running (run %d, sources: %s)", self.run_id, ", ".join(self.threads) or "none")
        start = time.monotonic()
        next_status = start + self.config.daemon.status_interval_s
        gate = self.notifier.watchdog_gate()
        try:
            while not self.stop_event.is_set():
                handled = self.step()
                now = time.monotonic()
                gate.tick(self.progress())
                if now >= next_status:
                    text = self.status_text(now - start)
                    self.notifier.status(text)
                    log.info("status: %s", text)
                    next_status = now + self.config.daemon.status_interval_s
                if stop_when is not None and stop_when():
                    self.request_stop("finished")
                    break
                if handled == 0:
                    self.wakeup.wait(0.05)
                    self.wakeup.clear()
        finally:
            self.notifier.stopping()
            self.stop_event.set()
            for t in self.threads.values():
                t.join(timeout=5.0)
            # Whatever was already received is still processed, so nothing read is lost.
            self.step()
            self.pipeline.finish()
            self.store.end_run(self.run_id, self.clock.now_ns())
            for sig, h in old_handlers.items():
                signal.signal(sig, h)
        report = DaemonReport(
            wall_s=time.monotonic() - start,
            counters=self.pipeline.counters,
            queue_drops={n: q.dropped for n, q in self.queues.items()},
            source_errors={n: t.errors for n, t in self.threads.items()},
            driver_stats=self.driver_stats(),
            stopped_by=self._stop_reason or "stop",
        )
        log.info("robotd stopped (%s)", report.stopped_by)
        return report
