"""The CAN base driver: the shipped DBC files against frames built by hand, and the driver
on a python-can ``virtual`` bus (conversion to ticks, stamps, pairing, faults, staleness).

Expected bytes are written by hand from the conventions (ODrive CANSimple: id = node << 5
| cmd, two little-endian float32; the generic base: big-endian 32-bit angles of 0.1 mrad,
a little-endian 16-bit yaw rate of 0.005 deg/s), with values that a wrong byte order or
scale would decode differently. python-can's virtual bus cannot go bus-off, so bus-off is
injected where the driver sees it: an error frame with the Linux CAN_ERR_BUSOFF class
(what socketcan delivers), and a bus whose ``state`` is ``BusState.ERROR``.
"""

from __future__ import annotations

import itertools
import math
import struct

import can
import pytest

from drivers.can.driver import (CAN_ERR_BUSOFF, CAN_ERR_CRTL, CAN_ERR_RESTARTED, SHIPPED_DBC,
                                CanBaseDriver, load_dbc)
from robotd.base.clock import ManualClock
from robotd.base.errors import ConfigError
from robotd.base.messages import BaseStatus, WheelTicks, YawRate
from robotd.odometry.kinematics import unwrap_ticks_delta

_channel = itertools.count()
TPR = 1000.0  # ticks per wheel turn in these tests: easy numbers


def _msg(fid: int, data: bytes, t: float, **kw) -> can.Message:
    return can.Message(timestamp=t, arbitration_id=fid, is_extended_id=kw.pop("ext", False),
                       data=data, dlc=len(data), **kw)


class Rig:
    """A driver and a sender on one virtual channel, with a manual clock."""

    def __init__(self, dbc: str = "diff_drive", *, bus_wrapper=None, **kw) -> None:
        ch = f"test-can-{next(_channel)}"
        self.clock = ManualClock(0)
        bus = can.Bus(interface="virtual", channel=ch)
        if bus_wrapper is not None:
            bus = bus_wrapper(bus)
        if dbc == "diff_drive":
            kw = {"left": "Base_Wheels.Left_Wheel_Pos", "right": "Base_Wheels.Right_Wheel_Pos",
                  "wheel_unit": "rad", "yaw": "Base_Gyro.Yaw_Rate", "yaw_unit": "deg/s", **kw}
        else:
            kw = {"left": "Left_Encoder_Estimates.Pos_Estimate",
                  "right": "Right_Encoder_Estimates.Pos_Estimate", "wheel_unit": "turn",
                  "left_scale": -1.0, **kw}
        self.driver = CanBaseDriver(bus, self.clock, load_dbc(dbc), ticks_per_rev=TPR, **kw)
        self.tx = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)

    def send(self, *msgs: can.Message) -> None:
        for m in msgs:
            self.tx.send(m)

    def read(self, at_s: float | None = None):
        if at_s is not None:
            self.clock.set_ns(int(round(at_s * 1e9)))
        return self.driver.read(0.0)

    def close(self) -> None:
        self.driver.close()
        self.tx.shutdown()


@pytest.fixture
def rig():
    made: list[Rig] = []

    def make(*a, **kw) -> Rig:
        made.append(Rig(*a, **kw))
        return made[-1]

    yield make
    for r in made:
        r.close()


def wheels_frame(left_rad: float, right_rad: float, t: float) -> can.Message:
    """Base_Wheels built by hand: two big-endian int32 of 0.1 mrad."""
    return _msg(0x100, struct.pack(">ii", round(left_rad * 1e4), round(right_rad * 1e4)), t)


def gyro_frame(yaw_degps: float, t: float, counter: int = 0) -> can.Message:
    """Base_Gyro built by hand: little-endian int16 of 0.005 deg/s, counter, status."""
    return _msg(0x101, struct.pack("<hBB", round(yaw_degps / 0.005), counter, 0), t)


def odrive_frame(node: int, pos_turns: float, vel_tps: float, t: float) -> can.Message:
    """Encoder estimates (cmd 0x009) of ``node``: id node << 5 | 9, two LE float32."""
    return _msg(node << 5 | 0x009, struct.pack("<ff", pos_turns, vel_tps), t)


# -- the DBC files against hand-built frames -------------------------------------------

def test_diff_drive_dbc_decodes_big_endian_angles_and_little_endian_gyro():
    db = load_dbc("diff_drive")
    wheels = db.get_message_by_frame_id(0x100)
    # 0x00003039 = 12345 -> 1.2345 rad; 0xFFFFB1E0 = -20000 -> -2 rad (little-endian reading
    # would give 0x39300000 and an unsigned 0xE0B1FFFF)
    got = wheels.decode(bytes.fromhex("00003039ffffb1e0"))
    assert got["Left_Wheel_Pos"] == pytest.approx(1.2345) and got["Right_Wheel_Pos"] == pytest.approx(-2.0)
    gyro = db.get_message_by_frame_id(0x101)
    got = gyro.decode(bytes.fromhex("1027" "07" "00"))  # 0x2710 = 10000 x 0.005 = 50 deg/s
    assert got["Yaw_Rate"] == pytest.approx(50.0) and got["Gyro_Counter"] == 7
    got = gyro.decode(bytes.fromhex("f0d8" "00" "00"))  # 0xD8F0 = -10000 -> -50 deg/s (signed)
    assert got["Yaw_Rate"] == pytest.approx(-50.0)
    speeds = db.get_message_by_frame_id(0x102)
    got = speeds.decode(bytes.fromhex("e803" "18fc"))  # 1000 and -1000 x 0.001 rad/s
    assert got["Left_Wheel_Speed"] == pytest.approx(1.0) and got["Right_Wheel_Speed"] == pytest.approx(-1.0)


def test_odrive_dbc_ids_follow_node_shift_cmd_and_floats_are_little_endian():
    db = load_dbc("odrive_cansimple")
    for node, side in ((0, "Left"), (1, "Right")):
        assert db.get_message_by_name(f"{side}_Encoder_Estimates").frame_id == node << 5 | 0x009
        assert db.get_message_by_name(f"{side}_Heartbeat").frame_id == node << 5 | 0x001
    enc = db.get_message_by_frame_id(0x029)
    got = enc.decode(bytes.fromhex("0000c03f" "000080be"))  # 1.5f, -0.25f little-endian
    assert got == {"Pos_Estimate": 1.5, "Vel_Estimate": -0.25}
    hb = db.get_message_by_frame_id(0x001)
    got = hb.decode(bytes.fromhex("04000000" "08" "00" "01" "00"))
    assert got["Axis_Error"] == 4 and got["Axis_State"] == 8 and got["Trajectory_Done_Flag"] == 1


def test_shipped_dbc_files_exist_and_a_bad_dbc_or_signal_is_one_config_error(tmp_path):
    assert all(p.is_file() for p in SHIPPED_DBC.values())
    with pytest.raises(ConfigError, match="no file"):
        load_dbc(str(tmp_path / "none.dbc"))
    bad = tmp_path / "bad.dbc"
    bad.write_text("BO_ this is not a dbc\n")
    with pytest.raises(ConfigError, match="not a readable DBC"):
        load_dbc(str(bad))
    bus = can.Bus(interface="virtual", channel="test-can-config")
    try:
        with pytest.raises(ConfigError, match="no message 'Wheels'"):
            CanBaseDriver(bus, ManualClock(0), load_dbc("diff_drive"), left="Wheels.Left",
                          right="Base_Wheels.Right_Wheel_Pos")
        with pytest.raises(ConfigError, match="has no signal 'Left'"):
            CanBaseDriver(bus, ManualClock(0), load_dbc("diff_drive"), left="Base_Wheels.Left",
                          right="Base_Wheels.Right_Wheel_Pos")
        with pytest.raises(ConfigError, match="Message.Signal"):
            CanBaseDriver(bus, ManualClock(0), load_dbc("diff_drive"), left="Left_Wheel_Pos",
                          right="Base_Wheels.Right_Wheel_Pos")
    finally:
        bus.shutdown()


# -- the driver: values, units, stamps -------------------------------------------------

def test_generic_base_wheels_become_ticks_at_the_robots_resolution(rig):
    r = rig("diff_drive")
    r.send(wheels_frame(math.pi, -2 * math.pi, 100.0), gyro_frame(50.0, 100.001))
    out = r.read(at_s=1.0)
    ticks = [m for m in out if isinstance(m, WheelTicks)]
    yaw = [m for m in out if isinstance(m, YawRate)]
    # half a turn = 500 ticks; minus one turn = -1000 = 64536 in the 16-bit counter
    assert [(t.left_ticks, t.right_ticks) for t in ticks] == [(500, 64536)]
    assert yaw[0].yaw_rate_radps == pytest.approx(math.radians(50.0)) and yaw[0].source == "can"
    # stamped on the driver's clock at the frames' own spacing (1 ms apart)
    assert ticks[0].stamp_ns == 1_000_000_000 - 1_000_000 and yaw[0].stamp_ns == 1_000_000_000
    st = r.driver.stats()
    assert st["frames"] == st["frames_used"] == 2 and st["wheel_samples"] == 1 and st["yaw_samples"] == 1


def test_the_frames_spacing_is_kept_and_the_offset_is_the_fastest_frames(rig):
    r = rig("diff_drive")
    r.send(wheels_frame(0.0, 0.0, 5000.00))
    r.read(at_s=10.004)  # 4 ms late
    r.send(wheels_frame(0.1, 0.1, 5000.02))
    out = r.read(at_s=10.021)  # 1 ms late: this frame sets the offset
    r.send(wheels_frame(0.2, 0.2, 5000.04))
    out += r.read(at_s=10.049)
    assert [m.stamp_ns for m in out] == [10_021_000_000, 10_041_000_000]


def test_a_wrapping_32_bit_angle_is_unwrapped(rig):
    r = rig("diff_drive")
    span = 2 ** 32 * 1e-4
    v1 = 214748.3
    v2 = v1 + 0.5 - span  # the field wrapped while the wheel turned 0.5 rad forward
    r.send(wheels_frame(v1, 0.0, 1.0), wheels_frame(v2, 0.0, 1.02))
    a, b = [m for m in r.read(at_s=1.02) if isinstance(m, WheelTicks)]
    assert unwrap_ticks_delta(a.left_ticks, b.left_ticks) in (79, 80)  # 0.5 / 2 pi x 1000
    assert unwrap_ticks_delta(a.right_ticks, b.right_ticks) == 0


@pytest.mark.parametrize(("unit", "value", "turns"), [
    ("turn", 0.25, 0.25), ("rad", math.pi, 0.5), ("deg", 90.0, 0.25),
    ("m", 2 * math.pi * 0.05 * 0.75, 0.75)])
def test_position_units_become_turns(rig, unit, value, turns):
    r = rig("odrive_cansimple", wheel_unit=unit, left_scale=1.0, wheel_radius_m=0.05)
    r.send(odrive_frame(0, 0.0, 0.0, 1.0), odrive_frame(1, 0.0, 0.0, 1.0))
    r.send(odrive_frame(0, value, 0.0, 1.02), odrive_frame(1, -value, 0.0, 1.02))
    a, b = [m for m in r.read(at_s=1.02) if isinstance(m, WheelTicks)]
    assert unwrap_ticks_delta(a.left_ticks, b.left_ticks) == round(turns * TPR)
    assert unwrap_ticks_delta(a.right_ticks, b.right_ticks) == -round(turns * TPR)


def test_odrive_pairs_two_nodes_at_the_later_stamp_moving_the_earlier_wheel_forward(rig):
    r = rig("odrive_cansimple")  # left mirrored: left_scale -1
    r.send(odrive_frame(0, 1.9, 0.0, 1.000), odrive_frame(1, 0.15, 0.0, 1.004))
    r.send(odrive_frame(0, 2.0, 0.0, 1.020), odrive_frame(1, 0.25, 0.0, 1.024))
    out = [m for m in r.read(at_s=1.024) if isinstance(m, WheelTicks)]
    assert len(out) == 2
    last = out[-1]
    # left: -2.0 turns at 1.020 s, moving at -5 turns/s, taken 4 ms on: -2.02 turns
    assert last.left_ticks == (-2020) % 65536 and last.right_ticks == 250
    assert last.stamp_ns == out[0].stamp_ns + 20_000_000
    # a heartbeat is known but not used
    r.send(_msg(0x001, bytes(8), 1.03))
    r.read(at_s=1.03)
    assert r.driver.stats()["frames_other"] == 1


def test_a_speed_signal_is_integrated_by_the_trapezoid_rule(rig):
    r = rig("odrive_cansimple", left="Left_Encoder_Estimates.Vel_Estimate",
            right="Right_Encoder_Estimates.Vel_Estimate", wheel_unit="turn/s", left_scale=1.0)
    for k, v in enumerate((1.0, 1.0, 3.0)):
        r.send(odrive_frame(0, 0.0, v, 1.0 + 0.02 * k), odrive_frame(1, 0.0, -v, 1.0 + 0.02 * k))
    out = [m for m in r.read(at_s=1.04) if isinstance(m, WheelTicks)]
    lefts = [m.left_ticks for m in out]
    # 0, then 1 turn/s x 20 ms = 20 ticks, then (1 + 3) / 2 x 20 ms = 40 more
    assert lefts == [0, 20, 60] and [m.right_ticks for m in out] == [0, 65516, 65476]


# -- faults: counted, never fatal ------------------------------------------------------

def test_unknown_ids_remote_and_undecodable_frames_are_counted_and_skipped(rig):
    r = rig("diff_drive")
    r.send(_msg(0x555, b"\x01", 1.0), _msg(0x555, b"\x02", 1.0), _msg(0x556, b"", 1.0),
           _msg(0x100, bytes(8), 1.0, ext=True),            # extended 0x100 is not Base_Wheels
           can.Message(timestamp=1.0, arbitration_id=0x100, is_remote_frame=True, dlc=8),
           _msg(0x100, b"\x00\x01\x02", 1.0))               # Base_Wheels cut to 3 bytes
    out = r.read(at_s=1.0)
    assert [m for m in out if not isinstance(m, BaseStatus)] == []
    st = r.driver.stats()
    assert (st["unknown_frames"], st["unknown_ids"], st["remote_frames"], st["decode_errors"]) == (4, 3, 1, 1)
    r.send(wheels_frame(0.0, 0.0, 1.02))
    assert any(isinstance(m, WheelTicks) for m in r.read(at_s=1.02))


def test_a_nan_position_is_a_counted_bad_value(rig):
    r = rig("odrive_cansimple")
    r.send(odrive_frame(0, float("nan"), 0.0, 1.0), odrive_frame(1, 0.5, 0.0, 1.0))
    assert not [m for m in r.read(at_s=1.0) if isinstance(m, WheelTicks)]
    assert r.driver.stats()["bad_values"] == 1


def test_a_flood_is_taken_in_batches_and_the_wheels_still_come_through(rig):
    r = rig("diff_drive", max_frames_per_read=1000)
    for k in range(5000):
        r.tx.send(_msg(0x600 + k % 50, bytes(8), 1.0))
        if k % 1000 == 999:
            r.tx.send(wheels_frame(0.01 * k, 0.01 * k, 1.0 + k * 1e-5))
    ticks = []
    for _ in range(10):
        ticks += [m for m in r.read(at_s=1.05) if isinstance(m, WheelTicks)]
    st = r.driver.stats()
    assert st["frames"] == 5005 and st["unknown_frames"] == 5000 and st["unknown_ids"] == 50
    assert st["flood_reads"] == 5 and len(ticks) == 5 and st["wheel_samples"] == 5


def test_error_frames_count_bus_off_restart_and_error_passive(rig):
    r = rig("diff_drive")
    r.send(can.Message(timestamp=1.0, arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True))
    r.read(at_s=1.0)
    assert r.driver.stats()["bus_off"] == 1 and "bus-off" in r.driver.status
    r.send(can.Message(timestamp=1.1, arbitration_id=CAN_ERR_RESTARTED, is_error_frame=True))
    r.read(at_s=1.1)
    r.send(can.Message(timestamp=1.2, arbitration_id=CAN_ERR_CRTL, is_error_frame=True,
                       data=bytes([0, 0x20, 0, 0, 0, 0, 0, 0])))
    r.read(at_s=1.2)
    st = r.driver.stats()
    assert (st["error_frames"], st["bus_off"], st["bus_restarts"], st["error_passive"]) == (3, 1, 1, 1)
    assert st["status"] == "bus silent, error passive"  # no data frame in 1.2 s


class _BusOffBus:
    """A virtual bus whose controller reports bus-off, and whose recv fails when told to
    (as socketcan's does with ENETDOWN once the interface is down)."""

    def __init__(self, bus) -> None:
        self.bus = bus
        self.state = can.BusState.ACTIVE
        self.fail = False

    def recv(self, timeout=None):
        if self.fail:
            raise can.CanOperationError("Network is down [Error Code 100]")
        return self.bus.recv(timeout)

    def shutdown(self) -> None:
        self.bus.shutdown()


def test_bus_off_from_the_bus_state_and_a_failing_recv_are_counted_not_fatal(rig):
    r = rig("diff_drive", bus_wrapper=_BusOffBus)
    bus = r.driver._bus
    bus.state = can.BusState.ERROR
    for k in range(3):
        r.read(at_s=1.0 + 0.01 * k)
    assert r.driver.stats()["bus_off"] == 1  # one episode, however many reads see it
    bus.fail = True
    assert r.read(at_s=1.04) == [] and r.read(at_s=1.05) == []
    bus.fail, bus.state = False, can.BusState.ACTIVE
    r.send(wheels_frame(0.0, 0.0, 1.06))
    assert any(isinstance(m, WheelTicks) for m in r.read(at_s=1.06))
    st = r.driver.stats()
    assert st["bus_errors"] == 2 and st["status"] == "ok" and st["errors"] == 0


def test_a_silent_bus_degrades_the_odometry_until_frames_come_back(rig):
    r = rig("diff_drive")  # stale after 5 x 20 ms
    assert r.read(at_s=0.05) == []
    out = r.read(at_s=0.2)
    assert out == [BaseStatus(200_000_000, True, "bus silent")]
    assert r.read(at_s=0.3) == []  # reported once
    r.send(wheels_frame(0.0, 0.0, 0.31))
    out = r.read(at_s=0.31)
    assert isinstance(out[0], WheelTicks) and out[-1] == BaseStatus(310_000_000, False, "")
    st = r.driver.stats()
    assert st["bus_silent"] == 1 and st["degraded"] == 0 and st["status"] == "ok"


def test_a_stale_wheel_is_counted_stops_the_pairs_and_recovers(rig):
    r = rig("odrive_cansimple")
    t = 0.0
    pairs = []
    statuses = []

    def step(left: bool) -> None:
        nonlocal t
        if left:
            r.send(odrive_frame(0, -t, 0.0, t))
        r.send(odrive_frame(1, t, 0.0, t + 0.004))
        got = r.read(at_s=t + 0.004)
        pairs.extend(m for m in got if isinstance(m, WheelTicks))
        statuses.extend(m for m in got if isinstance(m, BaseStatus))
        t += 0.02

    for _ in range(10):
        step(True)
    assert len(pairs) == 10
    for _ in range(10):
        step(False)  # the left node is silent for 200 ms
    assert len(pairs) == 10  # a pair needs a new sample of both wheels
    assert [(s.degraded, s.detail) for s in statuses] == [(True, "left wheel stale")]
    assert r.driver.stats()["stale_left"] == 1 and r.driver.status == "left wheel stale"
    step(True)
    assert statuses[-1].degraded is False and len(pairs) == 11
    st = r.driver.stats()
    assert st["stale_left"] == 1 and st["stale_right"] == 0 and st["degraded"] == 0


def test_the_registry_opens_a_can_base_from_the_config():
    from drivers.registry import open_driver
    from robotd.base.config import Config, replace

    cfg = replace(Config(), "base", driver="can")
    cfg = replace(cfg, "can", interface="virtual", channel="test-can-registry")
    tx = can.Bus(interface="virtual", channel="test-can-registry", preserve_timestamps=True)
    clock = ManualClock(0)
    with open_driver("base", "can", cfg, clock) as drv:
        tx.send(wheels_frame(math.pi, 0.0, 1.0))
        clock.set_ns(1_000_000_000)
        out = drv.read(0.5)
        # [robot] ticks_per_rev = 2578.33: half a turn is 1289 ticks
        assert [(m.left_ticks, m.right_ticks) for m in out if isinstance(m, WheelTicks)] == [(1289, 0)]
    tx.shutdown()
    bad = replace(cfg, "can", interface="no-such-interface")
    from robotd.base.errors import DriverError
    with pytest.raises(DriverError, match="cannot open CAN bus no-such-interface"):
        open_driver("base", "can", bad, clock)


def test_degraded_odometry_shows_in_the_counters_and_in_status():
    from robotd.app.daemon import Daemon
    from robotd.app.notify import Notifier
    from robotd.app.pipeline import Pipeline
    from robotd.app.stages.odometry import OdometryStage
    from robotd.odometry.fusion import OdometryFilter

    pipe = Pipeline()
    stage = pipe.add(OdometryStage(OdometryFilter()))
    stats = {"can": {"status": "left wheel stale", "frames": 10, "stale_left": 1, "bus_off": 0}}
    d = Daemon(ManualClock(0), pipe, {}, Notifier(), driver_stats=lambda: stats)
    pipe.feed(BaseStatus(1, True, "left wheel stale"))
    assert stage.counters()["odometry_degraded"] == 1
    text = d.status_text(1.0)
    assert text.endswith("odometry DEGRADED (left wheel stale); can: left wheel stale "
                         "(frames 10, stale_left 1)")
    pipe.feed(BaseStatus(2, False, ""))
    pipe.feed(BaseStatus(3, True, "bus silent"))
    c = stage.counters()
    assert c["odometry_degraded"] == 1 and c["odometry_degraded_episodes"] == 2


def test_the_service_opens_the_can_base_from_the_whole_config():
    from robotd.app.service import open_sources
    from robotd.base.config import Config, replace

    cfg = replace(Config(), "base", driver="can")
    cfg = replace(cfg, "can", interface="virtual", channel="test-can-service",
                  dbc="odrive_cansimple", left="Left_Encoder_Estimates.Pos_Estimate",
                  right="Right_Encoder_Estimates.Pos_Estimate", wheel_unit="turn", yaw="")
    cfg = replace(cfg, "floor_camera", source="none")
    sources = open_sources(cfg, ManualClock(0))
    drv = sources["base"]
    try:
        assert isinstance(drv, CanBaseDriver) and "odrive_cansimple.dbc" in str(drv)
        assert drv._ticks_per_rev == cfg.robot.ticks_per_rev  # [robot]'s geometry reached it
    finally:
        drv.close()


def test_frames_without_a_usable_time_take_their_receipt_time(rig):
    """The fuzz found a timestamp of 1.8e299 s overflowing the conversion to ns."""
    r = rig("diff_drive")
    r.send(wheels_frame(0.0, 0.0, 1.797693134862316e+299), gyro_frame(1.0, float("nan")))
    out = r.read(at_s=2.5)
    assert [m.stamp_ns for m in out] == [2_500_000_000, 2_500_000_000]
    assert r.driver.stats()["untimed_frames"] == 2
