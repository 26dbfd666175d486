"""The one configuration file: TOML read into frozen dataclasses.

Every section is a frozen dataclass whose fields carry their unit in the name and their
valid range in ``metadata``. Unknown sections, unknown keys, wrong types and out-of-range
values are :class:`~robotd.base.errors.ConfigError` naming the key (``[floor_camera] fps``).
There is exactly one source of configuration: the file (or the defaults when a key is
absent). Environment variables change nothing.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robotd.base.errors import ConfigError


def _f(default: Any, doc: str, *, lo: float | None = None, hi: float | None = None,
       choices: tuple[str, ...] | None = None, length: int | None = None,
       nonempty: bool = False) -> Any:
    """A config field with its documentation and validity constraints (``nonempty``: a
    string that must not be empty or blank, such as a file path)."""
    meta = {"doc": doc, "lo": lo, "hi": hi, "choices": choices, "length": length,
            "nonempty": nonempty}
    if isinstance(default, (list, tuple)):
        return field(default=tuple(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class RobotConfig:
    """Differential-drive geometry (Kobuki defaults)."""

    wheel_radius_m: float = _f(0.035, "wheel radius", lo=0.005, hi=1.0)
    wheel_base_m: float = _f(0.23, "distance between the wheel contact points", lo=0.02, hi=5.0)
    ticks_per_rev: float = _f(2578.33, "encoder ticks per wheel turn", lo=1.0, hi=1e7)


@dataclass(frozen=True)
class BaseConfig:
    """The mobile base: wheel encoders and gyro."""

    driver: str = _f("kobuki", "base driver ('can': the [can] section)", choices=("kobuki", "can", "none"))
    port: str = _f("/dev/kobuki", "serial port: a device path or any pyserial URL", nonempty=True)
    baudrate: int = _f(115200, "serial baud rate", lo=1200, hi=4_000_000)
    yaw_source: str = _f("raw_gyro", "which gyro reading feeds the filter",
                         choices=("raw_gyro", "inertial"))
    queue_size: int = _f(512, "samples buffered between the driver thread and the pipeline",
                         lo=1, hi=1_000_000)


@dataclass(frozen=True)
class CanConfig:
    """A base on a CAN bus (``[base] driver = "can"``): python-can for the bus, a DBC file
    for the frames, and which decoded signals are the wheels and the gyro.

    A signal is ``"Message.Signal"`` of the DBC. A wheel signal in a unit of angle or
    distance is a position (cumulative), one per second a speed (integrated by the
    driver). ``left_scale``/``right_scale`` multiply the decoded value first: -1 for a
    mirrored motor, 1/N for a gearbox of ratio N when the signal is motor turns."""

    interface: str = _f("socketcan", "python-can interface ('socketcan' on the robot, 'virtual' in tests)")
    channel: str = _f("can0", "python-can channel (the socketcan network interface)")
    dbc: str = _f("diff_drive", "a DBC shipped with robotd ('diff_drive', 'odrive_cansimple') or a .dbc path")
    left: str = _f("Base_Wheels.Left_Wheel_Pos", "left wheel signal, Message.Signal")
    right: str = _f("Base_Wheels.Right_Wheel_Pos", "right wheel signal, Message.Signal")
    wheel_unit: str = _f("rad", "unit of the wheel signals (per second: a speed)",
                         choices=("turn", "rad", "deg", "m", "turn/s", "rad/s", "deg/s", "m/s", "rpm"))
    left_scale: float = _f(1.0, "multiplies the left signal (-1: mirrored; 1/N: gear ratio N)", lo=-1e6, hi=1e6)
    right_scale: float = _f(1.0, "multiplies the right signal (-1: mirrored; 1/N: gear ratio N)", lo=-1e6, hi=1e6)
    yaw: str = _f("Base_Gyro.Yaw_Rate", "yaw-rate signal, Message.Signal ('': no gyro)")
    yaw_unit: str = _f("deg/s", "unit of the yaw-rate signal", choices=("rad/s", "deg/s"))
    yaw_scale: float = _f(1.0, "multiplies the yaw signal (-1: clockwise positive)", lo=-1e6, hi=1e6)
    period_s: float = _f(0.02, "the wheel frames' nominal period", lo=1e-4, hi=10.0)
    stale_periods: int = _f(5, "a wheel (or the bus) silent this many periods is stale", lo=1, hi=100_000)
    max_frames_per_read: int = _f(2000, "frames taken per read; more waiting is a flood (counted)",
                                  lo=1, hi=1_000_000)


@dataclass(frozen=True)
class FloorCameraConfig:
    """The downward-facing floor camera: device, intrinsics and mounting."""

    source: str = _f("v4l2", "camera source ('virtual': the built-in virtual robot, demo only)",
                     choices=("v4l2", "depthai", "none", "virtual"))
    device: str = _f("/dev/video0", "V4L2 device path")
    fourcc: str = _f("YUYV", "pixel format requested from the driver", choices=("YUYV", "MJPG", "GREY"))
    width_px: int = _f(640, "image width", lo=16, hi=8192)
    height_px: int = _f(480, "image height", lo=16, hi=8192)
    fps: float = _f(30.0, "frame rate", lo=0.1, hi=1000.0)
    buffer_size: int = _f(2, "driver-side frame buffers (small = low latency)", lo=1, hi=32)
    queue_size: int = _f(8, "frames buffered between the camera thread and the pipeline", lo=1, hi=10_000)
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
    depthai_device: str = _f("", "DepthAI device id, IP address or USB name ('' = the first found)")
    depthai_socket: str = _f("CAM_A", "board socket of the camera (OAK-D: CAM_A colour, CAM_B/CAM_C mono)",
                             choices=("CAM_A", "CAM_B", "CAM_C", "CAM_D", "CAM_E", "CAM_F", "CAM_G", "CAM_H"))
    colour: bool = _f(False, "DepthAI: request colour (NV12) instead of mono (GRAY8); the floor "
                      "camera is converted to grey either way")
    depthai_reconnection_attempts: int = _f(3, "times depthai reconnects a lost device itself before "
                                            "the driver reopens it with backoff", lo=0, hi=1000)


@dataclass(frozen=True)
class OdometryConfig:
    """Noise model of the wheel + gyro extended Kalman filter (1-sigma values)."""

    accel_noise_mps2: float = _f(0.5, "process noise: linear acceleration", lo=1e-6, hi=100.0)
    angular_accel_noise_radps2: float = _f(0.3, "process noise: angular acceleration", lo=1e-6, hi=1000.0)
    gyro_bias_walk_radps_sqrt_s: float = _f(2e-5, "gyro bias random walk", lo=0.0, hi=1.0)
    wheel_v_noise_mps: float = _f(0.01, "wheel speed noise at standstill", lo=1e-6, hi=10.0)
    wheel_v_noise_frac: float = _f(0.02, "wheel speed noise growing with speed (slip)", lo=0.0, hi=1.0)
    wheel_w_noise_radps: float = _f(0.05, "wheel yaw-rate noise", lo=1e-6, hi=10.0)
    wheel_w_noise_frac: float = _f(0.05, "wheel yaw-rate noise growing with turn rate", lo=0.0, hi=1.0)
    wheel_w_noise_per_mps: float = _f(0.5, "wheel yaw-rate noise growing with speed (unequal wheels)",
                                      lo=0.0, hi=100.0)
    gyro_noise_radps: float = _f(0.003, "gyro yaw-rate white noise per sample", lo=1e-7, hi=10.0)
    initial_gyro_bias_sigma_radps: float = _f(0.01, "prior on the gyro bias", lo=1e-7, hi=10.0)


@dataclass(frozen=True)
class KeyframeConfig:
    """When a floor frame becomes a keyframe, and what of it is stored."""

    distance_m: float = _f(0.05, "distance travelled since the last keyframe", lo=0.001, hi=100.0)
    rotation_deg: float = _f(10.0, "rotation since the last keyframe", lo=0.1, hi=360.0)
    image_width_px: int = _f(160, "width of the stored downsampled image (0 = none)", lo=0, hi=8192)
    jpeg_quality: int = _f(85, "JPEG quality of the stored image", lo=1, hi=100)
    max_sync_wait_s: float = _f(0.5, "how long a frame waits for odometry at its stamp", lo=0.0, hi=60.0)


@dataclass(frozen=True)
class FloorDetectorConfig:
    """Compact floor descriptors of every keyframe and the map query (paper 003)."""

    enabled: bool = _f(True, "describe keyframes and query the map for look-alikes")
    mode: int = _f(4, "descriptor mode: 1..6 = at most 512 B, 1, 2, 4, 8, 16 kB per image", lo=1, hi=6)
    candidates: int = _f(5, "candidates returned per query", lo=1, hi=100)
    shortlist: int = _f(30, "keyframes scored locally per query (after the global shortlist)",
                        lo=1, hi=100_000)
    exclude_recent_s: float = _f(20.0, "keyframes younger than this are not candidates", lo=0.0, hi=1e6)


@dataclass(frozen=True)
class VisualOdometryConfig:
    """Floor visual odometry between consecutive keyframes (paper 003, Sec. IV-D); the
    descriptor mode is ``[floor_detector] mode`` (the keyframe's descriptor is reused)."""

    enabled: bool = _f(True, "estimate the motion between consecutive keyframes from the floor camera")
    mode: str = _f("fused", "'fused': a measurement in the wheel + gyro filter; 'vision_only': the "
                   "chained steps are the odometry (no wheels; failed steps take the wheel + gyro "
                   "increment when there is one)", choices=("fused", "vision_only"))
    min_inliers: int = _f(8, "fewest metric inliers of a usable step", lo=3, hi=10_000)
    ransac_threshold_m: float = _f(0.003, "RANSAC inlier distance on the floor", lo=1e-5, hi=0.1)


@dataclass(frozen=True)
class PoseGraphConfig:
    """The live pose graph: keyframes, odometry edges and gated loop edges (GTSAM iSAM2)."""

    enabled: bool = _f(True, "keep a pose graph and store the loop-corrected poses in the map")
    gate_chi2: float = _f(16.27, "largest Mahalanobis distance squared of a loop against the graph's "
                          "prediction (16.27: 99.9 % of chi-square with 3 degrees of freedom)",
                          lo=0.1, hi=1e6)
    save_every_keyframes: int = _f(200, "re-solve the whole graph robustly and store the optimised "
                                   "poses every this many keyframes (0: only at the end of a run)",
                                   lo=0, hi=1_000_000)
    localise_mapped: bool = _f(False, "over ground the map already holds, once a loop is accepted, "
                               "keyframes only re-localise the robot and are not stored: the map and "
                               "the graph grow with the area covered, not the distance driven")
    mapped_radius_m: float = _f(0.15, "a keyframe this close to a stored one (by the graph's estimate) "
                                "is on mapped ground", lo=0.001, hi=100.0)
    max_unlocalised_m: float = _f(1.0, "on mapped ground, travel this far without an accepted match "
                                  "and the robot stores keyframes again", lo=0.01, hi=1000.0)


@dataclass(frozen=True)
class ForwardDetectorConfig:
    """The forward camera's Bayesian loop detector (paper 000) on forward keyframes; its
    verified loops enter the pose graph with the range taken from the graph's prediction."""

    enabled: bool = _f(False, "run the forward loop detector (needs a forward camera source)")
    features: str = _f("sift", "local features: 'sift' (the paper's) or 'orb' (binary, about 4x "
                       "faster, for small CPUs)", choices=("sift", "orb"))
    max_features: int = _f(500, "strongest keypoints kept per image (0: all)", lo=0, hi=100_000)
    distance_m: float = _f(0.5, "a forward keyframe every this far travelled", lo=0.01, hi=100.0)
    rotation_deg: float = _f(20.0, "or every this much turned", lo=0.1, hi=360.0)
    sync_tolerance_s: float = _f(0.04, "largest offset of the forward frame from its floor keyframe",
                                 lo=0.0, hi=1.0)
    width_px: int = _f(640, "forward camera image width", lo=16, hi=8192)
    height_px: int = _f(480, "forward camera image height", lo=16, hi=8192)
    fx_px: float = _f(525.0, "forward camera focal length x", lo=1.0, hi=1e5)
    fy_px: float = _f(525.0, "forward camera focal length y", lo=1.0, hi=1e5)
    cx_px: float = _f(319.5, "forward camera principal point x", lo=-1e5, hi=1e5)
    cy_px: float = _f(239.5, "forward camera principal point y", lo=-1e5, hi=1e5)
    mount_x_m: float = _f(0.1, "forward camera position in the robot frame, forward", lo=-2.0, hi=2.0)
    mount_y_m: float = _f(0.0, "forward camera position in the robot frame, left", lo=-2.0, hi=2.0)
    mount_yaw_deg: float = _f(0.0, "forward camera heading in the robot frame", lo=-180.0, hi=180.0)
    mount_height_m: float = _f(0.6, "forward camera lens height above the floor (level optical axis)",
                               lo=0.0, hi=5.0)
    sigma_bearing_deg: float = _f(2.0, "1-sigma of a loop's translation direction", lo=0.01, hi=90.0)
    sigma_yaw_deg: float = _f(1.0, "1-sigma of a loop's heading change", lo=0.01, hi=90.0)


@dataclass(frozen=True)
class ForwardCameraConfig:
    """The forward camera's device for `robotd run` (its size, intrinsics and mount are in
    ``[forward_detector]``, which uses its frames). Opened only when the detector is on."""

    source: str = _f("none", "camera source of the forward camera ('none': no forward camera)",
                     choices=("v4l2", "depthai", "none"))
    device: str = _f("/dev/video1", "V4L2 device path")
    fourcc: str = _f("YUYV", "pixel format requested from the driver", choices=("YUYV", "MJPG", "GREY"))
    fps: float = _f(15.0, "frame rate (the detector takes a keyframe every few frames)", lo=0.1, hi=1000.0)
    buffer_size: int = _f(2, "driver-side frame buffers (small = low latency)", lo=1, hi=32)
    depthai_device: str = _f("", "DepthAI device id, IP address or USB name ('' = the first found)")
    depthai_socket: str = _f("CAM_A", "board socket of the camera (OAK-D: CAM_A colour, CAM_B/CAM_C mono)",
                             choices=("CAM_A", "CAM_B", "CAM_C", "CAM_D", "CAM_E", "CAM_F", "CAM_G", "CAM_H"))
    colour: bool = _f(False, "DepthAI: request colour (NV12) instead of mono (GRAY8); converted to "
                      "grey either way")
    depthai_reconnection_attempts: int = _f(3, "times depthai reconnects a lost device itself before "
                                            "the driver reopens it with backoff", lo=0, hi=1000)


@dataclass(frozen=True)
class CalibrationConfig:
    """Where the calibration file is (written by ``robotd calibrate``)."""

    path: str = _f("/etc/robotd/calibration.yml",
                   "OpenCV YAML: intrinsics, floor mount, trained loop thresholds (optional)",
                   nonempty=True)


@dataclass(frozen=True)
class MapConfig:
    """The SQLite map file."""

    path: str = _f("/var/lib/robotd/map.sqlite", "map file (created if missing)", nonempty=True)


@dataclass(frozen=True)
class RecordingConfig:
    """How ``robotd record`` (and the demo's ``--record``) stores camera frames."""

    image_format: str = _f("jpeg", "camera frames as 'jpeg' (lossy, compact) or 'png' (lossless, "
                           "about 10x larger)", choices=("jpeg", "png"))
    jpeg_quality: int = _f(15, "JPEG quality of recorded frames (15: about 10x smaller than PNG)", lo=1, hi=100)
    png_compression: int = _f(1, "zlib level of recorded PNG frames (1: fastest)", lo=0, hi=9)


@dataclass(frozen=True)
class DaemonConfig:
    """Service behaviour."""

    status_interval_s: float = _f(5.0, "how often STATUS is sent to systemd and logged", lo=0.1, hi=3600.0)
    log_level: str = _f("info", "logging level", choices=("debug", "info", "warning", "error"))


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


def _check_value(section: str, f: dataclasses.Field[Any], value: Any) -> Any:
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


def config_from_dict(data: dict[str, Any]) -> Config:
    """Build a :class:`Config` from parsed TOML, validating every key."""
    sections = {f.name: f for f in dataclasses.fields(Config)}
    built: dict[str, Any] = {}
    for name, table in data.items():
        if name not in sections:
            raise ConfigError(f"unknown section [{name}] (known: {', '.join(sections)})")
        if not isinstance(table, dict):
            raise ConfigError(f"[{name}] must be a table, got {table!r}")
        cls: Any = sections[name].default_factory
        fields = {f.name: f for f in dataclasses.fields(cls)}
        values = {}
        for key, value in table.items():
            if key not in fields:
                raise ConfigError(f"unknown key [{name}] {key} (known: {', '.join(fields)})")
            values[key] = _check_value(name, fields[key], value)
        built[name] = cls(**values)
    cfg = Config(**built)
    fc = cfg.floor_camera
    if not (0 <= fc.cx_px < fc.width_px and 0 <= fc.cy_px < fc.height_px):
        raise ConfigError("[floor_camera] cx_px/cy_px: the principal point must lie inside the image")
    return cfg


def load_config(path: str | Path) -> Config:
    """Read and validate a TOML config file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {p}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read config file {p}: {exc}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    return config_from_dict(data)


def replace(cfg: Config, section: str, **changes: Any) -> Config:
    """A copy of ``cfg`` with some keys of one section changed (validated like the file)."""
    sec = getattr(cfg, section)
    fields = {f.name: f for f in dataclasses.fields(sec)}
    checked = {}
    for key, value in changes.items():
        if key not in fields:
            raise ConfigError(f"unknown key [{section}] {key}")
        v = list(value) if isinstance(value, tuple) else value
        checked[key] = _check_value(section, fields[key], v)
    return dataclasses.replace(cfg, **{section: dataclasses.replace(sec, **checked)})


def to_toml(cfg: Config) -> str:
    """Serialise a config back to TOML (stored with every run in the map file)."""
    lines: list[str] = []
    for sf in dataclasses.fields(cfg):
        lines.append(f"[{sf.name}]")
        for f in dataclasses.fields(getattr(cfg, sf.name)):
            v = getattr(getattr(cfg, sf.name), f.name)
            lines.append(f"{f.name} = {_toml_value(v)}")
        lines.append("")
    return "\n".join(lines)


def commented_toml(cfg: Config | None = None) -> str:
    """``cfg`` (default: the defaults) as TOML with each section's and key's description,
    unit and valid range as comments: what ``robotd config default`` prints, a config file
    to start from."""
    cfg = Config() if cfg is None else cfg
    lines = ["# robotd configuration (robotd config default). Unknown keys and out-of-range",
             "# values are errors that name the key. Units are in the key names.", ""]
    for sf in dataclasses.fields(cfg):
        section = getattr(cfg, sf.name)
        lines.append(f"[{sf.name}]")
        doc = " ".join((type(section).__doc__ or "").strip().split("\n\n")[0].split())
        if doc:
            lines.append(f"# {doc}")
        for f in dataclasses.fields(section):
            meta = f.metadata
            note = " ".join(str(meta.get("doc", "")).split())
            lo, hi, choices = meta.get("lo"), meta.get("hi"), meta.get("choices")
            if choices:
                note += f" (one of {', '.join(map(repr, choices))})"
            elif lo is not None or hi is not None:
                note += f" ({'' if lo is None else f'{lo:g} '}..{'' if hi is None else f' {hi:g}'})"
            lines.append(f"# {note}")
            lines.append(f"{f.name} = {_toml_value(getattr(section, f.name))}")
        lines.append("")
    return "\n".join(lines)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'
