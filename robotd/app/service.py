"""``robotd run``: the daemon on real hardware, as the config says.

Opens the drivers the config names (a missing device is a clear error at start-up, so
systemd's ``Restart=on-failure`` retries), opens the map, sends READY, and runs until
SIGTERM. A device that vanishes while running is retried by its source thread.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable

from robotd.base.clock import Clock, MonotonicClock
from robotd.base.config import Config, to_toml
from robotd.base.errors import ConfigError

log = logging.getLogger(__name__)


def build_odometry(cfg: Config) -> Any:
    """The wheel + gyro filter with the config's robot geometry and noise model."""
    from robotd.odometry.ekf import EkfParams, OdometryFilter
    from robotd.odometry.kinematics import DiffDriveParams

    o = cfg.odometry
    params = EkfParams(
        accel_noise_mps2=o.accel_noise_mps2,
        angular_accel_noise_radps2=o.angular_accel_noise_radps2,
        gyro_bias_walk_radps_sqrt_s=o.gyro_bias_walk_radps_sqrt_s,
        wheel_v_noise_mps=o.wheel_v_noise_mps,
        wheel_v_noise_frac=o.wheel_v_noise_frac,
        wheel_w_noise_radps=o.wheel_w_noise_radps,
        wheel_w_noise_frac=o.wheel_w_noise_frac,
        wheel_w_noise_per_mps=o.wheel_w_noise_per_mps,
        gyro_noise_radps=o.gyro_noise_radps,
        initial_gyro_bias_sigma_radps=o.initial_gyro_bias_sigma_radps,
    )
    drive = DiffDriveParams(wheel_radius_m=cfg.robot.wheel_radius_m,
                            wheel_base_m=cfg.robot.wheel_base_m,
                            ticks_per_rev=cfg.robot.ticks_per_rev)
    return OdometryFilter(drive, params)


def load_calibration(cfg: Config) -> Any:
    """The calibration file the config names, or None (logged clearly) when there is none.

    A file that exists but is damaged is an error: the daemon must not run on a
    half-read calibration.
    """
    from robotd.io.calibfile import read_calibration

    path = Path(cfg.calibration.path)
    if not path.exists():
        log.warning("no calibration file at %s: using the [floor_camera] values of the config, "
                    "and no floor loops will be declared (see `robotd calibrate`)", path)
        return None
    calib = read_calibration(path)
    log.info("calibration loaded from %s", path)
    return calib


def build_floor_detector(cfg: Config, store: Any, calib: Any = None) -> Any:
    """The floor loop detector with its index rebuilt from the map, or None if disabled.

    Loops are declared only with a trained threshold for the configured mode.
    """
    if not cfg.floor_detector.enabled or cfg.floor_camera.source == "none":
        return None
    from robotd.io.calibfile import camera_model
    from robotd.floor.detector import FloorDetectorParams, FloorLoopDetector

    f = cfg.floor_detector
    params = FloorDetectorParams(mode=f.mode, candidates=f.candidates, shortlist=f.shortlist,
                                 exclude_recent_s=f.exclude_recent_s)
    threshold = calib.loop.for_mode(f.mode) if calib is not None and calib.loop is not None else None
    if threshold is None:
        log.warning("no trained loop threshold for descriptor mode %d: floor loop candidates are "
                    "found and stored but no loop is declared (train with `robotd calibrate "
                    "loop-curve`)", f.mode)
    else:
        log.info("floor loops declared at local score >= %.2f (mode %d)", threshold, f.mode)
    return FloorLoopDetector.from_store(store, params, threshold, camera_model(calib, cfg.floor_camera))


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


def run_service(cfg: Config, record: Path | None = None) -> int:
    """Run until SIGTERM/SIGINT; returns the process exit status.

    With ``record``, everything the drivers deliver and the odometry are also written to
    that MCAP file (complete once the daemon stops, ``.partial`` until then).
    """
    from robotd.app.daemon import Daemon
    from robotd.app.notify import Notifier
    from robotd.io.store import MapStore

    clock = MonotonicClock()
    notifier = Notifier()
    writer = None
    observers: list[Any] = []
    with MapStore.open(cfg.map.path) as store:
        sources = open_sources(cfg, clock)
        try:
            if not sources:
                log.warning("no sources enabled: the daemon will only keep the map open")
            if record is not None:
                from drivers.recording.writer import OdometryRecorder, RecordingTee, RecordingWriter

                writer = RecordingWriter(record, config_toml=to_toml(cfg))
                sources = {name: (RecordingTee(drv, writer), _tee_reopen(reopen, writer))
                           for name, (drv, reopen) in sources.items()}
                observers.append(OdometryRecorder(writer, wheel_topic="/odom/wheel"))
            daemon = Daemon(cfg, clock, sources, build_odometry(cfg), store, notifier,
                            lossless=False, observers=observers,
                            driver_stats=lambda: {n: _stats(d) for n, (d, _) in sources.items()},
                            floor=build_floor_detector(cfg, store, load_calibration(cfg)))
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
    possible when None) and write the map the config names; returns the run's report."""
    from drivers.recording.reader import RecordingReader
    from drivers.recording.replay import ReplaySource
    from robotd.base.clock import ManualClock
    from robotd.app.daemon import Daemon
    from robotd.app.notify import Notifier
    from robotd.io.store import MapStore

    span = RecordingReader(path).time_range_ns
    if span is None:
        raise ConfigError(f"{path}: the recording holds no messages")
    clock = ManualClock(span[0])
    replay = ReplaySource(path, clock, speed)
    with replay, MapStore.open(cfg.map.path, clock=clock) as store:
        daemon = Daemon(cfg, clock, {"base": (replay.base, None), "floor": (replay.floor, None)},
                        build_odometry(cfg), store, Notifier(), lossless=True,
                        floor=build_floor_detector(cfg, store, load_calibration(cfg)))
        replay.start()

        def finished() -> bool:
            c = daemon.pipeline.counters
            if replay.error is not None:
                return True
            if not replay.done():
                return False
            # Frames still held for a settled pose are handled by Pipeline.finish at the end.
            return (c.wheel_msgs + c.yaw_msgs >= replay.base.handed_out
                    and c.frames >= replay.floor.handed_out)

        report = daemon.run(stop_when=finished)
    if replay.error is not None:
        raise replay.error
    return {"replayed": dict(replay.counts), "keyframes": report.counters.keyframes,
            "frames": report.counters.frames, "odometry_samples": report.counters.wheel_msgs,
            "wall_s": report.wall_s, "recording_s": (span[1] - span[0]) / 1e9}


def _stats(driver: Any) -> Any:
    s = getattr(driver, "stats", None)
    return s() if callable(s) else repr(s)
