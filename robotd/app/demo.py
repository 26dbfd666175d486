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
from typing import Any

from robotd.base.files import nonempty_path

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
    from robotd.base.config import Config, load_config, replace
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
    print_summary(summary, sys.stdout)
    return exit_status(summary)


def _nominal_drive_if_calibrated(cfg: Any, calibration: Any) -> Any:
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


class _Recorder:
    """Pipeline observer: writes the fused and wheel-only trajectories as they come, and
    keeps the keyframes and the floor queries for the report."""

    name = "demo_recorder"

    def __init__(self, out: Path, nominal_drive: Any = None) -> None:
        from robotd.io.trajectory import TumWriter
        from robotd.odometry.kinematics import WheelOdometry

        self.fused = TumWriter(out / "fused.tum")
        self.wheel = TumWriter(out / "wheel.tum")
        # With a calibrated odometry model: wheel-only odometry with the nominal [robot]
        # geometry beside it (the demo's "before calibration").
        self.nominal = WheelOdometry(nominal_drive) if nominal_drive is not None else None
        self.wheel_nominal = TumWriter(out / "wheel_nominal.tum") if nominal_drive is not None else None
        self.keyframe_poses: list[tuple[float, float]] = []
        self.keyframe_poses_full: list[tuple[float, float, float]] = []
        self.keyframe_ids: list[int] = []
        self.keyframe_stamps: list[int] = []
        self.visual_poses: dict[int, Any] = {}  # keyframe id -> VO-only pose, when VO is on
        self.queries: list[tuple[int, list[tuple[int, float, float, int]]]] = []
        self.loops: list[tuple[int, int]] = []  # declared loops: (older keyframe, newer)
        self.refused: list[tuple[int, int]] = []  # refused by the graph's gate: (older, newer)
        self.forward_loops: list[Any] = []  # ForwardLoop messages (verified by the camera)
        self.forward_fates: dict[tuple[int, int], str] = {}  # (older, newer) -> fate

    def subscriptions(self) -> dict[type, Any]:
        from robotd.base.messages import (
            CandidateFate,
            ForwardLoop,
            KeyframeStored,
            Link,
            OdometryUpdate,
        )
        from robotd.floor.detector import KeyframeQuery

        subs = {OdometryUpdate: self.on_odometry, KeyframeStored: self.on_keyframe,
                KeyframeQuery: self.on_floor_query, Link: self.on_link, CandidateFate: self.on_fate,
                ForwardLoop: self.forward_loops.append}
        if self.nominal is not None:
            from robotd.base.messages import WheelTicks

            subs[WheelTicks] = self.on_ticks
        return subs

    def on_ticks(self, msg: Any) -> None:
        p = self.nominal.update(msg)
        self.wheel_nominal.write(p.stamp_ns, p.x_m, p.y_m, p.yaw_rad)

    def on_fate(self, fate: Any) -> None:
        if fate.detail.startswith("forward: "):
            self.forward_fates[(fate.candidate_id, fate.query_id)] = fate.fate
        elif fate.fate == "failed_gate" and fate.detail.startswith("chi2"):  # not an earlier run's
            self.refused.append((fate.candidate_id, fate.query_id))

    def on_link(self, link: Any) -> None:
        if link.kind == "loop" and link.source == "floor":
            self.loops.append((link.from_id, link.to_id))

    def on_odometry(self, u: Any) -> None:
        self.fused.write(u.fused.stamp_ns, u.fused.x_m, u.fused.y_m, u.fused.yaw_rad)
        self.wheel.write(u.wheel.stamp_ns, u.wheel.x_m, u.wheel.y_m, u.wheel.yaw_rad)

    def on_keyframe(self, msg: Any) -> None:
        kf = msg.keyframe
        self.keyframe_poses.append((kf.pose.x_m, kf.pose.y_m))
        self.keyframe_poses_full.append((kf.pose.x_m, kf.pose.y_m, kf.pose.yaw_rad))
        self.keyframe_ids.append(kf.keyframe_id)
        self.keyframe_stamps.append(kf.stamp_ns)
        if kf.visual_pose is not None:
            self.visual_poses[kf.keyframe_id] = kf.visual_pose

    def on_floor_query(self, query: Any) -> None:
        self.queries.append((query.keyframe_id, [
            (c.keyframe_id, float(c.local.score), float(c.global_score), int(c.local.n_inliers))
            for c in query.candidates]))

    def close(self) -> None:
        self.fused.close()
        self.wheel.close()
        if self.wheel_nominal is not None:
            self.wheel_nominal.close()


class _Progress:
    """A progress line on stderr: robot time done, speed against real time."""

    def __init__(self, total_s: float) -> None:
        self.total_s = total_s
        self.start = time.monotonic()
        self.last = 0.0
        self.tty = sys.stderr.isatty()
        self.next_pct = 10

    def update(self, sim_s: float, keyframes: int, final: bool = False) -> None:
        now = time.monotonic()
        if not final and now - self.last < 0.5:
            return
        self.last = now
        wall = now - self.start
        pct = 100.0 * min(1.0, sim_s / self.total_s) if self.total_s > 0 else 100.0
        line = (f"demo: {pct:5.1f}%  robot time {sim_s:6.1f}/{self.total_s:.0f} s  "
                f"keyframes {keyframes}  x{sim_s / wall if wall > 0 else 0:.1f} real time")
        if self.tty:
            sys.stderr.write("\r" + line + ("\n" if final else ""))
            sys.stderr.flush()
        elif final or pct >= self.next_pct:
            sys.stderr.write(line + "\n")
            while self.next_pct <= pct:
                self.next_pct += 10


def run_demo(base_cfg: Any, *, out: Path, route: str = "office", floor_files: tuple[str, ...] = (),
             floor_scale: float = 0.001, floor_pattern: str | None = None,
             duration_s: float | None = None, seed: int = 0,
             realtime: bool = False, plot: bool = True, record: Path | None = None,
             observers: tuple[Any, ...] = (), base: str = "kobuki",
             can_convention: str = "diff_drive", can_faults: bool = False,
             kidnap: tuple[float, float, float] | None = None,
             startup: Any = None, base_seed: int | None = None) -> dict[str, Any]:
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
            _prepare_output_folder(out)
            map_path = (out / "map.sqlite").absolute()
            # One demo per folder: a second one into the same --out is refused here, before
            # it clears anything (robotd.io.maplock).
            with hold_map_lock(map_path):
                _clear_previous_map(map_path)
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


def _run_demo(base_cfg: Any, robot: Any, clock: Any, cam_model: Any, *, out: Path, map_path: Path,
              calibration: Any, early: Any, wall0: float, realtime: bool, plot: bool,
              record: Path | None, observers: tuple[Any, ...], base: str, can_convention: str,
              floor_files: tuple[str, ...], floor_pattern: str | None) -> dict[str, Any]:
    """The demo once its arguments are checked, its folder is ready and its map locked."""
    from robotd.base.config import replace, with_virtual_floor_camera
    from robotd.base.files import write_text_replacing

    if base == "can":
        from sim.emulators.can import can_config_changes

        cfg = replace(base_cfg, "base", driver="can")
        cfg = replace(cfg, "can", interface="virtual", channel=robot.port,
                      **can_config_changes(can_convention))
    else:
        cfg = replace(base_cfg, "base", driver="kobuki", port=robot.port)
    cfg = with_virtual_floor_camera(cfg)
    cfg = replace(cfg, "map", path=str(map_path))
    recorder = _Recorder(out, _nominal_drive_if_calibrated(cfg, calibration))
    live = _drive(robot, cfg, clock, recorder, realtime=realtime, record=record, observers=observers,
                  calibration=calibration, early=early)
    live["wall_s"] = time.monotonic() - wall0
    summary = _summarise(cfg, cam_model, robot, recorder, live, out, plot=plot,
                         floor_files=floor_files, floor_pattern=floor_pattern, record=record)
    write_text_replacing(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary


KIDNAP_CARRY_S = 5.0
"""How long ``--kidnap`` carries the robot, seconds."""

FORWARD_FPS = 15.0
"""The virtual forward camera's frame rate in the demo: a frame within 33 ms of each keyframe."""


def _can_faults(wanted: bool, duration_s: float | None, route: str) -> Any:
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

DEMO_MAP_META = "demo"
"""The ``meta`` key that marks a map written by the demo, which the next demo into the
same folder may replace; any other file at ``OUT/map.sqlite`` is left alone."""


def check_duration(duration_s: float | None) -> None:
    """ConfigError unless ``duration_s`` is None (the whole route) or a finite number of
    seconds of at least :data:`MIN_DURATION_S`."""
    from robotd.base.errors import ConfigError

    if duration_s is not None and not (math.isfinite(duration_s) and duration_s >= MIN_DURATION_S):
        raise ConfigError(f"--duration must be a number of seconds of robot time, at least "
                          f"{MIN_DURATION_S:g}, got {duration_s}")


def _prepare_output_folder(out: Path) -> None:
    """Make ``out`` (and its parents); ConfigError, naming it, when it is a file, cannot be
    made, or cannot be written."""
    import os

    from robotd.base.errors import ConfigError

    if out.exists() and not out.is_dir():
        raise ConfigError(f"output folder {out} exists and is not a folder (choose another --out)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create the output folder {out}: {exc.strerror or exc}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise ConfigError(f"output folder {out} is not writable (read-only file system or "
                          "permissions; choose another --out)")


def _clear_previous_map(map_path: Path) -> None:
    """Remove an earlier demo's map at ``map_path`` (with its ``-wal``/``-shm``); refuse,
    leaving it untouched, anything else there: a foreign or damaged file, a robotd map not
    written by the demo."""
    from robotd.base.errors import MapStoreError
    from robotd.io.mapfile import read_meta

    sidecars = [Path(str(map_path) + suffix) for suffix in ("-wal", "-shm")]
    if not map_path.exists():
        if any(p.exists() for p in sidecars):
            raise MapStoreError(f"{sidecars[0].name} or {sidecars[1].name} without their map is in "
                                f"{map_path.parent}; left as it is: move it away or choose another --out")
        return
    try:
        is_demo_map = map_path.is_file() and DEMO_MAP_META in read_meta(map_path)
    except MapStoreError as exc:
        raise MapStoreError(f"{map_path} is in the way and is not a demo map ({exc}); left as it "
                            "is: move it away or choose another --out") from None
    if not is_demo_map:
        raise MapStoreError(f"{map_path} is in the way: a robotd map without the demo's mark (not "
                            "written by the demo, or by a demo older than the mark); left as it "
                            "is: move it away or choose another --out")
    log.info("replacing the previous demo map %s", map_path)
    for stale in (map_path, *sidecars):
        stale.unlink(missing_ok=True)


def _drive(robot: Any, cfg: Any, clock: Any, recorder: _Recorder, *, realtime: bool,
           record: Path | None, observers: tuple[Any, ...] = (), calibration: Any = None,
           early: Any = None) -> dict[str, Any]:
    """Play the virtual robot out through the assembled daemon (its Kobuki bytes read by
    the real driver over the pty), optionally recording everything; returns the run's
    figures (report, keyframes stored, commands the robot saw, camera drops).

    A recording that cannot be written (disk full) stops the run: the daemon raises the
    :class:`~robotd.base.errors.RecordingError` after closing the run in the map, and the
    recording stays readable under its ``.partial`` name."""
    progress = _Progress(robot.duration_s)
    writer = None
    if record is not None:
        from robotd.app.service import open_recording

        writer = open_recording(cfg, record)
    try:
        return _drive_and_record(robot, cfg, clock, recorder, progress, realtime=realtime,
                                 writer=writer, observers=observers, calibration=calibration,
                                 early=early)
    finally:
        if writer is not None:
            writer.close(completed=False, reason="the demo stopped on an error")


def _drive_and_record(robot: Any, cfg: Any, clock: Any, recorder: _Recorder, progress: _Progress,
                      *, realtime: bool, writer: Any, observers: tuple[Any, ...] = (),
                      calibration: Any = None, early: Any = None) -> dict[str, Any]:
    from robotd.app.assemble import assemble_daemon, open_map
    from robotd.app.notify import Notifier
    from robotd.io.trajectory import write_tum

    out = Path(cfg.map.path).parent
    with robot, open_map(cfg, clock=clock) as store, _open_base(robot, cfg, clock) as driver:
        store.set_meta(DEMO_MAP_META, "written by robotd demo; the next demo into this folder "
                                      "replaces it")
        is_can = cfg.base.driver == "can"
        if not is_can:
            driver.request_extra(hardware_version=True, firmware_version=True, udid=True)
        sources: dict[str, Any] = {"base": driver, "floor": robot.camera}
        if robot.forward is not None:
            sources["forward"] = robot.forward
        watchers: list[Any] = [recorder, *observers]
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
                base_done = (st["frames"] >= robot.packets_emitted
                             and odo.wheel_msgs >= st["wheel_samples"])
            else:
                base_done = odo.wheel_msgs >= robot.packets_emitted
            return (robot.finished.is_set() and base_done
                    and c.frames >= robot.camera.frames_emitted - robot.camera.dropped)

        report = daemon.run(stop_when=finished)
        if early is not None:  # from here on Ctrl-C interrupts the report as usual
            early.release()
        progress.update(robot.sim_time_s, daemon.pipeline.stage("keyframes").keyframes, final=True)
        robot.stop()
        recorder.close()
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
        live = {"relocalisations": list(getattr(graph_stage, "relocalised_at", [])),"report": report, "keyframes_stored": store.count_keyframes(),
                "floor_threshold": floor.detector.threshold if floor is not None else None,
                "commands": dict(robot.commands_received), "camera_drops": robot.camera.dropped,
                "interrupted": interrupted,
                "robot_time_s": (min(reached_ns / 1e9, robot.duration_s) if reached_ns is not None
                                 else robot.duration_s)}
    if robot.error is not None:
        raise robot.error
    return live


def _open_base(robot: Any, cfg: Any, clock: Any) -> Any:
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


def exit_status(summary: dict[str, Any]) -> int:
    """The demo's exit status: 128 + the signal that interrupted it, else 0 when its
    figures are complete (``ok``), else 1."""
    if summary.get("interrupted"):
        return 128 + _STOP_SIGNALS[summary["interrupted"]]
    return 0 if summary["ok"] else 1


def _summarise(cfg: Any, cam_model: Any, robot: Any, recorder: _Recorder, live: dict[str, Any],
               out: Path, *, plot: bool, floor_files: tuple[str, ...], floor_pattern: str | None,
               record: Path | None) -> dict[str, Any]:
    """The demo's figures against ground truth (and its plots)."""
    from robotd.io.trajectory import read_tum, trajectory_errors

    stamps, fused = read_tum(out / "fused.tum")
    _, wheel = read_tum(out / "wheel.tum")
    truth = robot.motion.pose_at(stamps / 1e9)
    err_fused = trajectory_errors(truth, fused)
    err_wheel = trajectory_errors(truth, wheel)
    err_nominal = None
    if (out / "wheel_nominal.tum").exists() and recorder.nominal is not None:
        n_stamps, nominal = read_tum(out / "wheel_nominal.tum")
        if len(n_stamps):
            err_nominal = trajectory_errors(robot.motion.pose_at(n_stamps / 1e9), nominal).as_dict()
    report = live["report"]
    c = report.counters
    kob = report.driver_stats.get("kobuki", {})
    can_stats = report.driver_stats.get("can")
    wall_s = live["wall_s"]
    summary: dict[str, Any] = {
        "route": robot.settings.route, "seed": robot.settings.seed,
        "floor": list(floor_files) or ["skimage:brick,grass,gravel"], "floor_pattern": floor_pattern,
        "interrupted": live["interrupted"], "planned_robot_time_s": robot.duration_s,
        "robot_time_s": live["robot_time_s"], "wall_time_s": wall_s,
        "real_time_factor": live["robot_time_s"] / wall_s if wall_s > 0 else None,
        "distance_m": err_fused.distance_m,
        "frames_rendered": robot.camera.frames_emitted, "frames_processed": c["frames"],
        "keyframes": live["keyframes_stored"], "odometry_samples": c["wheel_msgs"],
        "links": {"odometry": c.get("links_odometry", 0), "loop": c.get("links_loop", 0)},
        "drops": {"camera": live["camera_drops"],
                  **{f"queue_{k}": v for k, v in report.queue_drops.items()},
                  "frames_unsynced": c["frames_unsynced"]},
        "packet_errors": {k: kob.get(k, 0) for k in
                          ("garbage_bytes", "bad_checksums", "truncated", "malformed_subpayloads")},
        "commands_seen_by_robot": live["commands"],
        "wheel_only": err_wheel.as_dict(), "fused": err_fused.as_dict(),
        "wheel_only_nominal": err_nominal,
        "stopped_by": report.stopped_by,
        "calibration": cfg.calibration.path if Path(cfg.calibration.path).exists() else None,
        "recording": str(record) if record is not None else None,
    }
    if can_stats is not None:
        summary["base"] = "can"
        summary["can"] = {**can_stats, "convention": robot.settings.can_convention,
                          "frames_sent": robot.base.frames_sent,
                          "faults_injected": robot.base.frames.injected,
                          "odometry_degraded_episodes": c.get("odometry_degraded_episodes", 0)}
    if cfg.visual_odometry.enabled:
        summary["visual_odometry"] = {"mode": cfg.visual_odometry.role,
                                      **{k: v for k, v in c.items() if k.startswith("vo_")}}
    if cfg.floor_detector.enabled and recorder.keyframe_ids:
        summary["floor_detector"] = floor_summary(cfg, cam_model, robot.motion, recorder,
                                                  out if plot else None)
        summary["floor_detector"]["threshold"] = live["floor_threshold"]
        summary["floor_detector"]["above_threshold"] = c.get("loop_candidates_above_threshold", 0)
    graph = _graph_summary(out / "map.sqlite", robot, c, recorder.visual_poses)
    if graph is not None:
        summary["pose_graph"] = graph
    if cfg.forward_detector.enabled:
        summary["forward_detector"] = forward_summary(cfg, robot, recorder, c)
    if robot.settings.kidnap is not None:
        summary["relocalisation"] = relocalisation_summary(robot, recorder, live, c)
    summary["ok"] = bool(c["frames"] == robot.camera.frames_emitted and not live["interrupted"]
                         and live["keyframes_stored"] == c["keyframes"])
    if plot:
        _plot_trajectories(out, robot, recorder, truth, fused, wheel, err_fused.distance_m,
                           graph)
    if graph is not None:
        graph.pop("_plot")
    return summary


FORWARD_YAW_OK_DEG = 5.0
FORWARD_BEARING_OK_DEG = 10.0
"""A forward loop's measured heading change and bearing are "right" when within these of the
truth (the bearing is judged only when the true cameras are more than 0.2 m apart)."""


def relocalisation_summary(robot: Any, recorder: _Recorder, live: dict[str, Any],
                           c: dict[str, Any]) -> dict[str, Any]:
    """The kidnapping judged by the truth: when the robot was put down, how long and how far
    it drove until the daemon relocalised (the daemon's own figures, from its odometry, and
    the truth's distance), and the pose error of the relocalising keyframe right after
    relocalisation (the graph's estimate then, in the map frame, against the true pose)."""
    import numpy as np

    from robotd.base.geometry import between, compose, inverse, wrap_angle

    at_s, to_s, carry_s = robot.settings.kidnap
    motion = robot.motion
    put_down_s = at_s + carry_s
    stamps = np.asarray(recorder.keyframe_stamps, dtype=np.int64)
    first_s = stamps[0] / 1e9 if len(stamps) else 0.0
    # The map frame is the first run's odometry frame: its origin is the truth's first keyframe pose
    # as the odometry saw it (the odometry starts at zero there, as the demo's plots assume).
    fused0 = np.array(recorder.keyframe_poses_full[0]) if recorder.keyframe_poses_full else np.zeros(3)
    to_world = compose(motion.pose_at(first_s), inverse(fused0))
    out: dict[str, Any] = {"kidnapped_at_s": at_s, "put_down_at_s": put_down_s, "carried_s": carry_s,
                           "put_down_where_route_was_at_s": to_s,
                           "carried_m": float(np.hypot(*(motion.pose_at(at_s)[:2] - motion.pose_at(put_down_s + 1e-3)[:2]))),
                           "lifts_detected": c.get("lifts", 0), "odometry_breaks": c.get("odometry_breaks", 0),
                           "relocalisations": c.get("relocalisations", 0),
                           "candidates_refused_before": c.get("reloc_candidates_refused", 0)}
    after = [r for r in live["relocalisations"] if r["stamp_ns"] / 1e9 >= put_down_s]
    if not after:
        out["relocalised"] = False
        return out
    r = after[0]
    t_s = r["stamp_ns"] / 1e9
    k0 = int(np.searchsorted(motion.t_s, put_down_s))
    k1 = int(np.searchsorted(motion.t_s, t_s))
    true_m = float(np.sum(np.abs(motion.v_mps[k0:k1])) * motion.dt_s)
    err = between(motion.pose_at(t_s), compose(to_world, np.asarray(r["pose"])))
    out.update({"relocalised": True, "against_run": r["run"], "after_s": t_s - put_down_s,
                "after_s_daemon": r["after_s"], "after_m_daemon": r["after_m"], "after_m_true": true_m,
                "agreeing_candidates": r["candidates"],
                "position_error_m": float(np.hypot(err[0], err[1])),
                "heading_error_deg": float(abs(np.degrees(wrap_angle(err[2]))))})
    return out


def forward_summary(cfg: Any, robot: Any, recorder: _Recorder, c: dict[str, Any]) -> dict[str, Any]:
    """The forward loops judged by the truth: each verified loop's heading change and bearing
    against the true camera poses of its two keyframes, and what the pose graph did with it."""
    import numpy as np

    from robotd.app.assemble import forward_mount
    from robotd.base.geometry import between, compose, wrap_angle

    mount = forward_mount(cfg)
    stamp_of = dict(zip(recorder.keyframe_ids, recorder.keyframe_stamps))
    rows = []
    for m in recorder.forward_loops:
        if m.from_id not in stamp_of or m.to_id not in stamp_of:
            continue
        a, b = (compose(robot.motion.pose_at(stamp_of[k] / 1e9), mount) for k in (m.from_id, m.to_id))
        rel = between(a, b)
        dist = float(np.hypot(rel[0], rel[1]))
        yaw_err = abs(math.degrees(wrap_angle(m.dyaw_rad - rel[2])))
        bearing_err = abs(math.degrees(wrap_angle(m.bearing_rad - math.atan2(rel[1], rel[0]))))
        right = yaw_err <= FORWARD_YAW_OK_DEG and (dist <= 0.2 or bearing_err <= FORWARD_BEARING_OK_DEG)
        rows.append({"from": m.from_id, "to": m.to_id, "probability": m.probability,
                     "inliers": m.inliers, "true_distance_m": dist, "yaw_error_deg": yaw_err,
                     "bearing_error_deg": bearing_err if dist > 0.2 else None, "right": right,
                     "measured_range_m": m.range_m,
                     "fate": recorder.forward_fates.get((m.from_id, m.to_id), "none")})
    accepted = [r for r in rows if r["fate"] == "accepted"]
    return {"images": c.get("forward_images", 0), "frames": c.get("forward_frames", 0),
            "unsynced": c.get("forward_unsynced", 0), "verified_loops": len(rows),
            "verified_right": sum(r["right"] for r in rows),
            "accepted": len(accepted), "accepted_right": sum(r["right"] for r in accepted),
            "refused_by_gate": c.get("forward_loops_failed_gate", 0),
            "failed_verification": c.get("forward_failed_verification", 0),
            "not_planar": c.get("forward_not_planar", 0),
            "vocabulary_words": c.get("forward_vocabulary", 0),
            "ms_per_image_median": c.get("forward_ms_median"), "ms_per_image_p99": c.get("forward_ms_p99"),
            "loops": rows}


def _graph_summary(map_path: Path, robot: Any, c: dict[str, int],
                   visual_poses: dict[int, Any]) -> dict[str, Any] | None:
    """The loop-corrected keyframe poses against ground truth, beside the keyframes' own
    poses (the wheel + gyro filter's: :class:`robotd.app.pipeline.KeyframeStage`) and (with
    visual odometry on) floor visual odometry alone at the same keyframes: end
    errors, ATE (RMS position error, start-anchored, no fit) and RPE (RMS error of each
    keyframe-to-keyframe step)."""
    import numpy as np

    from robotd.io.store import MapStore
    from robotd.io.trajectory import relative_pose_error, trajectory_errors, write_tum

    with MapStore.open(map_path, create=False) as store:
        kfs = list(store.keyframes())
        opt = store.optimized_poses()
        loops = [(lk.from_id, lk.to_id) for lk in store.links("loop")]
    if len(kfs) < 2 or not opt:
        return None
    kfs = [k for k in kfs if k.id in opt]
    odometry = np.array([[k.x_m, k.y_m, k.yaw_rad] for k in kfs])  # wheel + gyro (KeyframeStage)
    optimized = np.array([opt[k.id] for k in kfs])
    # Every trajectory the summary prints is a file, so evo compares them all.
    stamps = np.array([k.stamp_ns for k in kfs], dtype=np.int64)
    write_tum(map_path.parent / "corrected.tum", stamps, optimized)
    truth = robot.motion.pose_at(np.array([k.stamp_ns for k in kfs]) / 1e9)
    out: dict[str, Any] = {"keyframes": len(kfs), "loops_in_graph": len(loops),
                           **{k: v for k, v in c.items() if k.startswith(("loops_", "graph_"))}}
    columns = [("odometry", odometry), ("loop_corrected", optimized)]
    if visual_poses and all(k.id in visual_poses for k in kfs):
        columns.insert(1, ("vo_only", np.array([visual_poses[k.id] for k in kfs])))
    for name, est in columns:
        if name != "loop_corrected":
            write_tum(map_path.parent / f"{'keyframes' if name == 'odometry' else name}.tum", stamps, est)
        e = trajectory_errors(truth, est)
        rpe_t, rpe_r = relative_pose_error(truth, est)
        out[name] = {"end_position_error_m": e.end_position_error_m,
                     "end_heading_error_deg": e.end_heading_error_deg,
                     "ate_rmse_m": e.rmse_position_m, "rpe_rmse_mm": rpe_t * 1e3,
                     "rpe_rmse_deg": float(np.degrees(rpe_r))}
    out["_plot"] = {"ids": [k.id for k in kfs], "optimized": optimized, "truth0": truth[0],
                    "loops": loops, "vo_only": dict(columns).get("vo_only")}
    return out


def _plot_trajectories(out: Path, robot: Any, recorder: _Recorder, truth: Any, fused: Any,
                       wheel: Any, distance_m: float, graph: dict[str, Any] | None = None) -> None:
    import numpy as np

    from robotd.base.geometry import compose, inverse, transform_points
    from robotd.io.plots import plot_trajectories
    from robotd.io.trajectory import anchor_to

    # Odometry starts at its own origin; draw it from the route's start, as the errors do.
    to_world = compose(truth[0], inverse(fused[0]))
    kf = transform_points(to_world, np.asarray(recorder.keyframe_poses).reshape(-1, 2))
    estimates = {"wheel only": anchor_to(truth[0], wheel), "fused (EKF)": anchor_to(truth[0], fused)}
    loop_xy = None
    if graph is not None:
        g = graph["_plot"]
        opt = compose(to_world, g["optimized"])
        if g["vo_only"] is not None:
            estimates["floor VO alone (keyframes)"] = compose(to_world, g["vo_only"])
        estimates["loop-corrected (pose graph)"] = opt
        row = {k: i for i, k in enumerate(g["ids"])}
        pairs = [(row[a], row[b]) for a, b in g["loops"] if a in row and b in row]
        loop_xy = np.array([[opt[a, :2], opt[b, :2]] for a, b in pairs]).reshape(-1, 2, 2)
    plot_trajectories(out / "trajectories.png", robot.floor, truth, estimates,
                      keyframes_xy=kf, loop_edges_xy=loop_xy,
                      title=f"robotd demo: route {robot.settings.route}, {distance_m:.0f} m")


LOOP_R = 0.33  # the loop definition's overlap ratio r (paper 003 Sec. III-A)


def floor_summary(cfg: Any, camera: Any, motion: Any, recorder: _Recorder,
                  out: Path | None) -> dict[str, Any]:
    """The map queries' candidates judged by ground-truth footprint overlap."""
    import numpy as np

    from robotd.floor.evaluation import candidate_report, overlap_matrix

    ids = np.asarray(recorder.keyframe_ids)
    stamps = np.asarray(recorder.keyframe_stamps, dtype=np.int64)
    row = {int(k): i for i, k in enumerate(ids)}
    truth = motion.pose_at(stamps / 1e9)
    overlap = overlap_matrix(camera, truth)
    queries = [(row[q], [(row[c], s) for c, s, _g, _n in cs]) for q, cs in recorder.queries]
    rep = candidate_report(overlap, stamps, queries, cfg.floor_detector.exclude_recent_s)
    best = sorted(rep.candidates, key=lambda c: -c.local_score)[:10]
    scores = np.array([c.local_score for c in rep.candidates]) if rep.candidates else np.zeros(0)
    levels = sorted({float(np.quantile(scores, q)) for q in (0.5, 0.9, 0.99)}) if len(scores) else []
    d: dict[str, Any] = {
        "mode": cfg.floor_detector.descriptor_mode, "queries": rep.queries,
        "candidates_returned": len(rep.candidates),
        "queries_with_true_revisit": rep.queries_with_true_loop,
        "revisits_found_among_candidates": rep.found,
        "recall_of_candidates": rep.recall,
        "top1_true_overlap": rep.top1_true, "top1_total": rep.top1_total,
        "top1_precision_above_score": {f"{lv:.2f}": rep.precision_above(lv) for lv in levels},
        "best_candidates": [{"query_keyframe": int(ids[c.query]), "candidate_keyframe": int(ids[c.candidate]),
                             "local_score": c.local_score, "true_overlap_J": c.overlap} for c in best],
    }
    # Loop edges that entered the map (above the threshold, through the graph's gate),
    # judged by the truth.
    j = np.array([overlap[row[a], row[b]] for a, b in recorder.loops], dtype=float)
    d["loops_accepted"] = int(len(j))
    d["loops_truly_overlapping"] = int(np.sum(j >= LOOP_R))
    d["loops_sharing_floor"] = int(np.sum(j > 0))
    # The gate's refusals judged the same way: a truly overlapping one is a true loop the
    # graph's prediction disagreed with (odometry covariance too tight, or a bad transform).
    jr = np.array([overlap[row[a], row[b]] for a, b in recorder.refused if a in row and b in row], dtype=float)
    d["refused_by_gate"] = int(len(jr))
    d["refused_truly_overlapping"] = int(np.sum(jr >= LOOP_R))
    if out is not None:
        from robotd.io.plots import plot_similarity

        score_m = np.full(overlap.shape, np.nan, np.float32)
        for c in rep.candidates:
            score_m[c.query, c.candidate] = c.local_score
        plot_similarity(out / "similarity.png", overlap, score_m, stamps,
                        cfg.floor_detector.exclude_recent_s, mode=cfg.floor_detector.descriptor_mode)
    return d


def _print_comparison(f: Any, title: str, columns: list[tuple[str, dict[str, float]]],
                      rows: tuple[tuple[str, str, str], ...]) -> None:
    """A table: ``rows`` of (label, key, format) looked up in each column's dict."""
    print(f"{title:<26}" + "".join(f"{name:>12}" for name, _ in columns), file=f)
    for label, key, fmt in rows:
        print(f"{label:<26}" + "".join(f"{fmt.format(col[key]):>12}" for _, col in columns), file=f)


def print_summary(s: dict[str, Any], f: Any) -> None:
    """The short table the demo prints."""
    w, fu = s["wheel_only"], s["fused"]
    if s.get("interrupted"):
        print(f"interrupted ({s['interrupted']}) after {s['robot_time_s']:.1f} s of robot time of the "
              f"planned {s['planned_robot_time_s']:.1f} s; the figures below are of that part", file=f)
    rows = [
        ("route", f"{s['route']} (seed {s['seed']})"),
        ("distance", f"{s['distance_m']:.1f} m in {s['robot_time_s']:.0f} s robot time"),
        ("wall time", f"{s['wall_time_s']:.1f} s (x{s['real_time_factor']:.1f} real time)"),
        ("frames", f"{s['frames_processed']} processed of {s['frames_rendered']} rendered"),
        ("calibration", s.get("calibration") or "none (no loops declared)"),
        ("keyframes", f"{s['keyframes']}"),
        ("map links", f"odometry {s['links']['odometry']}, loop {s['links']['loop']}"),
        ("drops", ", ".join(f"{k} {v}" for k, v in s["drops"].items())),
        ("packet errors", ", ".join(f"{k} {v}" for k, v in s["packet_errors"].items())),
    ]
    if "can" in s:
        cs = s["can"]
        rows[-1] = ("CAN frames", f"{cs['frames']} read of {cs['frames_sent']} sent ({cs['convention']}): "
                    f"used {cs['frames_used']}, unknown {cs['unknown_frames']}, decode errors "
                    f"{cs['decode_errors']}, error frames {cs['error_frames']}, bus-off {cs['bus_off']}, "
                    f"floods {cs['flood_reads']}, stale left/right {cs['stale_left']}/{cs['stale_right']}, "
                    f"odometry degraded {cs['odometry_degraded_episodes']}x")
    width = max(len(r[0]) for r in rows)
    for k, v in rows:
        print(f"{k:<{width}}  {v}", file=f)
    print(file=f)
    columns = [("wheel only", w), ("fused", fu)]
    if s.get("wheel_only_nominal"):  # the odometry model is calibrated: before and after
        columns = [("wheel nom.", s["wheel_only_nominal"]), ("wheel cal.", w), ("fused", fu)]
    _print_comparison(f, "odometry vs ground truth", columns, (
        ("end position error (m)", "end_position_error_m", "{:.3f}"),
        ("end heading error (deg)", "end_heading_error_deg", "{:.2f}"),
        ("max position error (m)", "max_position_error_m", "{:.3f}"),
        ("end drift per 100 m (m)", "end_drift_per_100m_m", "{:.3f}"),
    ))
    g = s.get("pose_graph")
    if g:
        print(file=f)
        columns = [("wheel+gyro", g["odometry"]), ("loop-corr.", g["loop_corrected"])]
        if "vo_only" in g:
            columns.insert(1, ("VO only", g["vo_only"]))
        _print_comparison(f, f"at the {g['keyframes']} keyframes", columns, (
            ("end position error (m)", "end_position_error_m", "{:.3f}"),
            ("end heading error (deg)", "end_heading_error_deg", "{:.2f}"),
            ("ATE, RMS (m)", "ate_rmse_m", "{:.3f}"),
            ("RPE per step, RMS (mm)", "rpe_rmse_mm", "{:.2f}"),
        ))
        print(f"pose graph: {g['loops_in_graph']} loop edges accepted, {g.get('loops_failed_gate', 0)} "
              f"refused by the chi-square gate, {g.get('loops_down_weighted', 0)} down-weighted by the "
              f"optimiser; iSAM2 update median {g.get('graph_update_median_us', 0) / 1e3:.2f} ms, p99 "
              f"{g.get('graph_update_p99_us', 0) / 1e3:.2f} ms; last full solve {g.get('graph_solve_ms', 0)} ms",
              file=f)
    v = s.get("visual_odometry")
    if v:
        how = (f"{v.get('vo_combined', 0)} graph edges combined with the wheel + gyro edge, "
               f"{v.get('vo_disagreed', 0)} steps left out (disagreeing with it); the live filter "
               f"fused {v.get('vo_fused', 0)}, its gate refused {v.get('vo_rejected_by_filter', 0)}"
               if v["mode"] == "fused" else f"{v.get('vo_fallback', 0)} fell back to the wheel + gyro edge")
        print(f"floor visual odometry ({v['mode']}): {v.get('vo_ok', 0)} of {v.get('vo_steps', 0)} steps "
              f"measured; {how}", file=f)
    fw = s.get("forward_detector")
    if fw:
        print(file=f)
        print(f"forward loops: {fw['images']} forward keyframes ({fw['unsynced']} without a frame in time), "
              f"{fw['verified_loops']} loops verified, {fw['verified_right']} of them right by the truth "
              f"(heading within {FORWARD_YAW_OK_DEG:g} deg, bearing within {FORWARD_BEARING_OK_DEG:g} deg)", file=f)
        print(f"  into the pose graph: {fw['accepted']} accepted ({fw['accepted_right']} right), "
              f"{fw['refused_by_gate']} refused by the gate, {fw['not_planar']} not planar; "
              f"{fw['failed_verification']} candidates failed the epipolar check", file=f)
        print(f"  per forward keyframe: median {fw['ms_per_image_median']} ms, p99 {fw['ms_per_image_p99']} ms; "
              f"vocabulary {fw['vocabulary_words']} words", file=f)
    rl = s.get("relocalisation")
    if rl:
        print(file=f)
        print(f"kidnapped at {rl['kidnapped_at_s']:.1f} s, carried {rl['carried_s']:.0f} s over "
              f"{rl['carried_m']:.1f} m; lifts detected {rl['lifts_detected']}, odometry chain broken "
              f"{rl['odometry_breaks']}x", file=f)
        if rl.get("relocalised"):
            print(f"  relocalised against run {rl['against_run']} {rl['after_s']:.1f} s and "
                  f"{rl['after_m_true']:.2f} m (odometry: {rl['after_m_daemon']:.2f} m) after being put down, "
                  f"{rl['agreeing_candidates']} agreeing candidates; pose error then "
                  f"{rl['position_error_m']:.3f} m, {rl['heading_error_deg']:.2f} deg", file=f)
        else:
            print("  NOT relocalised before the end of the run", file=f)
    fd = s.get("floor_detector")
    if fd:
        print(file=f)
        print(f"floor loop candidates (mode {fd['mode']}): {fd['queries']} map queries, "
              f"{fd['candidates_returned']} candidates", file=f)
        print(f"  revisits (true overlap J >= 0.33 with an older keyframe): {fd['queries_with_true_revisit']}, "
              f"found among the candidates: {fd['revisits_found_among_candidates']}", file=f)
        print(f"  top candidate truly overlapping: {fd['top1_true_overlap']} of {fd['top1_total']}", file=f)
        if fd.get("threshold") is not None:
            print(f"  candidates at or above the threshold ({fd['threshold']:.2f}): "
                  f"{fd.get('above_threshold', 0)}; loop edges accepted: {fd['loops_accepted']}, "
                  f"truly overlapping (J >= {LOOP_R}): {fd['loops_truly_overlapping']}, "
                  f"sharing some floor: {fd['loops_sharing_floor']}", file=f)
            print(f"  refused by the graph's gate: {fd.get('refused_by_gate', 0)}, truly overlapping: "
                  f"{fd.get('refused_truly_overlapping', 0)}", file=f)
        else:
            print("  declared loops: none (no trained threshold for this mode)", file=f)
        for lv, (t, n) in fd["top1_precision_above_score"].items():
            print(f"  top candidates with local score >= {lv}: {t} of {n} truly overlapping", file=f)
        print(f"  {'query':>7} {'candidate':>9} {'local score':>11} {'true J':>7}", file=f)
        for b in fd["best_candidates"]:
            print(f"  {b['query_keyframe']:>7} {b['candidate_keyframe']:>9} {b['local_score']:>11.2f} "
                  f"{b['true_overlap_J']:>7.2f}", file=f)
