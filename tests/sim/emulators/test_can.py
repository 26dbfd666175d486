"""The CAN emulator: the virtual robot's SI streams as CAN frames, read back by the real
CAN driver; the ticks and rates it hands out against the streams, and injected faults
against the driver's counters."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.can.driver import load_dbc
from robotd.base.messages import BaseStatus, WheelTicks, YawRate
from robotd.odometry.kinematics import unwrap_ticks_delta
from sim.emulators.can import CanFaults, driver_messages, encode_can
from sim.route import build_route, plan_motion
from sim.sensors import BaseSensorParams, draw_errors, simulate_sensors

TPR = 2578.33  # [robot] ticks_per_rev, the driver's output resolution


@pytest.fixture(scope="module")
def sensors():
    motion = plan_motion(build_route("square")).truncated(12.0)
    rng = np.random.default_rng(4)
    params = BaseSensorParams()
    return simulate_sensors(motion, params, draw_errors(params, rng), rng)


def _cumulative(ticks: list[int]) -> np.ndarray:
    return np.concatenate([[0], np.cumsum([unwrap_ticks_delta(a, b) for a, b in zip(ticks, ticks[1:])])])


def test_frames_decode_with_the_shipped_dbc(sensors):
    frames = encode_can(sensors, "diff_drive", np.random.default_rng(0))
    db = load_dbc("diff_drive")
    n_wheels = int(np.sum(frames.frame_id == 0x100))
    n_gyro = int(np.sum(frames.frame_id == 0x101))
    assert n_wheels == len(sensors.t_s) and n_gyro == len(sensors.gyro_t_s)
    assert np.all(np.diff(frames.t_s) >= 0)
    k = int(np.flatnonzero(frames.frame_id == 0x101)[10])
    got = db.decode_message(0x101, frames.data[k])
    assert got["Gyro_Counter"] == 10
    assert got["Yaw_Rate"] == pytest.approx(math.degrees(sensors.gyro_radps[10, 2]), abs=0.0026)


def test_diff_drive_through_the_driver_gives_the_streams_ticks_rates_and_times(sensors):
    frames = encode_can(sensors, "diff_drive", np.random.default_rng(0))
    out, st = driver_messages(frames, sensors)
    wheels = [m for m in out if isinstance(m, WheelTicks)]
    yaw = [m for m in out if isinstance(m, YawRate)]
    assert len(wheels) == len(sensors.t_s) and len(yaw) == len(sensors.gyro_t_s)
    # the frames' float seconds (on a clock 1e6 s off) carry 0.1 ns: stamps to 2 ns
    assert np.abs(np.array([m.stamp_ns for m in wheels]) - sensors.stamp_ns).max() <= 2
    assert np.abs(np.array([m.stamp_ns for m in yaw]) - sensors.gyro_t_s * 1e9).max() <= 2
    truth = (sensors.wheel_angle_rad - sensors.wheel_angle_rad[0]) / (2 * math.pi) * TPR
    for side, col in (("left_ticks", 0), ("right_ticks", 1)):
        got = _cumulative([getattr(m, side) for m in wheels])
        assert np.abs(got - truth[:, col]).max() <= 1.0  # rounding to a tick, 0.1 mrad fields
    rates = np.array([m.yaw_rate_radps for m in yaw])
    assert np.abs(rates - sensors.gyro_radps[:, 2]).max() <= math.radians(0.0026)
    assert st["unknown_frames"] == st["decode_errors"] == st["bus_silent"] == 0
    assert not [m for m in out if isinstance(m, BaseStatus)]


def test_odrive_through_the_driver_pairs_the_skewed_nodes(sensors):
    frames = encode_can(sensors, "odrive_cansimple", np.random.default_rng(0), odrive_skew_s=0.004)
    out, st = driver_messages(frames, sensors)
    wheels = [m for m in out if isinstance(m, WheelTicks)]
    assert len(wheels) == len(sensors.t_s) and not any(isinstance(m, YawRate) for m in out)
    # each pair at the right node's time, 4 ms after the sample
    assert np.abs(np.array([m.stamp_ns for m in wheels]) - (sensors.stamp_ns + 4_000_000)).max() <= 2
    t = sensors.t_s[:-1] + 0.004  # the streams end at their last sample: compare up to there
    for side, col in (("left_ticks", 0), ("right_ticks", 1)):
        angle = np.interp(t, sensors.t_s, sensors.wheel_angle_rad[:, col])
        truth = (angle - angle[0]) / (2 * math.pi) * TPR
        got = _cumulative([getattr(m, side) for m in wheels[:-1]])
        # the left wheel is moved 4 ms forward at its last finite-difference speed
        assert np.abs(got - truth).max() <= 1.5
    assert st["frames_other"] > 0 and st["unknown_frames"] == 0  # heartbeats are known


def test_injected_faults_are_what_the_driver_counts(sensors):
    faults = CanFaults(flood_at_s=2.0, flood_frames=3000, bus_off_at_s=5.0, bus_off_s=0.2,
                       stale_at_s=8.0, stale_s=0.3, bad_length_frames=7)
    frames = encode_can(sensors, "diff_drive", np.random.default_rng(0), faults)
    out, st = driver_messages(frames, sensors)
    inj = frames.injected
    assert inj["flood_frames"] == st["unknown_frames"] > 2900
    assert inj["bad_length_frames"] == st["decode_errors"] == 7
    assert (st["bus_off"], st["bus_restarts"], st["error_frames"]) == (1, 1, 2)
    assert st["bus_silent"] == 1  # 200 ms without a data frame during the bus-off
    assert st["stale_left"] == 1 and st["stale_right"] == 1  # both wheels share Base_Wheels
    changes = [(m.degraded, m.detail) for m in out if isinstance(m, BaseStatus)]
    assert changes == [(True, "bus silent"), (False, ""),
                       (True, "left wheel stale, right wheel stale"), (False, "")]
    wheels = [m for m in out if isinstance(m, WheelTicks)]
    dropped = inj["left_wheel_frames_dropped"] + inj["bad_length_frames"]
    lost = sum(1 for t in sensors.t_s if 5.0 <= t < 5.2)
    assert len(wheels) == len(sensors.t_s) - dropped - lost
    assert st["degraded"] == 0 and st["status"] == "ok"
