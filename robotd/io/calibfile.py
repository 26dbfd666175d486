"""The calibration file the daemon loads: OpenCV's YAML, written and read by ``cv2.FileStorage``.

An OpenCV user recognises the intrinsic part at once: it uses the key names of OpenCV's
own calibration sample (``camera_matrix`` 3x3, ``distortion_coefficients`` 1x5 in the
order k1 k2 p1 p2 k3, ``image_width``, ``image_height``, ``avg_reprojection_error``), so
``cv2.FileStorage(path, cv2.FILE_STORAGE_READ).getNode("camera_matrix").mat()`` works on it
and the daemon reads the files OpenCV's sample writes. Two optional robotd sections follow:

* the floor camera's mount on the robot (``mount_height_m``, ``mount_tilt_deg``,
  ``mount_x_m``, ``mount_y_m``, ``mount_yaw_deg``; conventions of
  :class:`robotd.base.camera.FloorCameraModel`), measured by ``robotd calibrate floor-mount``;
* the floor loop detector's per-mode score thresholds (``loop_threshold_mode_1`` ..
  ``loop_threshold_mode_6``, ``loop_overlap_r``, ``loop_confidence``), trained by
  ``robotd calibrate loop-curve`` (paper 003, Sec. IV-C and Table III);
* the odometry model of this robot (``odometry_wheel_radius_left_m`` ..., see
  :class:`OdometryModel`), fitted by ``robotd calibrate odometry``; the daemon uses it in
  place of the config's nominal ``[robot]`` geometry and gyro noise.

Each part is optional, so the calibration runs can fill the file one step at a time:
:func:`update_calibration` reads the file, replaces one part and writes it back
atomically (a temporary file in the same directory, then ``os.replace``), so a crash or
a full disk never leaves a half-written calibration behind.

Keys that robotd does not know are ignored when they come from other tools (OpenCV's
sample writes ``nframes``, ``flags``, ``extrinsic_parameters`` and more), but a key in
robotd's own namespaces (``mount_*``, ``loop_*``, ``odometry_*``) that is not listed above is an error:
it is most likely a typo that would otherwise silently fall back to the config.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterable, Mapping

import cv2
import numpy as np

from robotd.base.errors import CalibrationError
from robotd.base.camera import CameraIntrinsics, FloorCameraModel

logger = logging.getLogger(__name__)

__all__ = [
    "N_MODES",
    "CalibrationFile",
    "FloorMount",
    "LoopThresholds",
    "OdometryModel",
    "camera_model",
    "merge",
    "read_calibration",
    "update_calibration",
    "write_calibration",
]

#: Number of descriptor modes (paper 003: modes 1..6, 512 B .. 16 kB per image).
N_MODES = 6

_MOUNT_KEYS = ("mount_height_m", "mount_tilt_deg", "mount_x_m", "mount_y_m", "mount_yaw_deg")
_LOOP_MODE_KEYS = tuple(f"loop_threshold_mode_{m}" for m in range(1, N_MODES + 1))
_LOOP_KEYS = _LOOP_MODE_KEYS + ("loop_overlap_r", "loop_confidence")
_ODOMETRY_FIELDS = (
    ("wheel_radius_left_m", "odometry_wheel_radius_left_m"),
    ("wheel_radius_right_m", "odometry_wheel_radius_right_m"),
    ("wheel_base_m", "odometry_wheel_base_m"),
    ("gyro_scale", "odometry_gyro_scale"),
    ("gyro_bias_radps", "odometry_gyro_bias_radps"),
    ("gyro_noise_radps_sqrt_hz", "odometry_gyro_noise_radps_sqrt_hz"),
    ("wheel_noise_m_sqrt_m", "odometry_wheel_noise_m_sqrt_m"),
    ("wheel_radius_left_sigma_m", "odometry_wheel_radius_left_sigma_m"),
    ("wheel_radius_right_sigma_m", "odometry_wheel_radius_right_sigma_m"),
    ("wheel_base_sigma_m", "odometry_wheel_base_sigma_m"),
    ("gyro_scale_sigma", "odometry_gyro_scale_sigma"),
    ("gyro_bias_sigma_radps", "odometry_gyro_bias_sigma_radps"),
)
#: Optional (a calibration written before they were fitted has none): the filter's white
#: accelerations by maximum likelihood, with their 1-sigma; all four or none.
_PROCESS_FIELDS = (
    ("accel_noise_mps2_sqrt_hz", "odometry_accel_noise_mps2_sqrt_hz"),
    ("angular_accel_noise_radps2_sqrt_hz", "odometry_angular_accel_noise_radps2_sqrt_hz"),
    ("accel_noise_sigma", "odometry_accel_noise_sigma"),
    ("angular_accel_noise_sigma", "odometry_angular_accel_noise_sigma"),
)
_PROCESS_KEYS = tuple(k for _f, k in _PROCESS_FIELDS)
#: Optional (a calibration written before they were fitted, or from a drive with too few of
#: them, has none): the wheel slip events' rate and RMS duration, with their 1-sigma; all
#: four or none.
_SLIP_EVENT_FIELDS = (
    ("slip_event_rate_hz", "odometry_slip_event_rate_hz"),
    ("slip_event_duration_s", "odometry_slip_event_duration_s"),
    ("slip_event_rate_sigma_hz", "odometry_slip_event_rate_sigma_hz"),
    ("slip_event_duration_sigma_s", "odometry_slip_event_duration_sigma_s"),
)
_SLIP_EVENT_KEYS = tuple(k for _f, k in _SLIP_EVENT_FIELDS)
_ODOMETRY_KEYS = tuple(k for _f, k in _ODOMETRY_FIELDS) + _PROCESS_KEYS + _SLIP_EVENT_KEYS
_INTRINSIC_KEYS = ("camera_matrix", "distortion_coefficients", "image_width", "image_height",
                   "avg_reprojection_error")


def _finite(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise CalibrationError(f"{name} must be a finite number, got {value!r}")
    return value


# ------------------------------------------------------------------------- parts


@dataclass(frozen=True)
class FloorMount:
    """Where the downward floor camera sits on the robot (FloorCameraModel conventions).

    Fields:
        height_m: lens centre above the floor, metres (> 0).
        tilt_deg: pitch of the optical axis from straight down towards robot forward,
            degrees, in (-90, 90).
        x_m, y_m: lens centre in the robot frame (x forward, y left), metres.
        yaw_deg: image rotation about the optical axis, counter-clockwise seen from above,
            degrees; 0 = image up is robot forward.
    """

    height_m: float
    tilt_deg: float
    x_m: float = 0.0
    y_m: float = 0.0
    yaw_deg: float = 0.0

    def __post_init__(self) -> None:
        for key, name in zip(_MOUNT_KEYS, ("height_m", "tilt_deg", "x_m", "y_m", "yaw_deg")):
            object.__setattr__(self, name, _finite(key, getattr(self, name)))
        if self.height_m <= 0.0:
            raise CalibrationError(f"mount_height_m must be positive (lens above the floor), got {self.height_m}")
        if not -90.0 < self.tilt_deg < 90.0:
            raise CalibrationError(f"mount_tilt_deg must lie in (-90, 90), got {self.tilt_deg}")


@dataclass(frozen=True)
class LoopThresholds:
    """Per-mode local-score thresholds above which a floor match is declared a loop.

    Fields:
        thresholds: ``N_MODES`` entries, index ``mode - 1``; ``None`` for a mode that was
            not trained (the daemon declares no loops in that mode).
        overlap_r: footprint overlap J that defines a loop when training (paper: 0.33).
        confidence: P(J >= r | score) the threshold guarantees (default 0.99).
    """

    thresholds: tuple[float | None, ...] = (None,) * N_MODES
    overlap_r: float = 0.33
    confidence: float = 0.99

    def __post_init__(self) -> None:
        th = tuple(None if t is None else _finite("loop threshold", t) for t in self.thresholds)
        if len(th) != N_MODES:
            raise CalibrationError(f"loop thresholds: need {N_MODES} entries (modes 1..{N_MODES}), got {len(th)}")
        object.__setattr__(self, "thresholds", th)
        r = _finite("loop_overlap_r", self.overlap_r)
        c = _finite("loop_confidence", self.confidence)
        if not 0.0 < r <= 1.0:
            raise CalibrationError(f"loop_overlap_r must lie in (0, 1], got {r}")
        if not 0.0 < c < 1.0:
            raise CalibrationError(f"loop_confidence must lie in (0, 1), got {c}")
        object.__setattr__(self, "overlap_r", r)
        object.__setattr__(self, "confidence", c)

    @classmethod
    def from_mapping(cls, by_mode: Mapping[int, float], overlap_r: float = 0.33,
                     confidence: float = 0.99) -> LoopThresholds:
        """From ``{mode: threshold}`` (modes 1..N_MODES); missing modes are untrained."""
        bad = [m for m in by_mode if not 1 <= int(m) <= N_MODES]
        if bad:
            raise CalibrationError(f"loop thresholds: modes must be 1..{N_MODES}, got {sorted(bad)}")
        th = tuple(by_mode.get(m) for m in range(1, N_MODES + 1))
        return cls(thresholds=th, overlap_r=overlap_r, confidence=confidence)

    def for_mode(self, mode: int) -> float | None:
        """The threshold of descriptor mode ``mode`` (1..N_MODES), ``None`` if untrained."""
        if not 1 <= mode <= N_MODES:
            raise ValueError(f"mode must be 1..{N_MODES}, got {mode}")
        return self.thresholds[mode - 1]


@dataclass(frozen=True)
class OdometryModel:
    """This robot's odometry model, fitted to a calibration drive (``robotd calibrate
    odometry``; :mod:`robotd.odometry.calibration`). Every value has its 1-sigma
    uncertainty beside it (``*_sigma*``).

    Fields: wheel_radius_left_m, wheel_radius_right_m, wheel_base_m (m); gyro_scale
    (measured over true yaw rate); gyro_bias_radps (the calibration drive's turn-on bias,
    rad/s: the firmware or the filter learns each power-on's own at standstill, so this is
    a record of the drive and a scale for the prior, not a correction);
    gyro_noise_radps_sqrt_hz (white rate noise density); wheel_noise_m_sqrt_m (slip noise
    per sqrt(m) of travel); accel_noise_mps2_sqrt_hz, angular_accel_noise_radps2_sqrt_hz
    (the filter's white linear and angular accelerations, m/s^2 and rad/s^2 per sqrt(Hz),
    with their 1-sigma ``*_noise_sigma``): None in a file written before they were fitted.
    slip_event_rate_hz (wheel slip events a second of accelerating or turning, all of
    them), slip_event_duration_s (their RMS duration, s), with their 1-sigma
    ``slip_event_*_sigma_*`` (:mod:`robotd.odometry.slip_events`): None in a file written
    before they were fitted or from a drive with too few of them.
    """

    wheel_radius_left_m: float
    wheel_radius_right_m: float
    wheel_base_m: float
    gyro_scale: float
    gyro_bias_radps: float
    gyro_noise_radps_sqrt_hz: float
    wheel_noise_m_sqrt_m: float
    wheel_radius_left_sigma_m: float
    wheel_radius_right_sigma_m: float
    wheel_base_sigma_m: float
    gyro_scale_sigma: float
    gyro_bias_sigma_radps: float
    accel_noise_mps2_sqrt_hz: float | None = None
    angular_accel_noise_radps2_sqrt_hz: float | None = None
    accel_noise_sigma: float | None = None
    angular_accel_noise_sigma: float | None = None
    slip_event_rate_hz: float | None = None
    slip_event_duration_s: float | None = None
    slip_event_rate_sigma_hz: float | None = None
    slip_event_duration_sigma_s: float | None = None

    @property
    def has_process_noise(self) -> bool:
        """True when the file holds the fitted white accelerations."""
        return self.accel_noise_mps2_sqrt_hz is not None

    @property
    def has_slip_events(self) -> bool:
        """True when the file holds the fitted slip events' rate and duration."""
        return self.slip_event_rate_hz is not None

    def __post_init__(self) -> None:
        given = [getattr(self, f) is not None for f, _k in _PROCESS_FIELDS]
        if any(given) and not all(given):
            raise CalibrationError("the odometry's white accelerations need all of " + ", ".join(_PROCESS_KEYS))
        for field_name, key in _PROCESS_FIELDS:
            if given[0]:
                v = _finite(key, getattr(self, field_name))
                if not (v > 0.0 if "sigma" not in key else v >= 0.0):
                    raise CalibrationError(f"{key} must be {'>= 0' if 'sigma' in key else 'positive'}, got {v}")
                object.__setattr__(self, field_name, v)
        slip_given = [getattr(self, f) is not None for f, _k in _SLIP_EVENT_FIELDS]
        if any(slip_given) and not all(slip_given):
            raise CalibrationError("the odometry's slip events need all of " + ", ".join(_SLIP_EVENT_KEYS))
        for field_name, key in _SLIP_EVENT_FIELDS if slip_given[0] else ():
            v = _finite(key, getattr(self, field_name))
            if "sigma" in key and v < 0.0:
                raise CalibrationError(f"{key} must be >= 0, got {v}")
            if "sigma" not in key and not 0.0 < v <= (100.0 if "rate" in key else 10.0):
                raise CalibrationError(f"{key} must be in (0, {100 if 'rate' in key else 10}], got {v}")
            object.__setattr__(self, field_name, v)
        for field_name, key in _ODOMETRY_FIELDS:
            v = _finite(key, getattr(self, field_name))
            if field_name in ("wheel_radius_left_m", "wheel_radius_right_m", "wheel_base_m",
                              "gyro_scale") and not v > 0.0:
                raise CalibrationError(f"{key} must be positive, got {v}")
            if field_name.endswith(("sigma_m", "sigma", "sigma_radps", "sqrt_hz", "sqrt_m")) and v < 0.0:
                raise CalibrationError(f"{key} must be >= 0, got {v}")
            object.__setattr__(self, field_name, v)


@dataclass(frozen=True)
class CalibrationFile:
    """Everything a calibration file holds; every part is optional.

    Fields:
        intrinsics: the camera's intrinsics (``image_width``, ``image_height``,
            ``camera_matrix``, ``distortion_coefficients``).
        reprojection_error_px: RMS reprojection error of the intrinsics calibration over
            all corners, pixels (OpenCV's ``avg_reprojection_error``); ``None`` when
            unknown, and always ``None`` without intrinsics.
        mount: the floor camera's mount on the robot.
        loop: the floor loop detector's thresholds.
        odometry: the fitted odometry model.
    """

    intrinsics: CameraIntrinsics | None = None
    reprojection_error_px: float | None = None
    mount: FloorMount | None = None
    loop: LoopThresholds | None = None
    odometry: OdometryModel | None = None

    def __post_init__(self) -> None:
        if self.reprojection_error_px is not None:
            if self.intrinsics is None:
                raise CalibrationError("avg_reprojection_error without intrinsics (camera_matrix ...)")
            err = _finite("avg_reprojection_error", self.reprojection_error_px)
            if err < 0.0:
                raise CalibrationError(f"avg_reprojection_error must be >= 0, got {err}")
            object.__setattr__(self, "reprojection_error_px", err)

    @property
    def is_empty(self) -> bool:
        """True when no part is present."""
        return (self.intrinsics is None and self.mount is None and self.loop is None
                and self.odometry is None)


def merge(base: CalibrationFile | None, update: CalibrationFile) -> CalibrationFile:
    """``base`` with every part that ``update`` has replaced; the other parts kept."""
    if base is None:
        return update
    # The reprojection error belongs to the intrinsics it was measured with.
    intr = update if update.intrinsics is not None else base
    return CalibrationFile(
        intrinsics=intr.intrinsics,
        reprojection_error_px=intr.reprojection_error_px,
        mount=update.mount if update.mount is not None else base.mount,
        loop=update.loop if update.loop is not None else base.loop,
        odometry=update.odometry if update.odometry is not None else base.odometry,
    )


# ------------------------------------------------------------------------ reading


class _Reader:
    """Typed access to the top-level keys of one parsed file; errors name the key."""

    def __init__(self, fs: Any, keys: tuple[str, ...]) -> None:
        self.fs = fs
        self.keys = set(keys)

    def has(self, key: str) -> bool:
        return key in self.keys

    def number(self, key: str) -> float:
        node = self.fs.getNode(key)
        if not (node.isInt() or node.isReal()):
            raise CalibrationError(f"{key} must be a number, got {_describe(node)}")
        return float(node.real())

    def integer(self, key: str) -> int:
        value = self.number(key)
        if not value.is_integer():
            raise CalibrationError(f"{key} must be an integer, got {value}")
        return int(value)

    def matrix(self, key: str) -> np.ndarray:
        node = self.fs.getNode(key)
        if not node.isMap() or not {"rows", "cols", "data"} <= set(node.keys()):
            raise CalibrationError(f"{key} must be an !!opencv-matrix (rows, cols, dt, data), got {_describe(node)}")
        try:
            m = node.mat()
        except (cv2.error, SystemError) as exc:
            raise CalibrationError(f"{key} is a damaged matrix: {_cv_message(exc)}") from None
        if m is None:
            raise CalibrationError(f"{key} is a damaged matrix")
        return np.asarray(m, dtype=np.float64)


def _describe(node: Any) -> str:
    if node.isString():
        return f"the string {node.string()!r}"
    if node.isInt() or node.isReal():
        return f"the number {node.real():g}"
    if node.isMap():
        return "a mapping"
    if node.isSeq():
        return "a sequence"
    if node.isNone():
        return "nothing"
    return "an unreadable value"


def _cv_message(exc: BaseException) -> str:
    """The useful last line of an OpenCV error (also when wrapped in a SystemError)."""
    cause = exc.__cause__ if isinstance(exc, SystemError) and exc.__cause__ is not None else exc
    text = str(cause).strip().splitlines()
    msg = text[-1] if text else type(exc).__name__
    # "OpenCV(5.0.0) /path/persistence_yml.cpp:681: error: (-212:Parsing error) parseValue in function ..."
    return msg.split(" error: ", 1)[-1]


def read_calibration(path: str | os.PathLike[str]) -> CalibrationFile:
    """Read a calibration file.

    Raises :class:`~robotd.base.errors.CalibrationError`, naming the path and what is wrong,
    when the file is missing or unreadable, is not YAML (binary, XML, plain text), is
    damaged (a parse error, a truncated matrix), holds no calibration at all, or has a
    missing, mistyped or out-of-range value.
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise CalibrationError(f"{p}: no such calibration file") from None
    except IsADirectoryError:
        raise CalibrationError(f"{p}: is a directory, not a calibration file") from None
    except OSError as exc:
        raise CalibrationError(f"{p}: cannot read the calibration file: {exc.strerror or exc}") from None
    try:
        return parse_calibration(raw)
    except CalibrationError as exc:
        raise CalibrationError(f"{p}: {exc}") from None


def parse_calibration(raw: bytes) -> CalibrationFile:
    """Parse the bytes of a calibration file (see :func:`read_calibration`)."""
    if b"\x00" in raw:
        raise CalibrationError("not a calibration file: binary data, expected OpenCV YAML text")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise CalibrationError("not a calibration file: not UTF-8 text, expected OpenCV YAML") from None
    head = text.lstrip()
    if not head:
        raise CalibrationError("the calibration file is empty")
    if head.startswith("<"):
        raise CalibrationError("not YAML (looks like XML); robotd calibration files are OpenCV YAML")
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_YAML)
    except (cv2.error, SystemError) as exc:
        raise CalibrationError(f"not valid OpenCV YAML: {_cv_message(exc)}") from None
    try:
        if not fs.isOpened():
            raise CalibrationError("not valid OpenCV YAML")
        root = fs.root()
        if not root.isMap():
            raise CalibrationError("not a calibration file: the YAML document is not a mapping of keys")
        keys = tuple(root.keys())
        dup = sorted({k for k in keys if keys.count(k) > 1})
        if dup:
            raise CalibrationError(f"key {dup[0]} appears more than once")
        known = _MOUNT_KEYS + _LOOP_KEYS + _ODOMETRY_KEYS
        ours = [k for k in keys if k.startswith(("mount_", "loop_", "odometry_")) and k not in known]
        if ours:
            raise CalibrationError(f"unknown key {ours[0]} (known: {', '.join(known)})")
        r = _Reader(fs, keys)
        intrinsics, err = _read_intrinsics(r)
        calib = CalibrationFile(intrinsics=intrinsics, reprojection_error_px=err, mount=_read_mount(r),
                                loop=_read_loop(r), odometry=_read_odometry(r))
    finally:
        fs.release()
    if calib.is_empty:
        raise CalibrationError(
            "holds no calibration (neither camera_matrix, nor mount_*, nor loop_*, nor odometry_* keys)")
    return calib


def _require(r: _Reader, section: str, keys: Iterable[str]) -> None:
    missing = [k for k in keys if not r.has(k)]
    if missing:
        raise CalibrationError(f"{section} is incomplete: {', '.join(missing)} missing")


def _read_intrinsics(r: _Reader) -> tuple[CameraIntrinsics | None, float | None]:
    """The intrinsics and their reprojection error (``None, None`` when absent)."""
    if not any(r.has(k) for k in _INTRINSIC_KEYS[:4]):
        return None, None
    _require(r, "the intrinsics section", _INTRINSIC_KEYS[:4])
    k = r.matrix("camera_matrix")
    if k.shape != (3, 3):
        raise CalibrationError(f"camera_matrix must be 3x3, got {k.shape[0]}x{k.shape[1] if k.ndim > 1 else 1}")
    d = r.matrix("distortion_coefficients")
    if d.ndim != 2 or min(d.shape) != 1:
        raise CalibrationError(f"distortion_coefficients must be 1xN or Nx1, got shape {d.shape}")
    err = r.number("avg_reprojection_error") if r.has("avg_reprojection_error") else None
    width, height = r.integer("image_width"), r.integer("image_height")
    try:
        return CameraIntrinsics.from_camera_matrix(k, d.ravel(), width, height), err
    except ValueError as exc:
        raise CalibrationError(str(exc)) from None


def _read_mount(r: _Reader) -> FloorMount | None:
    if not any(r.has(k) for k in _MOUNT_KEYS):
        return None
    _require(r, "the floor-mount section", _MOUNT_KEYS)
    h, t, x, y, yaw = (r.number(k) for k in _MOUNT_KEYS)
    return FloorMount(height_m=h, tilt_deg=t, x_m=x, y_m=y, yaw_deg=yaw)


def _read_loop(r: _Reader) -> LoopThresholds | None:
    if not any(r.has(k) for k in _LOOP_KEYS):
        return None
    _require(r, "the loop-threshold section", ("loop_overlap_r", "loop_confidence"))
    th = tuple(r.number(k) if r.has(k) else None for k in _LOOP_MODE_KEYS)
    return LoopThresholds(thresholds=th, overlap_r=r.number("loop_overlap_r"),
                          confidence=r.number("loop_confidence"))


def _read_odometry(r: _Reader) -> OdometryModel | None:
    if not any(r.has(k) for k in _ODOMETRY_KEYS):
        return None
    _require(r, "the odometry section", tuple(k for _f, k in _ODOMETRY_FIELDS))
    process = {f: r.number(k) for f, k in _PROCESS_FIELDS + _SLIP_EVENT_FIELDS if r.has(k)}
    return OdometryModel(**{f: r.number(k) for f, k in _ODOMETRY_FIELDS}, **process)


# ------------------------------------------------------------------------ writing


def format_calibration(calib: CalibrationFile) -> str:
    """The YAML text :func:`write_calibration` writes (OpenCV FileStorage output)."""
    if calib.is_empty:
        raise CalibrationError("refusing to write an empty calibration")
    fs = cv2.FileStorage("", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_YAML)
    fs.writeComment("robotd calibration (OpenCV FileStorage YAML). Units: pixels, metres, degrees.")
    ci = calib.intrinsics
    if ci is not None:
        fs.writeComment("Camera intrinsics; distortion_coefficients: k1 k2 p1 p2 k3.")
        fs.write("image_width", ci.width_px)
        fs.write("image_height", ci.height_px)
        fs.write("camera_matrix", ci.camera_matrix())
        fs.write("distortion_coefficients", ci.distortion_array().reshape(1, 5))
        if calib.reprojection_error_px is not None:
            fs.write("avg_reprojection_error", float(calib.reprojection_error_px))
    m = calib.mount
    if m is not None:
        fs.writeComment("Floor camera mount: lens height, forward tilt, position (x forward, y left), "
                        "image yaw (counter-clockwise from above).")
        for key, value in zip(_MOUNT_KEYS, (m.height_m, m.tilt_deg, m.x_m, m.y_m, m.yaw_deg)):
            fs.write(key, float(value))
    lp = calib.loop
    if lp is not None:
        fs.writeComment("Floor loop detector: per-mode local-score thresholds (absent = untrained), "
                        "loop overlap r, confidence.")
        for key, threshold in zip(_LOOP_MODE_KEYS, lp.thresholds):
            if threshold is not None:
                fs.write(key, float(threshold))
        fs.write("loop_overlap_r", float(lp.overlap_r))
        fs.write("loop_confidence", float(lp.confidence))
    od = calib.odometry
    if od is not None:
        fs.writeComment("Odometry model (robotd calibrate odometry): wheel radii and base (m), gyro "
                        "scale (measured / true), the drive's turn-on bias (rad/s), noise densities "
                        "(rad/s/sqrt(Hz), m/sqrt(m)), each value's 1-sigma uncertainty.")
        for field_name, key in _ODOMETRY_FIELDS:
            fs.write(key, float(getattr(od, field_name)))
        if od.has_process_noise:
            fs.writeComment("The filter's white accelerations (m/s^2, rad/s^2 per sqrt(Hz)) by maximum "
                            "likelihood on the drive's readings, each with its 1-sigma.")
            for field_name, key in _PROCESS_FIELDS:
                fs.write(key, float(getattr(od, field_name)))
        if od.has_slip_events:
            fs.writeComment("The wheel slip events: their rate (a second of accelerating or turning) and "
                            "RMS duration (s), from the slip the drive's heading windows saw, each with its 1-sigma.")
            for field_name, key in _SLIP_EVENT_FIELDS:
                fs.write(key, float(getattr(od, field_name)))
    return fs.releaseAndGetString()


def write_calibration(path: str | os.PathLike[str], calib: CalibrationFile) -> None:
    """Write ``calib`` to ``path`` atomically.

    The text goes to a temporary file in the same directory, is flushed to disk, and then
    replaces ``path`` in one ``os.replace``: readers see the old file or the new one,
    never a mixture. Raises :class:`~robotd.base.errors.CalibrationError` when it cannot write.
    """
    p = Path(path)
    data = format_calibration(calib).encode("utf-8")
    directory = p.parent if str(p.parent) else Path(".")
    tmp = directory / f".{p.name}.{os.getpid()}.{os.urandom(4).hex()}.tmp"
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, p)
    except OSError as exc:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise CalibrationError(f"{p}: cannot write the calibration file: {exc.strerror or exc}") from None
    try:  # make the rename itself durable
        dfd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass
    logger.info("wrote calibration %s", p)


def update_calibration(path: str | os.PathLike[str], update: CalibrationFile) -> CalibrationFile:
    """Merge ``update`` into the file at ``path`` (created if missing); returns the result.

    An existing file that cannot be read is never overwritten: the error is raised
    instead, so a damaged calibration is looked at rather than silently replaced.
    """
    p = Path(path)
    base = read_calibration(p) if p.exists() else None
    merged = merge(base, update)
    write_calibration(p, merged)
    return merged


# ----------------------------------------------------------------- camera model


def camera_model(calib: CalibrationFile | None, fallback_config: Any) -> FloorCameraModel:
    """The floor camera model: calibrated parts from ``calib``, the rest from the config.

    ``fallback_config`` is a ``[floor_camera]`` section (duck-typed like
    :meth:`FloorCameraModel.from_config`): the image size always comes from it (that is
    what the camera is asked to deliver); intrinsics come from ``calib.intrinsics`` and the
    mount from ``calib.mount`` when present, else from the config's ``fx_px`` .. and
    ``mount_*`` keys. Raises :class:`~robotd.base.errors.CalibrationError` when the calibrated
    intrinsics belong to another image size.
    """
    base = FloorCameraModel.from_config(fallback_config)
    values: dict[str, Any] = {}
    ci = calib.intrinsics if calib is not None else None
    if ci is not None:
        if (ci.width_px, ci.height_px) != (base.width_px, base.height_px):
            raise CalibrationError(
                f"the calibration is for {ci.width_px}x{ci.height_px} images but the floor camera "
                f"delivers {base.width_px}x{base.height_px}; recalibrate at that size")
        values.update(intrinsics=ci)
    m = calib.mount if calib is not None else None
    if m is not None:
        values.update(height_m=m.height_m, tilt_rad=math.radians(m.tilt_deg), offset_x_m=m.x_m,
                      offset_y_m=m.y_m, yaw_rad=math.radians(m.yaw_deg))
    return replace(base, **values) if values else base
