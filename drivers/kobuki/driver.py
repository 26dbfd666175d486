"""The Kobuki driver: a pyserial URL in, stamped WheelTicks and YawRate out.
"""

from __future__ import annotations

import dataclasses
import logging

import serial

from drivers.base import Driver, Message, StatValue
from drivers.kobuki.protocol import (
    _DEG,
    BAUDRATE,
    GYRO_DPS_PER_DIGIT,
    WHEELBASE_M,
    BasicSensorData,
    FeedbackSubPayload,
    InertialData,
    PacketParser,
    RawGyroData,
    base_control_from_twist,
    decode_feedback,
    encode_base_control,
    encode_request_extra,
)
from drivers.timesync import CounterUnwrapper, OffsetMapper
from robotd.base.clock import Clock
from robotd.base.config import BaseConfig
from robotd.base.errors import DriverError
from robotd.base.messages import WheelDrop, WheelTicks, YawRate

logger = logging.getLogger(__name__)

#: The Kobuki's feedback period (50 Hz), device time.
FEEDBACK_PERIOD_NS = 20_000_000


def open_kobuki(section: BaseConfig, clock: Clock) -> KobukiDriver:
    """The registry's factory of ``("base", "kobuki")``: a driver on ``section.port``."""
    return KobukiDriver(section.port, clock, yaw_source=section.yaw_source,
                        baudrate=section.baudrate)


class KobukiDriver(Driver):
    """A Kobuki base on any pyserial URL (``/dev/kobuki``, a pty path, ``loop://``).

    :meth:`read` returns one :class:`~robotd.base.messages.WheelTicks` per basic-sensor
    sub-payload and one :class:`~robotd.base.messages.YawRate` per packet, both stamped with the
    packet's device time mapped to ``clock``: the 16-bit millisecond timestamp is
    unwrapped (the number of 65.536 s wraps that best matches the host time elapsed since
    the previous read, so a long silence is not mistaken for a short one), and
    ``stamp = device time + offset`` with ``offset`` the minimum of ``receipt time -
    device time`` over the last ``offset_window_s`` of device time: the packet that
    travelled fastest sets the offset, transport delay and batching drop out, and the
    window lets the offset follow clock drift. Packets read together share their receipt
    time, so the whole batch enters the window before any of it is stamped. Stamps never
    go backwards (clamped and counted).

    The unwrapping and the offset are :mod:`drivers.timesync`'s
    :class:`~drivers.timesync.CounterUnwrapper` (16 bits, 1 ms) and
    :class:`~drivers.timesync.OffsetMapper`.

    ``yaw_source`` is ``"raw_gyro"`` (the mean yaw axis of the packet's raw 3-axis gyro
    samples, falling back to the inertial rate when a packet has none) or ``"inertial"``.
    A packet carries the raw samples taken since the previous packet, so their mean is the
    yaw rate in the *middle* of that interval: the raw-gyro :class:`YawRate` is stamped
    half the interval (the device time since the previous packet, at most one nominal
    period, ``FEEDBACK_PERIOD_NS``) before the packet, and comes before the packet's
    wheel message. Stamped at the packet itself, the heading lagged by about 10 ms, which
    in a 1 rad/s turn is 0.6 degrees (measured against the virtual robot's truth:
    heading error = -9.9 ms x yaw rate).

    :meth:`stats` adds to the base counters the parser's (``packets``,
    ``garbage_bytes``, ``bad_checksums``, ...), ``clock_clamps`` (packets whose mapped
    stamp would have gone back in time and was raised to the previous stamp),
    ``untimed_packets`` (packets without basic sensor data, stamped with their receipt
    time), ``commands_sent`` and ``wheel_drops`` (times the robot was lifted).

    The wheel-drop bits of the basic sensor data (0x01 right, 0x02 left) are reported when
    they change, as a :class:`~robotd.base.messages.WheelDrop` before that packet's wheel
    message (and at the first packet when a wheel already hangs free): the robot was picked
    up, or put down again.

    A port that fails (a USB adapter pulled, the pty's other end closed) is reopened by
    path with backoff (``initial_backoff_s``, doubling up to ``max_backoff_s``), as
    :mod:`drivers.base` does for every reconnecting driver: meanwhile :meth:`read`
    returns ``[]``, and the time without packets is counted as a gap.
    """

    def __init__(self, url: str, clock: Clock, *, yaw_source: str = "raw_gyro",
                 wheelbase_m: float = WHEELBASE_M, offset_window_s: float = 10.0,
                 gyro_dps_per_digit: float = GYRO_DPS_PER_DIGIT,
                 timeout_s: float = 0.1, baudrate: int = BAUDRATE, name: str = "base",
                 initial_backoff_s: float = 0.5, max_backoff_s: float = 8.0) -> None:
        if yaw_source not in ("raw_gyro", "inertial"):
            raise ValueError(f"yaw_source must be 'raw_gyro' or 'inertial', not {yaw_source!r}")
        super().__init__(name, clock=clock, initial_backoff_s=initial_backoff_s,
                         max_backoff_s=max_backoff_s)
        self._url = url
        self._baudrate = baudrate
        self._timeout_s = timeout_s
        self._serial: serial.SerialBase | None = None
        self._yaw_source = yaw_source
        self._wheelbase_m = wheelbase_m
        self._gyro_radps_per_digit = gyro_dps_per_digit * _DEG
        self._parser = PacketParser()
        self._device_clock = CounterUnwrapper(bits=16, tick_ns=1_000_000)
        self._mapper = OffsetMapper(int(offset_window_s * 1e9))
        self._untimed_packets = 0
        self._commands_sent = 0
        self._prev_device_ns: int | None = None
        self._prev_stamp_ns = 0
        self._wheel_drop: int | None = None
        self._wheel_drops = 0
        self._start()

    def _open_internal(self) -> None:
        try:
            self._serial = serial.serial_for_url(self._url, baudrate=self._baudrate,
                                                 timeout=self._timeout_s, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DriverError(f"cannot open Kobuki port {self._url}: {exc}") from exc
        logger.info("opened Kobuki port %s", self._url)

    def __str__(self) -> str:
        return f"{self.name}: Kobuki port {self._url}"

    @property
    def port(self) -> serial.SerialBase:
        """The underlying pyserial port (tests write feedback into ``loop://`` with it)."""
        return self._open_port()

    def _release_internal(self) -> None:
        port, self._serial = self._serial, None
        if port is not None:
            port.close()
            logger.info("closed Kobuki port %s", self._url)

    def _stats_internal(self) -> dict[str, StatValue]:
        out: dict[str, StatValue] = dict(dataclasses.asdict(self._parser.stats))
        out.update(clock_clamps=self._mapper.clamps, untimed_packets=self._untimed_packets,
                   commands_sent=self._commands_sent, wheel_drops=self._wheel_drops)
        return out

    def _open_port(self) -> serial.SerialBase:
        if self._serial is None:
            state = "closed" if self.closed else "lost (reconnecting)"
            raise DriverError(f"Kobuki port {self._url} is {state}")
        return self._serial

    def _read_internal(self, timeout_s: float) -> list[Message]:
        """Wait up to ``timeout_s`` for bytes, take all that are available, and return the
        messages of the packets they complete (possibly none)."""
        port = self._open_port()
        try:
            if port.timeout != timeout_s:
                port.timeout = timeout_s
            waiting = port.in_waiting
            data = port.read(waiting or 1)
            if data and not waiting:
                more = port.in_waiting
                if more:
                    data += port.read(more)
        except (serial.SerialException, OSError) as exc:
            raise DriverError(f"Kobuki port {self._url} failed: {exc}") from exc
        if not data:
            return []
        receipt_ns = self._clock.now_ns()
        stats = self._parser.stats
        bad_before = stats.bad_checksums + stats.truncated + stats.malformed_subpayloads
        packets = [decode_feedback(p, stats) for p in self._parser.feed(data)]
        messages = self._convert(packets, receipt_ns)
        bad_after = stats.bad_checksums + stats.truncated + stats.malformed_subpayloads
        if bad_after != bad_before:
            logger.debug("Kobuki %s: %d bad packets or sub-payloads in %d bytes",
                         self._url, bad_after - bad_before, len(data))
        return messages

    def _half_interval_ns(self, dev: int | None) -> int:
        """Half the device time since the previous packet (at most one nominal period)."""
        gap = FEEDBACK_PERIOD_NS
        if dev is not None and self._prev_device_ns is not None and dev > self._prev_device_ns:
            gap = min(gap, dev - self._prev_device_ns)
        return gap // 2

    def _wheel_drop_change(self, stamp: int, bits: int) -> WheelDrop | None:
        """A :class:`WheelDrop` when the wheel-drop bits changed (or are set at the start)."""
        bits &= 0x03
        prev, self._wheel_drop = self._wheel_drop, bits
        if bits == (prev if prev is not None else 0):
            return None
        if bits and not prev:
            self._wheel_drops += 1
            logger.warning("Kobuki %s: wheel drop (%s): the robot is lifted", self._url,
                           {1: "right", 2: "left", 3: "both"}[bits])
        elif not bits:
            logger.info("Kobuki %s: both wheels on the floor again", self._url)
        return WheelDrop(stamp, bool(bits), left=bool(bits & 0x02), right=bool(bits & 0x01))

    def _convert(self, packets: list[list[FeedbackSubPayload]],
                 receipt_ns: int) -> list[Message]:
        device_ns: list[int | None] = []
        for items in packets:
            basic = next((s for s in items if type(s) is BasicSensorData), None)
            if basic is None:
                device_ns.append(None)
                continue
            unwrapped = self._device_clock.unwrap(basic.timestamp_ms, receipt_ns)
            self._mapper.observe(unwrapped, receipt_ns)
            device_ns.append(unwrapped)
        out: list[Message] = []
        for items, dev in zip(packets, device_ns):
            if dev is None:
                self._untimed_packets += 1
                stamp = self._mapper.clamp(receipt_ns)
            else:
                stamp = self._mapper.stamp(dev)
            gyro_z: list[int] = []
            inertial = None
            wheels = []
            drop = None
            for s in items:
                if type(s) is BasicSensorData:
                    drop = self._wheel_drop_change(stamp, s.wheel_drop) or drop
                    wheels.append(WheelTicks(stamp, s.left_encoder, s.right_encoder, s.timestamp_ms))
                elif type(s) is RawGyroData:
                    gyro_z.extend(z for _, _, z in s.samples)
                elif type(s) is InertialData:
                    inertial = s
            if self._yaw_source == "raw_gyro" and gyro_z:
                rate = sum(gyro_z) / len(gyro_z) * self._gyro_radps_per_digit
                # never before the previous packet (nor before the clock's zero)
                mid = max(stamp - self._half_interval_ns(dev), self._prev_stamp_ns, 0)
                out.append(YawRate(mid, rate, "raw_gyro"))
            elif inertial is not None:
                out.append(YawRate(stamp, inertial.angle_rate_centidegps / 100.0 * _DEG,
                                   "inertial"))
            if drop is not None:
                out.append(drop)
            out.extend(wheels)
            if dev is not None:
                self._prev_device_ns = dev
            self._prev_stamp_ns = stamp
        return out

    def send_base_control(self, v_mps: float, w_radps: float) -> None:
        """Command a body twist (m/s forward, rad/s counter-clockwise)."""
        speed, radius = base_control_from_twist(v_mps, w_radps, self._wheelbase_m)
        self._write(encode_base_control(speed, radius))

    def request_extra(self, hardware_version: bool = True, firmware_version: bool = True,
                      udid: bool = True) -> None:
        """Ask the base for its version answers (they arrive in later feedback)."""
        self._write(encode_request_extra(hardware_version, firmware_version, udid))

    def _write(self, packet: bytes) -> None:
        port = self._open_port()
        try:
            port.write(packet)
        except (serial.SerialException, OSError) as exc:
            raise DriverError(f"Kobuki port {self._url} failed: {exc}") from exc
        self._commands_sent += 1


