"""The virtual base's SI sensors: consistent with the motion, within the drawn errors."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from robotd.odometry.kinematics import DiffDriveParams
from sim.route import build_route, plan_motion
from sim.sensors import BaseSensorParams, BaseSensorStreams, draw_errors, simulate_sensors

RADIUS_M = DiffDriveParams().wheel_radius_m
BASE_M = DiffDriveParams().wheel_base_m
IDEAL = BaseSensorParams.ideal()


def _simulate(motion, params: BaseSensorParams, seed: int) -> BaseSensorStreams:
    rng = np.random.default_rng(seed)
    return simulate_sensors(motion, params, draw_errors(params, rng), rng)


@pytest.fixture(scope="module")
def square():
    return plan_motion(build_route("square"))


@pytest.fixture(scope="module")
def straight():
    return plan_motion(build_route("straight"))


@pytest.fixture(scope="module")
def office_stream() -> BaseSensorStreams:
    return _simulate(plan_motion(build_route("office")), BaseSensorParams(), 2)


def _distance_at(motion, t_s: np.ndarray) -> np.ndarray:
    return np.interp(t_s, motion.t_s, np.concatenate([[0.0], np.cumsum(motion.v_mps[:-1] * motion.dt_s)]))


def test_errors_are_drawn_within_the_configured_ranges():
    draws = [draw_errors(BaseSensorParams(), np.random.default_rng(s)) for s in range(20)]
    for e in draws:
        assert 0.01 <= abs(e.wheel_base_error) <= 0.02
        assert math.radians(0.1) <= abs(e.gyro_bias0_radps) <= math.radians(0.3)
        assert abs(e.gyro_scale_error) <= 0.003
        assert abs(e.left_radius_error + e.right_radius_error) / 2 <= 0.005
        assert abs(e.right_radius_error - e.left_radius_error) / 2 <= 0.001
    # Both signs occur: these are random per seed, not one fixed offset.
    assert {math.copysign(1, e.wheel_base_error) for e in draws} == {-1.0, 1.0}
    assert {math.copysign(1, e.gyro_bias0_radps) for e in draws} == {-1.0, 1.0}


def test_same_seed_same_streams(square):
    a, b, c = (_simulate(square, BaseSensorParams(), s) for s in (4, 4, 5))
    for name in ("wheel_angle_rad", "gyro_t_s", "gyro_radps", "device_clock_s"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.wheel_angle_rad, c.wheel_angle_rad)


def test_a_kidnapped_drive_has_the_same_gyro_noise_as_the_drive_without_it():
    """The kidnapped drive is compared with the same drive without the kidnapping: until the
    lift both must measure the same (wheels and gyro). The slip draws after the lift differ
    in number, so without ``draws_of`` the gyro's draws (drawn after them) differ from the
    first sample on."""
    from sim.route import kidnapped

    plain = plan_motion(build_route("office")).truncated(120.0)
    kid = kidnapped(plan_motion(build_route("office")), 60.0, 20.0, 5.0).truncated(120.0)
    p = BaseSensorParams()

    def run(motion, draws_of):
        rng = np.random.default_rng(0)
        return simulate_sensors(motion, p, draw_errors(p, rng), rng, draws_of=draws_of), rng.random()

    (a, after_a), (b, after_b), (c, _) = run(plain, None), run(kid, plain), run(kid, None)
    wheels = a.t_s < 60.0
    np.testing.assert_array_equal(a.wheel_angle_rad[wheels], b.wheel_angle_rad[wheels])
    np.testing.assert_array_equal(a.gyro_t_s, b.gyro_t_s)
    gyro = a.gyro_t_s < 60.0
    np.testing.assert_array_equal(a.gyro_radps[gyro], b.gyro_radps[gyro])
    assert after_a == after_b  # the generator goes on as the plain drive's
    assert not np.array_equal(a.gyro_radps[gyro], c.gyro_radps[gyro])  # what draws_of is for
    assert not np.array_equal(a.wheel_angle_rad, b.wheel_angle_rad)  # after the lift: another drive
    # draws_of a drive's own motion changes nothing
    np.testing.assert_array_equal(run(plain, plain)[0].gyro_radps, a.gyro_radps)


def test_samples_at_50_hz_with_the_true_pose_and_device_clock(square):
    s = _simulate(square, IDEAL, 0)
    assert len(s.t_s) == math.floor(square.duration_s * 50) + 1
    np.testing.assert_allclose(np.diff(s.t_s), 0.02, atol=1e-12)
    np.testing.assert_array_equal(s.stamp_ns, np.round(s.t_s * 1e9).astype(np.int64))
    np.testing.assert_allclose(s.true_pose, square.poses_at(s.t_s))
    # No drift modelled: the device clock is the simulation time since the first sample.
    np.testing.assert_allclose(s.device_clock_s, s.t_s - s.t_s[0], atol=1e-12)


def test_ideal_wheel_angles_are_distance_over_radius(straight):
    s = _simulate(straight, IDEAL, 1)
    expected = _distance_at(straight, s.t_s) / RADIUS_M
    for wheel in range(2):
        np.testing.assert_allclose(s.wheel_angle_rad[:, wheel], expected, atol=1e-9)
    assert s.wheel_angle_rad[-1, 0] == pytest.approx(10.0 / RADIUS_M)


def test_wheel_angles_follow_the_drawn_radius_errors_and_slip_stays_small(straight):
    for seed in range(4):
        s = _simulate(straight, BaseSensorParams(), seed)
        e = s.errors
        for wheel, err in ((0, e.left_radius_error), (1, e.right_radius_error)):
            # A larger wheel turns less: 10 m is 10 / (r (1 + e)) rad; slip adds a few mm.
            measured_m = s.wheel_angle_rad[-1, wheel] * RADIUS_M
            assert measured_m == pytest.approx(10.0 / (1.0 + err), abs=0.015)


def test_wheel_base_error_scales_every_turn(square):
    params = dataclasses.replace(IDEAL, wheel_base_error_range=(0.02, 0.02))
    s = _simulate(square, params, 3)
    # Heading from the wheels with the nominal geometry: r (phi_R - phi_L) / B.
    turned = RADIUS_M * (s.wheel_angle_rad[-1, 1] - s.wheel_angle_rad[-1, 0]) / BASE_M
    true_turned = np.unwrap(s.true_pose[:, 2])[-1] - s.true_pose[0, 2]
    assert true_turned == pytest.approx(7 * math.pi / 2, abs=1e-6)
    # Seven quarter turns in place: the wheels roll (1 + e_B) times as far as nominal.
    assert turned - true_turned == pytest.approx(s.errors.wheel_base_error * 7 * math.pi / 2,
                                                 rel=1e-6)


def test_slip_events_happen_only_when_asked(office_stream, straight):
    assert office_stream.slip_events > 0
    none = dataclasses.replace(BaseSensorParams(), slip_event_rate_hz=0.0)
    assert _simulate(straight, none, 0).slip_events == 0


def test_ideal_gyro_reads_the_true_yaw_rate(square):
    s = _simulate(square, IDEAL, 6)
    assert s.gyro_radps.shape == (len(s.gyro_t_s), 3)
    np.testing.assert_allclose(np.diff(s.gyro_t_s), 1 / 108.0, atol=1e-12)
    # The first sample falls within one base period before the first wheel sample.
    assert s.t_s[0] - 0.02 <= s.gyro_t_s[0] < s.t_s[0] - 0.02 + 1 / 108.0
    step = np.clip(np.floor(s.gyro_t_s / square.dt_s).astype(int), 0, len(square.w_radps) - 2)
    truth = np.where(s.gyro_t_s >= 0.0, square.w_radps[step], 0.0)
    np.testing.assert_allclose(s.gyro_radps[:, 2], truth, atol=1e-12)
    np.testing.assert_array_equal(s.gyro_radps[:, :2], 0.0)
    # Integrated, the samples give the seven quarter turns.
    assert np.sum(s.gyro_radps[:, 2]) / 108.0 == pytest.approx(7 * math.pi / 2, abs=1e-3)


def test_gyro_bias_scale_and_noise(office_stream):
    s = office_stream
    e = s.errors
    # The first 2 s are at rest: z reads the turn-on bias, with white noise of
    # 0.03 deg/s/sqrt(Hz) * sqrt(108/2) = 0.22 deg/s per sample.
    sigma = math.radians(0.03 * math.sqrt(54.0))
    rest = s.gyro_radps[s.gyro_t_s < 1.9, 2]
    assert rest.mean() == pytest.approx(e.gyro_bias0_radps, abs=4 * sigma / math.sqrt(len(rest)))
    assert rest.std() == pytest.approx(sigma, rel=0.15)
    # x and y read their own offset (0.5 deg/s, 1 sigma) and the same noise.
    assert np.all(np.abs(s.gyro_radps[s.gyro_t_s < 1.9, :2].mean(axis=0)) < math.radians(2.0))


def test_gyro_scale_error_shows_on_the_turns(square):
    params = dataclasses.replace(IDEAL, gyro_scale_error_max=0.003)
    s = _simulate(square, params, 9)
    turned = np.sum(s.gyro_radps[:, 2]) / 108.0
    assert turned == pytest.approx((1 + s.errors.gyro_scale_error) * 7 * math.pi / 2, abs=1e-3)
    assert s.errors.gyro_scale_error != 0.0
