"""The one configuration file: TOML read into frozen dataclasses.

Every section is a frozen dataclass whose fields carry their unit in the name and their
valid range in ``metadata``. Unknown sections, unknown keys, wrong types and out-of-range
values are :class:`~robotd.base.errors.ConfigError` naming the key (``[floor_camera] fps``).
There is exactly one source of configuration: the file (or the defaults when a key is
absent). Environment variables change nothing. Reading and writing the file, the keys of
earlier versions and the commented default are in :mod:`robotd.base.configfile`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from robotd.base.errors import ConfigError



def _f(default: Any, doc: str, *, lo: float | None = None, hi: float | None = None,
       choices: tuple[str, ...] | None = None, length: int | None = None,
       nonempty: bool = False, live: bool = False, unit: str | None = None) -> Any:
    """A config field with its documentation and validity constraints.

    ``nonempty``: a string that must not be empty or blank, such as a file path.
    ``live``: ``systemctl reload robotd`` (SIGHUP) applies a change at once (the reload
    table of :mod:`robotd.app.reload` is checked against these). ``unit``: the unit when
    the key's name does not end in one of :data:`UNIT_SUFFIXES` (``""``: unitless).
    """
    meta = {"doc": doc, "lo": lo, "hi": hi, "choices": choices, "length": length,
            "nonempty": nonempty, "live": live, "unit": unit}
    if isinstance(default, (list, tuple)):
        return field(default=tuple(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class RobotConfig:
    """Differential-drive geometry (Kobuki / TurtleBot 2 defaults); ``robotd calibrate
    odometry`` measures this robot's wheel radii and wheel base into the calibration
    file, which then replaces them."""

    wheel_radius_m: float = _f(0.035, "wheel radius", lo=0.005, hi=1.0)
    wheel_base_m: float = _f(0.23, "distance between the wheel contact points", lo=0.02, hi=5.0)
    ticks_per_rev: float = _f(2578.33, "encoder ticks per wheel turn", lo=1.0, hi=1e7, unit="ticks")


@dataclass(frozen=True)
class BaseConfig:
    """The mobile base: wheel encoders and gyro."""

    driver: str = _f("kobuki", "base driver ('can': the [can] section; 'ros2': nav_msgs/Odometry "
                     "and sensor_msgs/Imu from the [ros2] input topics)",
                     choices=("kobuki", "can", "ros2", "none"))
    port: str = _f("/dev/kobuki", "serial port: a device path (the udev rule of systemd/ names the "
                   "Kobuki /dev/kobuki) or any pyserial URL, e.g. spy:///dev/kobuki?file=/tmp/k.txt "
                   "to log the traffic", nonempty=True)
    baudrate: int = _f(115200, "serial baud rate", lo=1200, hi=4_000_000, unit="baud")
    yaw_source: str = _f("raw_gyro", "which gyro reading feeds the filter: the Kobuki's raw gyro "
                         "(sub-payload 13, ~100 Hz, 0.00875 deg/s) or its inertial heading rate "
                         "(sub-payload 4)",
                         choices=("raw_gyro", "inertial"))
    queue_size: int = _f(512, "samples buffered between the driver thread and the pipeline (drops "
                         "are counted)",
                         lo=1, hi=1_000_000)


@dataclass(frozen=True)
class CanConfig:
    """A base on a CAN bus (``[base] driver = "can"``): python-can for the bus, a DBC file
    for the frames, and which decoded signals are the wheels and the gyro.

    A signal is ``"Message.Signal"`` of the DBC. A wheel signal in a unit of angle or
    distance is a position (cumulative), one per second a speed (integrated by the
    driver). ``left_scale``/``right_scale`` multiply the decoded value first: -1 for a
    mirrored motor, 1/N for a gearbox of ratio N when the signal is motor turns. The
    geometry is ``[robot]``'s.

    On the robot, bring the interface up first (it survives bus-off by itself): ``ip link
    set can0 type can bitrate 500000 restart-ms 100 && ip link set can0 up``. An ODrive
    per wheel (CANSimple), motors mirrored, 1:1: ``dbc = "odrive_cansimple"``, ``left =
    "Left_Encoder_Estimates.Pos_Estimate"``, ``right =
    "Right_Encoder_Estimates.Pos_Estimate"``, ``wheel_unit = "turn"``, ``left_scale =
    -1.0``, ``yaw = ""``."""

    interface: str = _f("socketcan", "python-can interface ('socketcan' on the robot, 'virtual' in tests)")
    channel: str = _f("can0", "python-can channel (the socketcan network interface)")
    dbc: str = _f("diff_drive", "a DBC shipped with robotd ('diff_drive': wheel angles in one frame, "
                  "the yaw gyro in another; 'odrive_cansimple': one ODrive per wheel, node 0 left, "
                  "node 1 right) or a .dbc path")
    left: str = _f("Base_Wheels.Left_Wheel_Pos", "left wheel signal, Message.Signal")
    right: str = _f("Base_Wheels.Right_Wheel_Pos", "right wheel signal, Message.Signal")
    wheel_unit: str = _f("rad", "unit of the wheel signals (per second: a speed)",
                         choices=("turn", "rad", "deg", "m", "turn/s", "rad/s", "deg/s", "m/s", "rpm"))
    left_scale: float = _f(1.0, "multiplies the left signal (-1: mirrored; 1/N: gear ratio N)", lo=-1e6, hi=1e6)
    right_scale: float = _f(1.0, "multiplies the right signal (-1: mirrored; 1/N: gear ratio N)", lo=-1e6, hi=1e6)
    yaw: str = _f("Base_Gyro.Yaw_Rate", "yaw-rate signal, Message.Signal, counter-clockwise positive "
                  "after yaw_scale ('': no gyro, wheel-only odometry)")
    yaw_unit: str = _f("deg/s", "unit of the yaw-rate signal", choices=("rad/s", "deg/s"))
    yaw_scale: float = _f(1.0, "multiplies the yaw signal (-1: clockwise positive)", lo=-1e6, hi=1e6)
    period_s: float = _f(0.02, "the wheel frames' nominal period", lo=1e-4, hi=10.0)
    stale_periods: int = _f(5, "a wheel (or the bus) silent this many periods is stale: counted, "
                            "logged once, and the odometry is marked degraded in STATUS until it "
                            "speaks again", lo=1, hi=100_000)
    max_frames_per_read: int = _f(2000, "frames taken per read; more waiting is a flood (counted)",
                                  lo=1, hi=1_000_000)


@dataclass(frozen=True)
class FloorCameraConfig:
    """The downward-facing floor camera: device, intrinsics and mounting. The calibration
    file's intrinsics and mount (``robotd calibrate intrinsics`` / ``floor-mount``), when
    it has them, replace the ones here (logged at start-up)."""

    source: str = _f("v4l2", "camera source: 'v4l2' the device below, 'depthai' a Luxonis OAK "
                     "camera (the depthai_* keys), 'ros2' the [ros2] floor_camera_topic, 'none' "
                     "odometry only. A camera that vanishes is reopened with backoff (0.5 s, "
                     "doubling up to 8 s) while odometry runs on; the time without frames shows "
                     "in STATUS", choices=("v4l2", "depthai", "none", "ros2"))
    device: str = _f("/dev/video0", "V4L2 device path")
    fourcc: str = _f("YUYV", "pixel format requested from the driver", choices=("YUYV", "MJPG", "GREY"))
    width_px: int = _f(640, "image width", lo=16, hi=8192)
    height_px: int = _f(480, "image height", lo=16, hi=8192)
    fps: float = _f(30.0, "frame rate", lo=0.1, hi=1000.0, unit="Hz")
    buffer_size: int = _f(2, "driver-side frame buffers (small = low latency; DepthAI: the host "
                          "queue's length)", lo=1, hi=32, unit="frames")
    queue_size: int = _f(8, "frames buffered between the camera thread and the pipeline (drops are "
                         "counted)", lo=1, hi=10_000, unit="frames")
    fx_px: float = _f(400.0, "focal length x", lo=1.0, hi=1e5)
    fy_px: float = _f(400.0, "focal length y", lo=1.0, hi=1e5)
    cx_px: float = _f(319.5, "principal point x", lo=-1e5, hi=1e5)
    cy_px: float = _f(239.5, "principal point y", lo=-1e5, hi=1e5)
    distortion: tuple[float, ...] = _f((-0.05, 0.0, 0.0, 0.0, 0.0), "OpenCV k1 k2 p1 p2 k3", length=5)
    mount_height_m: float = _f(0.40, "lens height above the floor", lo=0.01, hi=5.0)
    mount_tilt_deg: float = _f(0.0, "pitch away from straight down, towards forward", lo=-60.0, hi=60.0)
    mount_x_m: float = _f(0.0, "camera position in the robot frame, forward", lo=-2.0, hi=2.0)
    mount_y_m: float = _f(0.0, "camera position in the robot frame, left", lo=-2.0, hi=2.0)
    mount_yaw_deg: float = _f(0.0, "image rotation about the optical axis", lo=-180.0, hi=180.0)
    # DepthAI (source = "depthai"): width_px, height_px and fps as above, buffer_size is
    # the host queue's length in frames.
    depthai_device: str = _f("", "DepthAI device id (e.g. 14442C10D13EABCE00), IP address or USB name "
                             "('' = the first found)")
    depthai_socket: str = _f("CAM_A", "board socket of the camera (OAK-D: CAM_A colour, CAM_B/CAM_C mono)",
                             choices=("CAM_A", "CAM_B", "CAM_C", "CAM_D", "CAM_E", "CAM_F", "CAM_G", "CAM_H"))
    colour: bool = _f(False, "DepthAI: request colour (NV12) instead of mono (GRAY8); the floor "
                      "camera is converted to grey either way")
    depthai_reconnection_attempts: int = _f(3, "times depthai reconnects a lost device itself before "
                                            "the driver reopens it with backoff", lo=0, hi=1000)


@dataclass(frozen=True)
class OdometryConfig:
    """Noise model of the wheel + gyro extended Kalman filter: the process noises are
    spectral densities (the variance they add grows with the time step), the
    measurement noises 1-sigma per reading."""

    accel_noise_density_mps2_per_sqrt_hz: float = _f(
        0.5, "process noise: white linear acceleration driving the speed (the speed's "
        "variance grows by its square times the time step)", lo=1e-6, hi=100.0)
    angular_accel_noise_density_radps2_per_sqrt_hz: float = _f(
        0.3, "process noise: white angular acceleration driving the yaw rate", lo=1e-6, hi=1000.0)
    gyro_bias_walk_radps_per_sqrt_s: float = _f(2e-5, "gyro bias random walk (the bias's variance "
                                                "grows by its square times the time step)",
                                                lo=0.0, hi=1.0)
    wheel_v_noise_mps: float = _f(0.01, "1-sigma wheel speed noise at standstill", lo=1e-6, hi=10.0)
    wheel_v_noise_frac: float = _f(0.02, "wheel speed noise growing with speed (slip), a fraction "
                                   "of the speed", lo=0.0, hi=1.0)
    wheel_w_noise_radps: float = _f(0.05, "1-sigma wheel yaw-rate noise", lo=1e-6, hi=10.0)
    wheel_w_noise_frac: float = _f(0.05, "wheel yaw-rate noise growing with turn rate, a fraction of "
                                   "the turn rate", lo=0.0, hi=1.0)
    wheel_w_noise_per_mps: float = _f(0.5, "wheel yaw-rate noise growing with speed (unequal wheel "
                                      "diameters turn a straight run), rad/s per m/s",
                                      lo=0.0, hi=100.0, unit="rad/s per m/s")
    gyro_noise_radps: float = _f(0.003, "1-sigma white noise of one gyro reading", lo=1e-7, hi=10.0)
    initial_gyro_bias_sigma_radps: float = _f(0.01, "1-sigma prior on the gyro bias", lo=1e-7, hi=10.0)
    noise_model: str = _f("config", "which noise model the filters use: 'config' (this table's), "
                          "'calibration' (the graph's wheel + gyro edges take the calibration's fitted "
                          "sensor noise and white accelerations; the fused pose keeps this table's) or "
                          "'calibration_fused' (the fused filter too); without a calibration's odometry "
                          "model this table's (docs/odometry.md)",
                          choices=("config", "calibration", "calibration_fused"))
    slip_gate_sigma: float = _f(0.0, "with the calibration's noise model: a moving wheel reading whose yaw "
                                "rate disagrees with the gyro's by more than this many sigma is taken as "
                                "wheel slip and its speed and yaw-rate variances widened; 0 turns the test "
                                "off (docs/odometry.md)", lo=0.0, hi=100.0)
    wheel_increments: bool = _f(False, "the wheel + gyro filter whose edges the pose graph gets advances its "
                                "pose by the distance and heading change each wheel reading's ticks measured "
                                "over their packet (an integrated measurement) instead of taking them as the "
                                "rates at the reading, which trail the truth where the speed changes "
                                "(docs/odometry.md)")
    wheel_rounding: bool = _f(False, "with wheel_increments: the ticks' quantisation as the rounding of each "
                              "count, carried from one wheel reading to the next (it enters two neighbouring "
                              "readings with opposite signs and does not add up over many), instead of white "
                              "noise per reading (docs/odometry.md)")
    slip_event_rate_hz: float = _f(0.0, "with the slip test: wheel slip events (a wheel over- or under-rotating "
                                   "for a while) a second while the base accelerates or turns; the ones the test "
                                   "lets through widen those wheel readings' speed variance by what their bounded "
                                   "slip adds, and one it sees widens its reading as part of an event; 0: the "
                                   "calibration's fitted rate and duration (noise_model 'calibration') when it "
                                   "holds them, else none; above 0: this rate and slip_event_duration_s instead "
                                   "(docs/odometry.md)", lo=0.0, hi=100.0)
    slip_event_duration_s: float = _f(0.2, "with slip_event_rate_hz above 0: the slip events' RMS duration",
                                      lo=0.0, hi=10.0)
    edge_floor_m: float = _f(1e-4, "floor on the 1-sigma of an odometry edge's position (the pose graph's "
                             "conditioning; docs/odometry.md)", lo=1e-7, hi=0.01)


@dataclass(frozen=True)
class KeyframeConfig:
    """When a floor frame becomes a keyframe, and what of it is stored. 0.15 m is a third
    of the floor camera's footprint: closer keyframes cost more CPU per metre for more loop
    edges, farther ones save CPU for fewer (the trade-off measured: docs/performance.md,
    "Keyframe spacing and mapped-ground localisation")."""

    distance_m: float = _f(0.15, "distance travelled since the last keyframe", lo=0.001, hi=100.0,
                           live=True)
    rotation_deg: float = _f(10.0, "rotation since the last keyframe", lo=0.1, hi=360.0, live=True)
    image_width_px: int = _f(160, "width of the stored downsampled grey JPEG image (0 = none)", lo=0, hi=8192)
    jpeg_quality: int = _f(85, "JPEG quality of the stored image", lo=1, hi=100)
    max_sync_wait_s: float = _f(0.5, "how long a frame waits for odometry at its stamp, then is "
                                "dropped (counted)", lo=0.0, hi=60.0)


@dataclass(frozen=True)
class FloorDetectorConfig:
    """Compact floor descriptors of every keyframe and the map query (paper 003): each
    keyframe's floor image gets a descriptor with a hard byte budget, stored in the map;
    each new keyframe queries the map for earlier look-alikes: a global shortlist, then
    local matching with a geometric check on the shortlist only."""

    enabled: bool = _f(True, "describe keyframes and query the map for look-alikes")
    descriptor_mode: int = _f(4, "descriptor mode of paper 003, the byte budget of a keyframe's "
                              "descriptor: 1..6 = at most 512 B, 1, 2, 4, 8, 16 kB per image (floor "
                              "visual odometry reuses it; a trained loop threshold is per mode)",
                              lo=1, hi=6, unit="")
    candidates: int = _f(5, "candidates returned per query; a query stops once this many reach the loop threshold "
                         "(each checked geometrically): over ground driven again and again 2 takes about 0.5-0.6 of "
                         "the query's time for fewer loop edges (docs/performance.md)", lo=1, hi=100, live=True, unit="")
    shortlist: int = _f(10, "keyframes scored locally per query (after the global shortlist)",
                        lo=1, hi=100_000, live=True, unit="")
    exclude_recent_s: float = _f(20.0, "keyframes younger than this are not candidates", lo=0.0, hi=1e6,
                                 live=True)
    ransac_confidence: float = _f(0.99, "the floor query's geometric check stops RANSAC once the best inlier "
                                  "fraction so far says this confidence is reached (a true loop after its first "
                                  "ten draws; docs/performance.md); 0: every hypothesis scored", lo=0.0,
                                  hi=0.999999, unit="")


@dataclass(frozen=True)
class VisualOdometryConfig:
    """Floor visual odometry between consecutive keyframes (paper 003, Sec. IV-D): the
    matched keypoints of consecutive keyframes, mapped to the floor with the camera
    calibration, give the rigid motion (RANSAC, then a least-squares fit) with a
    covariance from the residuals. The
    descriptor mode is ``[floor_detector] descriptor_mode`` (the keyframe's descriptor is
    reused)."""

    enabled: bool = _f(True, "estimate the motion between consecutive keyframes from the floor camera")
    role: str = _f("fused", "'fused': a measurement in the wheel + gyro filter; 'vision_only': the "
                   "chained steps are the odometry (no wheels; failed steps take the wheel + gyro "
                   "increment when there is one)", choices=("fused", "vision_only"))
    live_pose: str = _f("fused", "with role 'fused', the live odometry pose: 'fused' (the filter's: wheels, "
                        "gyro and each step) or 'combined_edges' (the graph's wheel + gyro edges combined "
                        "with the steps, chained without loops, then the wheel + gyro motion since the "
                        "last keyframe; docs/odometry.md)", choices=("fused", "combined_edges"))
    min_inliers: int = _f(8, "fewest metric inliers of a usable step", lo=3, hi=10_000)
    ransac_threshold_m: float = _f(0.003, "RANSAC inlier distance on the floor", lo=1e-5, hi=0.1)
    keypoint_positions: str = _f("detected", "the points of the metric fit: 'detected' (where the keypoint "
                                 "detector found them, sub-pixel, kept beside the keyframe's descriptor) or "
                                 "'coded' (the descriptor's coordinate grid, as paper 003 reuses the stored "
                                 "descriptor; docs/odometry.md)", choices=("detected", "coded"))


@dataclass(frozen=True)
class PoseGraphConfig:
    """The live pose graph (GTSAM iSAM2): every keyframe with its odometry edge, and each
    loop candidate that passes a chi-square gate against the graph's own prediction; the
    optimised poses are stored in the map beside the odometry poses."""

    enabled: bool = _f(True, "keep a pose graph and store the loop-corrected poses in the map")
    gate_chi2: float = _f(16.27, "largest Mahalanobis distance squared of a loop against the graph's "
                          "prediction (16.27: 99.9 % of chi-square with 3 degrees of freedom)",
                          lo=0.1, hi=1e6, live=True, unit="")
    full_solve_every_keyframes: int = _f(200, "re-solve the whole graph robustly (LAGO, "
                                         "DCS-weighted Levenberg-Marquardt, then graduated non-convexity) "
                                         "and store the optimised "
                                         "poses every this many keyframes (0: only at the end of a run)",
                                         lo=0, hi=1_000_000, live=True, unit="keyframes")
    localise_mapped: bool = _f(False, "over ground the map already holds, once a loop is accepted, "
                               "keyframes only re-localise the robot and are not stored: the map and "
                               "the graph grow with the area covered, not the distance driven (on "
                               "in the service's config, for a robot that drives the same rooms for "
                               "weeks; off by default: the demo and the paper's experiment keep every "
                               "keyframe)")
    mapped_radius_m: float = _f(0.15, "a keyframe this close to a stored one (by the graph's estimate) "
                                "is on mapped ground", lo=0.001, hi=100.0)
    max_unlocalised_m: float = _f(1.0, "on mapped ground, travel this far without an accepted match "
                                  "and the robot stores keyframes again", lo=0.01, hi=1000.0)
    odometry_model: str = _f("independent", "what the odometry edges share: 'independent' (each edge its "
                             "own covariance) or 'bias_window' (the wheel + gyro edges share the gyro "
                             "bias: one factor per 10 edges with a bias variable, the windows chained; "
                             "docs/concepts.md) or 'bias_scale_window' (the same windows also sharing "
                             "one variable of the wheels' distance scale and the gyro scale errors, with "
                             "a prior of the calibration's uncertainty and scale_wear; docs/odometry.md)",
                             choices=("independent", "bias_window", "bias_scale_window"))
    scale_wear: float = _f(0.003, "with odometry_model 'bias_scale_window': how far (1-sigma, a "
                           "fraction) the wheels' distance scale may have moved from the calibration "
                           "with load, tyre wear and floor; added to the calibration's own uncertainty "
                           "in the scale variable's prior (0.003: 0.3 %)", lo=1e-6, hi=0.5, unit="")
    scale_wear_gyro: float = _f(0.002, "with odometry_model 'bias_scale_window': how far (1-sigma, a "
                                "fraction) the gyro's scale may have moved from the calibration with "
                                "temperature (MEMS gyro datasheets give about 0.02-0.03 % per kelvin; "
                                "0.002: 0.2 %, about 10 K from the calibration's); added to the "
                                "calibration's own uncertainty in the scale variable's prior",
                                lo=1e-6, hi=0.5, unit="")


@dataclass(frozen=True)
class ForwardDetectorConfig:
    """The forward camera's Bayesian loop detector (paper 000) on forward keyframes; its
    verified loops enter the pose graph with the range measured on the floor where the
    camera sees it ([forward_camera] mount_height_m), else the range the keyframes' poses
    predict.
    The camera itself (device, size, intrinsics, mount) is ``[forward_camera]``."""

    enabled: bool = _f(False, "run the forward loop detector (needs a forward camera source)")
    method: str = _f("default", "the detector: 'default' (binary ORB features, an incremental Hamming "
                     "vocabulary with purging, the levers docs/forward.md measures) or 'paper' (paper "
                     "000 as written: SIFT, 0.8 on a neighbourhood's posterior; the reference)",
                     choices=("default", "paper"))
    features: str = _f("auto", "local features: 'auto' (the method's: ORB for 'default', SIFT for "
                       "'paper'), 'sift' or 'orb'", choices=("auto", "sift", "orb"))
    max_features: int = _f(0, "strongest keypoints kept per image (0: the method's: 300 ORB, all SIFT)",
                           lo=0, hi=100_000, unit="")
    distance_m: float = _f(0.5, "a forward keyframe every this far travelled", lo=0.01, hi=100.0)
    rotation_deg: float = _f(20.0, "or every this much turned", lo=0.1, hi=360.0)
    sync_tolerance_s: float = _f(0.04, "largest offset of the forward frame from its floor keyframe",
                                 lo=0.0, hi=1.0)
    sigma_bearing_deg: float = _f(2.0, "1-sigma of a loop's translation direction", lo=0.01, hi=90.0)
    sigma_yaw_deg: float = _f(1.0, "1-sigma of a loop's heading change", lo=0.01, hi=90.0)
    max_deferred_tests: int = _f(4, "verified views whose level test (the planar scan, the ridge's fits) "
                                 "may wait for a later forward keyframe that verifies nothing, one per "
                                 "keyframe, to keep a keyframe's CPU bounded; with checks_per_keyframe, images "
                                 "whose verification (checks and tests) may wait, more finishing the oldest at "
                                 "once; their loops reach the pose graph that much later (0: every test in its "
                                 "own keyframe)",
                                 lo=0, hi=64, unit="")
    checks_per_keyframe: int = _f(0, "a budget of epipolar checks per forward keyframe for the images' "
                                  "verifications, the waiting ones first, a level test counting as one, the "
                                  "rest waiting for the next keyframes (measured, not the default: docs/forward.md); "
                                  "0: none, each image's checks in its own keyframe; needs max_deferred_tests > 0",
                                  lo=0, hi=16, unit="")


@dataclass(frozen=True)
class ForwardCameraConfig:
    """The forward camera: its device for `robotd run` (opened only when
    ``[forward_detector]`` is enabled; frames are converted to grey), its image size and
    pinhole intrinsics, and its mount (a level optical axis; the defaults are the virtual
    robot's forward camera, ``robotd demo --forward``)."""

    source: str = _f("none", "camera source of the forward camera ('none': no forward camera; "
                     "'ros2': the [ros2] forward_camera_topic)",
                     choices=("v4l2", "depthai", "none", "ros2"))
    device: str = _f("/dev/video1", "V4L2 device path")
    fourcc: str = _f("YUYV", "pixel format requested from the driver", choices=("YUYV", "MJPG", "GREY"))
    width_px: int = _f(640, "image width", lo=16, hi=8192)
    height_px: int = _f(480, "image height", lo=16, hi=8192)
    fps: float = _f(15.0, "frame rate (the detector takes a keyframe every few frames)", lo=0.1, hi=1000.0,
                    unit="Hz")
    buffer_size: int = _f(2, "driver-side frame buffers (small = low latency)", lo=1, hi=32, unit="frames")
    fx_px: float = _f(525.0, "focal length x", lo=1.0, hi=1e5)
    fy_px: float = _f(525.0, "focal length y", lo=1.0, hi=1e5)
    cx_px: float = _f(319.5, "principal point x", lo=-1e5, hi=1e5)
    cy_px: float = _f(239.5, "principal point y", lo=-1e5, hi=1e5)
    mount_x_m: float = _f(0.1, "camera position in the robot frame, forward", lo=-2.0, hi=2.0)
    mount_y_m: float = _f(0.0, "camera position in the robot frame, left", lo=-2.0, hi=2.0)
    mount_yaw_deg: float = _f(0.0, "camera heading in the robot frame", lo=-180.0, hi=180.0)
    mount_height_m: float = _f(0.6, "lens height above the floor (level optical axis); the range of "
                               "a forward loop is measured on the floor from it (0: unknown, the "
                               "pose graph's prediction instead)", lo=0.0, hi=5.0)
    depthai_device: str = _f("", "DepthAI device id, IP address or USB name ('' = the first found)")
    depthai_socket: str = _f("CAM_A", "board socket of the camera (OAK-D: CAM_A colour, CAM_B/CAM_C mono)",
                             choices=("CAM_A", "CAM_B", "CAM_C", "CAM_D", "CAM_E", "CAM_F", "CAM_G", "CAM_H"))
    colour: bool = _f(False, "DepthAI: request colour (NV12) instead of mono (GRAY8); converted to "
                      "grey either way")
    depthai_reconnection_attempts: int = _f(3, "times depthai reconnects a lost device itself before "
                                            "the driver reopens it with backoff", lo=0, hi=1000, unit="")


@dataclass(frozen=True)
class CalibrationConfig:
    """Where the calibration file is (written by ``robotd calibrate intrinsics |
    floor-mount | odometry | loop-curve``). Its calibrated values replace the config's
    ``[floor_camera]`` intrinsics and mount and ``[robot]`` geometry (logged); its
    trained loop thresholds let the daemon declare loops. Without the file the daemon
    says so at start-up and declares no floor loops."""

    path: str = _f("/etc/robotd/calibration.yml",
                   "OpenCV YAML: intrinsics, floor mount, trained loop thresholds (optional; a "
                   "reload reads the file again and applies its loop threshold live, its "
                   "intrinsics and mount at a restart)",
                   nonempty=True, live=True)


@dataclass(frozen=True)
class MapConfig:
    """The SQLite map file (WAL; the systemd unit's StateDirectory= is /var/lib/robotd)."""

    path: str = _f("/var/lib/robotd/map.sqlite", "map file (created if missing)", nonempty=True)


@dataclass(frozen=True)
class RecordingConfig:
    """How ``robotd record`` (and the demo's ``--record``) stores camera frames in the MCAP
    file (sensor_msgs/CompressedImage). JPEG at quality 15 is 10x smaller than lossless PNG
    on the 640x480 floor camera (41 MB instead of 413 MB per minute) but lowers the
    descriptor scores: thresholds trained on a JPEG drive are 9-15 % lower
    (docs/recordings.md). Record calibration drives as PNG, and train and replay on one
    format."""

    image_format: str = _f("jpeg", "camera frames as 'jpeg' (lossy, compact) or 'png' (lossless, "
                           "about 10x larger)", choices=("jpeg", "png"))
    jpeg_quality: int = _f(15, "JPEG quality of recorded frames (15: about 10x smaller than PNG)", lo=1, hi=100)
    png_compression: int = _f(1, "zlib level of recorded PNG frames (1: fastest)", lo=0, hi=9)


@dataclass(frozen=True)
class DaemonConfig:
    """Service behaviour: STATUS to systemd and a log line with rates and drops."""

    status_interval_s: float = _f(5.0, "how often STATUS is sent to systemd and logged", lo=0.1, hi=3600.0,
                                  live=True)
    log_level: str = _f("info", "logging level (--log-level on the command line wins)",
                        choices=("debug", "info", "warning", "error"), live=True)
    gc_freeze: bool = _f(False, "move the objects made at start-up (the map's load included) out of "
                         "Python's garbage collector for the run: its full collections then walk only "
                         "what the run made (measured, not yet the default: docs/performance.md)")
    gc_full_between_messages: bool = _f(False, "run Python's full garbage collections between the pipeline's "
                                        "messages instead of inside whichever stage's work allocates when one "
                                        "is due (after ten collections of generation 1, as CPython counts; "
                                        "measured, not yet the default: docs/forward.md)")


@dataclass(frozen=True)
class Ros2Config:
    """ROS 2 topics over DDS (the ``robotd[ros2]`` extra; docs/ros2.md): what robotd
    publishes when ``enabled``, and the topics the ``ros2`` base and camera sources read.
    Relative topic names resolve in ``namespace``; absolute ones (``/tf``) do not."""

    enabled: bool = _f(False, "publish robotd's outputs on ROS 2 (needs cyclonedds)")
    domain_id: int = _f(-1, "DDS domain; -1: ROS_DOMAIN_ID of the environment (0 when unset), as "
                        "a ROS 2 node does", lo=-1, hi=232)
    namespace: str = _f("", "namespace of the relative topics ('' = the root)")
    map_frame: str = _f("map", "the loop-corrected frame (REP 105)")
    odom_frame: str = _f("odom", "the odometry frame (REP 105)")
    base_frame: str = _f("base_footprint", "the robot's frame on the floor")
    odom_tf: str = _f("auto", "publish odom -> base_frame on /tf: 'auto' only when robotd reads the "
                      "base itself ([base] driver kobuki or can), 'always', 'never'",
                      choices=("auto", "always", "never"))
    tf: bool = _f(True, "publish map -> odom on /tf")
    static_tf: bool = _f(True, "publish base_link and the camera mounts on /tf_static (false when "
                         "robot_state_publisher does, from the robot's URDF)")
    odometry_topic: str = _f("robotd/odometry", "fused odometry (nav_msgs/Odometry); '' = off")
    pose_topic: str = _f("robotd/pose", "loop-corrected pose in the map frame "
                         "(geometry_msgs/PoseWithCovarianceStamped); '' = off")
    path_topic: str = _f("robotd/path", "corrected keyframe path (nav_msgs/Path); '' = off")
    loop_closures_topic: str = _f("robotd/loop_closures", "accepted loop edges "
                                  "(visualization_msgs/MarkerArray); '' = off")
    diagnostics: bool = _f(True, "publish /diagnostics (diagnostic_msgs/DiagnosticArray) at 1 Hz")
    keyframe_images: bool = _f(False, "publish each keyframe's image (JPEG) on "
                               "robotd/keyframes/<camera>/compressed")
    odometry_rate_hz: float = _f(20.0, "most odometry messages (and map -> odom) a second; 0: every "
                                 "update", lo=0.0, hi=1000.0)
    path_interval_s: float = _f(1.0, "the path and loop markers at most this often", lo=0.0, hi=3600.0)
    odometry_reliable: bool = _f(True, "robotd/odometry reliable (false: best effort, as sensor data)")
    ros_time: bool = _f(True, "stamp messages in ROS time (the Unix clock, what other nodes use): "
                        "robotd's stamps plus the offset between the clocks at start-up")
    # input ([base] driver = "ros2", [floor_camera]/[forward_camera] source = "ros2")
    input_odometry_topic: str = _f("/odom", "wheel odometry read by the ros2 base (nav_msgs/Odometry)")
    input_imu_topic: str = _f("/imu", "gyro read by the ros2 base (sensor_msgs/Imu); '' = none")
    floor_camera_topic: str = _f("/floor_camera/image_raw", "floor camera images (sensor_msgs/Image; "
                                 "a name ending in /compressed: sensor_msgs/CompressedImage)")
    forward_camera_topic: str = _f("/forward_camera/image_raw", "forward camera images (as above)")
    input_timeout_s: float = _f(0.5, "an input topic silent this long after data flowed begins a gap "
                                "(counted, shown in STATUS)", lo=0.01, hi=60.0)


@dataclass(frozen=True)
class FoxgloveConfig:
    """A live view for Foxglove (the ``robotd[foxglove]`` extra): a WebSocket server with the
    same ROS 2 messages as [ros2] (poses, path, loop edges, /tf, diagnostics) and the
    keyframe images. It has no authentication: keep it on the loopback unless the network
    is yours."""

    enabled: bool = _f(False, "serve the live view")
    host: str = _f("127.0.0.1", "address to listen on (127.0.0.1: this machine only)")
    port: int = _f(8765, "TCP port", lo=1, hi=65535)
    jpeg_quality: int = _f(60, "JPEG quality of the keyframe images", lo=1, hi=100)


@dataclass(frozen=True)
class Config:
    """The whole configuration, one dataclass per TOML table."""

    robot: RobotConfig = field(default_factory=RobotConfig)
    base: BaseConfig = field(default_factory=BaseConfig)
    can: CanConfig = field(default_factory=CanConfig)
    floor_camera: FloorCameraConfig = field(default_factory=FloorCameraConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    floor_detector: FloorDetectorConfig = field(default_factory=FloorDetectorConfig)
    visual_odometry: VisualOdometryConfig = field(default_factory=VisualOdometryConfig)
    pose_graph: PoseGraphConfig = field(default_factory=PoseGraphConfig)
    forward_detector: ForwardDetectorConfig = field(default_factory=ForwardDetectorConfig)
    forward_camera: ForwardCameraConfig = field(default_factory=ForwardCameraConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    map: MapConfig = field(default_factory=MapConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    daemon: DaemonConfig = field(default_factory=DaemonConfig)
    ros2: Ros2Config = field(default_factory=Ros2Config)
    foxglove: FoxgloveConfig = field(default_factory=FoxgloveConfig)


def check_value(section: str, f: dataclasses.Field[Any], value: Any) -> Any:
    """Type- and range-check one value; return it converted to the field's type."""
    key = f"[{section}] {f.name}"
    meta = f.metadata
    default = f.default
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
    elif isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
    elif isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{key}: must be finite, got {value!r}")
    elif isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        if meta.get("nonempty") and not value.strip():
            raise ConfigError(f"{key}: must not be empty")
    elif isinstance(default, tuple):
        if not isinstance(value, list) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
        ):
            raise ConfigError(f"{key}: expected a list of numbers, got {value!r}")
        if meta.get("length") is not None and len(value) != meta["length"]:
            raise ConfigError(f"{key}: expected {meta['length']} numbers, got {len(value)}")
        value = tuple(float(v) for v in value)
    lo, hi = meta.get("lo"), meta.get("hi")
    if lo is not None and value < lo:
        raise ConfigError(f"{key}: {value!r} is below the minimum {lo!r}")
    if hi is not None and value > hi:
        raise ConfigError(f"{key}: {value!r} is above the maximum {hi!r}")
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        raise ConfigError(f"{key}: {value!r} is not one of {', '.join(map(repr, choices))}")
    return value


Key = tuple[str, str]
"""A config key: ``(section, key)``."""

VIRTUAL_SOURCE = "virtual"
"""``[floor_camera] source`` of the demo's built-in robot and of replays: set by
:func:`with_virtual_floor_camera`, never read from a user's file (``robotd run`` has no
virtual camera); accepted only in configs robotd stored itself (recordings, maps)."""


def live_keys() -> frozenset[Key]:
    """The keys ``systemctl reload robotd`` (SIGHUP) applies at once: those whose
    metadata says ``live`` (:mod:`robotd.app.reload` applies them)."""
    return frozenset((sf.name, f.name) for sf in dataclasses.fields(Config)
                     for f in dataclasses.fields(sf.default_factory)  # type: ignore[arg-type]
                     if f.metadata.get("live"))


def with_virtual_floor_camera(cfg: Config) -> Config:
    """``cfg`` with ``[floor_camera] source`` the built-in virtual robot's (the demo) or a
    recording's (replay): the floor frames come from a source the caller gives the
    daemon, not from a device. Not a value a config file may hold."""
    return dataclasses.replace(cfg, floor_camera=dataclasses.replace(cfg.floor_camera,
                                                                      source=VIRTUAL_SOURCE))


def replace(cfg: Config, section: str, **changes: Any) -> Config:
    """A copy of ``cfg`` with some keys of one section changed (validated like the file)."""
    sec = getattr(cfg, section)
    fields = {f.name: f for f in dataclasses.fields(sec)}
    checked = {}
    for key, value in changes.items():
        if key not in fields:
            raise ConfigError(f"unknown key [{section}] {key}")
        v = list(value) if isinstance(value, tuple) else value
        checked[key] = check_value(section, fields[key], v)
    return dataclasses.replace(cfg, **{section: dataclasses.replace(sec, **checked)})
