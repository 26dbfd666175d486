"""The ROS 2 base and camera drivers, fed by a publisher in another process (a ROS 2 base
driver and camera node as far as DDS can tell), all on the loopback interface."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from drivers.ros2 import dds  # noqa: E402
from drivers.ros2.inputs import Ros2Base, Ros2Camera, image_to_grey  # noqa: E402
from robotd.base import ros2msg  # noqa: E402
from robotd.base.clock import MonotonicClock  # noqa: E402
from tests.drivers.test_ros2_dds import PEER, domain_for, peer_env  # noqa: E402

R, B, TPR = 0.035, 0.23, 2578.33


def unwrap(ticks: list[int]) -> np.ndarray:
    d = np.diff(np.asarray(ticks, dtype=np.int64))
    return np.concatenate([[0], np.cumsum((d + 32768) % 65536 - 32768)])


def test_base_and_camera_from_a_publisher_process() -> None:
    domain = domain_for(3)
    clock = MonotonicClock()
    cfg = dds.loopback_config()
    base = Ros2Base(clock, odometry_topic="/odom", imu_topic="/imu", wheel_radius_m=R, wheel_base_m=B,
                    ticks_per_rev=TPR, domain_id=domain, timeout_s=0.2, dds_config=cfg)
    cam = Ros2Camera(clock, camera="floor", topic="/floor_camera/image_raw", domain_id=domain, timeout_s=0.5,
                     dds_config=None)  # the same participant's domain: already configured above
    peer = subprocess.Popen([sys.executable, str(PEER), "pub", str(domain), "2.0"], env=peer_env(domain),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    got: list = []
    frames: list = []
    try:
        while peer.poll() is None:
            got += base.read(0.05)
            frames += cam.read(0.0)
        for _ in range(10):  # what is still in flight
            got += base.read(0.05)
            frames += cam.read(0.0)
        out, err = peer.communicate(timeout=10)
        bstats, cstats = base.stats(), cam.stats()
    finally:
        base.close()
        cam.close()
    assert peer.returncode == 0, err.decode()[-2000:]
    sent = [json.loads(line) for line in out.decode().splitlines()]
    odom_sent = [s["stamp_ns"] for s in sent if s["topic"] == "/odom"]
    ticks = [m for m in got if type(m).__name__ == "WheelTicks"]
    yaws = [m for m in got if type(m).__name__ == "YawRate"]
    # every odometry message arrived (reliable), stamped from its header on robotd's clock
    assert len(ticks) == len(odom_sent) == bstats["odometry_msgs"]
    offset = base._offset_ns
    assert [t.stamp_ns + offset for t in ticks] == odom_sent
    assert abs(ticks[0].stamp_ns - clock.now_ns()) < 30e9
    # the motion: 0.2 m/s along an arc turning at 0.1 rad/s, in [robot]'s ticks
    left, right = unwrap([t.left_ticks for t in ticks]), unwrap([t.right_ticks for t in ticks])
    t_s = (np.array([t.stamp_ns for t in ticks]) - ticks[0].stamp_ns) / 1e9
    per_m = TPR / (2 * math.pi * R)
    # (on the arc the chord between messages, along the mean heading, is the arc length to 1e-6)
    assert np.allclose((left + right) / 2, 0.2 * t_s * per_m, atol=1.0)
    assert np.allclose(right - left, 0.1 * t_s * B * per_m, atol=1.0)
    # the gyro: every message the driver took is the published yaw rate, with its variance
    assert len(yaws) >= 0.8 * len(odom_sent) and {y.yaw_rate_radps for y in yaws} == {0.1}
    assert {y.source for y in yaws} == {"ros2"}
    assert bstats["imu_yaw_rate_var_rad2ps2"] == pytest.approx(2.5e-5)
    assert bstats["odometry_var_x_m2"] == pytest.approx(1e-4)
    # the stated variances go with the readings to the filter: the IMU's yaw rate, the
    # odometry's twist (forward speed [0], yaw rate [35])
    assert {y.yaw_rate_var_rad2ps2 for y in yaws} == {2.5e-5}
    assert bstats["imu_cov_used"] == bstats["imu_msgs"] and bstats["imu_cov_fallbacks"] == 0
    assert {(t.speed_var_m2ps2, t.yaw_rate_var_rad2ps2) for t in ticks} == {(1e-4, 4e-4)}
    assert bstats["odometry_cov_used"] == len(ticks) and bstats["odometry_cov_fallbacks"] == 0
    # the 0.5 s pause of the base's odometry is one gap, counted and ended
    # (the publisher's end may already be a second loss, still open)
    assert bstats["gaps"] == 1 and bstats["losses"] in (1, 2) and 0.1 < bstats["last_gap_s"] < 1.0
    # the camera: grey frames in order, stamped from their headers (10 Hz), best effort
    cam_sent = [s["stamp_ns"] for s in sent if s["topic"] == "/floor_camera/image_raw"]
    assert len(frames) >= 0.8 * len(cam_sent) and cstats["frames"] == len(frames)
    assert all(f.camera == "floor" and f.image.shape == (48, 64) for f in frames)
    assert {f.stamp_ns + cam._offset_ns for f in frames} <= set(cam_sent)
    k = (frames[0].stamp_ns + cam._offset_ns - cam_sent[0]) // 20_000_000  # its publisher step
    assert np.array_equal(frames[0].image, ((np.arange(48 * 64) + k) % 256).astype(np.uint8).reshape(48, 64))


def test_image_encodings() -> None:
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[..., 0] = 255  # pure red in rgb8
    m = {"height": 2, "width": 3, "encoding": "rgb8", "step": 9, "is_bigendian": 0, "data": rgb.tobytes()}
    assert image_to_grey(m).tolist() == [[76] * 3] * 2  # 0.299 * 255
    m = {**m, "encoding": "bgr8"}
    assert image_to_grey(m).tolist() == [[29] * 3] * 2  # 0.114 * 255
    padded = np.arange(2 * 4, dtype=np.uint8).reshape(2, 4)  # step 4 for a width of 3
    m = {"height": 2, "width": 3, "encoding": "mono8", "step": 4, "is_bigendian": 0, "data": padded.tobytes()}
    assert image_to_grey(m).tolist() == [[0, 1, 2], [4, 5, 6]]
    m16 = {"height": 1, "width": 2, "encoding": "mono16", "step": 4, "is_bigendian": 0,
           "data": np.array([0x1234, 0xFF00], "<u2").tobytes()}
    assert image_to_grey(m16).tolist() == [[0x12, 0xFF]]
    with pytest.raises(ValueError, match="encoding"):
        image_to_grey({**m, "encoding": "yuv422"})
    with pytest.raises(ValueError, match="bytes"):
        image_to_grey({**m, "data": b"\0"})


def test_undecodable_and_stale_messages_are_counted() -> None:
    domain = domain_for(4)
    clock = MonotonicClock()
    base = Ros2Base(clock, odometry_topic="/odom", imu_topic="", wheel_radius_m=R, wheel_base_m=B,
                    ticks_per_rev=TPR, domain_id=domain, dds_config=dds.loopback_config())
    try:
        now = ros2msg.time_msg(0)  # Unix time 0: before robotd's clock began
        assert base._on_odometry({"header": {"stamp": now, "frame_id": "odom"}, "pose": {}}) is None
        assert base.stats()["before_start"] == 1
        stamp = base._offset_ns + clock.now_ns()
        m = ros2msg.decode("nav_msgs/msg/Odometry", ros2msg.encode("nav_msgs/msg/Odometry", ros2msg.odometry_msg(
            stamp, 0, 0, 0, np.eye(3), "odom", "base_footprint")))
        assert base._on_odometry(m) is not None
        assert base._on_odometry(m) is None  # the same stamp again
        assert base.stats()["out_of_order"] == 1
    finally:
        base.close()


def test_stated_variances_follow_the_ros_conventions() -> None:
    covariance_problem, stated_variances = ros2msg.covariance_problem, ros2msg.stated_variances
    diag = [0.0] * 36
    diag[0], diag[35] = 4e-4, 9e-3
    assert stated_variances(diag, (0, 35)) == (4e-4, 9e-3)
    assert covariance_problem(diag, (0, 35)) is None
    assert "no estimate" in covariance_problem([-1.0] + [0.0] * 8, (8,))
    assert "unknown" in covariance_problem([0.0] * 9, (8,))
    assert stated_variances([0.0] * 8 + [1e-4], (8,)) == (1e-4,)
    one_missing = [0.0] * 36
    one_missing[0] = 4e-4  # the yaw rate's variance is 0: not a usable measurement noise
    assert "element 35" in covariance_problem(one_missing, (0, 35))
    assert stated_variances([float("nan")] + [0.0] * 7 + [1e-4], (0, 8)) is None
    assert stated_variances([1e-4] * 8 + [-1e-4], (8,)) is None


def test_odometry_twist_covariance_goes_on_the_ticks(caplog: pytest.LogCaptureFixture) -> None:
    domain = domain_for(6)
    clock = MonotonicClock()
    base = Ros2Base(clock, odometry_topic="/odom", imu_topic="/imu", wheel_radius_m=R, wheel_base_m=B,
                    ticks_per_rev=TPR, domain_id=domain, dds_config=dds.loopback_config())
    try:
        stamp = base._offset_ns + clock.now_ns()
        twist = np.diag([4e-4, 0.0, 9e-3])
        m = ros2msg.odometry_msg(stamp, 0, 0, 0, np.eye(3), "odom", "base_footprint", twist_cov3=twist)
        t = base._on_odometry(ros2msg.decode("nav_msgs/msg/Odometry", ros2msg.encode("nav_msgs/msg/Odometry", m)))
        assert (t.speed_var_m2ps2, t.yaw_rate_var_rad2ps2) == (4e-4, 9e-3)
        unknown = ros2msg.odometry_msg(stamp + 10**7, 0.01, 0, 0, np.eye(3), "odom", "base_footprint")
        with caplog.at_level("INFO"):
            for k in range(3):
                unknown["header"] = ros2msg.header(stamp + (k + 1) * 10**7, "odom")
                t = base._on_odometry(unknown)
                assert (t.speed_var_m2ps2, t.yaw_rate_var_rad2ps2) == (None, None)
        assert sum("no usable covariance" in r.message for r in caplog.records) == 1  # logged once
        imu = ros2msg.imu_yaw_rate_msg(stamp, "imu", 0.1)  # all zeros: unknown
        assert base._on_imu(imu).yaw_rate_var_rad2ps2 is None
        st = base.stats()
        assert (st["odometry_cov_used"], st["odometry_cov_fallbacks"], st["imu_cov_fallbacks"]) == (1, 3, 1)
    finally:
        base.close()
