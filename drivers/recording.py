"""Recordings: a run written to MCAP with ROS 2 message types, read and replayed back.

A recording is one `MCAP <https://mcap.dev>`_ file (profile ``ros2``, CDR-encoded
messages) whose schemas are ROS 2 ``.msg`` definitions embedded as text, dependencies
included, so Foxglove and ``ros2 bag`` (with the MCAP storage plugin) open it without
robotd or a ROS workspace. Writing and reading use ``mcap`` and ``mcap-ros2-support``;
no ROS install is needed.

Topics (ROS 2 type -> what :func:`read_recording` gives back):

- ``/wheel_ticks``: ``robotd_msgs/msg/WheelTicks`` -> :class:`~robotd.messages.WheelTicks`
- ``/imu``: ``sensor_msgs/msg/Imu`` -> :class:`~robotd.messages.YawRate`
- ``/floor_camera/image/compressed``, ``/forward_camera/image/compressed``:
  ``sensor_msgs/msg/CompressedImage`` -> :class:`~robotd.messages.Frame`
- ``/odom`` (fused odometry), ``/ground_truth`` (virtual robot only), and any other
  topic given to :meth:`RecordingWriter.write_odometry`: ``nav_msgs/msg/Odometry`` ->
  :class:`~robotd.messages.PoseStamped`

Conventions:

- Publish time and the header stamp are the message's ``stamp_ns`` (the header splits it
  into ``sec``/``nanosec``). Log time is the stamp too, except that on the base stream
  (``/wheel_ticks`` and ``/imu``, which arrive together from one driver) it never goes
  back: a gyro sample stamped before the wheel reading received ahead of it is logged at
  that reading's time, so a replay hands the base messages to odometry in the order the
  daemon received them and reproduces its estimate exactly. Stamps are robotd's time base (host monotonic time,
  or the virtual robot's time from 0), not Unix time, so tools show dates near 1970.
- ``robotd_msgs/msg/WheelTicks`` is ours (no standard ROS 2 message holds raw 16-bit
  encoder counters); its definition travels in the file like the others. No
  ``/joint_states`` is written: wheel angles need the base's ticks per turn and unwrapped
  counters, which are odometry's business, not the recorder's.
- ``/imu``: only ``angular_velocity.z`` (the yaw rate, rad/s, counter-clockwise positive)
  is measured. ``orientation_covariance[0]`` and ``linear_acceleration_covariance[0]``
  are -1 ("not provided", as ``sensor_msgs/Imu`` defines); the angular velocity covariance
  is all zero ("unknown"). :attr:`YawRate.source <robotd.messages.YawRate.source>` has no
  ROS field; it is kept in the metadata record ``robotd.imu`` (the first source written;
  a later different source is logged and counted, and reads back as the first).
- Frames: PNG by default (lossless, so a replay gives the daemon the very pixels it saw)
  or JPEG (``image_format="jpeg"``, lossy; 2 to 4 times smaller on the virtual camera's
  noisy 640x480 frames, at quality 90 to 75). The frame's ``seq``
  is the MCAP message ``sequence``; the camera name is the topic's
  ``/<camera>_camera/image/compressed``; ``frame_id`` is ``<camera>_camera_optical_frame``.
- ``/odom`` (``frame_id`` ``odom``, ``child_frame_id`` ``base_footprint``): the 3x3
  (x, y, yaw) covariance goes into rows/columns 0, 1, 5 of the 6x6 pose covariance; z,
  roll and pitch are fixed on a flat floor and carry zero variance. The twist is not
  estimated and is written as zero with zero covariance. ``/ground_truth`` has
  ``frame_id`` ``world``. Yaw reads back wrapped to [-pi, pi].
- Metadata record ``robotd``: ``robotd_version``, ``config_toml``, ``start_time_utc``
  (ISO 8601, the host's wall clock, for people), ``image_format``, ``stamp_time_base``.

Crash safety (the choice made here): the writer writes ``NAME.partial`` and renames it to
``NAME`` only after :meth:`RecordingWriter.close` has written the summary and fsynced, so
a file under the final name is always complete. Messages are grouped in zstd-compressed
MCAP chunks of ``chunk_size`` bytes (default 256 KiB: one or two PNG floor frames with the
base data between them, or about 5 s of base-only data), and each finished chunk goes
straight to the operating system, so a process that dies loses only the chunk being
filled; a power cut can also lose what the kernel had not yet written. A ``.partial``
file is readable as it is by :class:`RecordingReader` (every complete chunk), or can be
finished with the ``mcap`` command-line tool's ``recover``.

Damage policy of the reader: a path that cannot be opened, is not MCAP, or is cut inside
its header raises :class:`~robotd.errors.DriverError` naming the path. Anything else is
read as far as it can be: with no valid summary (an interrupted or truncated recording)
the file is scanned record by record and every complete chunk with a good CRC is used; a
chunk that is incomplete, fails its CRC or does not decompress is skipped; a message that
does not decode (CDR or image) is skipped. Every such loss is counted in
:class:`RecordingDamage` and logged as a warning naming the path. Nothing raises a raw
``mcap`` exception. MCAP stores a channel's definition once, in the chunk where its topic
first appears (and again in the summary): in a file without a summary whose chunk holding
that definition is damaged, the topic's later messages cannot be decoded and are counted
as undecodable. Messages come out in log-time order by merging chunks on their time
ranges, so memory holds only the chunks that overlap in time.

:class:`ReplaySource` feeds a recording to the daemon through two driver-like
sub-sources (``replay.base``, ``replay.floor``), as fast as possible or paced at a
multiple of recorded speed.
"""

from __future__ import annotations

import datetime
import heapq
import io
import logging
import math
import os
import queue
import re
import struct
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Header, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer

from robotd.clock import ManualClock
from robotd.errors import DriverError, RobotdError
from robotd.messages import Frame, PoseStamped, WheelTicks, YawRate

__all__ = [
    "PARTIAL_SUFFIX",
    "TOPIC_GROUND_TRUTH",
    "TOPIC_IMU",
    "TOPIC_ODOM",
    "TOPIC_WHEEL_TICKS",
    "OdometryRecorder",
    "RecordingDamage",
    "RecordingReader",
    "RecordingTee",
    "RecordingWriter",
    "ReplayQueue",
    "ReplaySource",
    "camera_topic",
    "read_recording",
    "schema_text",
]

log = logging.getLogger(__name__)

TOPIC_WHEEL_TICKS = "/wheel_ticks"
TOPIC_IMU = "/imu"
TOPIC_ODOM = "/odom"
TOPIC_GROUND_TRUTH = "/ground_truth"
PARTIAL_SUFFIX = ".partial"
"""Suffix of a recording being written (``run.mcap.partial`` until close)."""

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_CAMERA_TOPIC = re.compile(r"^/([A-Za-z][A-Za-z0-9_]*)_camera/image/compressed$")
_CAMERA_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_NS_PER_S = 1_000_000_000
_MAX_STAMP_NS = (1 << 31) * _NS_PER_S  # builtin_interfaces/Time.sec is an int32
_RECORD_HEAD = struct.Struct("<BQ")  # opcode u8, record length u64

# --------------------------------------------------------------------------------------
# ROS 2 message definitions. Each schema written to the file is its type's definition
# followed by every type it uses, each after a line of '=' and a "MSG: pkg/Name" line,
# which is how rosbag2 and mcap-ros2-support expect a self-contained definition.
# --------------------------------------------------------------------------------------

_MSG_DEFS: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/msg/PoseWithCovariance": "Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/msg/Twist": "Vector3 linear\nVector3 angular\n",
    "geometry_msgs/msg/TwistWithCovariance": "Twist twist\nfloat64[36] covariance\n",
    "nav_msgs/msg/Odometry": (
        "std_msgs/Header header\n"
        "string child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\n"
        "geometry_msgs/TwistWithCovariance twist\n"
    ),
    "sensor_msgs/msg/Imu": (
        "std_msgs/Header header\n"
        "geometry_msgs/Quaternion orientation\n"
        "float64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\n"
        "float64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\n"
        "float64[9] linear_acceleration_covariance\n"
    ),
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "robotd_msgs/msg/WheelTicks": (
        "# Raw wheel encoder counters of a differential-drive base, as the base reports them.\n"
        "# The counters wrap at 16 bits; consumers unwrap consecutive differences.\n"
        "std_msgs/Header header\n"
        "uint16 left_ticks   # left wheel encoder counter, ticks, 0..65535, wrapping\n"
        "uint16 right_ticks  # right wheel encoder counter, ticks, 0..65535, wrapping\n"
        "uint16 device_ms    # the base's own millisecond clock, 0..65535, wrapping\n"
    ),
}

_PRIMITIVES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
    "int32", "uint32", "int64", "uint64", "string", "wstring",
})


def _dependencies(name: str) -> list[str]:
    """Full names of the types ``name`` uses, depth first, each once."""
    pkg = name.split("/")[0]
    out: list[str] = []
    for line in _MSG_DEFS[name].splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        ftype = re.sub(r"\[.*\]$", "", line.split()[0])
        if ftype in _PRIMITIVES or ftype.startswith("string<"):
            continue
        dep_pkg, dep_name = ftype.split("/") if "/" in ftype else (pkg, ftype)
        full = f"{dep_pkg}/msg/{dep_name}"
        for d in (full, *_dependencies(full)):
            if d not in out:
                out.append(d)
    return out


def schema_text(name: str) -> str:
    """The self-contained ROS 2 definition of ``name`` (e.g. ``"nav_msgs/msg/Odometry"``)."""
    parts = [_MSG_DEFS[name].rstrip("\n")]
    for dep in _dependencies(name):
        pkg, _, msg = dep.split("/")
        parts.append("=" * 80 + f"\nMSG: {pkg}/{msg}\n" + _MSG_DEFS[dep].rstrip("\n"))
    return "\n".join(parts) + "\n"


def camera_topic(camera: str) -> str:
    """The topic of camera ``camera``'s compressed images: ``/<camera>_camera/image/compressed``."""
    if not _CAMERA_NAME.match(camera):
        raise ValueError(f"camera name {camera!r} cannot be part of a ROS topic name")
    return f"/{camera}_camera/image/compressed"


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


class _UnbufferedSink:
    """The file under the MCAP writer: every write goes to the OS at once.

    ``mcap`` writes a chunk (and its indexes) only when the chunk is full, so each write
    here is a finished piece of the recording that must survive a process crash.
    """

    def __init__(self, fd: int) -> None:
        self._fd = fd
        self._pos = 0

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
        self._pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass


def _header(stamp_ns: int, frame_id: str) -> dict[str, Any]:
    sec, nanosec = divmod(stamp_ns, _NS_PER_S)
    return {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": frame_id}


def _check_stamp(stamp_ns: int) -> int:
    s = int(stamp_ns)
    if not 0 <= s < _MAX_STAMP_NS:
        raise ValueError(f"stamp_ns {stamp_ns} is outside 0 .. 2^31 s (ROS time)")
    return s


def _check_u16(name: str, value: int) -> int:
    v = int(value)
    if not 0 <= v <= 0xFFFF:
        raise ValueError(f"{name} {value} does not fit a uint16")
    return v


def _odometry_dict(stamp_ns: int, x_m: float, y_m: float, yaw_rad: float, cov3: np.ndarray,
                   frame_id: str, child_frame_id: str) -> dict[str, Any]:
    cov3 = np.asarray(cov3, dtype=np.float64)
    if cov3.shape != (3, 3):
        raise ValueError(f"pose covariance must be (3, 3), got {cov3.shape}")
    cov6 = np.zeros((6, 6))
    cov6[np.ix_((0, 1, 5), (0, 1, 5))] = cov3
    half = 0.5 * float(yaw_rad)
    return {
        "header": _header(stamp_ns, frame_id),
        "child_frame_id": child_frame_id,
        "pose": {
            "pose": {
                "position": {"x": float(x_m), "y": float(y_m), "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)},
            },
            "covariance": cov6.ravel().tolist(),
        },
        "twist": {"twist": {}, "covariance": [0.0] * 36},
    }


class RecordingWriter:
    """Writes a run to an MCAP file with ROS 2 message types; a context manager.

    ``path`` is the final name; until :meth:`close` the data goes to ``path + ".partial"``
    (see the module doc for what survives a crash). An existing ``path`` is an error
    unless ``overwrite``. ``image_format`` is ``"png"`` (lossless, default) or ``"jpeg"``;
    ``png_compression`` is zlib's level 0-9 (1: fastest, what a 30 Hz camera needs),
    ``jpeg_quality`` 0-100. ``config_toml`` (the daemon's configuration) and
    ``start_time_utc`` (default: now) go into the ``robotd`` metadata record.
    ``chunk_size`` (bytes of messages per compressed chunk) bounds what a crash can lose.

    The ``write_*`` methods may be called from several threads. Methods raise
    ``ValueError`` for a message that cannot be represented (negative stamp, counter out
    of range, bad image) and :class:`~robotd.errors.DriverError` naming the file when the
    disk fails.
    """

    def __init__(self, path: str | os.PathLike[str], *, image_format: str = "png",
                 png_compression: int = 1, jpeg_quality: int = 90, config_toml: str = "",
                 start_time_utc: datetime.datetime | None = None,
                 chunk_size: int = 256 * 1024, overwrite: bool = False,
                 imu_frame_id: str = "gyro_link") -> None:
        if image_format not in ("png", "jpeg"):
            raise ValueError(f"image_format must be 'png' or 'jpeg', got {image_format!r}")
        if not 0 <= png_compression <= 9:
            raise ValueError("png_compression must be 0..9")
        if not 0 <= jpeg_quality <= 100:
            raise ValueError("jpeg_quality must be 0..100")
        if chunk_size < 1024:
            raise ValueError("chunk_size must be at least 1024 bytes")
        from robotd import __version__

        self.path = Path(path)
        self.partial_path = self.path.with_name(self.path.name + PARTIAL_SUFFIX)
        self.image_format = image_format
        self.imu_frame_id = imu_frame_id
        if image_format == "png":
            self._encode_ext, self._encode_params = ".png", [cv2.IMWRITE_PNG_COMPRESSION, png_compression]
        else:
            self._encode_ext, self._encode_params = ".jpg", [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality]
        if self.path.exists() and not overwrite:
            raise DriverError(f"{self.path}: a recording already exists (choose another name)")
        flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL)
        try:
            self._fd = os.open(self.partial_path, flags, 0o644)
        except FileExistsError as exc:
            raise DriverError(f"{self.partial_path}: an interrupted recording is in the way (read "
                              "it, or remove it, first)") from exc
        except OSError as exc:
            raise DriverError(f"{self.partial_path}: cannot create the recording: {exc.strerror}") from exc
        self._lock = threading.Lock()
        self._base_log_time_ns = 0  # the base stream's log time never goes back (module docs)
        self._closed = False
        self._yaw_source: str | None = None
        self.counts: dict[str, int] = {}
        """Messages written per topic."""
        self.mixed_yaw_sources = 0
        """Yaw rates whose ``source`` differed from the first one's (stored as the first)."""
        start = start_time_utc or datetime.datetime.now(datetime.UTC)
        try:
            self._mcap = Ros2Writer(_UnbufferedSink(self._fd), chunk_size=chunk_size,
                                    compression=CompressionType.ZSTD)
            self._mcap.add_metadata("robotd", {
                "robotd_version": __version__,
                "config_toml": config_toml,
                "start_time_utc": start.isoformat(),
                "image_format": image_format,
                "stamp_time_base": "robotd clock (host monotonic or virtual robot time), not Unix time",
            })
        except OSError as exc:
            os.close(self._fd)
            self.partial_path.unlink(missing_ok=True)
            raise DriverError(f"{self.partial_path}: cannot write: {exc.strerror}") from exc
        self._schemas: dict[str, Any] = {}

    # -- writing ---------------------------------------------------------------------

    def _write(self, topic: str, type_name: str, stamp_ns: int, msg: dict[str, Any],
               sequence: int = 0) -> None:
        with self._lock:
            if self._closed:
                raise ValueError(f"{self.path}: the recording is closed")
            try:
                schema = self._schemas.get(type_name)
                if schema is None:
                    schema = self._mcap.register_msgdef(type_name, schema_text(type_name))
                    self._schemas[type_name] = schema
                log_time = stamp_ns
                if topic in (TOPIC_WHEEL_TICKS, TOPIC_IMU):
                    log_time = self._base_log_time_ns = max(self._base_log_time_ns, stamp_ns)
                self._mcap.write_message(topic, schema, msg, log_time=log_time,
                                         publish_time=stamp_ns, sequence=sequence)
            except OSError as exc:
                raise DriverError(f"{self.partial_path}: cannot write: {exc.strerror}") from exc
            self.counts[topic] = self.counts.get(topic, 0) + 1

    def write_wheel_ticks(self, msg: WheelTicks) -> None:
        """``/wheel_ticks`` (``robotd_msgs/msg/WheelTicks``, frame ``base_link``)."""
        stamp = _check_stamp(msg.stamp_ns)
        self._write(TOPIC_WHEEL_TICKS, "robotd_msgs/msg/WheelTicks", stamp, {
            "header": _header(stamp, "base_link"),
            "left_ticks": _check_u16("left_ticks", msg.left_ticks),
            "right_ticks": _check_u16("right_ticks", msg.right_ticks),
            "device_ms": _check_u16("device_ms", msg.device_ms),
        })

    def write_yaw_rate(self, msg: YawRate) -> None:
        """``/imu`` (``sensor_msgs/msg/Imu``): ``angular_velocity.z`` = the yaw rate, rad/s."""
        stamp = _check_stamp(msg.stamp_ns)
        if self._closed:
            raise ValueError(f"{self.path}: the recording is closed")
        if self._yaw_source is None:
            with self._lock:
                if self._yaw_source is None and not self._closed:
                    try:
                        self._mcap.add_metadata("robotd.imu", {"topic": TOPIC_IMU, "yaw_source": msg.source})
                    except OSError as exc:
                        raise DriverError(f"{self.partial_path}: cannot write: {exc.strerror}") from exc
                    self._yaw_source = msg.source
        if msg.source != self._yaw_source:
            if self.mixed_yaw_sources == 0:
                log.warning("%s: yaw rates from %r after %r; the recording keeps %r for all",
                            self.path, msg.source, self._yaw_source, self._yaw_source)
            self.mixed_yaw_sources += 1
        self._write(TOPIC_IMU, "sensor_msgs/msg/Imu", stamp, {
            "header": _header(stamp, self.imu_frame_id),
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            "orientation_covariance": [-1.0] + [0.0] * 8,
            "angular_velocity": {"x": 0.0, "y": 0.0, "z": float(msg.yaw_rate_radps)},
            "angular_velocity_covariance": [0.0] * 9,
            "linear_acceleration": {"x": 0.0, "y": 0.0, "z": 0.0},
            "linear_acceleration_covariance": [-1.0] + [0.0] * 8,
        })

    def write_frame(self, frame: Frame) -> None:
        """``/<camera>_camera/image/compressed`` (``sensor_msgs/msg/CompressedImage``).

        ``frame.image`` is ``(H, W) uint8`` or ``(H, W, 3) uint8`` (BGR); it is encoded
        in the calling thread (PNG level 1 of a 640x480 grey frame: a few milliseconds).
        """
        stamp = _check_stamp(frame.stamp_ns)
        topic = camera_topic(frame.camera)
        img = frame.image
        if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
            raise ValueError(f"frame image must be (H, W) or (H, W, 3) uint8, got {img.shape} {img.dtype}")
        ok, buf = cv2.imencode(self._encode_ext, img, self._encode_params)
        if not ok:
            raise ValueError(f"cannot encode a {img.shape} frame as {self.image_format}")
        self._write(topic, "sensor_msgs/msg/CompressedImage", stamp, {
            "header": _header(stamp, f"{frame.camera}_camera_optical_frame"),
            "format": self.image_format,
            "data": buf.tobytes(),
        }, sequence=int(frame.seq) & 0xFFFFFFFF)

    def write_odometry(self, pose: PoseStamped, topic: str = TOPIC_ODOM, *,
                       frame_id: str = "odom", child_frame_id: str = "base_footprint") -> None:
        """A planar pose estimate as ``nav_msgs/msg/Odometry`` on ``topic`` (default ``/odom``)."""
        stamp = _check_stamp(pose.stamp_ns)
        self._write(topic, "nav_msgs/msg/Odometry", stamp, _odometry_dict(
            stamp, pose.x_m, pose.y_m, pose.yaw_rad, pose.covariance, frame_id, child_frame_id))

    def write_ground_truth(self, stamp_ns: int, x_m: float, y_m: float, yaw_rad: float) -> None:
        """The virtual robot's true pose on ``/ground_truth`` (``nav_msgs/msg/Odometry``,
        frame ``world``, zero covariance)."""
        stamp = _check_stamp(stamp_ns)
        self._write(TOPIC_GROUND_TRUTH, "nav_msgs/msg/Odometry", stamp, _odometry_dict(
            stamp, x_m, y_m, yaw_rad, np.zeros((3, 3)), "world", "base_footprint"))

    # -- closing ---------------------------------------------------------------------

    def close(self, *, completed: bool = True, reason: str = "") -> None:
        """Finish the file (summary and indexes), fsync it and rename it to :attr:`path`.

        Safe to call twice. ``completed=False`` (what leaving the ``with`` block by an
        exception passes) still finishes the file, whose data are valid, and records
        ``completed: false`` and ``reason`` in the ``robotd.end`` metadata record.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._mcap.add_metadata("robotd.end", {
                    "completed": "true" if completed else "false", "reason": reason,
                    "messages": str(sum(self.counts.values()))})
                self._mcap.finish()
                os.fsync(self._fd)
            except OSError as exc:
                raise DriverError(f"{self.partial_path}: cannot finish the recording: "
                                  f"{exc.strerror}") from exc
            finally:
                os.close(self._fd)
            os.replace(self.partial_path, self.path)
            try:
                dir_fd = os.open(self.path.parent if str(self.path.parent) else ".", os.O_RDONLY)
                try:
                    os.fsync(dir_fd)
                finally:
                    os.close(dir_fd)
            except OSError:  # some filesystems cannot fsync a directory; the data are safe
                log.debug("%s: could not fsync the directory", self.path, exc_info=True)
        log.info("%s: recording closed (%d messages)", self.path, sum(self.counts.values()))

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.close()
        else:
            self.close(completed=False, reason=f"{exc_type.__name__}: {exc}")


class RecordingTee:
    """A driver wrapper: ``read`` returns what ``source.read`` returns and records it.

    Wrap a base driver (WheelTicks and YawRate) or a camera (Frame) before handing it to
    the daemon, so the recording holds exactly what the daemon received. ``close``
    closes the wrapped source, not the writer.
    """

    def __init__(self, source: Any, writer: RecordingWriter) -> None:
        self.source = source
        self.writer = writer

    def read(self, timeout_s: float) -> Any:
        got = self.source.read(timeout_s)
        if got is not None:
            for msg in got if isinstance(got, list) else (got,):
                self._record(msg)
        return got

    def _record(self, msg: Any) -> None:
        if isinstance(msg, WheelTicks):
            self.writer.write_wheel_ticks(msg)
        elif isinstance(msg, YawRate):
            self.writer.write_yaw_rate(msg)
        elif isinstance(msg, Frame):
            self.writer.write_frame(msg)

    def close(self) -> None:
        self.source.close()

    def __getattr__(self, name: str) -> Any:  # driver extras (stats, request_extra, ...)
        if name == "source":
            raise AttributeError(name)
        return getattr(self.source, name)


class OdometryRecorder:
    """A pipeline observer that records the fused odometry on ``/odom`` and, when
    ``wheel_topic`` is given (e.g. ``"/odom/wheel"``), the wheel-only odometry too."""

    def __init__(self, writer: RecordingWriter, wheel_topic: str | None = None) -> None:
        self.writer = writer
        self.wheel_topic = wheel_topic

    def on_odometry(self, fused: PoseStamped, wheel: PoseStamped) -> None:
        self.writer.write_odometry(fused, TOPIC_ODOM)
        if self.wheel_topic:
            self.writer.write_odometry(wheel, self.wheel_topic)

    def on_keyframe(self, keyframe_id: int, frame: Frame, pose: PoseStamped) -> None:
        pass

    def on_floor_query(self, query: Any) -> None:
        pass


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------


@dataclass
class RecordingDamage:
    """What could not be read from a recording (all zero/False for a sound file)."""

    no_summary: bool = False
    """The file has no valid summary (recording interrupted, or file cut); it was scanned."""
    unread_tail_bytes: int = 0
    """Bytes at the end that do not form a complete record (a cut inside a record)."""
    damaged_chunks: int = 0
    """Chunks skipped: incomplete, failing their CRC, or not decompressible."""
    undecodable_messages: int = 0
    """Messages skipped because their CDR data or their image did not decode."""

    @property
    def any(self) -> bool:
        """True when anything was lost or had to be recovered."""
        return bool(self.no_summary or self.unread_tail_bytes or self.damaged_chunks
                    or self.undecodable_messages)

    def as_dict(self) -> dict[str, int | bool]:
        return {"no_summary": self.no_summary, "unread_tail_bytes": self.unread_tail_bytes,
                "damaged_chunks": self.damaged_chunks,
                "undecodable_messages": self.undecodable_messages}


@dataclass(frozen=True)
class _ChunkRef:
    """Where a chunk (or a message written outside any chunk) starts, and its time span."""

    offset: int
    start_ns: int
    end_ns: int


RobotdMessage = WheelTicks | YawRate | Frame | PoseStamped


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * _NS_PER_S + int(header.stamp.nanosec)


def _yaw_from_quaternion(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _normalise_type(name: str) -> str:
    """``sensor_msgs/Imu`` and ``sensor_msgs/msg/Imu`` name the same type."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[-1]}" if len(parts) in (2, 3) else name


class RecordingReader:
    """Reads a recording back as robotd messages; a context manager.

    Opening reads the header and the summary (or, when there is none, scans the file):
    :attr:`metadata`, :attr:`topics` and :attr:`damage` are known from then on, and
    :attr:`damage` grows while :meth:`messages` runs into damaged chunks or messages.
    Raises :class:`~robotd.errors.DriverError` naming the path when the file cannot be
    opened or is not an MCAP file (see the module doc for the damage policy).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.damage = RecordingDamage()
        self.skipped: dict[str, int] = {}
        """Messages of topics or types robotd does not read, per topic (not damage)."""
        self.metadata: dict[str, dict[str, str]] = {}
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._chunks: list[_ChunkRef] = []
        self._summary_failed = False
        self._lock = threading.Lock()
        try:
            self._f = open(self.path, "rb")
        except OSError as exc:
            raise DriverError(f"{self.path}: cannot open the recording: {exc.strerror}") from exc
        try:
            self._size = os.fstat(self._f.fileno()).st_size
            self._read_header()
            if not self._read_summary():
                self._scan()
        except RobotdError:
            self._f.close()
            raise
        except OSError as exc:
            self._f.close()
            raise DriverError(f"{self.path}: cannot read the recording: {exc.strerror}") from exc
        if self.damage.any:
            log.warning("%s: damaged recording, reading what is intact (%s)", self.path,
                        ", ".join(f"{k} {v}" for k, v in self.damage.as_dict().items() if v))

    # -- opening -----------------------------------------------------------------------

    def _read_header(self) -> None:
        self._f.seek(0)
        magic = self._f.read(len(_MCAP_MAGIC))
        if magic != _MCAP_MAGIC:
            what = "is empty" if not magic else ("is cut before its header" if _MCAP_MAGIC.startswith(magic)
                                                 else "is not an MCAP file")
            raise DriverError(f"{self.path}: not a readable recording: the file {what}")
        head = self._f.read(_RECORD_HEAD.size)
        if len(head) == _RECORD_HEAD.size:
            opcode, length = _RECORD_HEAD.unpack(head)
            body = self._f.read(length) if length <= self._size else b""
            if opcode == Opcode.HEADER and len(body) == length:
                try:
                    Header.read(ReadDataStream(io.BytesIO(body)))
                    return
                except Exception:  # noqa: BLE001 - a malformed header is reported below
                    pass
        raise DriverError(f"{self.path}: not a readable recording: the file is cut or damaged "
                          "inside its header")

    def _read_summary(self) -> bool:
        """Use the file's summary; False when it has none that can be trusted."""
        self._f.seek(0)
        try:
            reader = SeekingReader(self._f)
            summary = reader.get_summary()
            if summary is None:
                return False
            metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except Exception:  # noqa: BLE001 - mcap raises many kinds on a cut file; we scan instead
            log.debug("%s: no usable summary", self.path, exc_info=True)
            self._summary_failed = True
            return False
        self._schemas = dict(summary.schemas)
        self._channels = dict(summary.channels)
        stats = summary.statistics
        if not summary.chunk_indexes and (stats is None or stats.message_count > 0):
            return False  # messages outside chunks (an unchunked file): only a scan finds them
        self._chunks = [_ChunkRef(ci.chunk_start_offset, ci.message_start_time, ci.message_end_time)
                        for ci in summary.chunk_indexes]
        self.metadata = metadata
        return True

    def _scan(self) -> None:
        """Walk the records from the start, keeping every complete, sound chunk (and any
        message written outside a chunk)."""
        self._f.seek(-len(_MCAP_MAGIC), os.SEEK_END)
        self.damage.no_summary = self._f.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC or self._summary_failed
        pos = len(_MCAP_MAGIC)
        self._f.seek(pos)
        while True:
            head = self._f.read(_RECORD_HEAD.size)
            if len(head) < _RECORD_HEAD.size:
                self.damage.unread_tail_bytes = self._size - pos
                return
            opcode, length = _RECORD_HEAD.unpack(head)
            end = pos + _RECORD_HEAD.size + length
            if end > self._size or opcode == 0:
                self.damage.unread_tail_bytes = self._size - pos
                return
            if opcode in (Opcode.DATA_END, Opcode.FOOTER):
                return  # the data section is complete; only the summary was bad
            if opcode in (Opcode.CHUNK, Opcode.MESSAGE, Opcode.SCHEMA, Opcode.CHANNEL, Opcode.METADATA):
                body = self._f.read(length)
                self._scan_record(opcode, body, pos)
            else:
                self._f.seek(end)
            pos = end

    def _scan_record(self, opcode: int, body: bytes, offset: int) -> None:
        stream = ReadDataStream(io.BytesIO(body))
        try:
            if opcode == Opcode.CHUNK:
                chunk = Chunk.read(stream)
                records = breakup_chunk(chunk, validate_crc=True)
                for rec in records:
                    self._remember(rec)
                if any(isinstance(r, Message) for r in records):
                    self._chunks.append(_ChunkRef(offset, chunk.message_start_time, chunk.message_end_time))
            elif opcode == Opcode.MESSAGE:
                m = Message.read(stream, len(body))
                self._chunks.append(_ChunkRef(offset, m.log_time, m.log_time))
            elif opcode == Opcode.SCHEMA:
                self._remember(Schema.read(stream))
            elif opcode == Opcode.CHANNEL:
                self._remember(Channel.read(stream))
            elif opcode == Opcode.METADATA:
                m = Metadata.read(stream)
                self.metadata[m.name] = dict(m.metadata)
        except Exception:  # noqa: BLE001 - damaged bytes: mcap, zstd or struct errors
            log.debug("%s: damaged record at offset %d", self.path, offset, exc_info=True)
            if opcode in (Opcode.CHUNK, Opcode.MESSAGE):
                self.damage.damaged_chunks += 1

    def _remember(self, rec: Any) -> None:
        if isinstance(rec, Schema):
            self._schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            self._channels[rec.id] = rec

    # -- what is inside ----------------------------------------------------------------

    @property
    def schemas(self) -> dict[int, Schema]:
        """The file's MCAP schema records by id."""
        return dict(self._schemas)

    @property
    def channels(self) -> dict[int, Channel]:
        """The file's MCAP channel records by id."""
        return dict(self._channels)

    @property
    def topics(self) -> dict[str, str]:
        """Topic -> schema name of every channel in the recording."""
        out = {}
        for ch in self._channels.values():
            schema = self._schemas.get(ch.schema_id)
            out[ch.topic] = schema.name if schema is not None else ""
        return out

    @property
    def time_range_ns(self) -> tuple[int, int] | None:
        """``(first, last)`` log time of the intact messages (from the chunks' time
        ranges), or None when there are none; e.g. ``ManualClock(reader.time_range_ns[0])``
        starts a replay's clock at the recording's start."""
        if not self._chunks:
            return None
        return min(c.start_ns for c in self._chunks), max(c.end_ns for c in self._chunks)

    @property
    def yaw_source(self) -> str:
        """``YawRate.source`` of the recorded yaw rates (``"gyro"`` when not recorded)."""
        return self.metadata.get("robotd.imu", {}).get("yaw_source", "gyro")

    # -- messages ----------------------------------------------------------------------

    def _load_chunk(self, ref: _ChunkRef) -> list[Any]:
        try:
            with self._lock:
                self._f.seek(ref.offset)
                head = self._f.read(_RECORD_HEAD.size)
                opcode, length = _RECORD_HEAD.unpack(head) if len(head) == _RECORD_HEAD.size else (0, 0)
                end = ref.offset + _RECORD_HEAD.size + length
                ok = opcode in (Opcode.CHUNK, Opcode.MESSAGE) and end <= self._size
                body = self._f.read(length) if ok else b""
        except OSError as exc:
            raise DriverError(f"{self.path}: cannot read the recording: {exc.strerror}") from exc
        try:
            if not body:
                raise ValueError("no complete chunk at this offset")
            stream = ReadDataStream(io.BytesIO(body))
            if opcode == Opcode.MESSAGE:
                return [Message.read(stream, len(body))]
            return breakup_chunk(Chunk.read(stream), validate_crc=True)
        except Exception as exc:  # noqa: BLE001 - damaged bytes: mcap, zstd or struct errors
            self.damage.damaged_chunks += 1
            log.warning("%s: skipping the damaged chunk at offset %d (%s)", self.path, ref.offset, exc)
            return []

    def raw_messages(self) -> Iterator[tuple[Channel, Message]]:
        """Every intact MCAP message in log-time order (ties: file order)."""
        refs = sorted(self._chunks, key=lambda r: (r.start_ns, r.offset))
        heap: list[tuple[int, int, int, Message]] = []
        for ref in refs:
            # Later chunks start no earlier than this one, so anything before its start
            # is final.
            while heap and heap[0][:3] < (ref.start_ns, ref.offset, 0):
                msg = heapq.heappop(heap)[3]
                yield self._channels[msg.channel_id], msg
            for i, rec in enumerate(self._load_chunk(ref)):
                if isinstance(rec, Message):
                    if rec.channel_id not in self._channels:
                        self.damage.undecodable_messages += 1
                        continue
                    heapq.heappush(heap, (rec.log_time, ref.offset, i, rec))
        while heap:
            msg = heapq.heappop(heap)[3]
            yield self._channels[msg.channel_id], msg

    def messages(self) -> Iterator[tuple[str, RobotdMessage]]:
        """``(topic, message)`` in log-time order, as robotd types.

        :class:`WheelTicks`, :class:`YawRate`, :class:`Frame` (image decoded) and
        :class:`PoseStamped` (every ``nav_msgs/msg/Odometry`` topic). Other types are
        skipped and counted in :attr:`skipped`; damage is counted in :attr:`damage`.
        """
        factory = DecoderFactory()
        decoders: dict[int, Callable[[bytes], Any] | None] = {}
        yaw_source = self.yaw_source
        for channel, msg in self.raw_messages():
            schema = self._schemas.get(channel.schema_id)
            kind = _normalise_type(schema.name) if schema is not None else ""
            if kind not in _CONVERTERS or channel.message_encoding != "cdr":
                self.skipped[channel.topic] = self.skipped.get(channel.topic, 0) + 1
                continue
            if channel.id not in decoders:
                try:
                    decoders[channel.id] = factory.decoder_for("cdr", schema)
                except Exception:  # noqa: BLE001 - a broken schema text in the file
                    log.warning("%s: cannot parse the schema of %s", self.path, channel.topic)
                    decoders[channel.id] = None
            decode = decoders[channel.id]
            try:
                if decode is None:
                    raise ValueError("no decoder")
                out = _CONVERTERS[kind](channel.topic, decode(msg.data), msg, yaw_source)
            except Exception as exc:  # noqa: BLE001 - CDR or image bytes that do not decode
                self.damage.undecodable_messages += 1
                log.debug("%s: undecodable %s message at %d: %s", self.path, channel.topic,
                          msg.log_time, exc)
                continue
            yield channel.topic, out

    def close(self) -> None:
        """Close the file; safe to call twice."""
        self._f.close()

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _to_wheel_ticks(topic: str, m: Any, rec: Message, yaw_source: str) -> WheelTicks:
    return WheelTicks(_stamp_ns(m.header), int(m.left_ticks), int(m.right_ticks), int(m.device_ms))


def _to_yaw_rate(topic: str, m: Any, rec: Message, yaw_source: str) -> YawRate:
    return YawRate(_stamp_ns(m.header), float(m.angular_velocity.z), yaw_source)


def _to_frame(topic: str, m: Any, rec: Message, yaw_source: str) -> Frame:
    image = cv2.imdecode(np.frombuffer(m.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"image data ({m.format!r}) does not decode")
    match = _CAMERA_TOPIC.match(topic)
    camera = match.group(1) if match else topic.strip("/")
    return Frame(_stamp_ns(m.header), camera, image, int(rec.sequence))


def _to_pose(topic: str, m: Any, rec: Message, yaw_source: str) -> PoseStamped:
    p = m.pose.pose
    cov6 = np.asarray(m.pose.covariance, dtype=np.float64).reshape(6, 6)
    return PoseStamped(_stamp_ns(m.header), float(p.position.x), float(p.position.y),
                       _yaw_from_quaternion(p.orientation), cov6[np.ix_((0, 1, 5), (0, 1, 5))].copy())


_CONVERTERS: dict[str, Callable[[str, Any, Message, str], RobotdMessage]] = {
    "robotd_msgs/msg/WheelTicks": _to_wheel_ticks,
    "sensor_msgs/msg/Imu": _to_yaw_rate,
    "sensor_msgs/msg/CompressedImage": _to_frame,
    "nav_msgs/msg/Odometry": _to_pose,
}


def read_recording(path: str | os.PathLike[str]) -> Iterator[tuple[str, RobotdMessage]]:
    """``(topic, message)`` of a recording in log-time order (see :meth:`RecordingReader.messages`).

    Raises :class:`~robotd.errors.DriverError` when the file is unreadable; damage that
    leaves a partly readable file is logged (one warning naming the path, with counts)
    and what is intact is yielded. Use :class:`RecordingReader` to see the counts.
    """
    with RecordingReader(path) as reader:
        yield from reader.messages()
        if reader.damage.undecodable_messages or reader.damage.damaged_chunks:
            log.warning("%s: %d damaged chunks and %d undecodable messages skipped", reader.path,
                        reader.damage.damaged_chunks, reader.damage.undecodable_messages)


# --------------------------------------------------------------------------------------
# Replay
# --------------------------------------------------------------------------------------


class ReplayQueue:
    """One driver-like output of a :class:`ReplaySource` (``replay.base``, ``replay.floor``).

    ``read(timeout_s)`` waits up to ``timeout_s`` for the next item and returns it (a
    camera: one :class:`Frame`), or every item then waiting, up to ``max_batch`` (the
    base: a list of :class:`WheelTicks` and :class:`YawRate`), or None. After the reader
    thread failed and the queue is empty, ``read`` raises its
    :class:`~robotd.errors.DriverError`. ``close`` does nothing: the
    :class:`ReplaySource` owns the file and the thread.
    """

    def __init__(self, name: str, maxsize: int, batch: bool, owner: ReplaySource,
                 max_batch: int = 64) -> None:
        self.name = name
        self.batch = batch
        self.max_batch = max_batch
        self._q: queue.Queue[Any] = queue.Queue(maxsize=maxsize)
        self._owner = owner
        self.handed_out = 0
        """Items returned by :meth:`read` so far."""
        self.queued = 0
        """Items the reader thread has queued so far."""

    def read(self, timeout_s: float) -> list[WheelTicks | YawRate] | Frame | None:
        self._owner.start()
        try:
            first = self._q.get(timeout=timeout_s)
        except queue.Empty:
            if self._owner.error is not None and self._owner.finished.is_set():
                raise self._owner.error from None
            return None
        if not self.batch:
            self.handed_out += 1
            return first
        items = [first]
        while len(items) < self.max_batch:
            try:
                items.append(self._q.get_nowait())
            except queue.Empty:
                break
        self.handed_out += len(items)
        return items

    def _put(self, item: Any, stop: threading.Event) -> bool:
        while not stop.is_set():
            try:
                self._q.put(item, timeout=0.1)
                self.queued += 1
                return True
            except queue.Full:
                continue
        return False

    def close(self) -> None:
        pass


class ReplaySource:
    """Feeds a recording back as the daemon's sources, in recorded order, losslessly.

    One reader thread walks the recording in log-time order and hands base messages
    (``/wheel_ticks``, ``/imu``) to :attr:`base` and frames of the cameras in ``cameras``
    to :attr:`floor` (and :meth:`camera` for others), each a bounded blocking queue of
    ``queue_size`` items: nothing is dropped, the thread waits for the daemon. Frames of
    other cameras and every other topic (``/odom``, ``/ground_truth``) are not handed
    out; they are passed to ``on_other(topic, message)`` when given (in the reader
    thread) and counted in :attr:`skipped`.

    ``speed=None`` replays as fast as the consumers take the data; ``speed=s`` paces the
    messages at ``s`` times recorded speed on the wall clock (inside the reader thread
    only). With a :class:`~robotd.clock.ManualClock`, the clock is set to each message's
    stamp just before the message is handed out (it never goes backwards), so the daemon
    runs on recorded time.

    The file is opened at construction (:class:`~robotd.errors.DriverError` if it is not a
    recording); the thread starts on :meth:`start` or the first ``read``. :attr:`finished`
    is set once every message has been queued (or the thread failed: :attr:`error`);
    :meth:`done` is true once they have also all been read.
    """

    def __init__(self, path: str | os.PathLike[str], clock: ManualClock | None = None,
                 speed: float | None = None, *, cameras: Sequence[str] = ("floor",),
                 queue_size: int = 64,
                 on_other: Callable[[str, RobotdMessage], None] | None = None) -> None:
        if speed is not None and not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"speed must be a positive number or None, got {speed}")
        if queue_size < 1:
            raise ValueError("queue_size must be >= 1")
        self.path = Path(path)
        self.clock = clock
        self.speed = speed
        self.on_other = on_other
        self.reader = RecordingReader(path)
        self.base = ReplayQueue("base", queue_size, batch=True, owner=self)
        self._cameras = {name: ReplayQueue(name, queue_size, batch=False, owner=self) for name in cameras}
        self.floor: ReplayQueue | None = self._cameras.get("floor")
        self.finished = threading.Event()
        self.error: DriverError | None = None
        self.counts: dict[str, int] = {}
        """Messages handed to the sub-sources, per topic."""
        self.skipped: dict[str, int] = {}
        """Messages not handed out, per topic."""
        self._stop = threading.Event()
        self._start_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._closed = False

    @property
    def damage(self) -> RecordingDamage:
        """Damage met in the recording so far."""
        return self.reader.damage

    def camera(self, name: str) -> ReplayQueue:
        """The sub-source of camera ``name`` (one of ``cameras``)."""
        return self._cameras[name]

    def start(self) -> None:
        """Start the reader thread (once; later calls do nothing)."""
        with self._start_lock:
            if self._thread is None and not self._closed:
                self._thread = threading.Thread(target=self._run, name="robotd-replay", daemon=True)
                self._thread.start()

    def done(self) -> bool:
        """True once every message was queued and :meth:`ReplayQueue.read` has returned
        each of them (an item being taken out counts only once ``read`` returns it)."""
        return self.finished.is_set() and all(
            q.handed_out == q.queued for q in (self.base, *self._cameras.values()))

    def _route(self, msg: RobotdMessage) -> ReplayQueue | None:
        if isinstance(msg, (WheelTicks, YawRate)):
            return self.base
        if isinstance(msg, Frame):
            return self._cameras.get(msg.camera)
        return None

    def _run(self) -> None:
        try:
            self._play()
        except RobotdError as exc:
            self.error = exc if isinstance(exc, DriverError) else DriverError(f"{self.path}: {exc}")
            log.warning("replay of %s failed: %s", self.path, exc)
        except OSError as exc:
            self.error = DriverError(f"{self.path}: cannot read the recording: {exc.strerror}")
            log.warning("%s", self.error)
        except Exception as exc:  # reported through read(), never silently lost
            self.error = DriverError(f"{self.path}: replay failed: {exc!r}")
            log.exception("replay of %s failed", self.path)
        finally:
            self.finished.set()

    def _play(self) -> None:
        wall0 = first_ns = None
        for topic, msg in self.reader.messages():
            if self._stop.is_set():
                return
            target = self._route(msg)
            if target is None:
                self.skipped[topic] = self.skipped.get(topic, 0) + 1
                if self.on_other is not None:
                    self.on_other(topic, msg)
                continue
            if self.speed is not None:
                if wall0 is None:
                    wall0, first_ns = time.monotonic(), msg.stamp_ns
                delay = wall0 + (msg.stamp_ns - first_ns) / 1e9 / self.speed - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
            if self.clock is not None:
                now = self.clock.now_ns()
                if msg.stamp_ns > now:
                    self.clock.set_ns(msg.stamp_ns)
            if not target._put(msg, self._stop):
                return
            self.counts[topic] = self.counts.get(topic, 0) + 1

    def close(self) -> None:
        """Stop the reader thread and close the file; safe to call twice."""
        with self._start_lock:
            if self._closed:
                return
            self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
        self.reader.close()

    def __enter__(self) -> ReplaySource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
