"""Recordings: a run written to MCAP with ROS 2 message types, read and replayed back.

A recording is one `MCAP <https://mcap.dev>`_ file (profile ``ros2``, CDR-encoded
messages) whose schemas are ROS 2 ``.msg`` definitions embedded as text, dependencies
included, so Foxglove and ``ros2 bag`` (with the MCAP storage plugin) open it without
robotd or a ROS workspace. Writing and reading use ``mcap`` and ``mcap-ros2-support``;
no ROS install is needed.

Topics (ROS 2 type -> what :func:`read_recording` gives back):

- ``/wheel_ticks``: ``robotd_msgs/msg/WheelTicks`` -> :class:`~robotd.base.messages.WheelTicks`
- ``/imu``: ``sensor_msgs/msg/Imu`` -> :class:`~robotd.base.messages.YawRate`
- ``/floor_camera/image/compressed``, ``/forward_camera/image/compressed``:
  ``sensor_msgs/msg/CompressedImage`` -> :class:`~robotd.base.messages.Frame`
- ``/odom`` (fused odometry), ``/ground_truth`` (virtual robot only), and any other
  topic given to :meth:`RecordingWriter.write_odometry`: ``nav_msgs/msg/Odometry`` ->
  :class:`~robotd.base.messages.PoseStamped`

and, for ROS tools only (a replay skips them; :attr:`RecordingReader.skipped` counts them):

- ``/tf``: ``tf2_msgs/msg/TFMessage``, ``base_footprint`` in ``odom`` at every ``/odom``
  pose, so Foxglove's 3D panel follows the robot;
- ``/tf_static``: ``tf2_msgs/msg/TFMessage``, latched (rosbag2's transient-local QoS in
  the channel's ``offered_qos_profiles``): ``base_link`` in ``base_footprint`` and the
  gyro's frame in ``base_link`` (both identity: robotd's robot frame is on the floor), and
  each described camera's ``<camera>_camera_optical_frame`` in ``base_link`` from its
  mount; written before the first message and again when a camera is added later;
- ``/<camera>_camera/camera_info``: ``sensor_msgs/msg/CameraInfo`` (``plumb_bob``) beside
  every frame of a camera given to :meth:`RecordingWriter.add_camera`, same stamp and
  ``frame_id`` as the image, so the image panel can undistort and project.

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
  is all zero ("unknown"). :attr:`YawRate.source <robotd.base.messages.YawRate.source>` has no
  ROS field; it is kept in the metadata record ``robotd.imu`` (the first source written;
  a later different source is logged and counted, and reads back as the first).
- Frames: PNG (lossless, so a replay gives the daemon the very pixels it saw) or JPEG
  (lossy, with optimised Huffman tables). On the virtual camera's noisy 640x480 frames
  JPEG is 2.4x smaller than PNG at quality 90, 4x at 75 and about 10x at 15 (the
  ``[recording]`` config section chooses; :mod:`drivers.recording.transcode` converts a
  recording either way). The frame's ``seq``
  is the MCAP message ``sequence``; the camera name is the topic's
  ``/<camera>_camera/image/compressed``; ``frame_id`` is ``<camera>_camera_optical_frame``.
- ``/odom`` (``frame_id`` ``odom``, ``child_frame_id`` ``base_footprint``): the 3x3
  (x, y, yaw) covariance goes into rows/columns 0, 1, 5 of the 6x6 pose covariance; z,
  roll and pitch are fixed on a flat floor and carry zero variance. The twist is not
  estimated and is written as zero with zero covariance. ``/ground_truth`` has
  ``frame_id`` ``world``. Yaw reads back wrapped to [-pi, pi].
- Metadata record ``robotd``: ``robotd_version``, ``config_toml``, ``start_time_utc``
  (ISO 8601, the host's wall clock, for people), ``image_format``, ``image_quality``
  (``"jpeg_quality Q"`` or ``"png_compression L"``; absent in older files),
  ``stamp_time_base``.

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
its header raises :class:`~robotd.base.errors.DriverError` naming the path. Anything else is
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

:class:`~drivers.recording.replay.ReplayDriver` feeds a recording back as one driver,
as fast as it is read or paced at a multiple of recorded speed.
"""

from __future__ import annotations

import logging
import re
import struct

log = logging.getLogger(__name__)

TOPIC_WHEEL_TICKS = "/wheel_ticks"
TOPIC_IMU = "/imu"
TOPIC_ODOM = "/odom"
TOPIC_GROUND_TRUTH = "/ground_truth"
TOPIC_TF = "/tf"
TOPIC_TF_STATIC = "/tf_static"
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
    "geometry_msgs/msg/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/msg/TransformStamped": (
        "std_msgs/Header header\n"
        "string child_frame_id\n"
        "Transform transform\n"
    ),
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "sensor_msgs/msg/RegionOfInterest": (
        "uint32 x_offset\n"
        "uint32 y_offset\n"
        "uint32 height\n"
        "uint32 width\n"
        "bool do_rectify\n"
    ),
    "sensor_msgs/msg/CameraInfo": (
        "std_msgs/Header header\n"
        "uint32 height\n"
        "uint32 width\n"
        "string distortion_model\n"
        "float64[] d\n"
        "float64[9] k\n"
        "float64[9] r\n"
        "float64[12] p\n"
        "uint32 binning_x\n"
        "uint32 binning_y\n"
        "RegionOfInterest roi\n"
    ),
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


def camera_info_topic(camera: str) -> str:
    """The topic of camera ``camera``'s calibration: ``/<camera>_camera/camera_info`` (beside
    its images, where image_transport and Foxglove look for it)."""
    return camera_topic(camera).removesuffix("/image/compressed") + "/camera_info"


def camera_topic(camera: str) -> str:
    """The topic of camera ``camera``'s compressed images: ``/<camera>_camera/image/compressed``."""
    if not _CAMERA_NAME.match(camera):
        raise ValueError(f"camera name {camera!r} cannot be part of a ROS topic name")
    return f"/{camera}_camera/image/compressed"


