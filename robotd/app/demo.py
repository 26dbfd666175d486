"""``robotd demo``: the whole daemon on the built-in virtual robot.

The virtual robot speaks Kobuki bytes over a pseudo-terminal and renders the floor
camera; the daemon opens the pty with its real serial driver, fuses odometry, selects
keyframes and writes the map, exactly as on the robot. Afterwards the demo compares the
trajectories with ground truth and writes:

``OUT/map.sqlite``, ``groundtruth.tum``, ``wheel.tum``, ``fused.tum``, ``summary.json``,
``trajectories.png``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from robotd.base.files import nonempty_path

if TYPE_CHECKING:  # the module stays light: the CLI imports it to build its parser
    from drivers.base import Driver
    from drivers.recording.writer import RecordingWriter
    from robotd.app.daemon import Source
    from robotd.app.demo_summary import DriveResult
    from robotd.app.pipeline import Stage as Observer  # a pipeline observer: a stage that only watches
    from robotd.app.progress import Progress
    from robotd.app.signals import StartupSignals
    from robotd.base.camera import FloorCameraModel
    from robotd.base.clock import ManualClock
    from robotd.base.config import Config
    from robotd.evaluation.groundtruth import Summary
    from robotd.io.calibfile import CalibrationFile
    from robotd.io.trajectory import TumRecorder
    from robotd.odometry.kinematics import DiffDriveParams
    from sim.emulators.can import CanFaults
    from sim.robot import VirtualRobot

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from sim.route import ROUTES

    p.add_argument("--route", default="office", choices=sorted(ROUTES),
                   help="route to drive (default: office, about 110 m with loops both ways)")
    p.add_argument("--floor", action="append", type=nonempty_path, metavar="FILE", default=None,
                   help="floor photograph(s) to build the floor from (repeat for several; "
                        "default: the scikit-image brick, grass and gravel photographs)")
    p.add_argument("--floor-pattern", choices=("planks", "tiles"), default=None,
                   help="a regular printed floor instead: planks or tiles whose few prints "
                        "repeat (the paper's worst case; the print is --floor's photo or gravel)")
    p.add_argument("--floor-scale", type=float, default=0.001, metavar="M_PER_PX",
                   help="size of one floor-photo pixel in metres (default 0.001)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after this many seconds of robot time (default: whole route)")
    p.add_argument("--out", type=nonempty_path, default=Path("demo-out"), metavar="DIR",
                   help="output folder (default: ./demo-out)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the virtual robot")
    p.add_argument("--config", type=nonempty_path, default=None,
                   help="start from this config file (the base port, camera source and map "
                        "path are replaced by the virtual robot's)")
    p.add_argument("--calibration", type=nonempty_path, default=None, metavar="FILE.yml",
                   help="calibration file with the loop thresholds (default: the config's, or, "
                        "when that does not exist, the demo's own calibration drive shipped "
                        "with robotd; see tools/demo_calibration.sh)")
    p.add_argument("--realtime", action="store_true",
                   help="pace the virtual robot on the wall clock (default: as fast as possible)")
    p.add_argument("--forward", action="store_true",
                   help="also render the forward camera in the route's textured world and run the "
                        "forward loop detector (paper 000) on it; its loops join the pose graph")
    p.add_argument("--no-plot", action="store_true", help="skip trajectories.png")
    p.add_argument("--record", type=nonempty_path, default=None, metavar="FILE.mcap",
                   help="also record the run (frames, ticks, gyro, odometry, ground truth) to MCAP")
    p.add_argument("--base", choices=("kobuki", "can"), default="kobuki",
                   help="the virtual robot's base: Kobuki bytes over a pty (default), or the same "
                        "sensor streams as CAN frames on a python-can virtual bus")
    p.add_argument("--can-dbc", choices=("diff_drive", "odrive_cansimple"), default="diff_drive",
                   help="with --base can: the convention of the frames (default diff_drive: wheel "
                        "angles and a gyro; odrive_cansimple: an ODrive per wheel, no gyro)")
    p.add_argument("--kidnap", type=float, default=None, metavar="T",
                   help="kidnap the robot at T s of the route: lifted (wheel drop, cameras covered), "
                        f"carried for {KIDNAP_CARRY_S:g} s and put down where the route is at --kidnap-to; "
                        "the daemon must notice, break its odometry chain and relocalise (Kobuki base)")
    p.add_argument("--kidnap-to", type=float, default=None, metavar="S",
                   help="with --kidnap: the route time of the place it is put down (default T/2, a "
                        "place driven before)")
    p.add_argument("--ros2", action="store_true",
                   help="publish the demo on ROS 2 (/tf map -> odom, robotd/odometry, path, loop closures, "
                        "diagnostics; DDS domain from ROS_DOMAIN_ID; needs robotd[ros2], docs/ros2.md)")
    p.add_argument("--foxglove", action="store_true",
                   help="serve a live Foxglove view of the demo on ws://127.0.0.1:8765 (needs robotd[foxglove])")
    p.add_argument("--foxglove-port", type=int, default=None, metavar="N",
                   help="with --foxglove: the port (default 8765)")
    p.add_argument("--can-faults", action="store_true",
                   help="with --base can: inject a flood of unknown ids, a bus-off, a stale wheel "
                        "and undecodable frames during the run")


def run_from_args(args: argparse.Namespace) -> int:
    from robotd.base.config import Config, replace
    from robotd.base.configfile import load_config
    from robotd.base.errors import ConfigError

    if args.floor_scale <= 0 or not math.isfinite(args.floor_scale):
        raise ConfigError(f"--floor-scale must be a positive number of metres, got {args.floor_scale}")
    base_cfg = load_config(args.config) if args.config else Config()
    calibration = args.calibration
    if calibration is not None and not calibration.is_file():
        raise ConfigError(f"--calibration {calibration}: no such file")
    if calibration is None and not Path(base_cfg.calibration.path).exists():
        calibration = shipped_calibration()
    if calibration is not None:
        base_cfg = replace(base_cfg, "calibration", path=str(calibration))
    if args.forward:
        base_cfg = replace(base_cfg, "forward_detector", enabled=True)
    if args.foxglove_port is not None and not args.foxglove:
        raise ConfigError("--foxglove-port needs --foxglove")
    if args.ros2:
        from drivers.ros2.dds import require_cyclonedds

        base_cfg = replace(base_cfg, "ros2", enabled=True)
        require_cyclonedds()  # before the demo's folder is touched
    if args.foxglove:
        from robotd.app.outputs import require_foxglove

        base_cfg = replace(base_cfg, "foxglove", enabled=True,
                           **({} if args.foxglove_port is None else {"port": args.foxglove_port}))
        require_foxglove()
    kidnap = None
    if args.kidnap is not None:
        kidnap = (args.kidnap, args.kidnap / 2 if args.kidnap_to is None else args.kidnap_to, KIDNAP_CARRY_S)
    elif args.kidnap_to is not None:
        raise ConfigError("--kidnap-to needs --kidnap")
    if args.can_faults and args.base != "can":
        raise ConfigError("--can-faults needs --base can (the faults are injected on the CAN bus)")
    if args.can_dbc != "diff_drive" and args.base != "can":
        raise ConfigError("--can-dbc needs --base can")
    summary = run_demo(base_cfg, out=args.out, route=args.route,
                       floor_files=tuple(str(f) for f in args.floor or ()),
                       floor_scale=args.floor_scale, floor_pattern=args.floor_pattern,
                       duration_s=args.duration, seed=args.seed,
                       realtime=args.realtime, plot=not args.no_plot, record=args.record,
                       base=args.base, can_convention=args.can_dbc, can_faults=args.can_faults,
                       kidnap=kidnap, startup=getattr(args, "startup", None))
    from robotd.app.demo_report import print_summary

    print_summary(summary, sys.stdout)
    return exit_status(summary)


def _nominal_drive_if_calibrated(cfg: Config, calibration: CalibrationFile | None) -> DiffDriveParams | None:
    """The config's nominal wheel geometry when the calibration holds an odometry model
    (the daemon then uses the model), else None."""
    from robotd.odometry.kinematics import DiffDriveParams

    if calibration is None or calibration.odometry is None:
        return None
    r = cfg.robot
    return DiffDriveParams(wheel_radius_m=r.wheel_radius_m, wheel_base_m=r.wheel_base_m,
                           ticks_per_rev=r.ticks_per_rev)


def shipped_calibration() -> Path | None:
    """The calibration file of the demo's own calibration drive, shipped as package data
    (``robotd/app/data/demo_calibration.yml``; ``tools/demo_calibration.sh`` makes it
    again), or None if this installation lacks it."""
    path = Path(__file__).with_name("data") / "demo_calibration.yml"
    return path if path.is_file() else None


def run_demo(base_cfg: Config, *, out: Path, route: str = "office", floor_files: tuple[str, ...] = (),
             floor_scale: float = 0.001, floor_pattern: str | None = None,
             duration_s: float | None = None, seed: int = 0,
             realtime: bool = False, plot: bool = True, record: Path | None = None,
             observers: tuple[Observer, ...] = (), base: str = "kobuki",
             can_convention: str = "diff_drive", can_faults: bool = False,
             kidnap: tuple[float, float, float] | None = None,
             startup: StartupSignals | None = None, base_seed: int | None = None) -> Summary:
    """Run the daemon on the virtual robot; returns the summary (also written as JSON).
    ``base_seed``: the seed whose base errors the robot has (default: ``seed``'s; see
    :attr:`sim.robot.VirtualRobotSettings.base_seed`).
    ``observers``: extra pipeline stages that watch the run (the benchmarks use this).
    ``base``: ``"kobuki"`` or ``"can"`` (the same sensor streams as ``can_convention``
    frames on a python-can virtual bus, read by the CAN driver; ``can_faults`` injects
    :meth:`sim.emulators.can.CanFaults.standard`). ``kidnap``: ``(at_s, to_s, carry_s)``, see
    :attr:`sim.robot.VirtualRobotSettings.kidnap`; the summary then has ``relocalisation``.

    Raises :class:`~robotd.base.errors.ConfigError` for a duration that is not a number of
    seconds of at least :data:`MIN_DURATION_S`, or an output folder that cannot be made or
    written, and :class:`~robotd.base.errors.MapStoreError` when ``out/map.sqlite`` holds
    something other than an earlier demo's map (which is left as it is).
    """
    from robotd.app.assemble import load_calibration
    from robotd.app.demo_output import clear_previous_map, prepare_output_folder
    from robotd.app.signals import held_signals
    from robotd.base.camera import FloorCameraModel
    from robotd.base.clock import ManualClock
    from robotd.io.maplock import hold_map_lock
    from sim.robot import VirtualRobot, VirtualRobotSettings

    # Everything is checked before the output folder is touched: a refused demo leaves the
    # previous demo's outputs (and anything else in --out) exactly as they were.
    with held_signals(startup) as early:
        check_demo_arguments(duration_s=duration_s, seed=seed, kidnap=kidnap, record=record, out=out,
                             base_seed=base_seed)
        calibration = load_calibration(base_cfg)
        clock = ManualClock()
        cam_model = FloorCameraModel.from_config(base_cfg.floor_camera)
        settings = VirtualRobotSettings(route=route, seed=seed, base_seed=base_seed,
                                        duration_s=duration_s, realtime=realtime, floor_files=floor_files,
                                        floor_metres_per_px=floor_scale,
                                        floor_pattern=floor_pattern,
                                        camera_fps=base_cfg.floor_camera.fps, base=base,
                                        can_convention=can_convention,
                                        can_faults=_can_faults(can_faults, duration_s, route),
                                        forward_camera=base_cfg.forward_detector.enabled,
                                        forward_fps=FORWARD_FPS, kidnap=kidnap)
        wall0 = time.monotonic()
        robot = VirtualRobot(settings, cam_model, clock)  # checks the route, floor and kidnapping
        with robot:
            early.stop_if_received()
            prepare_output_folder(out)
            map_path = (out / "map.sqlite").absolute()
            # One demo per folder: a second one into the same --out is refused here, before
            # it clears anything (robotd.io.maplock).
            with hold_map_lock(map_path):
                clear_previous_map(map_path)
                return _run_demo(base_cfg, robot, clock, cam_model, out=out, map_path=map_path,
                                 calibration=calibration, early=early, wall0=wall0,
                                 realtime=realtime, plot=plot, record=record,
                                 observers=observers, base=base, can_convention=can_convention,
                                 floor_files=floor_files, floor_pattern=floor_pattern)


def check_demo_arguments(*, duration_s: float | None, seed: int,
                         kidnap: tuple[float, float, float] | None,
                         record: Path | None, out: Path, base_seed: int | None = None) -> None:
    """ConfigError (or OutputError for ``record``) for arguments the demo cannot run with,
    before any output is touched."""
    from robotd.base.errors import ConfigError
    from robotd.base.files import check_output_file, check_utf8_path
    from drivers.recording.schemas import PARTIAL_SUFFIX

    check_duration(duration_s)
    check_utf8_path(out, "--out")
    for option, value in (("--seed", seed), ("--base-seed", base_seed)):
        if value is not None and not 0 <= value < 2**63:
            raise ConfigError(f"{option} must be a whole number from 0 to 2^63 - 1, got {value}")
    if kidnap is not None:
        at_s, to_s, _carry_s = kidnap
        if not (math.isfinite(at_s) and at_s > 0 and math.isfinite(to_s) and to_s >= 0):
            raise ConfigError(f"--kidnap and --kidnap-to must be route times in seconds, got "
                              f"{at_s:g} and {to_s:g}")
        if duration_s is not None and at_s >= duration_s:
            raise ConfigError(f"--kidnap {at_s:g} s is past the end of the run (--duration "
                              f"{duration_s:g} s): the robot would never be kidnapped")
    if record is not None:
        check_utf8_path(record, "--record")
        check_output_file(record, force=False, option="--record", force_option=None)
        partial = record.with_name(record.name + PARTIAL_SUFFIX)
        if partial.exists():
            raise ConfigError(f"{partial}: an interrupted recording is in the way (read it, or "
                              "remove it, first)")


def _run_demo(base_cfg: Config, robot: VirtualRobot, clock: ManualClock, cam_model: FloorCameraModel, *,
              out: Path, map_path: Path, calibration: CalibrationFile | None, early: StartupSignals,
              wall0: float, realtime: bool, plot: bool, record: Path | None, observers: tuple[Observer, ...],
              base: str, can_convention: str, floor_files: tuple[str, ...],
              floor_pattern: str | None) -> Summary:
    """The demo once its arguments are checked, its folder is ready and its map locked."""
    from robotd.app.demo_summary import summarise
    from robotd.base.config import replace, with_virtual_floor_camera
    from robotd.base.files import write_text_replacing
    from robotd.evaluation.observations import RunObservations
    from robotd.io.trajectory import TumRecorder

    if base == "can":
        from sim.emulators.can import can_config_changes

        cfg = replace(base_cfg, "base", driver="can")
        cfg = replace(cfg, "can", interface="virtual", channel=robot.port,
                      **can_config_changes(can_convention))
    else:
        cfg = replace(base_cfg, "base", driver="kobuki", port=robot.port)
    cfg = with_virtual_floor_camera(cfg)
    cfg = replace(cfg, "map", path=str(map_path))
    tum = TumRecorder(out, _nominal_drive_if_calibrated(cfg, calibration))
    obs = RunObservations()
    live = _drive(robot, cfg, clock, (tum, obs), realtime=realtime, record=record, observers=observers,
                  calibration=calibration, early=early)
    live.wall_s = time.monotonic() - wall0
    live.nominal_written = tum.wheel_nominal is not None
    summary = summarise(cfg, cam_model, robot, obs, live, out, plot=plot,
                        floor_files=floor_files, floor_pattern=floor_pattern, record=record)
    write_text_replacing(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary


KIDNAP_CARRY_S = 5.0
"""How long ``--kidnap`` carries the robot, seconds."""

FORWARD_FPS = 15.0
"""The virtual forward camera's frame rate in the demo: a frame within 33 ms of each keyframe."""


def _can_faults(wanted: bool, duration_s: float | None, route: str) -> CanFaults | None:
    """The standard CAN faults over the run's length, or None."""
    if not wanted:
        return None
    from sim.emulators.can import CanFaults
    from sim.route import MotionLimits, build_route, plan_motion

    length = duration_s if duration_s is not None else float(
        plan_motion(build_route(route), MotionLimits()).t_s[-1])
    return CanFaults.standard(length)


MIN_DURATION_S = 0.1
"""The shortest demo, seconds of robot time: a few odometry packets and camera frames."""

def check_duration(duration_s: float | None) -> None:
    """ConfigError unless ``duration_s`` is None (the whole route) or a finite number of
    seconds of at least :data:`MIN_DURATION_S`."""
    from robotd.base.errors import ConfigError

    if duration_s is not None and not (math.isfinite(duration_s) and duration_s >= MIN_DURATION_S):
        raise ConfigError(f"--duration must be a number of seconds of robot time, at least "
                          f"{MIN_DURATION_S:g}, got {duration_s}")


def _drive(robot: VirtualRobot, cfg: Config, clock: ManualClock, recorders: tuple[TumRecorder, Observer], *,
           realtime: bool, record: Path | None, observers: tuple[Observer, ...] = (),
           calibration: CalibrationFile | None = None, early: StartupSignals | None = None) -> DriveResult:
    """Play the virtual robot out through the assembled daemon (its Kobuki bytes read by
    the real driver over the pty), optionally recording everything; returns the run's
    figures (report, keyframes stored, commands the robot saw, camera drops).

    A recording that cannot be written (disk full) stops the run: the daemon raises the
    :class:`~robotd.base.errors.RecordingError` after closing the run in the map, and the
    recording stays readable under its ``.partial`` name."""
    from robotd.app.progress import Progress

    progress = Progress(robot.duration_s)
    writer = None
    if record is not None:
        from robotd.app.service import open_recording

        writer = open_recording(cfg, record)
    try:
        return _drive_and_record(robot, cfg, clock, recorders, progress, realtime=realtime,
                                 writer=writer, observers=observers, calibration=calibration,
                                 early=early)
    finally:
        if writer is not None:
            writer.close(completed=False, reason="the demo stopped on an error")


def _drive_and_record(robot: VirtualRobot, cfg: Config, clock: ManualClock,
                      recorders: tuple[TumRecorder, Observer], progress: Progress, *, realtime: bool,
                      writer: RecordingWriter | None, observers: tuple[Observer, ...] = (),
                      calibration: CalibrationFile | None = None,
                      early: StartupSignals | None = None) -> DriveResult:
    from drivers.kobuki.driver import KobukiDriver
    from robotd.app.assemble import assemble_daemon, open_map
    from robotd.app.demo_output import DEMO_MAP_META
    from robotd.app.demo_summary import DriveResult
    from robotd.app.notify import Notifier
    from robotd.io.trajectory import write_tum

    out = Path(cfg.map.path).parent
    with robot, open_map(cfg, clock=clock) as store, _open_base(robot, cfg, clock) as driver:
        store.set_meta(DEMO_MAP_META, "written by robotd demo; the next demo into this folder "
                                      "replaces it")
        is_can = cfg.base.driver == "can"
        if isinstance(driver, KobukiDriver):
            driver.request_extra(hardware_version=True, firmware_version=True, udid=True)
        sources: dict[str, Source] = {"base": driver, "floor": robot.camera}
        if robot.forward is not None:
            sources["forward"] = robot.forward
        watchers: list[Observer] = [*recorders, *observers]
        if writer is not None:
            from drivers.recording.writer import RecordingTee
            from robotd.app.service import OdometryRecorder

            sources = {name: RecordingTee(src, writer) for name, src in sources.items()}
            watchers.append(OdometryRecorder(writer))
        daemon = assemble_daemon(cfg, clock, sources, store, Notifier(), lossless=not realtime,
                                 observers=watchers, calibration=calibration,
                                 driver_stats=lambda: {"can" if is_can else "kobuki": driver.stats()})
        if early is not None:  # a Ctrl-C held during start-up stops the run at once
            early.attach(daemon)
        robot.start()

        def finished() -> bool:
            c = daemon.pipeline.stage("keyframes")
            progress.update(robot.sim_time_s, c.keyframes)
            if robot.error is not None:
                return True
            # Frames still held for a settled pose are handled by Pipeline.finish at the end.
            odo = daemon.pipeline.stage("odometry")
            if is_can:  # every frame read, and every wheel pair it made handled
                st = driver.stats()
                base_done = (int(st["frames"]) >= robot.packets_emitted
                             and odo.wheel_msgs >= int(st["wheel_samples"]))
            else:
                base_done = odo.wheel_msgs >= robot.packets_emitted
            return (robot.finished.is_set() and base_done
                    and c.frames >= robot.camera.frames_emitted - robot.camera.dropped)

        report = daemon.run(stop_when=finished)
        if early is not None:  # from here on Ctrl-C interrupts the report as usual
            early.release()
        progress.update(robot.sim_time_s, daemon.pipeline.stage("keyframes").keyframes, final=True)
        robot.stop()
        recorders[0].close()
        # Interrupted (Ctrl-C, SIGTERM), the run covers the robot time reached, not the route.
        interrupted = report.stopped_by if report.stopped_by in _STOP_SIGNALS else None
        reached_ns = clock.now_ns() if interrupted else None
        stamps, poses = robot.ground_truth()
        base_stamps, base_poses = robot.base.stamp_ns, robot.base.true_pose
        if reached_ns is not None:
            stamps, poses = stamps[stamps <= reached_ns], poses[stamps <= reached_ns]
            base_poses = base_poses[base_stamps <= reached_ns]
            base_stamps = base_stamps[base_stamps <= reached_ns]
        write_tum(out / "groundtruth.tum", stamps, poses)
        if writer is not None:
            for stamp, pose in zip(base_stamps, base_poses):
                writer.write_ground_truth(int(stamp), *map(float, pose))
            writer.close(completed=interrupted is None,
                         reason=f"interrupted ({interrupted})" if interrupted else "")
        floor = next((st for st in daemon.pipeline.stages if st.name == "floor"), None)
        graph_stage = next((st for st in daemon.pipeline.stages if st.name == "graph"), None)
        live = DriveResult(
            report=report, keyframes_stored=store.count_keyframes(),
            floor_threshold=floor.detector.threshold if floor is not None else None,
            commands=dict(robot.commands_received), camera_drops=robot.camera.dropped,
            interrupted=interrupted,
            robot_time_s=(min(reached_ns / 1e9, robot.duration_s) if reached_ns is not None
                          else robot.duration_s),
            relocalisations=list(getattr(graph_stage, "relocalised_at", [])))
    if robot.error is not None:
        raise robot.error
    return live


def _open_base(robot: VirtualRobot, cfg: Config, clock: ManualClock) -> Driver:
    """The daemon's driver of the virtual robot's base: the Kobuki driver on its pty, or
    the CAN driver on its virtual bus channel (through the registry, as ``robotd run``)."""
    if cfg.base.driver == "can":
        from drivers.registry import open_driver

        return open_driver("base", "can", cfg, clock)
    from drivers.kobuki.driver import KobukiDriver

    return KobukiDriver(robot.port, clock=clock, baudrate=cfg.base.baudrate,
                        yaw_source=cfg.base.yaw_source)


_STOP_SIGNALS = {"SIGINT": 2, "SIGTERM": 15}
"""The daemon's stop reasons that mean the user stopped the run, with their numbers."""


def exit_status(summary: Summary) -> int:
    """The demo's exit status: 128 + the signal that interrupted it, else 0 when its
    figures are complete (``ok``), else 1."""
    if summary.get("interrupted"):
        return 128 + _STOP_SIGNALS[summary["interrupted"]]
    return 0 if summary["ok"] else 1
