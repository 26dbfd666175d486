"""Variances stated with the readings (a ROS 2 base's odometry twist covariance, its IMU's
angular velocity covariance) replace the filter's noise model: single steps against the
closed-form Kalman update, then the stream filter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.base.messages import WheelTicks, YawRate
from robotd.odometry.ekf import IB, IV, IW, EkfParams, EkfState, update_gyro, update_wheels, wheel_noise
from robotd.odometry.fusion import OdometryFilter
from robotd.odometry.kinematics import DiffDriveParams

MS = 1_000_000
ROUND = DiffDriveParams(wheel_radius_m=0.05, wheel_base_m=0.5, ticks_per_rev=1000.0)


def _prior() -> EkfState:
    return EkfState(0, np.array([0, 0, 0, 0.1, 0.0, 0.0]), np.diag([1e-6, 1e-6, 1e-6, 0.04, 0.09, 1e-4]))


def test_a_stated_gyro_variance_weighs_the_update() -> None:
    prior, z = _prior(), 0.3
    # h = [w + bias]: prior variance of h x is 0.09 + 1e-4, its mean 0
    hph = 0.09 + 1e-4
    for var in (1e-4, 1e-2):
        post = update_gyro(prior, z, EkfParams(), yaw_rate_var_rad2ps2=var)
        k_w = 0.09 / (hph + var)  # the gain's yaw-rate row
        assert post.mean[IW] == pytest.approx(k_w * z, rel=1e-9)
        h_var = post.cov[IW, IW] + post.cov[IB, IB] + 2 * post.cov[IW, IB]
        assert h_var == pytest.approx(hph * var / (hph + var), rel=1e-9)
    default = update_gyro(prior, z, EkfParams())  # gyro_noise_radps = 0.003
    assert default.mean[IW] == pytest.approx(0.09 / (hph + 0.003 ** 2) * z, rel=1e-9)


def test_stated_wheel_variances_replace_the_noise_model_except_at_rest() -> None:
    p = EkfParams()
    assert wheel_noise(0.2, 0.1, p, False, 4e-4, 9e-4) == pytest.approx((0.02, 0.03))
    assert wheel_noise(0.2, 0.1, p, False, None, 9e-4)[0] == pytest.approx(
        p.wheel_v_noise_mps + p.wheel_v_noise_frac * 0.2)
    assert wheel_noise(0.0, 0.0, p, True, 4e-4, 9e-4) == (p.stationary_noise_mps, p.stationary_noise_radps)
    prior = _prior()
    post = update_wheels(prior, 0.2, 0.1, p, False, 4e-4, 9e-4)
    assert post.mean[IV] == pytest.approx(0.1 + 0.04 / (0.04 + 4e-4) * 0.1, rel=1e-9)
    assert post.cov[IV, IV] == pytest.approx(0.04 * 4e-4 / (0.04 + 4e-4), rel=1e-9)


def _drive(w_wheels: float, w_gyro: float, seconds: float, **stated: float | None) -> OdometryFilter:
    """A filter fed 50 Hz ticks of a base driving 0.2 m/s and turning at ``w_wheels`` and a
    100 Hz gyro reading ``w_gyro``; ``stated``: the variances every reading states."""
    f = OdometryFilter(drive=ROUND)
    tpm = 1.0 / ROUND.metres_per_tick
    half = 0.5 * ROUND.wheel_base_m
    left = right = 0.0
    for i in range(int(seconds * 100) + 1):
        t = i * 10 * MS
        f.on_yaw_rate(YawRate(t, w_gyro, "ros2", yaw_rate_var_rad2ps2=stated.get("gyro")))
        if i % 2 == 0:
            f.on_wheels(WheelTicks(t, int(round(left)) % 65536, int(round(right)) % 65536,
                                   speed_var_m2ps2=stated.get("speed"), yaw_rate_var_rad2ps2=stated.get("wheel_w")))
            left += (0.2 - w_wheels * half) * 0.02 * tpm
            right += (0.2 + w_wheels * half) * 0.02 * tpm
    return f


def test_the_filter_follows_the_tighter_stated_source() -> None:
    # The wheels say 0.2 rad/s, the gyro 0.3 rad/s. With the noise model the gyro (3 mrad/s)
    # is far tighter than the wheels' yaw rate (~0.07 rad/s at 0.2 m/s): the estimate
    # follows the gyro. A wheel odometry stating 1 mrad/s makes the wheels the tighter:
    # the filter's yaw rate follows them, its variance is smaller, and the 0.1 rad/s
    # difference goes into the gyro bias.
    own = _drive(0.2, 0.3, 1.0)
    tight_wheels = _drive(0.2, 0.3, 1.0, wheel_w=1e-6)
    s_own, s_tight = own.state, tight_wheels.state
    assert s_own is not None and s_tight is not None
    assert s_own.mean[IW] + s_own.mean[IB] == pytest.approx(0.3, abs=0.005)
    assert abs(s_own.mean[IW] - 0.3) < abs(s_own.mean[IW] - 0.2)
    assert s_own.mean[2] == pytest.approx(0.28, abs=0.01)  # the heading after 1 s, rad
    # tight wheels: the heading turns at their 0.2 rad/s, the bias takes the difference
    assert s_tight.mean[2] == pytest.approx(0.2, abs=0.005)
    assert s_tight.mean[IB] == pytest.approx(0.1, abs=0.01)
    assert abs(s_tight.mean[IW] - 0.2) < 0.025
    assert s_tight.cov[IW, IW] < 0.05 * s_own.cov[IW, IW]
    # a loose stated gyro variance (0.1 rad/s, against the model's 3 mrad/s): the wheels
    # pull the yaw rate towards their 0.2 rad/s, and it is less certain
    loose_gyro = _drive(0.2, 0.3, 1.0, gyro=1e-2).state
    assert loose_gyro is not None
    assert loose_gyro.mean[IW] < s_own.mean[IW] - 0.005
    assert loose_gyro.cov[IW, IW] > 10 * s_own.cov[IW, IW]


def test_a_stated_speed_variance_tightens_the_speed() -> None:
    own = _drive(0.0, 0.0, 0.5).state
    tight = _drive(0.0, 0.0, 0.5, speed=1e-6).state
    assert own is not None and tight is not None
    # (each 20 ms reading is 12 or 13 ticks of 0.31 mm: 0.19 or 0.20 m/s)
    assert math.isclose(own.mean[IV], 0.2, abs_tol=0.015) and math.isclose(tight.mean[IV], 0.2, abs_tol=0.015)
    assert own.mean[0] == pytest.approx(0.1, abs=0.001) and tight.mean[0] == pytest.approx(0.1, abs=0.001)
    assert tight.cov[IV, IV] < 0.1 * own.cov[IV, IV]
