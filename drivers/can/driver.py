"""The CAN base driver: python-can frames in, stamped WheelTicks, YawRate and BaseStatus out.

A CAN base is a DBC file plus the ``[can]`` config section that names which decoded
signals are the left and right wheel (a position or a speed), which is the yaw rate, and
their units; the wheel geometry is ``[robot]``'s. Two DBC files written for robotd are
shipped (:data:`SHIPPED_DBC`): ODrive's CANSimple with one axis per wheel, and a generic
differential-drive base with a gyro frame.

What the odometry consumes
--------------------------
The odometry (:mod:`robotd.odometry`) takes :class:`~robotd.base.messages.WheelTicks`:
both wheels' encoder counters at one stamp, 16-bit and wrapping, turned into distance
with ``[robot] ticks_per_rev`` and ``wheel_radius_m``. So this driver keeps each wheel's
cumulative angle in *turns* (a float) and hands out ``round(turns * ticks_per_rev) mod
2**16``: the odometry then sees the wheel as an encoder of exactly ``ticks_per_rev``, and
its tick (85 um of rim on a Kobuki's geometry) is the only quantisation added.

- A position signal (``turn``, ``rad``, ``deg``, ``m`` of rim) is converted to turns
  (``m``: divided by the circumference ``2 pi wheel_radius_m``). An integer signal that
  wraps (the generic DBC's 32-bit angle) is unwrapped by its own span (``2**length *
  scale``).
- A speed signal (``turn/s``, ``rad/s``, ``deg/s``, ``m/s``, ``rpm``) is integrated into
  turns by the trapezoid rule between consecutive frames' stamps; over a gap longer than
  the staleness limit nothing is integrated (the distance is lost, counted in
  ``speed_gaps``). Integrated speed drifts with the speed's quantisation; a position
  signal does not, so prefer one.
- ``left_scale``/``right_scale`` multiply the decoded value first (a mirrored motor, a
  gearbox).

When both wheels are in one frame (the generic DBC) the pair is emitted at that frame's
stamp. When each wheel has its own frame (an ODrive per wheel), a pair is emitted when
both wheels have a sample newer than the last pair, at the later sample's stamp; the
earlier wheel is moved forward to that stamp at its own latest speed (finite difference
of its positions, or its speed signal) when the two are at most one period apart.
Positions are absolute, so an error of this step does not accumulate.

The yaw rate is converted to rad/s (``yaw_unit``, ``yaw_scale``) and stamped at its
frame: the generic DBC sends one gyro sample per frame, as it is measured (unlike the
Kobuki, whose packet carries the mean of the samples since the previous one).

Timestamps
----------
Every frame is stamped from python-can's ``Message.timestamp`` (the kernel's receive time
on socketcan, in the wall-clock's time base; the sender's time on a virtual bus that
preserves it) mapped to the driver's clock as the Kobuki driver maps its device clock
(:class:`~drivers.timesync.OffsetMapper`): ``stamp = frame time + offset``, the offset the
minimum ``receipt - frame time`` over the last ``offset_window_s``. So the frames' own
spacing is kept, batching and read latency drop out, and a wall-clock step is followed
within the window. A frame time that goes backwards is raised to the previous one
(``timestamps_backwards``); a frame without a time (0, NaN, or absurdly large) takes its
receipt time (``untimed_frames``).

Faults: counted, never fatal
----------------------------
``unknown_frames``/``unknown_ids`` (ids not in the DBC), ``decode_errors`` (a known id
with the wrong length or undecodable data), ``bad_values`` (a NaN or infinite float),
``remote_frames``, ``error_frames`` (with ``bus_off``, ``bus_restarts`` and
``error_passive`` from the Linux error classes in their id), ``bus_errors`` (python-can
raised: the interface is down, e.g. after bus-off without ``restart-ms``), ``flood_reads``
(a read that hit ``max_frames_per_read``). python-can's ``bus.state`` is also read each
time: ``BusState.ERROR`` (bus-off) counts in ``bus_off`` once per episode.

A wheel without a frame for ``stale_periods`` periods while other frames arrive is stale
(``stale_left``/``stale_right`` count the episodes; the first is logged as a warning,
later ones at debug); a bus with no frame at all for as long is silent (``bus_silent``).
While either lasts the driver is degraded: it emits a
:class:`~robotd.base.messages.BaseStatus` when that changes, the odometry stage marks the
odometry degraded (its STATUS line says so), and :meth:`stats` has ``degraded`` and a
one-line ``status``. A wheel that never spoke is stale once the bus has run that long
without it. No wheel pair is emitted while a wheel is silent: a pair needs a new sample
of both (a new sample of one wheel with the other's old one would read as a turn).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import cantools

from drivers.base import Driver, Message, StatValue
from drivers.timesync import OffsetMapper
from robotd.base.clock import Clock
from robotd.base.errors import ConfigError, DriverError
from robotd.base.messages import BaseStatus, WheelTicks, YawRate

__all__ = ["SHIPPED_DBC", "CanBaseDriver", "dbc_path", "load_dbc", "open_can"]

logger = logging.getLogger(__name__)

DBC_DIR = Path(__file__).with_name("dbc")
SHIPPED_DBC = {"diff_drive": DBC_DIR / "diff_drive.dbc",
               "odrive_cansimple": DBC_DIR / "odrive_cansimple.dbc"}
"""The DBC files shipped with robotd, by the name ``[can] dbc`` may give."""

# Linux <linux/can/error.h>: the error class bits in an error frame's id, and the
# controller status in its data[1].
CAN_ERR_CRTL = 0x004
CAN_ERR_BUSOFF = 0x040
CAN_ERR_RESTARTED = 0x100
CAN_ERR_CRTL_PASSIVE = 0x10 | 0x20  # RX or TX error passive

_U16 = 1 << 16
_MAX_TIMESTAMP_S = 1e11
"""A frame time beyond this (the year 5138, or infinite) is taken as none (the fuzz found
that 1.8e299 s overflowed the conversion to ns)."""
_MAX_UNKNOWN_IDS = 4096
"""Distinct unknown ids remembered (bounds memory on a flood of random ids)."""

_TURNS_PER_UNIT = {"turn": 1.0, "rad": 1.0 / (2.0 * math.pi), "deg": 1.0 / 360.0,
                   "turn/s": 1.0, "rad/s": 1.0 / (2.0 * math.pi), "deg/s": 1.0 / 360.0,
                   "rpm": 1.0 / 60.0}
_RADPS_PER_UNIT = {"rad/s": 1.0, "deg/s": math.pi / 180.0}


def dbc_path(name: str) -> Path:
    """The file of ``[can] dbc``: a shipped name (:data:`SHIPPED_DBC`) or a path."""
    return SHIPPED_DBC.get(name, Path(name))


def load_dbc(name: str) -> cantools.database.can.Database:
    """The cantools database of ``[can] dbc``; :class:`ConfigError` in one line if it
    cannot be read or parsed."""
    path = dbc_path(name)
    try:
        db = cantools.database.load_file(str(path), database_format="dbc")
    except FileNotFoundError:
        known = ", ".join(sorted(SHIPPED_DBC))
        raise ConfigError(f"[can] dbc: no file {path} (shipped: {known})") from None
    except Exception as exc:  # cantools raises its own parse errors and plain ones
        raise ConfigError(f"[can] dbc: {path} is not a readable DBC file: {exc}") from None
    if not isinstance(db, cantools.database.can.Database):  # a DBC file is always a CAN database
        raise ConfigError(f"[can] dbc: {path} is not a CAN database")
    return db


@dataclass(frozen=True)
class _Use:
    """One decoded signal the driver uses: ``role`` is ``left``, ``right`` or ``yaw``;
    ``factor`` takes the decoded value to turns (or turns/s, or rad/s for the yaw);
    ``wrap`` is the span of an integer position signal (None: float or speed)."""

    role: str
    signal: str
    factor: float
    wrap: float | None


class _Wheel:
    """One wheel's cumulative angle in turns, from a position or a speed signal."""

    def __init__(self, name: str, is_speed: bool) -> None:
        self.name = name
        self.is_speed = is_speed
        self.turns: float | None = None
        self.speed_tps = 0.0          # turns/s: the signal, or the last finite difference
        self.stamp_ns: int | None = None
        self.fresh = False            # a sample newer than the last emitted pair
        self.stale = False
        self.stale_episodes = 0
        self.speed_gaps = 0
        self._raw: float | None = None  # last position in signal units (for unwrapping)

    def update(self, value: float, use: _Use, stamp_ns: int, max_gap_ns: int) -> None:
        """Take one decoded value (signal units) stamped ``stamp_ns``."""
        if self.is_speed:
            speed = value * use.factor
            if self.turns is None:
                self.turns = 0.0
            elif self.stamp_ns is not None:
                dt_ns = stamp_ns - self.stamp_ns
                if dt_ns > max_gap_ns:
                    self.speed_gaps += 1
                elif dt_ns > 0:
                    self.turns += 0.5 * (self.speed_tps + speed) * dt_ns * 1e-9
            self.speed_tps = speed
        else:
            if self._raw is None or self.turns is None:
                self.turns = value * use.factor
            else:
                step = value - self._raw
                if use.wrap is not None and abs(step) > use.wrap / 2.0:
                    step -= math.copysign(use.wrap, step)
                turns = self.turns + step * use.factor
                if self.stamp_ns is not None and stamp_ns > self.stamp_ns:
                    self.speed_tps = (turns - self.turns) / ((stamp_ns - self.stamp_ns) * 1e-9)
                self.turns = turns
            self._raw = value
        self.stamp_ns = stamp_ns
        self.fresh = True

    def turns_at(self, stamp_ns: int, max_lead_ns: int) -> float:
        """The angle moved forward to ``stamp_ns`` at the wheel's speed (at most
        ``max_lead_ns`` ahead of its own sample; further, the sample as it is)."""
        assert self.turns is not None and self.stamp_ns is not None
        lead = stamp_ns - self.stamp_ns
        if 0 < lead <= max_lead_ns:
            return self.turns + self.speed_tps * lead * 1e-9
        return self.turns


class CanBaseDriver(Driver):
    """A differential-drive base on a python-can bus, decoded with a DBC; see the module doc.

    ``bus`` is an open ``can.BusABC`` (the driver shuts it down on :meth:`close`);
    ``db`` the cantools database; ``left``, ``right`` and ``yaw`` are
    ``"Message.Signal"`` (``yaw`` may be ``""``: no gyro). ``ticks_per_rev`` and
    ``wheel_radius_m`` are the odometry's ``[robot]`` values.
    """

    def __init__(self, bus: Any, clock: Clock, db: Any, *, left: str, right: str,
                 wheel_unit: str = "rad", left_scale: float = 1.0, right_scale: float = 1.0,
                 yaw: str = "", yaw_unit: str = "deg/s", yaw_scale: float = 1.0,
                 ticks_per_rev: float = 2578.33, wheel_radius_m: float = 0.035,
                 period_s: float = 0.02, stale_periods: int = 5,
                 max_frames_per_read: int = 2000, offset_window_s: float = 10.0,
                 name: str = "base", label: str = "") -> None:
        super().__init__(name)
        if wheel_unit not in _TURNS_PER_UNIT and wheel_unit not in ("m", "m/s"):
            raise ConfigError(f"[can] wheel_unit: {wheel_unit!r} is not a unit of angle, "
                              "distance or speed")
        if yaw and yaw_unit not in _RADPS_PER_UNIT:
            raise ConfigError(f"[can] yaw_unit: {yaw_unit!r} is not rad/s or deg/s")
        self._bus = bus
        self._clock = clock
        self._label = label or f"CAN bus {getattr(bus, 'channel_info', '')}".strip()
        self._ticks_per_rev = float(ticks_per_rev)
        is_speed = wheel_unit.endswith("/s") or wheel_unit == "rpm"
        per_unit = (1.0 / (2.0 * math.pi * wheel_radius_m) if wheel_unit in ("m", "m/s")
                    else _TURNS_PER_UNIT[wheel_unit])
        self._routes: dict[tuple[int, bool], tuple[Any, list[_Use]]] = {}
        self._add_use(db, "left", left, per_unit * left_scale, position=not is_speed)
        self._add_use(db, "right", right, per_unit * right_scale, position=not is_speed)
        if yaw:
            self._add_use(db, "yaw", yaw, _RADPS_PER_UNIT[yaw_unit] * yaw_scale, position=False)
        self._known_ids = {(m.frame_id, bool(m.is_extended_frame)) for m in db.messages}
        self._wheels = {"left": _Wheel("left", is_speed), "right": _Wheel("right", is_speed)}
        self._period_ns = int(period_s * 1e9)
        self._stale_ns = int(stale_periods * period_s * 1e9)
        self._max_frames = int(max_frames_per_read)
        self._mapper = OffsetMapper(int(offset_window_s * 1e9))
        self._last_device_ns: int | None = None
        self._newest_ns: int | None = None      # newest data frame's stamp
        self._first_ns: int | None = None       # first data frame's stamp
        self._opened_ns = clock.now_ns()
        self._last_receipt_ns: int | None = None
        self._silent = False
        self._bus_off = False
        self._error_passive = False
        self._degraded = False
        self._detail = ""
        self._unknown_ids: set[tuple[int, bool]] = set()
        self._logged: set[str] = set()
        self._n = dict.fromkeys((
            "frames", "frames_used", "frames_other", "unknown_frames", "decode_errors",
            "bad_values", "remote_frames", "error_frames", "bus_off", "bus_restarts",
            "error_passive", "bus_errors", "flood_reads", "bus_silent", "timestamps_backwards",
            "untimed_frames", "wheel_samples", "yaw_samples"), 0)

    def _add_use(self, db: Any, role: str, ref: str, factor: float, *, position: bool) -> None:
        msg_name, dot, sig_name = ref.partition(".")
        if not dot or not msg_name or not sig_name:
            raise ConfigError(f"[can] {role}: {ref!r} is not \"Message.Signal\"")
        try:
            message = db.get_message_by_name(msg_name)
        except KeyError:
            known = ", ".join(m.name for m in db.messages)
            raise ConfigError(f"[can] {role}: no message {msg_name!r} in the DBC (it has: {known})") from None
        signal = next((s for s in message.signals if s.name == sig_name), None)
        if signal is None:
            known = ", ".join(s.name for s in message.signals)
            raise ConfigError(f"[can] {role}: message {msg_name} has no signal {sig_name!r} "
                              f"(it has: {known})")
        wrap = None
        if position and not signal.is_float:
            wrap = float(2 ** signal.length) * abs(float(signal.scale))
        key = (message.frame_id, bool(message.is_extended_frame))
        self._routes.setdefault(key, (message, []))[1].append(_Use(role, sig_name, factor, wrap))

    def __str__(self) -> str:
        return f"{self.name}: {self._label}"

    # -- the Driver interface ----------------------------------------------------------

    def _close_internal(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except Exception as exc:  # a bus that fails to shut down is already gone
                logger.debug("%s: shutdown failed: %s", self, exc)
            logger.info("closed %s", self._label)

    def _stats_internal(self) -> dict[str, StatValue]:
        out: dict[str, StatValue] = dict(self._n)
        out.update(unknown_ids=len(self._unknown_ids), clock_clamps=self._mapper.clamps,
                   stale_left=self._wheels["left"].stale_episodes,
                   stale_right=self._wheels["right"].stale_episodes,
                   speed_gaps=sum(w.speed_gaps for w in self._wheels.values()),
                   degraded=int(self._degraded), status=self.status)
        return out

    @property
    def status(self) -> str:
        """One line: ``ok``, or what is wrong now (``left wheel stale``, ``bus-off``, ...)."""
        parts = [self._detail] if self._degraded else []
        if self._bus_off:
            parts.append("bus-off")
        elif self._error_passive:
            parts.append("error passive")
        return ", ".join(parts) or "ok"

    def _read_internal(self, timeout_s: float) -> list[Message]:
        bus = self._bus
        if bus is None:
            raise DriverError(f"{self._label} is closed")
        frames: list[can.Message] = []
        try:
            msg = bus.recv(timeout_s)
            while msg is not None:
                frames.append(msg)
                if len(frames) >= self._max_frames:
                    self._n["flood_reads"] += 1
                    self._log_once("flood", f"{len(frames)} frames waiting in one read (a flood); "
                                   "taking them in batches of max_frames_per_read")
                    break
                msg = bus.recv(0.0)
        except can.CanError as exc:
            self._n["bus_errors"] += 1
            self._log_once(f"bus error {exc}", f"bus error (counted, reading on): {exc}")
            if not frames:  # an interface that refuses at once must not make us spin
                time.sleep(min(timeout_s, 0.1))
        self._check_bus_state(bus)
        receipt_ns = self._clock.now_ns()
        out = self._handle(frames, receipt_ns)
        status = self._check_health(receipt_ns)
        if status is not None:
            out.append(status)
        return out

    # -- frames ------------------------------------------------------------------------

    def _log_once(self, key: str, text: str) -> None:
        if key in self._logged:
            logger.debug("%s: %s", self, text)
            return
        if len(self._logged) < 256:
            self._logged.add(key)
        logger.warning("%s: %s", self, text)

    def _check_bus_state(self, bus: Any) -> None:
        try:
            state = bus.state
        except Exception:  # an interface without a bus state
            return
        if state == can.BusState.ERROR:
            self._enter_bus_off("the interface reports bus-off (BusState.ERROR)")

    def _enter_bus_off(self, why: str) -> None:
        if not self._bus_off:
            self._bus_off = True
            self._n["bus_off"] += 1
            self._log_once("bus-off", f"bus-off: {why} (counted; reading on)")

    def _error_frame(self, msg: can.Message) -> None:
        self._n["error_frames"] += 1
        cls = int(msg.arbitration_id)
        if cls & CAN_ERR_BUSOFF:
            self._enter_bus_off("error frame with CAN_ERR_BUSOFF")
        if cls & CAN_ERR_RESTARTED:
            self._n["bus_restarts"] += 1
            self._bus_off = False
            self._error_passive = False
        if cls & CAN_ERR_CRTL and len(msg.data) > 1 and msg.data[1] & CAN_ERR_CRTL_PASSIVE:
            if not self._error_passive:
                self._n["error_passive"] += 1
            self._error_passive = True
        self._log_once("error frame", f"error frame, class 0x{cls:03x} (counted)")

    def _device_ns(self, msg: can.Message, receipt_ns: int) -> int | None:
        """The frame's own time in ns (non-decreasing), None when it has none."""
        ts = msg.timestamp
        if not (isinstance(ts, float | int) and 0.0 < ts < _MAX_TIMESTAMP_S):
            self._n["untimed_frames"] += 1
            return None
        dev = int(round(ts * 1e9))
        if self._last_device_ns is not None and dev < self._last_device_ns:
            self._n["timestamps_backwards"] += 1
            dev = self._last_device_ns
        self._last_device_ns = dev
        return dev

    def _handle(self, frames: list[can.Message], receipt_ns: int
                ) -> list[Message]:
        n = self._n
        data: list[tuple[can.Message, int | None]] = []
        for msg in frames:
            n["frames"] += 1
            if msg.is_error_frame:
                self._error_frame(msg)
                continue
            if msg.is_remote_frame:
                n["remote_frames"] += 1
                continue
            dev = self._device_ns(msg, receipt_ns)
            if dev is not None:
                self._mapper.observe(dev, receipt_ns)
            data.append((msg, dev))
        if data:
            self._last_receipt_ns = receipt_ns
            if self._bus_off:  # frames flow again: the controller is back on the bus
                self._bus_off = False
        out: list[Message] = []
        for msg, dev in data:
            stamp = self._mapper.stamp(dev) if dev is not None else self._mapper.clamp(receipt_ns)
            self._newest_ns = stamp
            if self._first_ns is None:
                self._first_ns = stamp
            key = (int(msg.arbitration_id), bool(msg.is_extended_id))
            route = self._routes.get(key)
            if route is None:
                if key in self._known_ids:
                    n["frames_other"] += 1
                else:
                    n["unknown_frames"] += 1
                    if key not in self._unknown_ids and len(self._unknown_ids) < _MAX_UNKNOWN_IDS:
                        self._unknown_ids.add(key)
                        if len(self._unknown_ids) <= 10:
                            logger.info("%s: frame id 0x%x is not in the DBC (counted, ignored)",
                                        self, key[0])
                continue
            message, uses = route
            try:
                values = message.decode(bytes(msg.data), decode_choices=False)
            except Exception as exc:  # cantools' DecodeError and whatever bad data provokes
                n["decode_errors"] += 1
                self._log_once(f"decode {message.name}", f"{message.name} (0x{key[0]:x}) "
                               f"does not decode: {exc} (counted, skipped)")
                continue
            n["frames_used"] += 1
            wheels_moved = False
            for use in uses:
                value = values.get(use.signal)
                if not isinstance(value, int | float) or not math.isfinite(value):
                    n["bad_values"] += 1
                    self._log_once(f"bad {use.signal}", f"{message.name}.{use.signal} = "
                                   f"{value!r} is not a finite number (counted, skipped)")
                    continue
                if use.role == "yaw":
                    out.append(YawRate(stamp, float(value) * use.factor, "can"))
                    n["yaw_samples"] += 1
                else:
                    self._wheels[use.role].update(float(value), use, stamp, self._stale_ns)
                    wheels_moved = True
            if wheels_moved:
                pair = self._pair()
                if pair is not None:
                    out.append(pair)
        return out

    def _pair(self) -> WheelTicks | None:
        """Both wheels' ticks at the later of their samples, once both are fresh."""
        left, right = self._wheels["left"], self._wheels["right"]
        if not (left.fresh and right.fresh):
            return None
        assert left.stamp_ns is not None and right.stamp_ns is not None
        stamp = max(left.stamp_ns, right.stamp_ns)
        ticks = [int(round(w.turns_at(stamp, self._period_ns) * self._ticks_per_rev)) % _U16
                 for w in (left, right)]
        left.fresh = right.fresh = False
        self._n["wheel_samples"] += 1
        return WheelTicks(stamp, ticks[0], ticks[1])

    # -- health ------------------------------------------------------------------------

    def _check_health(self, receipt_ns: int) -> BaseStatus | None:
        """Update the stale wheels and the silent bus; a :class:`BaseStatus` when the
        degraded state changed."""
        since = receipt_ns - (self._last_receipt_ns if self._last_receipt_ns is not None
                              else self._opened_ns)
        silent = since > self._stale_ns
        if silent and not self._silent:
            self._n["bus_silent"] += 1
            self._log_once("silent", f"no frame for {since / 1e9:.2f} s: the bus is silent "
                           "(counted; odometry degraded until frames come back)")
        self._silent = silent
        stale: list[str] = []
        if self._newest_ns is not None and self._first_ns is not None:
            for w in self._wheels.values():
                last = w.stamp_ns if w.stamp_ns is not None else self._first_ns
                is_stale = self._newest_ns - last > self._stale_ns
                if is_stale and not w.stale:
                    w.stale_episodes += 1
                    text = (f"{w.name} wheel stale: no frame for {(self._newest_ns - last) / 1e9:.2f} s "
                            "while the bus runs (counted; odometry degraded)")
                    if w.stale_episodes == 1:
                        logger.warning("%s: %s", self, text)
                    else:
                        logger.debug("%s: %s", self, text)
                if w.stale and not is_stale:
                    logger.info("%s: %s wheel speaks again", self, w.name)
                w.stale = is_stale
                if is_stale:
                    stale.append(f"{w.name} wheel stale")
        if silent:
            stale = ["bus silent"]
        degraded = bool(stale)
        detail = ", ".join(stale)
        if degraded == self._degraded and detail == self._detail:
            return None
        changed = degraded != self._degraded
        self._degraded, self._detail = degraded, detail
        if not changed:
            return None
        if not degraded:
            logger.info("%s: odometry no longer degraded", self)
        return BaseStatus(receipt_ns, degraded, detail)


def open_can(config: Any, clock: Clock) -> CanBaseDriver:
    """The registry's factory of ``("base", "can")``.

    ``config`` is the whole :class:`~robotd.base.config.Config`: the driver needs ``[can]``
    and ``[robot]`` (the wheel geometry that turns the wheels' turns into the odometry's
    ticks). Raises :class:`ConfigError` for a DBC or signal that does not exist and
    :class:`DriverError` when the bus cannot be opened.
    """
    c, robot = config.can, config.robot
    db = load_dbc(c.dbc)
    label = f"CAN bus {c.interface}:{c.channel} ({dbc_path(c.dbc).name})"
    try:
        bus = can.Bus(interface=c.interface, channel=c.channel)
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        raise DriverError(f"cannot open {label}: {exc}") from exc
    try:
        driver = CanBaseDriver(
            bus, clock, db, left=c.left, right=c.right, wheel_unit=c.wheel_unit,
            left_scale=c.left_scale, right_scale=c.right_scale, yaw=c.yaw, yaw_unit=c.yaw_unit,
            yaw_scale=c.yaw_scale, ticks_per_rev=robot.ticks_per_rev,
            wheel_radius_m=robot.wheel_radius_m, period_s=c.period_s,
            stale_periods=c.stale_periods, max_frames_per_read=c.max_frames_per_read, label=label)
    except BaseException:
        bus.shutdown()
        raise
    logger.info("opened %s", label)
    return driver
