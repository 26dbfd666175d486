"""What a keyframe edge shares with the gyro bias (:meth:`OdometryFilter.keyframe_edge_terms`):
the covariance given the bias at the edge's start and the edge's Jacobian on it, from the
filter's joint covariance of the two keyframes' states."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.base.messages import WheelTicks
from robotd.keyframes import KeyframeSelector
from robotd.odometry.fusion import OdometryFilter
from sim.emulators.kobuki import driver_messages, simulate_kobuki
from sim.route import MotionLimits, build_route, plan_motion
from sim.sensors import BaseSensorParams


def _drive(route: str) -> tuple[list, list, list]:
    """Keyframes (5 cm or 10 deg) on ``route`` with two filters fed the same messages: one
    asked for :meth:`keyframe_edge`, the other for :meth:`keyframe_edge_terms`."""
    motion = plan_motion(build_route(route), MotionLimits())
    msgs = driver_messages(simulate_kobuki(motion, BaseSensorParams(), np.random.default_rng(0)))
    a, b = OdometryFilter(), OdometryFilter()
    selector = KeyframeSelector(0.05, math.radians(10.0))
    frames_ns = (np.arange(0.0, float(motion.t_s[-1]), 1.0 / 30.0) * 1e9).round().astype(np.int64)
    stamps, plain, terms = [], [], []
    i = 0
    for m in msgs:
        for f in (a, b):
            (f.on_wheels if isinstance(m, WheelTicks) else f.on_yaw_rate)(m)
        settled = a.settled_stamp_ns()
        while settled is not None and i < len(frames_ns) and frames_ns[i] <= settled:
            p = a.pose_at(int(frames_ns[i]))
            if p is not None and selector.offer(np.array([p.x_m, p.y_m, p.yaw_rad])):
                stamps.append(int(frames_ns[i]))
                plain.append(a.keyframe_edge(int(frames_ns[i])))
                terms.append(b.keyframe_edge_terms(int(frames_ns[i])))
            i += 1
    return stamps, plain, terms


def test_edge_bias_terms_on_the_square_route():
    """The same edges as :meth:`keyframe_edge`; the conditional covariance plus the bias's
    share ``J J^T P`` gives the edge's covariance back (before the floor); the yaw's
    Jacobian is minus the edge's duration while driving (the heading follows the
    bias-corrected gyro: a bias too large by ``db`` turns the edge by ``-db dt``); the bias
    chain's coefficient lies in [0, 1] and its end variance is the next edge's start one."""
    stamps, plain, terms = _drive("square")
    assert plain[0] is None and terms[0] is None
    assert len(terms) > 300
    ratios = []
    checked = 0
    for k in range(1, len(terms)):
        delta, cov, t = terms[k]
        assert delta == pytest.approx(plain[k][0], abs=1e-12)
        assert cov == pytest.approx(plain[k][1], rel=1e-9, abs=1e-18)
        if np.linalg.eigvalsh(t.cov_given_bias).min() > 1.001e-8:  # not raised to the floor (1e-4 m or rad)
            back = t.cov_given_bias + t.bias_var * np.outer(t.jac_bias, t.jac_bias)
            assert back == pytest.approx(cov, rel=1e-6, abs=1e-14)
            assert np.all(np.linalg.eigvalsh(cov - t.cov_given_bias) > -1e-15)
            checked += 1
        assert 0.0 <= t.bias_cov / t.bias_var <= 1.0 + 1e-9
        if k + 1 < len(terms):
            assert terms[k + 1][2].bias_var == pytest.approx(t.bias_end_var, rel=1e-9)
            assert terms[k + 1][2].bias_radps == pytest.approx(t.bias_end_radps, abs=1e-15)
        dt = (stamps[k] - stamps[k - 1]) * 1e-9
        if abs(delta[0]) > 0.02:  # driving, not turning on the spot or at rest
            ratios.append(t.jac_bias[2] / -dt)
    assert checked > 10  # most edges have one direction (the lateral offset and heading of a straight drive) at the floor
    assert len(ratios) > 200
    assert np.median(ratios) == pytest.approx(1.0, abs=0.05)
