"""The same virtual robot on another drive: a run's base errors from another seed."""

from __future__ import annotations

import numpy as np

from sim.emulators.kobuki import simulate_kobuki
from sim.route import build_route, plan_motion
from sim.sensors import BaseSensorParams, draw_errors


def test_given_errors_are_the_bases_and_the_rest_of_the_run_is_the_seeds():
    motion = plan_motion(build_route("straight")).truncated(3.0)
    p = BaseSensorParams()
    own = simulate_kobuki(motion, p, np.random.default_rng(11))
    base0 = draw_errors(p, np.random.default_rng(0))
    other = simulate_kobuki(motion, p, np.random.default_rng(11), errors=base0)
    e = other.sensors.errors
    assert (e.left_radius_error, e.right_radius_error, e.wheel_base_error, e.gyro_scale_error) == (
        base0.left_radius_error, base0.right_radius_error, base0.wheel_base_error, base0.gyro_scale_error)
    # The turn-on bias is the drive's (seed 11's), and so is every later draw: the gyro noise
    # differs only by the scale, which multiplies a standstill's zero true rate.
    assert e.gyro_bias0_radps == own.sensors.errors.gyro_bias0_radps
    still = motion.t_s[:-1] < 1.0
    n = int(still.sum()) // 4
    assert np.array_equal(other.sensors.gyro_radps[:n], own.sensors.gyro_radps[:n])
    assert not np.array_equal(other.sensors.wheel_angle_rad, own.sensors.wheel_angle_rad)
