"""A second process on the DDS bus for the ROS 2 tests (run as a script, with its own
``CYCLONEDDS_URI`` pinned to the loopback interface by the test).

``sub DOMAIN OUT.json TIMEOUT_S [MIN_TF [MIN_DISTINCT [MIN_ODOMETRY]]]``: subscribes to ``/tf`` and
``robotd/odometry`` (and ``ros_discovery_info``, in ``ROS_DISTRO``'s layout); once a ``/tf`` sample has arrived (so the publisher has long sent
``/tf_static``) it subscribes to ``/tf_static`` as a late joiner; it stops after MIN_TF
map -> odom transforms with MIN_DISTINCT different values, MIN_ODOMETRY odometry
messages and one static message (or at
the timeout) and writes what it received.

``pub DOMAIN SECONDS``: publishes ``/odom`` (nav_msgs/Odometry: an arc of radius 2 m at
0.2 m/s, 0.1 rad/s) and ``/imu``
(sensor_msgs/Imu) at 50 Hz and ``/floor_camera/image_raw`` (sensor_msgs/Image, best
effort) at 10 Hz, as a ROS 2 base driver and camera node would, with a gap of 0.5 s in
the odometry after 1 s; prints one JSON line per message sent.
"""

from __future__ import annotations

import json
import math
import sys
import time

import numpy as np

from drivers.ros2 import dds
from robotd.base import ros2msg


def sub(domain: int, out: str, timeout_s: float, min_tf: int, min_distinct: int, min_odometry: int) -> None:
    got: dict = {"tf": [], "static": [], "odometry": [], "tf_static_joined_after_s": None, "discovery": []}
    with dds.Participant(domain) as p:
        tf = p.reader("/tf", "tf2_msgs/msg/TFMessage", dds.QOS_TF)
        odom = p.reader("robotd/odometry", "nav_msgs/msg/Odometry")
        discovery = p.discovery_reader(dds.ros_distro())
        readers = [tf, odom, discovery]
        ws = dds.WaitSet(p, readers)
        static = None
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            ws.wait(0.2)
            for m in tf.take_decoded():
                for t in m["transforms"]:
                    tr = t["transform"]
                    got["tf"].append([ros2msg.stamp_ns_of(t["header"]), t["header"]["frame_id"], t["child_frame_id"],
                                      tr["translation"]["x"], tr["translation"]["y"],
                                      ros2msg.yaw_of_quaternion(tr["rotation"]), time.time_ns()])
            for data in discovery.take():
                m = dds.discovery_codec(dds.ros_distro()).decode(data)
                got["discovery"].append({"gid": m["gid"]["data"].hex(), "nodes": [
                    [n["node_namespace"], n["node_name"], [g["data"].hex() for g in n["reader_gid_seq"]],
                     [g["data"].hex() for g in n["writer_gid_seq"]]] for n in m["node_entities_info_seq"]]})
            for m in odom.take_decoded():
                got["odometry"].append([ros2msg.stamp_ns_of(m["header"]), m["header"]["frame_id"],
                                        m["child_frame_id"], m["pose"]["covariance"][0]])
            if static is None and got["tf"]:
                static = p.reader("/tf_static", "tf2_msgs/msg/TFMessage", dds.QOS_TF_STATIC)
                got["tf_static_joined_after_s"] = time.monotonic() - t0
                ws = dds.WaitSet(p, [*readers, static])
            if static is not None:
                for m in static.take_decoded():
                    got["static"].append([[t["header"]["frame_id"], t["child_frame_id"],
                                           t["transform"]["translation"]["z"]] for t in m["transforms"]])
            map_odom = [tuple(t[3:6]) for t in got["tf"] if t[1] == "map"]
            if (got["static"] and len(map_odom) >= min_tf and len(set(map_odom)) >= min_distinct
                    and len(got["odometry"]) >= min_odometry):
                break
    with open(out, "w") as f:
        json.dump(got, f)


def pub(domain: int, seconds: float) -> None:
    with dds.Participant(domain) as p:
        odom = p.writer("/odom", "nav_msgs/msg/Odometry")
        imu = p.writer("/imu", "sensor_msgs/msg/Imu", dds.QOS_SENSOR)
        cam = p.writer("/floor_camera/image_raw", "sensor_msgs/msg/Image", dds.QOS_SENSOR)
        t0 = time.monotonic()  # wait until the driver under test has matched (at most 10 s)
        while time.monotonic() - t0 < 10 and not (odom.matched() and cam.matched()):
            time.sleep(0.01)
        t_start = time.monotonic()
        i = 0
        stamp0 = time.time_ns()
        while (elapsed_s := time.monotonic() - t_start) < seconds:
            stamp = stamp0 + i * 20_000_000
            t_s = i * 0.02
            # a 0.5 s gap in the base's odometry, in wall time (the driver times gaps on its
            # clock; on a loaded machine the loop runs slower than its 20 ms stamps)
            if not 1.0 <= elapsed_s < 1.5:
                yaw = 0.1 * t_s  # an arc of radius 2 m at 0.2 m/s, as a differential drive moves
                odom.publish(ros2msg.odometry_msg(stamp, 2.0 * math.sin(yaw), 2.0 * (1.0 - math.cos(yaw)), yaw,
                                                  np.diag([1e-4, 1e-4, 1e-3]), "odom", "base_footprint",
                                                  v_mps=0.2, w_radps=0.1, twist_cov3=np.diag([1e-4, 1e-4, 4e-4])))
                print(json.dumps({"topic": "/odom", "stamp_ns": stamp}), flush=True)
            m = ros2msg.imu_yaw_rate_msg(stamp, "imu_link", 0.1)
            m["angular_velocity_covariance"] = [0.0] * 8 + [2.5e-5]
            imu.publish(m)
            if i % 5 == 0:
                img = ((np.arange(48 * 64) + i) % 256).astype(np.uint8).reshape(48, 64)
                cam.publish({"header": ros2msg.header(stamp, "floor_camera_optical_frame"), "height": 48,
                             "width": 64, "encoding": "mono8", "is_bigendian": 0, "step": 64,
                             "data": img.tobytes()})
                print(json.dumps({"topic": "/floor_camera/image_raw", "stamp_ns": stamp}), flush=True)
            i += 1
            time.sleep(0.02)


if __name__ == "__main__":
    role, domain = sys.argv[1], int(sys.argv[2])
    if role == "sub":
        sub(domain, sys.argv[3], float(sys.argv[4]), int(sys.argv[5]) if len(sys.argv) > 5 else 3,
            int(sys.argv[6]) if len(sys.argv) > 6 else 1, int(sys.argv[7]) if len(sys.argv) > 7 else 1)
    else:
        pub(domain, float(sys.argv[3]))
