"""The Kobuki emulator: SI sensor streams encoded as the base does, read by the real driver."""

from __future__ import annotations

import math
import os
import select

import numpy as np
import pytest

from drivers.kobuki import protocol
from robotd.base.messages import WheelTicks, YawRate
from sim.emulators.kobuki import (KobukiEmulator, KobukiFeedback, KobukiParams, KobukiState,
                                  driver_messages, encode, simulate_kobuki)
from sim.route import build_route, plan_motion
from sim.sensors import BaseSensorParams, draw_errors, simulate_sensors

TPR = 2578.33
DIGIT_DEGPS = 0.00875


@pytest.fixture(scope="module")
def square():
    return plan_motion(build_route("square"))


@pytest.fixture(scope="module")
def square_feedback(square) -> KobukiFeedback:
    return simulate_kobuki(square, BaseSensorParams(), np.random.default_rng(0))


@pytest.fixture(scope="module")
def office_feedback() -> KobukiFeedback:
    return simulate_kobuki(plan_motion(build_route("office")), BaseSensorParams(),
                           np.random.default_rng(2))


def _packet_of_sample(t_pk: np.ndarray, t_g: np.ndarray) -> np.ndarray:
    """Packet index of each gyro sample: the first packet at or after it (by hand)."""
    return np.array([int(np.argmax(t_pk >= t)) if t <= t_pk[-1] else len(t_pk) for t in t_g])


def test_the_same_seed_gives_the_packets_of_the_model_before_the_split(square_feedback):
    """Values printed by the single Kobuki-unit model this was split from (seed 0, square):
    the random draws are made in the same order."""
    f = square_feedback
    expected = {0: (41436, 35627, 43966, 12867, 1, [-14, -45]),
                1000: (40803, 43618, 63966, -5170, 6, [-41, -5]),
                2000: (37311, 52967, 18430, -14196, -6, [-40, -33])}
    for k, (left, right, ms, angle, rate, z) in expected.items():
        got = (int(f.left_ticks[k]), int(f.right_ticks[k]), int(f.device_ms[k]),
               int(f.angle_cdeg[k]), int(f.angle_rate_cdegps[k]), f.raw_gyro_z[k].tolist())
        assert got == (left, right, ms, angle, rate, z)


def test_driver_messages_match_a_hand_conversion_of_the_si_streams(square_feedback):
    f = square_feedback
    s, st = f.sensors, f.state
    msgs = driver_messages(f)
    wheels = [m for m in msgs if isinstance(m, WheelTicks)]
    yaws = [m for m in msgs if isinstance(m, YawRate)]
    assert len(wheels) == len(yaws) == len(s.t_s)
    # Encoders: whole ticks of angle / 2 pi * 2578.33 from the power-on counter and phase.
    for wheel, ticks0, attr in ((0, st.left_ticks0, "left_ticks"), (1, st.right_ticks0, "right_ticks")):
        ticks = np.floor(s.wheel_angle_rad[:, wheel] / (2 * math.pi) * TPR + st.tick_phase[wheel])
        expected = (ticks.astype(np.int64) + ticks0) % 65536
        np.testing.assert_array_equal([getattr(m, attr) for m in wheels], expected)
    ms = (st.device_ms0 + np.round(s.device_clock_s * 1000).astype(np.int64)) % 65536
    np.testing.assert_array_equal([m.device_ms for m in wheels], ms)
    # Stamps: the packets' times; the yaw rate (a mean of the samples since the previous
    # packet) half a packet interval earlier, which is where its samples' mean time is.
    np.testing.assert_array_equal([m.stamp_ns for m in wheels], s.stamp_ns)
    owner = _packet_of_sample(s.t_s, s.gyro_t_s)
    for k in (1, 2, 500, 1500, len(s.t_s) - 1):
        mean_t_ns = s.gyro_t_s[owner == k].mean() * 1e9
        assert abs(yaws[k].stamp_ns - mean_t_ns) < 5e6
        assert abs(s.stamp_ns[k] - mean_t_ns) > 5e6  # the packet's own stamp is not
    # Yaw rate: the mean of the packet's yaw samples, each rounded to 0.00875 deg/s.
    digits = np.round(np.degrees(s.gyro_radps[:, 2]) / DIGIT_DEGPS)
    for k in (0, 1, 500, 1500, len(s.t_s) - 1):
        mean_deg = digits[owner == k].mean() * DIGIT_DEGPS
        assert yaws[k].yaw_rate_radps == pytest.approx(math.radians(mean_deg), abs=1e-15)
        assert yaws[k].source == "raw_gyro"


def test_decoded_bytes_give_back_the_si_values_within_quantisation(square_feedback):
    f = square_feedback
    s = f.sensors
    owner = _packet_of_sample(s.t_s, s.gyro_t_s)
    rad_per_tick = 2 * math.pi / TPR
    first = None
    for k in (0, 10, 700, 1400, 2800):
        parser = protocol.PacketParser()
        (payload,) = parser.feed(f.packet(k))
        basic, inertial, gyro = protocol.decode_feedback(payload)
        assert isinstance(basic, protocol.BasicSensorData) and isinstance(gyro, protocol.RawGyroData)
        assert isinstance(inertial, protocol.InertialData)
        if first is None:
            first = basic
        # Encoders: the angle turned since packet 0 to within a tick, modulo the 16-bit wrap.
        for enc0, enc, wheel in ((first.left_encoder, basic.left_encoder, 0),
                                 (first.right_encoder, basic.right_encoder, 1)):
            turned_ticks = (s.wheel_angle_rad[k, wheel] - s.wheel_angle_rad[0, wheel]) / rad_per_tick
            assert abs(math.remainder((enc - enc0) - turned_ticks, 65536)) <= 1.0
        assert ((basic.timestamp_ms - first.timestamp_ms) % 65536) / 1000 == pytest.approx(
            s.device_clock_s[k], abs=5e-4)
        # Raw gyro: the packet's samples, gyro x = robot y, gyro y = -robot x, z = z,
        # each within half a digit.
        rates = np.radians(np.array(gyro.samples, dtype=float) * DIGIT_DEGPS)
        robot = s.gyro_radps[owner == k]
        half = math.radians(DIGIT_DEGPS / 2) + 1e-12
        np.testing.assert_allclose(rates[:, 0], robot[:, 1], atol=half)
        np.testing.assert_allclose(rates[:, 1], -robot[:, 0], atol=half)
        np.testing.assert_allclose(rates[:, 2], robot[:, 2], atol=half)


def test_16_bit_counters_and_device_clock_wrap(office_feedback):
    f = office_feedback
    assert f.left_ticks.dtype == np.uint16 and f.device_ms.dtype == np.uint16
    assert (f.left_ticks[0], f.right_ticks[0]) == (f.state.left_ticks0, f.state.right_ticks0)
    for counter in (f.left_ticks, f.right_ticks):
        assert np.any(np.diff(counter.astype(np.int64)) < -30000)  # wrapped forwards
    # 232 s of 20 ms packets on a 65.536 s clock: it wraps, and every step is 20 ms.
    assert f.device_ms[0] == f.state.device_ms0
    dms = np.diff(f.device_ms.astype(np.int64))
    assert np.any(dms < 0)
    np.testing.assert_array_equal(dms % 65536, 20)
    assert set(np.unique(f.gyro_count)) <= {1, 2, 3}
    assert f.gyro_count.mean() == pytest.approx(108.0 / 50.0, abs=0.01)


def test_inertial_heading_wraps_at_180_deg_and_tracks_the_truth(square):
    rng = np.random.default_rng(6)
    f = simulate_kobuki(square, BaseSensorParams.ideal(), rng, KobukiParams.ideal())
    assert f.angle_cdeg.dtype == np.int16
    assert f.angle_cdeg.min() >= -18000 and f.angle_cdeg.max() < 18000
    assert np.any(np.diff(f.angle_cdeg.astype(np.int64)) < -30000)  # +180 -> -180
    angle = np.unwrap(np.deg2rad(f.angle_cdeg / 100.0))
    truth = np.unwrap(f.true_pose[:, 2])
    assert angle[0] == pytest.approx(math.radians(f.state.angle0_deg), abs=1e-3)
    # Ideal gyro: only digit, sample-timing and 0.01 deg quantisation.
    np.testing.assert_allclose(angle - angle[0], truth - truth[0], atol=math.radians(0.5))
    assert (angle[-1] - angle[0]) == pytest.approx(7 * math.pi / 2, abs=math.radians(0.05))


def test_firmware_heading_drifts_by_its_calibration_error(square):
    f = simulate_kobuki(square, BaseSensorParams(), np.random.default_rng(8))
    angle = np.unwrap(np.deg2rad(f.angle_cdeg / 100.0))
    truth = np.unwrap(f.true_pose[:, 2])
    drift = math.degrees((angle[-1] - angle[0]) - (truth[-1] - truth[0]))
    e = f.sensors.errors
    # Residual bias (calibration error) over the run, plus the scale error on 630 deg,
    # plus the bias random walk and white noise (a few hundredths of a degree).
    expected = (math.degrees(e.gyro_bias0_radps) - f.state.firmware_bias_degps) * square.duration_s
    expected += e.gyro_scale_error * 630.0
    assert drift == pytest.approx(expected, abs=0.5)
    assert abs(f.state.firmware_bias_degps - math.degrees(e.gyro_bias0_radps)) < 0.1


def test_inertial_rate_is_the_compensated_mean_of_the_packet(square):
    f = simulate_kobuki(square, BaseSensorParams(), np.random.default_rng(9))
    # Turns in place peak at 1.5 rad/s = 85.94 deg/s = 8594 cdeg/s.
    assert f.angle_rate_cdegps.max() == pytest.approx(8594, abs=60)
    for k in (3, 400, 1000):
        mean_degps = f.raw_gyro_z[k].astype(float).mean() * DIGIT_DEGPS
        expected = round((mean_degps - f.state.firmware_bias_degps) * 100)
        assert abs(int(f.angle_rate_cdegps[k]) - expected) <= 1


def test_encode_is_a_function_of_the_streams_and_the_state(square):
    rng = np.random.default_rng(3)
    errors = draw_errors(BaseSensorParams(), rng)
    state = KobukiState.draw(errors, KobukiParams(), rng)
    sensors = simulate_sensors(square, BaseSensorParams(), errors, rng)
    a, b = encode(sensors, state), encode(sensors, state)
    assert [a.packet(k) for k in range(0, 2800, 700)] == [b.packet(k) for k in range(0, 2800, 700)]
    assert state.device_ms0 == a.device_ms[0]


def test_raw_gyro_samples_and_inertial_sources(square_feedback):
    f = square_feedback
    samples = driver_messages(f, "raw_gyro_samples")
    yaws = [m for m in samples if isinstance(m, YawRate)]
    assert len(yaws) == f.gyro_count.sum()
    assert [m.stamp_ns for m in samples] == sorted(m.stamp_ns for m in samples)
    inertial = [m for m in driver_messages(f, "inertial") if isinstance(m, YawRate)]
    assert inertial[200].source == "inertial"
    assert inertial[200].yaw_rate_radps == pytest.approx(math.radians(f.angle_rate_cdegps[200] / 100))
    with pytest.raises(ValueError, match="yaw_source"):
        driver_messages(f, "magnetometer")


def _read_packets(fd: int, parser: protocol.PacketParser, want: int) -> list[bytes]:
    """Payloads from ``fd`` until ``want`` packets came (waits on the fd, 5 s at most)."""
    got: list[bytes] = []
    while len(got) < want:
        ready, _, _ = select.select([fd], [], [], 5.0)
        assert ready, f"only {len(got)} of {want} packets came"
        got += parser.feed(os.read(fd, 4096))
    return got


def test_emulator_writes_packets_and_answers_request_extra(square_feedback):
    with KobukiEmulator(square_feedback) as emulator:
        fd = os.open(emulator.port, os.O_RDWR | os.O_NOCTTY)
        try:
            parser = protocol.PacketParser()
            emulator.emit(0)
            (first,) = _read_packets(fd, parser, 1)
            assert first == square_feedback.packet(0)[3:-1]
            os.write(fd, protocol.encode_request_extra(True, True, True)
                     + protocol.encode_base_control(100, 0))
            while sum(emulator.commands_received.values()) < 2:
                assert emulator.poll_commands(5.0) > 0, emulator.commands_received
            emulator.emit(1)
            assert emulator.commands_received == {"RequestExtra": 1, "BaseControl": 1}
            payloads = _read_packets(fd, parser, emulator.packets_emitted)
            extra = [p for p in payloads if p[0] != protocol.BasicSensorData.ID]
            items = protocol.decode_feedback(extra[0])
            assert items == [protocol.HardwareVersion(1, 0, 4), protocol.FirmwareVersion(1, 2, 0),
                             protocol.UniqueDeviceId(0x524F424F, 0x54440000, 0x00000001)]
        finally:
            os.close(fd)
    assert emulator.extra_reply(protocol.RequestExtra(0)) == b""
