"""One place that assembles a daemon from a config, its sources and a clock.

The service (:mod:`robotd.app.service`), replay, the demo (:mod:`robotd.app.demo`) and the
loop-curve training (:mod:`calibration.train`) all build their daemon here, so they run
the same stages with the same parameters and differ only in their sources, their clock,
and the observers they add.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from robotd.app.daemon import Daemon, Source
from robotd.app.notify import Notifier
from robotd.app.pipeline import Pipeline
from robotd.app.stages.floor import FloorDetectorStage
from robotd.app.stages.keyframes import KeyframeStage
from robotd.app.stages.loops_ungated import LoopsUngated
from robotd.app.stages.map_writer import MapWriterStage
from robotd.app.stages.odometry import OdometryStage
from robotd.app.stages.visual_odometry import VisualOdometryStage
from robotd.base.clock import Clock
from robotd.base.config import Config
from robotd.base.configfile import to_toml
from robotd.base.messages import DescribedKeyframe, Keyframe, MeasuredKeyframe
from robotd.floor.detector import FloorDetectorParams, FloorLoopDetector
from robotd.forward.planar import PlanarLoopParams
from robotd.io.calibfile import CalibrationFile, OdometryModel
from robotd.io.store import MapStore
from robotd.odometry.ekf import EkfParams
from robotd.odometry.fusion import OdometryFilter
from robotd.odometry.kinematics import DiffDriveParams

if TYPE_CHECKING:
    from robotd.forward.features import FeatureKind

log = logging.getLogger(__name__)


#: Gyro readings a second from the base (the Kobuki driver's one mean rate per 50 Hz
#: feedback packet): the rate at which ``robotd calibrate odometry`` measured the gyro's
#: noise density, whose reading's 1-sigma is ``density * sqrt(rate / 2)``
#: (:func:`robotd.odometry.calibration.fit_odometry`).
GYRO_READINGS_HZ = 50.0


def build_odometry(cfg: Config, calibration: CalibrationFile | None = None) -> OdometryFilter:
    """The wheel + gyro filter with the config's robot geometry and noise model; with a
    calibrated odometry model (``robotd calibrate odometry``), its wheel radii, wheel base
    and gyro scale instead of the nominal ``[robot]`` values, and its gyro noise density
    as the gyro's reading noise (``gyro_noise_radps``) of the filter whose edges the pose
    graph gets (the wheel + gyro twin when visual odometry is fused; the fused filter keeps
    the config's, as ``docs/calibration.md`` explains). The fitted wheel slip density is
    not used here: the config's wheel noise covers the tick quantisation and slip.
    ``[odometry] noise_model = "calibration"`` gives that filter the calibration's whole
    sensor-level noise model instead (:func:`calibration_noise`: the fitted densities, the
    tick quantisation, each wheel's slip per metre of its own travel and the white
    accelerations fitted by maximum likelihood);
    ``"calibration_fused"`` gives it to the fused filter too. Without a calibration's
    odometry model both keep the config's (logged)."""
    params = EkfParams.from_config(cfg.odometry)
    drive = DiffDriveParams.from_config(cfg.robot)
    gyro_scale = 1.0
    edge_params = params  # the noise model of the filter whose edges the graph gets
    model = calibration.odometry if calibration is not None else None
    if model is not None:
        drive = DiffDriveParams.from_config(cfg.robot, wheel_base_m=model.wheel_base_m,
                                            wheel_radius_left_m=model.wheel_radius_left_m,
                                            wheel_radius_right_m=model.wheel_radius_right_m)
        gyro_scale = model.gyro_scale
        if model.gyro_noise_radps_sqrt_hz > 0.0:
            edge_params = dataclasses.replace(params, gyro_noise_radps=model.gyro_noise_radps_sqrt_hz
                                              * math.sqrt(GYRO_READINGS_HZ / 2.0))
        log.info("odometry model from the calibration: wheel radii %.5f / %.5f m, wheel base %.4f m, "
                 "gyro scale %.5f, gyro noise %.5f rad/s per reading (the graph's edges)",
                 model.wheel_radius_left_m, model.wheel_radius_right_m, model.wheel_base_m,
                 model.gyro_scale, edge_params.gyro_noise_radps)
    v = cfg.visual_odometry
    # Fusing visual odometry: the graph's edges come from a wheel + gyro twin (fusion.py).
    twin = v.enabled and v.role == "fused" and cfg.floor_camera.source != "none"
    if cfg.odometry.noise_model != "config" and model is not None:
        edge_params = calibration_noise(params, model, cfg.robot.ticks_per_rev, cfg.odometry.slip_gate_sigma)
        if cfg.odometry.noise_model == "calibration_fused" or not twin:
            params = edge_params
        log.info("noise model from the calibration (%s): white accelerations %.4f m/s^2 and %.4f rad/s^2 "
                 "per sqrt(Hz), wheel speed noise %.5f m/s, each wheel's slip %.3f mm per sqrt(m), gyro %.5f "
                 "rad/s per reading", cfg.odometry.noise_model, edge_params.accel_noise_density_mps2_per_sqrt_hz,
                 edge_params.angular_accel_noise_density_radps2_per_sqrt_hz, edge_params.wheel_v_noise_mps,
                 1e3 * math.sqrt(edge_params.wheel_slip_var_m2_per_m), edge_params.gyro_noise_radps)
    elif cfg.odometry.noise_model != "config":
        log.warning("[odometry] noise_model = %r but no calibration's odometry model: the [odometry] noise "
                    "model is used", cfg.odometry.noise_model)
    if twin:
        return OdometryFilter(drive, params, vo_twin=True, gyro_scale=gyro_scale, twin_params=edge_params,
                              live_pose=v.live_pose)
    return OdometryFilter(drive, edge_params, gyro_scale=gyro_scale)


def calibration_noise(params: EkfParams, model: OdometryModel, ticks_per_rev: float,
                      slip_gate_sigma: float = 0.0) -> EkfParams:
    """``params`` with the calibration's noise model (``[odometry] noise_model =
    "calibration"``): the sensors' fitted densities (:func:`robotd.odometry.calibration.sensor_noise_params`)
    and the white accelerations fitted by maximum likelihood; with ``slip_gate_sigma`` > 0
    (``[odometry] slip_gate_sigma``) the wheel slip test, over the calibrated wheel base,
    and the calibration's slip events (their fitted rate and duration) unless ``params``
    has a rate of its own (``[odometry] slip_event_rate_hz`` above 0: the config's rate and
    duration instead). A calibration written before they were fitted keeps ``params``'
    accelerations (logged) and has no slip events."""
    from robotd.odometry.calibration import sensor_noise_params

    if not model.has_process_noise:
        log.warning("the calibration's odometry model has no white accelerations (written before they "
                    "were fitted; run `robotd calibrate odometry` again): the [odometry] ones are used")
    tick_m = 2.0 * math.pi * 0.5 * (model.wheel_radius_left_m + model.wheel_radius_right_m) / ticks_per_rev
    out = sensor_noise_params(params, model.gyro_noise_radps_sqrt_hz, model.wheel_noise_m_sqrt_m, tick_m,
                              model.accel_noise_mps2_sqrt_hz, model.angular_accel_noise_radps2_sqrt_hz,
                              readings_hz=GYRO_READINGS_HZ, wheel_base_m=model.wheel_base_m,
                              slip_gate_sigma=slip_gate_sigma)
    if (slip_gate_sigma > 0.0 and params.slip_event_rate_hz <= 0.0 and model.slip_event_rate_hz is not None
            and model.slip_event_duration_s is not None):
        out = dataclasses.replace(out, slip_event_rate_hz=model.slip_event_rate_hz,
                                  slip_event_duration_s=model.slip_event_duration_s)
        log.info("slip events from the calibration: %.3f a second of accelerating or turning, %.3f s RMS",
                 model.slip_event_rate_hz, model.slip_event_duration_s)
    return out


def load_calibration(cfg: Config) -> CalibrationFile | None:
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
    overridden = calibration_overrides(calib)
    if overridden:
        log.info("the calibration file %s replaces [floor_camera] %s of the config", path,
                 ", ".join(overridden))
    return calib


def calibration_overrides(calib: CalibrationFile) -> list[str]:
    """The ``[floor_camera]`` keys whose config values the calibration file replaces (its
    intrinsics and its mount; :func:`robotd.io.calibfile.camera_model`)."""
    keys: list[str] = []
    if calib.intrinsics is not None:
        keys += ["fx_px", "fy_px", "cx_px", "cy_px", "distortion"]
    if calib.mount is not None:
        keys += ["mount_height_m", "mount_tilt_deg", "mount_x_m", "mount_y_m", "mount_yaw_deg"]
    return keys


def build_floor_detector(cfg: Config, store: MapStore, calib: CalibrationFile | None = None,
                         ) -> FloorLoopDetector | None:
    """The floor loop detector with its index rebuilt from the map, or None if disabled.

    Loops are declared only with a trained threshold for the configured mode.
    """
    if not cfg.floor_detector.enabled or cfg.floor_camera.source == "none":
        return None
    from robotd.io.calibfile import camera_model

    params = FloorDetectorParams.from_config(cfg.floor_detector)
    mode = params.descriptor_mode
    threshold = calib.loop.for_mode(mode) if calib is not None and calib.loop is not None else None
    if threshold is None:
        log.warning("no trained loop threshold for descriptor mode %d: floor loop candidates are "
                    "found and stored but no loop is declared (train with `robotd calibrate "
                    "loop-curve`)", mode)
    else:
        log.info("floor loops declared at local score >= %.2f (mode %d)", threshold, mode)
    return FloorLoopDetector.from_store(store, params, threshold, camera_model(calib, cfg.floor_camera))


def build_visual_odometry(cfg: Config, odometry: OdometryStage,
                          calib: CalibrationFile | None = None, *,
                          takes: type[Keyframe] = DescribedKeyframe) -> VisualOdometryStage:
    """Floor visual odometry in the floor detector's descriptor mode (the keyframe's
    descriptor is reused), with the calibrated camera model; its steps go to ``odometry``'s
    filter (fused mode) and meet that filter's gate. With ``[pose_graph] odometry_model =
    "bias_scale_window"`` the wheel + gyro edge meets the step with the graph's scale prior
    in its covariance (:func:`scale_prior_sigmas`)."""
    from robotd.floor.vo import FloorVisualOdometry, VoParams
    from robotd.io.calibfile import camera_model

    v = cfg.visual_odometry
    params = VoParams.from_config(v, cfg.floor_detector.descriptor_mode)
    vo = FloorVisualOdometry(camera_model(calib, cfg.floor_camera), params)
    log.info("floor visual odometry on (%s, mode %d)", v.role, params.descriptor_mode)
    g = cfg.pose_graph
    scale = scale_prior_sigmas(cfg, calib) if g.enabled and g.odometry_model == "bias_scale_window" else None
    return VisualOdometryStage(vo, v.role, gate_nis=odometry.vo_gate_nis, takes=takes, scale_sigmas=scale)


def forward_mount(cfg: Config) -> np.ndarray:
    """The forward camera's ``(x_m, y_m, yaw_rad)`` in the robot frame."""
    f = cfg.forward_camera
    return np.array([f.mount_x_m, f.mount_y_m, math.radians(f.mount_yaw_deg)])


def forward_loop_params(cfg: Config) -> PlanarLoopParams:
    """The noise of a forward loop edge, from the config."""
    return PlanarLoopParams.from_config(cfg.forward_detector)


def build_forward_stage(cfg: Config, store: MapStore | None = None) -> Any:
    """The forward loop detector stage (paper 000) with the config's features and camera;
    with ``store``, its memory is kept in the map and taken up from earlier runs."""
    from robotd.app.stages.forward_loops import ForwardLoopStage, RidgeParams
    from dataclasses import replace

    from robotd.forward import FeatureParams, ForwardDetector, method_params
    from robotd.forward.detector import daemon_params

    f, cam = cfg.forward_detector, cfg.forward_camera
    k = np.array([[cam.fx_px, 0.0, cam.cx_px], [0.0, cam.fy_px, cam.cy_px], [0.0, 0.0, 1.0]])
    params = method_params(f.method)
    if f.method == "default":  # the keyframes' fused pose and the graph's gate behind it
        params = daemon_params(params)
    # [forward_detector] features is one of 'auto', 'sift', 'orb' (the config's choices).
    kind = params.features.kind if f.features == "auto" else cast(FeatureKind, f.features)
    n_feat = f.max_features or (params.features.max_features if kind == params.features.kind else 0)
    # The camera's height gives the loops their range on the floor (robotd.forward.verify).
    params = replace(params, features=FeatureParams(kind=kind, max_features=n_feat),
                     verify=replace(params.verify,
                                    camera_height_m=cam.mount_height_m if cam.mount_height_m > 0 else None))
    log.info("forward loop detector on (method %s, %s features, a keyframe every %.2f m or %.0f deg)",
             f.method, kind, f.distance_m, f.rotation_deg)
    return ForwardLoopStage(ForwardDetector(params, camera_matrix=k), distance_m=f.distance_m,
                            rotation_rad=math.radians(f.rotation_deg), sync_tolerance_s=f.sync_tolerance_s,
                            store=store, mount=forward_mount(cfg),
                            ridge=RidgeParams(edge_sigma_yaw_rad=math.radians(f.sigma_yaw_deg)),
                            defer_accept=f.max_deferred_tests > 0, max_deferred=max(1, f.max_deferred_tests),
                            check_budget=f.checks_per_keyframe if f.max_deferred_tests and f.checks_per_keyframe
                            else None)


#: The relative scale errors ``(wheel distance, gyro)`` (1-sigma) of a base run on its
#: nominal ``[robot]`` geometry, without an odometry calibration: a tyre's and a gyro's
#: manufacturing tolerance.
UNCALIBRATED_SCALE_SIGMAS = (0.005, 0.003)

#: Smallest gyro scale sigma of the prior (a calibration may give 0).
_MIN_SCALE_SIGMA = 1e-5


def scale_prior_sigmas(cfg: Config, calibration: CalibrationFile | None = None) -> tuple[float, float]:
    """The prior ``(wheel, gyro)`` 1-sigma relative scale errors of the pose graph's scale
    variable (``[pose_graph] odometry_model = "bias_scale_window"``): the calibration's own
    uncertainty of the mean wheel radius and of the gyro scale (without an odometry
    calibration :data:`UNCALIBRATED_SCALE_SIGMAS`), the wheels' widened by ``[pose_graph]
    scale_wear`` (what load, tyre wear and floor move them by since the calibration) and the
    gyro's by ``[pose_graph] scale_wear_gyro`` (what temperature moves it by)."""
    odo = calibration.odometry if calibration is not None else None
    if odo is None:
        wheel, gyro = UNCALIBRATED_SCALE_SIGMAS
    else:
        wheel = 0.5 * math.hypot(odo.wheel_radius_left_sigma_m / odo.wheel_radius_left_m,
                                 odo.wheel_radius_right_sigma_m / odo.wheel_radius_right_m)
        gyro = odo.gyro_scale_sigma / odo.gyro_scale
    g = cfg.pose_graph
    return math.hypot(wheel, g.scale_wear), max(math.hypot(gyro, g.scale_wear_gyro), _MIN_SCALE_SIGMA)


def build_pipeline(cfg: Config, clock: Clock, store: MapStore, run_id: int, *, lossless: bool,
                   calibration: CalibrationFile | None = None, observers: Sequence[Any] = (),
                   floor_detector: bool = True, pose_graph: bool = True) -> Pipeline:
    """The daemon's stages in their order (see :mod:`robotd.app.pipeline`), then
    ``observers`` (stages that only watch: trajectory writers, recorders, training)."""
    kf = cfg.keyframes
    pipeline = Pipeline()
    odometry = build_odometry(cfg, calibration) if cfg.base.driver != "none" else None
    odometry_stage = pipeline.add(OdometryStage(odometry)) if odometry is not None else None
    pipeline.add(KeyframeStage(odometry_stage.keyframe_odometry() if odometry_stage is not None else None,
                               clock, distance_m=kf.distance_m, rotation_rad=math.radians(kf.rotation_deg),
                               max_sync_wait_s=kf.max_sync_wait_s, lossless=lossless,
                               bias_terms=(cfg.pose_graph.enabled and pose_graph
                                           and cfg.pose_graph.odometry_model != "independent")),
                 reads={"odometry": "KeyframeOdometry"} if odometry_stage is not None else None)
    mapped_ground = None
    if cfg.pose_graph.enabled and pose_graph:
        from robotd.app.stages.pose_graph import PoseGraphStage
        from robotd.graph.incremental import IncrementalGraph, IncrementalParams
        from robotd.graph.mappedground import MappedGroundParams

        g = cfg.pose_graph
        graph_stage = pipeline.add(PoseGraphStage(
            IncrementalGraph(IncrementalParams(odometry_model=g.odometry_model,
                                               scale_sigmas=scale_prior_sigmas(cfg, calibration))), store, gate_chi2=g.gate_chi2, save_every=g.full_solve_every_keyframes,
            forward_mount=forward_mount(cfg), forward_params=forward_loop_params(cfg),
            mapped_ground=MappedGroundParams(g.mapped_radius_m, g.max_unlocalised_m) if g.localise_mapped else None))
        mapped_ground = graph_stage.mapped_ground  # owned by the graph stage; the writer's interface
    else:
        pipeline.add(LoopsUngated())
    if cfg.forward_detector.enabled:
        pipeline.add(build_forward_stage(cfg, store))
    # Each keyframe message type is made by one stage and read by the next (robotd.app.pipeline).
    last: type[Keyframe] = Keyframe
    detector = build_floor_detector(cfg, store, calibration) if floor_detector else None
    if detector is not None:
        pipeline.add(FloorDetectorStage(detector))
        last = DescribedKeyframe
    if cfg.visual_odometry.enabled and cfg.floor_camera.source != "none" and odometry_stage is not None:
        pipeline.add(build_visual_odometry(cfg, odometry_stage, calibration, takes=last))
        last = MeasuredKeyframe
    pipeline.add(MapWriterStage(store, run_id, image_width_px=kf.image_width_px, takes=last,
                                chain=mapped_ground),
                 reads={"graph": "KeyframeChain"} if mapped_ground is not None else None)
    pipeline.check()
    for o in observers:
        pipeline.add(o)
    return pipeline


def assemble_daemon(cfg: Config, clock: Clock, sources: dict[str, Source], store: MapStore,
                    notifier: Notifier, *, lossless: bool, observers: Sequence[Any] = (),
                    calibration: CalibrationFile | None = None,
                    load_calibration_file: bool = True, floor_detector: bool = True,
                    pose_graph: bool = True,
                    driver_stats: Callable[[], dict[str, Any]] | None = None) -> Daemon:
    """A daemon over ``sources`` writing into ``store``: begins a run in the map, builds the
    pipeline from ``cfg`` and returns the daemon, ready to :meth:`~Daemon.run`. Runs in the
    map that never ended (the daemon was killed) are first marked as such, with a warning.

    ``calibration``: the calibration file's contents (default: loaded from the path the
    config names, when ``load_calibration_file``). ``lossless``: queues block instead of
    dropping, and frames wait for their odometry as long as it takes (replay, simulation).
    """
    if calibration is None and load_calibration_file:
        calibration = load_calibration(cfg)
    # ROS 2 and Foxglove outputs ([ros2], [foxglove]): built first, so a missing package
    # is an error before a run begins in the map.
    from robotd.app.outputs import build_output_stage

    outputs = build_output_stage(cfg, clock)
    try:
        for run, keyframes in store.mark_unfinished_runs():
            log.warning("map %s: run %d did not end cleanly (killed or power cut?); its %d keyframes are "
                        "kept and it is marked as ended at its last one", store.path, run.id, keyframes)
        run_id = store.begin_run(to_toml(cfg))
        pipeline = build_pipeline(cfg, clock, store, run_id, lossless=lossless, calibration=calibration,
                                  observers=observers, floor_detector=floor_detector,
                                  pose_graph=pose_graph)
    except BaseException:
        if outputs is not None:  # the sockets and the server thread, when the run never starts
            outputs.close()
        raise
    sizes = {"base": cfg.base.queue_size, "floor": cfg.floor_camera.queue_size,
             "forward": cfg.floor_camera.queue_size}
    if outputs is not None:
        pipeline.add(outputs)
    # Python's garbage collections timed (counters gc_*, the forward stage's gc part); with
    # [daemon] gc_freeze, the objects of the start-up and the map's load frozen out of them;
    # [daemon] gc_full_between_messages, the full collections run by the watch between messages.
    from robotd.app import gcwatch

    watch = pipeline.add(gcwatch.GcWatch().install())
    if cfg.daemon.gc_freeze:
        watch.freeze()
    if cfg.daemon.gc_full_between_messages:
        watch.defer_full()
    daemon = Daemon(clock, pipeline, sources, notifier, store=store, run_id=run_id, lossless=lossless,
                    status_interval_s=cfg.daemon.status_interval_s, queue_sizes=sizes,
                    driver_stats=driver_stats)
    if outputs is not None:
        outputs.bind(lambda: {n: q.dropped for n, q in daemon.queues.items()}, daemon.driver_stats)
    return daemon


def open_map(cfg: Config, clock: Clock | None = None) -> MapStore:
    """The map store the config names, with the config's keyframe image quality."""
    return MapStore.open(cfg.map.path, jpeg_quality=cfg.keyframes.jpeg_quality, clock=clock)


def data_flow_diagram() -> str:
    """The daemon's data flow as a Mermaid flowchart, drawn from the registrations of a
    pipeline with every optional stage on (a base, the pose graph with localisation over
    mapped ground, the forward camera, the floor detector, fused visual odometry), built
    over a scratch map (:meth:`robotd.app.pipeline.Pipeline.mermaid`). docs/concepts.md
    holds it (``tools/dataflow_doc.py`` writes it; a test keeps the two equal)."""
    import tempfile

    from robotd.base.clock import ManualClock
    from robotd.base.config import replace

    cfg = replace(Config(), "base", driver="kobuki")
    cfg = replace(cfg, "forward_detector", enabled=True)
    cfg = replace(cfg, "pose_graph", localise_mapped=True)
    cfg = replace(cfg, "visual_odometry", enabled=True, role="fused")
    with tempfile.TemporaryDirectory() as tmp:
        cfg = replace(cfg, "calibration", path=str(Path(tmp) / "none.yml"))
        with MapStore.open(Path(tmp) / "map.sqlite") as store:
            run = store.begin_run("")
            return build_pipeline(cfg, ManualClock(), store, run, lossless=True).mermaid()
