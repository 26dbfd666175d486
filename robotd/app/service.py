"""``robotd run``: the daemon on real hardware, as the config says.

Opens the drivers the config names (a missing device is a clear error at start-up, so
systemd's ``Restart=on-failure`` retries), opens the map, sends READY, and runs until
SIGTERM. A device that vanishes while running is retried by its source thread.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable

from robotd.app.assemble import assemble_daemon, open_map
from robotd.base.clock import Clock, MonotonicClock
from robotd.base.config import Config, to_toml
from robotd.base.errors import ConfigError
from robotd.base.messages import OdometryUpdate

log = logging.getLogger(__name__)


def open_sources(cfg: Config, clock: Clock) -> dict[str, tuple[Any, Callable[[], Any]]]:
    """Open every driver the config enables: name -> (open driver, function to reopen it)."""
    from drivers.camera import V4L2Camera
    from drivers.kobuki.driver import KobukiDriver

    sources: dict[str, tuple[Any, Callable[[], Any]]] = {}
    if cfg.base.driver == "kobuki":
        b = cfg.base

        def open_base() -> Any:
            return KobukiDriver(b.port, clock=clock, baudrate=b.baudrate, yaw_source=b.yaw_source)

        sources["base"] = (open_base(), open_base)
    fc = cfg.floor_camera
    if fc.source == "virtual":
        raise ConfigError("[floor_camera] source: 'virtual' exists only in `robotd demo`")
    if fc.source == "v4l2":

        def open_floor() -> Any:
            return V4L2Camera(fc.device, width_px=fc.width_px, height_px=fc.height_px, fps=fc.fps,
                              fourcc=fc.fourcc, buffer_size=fc.buffer_size, grey=True,
                              clock=clock, name="floor")

        try:
            sources["floor"] = (open_floor(), open_floor)
        except Exception:
            for drv, _ in sources.values():
                drv.close()
            raise
    return sources


class OdometryRecorder:
    """A pipeline observer that records the fused and wheel-only odometry to MCAP."""

    name = "record_odometry"

    def __init__(self, writer: Any, wheel_topic: str = "/odom/wheel") -> None:
        self.writer = writer
        self.wheel_topic = wheel_topic

    def subscriptions(self) -> dict[type, Callable[[Any], None]]:
        return {OdometryUpdate: self.on_odometry}

    def on_odometry(self, u: OdometryUpdate) -> None:
        self.writer.write_odometry(u.fused)
        self.writer.write_odometry(u.wheel, self.wheel_topic)


def run_service(cfg: Config, record: Path | None = None) -> int:
    """Run until SIGTERM/SIGINT; returns the process exit status.

    With ``record``, everything the drivers deliver and the odometry are also written to
    that MCAP file (complete once the daemon stops, ``.partial`` until then).
    """
    from robotd.app.notify import Notifier

    clock = MonotonicClock()
    notifier = Notifier()
    writer = None
    observers: list[Any] = []
    with open_map(cfg) as store:
        sources = open_sources(cfg, clock)
        try:
            if not sources:
                log.warning("no sources enabled: the daemon will only keep the map open")
            drivers = {name: drv for name, (drv, _) in sources.items()}
            reopen = {name: r for name, (_, r) in sources.items() if r is not None}
            if record is not None:
                from drivers.recording.writer import RecordingTee, RecordingWriter

                writer = RecordingWriter(record, config_toml=to_toml(cfg))
                drivers = {name: RecordingTee(drv, writer) for name, drv in drivers.items()}
                reopen = {name: _tee_reopen(r, writer) for name, r in reopen.items()}
                observers.append(OdometryRecorder(writer))
            daemon = assemble_daemon(cfg, clock, drivers, store, notifier, lossless=False,
                                     observers=observers, reopen=reopen,
                                     driver_stats=lambda: {n: _stats(d) for n, d in drivers.items()})
            report = daemon.run()
        finally:
            for drv, _ in sources.values():
                drv.close()
            if writer is not None:
                writer.close()
    log.info("final: %s", report.as_dict())
    return 0


def _tee_reopen(reopen: Callable[[], Any], writer: Any) -> Callable[[], Any]:
    from drivers.recording.writer import RecordingTee

    return lambda: RecordingTee(reopen(), writer)


def run_replay(cfg: Config, path: Path, speed: float | None) -> dict[str, Any]:
    """Feed a recording through the daemon (at ``speed`` x recorded time, or as fast as
    possible when None) and write the map the config names; returns the run's report.

    As fast as possible, the replay is lossless: every message reaches the pipeline and
    every frame waits for its odometry, so the map is the same on every replay.
    """
    from drivers.recording.reader import RecordingReader
    from drivers.recording.replay import ReplaySource
    from robotd.app.notify import Notifier
    from robotd.base.clock import ManualClock

    span = RecordingReader(path).time_range_ns
    if span is None:
        raise ConfigError(f"{path}: the recording holds no messages")
    clock = ManualClock(span[0])
    replay = ReplaySource(path, clock, speed)
    with replay, open_map(cfg, clock=clock) as store:
        daemon = assemble_daemon(cfg, clock, {"base": replay.base, "floor": replay.floor}, store,
                                 Notifier(), lossless=True)
        replay.start()

        def finished() -> bool:
            if replay.error is not None:
                return True
            # Frames still held for a settled pose are handled by Pipeline.finish at the end.
            return replay.done() and daemon.pipeline.inputs >= replay.base.handed_out + replay.floor.handed_out

        report = daemon.run(stop_when=finished)
    if replay.error is not None:
        raise replay.error
    c = report.counters
    return {"replayed": dict(replay.counts), "keyframes": c.get("keyframes", 0),
            "frames": c.get("frames", 0), "frames_unsynced": c.get("frames_unsynced", 0),
            "odometry_samples": c.get("wheel_msgs", 0),
            "wall_s": report.wall_s, "recording_s": (span[1] - span[0]) / 1e9}


def _stats(driver: Any) -> Any:
    s = getattr(driver, "stats", None)
    return s.as_dict() if hasattr(s, "as_dict") else repr(s)
