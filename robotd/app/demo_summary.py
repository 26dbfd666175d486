"""The demo's summary: a finished drive's figures against the virtual robot's ground truth
(:mod:`robotd.evaluation` judges, this module gathers), the keyframe trajectories as TUM
files beside the map, and the plots."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from robotd.app.daemon import DaemonReport
    from robotd.app.demo_report import GraphPlot
    from robotd.base.camera import FloorCameraModel
    from robotd.base.config import Config
    from robotd.evaluation.groundtruth import Summary
    from robotd.evaluation.observations import RunObservations
    from sim.robot import VirtualRobot


@dataclass
class DriveResult:
    """What the drive leaves for the summary besides the pipeline's observations."""

    report: DaemonReport
    keyframes_stored: int
    floor_threshold: float | None
    """The floor detector's loop threshold (None without a trained one)."""
    commands: dict[str, int]
    """The commands the virtual robot received, by kind."""
    camera_drops: int
    interrupted: str | None
    """The signal that stopped the run (``SIGINT``, ``SIGTERM``), else None."""
    robot_time_s: float
    relocalisations: list[dict[str, Any]] = field(default_factory=list)
    """The graph stage's record of each relocalisation (its own figures)."""
    wall_s: float = 0.0
    nominal_written: bool = False


def summarise(cfg: Config, cam_model: FloorCameraModel, robot: VirtualRobot, obs: RunObservations,
               live: DriveResult, out: Path, *, plot: bool, floor_files: tuple[str, ...],
               floor_pattern: str | None, record: Path | None) -> Summary:
    """The demo's figures against ground truth (:mod:`robotd.evaluation`), and its plots
    (with ``plot``) in ``out``."""
    from robotd.app.assemble import forward_loop_params, forward_mount
    from robotd.app.demo_report import plot_demo_trajectories, plot_floor_similarity
    from robotd.evaluation.groundtruth import floor_evaluation, forward_evaluation, relocalisation_evaluation
    from robotd.evaluation.metrics import odometry_errors
    from robotd.io.trajectory import read_tum

    stamps, fused = read_tum(out / "fused.tum")
    _, wheel = read_tum(out / "wheel.tum")
    truth = robot.motion.pose_at(stamps / 1e9)
    err_fused = odometry_errors(truth, fused)
    err_wheel = odometry_errors(truth, wheel)
    err_nominal = None
    nominal = None
    if live.nominal_written and (out / "wheel_nominal.tum").exists():
        n_stamps, nominal = read_tum(out / "wheel_nominal.tum")
        if not len(n_stamps):
            nominal = None
        else:
            err_nominal = odometry_errors(robot.motion.pose_at(n_stamps / 1e9), nominal).as_dict()
    report = live.report
    c = report.counters
    kob = report.driver_stats.get("kobuki", {})
    can_stats = report.driver_stats.get("can")
    wall_s = live.wall_s
    summary: Summary = {
        "route": robot.settings.route, "seed": robot.settings.seed,
        "floor": list(floor_files) or ["skimage:brick,grass,gravel"], "floor_pattern": floor_pattern,
        "interrupted": live.interrupted, "planned_robot_time_s": robot.duration_s,
        "robot_time_s": live.robot_time_s, "wall_time_s": wall_s,
        "real_time_factor": live.robot_time_s / wall_s if wall_s > 0 else None,
        "distance_m": err_fused.distance_m,
        "frames_rendered": robot.camera.frames_emitted, "frames_processed": c["frames"],
        "keyframes": live.keyframes_stored, "odometry_samples": c["wheel_msgs"],
        "links": {"odometry": c.get("links_odometry", 0), "loop": c.get("links_loop", 0)},
        "drops": {"camera": live.camera_drops,
                  **{f"queue_{k}": v for k, v in report.queue_drops.items()},
                  "frames_unsynced": c["frames_unsynced"]},
        "packet_errors": {k: kob.get(k, 0) for k in
                          ("garbage_bytes", "bad_checksums", "truncated", "malformed_subpayloads")},
        "commands_seen_by_robot": live.commands,
        "wheel_only": err_wheel.as_dict(), "fused": err_fused.as_dict(),
        "wheel_only_nominal": err_nominal,
        "stopped_by": report.stopped_by,
        "calibration": cfg.calibration.path if Path(cfg.calibration.path).exists() else None,
        "recording": str(record) if record is not None else None,
    }
    if can_stats is not None:
        from sim.emulators.can import CanEmulator

        assert isinstance(robot.base, CanEmulator)  # the CAN driver's stats come from its bus
        summary["base"] = "can"
        summary["can"] = {**can_stats, "convention": robot.settings.can_convention,
                          "frames_sent": robot.base.frames_sent,
                          "faults_injected": robot.base.frames.injected,
                          "odometry_degraded_episodes": c.get("odometry_degraded_episodes", 0)}
    if cfg.visual_odometry.enabled:
        summary["visual_odometry"] = {"role": cfg.visual_odometry.role,
                                      **{k: v for k, v in c.items() if k.startswith("vo_")}}
    fd = cfg.floor_detector
    if fd.enabled and obs.keyframe_ids:
        floor = floor_evaluation(cam_model, robot.motion, obs, exclude_recent_s=fd.exclude_recent_s, mode=fd.descriptor_mode)
        summary["floor_detector"] = {**floor.summary, "threshold": live.floor_threshold,
                                     "above_threshold": c.get("loop_candidates_above_threshold", 0)}
        if plot:
            plot_floor_similarity(out, floor, obs.stamps_ns, fd.exclude_recent_s, fd.descriptor_mode)
    graph = _graph_summary(out / "map.sqlite", robot, c, obs)
    if graph is not None:
        summary["pose_graph"] = graph[0]
    if cfg.forward_detector.enabled:
        summary["forward_detector"] = forward_evaluation(robot.motion, forward_mount(cfg), obs, c,
                                                           forward_loop_params(cfg))
        # The arrival-order cases the forward stage cannot hide (its module notes): 0 when the
        # run's forward loops do not depend on the machine's load.
        summary["forward_detector"]["order_dependent"] = {
            "late": c.get("forward_late", 0), "frames_evicted": c.get("forward_frames_evicted", 0)}
        # Level tests that waited for a forward keyframe verifying nothing (the stage's notes).
        summary["forward_detector"]["deferred"] = {
            k: c.get(f"forward_deferred{s}", 0)
            for k, s in (("deferred", ""), ("inline", "_inline"), ("at_end", "_at_end"), ("wait_max", "_wait_max"),
                                 ("across", "_across"), ("forced", "_forced"))}
        summary["forward_detector"]["deferred"]["checks_max"] = c.get("forward_checks_max", 0)
    if robot.settings.kidnap is not None:
        summary["relocalisation"] = relocalisation_evaluation(robot.motion, robot.settings.kidnap, obs,
                                                              live.relocalisations, c)
    summary["ok"] = bool(c["frames"] == robot.camera.frames_emitted and not live.interrupted
                         and live.keyframes_stored == c["keyframes"])
    if plot:
        plot_demo_trajectories(out, robot, obs, truth, fused, wheel, err_fused.distance_m,
                               graph[1] if graph is not None else None, wheel_nominal=nominal)
    return summary


def _graph_summary(map_path: Path, robot: VirtualRobot, c: Mapping[str, int],
                   obs: RunObservations) -> tuple[Summary, GraphPlot] | None:
    """The map's loop-corrected keyframe poses against ground truth, beside the keyframes'
    own poses (the wheel + gyro filter's) and (with visual odometry on) floor visual
    odometry alone at the same keyframes (:func:`robotd.evaluation.groundtruth.keyframe_errors`);
    each is also written as a TUM file beside the map, so that evo can compare them all."""
    import numpy as np

    from robotd.app.demo_report import GraphPlot
    from robotd.evaluation.groundtruth import keyframe_errors
    from robotd.io.store import MapStore
    from robotd.io.trajectory import write_tum

    with MapStore.open(map_path, create=False) as store:
        kfs = list(store.keyframes())
        opt = store.optimized_poses()
        loops = [(lk.from_id, lk.to_id) for lk in store.links("loop")]
    if len(kfs) < 2 or not opt:
        return None
    kfs = [k for k in kfs if k.id in opt]
    odometry = np.array([[k.x_m, k.y_m, k.yaw_rad] for k in kfs])  # wheel + gyro (the keyframe stage)
    optimized = np.array([opt[k.id] for k in kfs])
    stamps = np.array([k.stamp_ns for k in kfs], dtype=np.int64)
    truth = robot.motion.pose_at(stamps / 1e9)
    columns = [("odometry", odometry), ("loop_corrected", optimized)]
    visual = obs.visual_poses
    if visual and all(k.id in visual for k in kfs):
        columns.insert(1, ("vo_only", np.array([visual[k.id] for k in kfs])))
    for name, est in columns:
        write_tum(map_path.parent / f"{_GRAPH_TUM[name]}.tum", stamps, est)
    out: Summary = {"keyframes": len(kfs), "loops_in_graph": len(loops),
                    **{k: v for k, v in c.items() if k.startswith(("loops_", "graph_"))},
                    **keyframe_errors(truth, columns)}
    return out, GraphPlot([k.id for k in kfs], optimized, dict(columns).get("vo_only"), loops)


_GRAPH_TUM = {"odometry": "keyframes", "vo_only": "vo_only", "loop_corrected": "corrected"}
"""The TUM file (``OUT/NAME.tum``) of each keyframe trajectory of the summary."""
