"""The virtual Kobuki's encoders and gyro: consistent with the motion, within the errors."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from robotd.base.geometry import wrap_angle
from robotd.base.messages import WheelTicks, YawRate
from robotd.odometry.kinematics import DiffDriveParams, WheelOdometry, unwrap_ticks_delta
from sim.route import build_route, plan_motion
from sim.sensors import BaseSensorParams, BaseStream, simulate_base

MPT = DiffDriveParams().metres_per_tick
IDEAL = BaseSensorParams.ideal()


@pytest.fixture(scope="module")
def square():
    return plan_motion(build_route("square"))


@pytest.fixture(scope="module")
def straight():
    return plan_motion(build_route("straight"))


@pytest.fixture(scope="module")
def office_stream() -> BaseStream:
    return simulate_base(plan_motion(build_route("office")), BaseSensorParams(),
                         np.random.default_rng(2))


def _unwrapped(counter: np.ndarray) -> np.ndarray:
    steps = [unwrap_ticks_delta(a, b) for a, b in zip(counter[:-1], counter[1:])]
    return np.concatenate([[0], np.cumsum(steps)])


def test_errors_are_drawn_within_the_configured_ranges(straight):
    p = BaseSensorParams()
    draws = [simulate_base(straight, p, np.random.default_rng(s)).errors for s in range(20)]
    for e in draws:
        assert 0.01 <= abs(e.wheel_base_error) <= 0.02
        assert 0.1 <= abs(e.gyro_bias0_degps) <= 0.3
        assert abs(e.gyro_scale_error) <= 0.003
        assert abs(e.left_radius_error + e.right_radius_error) / 2 <= 0.005
        assert abs(e.right_radius_error - e.left_radius_error) / 2 <= 0.001
        assert abs(e.firmware_bias_degps - e.gyro_bias0_degps) < 0.1
        assert 0 <= e.left_ticks0 < 65536 and 0 <= e.device_ms0 < 65536
    # Both signs occur: these are random per seed, not one fixed offset.
    assert {math.copysign(1, e.wheel_base_error) for e in draws} == {-1.0, 1.0}
    assert {math.copysign(1, e.gyro_bias0_degps) for e in draws} == {-1.0, 1.0}


def test_same_seed_same_stream(square):
    a = simulate_base(square, BaseSensorParams(), np.random.default_rng(4))
    b = simulate_base(square, BaseSensorParams(), np.random.default_rng(4))
    c = simulate_base(square, BaseSensorParams(), np.random.default_rng(5))
    for field in ("left_ticks", "right_ticks", "angle_cdeg", "gyro_digits", "device_ms"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert not np.array_equal(a.left_ticks, c.left_ticks)


def test_packets_at_50_hz_with_the_true_pose(square):
    s = simulate_base(square, IDEAL, np.random.default_rng(0))
    assert len(s.t_s) == math.floor(square.duration_s * 50) + 1
    np.testing.assert_allclose(np.diff(s.t_s), 0.02, atol=1e-12)
    np.testing.assert_array_equal(s.stamp_ns, np.round(s.t_s * 1e9).astype(np.int64))
    np.testing.assert_allclose(s.true_pose, square.poses_at(s.t_s))


def test_ideal_ticks_match_the_motion_to_a_tick(straight):
    s = simulate_base(straight, IDEAL, np.random.default_rng(1))
    true_dist = np.interp(s.t_s, straight.t_s, np.concatenate(
        [[0.0], np.cumsum(straight.v_mps[:-1] * straight.dt_s)]))
    for counter in (s.left_ticks, s.right_ticks):
        ticks = _unwrapped(counter.astype(np.int64))
        assert np.max(np.abs(ticks * MPT - true_dist)) <= MPT * 1.0001
    assert _unwrapped(s.left_ticks.astype(np.int64))[-1] == pytest.approx(10.0 / MPT, abs=1)


def test_ticks_follow_the_drawn_radius_errors_and_slip_stays_small(straight):
    for seed in range(4):
        s = simulate_base(straight, BaseSensorParams(), np.random.default_rng(seed))
        e = s.errors
        for counter, err in ((s.left_ticks, e.left_radius_error),
                             (s.right_ticks, e.right_radius_error)):
            measured = _unwrapped(counter.astype(np.int64))[-1] * MPT
            # A larger wheel turns less: 10 m reads as 10/(1+e); slip adds a few mm.
            assert measured == pytest.approx(10.0 / (1.0 + err), abs=0.015)


def test_wheel_base_error_scales_every_turn(square):
    params = dataclasses.replace(IDEAL, wheel_base_error_range=(0.02, 0.02))
    s = simulate_base(square, params, np.random.default_rng(3))
    odo = WheelOdometry()
    for msg in s.wheel_ticks():
        odo.update(msg)
    # Seven quarter turns in place: the encoders see (1 + e_B) times each.
    turned = odo.pose().yaw_rad - s.true_pose[-1, 2]
    expected = s.errors.wheel_base_error * 7 * math.pi / 2
    assert wrap_angle(turned) == pytest.approx(expected, rel=0.01)


def test_16_bit_counters_and_device_clock_wrap(office_stream):
    s = office_stream
    assert s.left_ticks.dtype == np.uint16 and s.device_ms.dtype == np.uint16
    assert s.left_ticks[0] == s.errors.left_ticks0 and s.right_ticks[0] == s.errors.right_ticks0
    for counter in (s.left_ticks, s.right_ticks):
        raw = np.diff(counter.astype(np.int64))
        assert np.any(raw < -30000)  # wrapped forwards at least once
        steps = np.diff(_unwrapped(counter.astype(np.int64)))
        # The outer wheel of a rounded corner runs at 0.5 + 1.0 * 0.115 m/s, slip adds a few %.
        assert 0.6 * 0.02 / MPT < np.max(np.abs(steps)) < 0.75 * 0.02 / MPT
    # 232 s of 20 ms ticks on a 65.536 s clock: it wraps, and every step is 20 ms.
    assert s.device_ms[0] == s.errors.device_ms0
    dms = np.diff(s.device_ms.astype(np.int64))
    assert np.any(dms < 0)
    np.testing.assert_array_equal(dms % 65536, 20)


def test_slip_events_happen_only_when_asked(office_stream, straight):
    assert office_stream.errors.slip_events > 0
    none = dataclasses.replace(BaseSensorParams(), slip_event_rate_hz=0.0)
    assert simulate_base(straight, none, np.random.default_rng(0)).errors.slip_events == 0


def test_inertial_heading_wraps_at_180_deg_and_tracks_the_truth(square):
    s = simulate_base(square, IDEAL, np.random.default_rng(6))
    assert s.angle_cdeg.dtype == np.int16
    assert s.angle_cdeg.min() >= -18000 and s.angle_cdeg.max() < 18000
    assert np.any(np.diff(s.angle_cdeg.astype(np.int64)) < -30000)  # +180 -> -180
    angle = np.unwrap(np.deg2rad(s.angle_cdeg / 100.0))
    truth = np.unwrap(s.true_pose[:, 2])
    assert angle[0] == pytest.approx(math.radians(s.errors.angle0_deg), abs=1e-3)
    # Ideal gyro: only digit, sample-timing and 0.01 deg quantisation.
    np.testing.assert_allclose(angle - angle[0], truth - truth[0], atol=math.radians(0.5))
    assert (angle[-1] - angle[0]) == pytest.approx(7 * math.pi / 2, abs=math.radians(0.05))


def test_firmware_heading_drifts_by_its_calibration_error(square):
    s = simulate_base(square, BaseSensorParams(), np.random.default_rng(8))
    angle = np.unwrap(np.deg2rad(s.angle_cdeg / 100.0))
    truth = np.unwrap(s.true_pose[:, 2])
    drift = math.degrees((angle[-1] - angle[0]) - (truth[-1] - truth[0]))
    e = s.errors
    # Residual bias (calibration error) over the run, plus the scale error on 630 deg,
    # plus the bias random walk and white noise (a few hundredths of a degree).
    expected = (e.gyro_bias0_degps - e.firmware_bias_degps) * square.duration_s
    expected += e.gyro_scale_error * 630.0
    assert drift == pytest.approx(expected, abs=0.5)


def test_raw_gyro_samples_per_packet_bias_and_noise(office_stream):
    s = office_stream
    assert set(np.unique(s.gyro_count)) <= {1, 2, 3}
    assert s.gyro_count.mean() == pytest.approx(108.0 / 50.0, abs=0.01)
    assert len(s.raw_gyro_z) == len(s.t_s) and len(s.raw_gyro_z[5]) == s.gyro_count[5]
    # The first 2 s are at rest: z reads the turn-on bias, with white noise of
    # 0.03 deg/s/sqrt(Hz) * sqrt(108/2) = 0.22 deg/s per sample.
    rest = np.concatenate(s.raw_gyro_z[:95]).astype(float) * 0.00875
    assert rest.mean() == pytest.approx(s.errors.gyro_bias0_degps,
                                        abs=4 * 0.22 / math.sqrt(len(rest)))
    assert rest.std() == pytest.approx(0.03 * math.sqrt(54.0), rel=0.15)
    xy = s.gyro_digits[:95, :2, :2].astype(float) * 0.00875
    assert np.all(np.abs(xy.mean(axis=(0, 1))) < 2.0)
    # The inertial rate at rest is what the firmware's calibration left: a few 0.01 deg/s.
    assert abs(s.angle_rate_cdegps[:95].mean() / 100.0
               - (s.errors.gyro_bias0_degps - s.errors.firmware_bias_degps)) < 0.05


def test_inertial_rate_follows_the_turns(square):
    s = simulate_base(square, BaseSensorParams(), np.random.default_rng(9))
    # Turns in place peak at 1.5 rad/s = 85.94 deg/s = 8594 cdeg/s.
    assert s.angle_rate_cdegps.max() == pytest.approx(8594, abs=60)
    assert s.angle_rate_cdegps.dtype == np.int16


def test_messages_mirror_the_driver(square):
    s = simulate_base(square, BaseSensorParams(), np.random.default_rng(10))
    msgs = s.messages()
    wheels = [m for m in msgs if isinstance(m, WheelTicks)]
    yaws = [m for m in msgs if isinstance(m, YawRate)]
    assert len(wheels) == len(yaws) == len(s.t_s)
    stamps = [m.stamp_ns for m in msgs]
    assert stamps == sorted(stamps)
    assert isinstance(msgs[0], WheelTicks) and isinstance(msgs[1], YawRate)
    assert msgs[0].stamp_ns == msgs[1].stamp_ns
    # The raw_gyro source: the packet's mean yaw digit in rad/s.
    k = 200
    mean_digit = s.raw_gyro_z[k].astype(float).mean()
    assert yaws[k].yaw_rate_radps == pytest.approx(math.radians(mean_digit * 0.00875))
    assert (wheels[k].left_ticks, wheels[k].device_ms) == (s.left_ticks[k], s.device_ms[k])
    samples = s.yaw_rates("raw_gyro_samples")
    assert len(samples) == s.gyro_count.sum()
    inertial = s.yaw_rates("inertial")
    assert inertial[k].yaw_rate_radps == pytest.approx(math.radians(s.angle_rate_cdegps[k] / 100))
    with pytest.raises(ValueError, match="source"):
        s.yaw_rates("magnetometer")
