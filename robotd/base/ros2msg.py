"""The ROS 2 message model: the message types robotd speaks, defined once, and their CDR.

Every ROS 2 message robotd writes or reads (to DDS, into MCAP recordings, to Foxglove,
from ROS 2 topics) is defined by its ``.msg`` text and encoded or decoded by one codec
compiled from that text. The model is three modules by job, and this one is its front
door (import ``robotd.base.ros2msg`` and use the names below):

- :mod:`robotd.base.ros2msg_types`: the ``.msg`` text of every type (:data:`DEFINITIONS`),
  its fields, the ``ros2msg`` schema text MCAP files and the Foxglove server carry
  (:func:`schema_text`) and the DDS type and topic names ROS 2's middlewares expect
  (:func:`dds_type_name`, :func:`dds_topic_name`);
- :mod:`robotd.base.ros2msg_cdr`: the CDR codec (:func:`encode`, :func:`decode`; plain
  little-endian XCDR1, what ``rmw`` puts on the wire and ``rosbag2`` into a file);
- here: the builders that turn robotd's own values (stamps in ns, planar poses, 3x3
  covariances) into message dicts, so every output writes a pose or a transform the same
  way (REP 103: x forward, y left, yaw counter-clockwise; REP 105 frames).

Messages are plain ``dict`` trees keyed by field name (what ``mcap-ros2-support`` and most
ROS 2 Python tools use).

Why in the base layer and not in io (as DESIGN.md's layout puts message formats): the
drivers (the MCAP recorder, the ROS 2 input drivers) may import only :mod:`robotd.base`,
and the app's outputs need the same bytes, so the one model sits where both can reach it.
It does no I/O (it only turns dicts into bytes and back), which is what base allows.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from robotd.base.ros2msg_cdr import CDR_LE_HEADER, Codec, codec, decode, encode
from robotd.base.ros2msg_types import (DEFINITIONS, DISTRO_DEFINITIONS, DISTROS, Field, dds_topic_name, dds_type_name, definitions,
                                       dependencies, gid_size, parse_definition, parse_schema_text, ros_topic_name,
                                       schema_text)

__all__ = [
    "CDR_LE_HEADER", "DEFINITIONS", "DISTROS", "DISTRO_DEFINITIONS", "MAX_STAMP_NS", "NS_PER_S", "Codec", "Field", "check_stamp", "codec",
    "compressed_image_msg", "covariance3", "covariance6", "covariance_problem", "dds_topic_name", "dds_type_name", "decode",
    "definitions", "dependencies", "diagnostic_status", "encode", "gid_size", "header", "imu_yaw_rate_msg", "key_values",
    "line_list_marker", "odometry_msg", "parse_definition", "parse_schema_text", "participant_entities_info", "path_msg", "planar_pose",
    "planar_transform_msg", "pose_with_covariance_msg", "ros_topic_name", "schema_text", "stamp_ns_of", "stated_variances",
    "tf_message", "time_msg", "transform_msg", "yaw_of_quaternion", "yaw_quaternion",
]

NS_PER_S = 1_000_000_000
MAX_STAMP_NS = (1 << 31) * NS_PER_S
"""``builtin_interfaces/Time.sec`` is an ``int32``: stamps must be below 2^31 s."""


# --------------------------------------------------------------------------------------
# Builders: robotd's values -> message dicts
# --------------------------------------------------------------------------------------


def check_stamp(stamp_ns: int) -> int:
    """``stamp_ns`` as an int, or ``ValueError`` when ROS time cannot hold it."""
    s = int(stamp_ns)
    if not 0 <= s < MAX_STAMP_NS:
        raise ValueError(f"stamp_ns {stamp_ns} is outside 0 .. 2^31 s (ROS time)")
    return s


def time_msg(stamp_ns: int) -> dict[str, int]:
    """``builtin_interfaces/Time`` of ``stamp_ns``."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return {"sec": sec, "nanosec": nanosec}


def stamp_ns_of(header: Mapping[str, Any]) -> int:
    """The stamp of a decoded ``std_msgs/Header``, ns."""
    t = header["stamp"]
    return int(t["sec"]) * NS_PER_S + int(t["nanosec"])


def header(stamp_ns: int, frame_id: str) -> dict[str, Any]:
    """``std_msgs/Header``."""
    return {"stamp": time_msg(stamp_ns), "frame_id": frame_id}


def yaw_quaternion(yaw_rad: float) -> dict[str, float]:
    """``geometry_msgs/Quaternion`` of a rotation by ``yaw_rad`` about z."""
    half = 0.5 * float(yaw_rad)
    return {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)}


def yaw_of_quaternion(q: Mapping[str, float]) -> float:
    """The yaw (rad, about z) of a ``geometry_msgs/Quaternion`` dict."""
    x, y, z, w = (float(q[k]) for k in ("x", "y", "z", "w"))
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def planar_pose(x_m: float, y_m: float, yaw_rad: float) -> dict[str, Any]:
    """``geometry_msgs/Pose`` of a planar pose (z = 0)."""
    return {"position": {"x": float(x_m), "y": float(y_m), "z": 0.0},
            "orientation": yaw_quaternion(yaw_rad)}


def covariance6(cov3: np.ndarray) -> list[float]:
    """A ``(3, 3)`` ``(x, y, yaw)`` covariance as the 36 values of a ROS pose covariance
    (rows and columns 0, 1 and 5; z, roll and pitch are fixed on a flat floor: 0)."""
    c = np.asarray(cov3, dtype=np.float64)
    if c.shape != (3, 3):
        raise ValueError(f"pose covariance must be (3, 3), got {c.shape}")
    cov6 = np.zeros((6, 6))
    cov6[np.ix_((0, 1, 5), (0, 1, 5))] = c
    return cov6.ravel().tolist()


def covariance3(cov36: Sequence[float]) -> np.ndarray:
    """The ``(3, 3)`` ``(x, y, yaw)`` block of a ROS 36-value pose or twist covariance."""
    c = np.asarray(cov36, dtype=np.float64).reshape(6, 6)
    return c[np.ix_((0, 1, 5), (0, 1, 5))].copy()


def covariance_problem(cov: Sequence[float], diagonal: tuple[int, ...]) -> str | None:
    """Why a ROS covariance (row-major values) states no variance at ``diagonal``, or None
    when it does: ``-1`` in element 0 ("no estimate"), all zeros ("unknown"), or an entry
    that is not finite and positive."""
    if len(cov) == 0 or cov[0] == -1.0:
        return "element 0 is -1: no estimate"
    if not any(cov):
        return "all zeros: unknown"
    for i in diagonal:
        if not (math.isfinite(cov[i]) and cov[i] > 0.0):
            return f"element {i} is {cov[i]!r}, not a positive variance"
    return None


def stated_variances(cov: Sequence[float], diagonal: tuple[int, ...]) -> tuple[float, ...] | None:
    """The variances at ``diagonal`` of a ROS covariance, or None when it states none
    (:func:`covariance_problem`)."""
    if covariance_problem(cov, diagonal) is not None:
        return None
    return tuple(float(cov[i]) for i in diagonal)


def odometry_msg(stamp_ns: int, x_m: float, y_m: float, yaw_rad: float, cov3: np.ndarray,
                 frame_id: str, child_frame_id: str, *, v_mps: float = 0.0, w_radps: float = 0.0,
                 twist_cov3: np.ndarray | None = None) -> dict[str, Any]:
    """``nav_msgs/Odometry`` of a planar pose (``frame_id``) with its ``(3, 3)``
    covariance, and the body velocity in ``child_frame_id`` (zero with zero covariance
    when not estimated)."""
    return {
        "header": header(stamp_ns, frame_id),
        "child_frame_id": child_frame_id,
        "pose": {"pose": planar_pose(x_m, y_m, yaw_rad), "covariance": covariance6(cov3)},
        "twist": {"twist": {"linear": {"x": float(v_mps)}, "angular": {"z": float(w_radps)}},
                  "covariance": covariance6(np.zeros((3, 3)) if twist_cov3 is None else twist_cov3)},
    }


def pose_with_covariance_msg(stamp_ns: int, frame_id: str, x_m: float, y_m: float, yaw_rad: float,
                             cov3: np.ndarray) -> dict[str, Any]:
    """``geometry_msgs/PoseWithCovarianceStamped`` of a planar pose."""
    return {"header": header(stamp_ns, frame_id),
            "pose": {"pose": planar_pose(x_m, y_m, yaw_rad), "covariance": covariance6(cov3)}}


def transform_msg(stamp_ns: int, parent: str, child: str, xyz: Sequence[float],
                  quat_xyzw: Sequence[float]) -> dict[str, Any]:
    """``geometry_msgs/TransformStamped``: frame ``child`` in frame ``parent``."""
    return {"header": header(stamp_ns, parent), "child_frame_id": child, "transform": {
        "translation": {"x": float(xyz[0]), "y": float(xyz[1]), "z": float(xyz[2])},
        "rotation": {"x": float(quat_xyzw[0]), "y": float(quat_xyzw[1]),
                     "z": float(quat_xyzw[2]), "w": float(quat_xyzw[3])}}}


def planar_transform_msg(stamp_ns: int, parent: str, child: str,
                         pose_xyyaw: Sequence[float] | np.ndarray) -> dict[str, Any]:
    """``geometry_msgs/TransformStamped`` of a planar pose ``(x_m, y_m, yaw_rad)``."""
    q = yaw_quaternion(pose_xyyaw[2])
    return transform_msg(stamp_ns, parent, child, (pose_xyyaw[0], pose_xyyaw[1], 0.0),
                         (q["x"], q["y"], q["z"], q["w"]))


def path_msg(stamp_ns: int, frame_id: str, stamps_ns: Sequence[int], poses_xyyaw: np.ndarray) -> dict[str, Any]:
    """``nav_msgs/Path`` of ``(N, 3)`` planar poses with their stamps (ns)."""
    poses = np.asarray(poses_xyyaw, dtype=np.float64).reshape(-1, 3)
    return {"header": header(stamp_ns, frame_id), "poses": [
        {"header": header(int(s), frame_id), "pose": planar_pose(*p)} for s, p in zip(stamps_ns, poses)]}


def line_list_marker(stamp_ns: int, frame_id: str, ns: str, marker_id: int,
                     segments_xy: np.ndarray, rgba: Sequence[float], width_m: float) -> dict[str, Any]:
    """A ``visualization_msgs/Marker`` ``LINE_LIST``: ``(N, 2, 2)`` segments (start and end
    x, y, metres) at z = 0, ``width_m`` wide, colour ``rgba`` (0..1). With no segment it is
    a ``DELETE`` of that id (RViz refuses an empty line list)."""
    seg = np.asarray(segments_xy, dtype=np.float64).reshape(-1, 2, 2)
    points = [{"x": float(x), "y": float(y), "z": 0.0} for x, y in seg.reshape(-1, 2)]
    return {"header": header(stamp_ns, frame_id), "ns": ns, "id": int(marker_id),
            "type": 5, "action": 0 if len(points) else 2,
            "pose": {"orientation": {"w": 1.0}}, "scale": {"x": float(width_m)},
            "color": {"r": rgba[0], "g": rgba[1], "b": rgba[2], "a": rgba[3]},
            "points": points}


def key_values(values: Mapping[str, Any]) -> list[dict[str, str]]:
    """``diagnostic_msgs/KeyValue`` list of a mapping (values as text)."""
    return [{"key": str(k), "value": str(v)} for k, v in values.items()]


def diagnostic_status(level: int, name: str, message: str, hardware_id: str,
                      values: Mapping[str, Any]) -> dict[str, Any]:
    """``diagnostic_msgs/DiagnosticStatus`` (``level``: 0 OK, 1 WARN, 2 ERROR, 3 STALE)."""
    if level not in (0, 1, 2, 3):
        raise ValueError(f"diagnostic level must be 0..3, got {level}")
    return {"level": level, "name": name, "message": message, "hardware_id": hardware_id,
            "values": key_values(values)}


def compressed_image_msg(stamp_ns: int, frame_id: str, image_format: str, data: bytes) -> dict[str, Any]:
    """``sensor_msgs/CompressedImage`` (``image_format``: ``"jpeg"`` or ``"png"``)."""
    return {"header": header(stamp_ns, frame_id), "format": image_format, "data": data}


def imu_yaw_rate_msg(stamp_ns: int, frame_id: str, yaw_rate_radps: float,
                     yaw_rate_var_rad2ps2: float | None = None) -> dict[str, Any]:
    """``sensor_msgs/Imu`` holding only a yaw rate: ``angular_velocity.z`` (rad/s); the
    orientation and linear acceleration are "not provided" (covariance[0] = -1) and the
    angular velocity covariance is all zero ("unknown"), or holds only the yaw rate's
    variance (element 8, (rad/s)^2) when ``yaw_rate_var_rad2ps2`` is given."""
    av_cov = [0.0] * 9
    if yaw_rate_var_rad2ps2 is not None:
        av_cov[8] = float(yaw_rate_var_rad2ps2)
    return {
        "header": header(stamp_ns, frame_id),
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        "orientation_covariance": [-1.0] + [0.0] * 8,
        "angular_velocity": {"x": 0.0, "y": 0.0, "z": float(yaw_rate_radps)},
        "angular_velocity_covariance": av_cov,
        "linear_acceleration": {"x": 0.0, "y": 0.0, "z": 0.0},
        "linear_acceleration_covariance": [-1.0] + [0.0] * 8,
    }


def tf_message(transforms: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """``tf2_msgs/TFMessage`` of ``TransformStamped`` dicts."""
    return {"transforms": list(transforms)}


def participant_entities_info(participant_guid: bytes, node_namespace: str, node_name: str,
                              reader_guids: Iterable[bytes], writer_guids: Iterable[bytes],
                              distro: str | None = None) -> dict[str, Any]:
    """``rmw_dds_common/msg/ParticipantEntitiesInfo`` of one participant holding one node:
    what a ROS 2 node publishes on ``ros_discovery_info`` so that ``ros2 node list`` and
    ``ros2 node info`` know which DDS readers and writers are the node's. The GUIDs (16
    bytes each) are zero-padded to ``distro``'s GID size (:func:`gid_size`)."""
    n = gid_size(distro)

    def gid(guid: bytes) -> dict[str, bytes]:
        g = bytes(guid)
        if len(g) > n:
            raise ValueError(f"a GUID of {len(g)} bytes does not fit a GID of {n}")
        return {"data": g + b"\x00" * (n - len(g))}

    return {"gid": gid(participant_guid), "node_entities_info_seq": [{
        "node_namespace": node_namespace or "/", "node_name": node_name,
        "reader_gid_seq": [gid(g) for g in reader_guids], "writer_gid_seq": [gid(g) for g in writer_guids]}]}
