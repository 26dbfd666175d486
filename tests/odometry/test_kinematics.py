"""Differential-drive kinematics against hand-derived answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from robotd.base.messages import WheelTicks
from robotd.odometry.kinematics import (
    DiffDriveParams,
    WheelOdometry,
    arc_increment,
    integrate_pose,
    unwrap_ticks_delta,
    wheel_increment,
)

# Round numbers so the answers can be worked out by hand: 1000 ticks per turn of a
# 5 cm wheel is 2*pi*0.05/1000 m per tick; the wheels are 0.5 m apart.
ROUND = DiffDriveParams(wheel_radius_m=0.05, wheel_base_m=0.5, ticks_per_rev=1000.0)


@pytest.mark.parametrize("prev, cur, expected", [
    (65535, 0, 1),          # the counter wraps forwards
    (0, 65535, -1),         # and backwards
    (100, 250, 150),
    (65000, 500, 1036),     # 536 to the wrap, then 500
    (500, 65000, -1036),
    (0, 32767, 32767),      # the largest forward step
    (0, 32768, -32768),     # half the range is taken as backwards
    (7, 7, 0),
])
def test_unwrap_ticks_delta_16_bit(prev, cur, expected):
    assert unwrap_ticks_delta(prev, cur) == expected


def test_unwrap_ticks_delta_other_widths():
    assert unwrap_ticks_delta(250, 4, bits=8) == 10
    assert unwrap_ticks_delta(4, 250, bits=8) == -10
    assert unwrap_ticks_delta(2**32 - 3, 2, bits=32) == 5


@given(prev=st.integers(0, 65535), delta=st.integers(-32768, 32767))
def test_unwrap_recovers_any_step_below_half_the_range(prev, delta):
    assert unwrap_ticks_delta(prev, (prev + delta) % 65536) == delta


def test_kobuki_metres_per_tick():
    p = DiffDriveParams()
    assert (p.wheel_radius_m, p.wheel_base_m, p.ticks_per_rev) == (0.035, 0.23, 2578.33)
    assert p.metres_per_tick == pytest.approx(2 * math.pi * 0.035 / 2578.33, rel=1e-12)
    assert p.metres_per_tick == pytest.approx(85.29e-6, rel=1e-3)


def test_params_reject_non_positive_geometry():
    with pytest.raises(ValueError, match="wheel_base_m"):
        DiffDriveParams(wheel_base_m=0.0)


def test_straight_tick_count_gives_exact_distance():
    # One full wheel turn on both sides: the rim circumference, no turn.
    ds, dyaw = wheel_increment(1000, 1000, ROUND)
    assert ds == pytest.approx(2 * math.pi * 0.05, abs=1e-15)
    assert dyaw == 0.0


def test_pure_rotation_is_tick_difference_over_wheel_base():
    # Half a turn backwards on the left, forwards on the right: each rim moves
    # pi*0.05 m, so dyaw = (dr - dl)/B = 2*pi*0.05/0.5 = pi/5, and the centre stays put.
    ds, dyaw = wheel_increment(-500, 500, ROUND)
    assert ds == pytest.approx(0.0, abs=1e-15)
    assert dyaw == pytest.approx(math.pi / 5, abs=1e-14)


def test_one_wheel_only_turns_about_the_other():
    ds, dyaw = wheel_increment(0, 1000, ROUND)
    assert ds == pytest.approx(math.pi * 0.05)
    assert dyaw == pytest.approx(2 * math.pi * 0.05 / 0.5)


def test_integrate_straight_along_current_heading():
    pose = integrate_pose(np.array([1.0, 2.0, math.pi / 2]), 1.0, 0.0)
    np.testing.assert_allclose(pose, [1.0, 3.0, math.pi / 2], atol=1e-15)


def test_integrate_quarter_circle_is_arc_exact():
    # Radius 1 m, a quarter turn to the left: from the origin facing +x to (1, 1) facing +y.
    pose = integrate_pose(np.zeros(3), math.pi / 2, math.pi / 2)
    np.testing.assert_allclose(pose, [1.0, 1.0, math.pi / 2], atol=1e-15)


def test_integrate_turn_in_place_and_wrap():
    np.testing.assert_allclose(integrate_pose(np.zeros(3), 0.0, math.pi / 3), [0, 0, math.pi / 3])
    pose = integrate_pose(np.array([0.0, 0.0, 3.0]), 0.0, 0.5)
    assert pose[2] == pytest.approx(3.5 - 2 * math.pi)


def test_arc_increment_on_arrays_matches_single_steps():
    ds = np.array([0.0, 1.0, 2.0])
    dth = np.array([0.3, 0.0, -1.0])
    stacked = arc_increment(ds, dth)
    assert stacked.shape == (3, 3)
    for i in range(3):
        np.testing.assert_allclose(stacked[i], arc_increment(ds[i], dth[i]), atol=1e-15)
    # Chord of a 1-rad arc of length 2 (radius 2): 2*2*sin(0.5), at -0.5 rad.
    chord = 4 * math.sin(0.5)
    np.testing.assert_allclose(stacked[2], [chord * math.cos(0.5), -chord * math.sin(0.5), -1.0])


def test_wheel_odometry_straight_across_the_counter_wrap():
    odo = WheelOdometry(ROUND, noise_m_per_sqrt_m=0.01)
    first = odo.update(WheelTicks(0, 65000, 64000))
    assert (first.x_m, first.y_m, first.yaw_rad) == (0.0, 0.0, 0.0)
    # Both wheels advance 2000 ticks; both counters wrap on the way.
    p = odo.update(WheelTicks(20_000_000, (65000 + 2000) % 65536, (64000 + 2000) % 65536))
    s = 2000 * 2 * math.pi * 0.05 / 1000  # 2 turns = 0.6283 m
    assert (p.x_m, p.y_m, p.yaw_rad) == pytest.approx((s, 0.0, 0.0), abs=1e-12)
    assert p.stamp_ns == 20_000_000
    assert odo.distance_m == pytest.approx(s)
    # Covariance from the per-wheel variance q*|s_i| (q = 0.01^2) along +x:
    # var_x = (1/2)^2 q s * 2 = q s / 2 and var_yaw = (1/B)^2 q s * 2 = 2 q s / B^2.
    q = 0.01 ** 2
    assert p.covariance[0, 0] == pytest.approx(q * s / 2)
    assert p.covariance[2, 2] == pytest.approx(2 * q * s / 0.5 ** 2)
    assert p.covariance[0, 2] == pytest.approx(0.0, abs=1e-18)


def test_wheel_odometry_turn_then_drive():
    odo = WheelOdometry(ROUND)
    odo.update(WheelTicks(0, 0, 0))
    # Turn left in place by pi/2: each rim moves B/2 * pi/2 = 0.3927 m, 1250 ticks.
    ticks = round(0.25 * math.pi / 2 / (2 * math.pi * 0.05 / 1000))  # 1250
    odo.update(WheelTicks(1, (-ticks) % 65536, ticks))
    p = odo.update(WheelTicks(2, (-ticks + 1000) % 65536, ticks + 1000))
    assert p.yaw_rad == pytest.approx(math.pi / 2, abs=1e-12)
    assert (p.x_m, p.y_m) == pytest.approx((0.0, 2 * math.pi * 0.05), abs=1e-12)


def test_wheel_odometry_rebase_does_not_move():
    odo = WheelOdometry(ROUND)
    odo.update(WheelTicks(0, 100, 100))
    odo.rebase(WheelTicks(5, 40000, 9000))
    p = odo.update(WheelTicks(6, 40000, 9000))
    assert (p.x_m, p.y_m, p.yaw_rad) == (0.0, 0.0, 0.0)
