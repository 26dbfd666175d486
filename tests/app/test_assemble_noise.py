"""``[odometry] noise_model``: which filter takes the calibration's noise model."""

from __future__ import annotations

import dataclasses
import math

import pytest

from robotd.app.assemble import GYRO_READINGS_HZ, build_odometry, scale_prior_sigmas
from robotd.app.demo import shipped_calibration
from robotd.base.config import Config, replace
from robotd.io.calibfile import CalibrationFile, read_calibration


def _shipped() -> CalibrationFile:
    path = shipped_calibration()
    assert path is not None
    cal = read_calibration(path)
    assert cal.odometry is not None and cal.odometry.has_process_noise
    return cal


def _accel(p):
    return p.accel_noise_density_mps2_per_sqrt_hz, p.angular_accel_noise_density_radps2_per_sqrt_hz


def test_calibration_noise_goes_to_the_edges_and_the_fused_filter_keeps_the_config():
    cal = _shipped()
    m = cal.odometry
    cfg = replace(Config(), "odometry", noise_model="calibration")
    f = build_odometry(cfg, cal)
    assert f.vo_twin
    twin = f.wheel_gyro.params
    assert _accel(twin) == (m.accel_noise_mps2_sqrt_hz, m.angular_accel_noise_radps2_sqrt_hz)
    assert twin.gyro_noise_radps == pytest.approx(m.gyro_noise_radps_sqrt_hz * math.sqrt(GYRO_READINGS_HZ / 2))
    # The wheel speed's noise: the ticks' quantisation over a 20 ms packet (the mean of the
    # two wheels' counts, each the difference of two roundings), and each wheel's fitted
    # slip density per metre of its own travel in place of the config's slip fraction.
    tick_m = 2 * math.pi * 0.5 * (m.wheel_radius_left_m + m.wheel_radius_right_m) / cfg.robot.ticks_per_rev
    assert twin.wheel_v_noise_mps == pytest.approx(tick_m / 0.02 / math.sqrt(12))
    assert twin.wheel_v_noise_frac == 0.0
    assert twin.wheel_slip_var_m2_per_m == pytest.approx(m.wheel_noise_m_sqrt_m ** 2)
    assert twin.slip_half_base_m == pytest.approx(0.5 * m.wheel_base_m)
    assert twin.wheel_w_noise_per_mps == cfg.odometry.wheel_w_noise_per_mps  # the config's
    # The fused filter: the config's white accelerations and reading noise.
    assert _accel(f.params) == (cfg.odometry.accel_noise_density_mps2_per_sqrt_hz,
                                cfg.odometry.angular_accel_noise_density_radps2_per_sqrt_hz)
    assert f.params.gyro_noise_radps == cfg.odometry.gyro_noise_radps
    # Without visual odometry the one filter gives the edges: it takes the calibration's.
    alone = build_odometry(replace(cfg, "visual_odometry", enabled=False), cal)
    assert not alone.vo_twin and _accel(alone.params) == _accel(twin)


def test_calibration_fused_gives_the_fused_filter_the_same_noise():
    cal = _shipped()
    f = build_odometry(replace(Config(), "odometry", noise_model="calibration_fused"), cal)
    twin = f.wheel_gyro.params
    assert _accel(f.params) == _accel(twin)
    assert f.params.gyro_noise_radps == twin.gyro_noise_radps
    assert not f.params.rate_only_process and not twin.rate_only_process  # the pose keeps its own process noise


def test_without_a_calibration_or_its_accelerations_the_config_is_kept(caplog):
    cfg = replace(Config(), "odometry", noise_model="calibration")
    f = build_odometry(cfg, None)
    assert f.wheel_gyro.params == build_odometry(Config()).wheel_gyro.params
    assert _accel(f.wheel_gyro.params) == (0.5, 0.3)
    assert "no calibration's odometry model" in caplog.text
    # A calibration written before the accelerations were fitted: its densities, the
    # config's accelerations, a warning.
    cal = _shipped()
    old = dataclasses.replace(cal, odometry=dataclasses.replace(
        cal.odometry, accel_noise_mps2_sqrt_hz=None, angular_accel_noise_radps2_sqrt_hz=None,
        accel_noise_sigma=None, angular_accel_noise_sigma=None))
    g = build_odometry(cfg, old)
    assert _accel(g.wheel_gyro.params) == (0.5, 0.3)
    assert g.wheel_gyro.params.wheel_v_noise_mps < cfg.odometry.wheel_v_noise_mps  # the tick's, not the config's
    assert "no white accelerations" in caplog.text
    # The default, "config": today's filters, calibration or not.
    assert build_odometry(Config(), cal).wheel_gyro.params == build_odometry(
        replace(Config(), "odometry", noise_model="config"), cal).wheel_gyro.params
    assert _accel(build_odometry(Config(), cal).wheel_gyro.params) == (0.5, 0.3)


def test_the_slip_test_goes_with_the_calibration_noise_over_the_calibrated_wheel_base():
    cal = _shipped()
    m = cal.odometry
    cfg = replace(replace(Config(), "odometry", noise_model="calibration", slip_gate_sigma=3.0),
                  "visual_odometry", enabled=False)
    p = build_odometry(cfg, cal).params
    assert p.slip_gate_sigma == 3.0
    assert p.slip_half_base_m == pytest.approx(0.5 * m.wheel_base_m)
    # the wheels' own yaw-rate noise: each wheel's tick quantisation (sqrt(2) times the speed's,
    # the mean of two counts), sqrt(2) of it over the base
    assert p.slip_yaw_rate_noise_radps == pytest.approx(2.0 * p.wheel_v_noise_mps / m.wheel_base_m)
    # off (0), or with the config's noise model, no slip test
    assert build_odometry(replace(cfg, "odometry", slip_gate_sigma=0.0), cal).params.slip_gate_sigma == 0.0
    plain = build_odometry(replace(cfg, "odometry", noise_model="config"), cal).params
    assert (plain.slip_gate_sigma, plain.slip_half_base_m) == (0.0, 0.0)


def test_the_live_pose_key_reaches_the_fused_filter():
    """``[visual_odometry] live_pose``: the daemon's fused filter gets it (default: its own
    fused pose); without visual odometry there is no twin and no combined edges."""
    cal = _shipped()
    assert build_odometry(Config(), cal).live_pose == "fused"
    f = build_odometry(replace(Config(), "visual_odometry", live_pose="combined_edges"), cal)
    assert f.live_pose == "combined_edges" and f.wheel_gyro is not f
    off = build_odometry(replace(replace(Config(), "visual_odometry", live_pose="combined_edges"),
                                 "visual_odometry", enabled=False), cal)
    assert off.wheel_gyro is off and off.live_pose == "fused"


def test_the_scale_prior_adds_each_wear_to_its_own_sensor():
    """``[pose_graph] scale_wear`` widens the wheels' scale prior, ``scale_wear_gyro`` the
    gyro's, each in quadrature with the calibration's own uncertainty."""
    cal = _shipped()
    m = cal.odometry
    wheel = 0.5 * math.hypot(m.wheel_radius_left_sigma_m / m.wheel_radius_left_m,
                             m.wheel_radius_right_sigma_m / m.wheel_radius_right_m)
    gyro = m.gyro_scale_sigma / m.gyro_scale
    cfg = replace(Config(), "pose_graph", odometry_model="bias_scale_window", scale_wear=0.004,
                  scale_wear_gyro=0.001)
    assert scale_prior_sigmas(cfg, cal) == pytest.approx((math.hypot(wheel, 0.004), math.hypot(gyro, 0.001)))
    wider = replace(cfg, "pose_graph", scale_wear_gyro=0.005)
    assert scale_prior_sigmas(wider, cal)[0] == scale_prior_sigmas(cfg, cal)[0]
    assert scale_prior_sigmas(wider, cal)[1] == pytest.approx(math.hypot(gyro, 0.005))


def test_the_slip_events_come_from_the_calibration_unless_the_config_sets_a_rate():
    """With the calibration's noise model and the slip test, the file's fitted slip events;
    ``[odometry] slip_event_rate_hz`` above 0 overrides them (with its duration); without
    the slip test, none."""
    cal = _shipped()
    m = dataclasses.replace(cal.odometry, slip_event_rate_hz=0.23, slip_event_duration_s=0.17,
                            slip_event_rate_sigma_hz=0.05, slip_event_duration_sigma_s=0.02)
    cal = dataclasses.replace(cal, odometry=m)
    cfg = replace(Config(), "odometry", noise_model="calibration", slip_gate_sigma=3.0)
    p = build_odometry(cfg, cal).wheel_gyro.params
    assert (p.slip_event_rate_hz, p.slip_event_duration_s) == (0.23, 0.17)
    own = build_odometry(replace(cfg, "odometry", slip_event_rate_hz=0.3, slip_event_duration_s=0.19),
                         cal).wheel_gyro.params
    assert (own.slip_event_rate_hz, own.slip_event_duration_s) == (0.3, 0.19)
    off = build_odometry(replace(cfg, "odometry", slip_gate_sigma=0.0), cal).wheel_gyro.params
    assert off.slip_event_rate_hz == 0.0
    # A file without them: none, as before.
    bare = dataclasses.replace(cal.odometry, slip_event_rate_hz=None, slip_event_duration_s=None,
                               slip_event_rate_sigma_hz=None, slip_event_duration_sigma_s=None)
    assert build_odometry(cfg, dataclasses.replace(cal, odometry=bare)).wheel_gyro.params.slip_event_rate_hz == 0.0
    # The shipped file holds them: the demo's honest edges take its fitted events.
    shipped = _shipped().odometry
    assert shipped.has_slip_events
    assert build_odometry(cfg, _shipped()).wheel_gyro.params.slip_event_rate_hz == shipped.slip_event_rate_hz
