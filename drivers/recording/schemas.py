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

from robotd.base import ros2msg

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
_RECORD_HEAD = struct.Struct("<BQ")  # opcode u8, record length u64

# The ROS 2 message definitions (and the CDR written with them) are robotd's one message
# model, robotd.base.ros2msg; schema_text is re-exported here for the recording's users.
schema_text = ros2msg.schema_text


def camera_info_topic(camera: str) -> str:
    """The topic of camera ``camera``'s calibration: ``/<camera>_camera/camera_info`` (beside
    its images, where image_transport and Foxglove look for it)."""
    return camera_topic(camera).removesuffix("/image/compressed") + "/camera_info"


def camera_topic(camera: str) -> str:
    """The topic of camera ``camera``'s compressed images: ``/<camera>_camera/image/compressed``."""
    if not _CAMERA_NAME.match(camera):
        raise ValueError(f"camera name {camera!r} cannot be part of a ROS topic name")
    return f"/{camera}_camera/image/compressed"


