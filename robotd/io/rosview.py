"""robotd's state as ROS 2 messages: the frame tree, the topics and what goes on them.

Pure functions of robotd's values (no I/O): the app's output stage
(:mod:`robotd.app.outputs`) calls them and hands the encoded bytes to DDS and Foxglove.

Frames (REP 105): ``map`` is the pose graph's loop-corrected frame; ``odom`` is the fused
odometry's frame (continuous, drifting); ``base_footprint`` is the robot on the floor.
The loop correction is the transform ``map -> odom`` = ``T_map_base(k) * T_odom_base(k)^-1``
of the newest keyframe ``k`` in the graph: its optimised pose in the map frame, and the
fused odometry pose at its stamp. It changes when a keyframe enters the graph and when a
loop is accepted; between keyframes it is constant, so ``map -> base_footprint`` moves
with the odometry, as Nav2 expects.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from robotd.base import ros2msg
from robotd.base.camera import FloorCameraModel
from robotd.base.geometry import compose, inverse, quaternion_from_rotation


@dataclass(frozen=True)
class TopicSpec:
    """A topic robotd publishes: ROS name, ROS type and QoS (in ROS 2's terms:
    ``reliable`` or best effort, ``transient_local`` (latched) or volatile, KEEP_LAST
    ``depth``)."""

    topic: str
    type_name: str
    reliable: bool = True
    transient_local: bool = False
    depth: int = 10


def map_to_odom(map_pose_xyyaw: np.ndarray, odom_pose_xyyaw: np.ndarray) -> np.ndarray:
    """``(x_m, y_m, yaw_rad)`` of the ``odom`` frame in the ``map`` frame, from one
    keyframe's pose in each (``(3,)`` each): ``map_pose * odom_pose^-1``."""
    return compose(np.asarray(map_pose_xyyaw, float), inverse(np.asarray(odom_pose_xyyaw, float)))


def forward_camera_rotation(mount_yaw_deg: float) -> np.ndarray:
    """``(3, 3)`` rotation of a level forward camera's optical frame (x right, y down,
    z along the view) in the robot frame, looking along ``mount_yaw_deg``; the columns
    are the optical axes."""
    c, s = math.cos(math.radians(mount_yaw_deg)), math.sin(math.radians(mount_yaw_deg))
    return np.array([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]])


def camera_mounts(cfg: Any) -> list[tuple[str, tuple[float, float, float], tuple[float, float, float, float]]]:
    """The static transforms of the cameras in ``base_link``: ``(child frame, xyz metres,
    quaternion xyzw)`` for ``<camera>_camera_optical_frame`` of the floor camera (from
    ``[floor_camera]``, when it has a source) and the forward camera (from
    ``[forward_camera]``, when the forward detector is on). ``cfg``: a :class:`~robotd.base.config.Config`."""
    out = []
    if cfg.floor_camera.source != "none":
        model = FloorCameraModel.from_config(cfg.floor_camera)
        p = model.position_robot_m
        out.append(("floor_camera_optical_frame", (float(p[0]), float(p[1]), float(p[2])),
                    quaternion_from_rotation(model.rotation_robot_from_camera)))
    fw = cfg.forward_camera
    if cfg.forward_detector.enabled:
        out.append(("forward_camera_optical_frame", (fw.mount_x_m, fw.mount_y_m, fw.mount_height_m),
                    quaternion_from_rotation(forward_camera_rotation(fw.mount_yaw_deg))))
    return out


def static_transforms(stamp_ns: int, base_frame: str, cfg: Any) -> dict[str, Any]:
    """``/tf_static``: ``base_link`` in ``base_frame`` (identity: robotd's robot frame is on
    the floor) and every camera mount in ``base_link``, one ``tf2_msgs/TFMessage``."""
    tfs = [ros2msg.transform_msg(stamp_ns, base_frame, "base_link", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))]
    tfs += [ros2msg.transform_msg(stamp_ns, "base_link", child, xyz, q) for child, xyz, q in camera_mounts(cfg)]
    return ros2msg.tf_message(tfs)


LOOP_COLOURS = {"floor": (0.1, 0.8, 0.2, 0.9), "forward": (0.2, 0.5, 1.0, 0.9)}
"""RGBA of accepted loop edges by source (floor camera: green, forward camera: blue)."""


def loop_markers(stamp_ns: int, frame_id: str, edges: Mapping[str, list[tuple[int, int]]],
                 positions: Mapping[int, tuple[float, float]]) -> dict[str, Any]:
    """``visualization_msgs/MarkerArray`` of accepted loop edges: one ``LINE_LIST`` per
    source (namespace ``loops/<source>``) between the two keyframes' corrected positions
    (``positions``: keyframe id -> (x_m, y_m) in ``frame_id``); edges whose keyframes have
    no position (not in the graph) are left out."""
    markers = []
    for n, source in enumerate(sorted(edges)):
        seg = [(positions[a], positions[b]) for a, b in edges[source] if a in positions and b in positions]
        markers.append(ros2msg.line_list_marker(
            stamp_ns, frame_id, f"loops/{source}", n, np.asarray(seg, float).reshape(-1, 2, 2),
            LOOP_COLOURS.get(source, (1.0, 0.5, 0.0, 0.9)), 0.03))
    return {"markers": markers}


def _level(warn: bool, error: bool = False) -> int:
    return 2 if error else 1 if warn else 0


def diagnostics(stamp_ns: int, counters: Mapping[str, Any], driver_stats: Mapping[str, Mapping[str, Any]],
                queue_drops: Mapping[str, int], localisation: str) -> dict[str, Any]:
    """``diagnostic_msgs/DiagnosticArray`` from what the STATUS line shows: the odometry
    (degraded or not), each driver (connected, gaps), the queues (drops), the map
    (keyframes, loops; the floor's and the forward camera's accepted and refused apart) and the localisation state (``localisation``: ``"localised"``,
    ``"not localised in the stored map"``, ``"lost"``, or ``""`` without a pose graph)."""
    c = counters
    status = [
        ros2msg.diagnostic_status(
            _level(bool(c.get("odometry_degraded"))), "robotd: odometry",
            "degraded" if c.get("odometry_degraded") else "ok", "",
            {k: c[k] for k in ("wheel_msgs", "yaw_msgs", "odometry_rejected", "odometry_degraded_episodes",
                               "vo_fused") if k in c}),
        ros2msg.diagnostic_status(
            0, "robotd: map", f"{c.get('keyframes_stored', 0)} keyframes, {c.get('links_loop', 0)} loops", "",
            {k: c[k] for k in ("keyframes", "keyframes_stored", "links_loop", "loops_accepted",
                               "loops_failed_gate", "forward_loops_accepted", "forward_loops_failed_gate",
                               "frames_unsynced") if k in c}),
        ros2msg.diagnostic_status(
            _level(sum(queue_drops.values()) > 0), "robotd: queues",
            f"{sum(queue_drops.values())} dropped", "", {f"dropped_{k}": v for k, v in queue_drops.items()}),
    ]
    if localisation:
        status.append(ros2msg.diagnostic_status(
            _level(localisation != "localised"), "robotd: localisation", localisation, "",
            {k: c[k] for k in ("localised", "relocalisations", "reloc_candidates_refused", "reloc_group_edges",
                               "forward_loops_grouped") if k in c}))
    for name, st in sorted(driver_stats.items()):
        connected = st.get("connected", 1)
        away = float(st.get("away_s", 0.0) or 0.0)
        msg = "connected" if connected and not away else f"no data for {away:.1f} s"
        status.append(ros2msg.diagnostic_status(
            _level(not connected or away > 0), f"robotd: driver {name}", msg, str(st.get("name", name)),
            {k: v for k, v in st.items() if isinstance(v, int | float | str)}))
    return {"header": ros2msg.header(stamp_ns, ""), "status": status}
