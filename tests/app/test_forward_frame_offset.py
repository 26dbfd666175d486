"""The forward stage carries a loop measured between two forward frames to the two floor
keyframes it joins: each frame is up to 33 ms off its keyframe's stamp, and the robot's
motion over that time, from the wheel odometry, is taken out of the loop's heading change
and bearing (robotd.app.stages.forward_loops, module notes)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.app.stages.forward_loops import ForwardLoopStage
from robotd.base.geometry import between, compose, wrap_angle
from robotd.base.messages import OdometryUpdate, PoseStamped
from robotd.forward import ForwardDetector, method_params

MOUNT = np.array([0.1, 0.0, 0.0])  # the forward camera 10 cm ahead of the robot's centre
V_MPS, W_RADPS = 0.3, 0.5  # the robot drives an arc


def _pose(t_s: float, start: np.ndarray) -> np.ndarray:
    """The robot on its arc ``t_s`` seconds after ``start``."""
    yaw = W_RADPS * t_s
    r = V_MPS / W_RADPS
    return compose(start, np.array([r * math.sin(yaw), r * (1.0 - math.cos(yaw)), yaw]))


def _feed(stage: ForwardLoopStage, t0_s: float, t1_s: float, start: np.ndarray) -> None:
    """Wheel odometry every 20 ms over ``[t0_s, t1_s]`` of the arc from ``start`` (at time 0)."""
    for t in np.arange(t0_s, t1_s + 1e-9, 0.02):
        p = _pose(float(t), start)
        ps = PoseStamped(int(round(t * 1e9)), float(p[0]), float(p[1]), float(p[2]))
        stage.on_odometry(OdometryUpdate(ps, ps))


def _image(stage: ForwardLoopStage, kf_s: float, frame_s: float, start: np.ndarray) -> None:
    """A forward keyframe at ``kf_s`` whose frame was taken at ``frame_s`` (odometry fed
    around both, as the pipeline has it when the frame comes in)."""
    _feed(stage, kf_s - 0.4, max(kf_s, frame_s), start)
    off = stage._frame_offset(int(round(kf_s * 1e9)), int(round(frame_s * 1e9)))
    assert off is not None
    stage._offsets.append(off)
    stage._poses.append(_pose(kf_s, start))
    stage._chains.append(0)


def _measured(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """``(dyaw, bearing, range)`` of camera pose ``b`` in camera pose ``a``'s planar frame."""
    rel = between(a, b)
    return float(rel[2]), math.atan2(rel[1], rel[0]), math.hypot(rel[0], rel[1])


@pytest.mark.parametrize("measured_range", [True, False])
def test_a_loop_between_frames_is_carried_to_its_keyframes(measured_range):
    stage = ForwardLoopStage(ForwardDetector(method_params("default")), mount=MOUNT)
    # The second pass drives beside the first, 0.25 m to its left and turned 5 deg: the
    # frames' offsets, along the way, are across the bearing.
    first, second = np.zeros(3), np.array([0.0, 0.25, math.radians(5.0)])
    kf_old, fr_old = 0.5, 0.533  # frame 33 ms after its keyframe
    kf_new, fr_new = 0.5, 0.467  # frame 33 ms before
    _image(stage, kf_old, fr_old, first)
    stage._odom.clear()  # the second pass, later in the run
    _image(stage, kf_new, fr_new, second)
    cam = [compose(_pose(t, s), MOUNT) for t, s in ((fr_old, first), (fr_new, second), (kf_old, first),
                                                     (kf_new, second))]
    dyaw, bearing, rng = _measured(cam[0], cam[1])  # what the frames show
    t_dyaw, t_bearing, t_range = _measured(cam[2], cam[3])  # the edge between the keyframes
    # Not correcting would leave the bearing degrees off at this range: the test can fail.
    assert abs(math.degrees(wrap_angle(bearing - t_bearing))) > 3.0
    out = stage._to_keyframes(0, 1, dyaw, bearing, rng if measured_range else None)
    assert math.degrees(abs(wrap_angle(out[0] - t_dyaw))) < 0.01
    assert math.degrees(abs(wrap_angle(out[1] - t_bearing))) < 0.05
    if measured_range:
        assert out[2] == pytest.approx(t_range, abs=1e-4)
    else:
        assert out[2] is None


def test_without_odometry_the_loop_is_published_as_measured():
    stage = ForwardLoopStage(ForwardDetector(method_params("default")), mount=MOUNT)
    assert stage._frame_offset(1_000_000_000, 1_033_000_000) is None
    stage._offsets += [np.zeros(3), np.zeros(3)]
    stage._poses += [None, None]
    stage._chains += [-1, 0]
    assert stage._to_keyframes(0, 1, 0.1, 0.7, None) == pytest.approx((0.1, 0.7, None))


def test_odometry_is_extrapolated_a_little_past_its_newest_sample_only():
    stage = ForwardLoopStage(ForwardDetector(method_params("default")), mount=MOUNT)
    _feed(stage, 0.0, 1.0, np.zeros(3))
    ahead = stage._odom_at(1_030_000_000)
    assert ahead is not None
    np.testing.assert_allclose(ahead, _pose(1.03, np.zeros(3)), atol=1e-4)
    assert stage._odom_at(1_200_000_000) is None
