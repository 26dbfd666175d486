"""Routes and the planned true motion: lengths, limits, closure, revisits, interpolation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.base.errors import ConfigError
from robotd.base.geometry import wrap_angle
from sim.route import ROUTES, Motion, MotionLimits, Route, build_route, plan_motion

LIMITS = MotionLimits()


@pytest.fixture(scope="module")
def motions() -> dict[str, Motion]:
    return {name: plan_motion(build_route(name), LIMITS) for name in ROUTES}


def test_every_route_has_a_description_and_the_expected_names():
    assert set(ROUTES) == {"office", "square", "figure8", "calibration", "straight", "corridor"}
    for name, entry in ROUTES.items():
        assert entry.description and "\n" not in entry.description
        assert entry.build().name == name


@pytest.mark.parametrize("name, length_m",
                         [("square", 16.0), ("straight", 10.0), ("corridor", 16.0)])
def test_routes_with_turns_in_place_drive_exactly_their_polyline(motions, name, length_m):
    assert build_route(name).polyline_length_m == pytest.approx(length_m)
    assert motions[name].length_m == pytest.approx(length_m, abs=1e-6)


def test_rounded_corners_shorten_the_path(motions):
    office = build_route("office")
    # 4 corridor sides of 10 and 6 m twice, two rooms of 4 x 3.5 m, the west loop 22 m.
    assert office.polyline_length_m == pytest.approx(114.0)
    assert 105.0 < motions["office"].length_m < office.polyline_length_m
    fig8 = build_route("figure8")
    assert fig8.polyline_length_m == pytest.approx(4 * math.sqrt(8) + 2 * (2 + 4 + 2))
    assert 0.9 * fig8.polyline_length_m < motions["figure8"].length_m < fig8.polyline_length_m


def test_calibration_drive_is_the_figure_eight_driven_over_and_over(motions):
    from sim.route import CALIBRATION_LAPS

    laps, one = motions["calibration"], motions["figure8"]
    assert CALIBRATION_LAPS >= 3
    # Each lap after the first goes through the crossing without stopping: more than
    # CALIBRATION_LAPS figure eights' length, less time than as many separate drives.
    assert laps.length_m == pytest.approx(CALIBRATION_LAPS * one.length_m, rel=0.01)
    assert laps.duration_s < CALIBRATION_LAPS * one.duration_s
    # It turns the same amount each way (the gyro's scale apart from its bias).
    turn = np.diff(laps.yaw_unwrapped_rad)
    assert turn[turn > 0].sum() == pytest.approx(-turn[turn < 0].sum(), rel=0.01)


def test_square_takes_the_trapezoid_times(motions):
    # Each 2 m side: 1 s up to 0.5 m/s (0.25 m), 3 s cruising, 1 s down. Each 90 deg turn:
    # 0.75 s up to 1.5 rad/s, (pi/2 - 1.125)/1.5 s cruising, 0.75 s down. Plus 2 x 2 s still.
    turn = 1.5 + (math.pi / 2 - 1.5 ** 2 / 2.0) / 1.5
    assert motions["square"].duration_s == pytest.approx(4.0 + 8 * 5.0 + 7 * turn, abs=0.003)


@pytest.mark.parametrize("name", sorted(ROUTES))
def test_motion_stays_within_the_limits(motions, name):
    m = motions[name]
    dt = m.dt_s
    assert np.all(m.v_mps >= -1e-12)
    assert np.max(m.v_mps) <= LIMITS.v_max_mps + 1e-9
    assert np.max(np.abs(m.w_radps)) <= LIMITS.w_max_radps + 1e-9
    assert np.max(np.abs(np.diff(m.v_mps[:-1]))) / dt <= LIMITS.a_max_mps2 * 1.001
    assert np.max(np.abs(np.diff(m.w_radps[:-1]))) / dt <= LIMITS.alpha_max_radps2 * 1.001
    # Driven at the limits somewhere (the planner is not needlessly slow).
    assert np.max(m.v_mps) == pytest.approx(LIMITS.v_max_mps, rel=1e-6)


@pytest.mark.parametrize("name", sorted(ROUTES))
def test_standstill_at_both_ends(motions, name):
    m = motions[name]
    still = m.t_s < 2.0 - 1e-9
    assert np.all(m.v_mps[still] == 0.0) and np.all(m.w_radps[still] == 0.0)
    end = m.t_s > m.t_s[-1] - 2.0 + m.dt_s
    assert np.all(np.abs(m.v_mps[end]) < 1e-12) and np.all(np.abs(m.w_radps[end]) < 1e-12)
    assert m.v_mps[-1] == 0.0 and m.w_radps[-1] == 0.0


@pytest.mark.parametrize("name, end_xy", [("office", (0.0, 0.0)), ("square", (0.0, 0.0)),
                                           ("figure8", (0.0, 0.0)), ("corridor", (0.0, 0.0)),
                                           ("calibration", (0.0, 0.0)),
                                           ("straight", (10.0, 0.0))])
def test_routes_end_where_they_should(motions, name, end_xy):
    m = motions[name]
    start = build_route(name).points()[0]
    assert (m.x_m[0], m.y_m[0]) == pytest.approx(tuple(start))
    assert math.hypot(m.x_m[-1] - end_xy[0], m.y_m[-1] - end_xy[1]) < 0.01


@pytest.mark.parametrize("name", sorted(ROUTES))
def test_path_stays_inside_the_documented_bounds(motions, name):
    x0, y0, x1, y1 = build_route(name).bounds_m()
    m = motions[name]
    tol = 1e-5  # the poses integrate (v, w) over 10^5 steps: rounding, micrometres
    assert m.x_m.min() >= x0 - tol and m.x_m.max() <= x1 + tol
    assert m.y_m.min() >= y0 - tol and m.y_m.max() <= y1 + tol
    assert build_route(name).bounds_m(margin_m=1.0) == (x0 - 1, y0 - 1, x1 + 1, y1 + 1)


def test_office_bounds_fit_a_10_by_8_m_area():
    x0, y0, x1, y1 = build_route("office").bounds_m(margin_m=1.0)
    assert (x1 - x0, y1 - y0) == (12.0, 8.0)


def test_office_revisits_places_in_both_directions(motions):
    m = motions["office"]
    s = np.concatenate([[0.0], np.cumsum(m.v_mps[:-1] * m.dt_s)])
    idx = np.searchsorted(s, np.arange(0.0, s[-1], 0.1))  # a pose every 10 cm of travel
    xy = np.stack([m.x_m[idx], m.y_m[idx]], axis=1)
    yaw, dist = m.yaw_rad[idx], s[idx]
    near = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1)) < 0.05
    later = dist[None, :] - dist[:, None] > 5.0  # the same place, >5 m of travel later
    i, j = np.nonzero(near & later)
    diff = np.abs(wrap_angle(yaw[j] - yaw[i]))
    assert np.sum(diff > math.radians(170)) > 100  # driven the other way
    assert np.sum(diff < math.radians(10)) > 100   # driven the same way again
    # Both loops (corridor: y = 6, room: x = 3.5) are revisited the other way.
    opposite = diff > math.radians(170)
    assert np.any(opposite & (np.abs(xy[i, 1] - 6.0) < 0.01))
    assert np.any(opposite & (np.abs(xy[i, 0] - 3.5) < 0.01))


def test_from_velocities_integrates_a_circle_exactly():
    dt = 0.01
    n = round(2 * math.pi / dt)
    m = Motion.from_velocities(np.full(n, 1.0), np.full(n, 1.0), dt, (0.0, 0.0, 0.0))
    t = m.t_s
    np.testing.assert_allclose(m.x_m, np.sin(t), atol=1e-12)
    np.testing.assert_allclose(m.y_m, 1.0 - np.cos(t), atol=1e-12)
    # Between samples too: the step's arc, not a straight line.
    p = m.pose_at(0.123)
    np.testing.assert_allclose(p, [math.sin(0.123), 1 - math.cos(0.123), 0.123], atol=1e-12)
    assert m.length_m == pytest.approx(n * dt)


def test_pose_at_moves_yaw_along_the_circle_through_pi():
    # Turning in place at 1 rad/s from yaw 3.1: pi is passed at t = 0.0416 s.
    m = Motion.from_velocities(np.zeros(10), np.ones(10), 0.01, (0.0, 0.0, 3.1))
    yaw = m.pose_at(0.045)[2]
    assert yaw == pytest.approx(3.145 - 2 * math.pi)
    poses = m.poses_at(np.array([0.0, 0.035, 0.2]))
    assert poses.shape == (3, 3)
    assert poses[1, 2] == pytest.approx(3.135)
    assert poses[2, 2] == pytest.approx(3.2 - 2 * math.pi)  # clamped at the end


def test_truncated_and_velocity_at(motions):
    m = motions["straight"]
    short = m.truncated(5.0)
    assert short.t_s[-1] == pytest.approx(5.0)
    # 2 s still, then 1 s of 0.5 m/s^2 to 0.5 m/s (0.25 m) and 2 s cruising (1.0 m).
    assert short.x_m[-1] == pytest.approx(1.25, abs=1e-6)
    assert m.velocity_at(2.5) == pytest.approx((0.25, 0.0), abs=0.002)
    assert m.velocity_at(10.0) == pytest.approx((0.5, 0.0), abs=1e-9)
    assert m.velocity_at(-1.0) == (0.0, 0.0)


def test_unknown_route_and_bad_routes_are_errors():
    with pytest.raises(ConfigError, match="unknown route 'moon'"):
        build_route("moon")
    with pytest.raises(ValueError, match="corner"):
        Route("x", ((0, 0), (1, 0)), corner="spline")
    with pytest.raises(ValueError, match="too short"):
        plan_motion(Route("tight", ((0, 0), (0.5, 0), (0.5, 0.5)), corner="arc"))


def test_a_kidnapped_motion_holds_the_lift_pose_then_goes_on_from_the_put_down_place(motions):
    from sim.route import kidnapped

    m = motions["square"]
    k = kidnapped(m, 10.0, 3.0, 5.0)
    assert k.duration_s == pytest.approx(m.duration_s + 7.0 + 5.0, abs=1e-9)  # 7 s driven again
    assert np.sum(k.lifted) * k.dt_s == pytest.approx(5.0)
    assert not k.lifted_at(9.99) and k.lifted_at(10.0) and k.lifted_at(14.99) and not k.lifted_at(15.0)
    assert list(k.lifted_at(np.array([9.0, 12.0, 16.0]))) == [False, True, False]
    # Held where it was lifted, wheels still; then where the route was at 3 s.
    assert np.allclose(k.pose_at(12.0), m.pose_at(10.0), atol=1e-9)
    assert np.all(k.v_mps[k.lifted] == 0) and np.all(k.w_radps[k.lifted] == 0)
    assert np.allclose(k.pose_at(15.0), m.pose_at(3.0), atol=1e-9)
    assert np.allclose(k.pose_at(20.0), m.pose_at(8.0), atol=1e-6)
    assert not m.lifted_at(12.0) and m.lifted is None
    assert k.truncated(12.0).lifted_at(11.0)
    with pytest.raises(ValueError, match="does not fit"):
        kidnapped(m, 10.0, m.duration_s + 1.0)


def test_the_kidnapped_kobuki_reports_wheel_drop_and_its_wheels_stand_still(motions):
    from sim.emulators.kobuki import simulate_kobuki
    from sim.route import kidnapped
    from sim.sensors import BaseSensorParams

    k = kidnapped(motions["square"], 10.0, 3.0, 5.0)
    fb = simulate_kobuki(k, BaseSensorParams(), np.random.default_rng(0))
    lifted = (fb.t_s >= 10.0) & (fb.t_s < 15.0)
    assert np.all(fb.wheel_drop[lifted] == 3) and np.all(fb.wheel_drop[~lifted] == 0)
    inside = np.flatnonzero(lifted)[1:]
    assert np.all(fb.left_ticks[inside] == fb.left_ticks[inside[0]])
    assert np.all(fb.right_ticks[inside] == fb.right_ticks[inside[0]])
    assert simulate_kobuki(motions["square"], BaseSensorParams(), np.random.default_rng(0)).wheel_drop is None
