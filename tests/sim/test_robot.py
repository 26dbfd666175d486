"""The virtual robot: parts played in time order on the injected clock, read by real drivers."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.kobuki.driver import KobukiDriver
from robotd.base.camera import FloorCameraModel
from robotd.base.clock import ManualClock
from robotd.base.errors import ConfigError
from robotd.base.messages import Frame, WheelTicks, YawRate
from sim.robot import VirtualRobot, VirtualRobotSettings


def test_a_short_run_through_the_kobuki_driver_and_the_camera():
    clock = ManualClock()
    settings = VirtualRobotSettings(route="square", seed=3, duration_s=0.5, camera_queue_size=2)
    with VirtualRobot(settings, FloorCameraModel.default(), clock) as robot, \
            KobukiDriver(robot.port, clock) as driver:
        assert robot.emulators == [robot.base] and robot.cameras == [robot.camera]
        robot.start()
        base: list[WheelTicks | YawRate] = []
        frames: list[tuple[int, Frame]] = []
        while not (robot.finished.is_set() and len(frames) == robot.frames_emitted
                   and sum(isinstance(m, WheelTicks) for m in base) >= robot.packets_emitted):
            base += driver.read(0.01)
            frame = robot.camera.read(0.01)
            if frame is not None:
                frames.append((clock.now_ns(), frame))
        assert robot.error is None
    assert robot.packets_emitted == 26 and robot.frames_emitted == 15  # 50 Hz and 30 Hz
    wheels = [m for m in base if isinstance(m, WheelTicks)]
    assert [m.stamp_ns for m in wheels] == list(robot.base.stamp_ns)
    # The clock was at each frame's time when it was emitted, never behind.
    assert [f.stamp_ns for _, f in frames] == [round(i * 1e9 / 30) for i in range(15)]
    assert all(now >= f.stamp_ns for now, f in frames)
    assert clock.now_ns() == robot.base.stamp_ns[-1] == 500_000_000
    stamps_ns, poses = robot.ground_truth(rate_hz=10.0)
    np.testing.assert_array_equal(stamps_ns, np.arange(5) * 100_000_000)
    np.testing.assert_allclose(poses, robot.motion.pose_at(stamps_ns / 1e9))
    assert robot.duration_s == 0.5 and robot.sim_time_s == 0.5


def test_an_unknown_route_is_a_config_error():
    with pytest.raises(ConfigError, match="unknown route"):
        VirtualRobot(VirtualRobotSettings(route="moon"), FloorCameraModel.default(), ManualClock())


def test_the_optional_forward_camera_plays_with_the_floor_camera():
    clock = ManualClock()
    settings = VirtualRobotSettings(route="corridor", seed=1, duration_s=0.5, camera_queue_size=2,
                                    forward_camera=True, forward_fps=10.0)
    with VirtualRobot(settings, FloorCameraModel.default(), clock) as robot:
        assert robot.forward is not None and robot.cameras == [robot.camera, robot.forward]
        robot.start()
        floor, forward = [], []
        while not (robot.finished.is_set() and len(floor) + len(forward) == robot.frames_emitted):
            for cam, got in ((robot.camera, floor), (robot.forward, forward)):
                frame = cam.read(0.01)
                if frame is not None:
                    got.append(frame)
        assert robot.error is None
    assert len(floor) == 15 and len(forward) == 5  # 30 Hz and 10 Hz over 0.5 s
    assert [f.stamp_ns for f in forward] == [i * 100_000_000 for i in range(5)]
    assert all(f.camera == "forward" and f.image.shape == (480, 640) for f in forward)
    # The robot stands still for its first 2 s: the forward frames differ only by noise.
    diff = np.abs(forward[0].image.astype(int) - forward[-1].image.astype(int))
    assert diff.mean() < 4.0


def test_without_the_forward_camera_nothing_changes():
    settings = VirtualRobotSettings(route="square", duration_s=0.2)
    with VirtualRobot(settings, FloorCameraModel.default(), ManualClock()) as robot:
        assert robot.forward is None and robot.cameras == [robot.camera]


def test_a_kidnapped_robot_measures_what_the_same_drive_without_the_kidnapping_does_until_the_lift():
    """``robotd demo --kidnap`` is judged against the same drive without it: same seed,
    same wheel and gyro readings until the lift (sim.sensors.simulate_sensors' ``draws_of``)."""
    def feedback(kidnap):
        settings = VirtualRobotSettings(route="office", seed=2, duration_s=40.0, kidnap=kidnap)
        with VirtualRobot(settings, FloorCameraModel.default(), ManualClock()) as robot:
            return robot.base.feedback

    plain, kid = feedback(None), feedback((20.0, 8.0, 5.0))
    before = plain.t_s < 20.0
    for name in ("left_ticks", "right_ticks", "angle_cdeg", "gyro_digits"):
        np.testing.assert_array_equal(getattr(plain, name)[before], getattr(kid, name)[before])
    assert not np.array_equal(plain.left_ticks, kid.left_ticks)
