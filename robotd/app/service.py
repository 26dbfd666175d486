"""``robotd run``: the daemon on real hardware, as the config says.

Opens the drivers the config names (a missing device is a clear error at start-up, so
systemd's ``Restart=on-failure`` retries), opens the map, sends READY, and runs until
SIGTERM. A device that vanishes while running is reopened by its driver, with backoff,
while the other sources run on; the gap shows in STATUS (:func:`~robotd.app.daemon.gap_text`).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np

from robotd.app.assemble import assemble_daemon, load_calibration, open_map
from robotd.app.signals import StartupSignals, held_signals
from robotd.base.clock import Clock, MonotonicClock
from robotd.base.config import Config, VIRTUAL_SOURCE
from robotd.base.configfile import to_toml
from robotd.base.errors import ConfigError, DriverError
from robotd.base.messages import OdometryUpdate

log = logging.getLogger(__name__)


def open_sources(cfg: Config, clock: Clock) -> dict[str, Any]:
    """Open every driver the config enables, each backend chosen by name through the
    driver registry: source name -> open driver (which reopens its device itself when it
    vanishes)."""
    from drivers.registry import open_driver

    wanted: list[tuple[str, str, str, Any]] = []  # (source, role, backend, config section)
    if cfg.base.driver != "none":
        # The CAN and ROS 2 bases take the whole config: their [can] or [ros2] section and
        # [robot]'s geometry.
        wanted.append(("base", "base", cfg.base.driver, cfg if cfg.base.driver in ("can", "ros2") else cfg.base))
    fc = cfg.floor_camera
    if fc.source == VIRTUAL_SOURCE:  # set by code only (the demo, replay), never read from a file
        raise ConfigError("[floor_camera] source: 'virtual' exists only in `robotd demo`")
    if fc.source != "none":
        wanted.append(("floor", "floor_camera", fc.source, cfg if fc.source == "ros2" else fc))
    fw, fd = cfg.forward_camera, cfg.forward_detector
    if fw.source != "none" and not fd.enabled:
        log.warning("[forward_camera] source = %r but [forward_detector] is off: the forward camera "
                    "is not opened", fw.source)
    elif fw.source != "none":
        section: Any = cfg if fw.source == "ros2" else fw  # a ros2 camera's topic is in [ros2]
        wanted.append(("forward", "forward_camera", fw.source, section))
    sources: dict[str, Any] = {}
    try:
        for source, role, backend, section in wanted:
            sources[source] = open_driver(role, backend, section, clock)
    except BaseException:
        for drv in sources.values():
            drv.close()
        raise
    return sources


class OdometryRecorder:
    """A pipeline observer that records the fused and wheel-only odometry to MCAP.

    Once the writer has failed (its ``error``: the disk is full), the run is stopping on
    that error (raised here the first time, or by a source's recording tee): the odometry
    still handled during the shutdown is not offered to the writer again.
    """

    name = "record_odometry"

    def __init__(self, writer: Any, wheel_topic: str = "/odom/wheel") -> None:
        self.writer = writer
        self.wheel_topic = wheel_topic

    def subscriptions(self) -> dict[type, Callable[[Any], None]]:
        return {OdometryUpdate: self.on_odometry}

    def on_odometry(self, u: OdometryUpdate) -> None:
        if self.writer.error is not None:
            return
        self.writer.write_odometry(u.fused)
        self.writer.write_odometry(u.wheel, self.wheel_topic)


def run_service(cfg: Config, record: Path | None = None, *, config_path: Path | None = None,
                log_level_fixed: bool = False, startup: StartupSignals | None = None) -> int:
    """Run until SIGTERM/SIGINT; returns the process exit status.

    With ``record``, everything the drivers deliver and the odometry are also written to
    that MCAP file (complete once the daemon stops, ``.partial`` until then). With
    ``config_path`` (the file ``cfg`` came from), SIGHUP reloads it
    (:class:`~robotd.app.reload.ConfigReloader`; ``log_level_fixed``: ``--log-level`` was
    given and stays). ``startup``: the CLI's guard of SIGINT/SIGTERM during start-up
    (default: one of its own).
    """
    from robotd.io.maplock import hold_map_lock

    # The map's lock first: a second daemon on the same map is refused before it opens a
    # device, and the first one's run is never touched.
    with held_signals(startup) as early, hold_map_lock(Path(cfg.map.path).absolute()):
        early.stop_if_received()
        return _run_service(cfg, record, config_path, log_level_fixed, early)


def _run_service(cfg: Config, record: Path | None, config_path: Path | None,
                 log_level_fixed: bool, early: StartupSignals) -> int:
    from robotd.app.notify import Notifier

    clock = MonotonicClock()
    notifier = Notifier()
    writer = None
    observers: list[Any] = []
    # The devices and the calibration first: a missing port or camera, or a calibration
    # file that does not read, is reported before any map is created.
    sources = open_sources(cfg, clock)
    try:
        calibration = load_calibration(cfg)
        with open_map(cfg) as store:
            if not sources:
                log.warning("no sources enabled: the daemon will only keep the map open")
            if cfg.forward_detector.enabled and "forward" not in sources:
                log.warning("[forward_detector] is enabled but [forward_camera] source is 'none': "
                            "no forward loops")
            drivers = dict(sources)
            if record is not None:
                from drivers.recording.writer import RecordingTee

                writer = open_recording(cfg, record)
                drivers = {name: RecordingTee(drv, writer) for name, drv in drivers.items()}
                observers.append(OdometryRecorder(writer))
            daemon = assemble_daemon(cfg, clock, drivers, store, notifier, lossless=False,
                                     observers=observers, calibration=calibration,
                                     load_calibration_file=False,
                                     driver_stats=lambda: {n: d.stats() for n, d in drivers.items()})
            if config_path is not None:
                from robotd.app.reload import ConfigReloader

                daemon.on_reload = ConfigReloader(config_path, cfg, calibration,
                                                  log_level_fixed=log_level_fixed)
            early.attach(daemon)
            report = daemon.run()
    finally:
        for drv in sources.values():
            drv.close()
        if writer is not None:
            writer.close()
    log.info("final: %s", report.as_dict())
    return 0


def open_recording(cfg: Config, path: Path) -> Any:
    """A :class:`~drivers.recording.writer.RecordingWriter` for ``path`` as ``[recording]``
    says (frame format and quality), with the floor camera's CameraInfo and mount (for
    ``/tf_static``) from ``[floor_camera]``."""
    from drivers.recording.writer import RecordingWriter
    from robotd.base.camera import FloorCameraModel

    rc = cfg.recording
    writer = RecordingWriter(path, image_format=rc.image_format, jpeg_quality=rc.jpeg_quality,
                             png_compression=rc.png_compression, config_toml=to_toml(cfg))
    model = FloorCameraModel.from_config(cfg.floor_camera)
    writer.add_camera("floor", model.intrinsics, model.rotation_robot_from_camera, model.position_robot_m)
    fw = cfg.forward_camera
    if cfg.forward_detector.enabled:  # a level camera looking along mount_yaw_deg
        from robotd.base.camera import CameraIntrinsics

        c, s = math.cos(math.radians(fw.mount_yaw_deg)), math.sin(math.radians(fw.mount_yaw_deg))
        rot = np.array([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]])  # columns: optical x, y, z
        writer.add_camera("forward", CameraIntrinsics(fw.width_px, fw.height_px, fw.fx_px, fw.fy_px,
                                                      fw.cx_px, fw.cy_px),
                          rot, np.array([fw.mount_x_m, fw.mount_y_m, fw.mount_height_m]))
    return writer


def run_replay(cfg: Config, path: Path, speed: float | None,
               startup: StartupSignals | None = None) -> dict[str, Any]:
    """Feed a recording through the daemon (at ``speed`` x recorded time, or as fast as
    possible when None) and write the map the config names; returns the run's report:
    ``recording_s`` is how much of the recording was replayed (``recording_total_s`` of it
    all), short of it when ``interrupted`` names the signal (SIGINT, SIGTERM) that stopped
    the replay; the map is consistent either way (the run is ended in it).

    As fast as possible, the replay is lossless: every message reaches the pipeline and
    every frame waits for its odometry, so the map is the same on every replay.
    """
    from drivers.recording.replay import ReplayDriver
    from robotd.app.notify import Notifier
    from robotd.base.clock import ManualClock

    from robotd.io.maplock import hold_map_lock

    clock = ManualClock()
    with held_signals(startup) as early, hold_map_lock(Path(cfg.map.path).absolute()), \
            ReplayDriver(path, clock, speed) as replay:
        span = replay.time_range_ns
        if span is None or replay.peek() is None:
            # Checked before the map is opened: a file robotd cannot replay adds no empty run.
            raise DriverError(f"{path}: no message robotd replays (wheel ticks, yaw rates, camera "
                              f"frames); the file holds {replay.describe_contents()}")
        calibration = load_calibration(cfg)
        early.stop_if_received()
        clock.set_ns(span[0])
        with open_map(cfg, clock=clock) as store:
            daemon = assemble_daemon(cfg, clock, {"replay": replay}, store, Notifier(), lossless=True,
                                     calibration=calibration, load_calibration_file=False,
                                     driver_stats=lambda: {"replay": replay.stats()})
            early.attach(daemon)
            report = daemon.run(stop_when=lambda: replay_finished(replay, daemon))
            early.release()  # from here on Ctrl-C interrupts at once (closing the map included)
    c = report.counters
    interrupted = report.stopped_by if report.stopped_by in ("SIGINT", "SIGTERM") else None
    reached_ns = min(clock.now_ns(), span[1]) if interrupted else span[1]
    return {"replayed": dict(replay.counts), "keyframes": c.get("keyframes", 0),
            "frames": c.get("frames", 0), "frames_unsynced": c.get("frames_unsynced", 0),
            "odometry_samples": c.get("wheel_msgs", 0), "damage": replay.damage.as_dict(),
            "wall_s": report.wall_s, "interrupted": interrupted,
            "recording_s": (reached_ns - span[0]) / 1e9,
            "recording_total_s": (span[1] - span[0]) / 1e9}


def replay_finished(replay: Any, daemon: Any) -> bool:
    """True once a replay's last message has gone through the pipeline (frames still
    held for a settled pose are handled by the pipeline's finish)."""
    reading = daemon.threads["replay"].is_alive()  # a replay that failed stops reading
    return (replay.finished or not reading) and daemon.pipeline.inputs >= replay.handed_out
