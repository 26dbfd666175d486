"""The CAN base emulator: the virtual robot's SI sensor streams as CAN frames on a python-can bus.

:func:`encode_can` turns :class:`~sim.sensors.BaseSensorStreams` (the same streams, with
the same drawn errors, that the Kobuki emulator encodes) into the frames a CAN base sends,
in one of the two conventions robotd ships a DBC for (:data:`CONVENTIONS`), encoded with
that DBC by cantools:

- ``diff_drive``: at each wheel sample (50 Hz) one ``Base_Wheels`` frame with both wheels'
  cumulative angles (0.1 mrad per bit, 32-bit, from a random power-on angle), and one
  ``Base_Gyro`` frame per gyro sample (108 Hz) at the sample's own time, 0.005 deg/s per
  bit, with a rolling counter.
- ``odrive_cansimple``: one ODrive axis per wheel (node 0 left, node 1 right), each
  sending ``Encoder_Estimates`` (position in motor turns from a random power-on value,
  velocity in turns/s, float32) every wheel period, the right node ``odrive_skew_s`` (4 ms)
  after the left, its position interpolated at its own time; the left motor is mirrored
  (its turns count backwards: ``[can] left_scale = -1``); heartbeats every 100 ms. No gyro.

Every frame carries its send time as its timestamp (the bus preserves it), as a kernel
timestamps a frame on receipt, on a clock of its own (:data:`FRAME_TIME_BASE_S`). :class:`CanFaults` injects faults into the stream: a
flood of frames with ids not in the DBC, a bus-off (error frame, silence, restart), a
wheel gone silent, and frames of a known id with a wrong length.

:class:`CanEmulator` is a part of the virtual robot (:mod:`sim.robot`): ``emit(i)`` sends
frame ``i`` on a python-can ``virtual`` bus channel that the daemon's
:class:`~drivers.can.driver.CanBaseDriver` opens by name.
"""

from __future__ import annotations

import math
import os
import threading
from dataclasses import dataclass, field
from itertools import count
from typing import Any

import cantools
import numpy as np

from drivers.can.driver import CAN_ERR_BUSOFF, CAN_ERR_RESTARTED, load_dbc
from sim.sensors import BaseSensorStreams

__all__ = ["CONVENTIONS", "CanEmulator", "CanFaults", "CanFrames", "can_config_changes",
           "driver_messages", "encode_can"]

CONVENTIONS = ("diff_drive", "odrive_cansimple")

FRAME_TIME_BASE_S = 1_000_000.0
"""Frame timestamps are simulation time plus this: a clock that is not the daemon's, as
socketcan's wall-clock timestamps are not its monotonic clock (and python-can reads a
timestamp of 0 as none)."""

_ERROR_FRAME = -1
"""``frame_id`` marker of an error frame (its class is in ``data``)."""

_channels = count()


@dataclass(frozen=True)
class CanFaults:
    """Faults to inject, each at a time of the run (s; ``None``: not injected).

    ``flood_at_s``: ``flood_frames`` frames with random ids not in the DBC, all sent at
    that instant. ``bus_off_at_s``: an error frame with CAN_ERR_BUSOFF, then no data frame
    for ``bus_off_s``, then an error frame with CAN_ERR_RESTARTED (what the kernel delivers
    when the robot's own controller goes bus-off and restarts). ``stale_at_s``: the left
    wheel (``diff_drive``: the wheels frame; ``odrive``: node 0) sends nothing for
    ``stale_s``. ``bad_length_frames``: that many wheel frames, evenly spread, sent with
    3 bytes instead of 8 (they cannot be decoded).
    """

    flood_at_s: float | None = None
    flood_frames: int = 5000
    bus_off_at_s: float | None = None
    bus_off_s: float = 0.2
    stale_at_s: float | None = None
    stale_s: float = 0.3
    bad_length_frames: int = 0

    @classmethod
    def standard(cls, duration_s: float) -> CanFaults:
        """One of each, spread over a run of ``duration_s`` (the bench's and the e2e test's)."""
        return cls(flood_at_s=0.2 * duration_s, bus_off_at_s=0.45 * duration_s,
                   stale_at_s=0.7 * duration_s, bad_length_frames=20)


@dataclass(frozen=True, eq=False)
class CanFrames:
    """The frames of one run, in send order: ``t_s`` ``(K,)`` send times, ``frame_id``
    ``(K,)`` (``-1``: an error frame), ``data`` their payloads. ``injected`` counts the
    faults put in (by kind)."""

    t_s: np.ndarray
    frame_id: np.ndarray
    data: list[bytes]
    convention: str
    injected: dict[str, int] = field(default_factory=dict)


def can_config_changes(convention: str) -> dict[str, object]:
    """The ``[can]`` keys that read this emulator's convention (for :func:`robotd.base.config.replace`)."""
    if convention == "diff_drive":
        return {"dbc": "diff_drive", "left": "Base_Wheels.Left_Wheel_Pos",
                "right": "Base_Wheels.Right_Wheel_Pos", "wheel_unit": "rad", "left_scale": 1.0,
                "right_scale": 1.0, "yaw": "Base_Gyro.Yaw_Rate", "yaw_unit": "deg/s"}
    if convention == "odrive_cansimple":
        return {"dbc": "odrive_cansimple", "left": "Left_Encoder_Estimates.Pos_Estimate",
                "right": "Right_Encoder_Estimates.Pos_Estimate", "wheel_unit": "turn",
                "left_scale": -1.0, "right_scale": 1.0, "yaw": ""}
    raise ValueError(f"unknown CAN convention {convention!r} (known: {', '.join(CONVENTIONS)})")


def encode_can(sensors: BaseSensorStreams, convention: str, rng: np.random.Generator,
               faults: CanFaults | None = None, odrive_skew_s: float = 0.004) -> CanFrames:
    """The frames a CAN base of ``convention`` sends for ``sensors``; see the module doc."""
    if convention not in CONVENTIONS:
        raise ValueError(f"unknown CAN convention {convention!r} (known: {', '.join(CONVENTIONS)})")
    db = load_dbc(convention)
    faults = faults or CanFaults()
    rows: list[tuple[float, int, int, bytes, str]] = []  # (t, order, id, data, role)
    t = sensors.t_s
    angle = sensors.wheel_angle_rad
    if convention == "diff_drive":
        wheels = db.get_message_by_name("Base_Wheels")
        gyro = db.get_message_by_name("Base_Gyro")
        a0 = rng.uniform(-2e5, 2e5, 2)
        span = 2 ** 32 * 1e-4
        for ti, (al, ar) in zip(t, angle):
            # the 32-bit field wraps; cantools wants the value inside its range
            vals = [((a + a0[k] + span / 2) % span) - span / 2 for k, a in enumerate((al, ar))]
            rows.append((float(ti), 1, wheels.frame_id,
                         wheels.encode({"Left_Wheel_Pos": vals[0], "Right_Wheel_Pos": vals[1]}), "wheel"))
        yaw_degps = np.clip(np.rad2deg(sensors.gyro_radps[:, 2]), -163.84, 163.835)
        for k, (tg, w) in enumerate(zip(sensors.gyro_t_s, yaw_degps)):
            rows.append((float(tg), 0, gyro.frame_id,
                         gyro.encode({"Yaw_Rate": round(float(w) / 0.005) * 0.005,
                                      "Gyro_Counter": k % 256, "Gyro_Status": 0}), "gyro"))
    else:
        turns = angle / (2.0 * math.pi) * np.array([-1.0, 1.0])  # the left motor is mirrored
        turns0 = rng.uniform(-50.0, 50.0, 2)
        t_right = t + odrive_skew_s
        vel = np.gradient(turns, t, axis=0) if len(t) > 1 else np.zeros_like(turns)
        right = np.interp(t_right, t, turns[:, 1])
        right[-1] = turns[-1, 1] + vel[-1, 1] * odrive_skew_s  # past the streams' last sample
        enc = [db.get_message_by_name("Left_Encoder_Estimates"),
               db.get_message_by_name("Right_Encoder_Estimates")]
        for i, ti in enumerate(t):
            for k, (tk, pos) in enumerate(((float(ti), turns[i, 0]), (float(t_right[i]), right[i]))):
                rows.append((tk, 1, enc[k].frame_id,
                             enc[k].encode({"Pos_Estimate": float(np.float32(pos + turns0[k])),
                                            "Vel_Estimate": float(np.float32(vel[i, k]))}),
                             "wheel" if k == 0 else "wheel_right"))
        beats = [db.get_message_by_name("Left_Heartbeat"), db.get_message_by_name("Right_Heartbeat")]
        for tb in np.arange(0.0, float(t[-1]) if len(t) else 0.0, 0.1):
            for k, hb in enumerate(beats):
                rows.append((float(tb) + 0.001 * k, 2, hb.frame_id,
                             hb.encode({"Axis_Error": 0, "Axis_State": 8, "Procedure_Result": 0,
                                        "Trajectory_Done_Flag": 0}), "other"))
    injected: dict[str, int] = {}
    rows = _inject(rows, faults, db, rng, injected, convention)
    rows.sort(key=lambda r: (r[0], r[1]))
    return CanFrames(np.array([r[0] for r in rows]), np.array([r[2] for r in rows], dtype=np.int64),
                     [r[3] for r in rows], convention, injected)


def _inject(rows: list[tuple[float, int, int, bytes, str]], faults: CanFaults,
            db: cantools.database.can.Database, rng: np.random.Generator,
            injected: dict[str, int], convention: str) -> list[tuple[float, int, int, bytes, str]]:
    known = {m.frame_id for m in db.messages}
    if faults.stale_at_s is not None:
        lo, hi = faults.stale_at_s, faults.stale_at_s + faults.stale_s
        before = len(rows)
        rows = [r for r in rows if not (r[4] == "wheel" and lo <= r[0] < hi)]
        injected["left_wheel_frames_dropped"] = before - len(rows)
    if faults.bus_off_at_s is not None:
        lo, hi = faults.bus_off_at_s, faults.bus_off_at_s + faults.bus_off_s
        before = len(rows)
        rows = [r for r in rows if not lo <= r[0] < hi]
        injected["frames_lost_in_bus_off"] = before - len(rows)
        rows.append((lo, -1, _ERROR_FRAME, CAN_ERR_BUSOFF.to_bytes(4, "little"), "error"))
        rows.append((hi, -1, _ERROR_FRAME, CAN_ERR_RESTARTED.to_bytes(4, "little"), "error"))
        injected["bus_off"] = 1
    if faults.flood_at_s is not None:
        drawn = rng.integers(0, 0x800, faults.flood_frames * 2)
        ids = [int(i) for i in drawn if int(i) not in known][: faults.flood_frames]
        for i in ids:
            rows.append((faults.flood_at_s, 3, i, rng.integers(0, 256, 8, dtype=np.uint8).tobytes(), "flood"))
        injected["flood_frames"] = len(ids)
    if faults.bad_length_frames:
        wheel_rows = [k for k, r in enumerate(rows) if r[4] == "wheel"]
        pick = np.linspace(0, len(wheel_rows) - 1, faults.bad_length_frames + 2)[1:-1].astype(int)
        for k in pick:
            t, order, fid, data, role = rows[wheel_rows[k]]
            rows[wheel_rows[k]] = (t, order, fid, data[:3], "bad")
        injected["bad_length_frames"] = len(pick)
    return rows


class CanEmulator:
    """The CAN base as a part of the virtual robot: ``emit(i)`` sends frame ``i`` of
    ``frames`` on the python-can ``virtual`` bus :attr:`channel` (a name unique to this
    emulator). A driver must be connected to the channel before frames are sent (a
    virtual bus delivers only to the buses open at that time).

    ``stamp_ns`` and ``true_pose`` are the ground truth at the wheel samples (as the
    Kobuki emulator's); :attr:`frames_sent` counts frames sent.
    """

    def __init__(self, frames: CanFrames, sensors: BaseSensorStreams,
                 stop: threading.Event | None = None) -> None:
        import can

        self.frames = frames
        self.sensors = sensors
        self.channel = f"robotd-virtual-{os.getpid()}-{next(_channels)}"
        self._bus: can.BusABC | None = can.Bus(interface="virtual", channel=self.channel,
                                               preserve_timestamps=True)
        self._can = can
        self.frames_sent = 0
        self.commands_received: dict[str, int] = {}  # a CAN base here takes no commands

    @property
    def packets_emitted(self) -> int:
        """Frames sent (the robot's progress figure; error frames included)."""
        return self.frames_sent

    @property
    def event_times_s(self) -> np.ndarray:
        return self.frames.t_s

    @property
    def stamp_ns(self) -> np.ndarray:
        """``(N,) int64`` the wheel samples' times, ns (ground-truth stamps)."""
        return self.sensors.stamp_ns

    @property
    def true_pose(self) -> np.ndarray:
        """``(N, 3) float64`` the true ``(x_m, y_m, yaw_rad)`` at each wheel sample."""
        return self.sensors.true_pose

    @property
    def port(self) -> str:
        """The channel a driver opens (what a serial emulator's pty path is)."""
        return self.channel

    def emit(self, i: int) -> None:
        fid = int(self.frames.frame_id[i])
        data = self.frames.data[i]
        t = float(self.frames.t_s[i]) + FRAME_TIME_BASE_S
        if fid == _ERROR_FRAME:
            msg = self._can.Message(timestamp=t, arbitration_id=int.from_bytes(data, "little"),
                                    is_extended_id=False, is_error_frame=True, dlc=0, data=b"")
        else:
            msg = self._can.Message(timestamp=t, arbitration_id=fid, is_extended_id=False,
                                    data=data, dlc=len(data))
        if self._bus is None:
            raise RuntimeError("the CAN emulator is closed")
        self._bus.send(msg)
        self.frames_sent += 1

    def close(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()

    def __enter__(self) -> CanEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def driver_messages(frames: CanFrames, sensors: BaseSensorStreams, *, read_every: int = 8,
                    ) -> tuple[list[Any], dict[str, Any]]:
    """What the real :class:`~drivers.can.driver.CanBaseDriver` makes of ``frames``, and its
    stats: the emulator sends them on a virtual bus in time order with a
    :class:`~robotd.base.clock.ManualClock` at each frame's time, and the driver (opened
    through its registry factory with the convention's ``[can]`` keys and the default
    ``[robot]``) reads after every ``read_every`` frames, at least every ``[can]
    period_s`` of a quiet bus, and at the end."""
    from drivers.can.driver import open_can
    from robotd.base.clock import ManualClock
    from robotd.base.config import Config, replace

    clock = ManualClock()
    out: list[Any] = []
    with CanEmulator(frames, sensors) as emulator:
        cfg = replace(Config(), "can", interface="virtual", channel=emulator.channel,
                      **can_config_changes(frames.convention))
        with open_can(cfg, clock) as driver:
            period_ns = int(cfg.can.period_s * 1e9)
            last_read_ns = 0
            for i, t in enumerate(frames.t_s):
                t_ns = int(round(float(t) * 1e9))
                while t_ns - last_read_ns > period_ns:  # a quiet bus is still read
                    last_read_ns += period_ns
                    clock.set_ns(max(clock.now_ns(), last_read_ns))
                    out += driver.read(0.0)
                clock.set_ns(max(clock.now_ns(), t_ns))
                emulator.emit(i)
                if i % read_every == read_every - 1:
                    out += driver.read(0.0)
                    last_read_ns = clock.now_ns()
            for _ in range(emulator.frames_sent):  # the virtual bus has them all already
                out += driver.read(0.0)
                if int(driver.stats()["frames"]) >= emulator.frames_sent:
                    break
            return out, driver.stats()
