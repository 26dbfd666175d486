"""Writing recordings: the MCAP writer, a tee that records what a driver reads, and an odometry recorder.
"""

from __future__ import annotations

import datetime
import logging
import os
import threading
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from drivers.base import Driver, Message, StatValue
from drivers.recording.schemas import (
    PARTIAL_SUFFIX,
    TOPIC_GROUND_TRUTH,
    TOPIC_IMU,
    TOPIC_ODOM,
    TOPIC_TF,
    TOPIC_TF_STATIC,
    TOPIC_WHEEL_TICKS,
    camera_info_topic,
    camera_topic,
)
from robotd.base import ros2msg
from robotd.base.camera import CameraIntrinsics
from robotd.base.errors import DriverError, RecordingError
from robotd.base.geometry import quaternion_from_rotation
from robotd.base.messages import Frame, PoseStamped, WheelTicks, YawRate
from robotd.base.ros2msg import check_stamp as _check_stamp
from robotd.base.ros2msg import header as _header

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


class _UnbufferedSink:
    """The file under the MCAP writer: every write goes to the OS at once.

    ``mcap`` writes a chunk (and its indexes) only when the chunk is full, so each write
    here is a finished piece of the recording that must survive a process crash.

    ``mcap`` hands over whole records in each write, so when a write fails (the disk is
    full) the file is cut back to the end of the last complete write: it then ends on a
    record boundary, and the space the failed write took is given back.
    """

    def __init__(self, fd: int) -> None:
        self._fd = fd
        self._pos = 0

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        try:
            while view:
                n = os.write(self._fd, view)
                view = view[n:]
        except OSError:
            self.cut_back()
            raise
        self._pos += len(data)
        return len(data)

    def cut_back(self) -> None:
        """Truncate the file to the end of the last complete write (best effort)."""
        try:
            os.ftruncate(self._fd, self._pos)
            os.lseek(self._fd, self._pos, os.SEEK_SET)
        except OSError:
            log.debug("could not truncate the recording back to %d bytes", self._pos, exc_info=True)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass


def image_encoding(image_format: str, jpeg_quality: int, png_compression: int) -> tuple[str, list[int]]:
    """``cv2.imencode``'s extension and parameters for a recorded frame. JPEG gets
    optimised Huffman tables: lossless, 5-7 % smaller on the floor camera's frames, about
    5 ms more per 640x480 frame."""
    if image_format == "png":
        return ".png", [cv2.IMWRITE_PNG_COMPRESSION, png_compression]
    return ".jpg", [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality, cv2.IMWRITE_JPEG_OPTIMIZE, 1]


def _check_u16(name: str, value: int) -> int:
    v = int(value)
    if not 0 <= v <= 0xFFFF:
        raise ValueError(f"{name} {value} does not fit a uint16")
    return v


# rosbag2's QoS of a latched topic (keep last 1, reliable, transient local), as it stores
# it in a channel's ``offered_qos_profiles``: ``ros2 bag play`` then re-offers /tf_static
# to late subscribers, as tf2's static broadcaster does (durations: "infinite").
_LATCHED_QOS_YAML = """- history: 1
  depth: 1
  reliability: 1
  durability: 1
  deadline:
    sec: 2147483647
    nsec: 4294967295
  lifespan:
    sec: 2147483647
    nsec: 4294967295
  liveliness: 1
  liveliness_lease_duration:
    sec: 2147483647
    nsec: 4294967295
  avoid_ros_namespace_conventions: false
"""


def _camera_info(stamp_ns: int, frame_id: str, k: CameraIntrinsics) -> dict[str, Any]:
    """``sensor_msgs/msg/CameraInfo`` of an unrectified camera (``plumb_bob``: OpenCV's
    k1 k2 p1 p2 k3; ``r`` identity; ``p`` = K with a zero fourth column, as a monocular
    camera that nobody has rectified publishes it)."""
    return {
        "header": _header(stamp_ns, frame_id),
        "height": k.height_px, "width": k.width_px, "distortion_model": "plumb_bob",
        "d": [float(c) for c in k.distortion],
        "k": [k.fx_px, 0.0, k.cx_px, 0.0, k.fy_px, k.cy_px, 0.0, 0.0, 1.0],
        "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "p": [k.fx_px, 0.0, k.cx_px, 0.0, 0.0, k.fy_px, k.cy_px, 0.0, 0.0, 0.0, 1.0, 0.0],
        "binning_x": 0, "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
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
    ``/tf_static`` is written before the first message; :meth:`add_camera` adds a camera's
    mount to it and a CameraInfo beside each of its frames; ``/odom`` poses also go to
    ``/tf`` (see the module doc of :mod:`drivers.recording.schemas`).

    The ``write_*`` methods may be called from several threads. Methods raise
    ``ValueError`` for a message that cannot be represented (negative stamp, counter out
    of range, bad image) and :class:`~robotd.base.errors.RecordingError` naming the file when
    the disk fails (full, I/O error). The first such failure ends the recording: the file
    is cut back to its last complete record and stays under its ``.partial`` name, readable
    by :class:`~drivers.recording.reader.RecordingReader`; every later write raises the
    same error (also kept in :attr:`error`), and :meth:`close` only closes the file.
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
        self._encode_ext, self._encode_params = image_encoding(image_format, jpeg_quality, png_compression)
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
        self.error: RecordingError | None = None
        """The write failure that ended the recording, None while it is sound."""
        self._base_log_time_ns = 0  # the base stream's log time never goes back (module docs)
        self._closed = False
        self._yaw_source: str | None = None
        self.counts: dict[str, int] = {}
        """Messages written per topic."""
        self.mixed_yaw_sources = 0
        """Yaw rates whose ``source`` differed from the first one's (stored as the first)."""
        start = start_time_utc or datetime.datetime.now(datetime.UTC)
        self._sink = _UnbufferedSink(self._fd)
        try:
            self._mcap = McapWriter(self._sink, chunk_size=chunk_size, compression=CompressionType.ZSTD)
            self._mcap.start(profile="ros2", library=f"robotd {__version__}")
            self._mcap.add_metadata("robotd", {
                "robotd_version": __version__,
                "config_toml": config_toml,
                "start_time_utc": start.isoformat(),
                "image_format": image_format,
                "image_quality": (f"jpeg_quality {jpeg_quality}" if image_format == "jpeg"
                                  else f"png_compression {png_compression}"),
                "stamp_time_base": "robotd clock (host monotonic or virtual robot time), not Unix time",
            })
        except OSError as exc:
            os.close(self._fd)
            self.partial_path.unlink(missing_ok=True)
            raise RecordingError(f"{self.partial_path}: cannot write: {exc.strerror}") from exc
        self._schemas: dict[str, int] = {}  # type name -> MCAP schema id
        self._channels: dict[str, int] = {}  # topic -> MCAP channel id
        self._camera_info: dict[str, CameraIntrinsics] = {}
        # Static transforms (parent, child, xyz, quaternion), written on /tf_static with the
        # stamp of the first message after a change.
        self._static: dict[str, tuple[str, tuple[float, float, float],
                                      tuple[float, float, float, float]]] = {
            "base_link": ("base_footprint", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
            imu_frame_id: ("base_link", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
        }
        self._static_written = False

    # -- ROS extras ------------------------------------------------------------------

    def add_camera(self, camera: str, intrinsics: CameraIntrinsics, rotation_robot_from_camera: np.ndarray,
                   position_robot_m: np.ndarray) -> None:
        """Describe camera ``camera`` so ROS tools can place and undistort its images.

        From then on every frame of that camera is followed by a
        ``sensor_msgs/msg/CameraInfo`` on ``/<camera>_camera/camera_info`` (same stamp and
        ``frame_id``), and ``/tf_static`` holds the mount: ``<camera>_camera_optical_frame``
        in ``base_link`` (``rotation_robot_from_camera``: ``(3, 3)``, columns = the optical
        frame's x right, y down, z along the optical axis in the robot frame;
        ``position_robot_m``: ``(3,)`` lens centre, metres). Call it before the camera's
        first frame.
        """
        topic = camera_topic(camera)  # validates the name
        rot = np.asarray(rotation_robot_from_camera, dtype=np.float64)
        pos = np.asarray(position_robot_m, dtype=np.float64).reshape(-1)
        if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) \
                or np.linalg.det(rot) < 0.0:
            raise ValueError(f"{topic}: rotation_robot_from_camera must be a (3, 3) rotation")
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise ValueError(f"{topic}: position_robot_m must be 3 finite numbers")
        with self._lock:
            self._camera_info[camera] = intrinsics
            self._static[f"{camera}_camera_optical_frame"] = (
                "base_link", (float(pos[0]), float(pos[1]), float(pos[2])), quaternion_from_rotation(rot))
            self._static_written = False

    def _write_static_locked(self, stamp_ns: int) -> None:
        """``/tf_static``: every static transform in one ``tf2_msgs/msg/TFMessage``, as
        tf2's static broadcaster latches them (the lock is held)."""
        transforms = [ros2msg.transform_msg(stamp_ns, parent, child, xyz, q)
                      for child, (parent, xyz, q) in self._static.items()]
        self._write_locked(TOPIC_TF_STATIC, "tf2_msgs/msg/TFMessage", stamp_ns,
                           {"transforms": transforms}, latched=True)
        self._static_written = True

    # -- writing ---------------------------------------------------------------------

    def _write(self, topic: str, type_name: str, stamp_ns: int, msg: dict[str, Any],
               sequence: int = 0, extra: tuple[tuple[str, str, dict[str, Any]], ...] = ()) -> None:
        """Write one message, then ``extra`` ``(topic, type, message)`` at the same stamp
        (a frame's CameraInfo, an odometry's /tf), with /tf_static first when it changed."""
        with self._lock:
            if self.error is not None:
                raise self.error
            if self._closed:
                raise ValueError(f"{self.path}: the recording is closed")
            if not self._static_written:
                self._write_static_locked(stamp_ns)
            self._write_locked(topic, type_name, stamp_ns, msg, sequence=sequence)
            for e_topic, e_type, e_msg in extra:
                self._write_locked(e_topic, e_type, stamp_ns, e_msg, sequence=sequence)

    def _write_locked(self, topic: str, type_name: str, stamp_ns: int, msg: dict[str, Any],
                      sequence: int = 0, latched: bool = False) -> None:
        data = ros2msg.encode(type_name, msg)  # the one CDR path (robotd.base.ros2msg)
        try:
            schema_id = self._schemas.get(type_name)
            if schema_id is None:
                schema_id = self._mcap.register_schema(type_name, SchemaEncoding.ROS2,
                                                       ros2msg.schema_text(type_name).encode())
                self._schemas[type_name] = schema_id
            channel_id = self._channels.get(topic)
            if channel_id is None:
                # A latched topic carries rosbag2's transient-local QoS in its metadata.
                channel_id = self._channels[topic] = self._mcap.register_channel(
                    topic=topic, message_encoding=MessageEncoding.CDR, schema_id=schema_id,
                    metadata={"offered_qos_profiles": _LATCHED_QOS_YAML} if latched else {})
            log_time = stamp_ns
            if topic in (TOPIC_WHEEL_TICKS, TOPIC_IMU):
                log_time = self._base_log_time_ns = max(self._base_log_time_ns, stamp_ns)
            self._mcap.add_message(channel_id, log_time=log_time, data=data,
                                   publish_time=stamp_ns, sequence=sequence)
        except OSError as exc:
            raise self._failed(exc) from exc
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
        """``/imu`` (``sensor_msgs/msg/Imu``): ``angular_velocity.z`` = the yaw rate, rad/s, and
        its stated variance, when the reading has one, in ``angular_velocity_covariance[8]``."""
        stamp = _check_stamp(msg.stamp_ns)
        if self.error is not None:
            raise self.error
        if self._closed:
            raise ValueError(f"{self.path}: the recording is closed")
        if self._yaw_source is None:
            with self._lock:
                if self._yaw_source is None and not self._closed and self.error is None:
                    try:
                        self._mcap.add_metadata("robotd.imu", {"topic": TOPIC_IMU, "yaw_source": msg.source})
                    except OSError as exc:
                        raise self._failed(exc) from exc
                    self._yaw_source = msg.source
        if msg.source != self._yaw_source:
            if self.mixed_yaw_sources == 0:
                log.warning("%s: yaw rates from %r after %r; the recording keeps %r for all",
                            self.path, msg.source, self._yaw_source, self._yaw_source)
            self.mixed_yaw_sources += 1
        self._write(TOPIC_IMU, "sensor_msgs/msg/Imu", stamp,
                    ros2msg.imu_yaw_rate_msg(stamp, self.imu_frame_id, msg.yaw_rate_radps,
                                             msg.yaw_rate_var_rad2ps2))

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
        frame_id = f"{frame.camera}_camera_optical_frame"
        intrinsics = self._camera_info.get(frame.camera)
        extra = () if intrinsics is None else (
            (camera_info_topic(frame.camera), "sensor_msgs/msg/CameraInfo",
             _camera_info(stamp, frame_id, intrinsics)),)
        self._write(topic, "sensor_msgs/msg/CompressedImage", stamp,
                    ros2msg.compressed_image_msg(stamp, frame_id, self.image_format, buf.tobytes()),
                    sequence=int(frame.seq) & 0xFFFFFFFF, extra=extra)

    def write_odometry(self, pose: PoseStamped, topic: str = TOPIC_ODOM, *,
                       frame_id: str = "odom", child_frame_id: str = "base_footprint") -> None:
        """A planar pose estimate as ``nav_msgs/msg/Odometry`` on ``topic`` (default ``/odom``).

        On ``/odom`` the same pose also goes to ``/tf`` (``tf2_msgs/msg/TFMessage``:
        ``child_frame_id`` in ``frame_id``, by default ``base_footprint`` in ``odom``), as a
        ROS odometry node broadcasts it, so 3D views follow the robot.
        """
        stamp = _check_stamp(pose.stamp_ns)
        extra: tuple[tuple[str, str, dict[str, Any]], ...] = ()
        if topic == TOPIC_ODOM:
            tf = ros2msg.planar_transform_msg(stamp, frame_id, child_frame_id,
                                              (pose.x_m, pose.y_m, pose.yaw_rad))
            extra = ((TOPIC_TF, "tf2_msgs/msg/TFMessage", {"transforms": [tf]}),)
        self._write(topic, "nav_msgs/msg/Odometry", stamp, ros2msg.odometry_msg(
            stamp, pose.x_m, pose.y_m, pose.yaw_rad, pose.covariance, frame_id, child_frame_id),
            extra=extra)

    def write_ground_truth(self, stamp_ns: int, x_m: float, y_m: float, yaw_rad: float) -> None:
        """The virtual robot's true pose on ``/ground_truth`` (``nav_msgs/msg/Odometry``,
        frame ``world``, zero covariance)."""
        stamp = _check_stamp(stamp_ns)
        self._write(TOPIC_GROUND_TRUTH, "nav_msgs/msg/Odometry", stamp, ros2msg.odometry_msg(
            stamp, x_m, y_m, yaw_rad, np.zeros((3, 3)), "world", "base_footprint"))

    def _failed(self, exc: OSError) -> RecordingError:
        """Remember the write failure that ends the recording (the lock is held)."""
        self.error = RecordingError(
            f"{self.partial_path}: cannot write: {exc.strerror or exc}; the recording stopped "
            f"there ({self._sink.tell()} bytes, {sum(self.counts.values())} messages kept, "
            f"readable as they are in {self.partial_path})")
        return self.error

    # -- closing ---------------------------------------------------------------------

    def close(self, *, completed: bool = True, reason: str = "") -> None:
        """Finish the file (summary and indexes), fsync it and rename it to :attr:`path`.

        Safe to call twice. ``completed=False`` (what leaving the ``with`` block by an
        exception passes) still finishes the file, whose data are valid, and records
        ``completed: false`` and ``reason`` in the ``robotd.end`` metadata record.

        After a write failure (:attr:`error`) it only closes the file, which keeps its
        ``.partial`` name; it raises :class:`~robotd.base.errors.RecordingError` if the
        summary itself cannot be written, leaving the ``.partial`` file cut back to its last
        complete record.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self.error is not None:
                os.close(self._fd)
                log.info("%s: recording left incomplete (%s)", self.partial_path, self.error)
                return
            try:
                self._mcap.add_metadata("robotd.end", {
                    "completed": "true" if completed else "false", "reason": reason,
                    "messages": str(sum(self.counts.values()))})
                self._mcap.finish()
                os.fsync(self._fd)
            except OSError as exc:
                self.error = RecordingError(
                    f"{self.partial_path}: cannot finish the recording: {exc.strerror or exc}; "
                    f"its messages are readable as they are in {self.partial_path}")
                raise self.error from exc
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


class RecordingTee(Driver):
    """A driver wrapper: ``read`` returns what ``source.read`` returns and records it.

    Wrap a base driver (WheelTicks and YawRate) or a camera (Frame) before handing it to
    the daemon, so the recording holds exactly what the daemon received. ``source`` is a
    :class:`~drivers.base.Driver` or any object whose ``read(timeout_s)`` returns None,
    one message or a list (the virtual robot's camera). ``close`` closes the wrapped
    source, not the writer. :meth:`stats` are the wrapped driver's (the tee's own
    counters for a source without ``stats()``); other attributes (``request_extra``,
    ``port``, ...) are the wrapped source's.

    When the writer fails (:class:`~robotd.base.errors.RecordingError`: the disk is full),
    the messages of that read are still returned, so the daemon loses nothing it read, and
    the next ``read`` raises the error: a recording run must stop, not go on unrecorded.
    """

    def __init__(self, source: Any, writer: RecordingWriter) -> None:
        super().__init__(str(getattr(source, "name", "tee")))
        self.source = source
        self.writer = writer
        self._failure: RecordingError | None = None

    def _read_internal(self, timeout_s: float) -> list[Message]:
        if self._failure is not None:
            raise self._failure
        got = self.source.read(timeout_s)
        messages = [] if got is None else got if isinstance(got, list) else [got]
        try:
            for msg in messages:
                self._record(msg)
        except RecordingError as exc:
            self._failure = exc
        return messages

    def _record(self, msg: Any) -> None:
        if isinstance(msg, WheelTicks):
            self.writer.write_wheel_ticks(msg)
        elif isinstance(msg, YawRate):
            self.writer.write_yaw_rate(msg)
        elif isinstance(msg, Frame):
            self.writer.write_frame(msg)

    def _close_internal(self) -> None:
        self.source.close()

    def stats(self) -> dict[str, StatValue]:
        """The wrapped driver's :meth:`~drivers.base.Driver.stats`."""
        inner = getattr(self.source, "stats", None)
        return inner() if callable(inner) else super().stats()

    def __str__(self) -> str:
        return f"recording tee of {self.source}"

    def __getattr__(self, name: str) -> Any:  # driver extras (request_extra, port, ...)
        if name == "source":
            raise AttributeError(name)
        return getattr(self.source, name)
