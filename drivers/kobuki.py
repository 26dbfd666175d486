"""Kobuki (TurtleBot 2 base) serial protocol and driver.

The base talks 115200 8N1. Every packet, in both directions, is::

    AA 55 | LEN | payload (LEN bytes) | CS        CS = LEN ^ payload[0] ^ ... ^ payload[-1]

and the payload is a chain of sub-payloads ``[id u8, len u8, data (len bytes)]`` with
little-endian fields. Layouts follow the Kobuki protocol specification (kobuki_driver
documentation, "Appendix: Protocol Specification") and kobuki_core's packet classes:

======  =================  ==========================================================
id      feedback           data
======  =================  ==========================================================
1       basic sensor data  15 B: u16 timestamp ms, u8 bumper, u8 wheel drop, u8 cliff,
                           u16 left/right encoder, s8 left/right PWM, u8 buttons,
                           u8 charger, u8 battery (0.1 V), u8 overcurrent
4       inertial           7 B: s16 angle (0.01 deg), s16 rate (0.01 deg/s), 3 unused
10, 11  hw / fw version    4 B: u8 patch, u8 minor, u8 major, u8 0
13      raw 3-axis gyro    2 + 6N B: u8 frame id, u8 followed length (= 3N, a count of
                           16-bit values), N x (s16 x, s16 y, s16 z) at 0.00875 deg/s per
                           digit; the gyro frame is the robot frame turned 90 deg about z,
                           so the robot's yaw rate is +z
19      UDID               12 B: u32 udid0, udid1, udid2
======  =================  ==========================================================

Commands: base control (id 1: s16 speed mm/s, s16 radius mm) and request extra (id 9:
u16 flags, 0x01 hardware version, 0x02 firmware version, 0x08 UDID).

The module has four layers, each usable alone: sub-payload dataclasses with ``encode()``
(so the virtual robot can speak real bytes), framing (:func:`encode_packet`,
:class:`PacketParser`), decoding (:func:`decode_feedback`, :func:`decode_commands`), and
:class:`KobukiDriver`, which turns a pyserial URL into :class:`~robotd.messages.WheelTicks`
and :class:`~robotd.messages.YawRate`. :func:`main` decodes a capture file to JSON lines.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import functools
import json
import logging
import math
import operator
import re
import struct
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, TextIO, Union

import numpy as np
import serial

from robotd.clock import Clock
from robotd.errors import DriverError, RobotdError
from robotd.messages import WheelTicks, YawRate

logger = logging.getLogger(__name__)

HEADER = b"\xaa\x55"
BAUDRATE = 115200
LINE_RATE_BYTES_PER_S = BAUDRATE // 10  # 8N1: 10 bits on the wire per byte
MIN_PAYLOAD_LEN = 3  # the smallest sub-payload: id, len, one data byte
WHEELBASE_M = 0.23
GYRO_DPS_PER_DIGIT = 0.00875  # L3G4200D at 250 deg/s full scale
_DEG = math.pi / 180.0


def _pack(st: struct.Struct, *values: int) -> bytes:
    try:
        return st.pack(*values)
    except struct.error as exc:
        raise ValueError(f"value out of range for the Kobuki protocol: {exc}") from None


def _subpayload(sub_id: int, data: bytes) -> bytes:
    if len(data) > 255:
        raise ValueError(f"sub-payload {sub_id} data is {len(data)} bytes, at most 255 fit")
    return bytes((sub_id, len(data))) + data


# --------------------------------------------------------------------------------------
# Sub-payloads (raw protocol units)
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class BasicSensorData:
    """Feedback id 1: the core sensors, sent in every packet at 50 Hz.

    ``timestamp_ms`` and the encoders are 16-bit counters that wrap at 65536; encoder
    ticks increase when the wheel turns forward. Bit flags: bumper 0x01 right, 0x02
    centre, 0x04 left; wheel drop 0x01 right, 0x02 left; cliff as bumper; overcurrent 0x01
    left, 0x02 right. PWMs are signed (negative = backwards).
    """

    ID: ClassVar[int] = 1
    NAME: ClassVar[str] = "basic_sensor_data"
    _ST: ClassVar[struct.Struct] = struct.Struct("<HBBBHHbbBBBB")

    timestamp_ms: int
    bumper: int
    wheel_drop: int
    cliff: int
    left_encoder: int
    right_encoder: int
    left_pwm: int
    right_pwm: int
    buttons: int
    charger: int
    battery_decivolts: int
    overcurrent: int

    def encode(self) -> bytes:
        """The sub-payload bytes ``[1, 15, data]``."""
        return _subpayload(self.ID, _pack(self._ST, *dataclasses.astuple(self)))


@dataclass(frozen=True, slots=True)
class InertialData:
    """Feedback id 4: the factory-calibrated single-axis gyro.

    ``angle_centideg`` is the integrated heading in 0.01 deg, ``angle_rate_centidegps``
    the yaw rate in 0.01 deg/s, both counter-clockwise positive; ``unused`` keeps the three
    trailing bytes so a decode/encode round trip is byte-exact.
    """

    ID: ClassVar[int] = 4
    NAME: ClassVar[str] = "inertial"
    _ST: ClassVar[struct.Struct] = struct.Struct("<hh3s")

    angle_centideg: int
    angle_rate_centidegps: int
    unused: bytes = b"\x00\x00\x00"

    def encode(self) -> bytes:
        """The sub-payload bytes ``[4, 7, data]``."""
        if len(self.unused) != 3:
            raise ValueError("InertialData.unused must be 3 bytes")
        return _subpayload(self.ID, _pack(self._ST, self.angle_centideg,
                                          self.angle_rate_centidegps, self.unused))


@dataclass(frozen=True, slots=True)
class RawGyroData:
    """Feedback id 13: raw samples of the 3-axis gyro (2-3 per packet: it runs at 100 Hz).

    ``samples`` holds ``(x, y, z)`` signed raw digits in the gyro's own axes,
    :data:`GYRO_DPS_PER_DIGIT` deg/s per digit. The gyro is mounted turned 90 deg
    counter-clockwise about z, so robot x = -gyro y, robot y = gyro x, robot z = gyro z.
    ``frame_id`` counts the first sample (wraps at 256).
    """

    ID: ClassVar[int] = 13
    NAME: ClassVar[str] = "raw_gyro"

    frame_id: int
    samples: tuple[tuple[int, int, int], ...]

    def encode(self) -> bytes:
        """The sub-payload bytes ``[13, 2 + 6N, frame_id, 3N, x0, y0, z0, ...]``."""
        values = [v for sample in self.samples for v in sample]
        if len(values) != 3 * len(self.samples):
            raise ValueError("RawGyroData samples must be (x, y, z) triples")
        head = _pack(_U8U8, self.frame_id, len(values))
        return _subpayload(self.ID, head + _pack(_s16_struct(len(values)), *values))


@dataclass(frozen=True, slots=True)
class HardwareVersion:
    """Feedback id 10, sent on request: hardware version ``major.minor.patch``."""

    ID: ClassVar[int] = 10
    NAME: ClassVar[str] = "hardware_version"
    _ST: ClassVar[struct.Struct] = struct.Struct("<BBBx")

    major: int
    minor: int
    patch: int

    def encode(self) -> bytes:
        """The sub-payload bytes ``[10, 4, patch, minor, major, 0]``."""
        return _encode_version(self)


@dataclass(frozen=True, slots=True)
class FirmwareVersion:
    """Feedback id 11, sent on request: firmware version ``major.minor.patch``."""

    ID: ClassVar[int] = 11
    NAME: ClassVar[str] = "firmware_version"
    _ST: ClassVar[struct.Struct] = struct.Struct("<BBBx")

    major: int
    minor: int
    patch: int

    def encode(self) -> bytes:
        """The sub-payload bytes ``[11, 4, patch, minor, major, 0]``."""
        return _encode_version(self)


def _encode_version(v: HardwareVersion | FirmwareVersion) -> bytes:
    return _subpayload(v.ID, _pack(v._ST, v.patch, v.minor, v.major))


@dataclass(frozen=True, slots=True)
class UniqueDeviceId:
    """Feedback id 19, sent on request: the base's unique id, ``udid0-udid1-udid2``."""

    ID: ClassVar[int] = 19
    NAME: ClassVar[str] = "udid"
    _ST: ClassVar[struct.Struct] = struct.Struct("<III")

    udid0: int
    udid1: int
    udid2: int

    def encode(self) -> bytes:
        """The sub-payload bytes ``[19, 12, data]``."""
        return _subpayload(self.ID, _pack(self._ST, self.udid0, self.udid1, self.udid2))


@dataclass(frozen=True, slots=True)
class BaseControl:
    """Command id 1: drive along an arc of ``radius_mm`` at ``speed_mm_s``.

    Radius 0 means straight; radius 1 means turn on the spot, ``speed_mm_s`` being the
    wheel speed (positive = counter-clockwise). See :func:`base_control_from_twist`.
    """

    ID: ClassVar[int] = 1
    NAME: ClassVar[str] = "base_control"
    _ST: ClassVar[struct.Struct] = struct.Struct("<hh")

    speed_mm_s: int
    radius_mm: int

    def encode(self) -> bytes:
        """The sub-payload bytes ``[1, 4, speed, radius]``."""
        return _subpayload(self.ID, _pack(self._ST, self.speed_mm_s, self.radius_mm))


@dataclass(frozen=True, slots=True)
class RequestExtra:
    """Command id 9: ask for version answers; ``flags`` keeps unknown bits as sent."""

    ID: ClassVar[int] = 9
    NAME: ClassVar[str] = "request_extra"
    HARDWARE_VERSION: ClassVar[int] = 0x01
    FIRMWARE_VERSION: ClassVar[int] = 0x02
    UDID: ClassVar[int] = 0x08
    _ST: ClassVar[struct.Struct] = struct.Struct("<H")

    flags: int

    @property
    def hardware_version(self) -> bool:
        return bool(self.flags & self.HARDWARE_VERSION)

    @property
    def firmware_version(self) -> bool:
        return bool(self.flags & self.FIRMWARE_VERSION)

    @property
    def udid(self) -> bool:
        return bool(self.flags & self.UDID)

    def encode(self) -> bytes:
        """The sub-payload bytes ``[9, 2, flags]``."""
        return _subpayload(self.ID, _pack(self._ST, self.flags))


@dataclass(frozen=True, slots=True)
class UnknownSubPayload:
    """A sub-payload whose id this module does not decode, kept verbatim."""

    NAME: ClassVar[str] = "unknown"

    id: int
    data: bytes

    def encode(self) -> bytes:
        return _subpayload(self.id, self.data)


FeedbackSubPayload = Union[BasicSensorData, InertialData, RawGyroData, HardwareVersion,
                           FirmwareVersion, UniqueDeviceId, UnknownSubPayload]
CommandSubPayload = Union[BaseControl, RequestExtra, UnknownSubPayload]

_U8U8 = struct.Struct("<BB")


@functools.lru_cache(maxsize=None)
def _s16_struct(count: int) -> struct.Struct:
    return struct.Struct(f"<{count}h")


# Decoders: (payload, start, length) -> instance, or None when the length is wrong.
def _fixed(cls, size: int):
    st = cls._ST

    def decode(payload: bytes, start: int, length: int):
        return cls(*st.unpack_from(payload, start)) if length == size else None
    return decode


def _decode_raw_gyro(payload: bytes, start: int, length: int) -> RawGyroData | None:
    if length < 2:
        return None
    frame_id, count = payload[start], payload[start + 1]
    if count % 3 or length != 2 + 2 * count:
        return None
    v = _s16_struct(count).unpack_from(payload, start + 2)
    return RawGyroData(frame_id, tuple(zip(v[0::3], v[1::3], v[2::3])))


def _decode_version(cls):
    def decode(payload: bytes, start: int, length: int):
        if length != 4:
            return None
        patch, minor, major = payload[start:start + 3]
        return cls(major, minor, patch)
    return decode


_FEEDBACK_DECODERS = {
    BasicSensorData.ID: _fixed(BasicSensorData, 15),
    InertialData.ID: _fixed(InertialData, 7),
    RawGyroData.ID: _decode_raw_gyro,
    HardwareVersion.ID: _decode_version(HardwareVersion),
    FirmwareVersion.ID: _decode_version(FirmwareVersion),
    UniqueDeviceId.ID: _fixed(UniqueDeviceId, 12),
}
_COMMAND_DECODERS = {
    BaseControl.ID: _fixed(BaseControl, 4),
    RequestExtra.ID: _fixed(RequestExtra, 2),
}


# --------------------------------------------------------------------------------------
# Framing
# --------------------------------------------------------------------------------------


def encode_packet(payload: bytes) -> bytes:
    """Frame ``payload`` as ``AA 55 LEN payload CS``; 3 <= len(payload) <= 255."""
    n = len(payload)
    if not MIN_PAYLOAD_LEN <= n <= 255:
        raise ValueError(f"a Kobuki payload is 3..255 bytes, not {n}")
    cs = functools.reduce(operator.xor, payload, n)
    return HEADER + bytes((n,)) + bytes(payload) + bytes((cs,))


def encode_feedback(*subpayloads: FeedbackSubPayload) -> bytes:
    """A full feedback packet carrying ``subpayloads`` in order."""
    return encode_packet(b"".join(s.encode() for s in subpayloads))


def encode_commands(*commands: CommandSubPayload) -> bytes:
    """A full command packet carrying ``commands`` in order."""
    return encode_packet(b"".join(c.encode() for c in commands))


def encode_base_control(speed_mm_s: int, radius_mm: int) -> bytes:
    """A full base-control command packet (see :class:`BaseControl`)."""
    return encode_commands(BaseControl(speed_mm_s, radius_mm))


def encode_request_extra(hardware_version: bool = True, firmware_version: bool = True,
                         udid: bool = True) -> bytes:
    """A full request-extra command packet asking for the chosen version answers."""
    flags = ((RequestExtra.HARDWARE_VERSION if hardware_version else 0)
             | (RequestExtra.FIRMWARE_VERSION if firmware_version else 0)
             | (RequestExtra.UDID if udid else 0))
    return encode_commands(RequestExtra(flags))


@dataclass(slots=True)
class ParserStats:
    """Counters of a :class:`PacketParser` (and of :func:`decode_feedback` given them).

    Every byte fed ends up in exactly one place, so
    ``bytes_in == packet_bytes + garbage_bytes + bytes still buffered``.

    - ``packets``: valid packets returned; ``packet_bytes``: their bytes, framing included.
    - ``garbage_bytes``: bytes dropped outside valid packets, including the two header
      bytes of every rejected candidate (its remaining bytes are rescanned).
    - ``bad_checksums`` / ``truncated``: rejected candidates, each counted once. A header
      whose declared packet fails the checksum counts as ``truncated`` when another
      header starts inside the declared span (the packet was cut short by a new one),
      else as ``bad_checksums``. The 8-bit checksum passes 1 in 256 corrupt packets, so a
      checksum-valid packet with another header inside is still rejected as
      ``truncated`` when its sub-payload chain does not end exactly at its length or the
      inner header starts a valid packet. At :meth:`PacketParser.finish`
      a header whose declared packet runs past the end of the data is ``truncated`` too.
      A header with LEN < 3 is not a header: its bytes are garbage.
    - ``unknown_subpayloads`` / ``malformed_subpayloads``: counted by the decoders.
    """

    bytes_in: int = 0
    packets: int = 0
    packet_bytes: int = 0
    garbage_bytes: int = 0
    bad_checksums: int = 0
    truncated: int = 0
    unknown_subpayloads: int = 0
    malformed_subpayloads: int = 0

    def copy(self) -> ParserStats:
        return dataclasses.replace(self)


def _chain_ends_at(buf: bytes, start: int, stop: int) -> bool:
    """True when the sub-payloads in ``buf[start:stop]`` chain exactly to ``stop``."""
    k = start
    while k + 2 <= stop:
        k += 2 + buf[k + 1]
    return k == stop


def _overlaps_next(buf: bytes, px: bytes, i: int, end: int, j: int, final: bool) -> bool | None:
    """For a checksum-valid candidate ``buf[i:end]`` with another header at ``j`` inside:
    is it really a packet cut short by the next one that passed the 8-bit checksum by
    chance (1 in 256)? Yes if its sub-payload chain does not end at its end, or if a
    header inside it starts a complete packet with a valid checksum and chain. ``None``
    when such an inner packet is not complete yet (and more data may come)."""
    if not _chain_ends_at(buf, i + 3, end - 1):
        return True
    n = len(buf)
    while j >= 0:
        if j + 2 >= n:
            if not final:
                return None
        elif buf[j + 2] >= MIN_PAYLOAD_LEN:
            end_j = j + 4 + buf[j + 2]
            if end_j > n:
                if not final:
                    return None
            elif px[end_j - 1] == px[j + 1] and _chain_ends_at(buf, j + 3, end_j - 1):
                return True
        j = buf.find(HEADER, j + 2, end)
    return False


class PacketParser:
    """Incremental packet finder: bytes in, payloads of valid packets out.

    It never raises on bad input and never loses a valid packet behind garbage: a rejected
    candidate is skipped by its two header bytes only, so a packet hidden inside it is
    found on the rescan. Headers are found with ``bytes.find`` and checksums come from one
    vectorised prefix XOR per :meth:`feed`, so the per-byte work on good data is in C.
    An incomplete packet at the end of the data waits for the next :meth:`feed` (at most
    258 bytes); call :meth:`finish` at the end of a stream to flush it.
    """

    def __init__(self) -> None:
        self.stats = ParserStats()
        #: Stream offsets (bytes since creation) of the headers of the packets returned by
        #: the latest :meth:`feed` or :meth:`finish`.
        self.last_offsets: list[int] = []
        self._rest = b""
        self._rest_offset = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Add ``data``; return the payloads (without LEN and CS) of completed packets."""
        return self._scan(bytes(data), final=False)

    def finish(self) -> list[bytes]:
        """End of stream: settle the buffered bytes and return any packet they hide."""
        return self._scan(b"", final=True)

    def _scan(self, data: bytes, final: bool) -> list[bytes]:
        st = self.stats
        st.bytes_in += len(data)
        buf = self._rest + data if self._rest else data
        n = len(buf)
        base = self._rest_offset
        find = buf.find
        payloads: list[bytes] = []
        offsets: list[int] = []
        px = None
        pos = 0
        while True:
            i = find(HEADER, pos)
            if i < 0:
                # a trailing 0xAA may be the first half of a header split across feeds
                stop = n - 1 if (not final and n > pos and buf[n - 1] == 0xAA) else n
                st.garbage_bytes += stop - pos
                pos = stop
                break
            st.garbage_bytes += i - pos
            if i + 2 < n and buf[i + 2] < MIN_PAYLOAD_LEN:
                st.garbage_bytes += 2  # not a header
                pos = i + 2
                continue
            end = i + 4 + buf[i + 2] if i + 2 < n else n + 1
            if end > n:
                if not final:
                    pos = i
                    break
                st.truncated += 1
                st.garbage_bytes += 2
                pos = i + 2
                continue
            if px is None:
                px = np.bitwise_xor.accumulate(np.frombuffer(buf, dtype=np.uint8)).tobytes()
            inner = find(HEADER, i + 2, end)
            if px[end - 1] != px[i + 1]:
                overlapped: bool | None = inner >= 0
                accepted = False
            else:
                overlapped = inner >= 0 and _overlaps_next(buf, px, i, end, inner, final)
                accepted = overlapped is False
            if overlapped is None:  # cannot tell before the next packet is complete
                pos = i
                break
            if accepted:
                payloads.append(buf[i + 3:end - 1])
                offsets.append(base + i)
                st.packets += 1
                st.packet_bytes += end - i
                pos = end
            else:
                if overlapped:
                    st.truncated += 1
                else:
                    st.bad_checksums += 1
                st.garbage_bytes += 2
                pos = i + 2
        self._rest = buf[pos:]
        self._rest_offset = base + pos
        self.last_offsets = offsets
        return payloads


def _decode_chain(payload: bytes, decoders: dict, stats: ParserStats | None) -> list:
    out = []
    n = len(payload)
    k = 0
    while k < n:
        if k + 2 > n or k + 2 + payload[k + 1] > n:
            if stats is not None:
                stats.malformed_subpayloads += 1
            logger.debug("sub-payload at %d runs past a %d-byte payload", k, n)
            break
        sub_id, length = payload[k], payload[k + 1]
        decode = decoders.get(sub_id)
        if decode is None:
            out.append(UnknownSubPayload(sub_id, payload[k + 2:k + 2 + length]))
            if stats is not None:
                stats.unknown_subpayloads += 1
        else:
            item = decode(payload, k + 2, length)
            if item is None:
                if stats is not None:
                    stats.malformed_subpayloads += 1
                logger.debug("sub-payload id %d has a wrong length %d", sub_id, length)
                break
            out.append(item)
        k += 2 + length
    return out


def decode_feedback(payload: bytes, stats: ParserStats | None = None) -> list[FeedbackSubPayload]:
    """Decode a feedback payload into sub-payload dataclasses, in order.

    Unknown ids are skipped by their length and returned as :class:`UnknownSubPayload`. A
    sub-payload that runs past the payload, or a known id with a wrong length, ends the
    decoding of this payload (what came before is kept). ``stats``, if given, counts both.
    Never raises on bad bytes.
    """
    return _decode_chain(bytes(payload), _FEEDBACK_DECODERS, stats)


def decode_commands(payload: bytes, stats: ParserStats | None = None) -> list[CommandSubPayload]:
    """Decode a command payload (what the daemon sends) like :func:`decode_feedback`."""
    return _decode_chain(bytes(payload), _COMMAND_DECODERS, stats)


# --------------------------------------------------------------------------------------
# Kinematics of the base-control command
# --------------------------------------------------------------------------------------


def _bound_s16(value: float) -> int:
    return max(-32768, min(32767, round(value)))


def base_control_from_twist(v_mps: float, w_radps: float,
                            wheelbase_m: float = WHEELBASE_M) -> tuple[int, int]:
    """Body twist -> ``(speed_mm_s, radius_mm)`` the way kobuki_core's DiffDrive does it.

    Straight (|w| < 1e-4): radius 0, speed = v. Turning on the spot (|v| < 1e-4 or
    |radius| <= 1 mm): radius 1, speed = w * wheelbase / 2 (the wheel speed). Otherwise
    radius = v / w and speed = (radius +- wheelbase / 2) * w, the sign following radius:
    the speed of the outer wheel. Values are rounded (kobuki_core truncates) and bounded
    to int16.
    """
    eps = 1e-4
    if abs(w_radps) < eps:
        return _bound_s16(1000.0 * v_mps), 0
    radius_mm = 1000.0 * v_mps / w_radps
    if abs(v_mps) < eps or abs(radius_mm) <= 1.0:
        return _bound_s16(1000.0 * wheelbase_m * w_radps / 2.0), 1
    half_mm = math.copysign(500.0 * wheelbase_m, radius_mm)
    return _bound_s16((radius_mm + half_mm) * w_radps), _bound_s16(radius_mm)


def twist_from_base_control(speed_mm_s: int, radius_mm: int,
                            wheelbase_m: float = WHEELBASE_M) -> tuple[float, float]:
    """Inverse of :func:`base_control_from_twist`: ``(v_mps, w_radps)``; radius +-1 turns
    on the spot."""
    if radius_mm == 0:
        return speed_mm_s / 1000.0, 0.0
    if radius_mm in (1, -1):
        return 0.0, 2.0 * speed_mm_s / (1000.0 * wheelbase_m)
    radius_m = radius_mm / 1000.0
    w_radps = (speed_mm_s / 1000.0) / (radius_m + math.copysign(wheelbase_m / 2.0, radius_m))
    return radius_m * w_radps, w_radps


# --------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class KobukiDriverStats:
    """A snapshot of a driver's counters.

    ``clock_clamps`` counts packets whose mapped stamp would have gone back in time and
    was raised to the previous stamp; ``untimed_packets`` counts packets without basic
    sensor data, stamped with their receipt time.
    """

    parser: ParserStats
    messages_out: int
    clock_clamps: int
    untimed_packets: int
    commands_sent: int

    def as_dict(self) -> dict[str, int]:
        """Every counter in one flat mapping (parser counters first), for JSON and STATUS."""
        d = dataclasses.asdict(self.parser)
        d.update(messages_out=self.messages_out, clock_clamps=self.clock_clamps,
                 untimed_packets=self.untimed_packets, commands_sent=self.commands_sent)
        return d


class KobukiDriver:
    """A Kobuki base on any pyserial URL (``/dev/kobuki``, a pty path, ``loop://``).

    :meth:`read` returns one :class:`~robotd.messages.WheelTicks` per basic-sensor
    sub-payload and one :class:`~robotd.messages.YawRate` per packet, both stamped with the
    packet's device time mapped to ``clock``: the 16-bit millisecond timestamp is
    unwrapped (the number of 65.536 s wraps that best matches the host time elapsed since
    the previous read, so a long silence is not mistaken for a short one), and
    ``stamp = device time + offset`` with ``offset`` the minimum of ``receipt time -
    device time`` over the last ``offset_window_s`` of device time: the packet that
    travelled fastest sets the offset, transport delay and batching drop out, and the
    window lets the offset follow clock drift. Packets read together share their receipt
    time, so the whole batch enters the window before any of it is stamped. Stamps never
    go backwards (clamped and counted).

    ``yaw_source`` is ``"raw_gyro"`` (the mean yaw axis of the packet's raw 3-axis gyro
    samples, falling back to the inertial rate when a packet has none) or ``"inertial"``.
    """

    def __init__(self, url: str, clock: Clock, *, yaw_source: str = "raw_gyro",
                 wheelbase_m: float = WHEELBASE_M, offset_window_s: float = 10.0,
                 gyro_dps_per_digit: float = GYRO_DPS_PER_DIGIT,
                 timeout_s: float = 0.1, baudrate: int = BAUDRATE) -> None:
        if yaw_source not in ("raw_gyro", "inertial"):
            raise ValueError(f"yaw_source must be 'raw_gyro' or 'inertial', not {yaw_source!r}")
        self._url = url
        self._clock = clock
        self._yaw_source = yaw_source
        self._wheelbase_m = wheelbase_m
        self._window_ns = int(offset_window_s * 1e9)
        self._gyro_radps_per_digit = gyro_dps_per_digit * _DEG
        self._parser = PacketParser()
        self._window: collections.deque[tuple[int, int]] = collections.deque()
        self._last_raw_ms: int | None = None
        self._device_ms = 0
        self._last_receipt_ns = 0
        self._last_stamp_ns: int | None = None
        self._messages_out = 0
        self._clock_clamps = 0
        self._untimed_packets = 0
        self._commands_sent = 0
        try:
            self._serial = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s,
                                                 exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DriverError(f"cannot open Kobuki port {url}: {exc}") from exc
        logger.info("opened Kobuki port %s", url)

    def __enter__(self) -> KobukiDriver:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @property
    def port(self) -> serial.SerialBase:
        """The underlying pyserial port (tests write feedback into ``loop://`` with it)."""
        return self._open_port()

    def close(self) -> None:
        """Close the port; safe to call more than once."""
        port, self._serial = self._serial, None
        if port is not None:
            port.close()
            logger.info("closed Kobuki port %s", self._url)

    @property
    def stats(self) -> KobukiDriverStats:
        return KobukiDriverStats(self._parser.stats.copy(), self._messages_out,
                                 self._clock_clamps, self._untimed_packets, self._commands_sent)

    def _open_port(self) -> serial.SerialBase:
        if self._serial is None:
            raise DriverError(f"Kobuki port {self._url} is closed")
        return self._serial

    def read(self, timeout_s: float) -> list[WheelTicks | YawRate]:
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

    def _convert(self, packets: list[list[FeedbackSubPayload]],
                 receipt_ns: int) -> list[WheelTicks | YawRate]:
        device_ns: list[int | None] = []
        for items in packets:
            basic = next((s for s in items if type(s) is BasicSensorData), None)
            if basic is None:
                device_ns.append(None)
                continue
            dev = self._unwrap_ms(basic.timestamp_ms, receipt_ns) * 1_000_000
            self._push_offset(dev, receipt_ns - dev)
            device_ns.append(dev)
        out: list[WheelTicks | YawRate] = []
        for items, dev in zip(packets, device_ns):
            if dev is None:
                self._untimed_packets += 1
                stamp = receipt_ns
            else:
                stamp = dev + self._window[0][1]
            if self._last_stamp_ns is not None and stamp < self._last_stamp_ns:
                self._clock_clamps += 1
                stamp = self._last_stamp_ns
            self._last_stamp_ns = stamp
            gyro_z: list[int] = []
            inertial = None
            for s in items:
                if type(s) is BasicSensorData:
                    out.append(WheelTicks(stamp, s.left_encoder, s.right_encoder, s.timestamp_ms))
                elif type(s) is RawGyroData:
                    gyro_z.extend(z for _, _, z in s.samples)
                elif type(s) is InertialData:
                    inertial = s
            if self._yaw_source == "raw_gyro" and gyro_z:
                rate = sum(gyro_z) / len(gyro_z) * self._gyro_radps_per_digit
                out.append(YawRate(stamp, rate, "raw_gyro"))
            elif inertial is not None:
                out.append(YawRate(stamp, inertial.angle_rate_centidegps / 100.0 * _DEG,
                                   "inertial"))
        self._messages_out += len(out)
        return out

    def _unwrap_ms(self, raw_ms: int, receipt_ns: int) -> int:
        if self._last_raw_ms is None:
            self._device_ms = raw_ms
        else:
            delta = (raw_ms - self._last_raw_ms) & 0xFFFF
            elapsed_ms = (receipt_ns - self._last_receipt_ns) / 1e6
            wraps = max(0, round((elapsed_ms - delta) / 65536.0))
            self._device_ms += delta + 65536 * wraps
        self._last_raw_ms = raw_ms
        self._last_receipt_ns = receipt_ns
        return self._device_ms

    def _push_offset(self, device_ns: int, candidate_ns: int) -> None:
        # sliding-window minimum: a deque of increasing candidates (Lemire's algorithm)
        w = self._window
        while w and w[-1][1] >= candidate_ns:
            w.pop()
        w.append((device_ns, candidate_ns))
        horizon = device_ns - self._window_ns
        while w[0][0] < horizon:
            w.popleft()

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


# --------------------------------------------------------------------------------------
# Capture decoding (``robotd kobuki decode CAPTURE``)
# --------------------------------------------------------------------------------------

_ANSI = re.compile(rb"\x1b\[[0-9;]*m")
_SPY_START = re.compile(rb"(?:\x1b\[[0-9;]*m)*\d{6,}\.\d{3} \S")
# pyserial spy:// hexdump line: "{time:010.3f} RX   {offset:04X}  {16 x 'HH '}{' ' at 8} {ascii}"
_SPY_RX = re.compile(rb"\d+\.\d{3} RX   [0-9A-F]{4,}  (.*)")
_SPY_HEX_WIDTH = 16 * 3 + 1


def _spy_rx_bytes(text: bytes) -> bytes:
    """The received bytes of a pyserial ``spy://`` hexdump, in order (TX and control
    lines are skipped; the ASCII column is cut off by its fixed position)."""
    chunks = []
    for line in text.splitlines():
        m = _SPY_RX.match(_ANSI.sub(b"", line))
        if m:
            chunks.append(bytes.fromhex(m.group(1)[:_SPY_HEX_WIDTH].decode("ascii")))
    return b"".join(chunks)


def detect_capture_format(data: bytes) -> str:
    """``"spy"`` when ``data`` starts like a pyserial ``spy://`` hexdump, else ``"raw"``."""
    return "spy" if _SPY_START.match(data) else "raw"


def _subpayload_dict(item: FeedbackSubPayload) -> dict:
    d: dict = {"type": item.NAME, "id": item.id if isinstance(item, UnknownSubPayload) else item.ID}
    for f in dataclasses.fields(item):
        value = getattr(item, f.name)
        if f.name != "id":
            d[f.name] = value.hex() if isinstance(value, bytes) else value
    return d


def decode_capture(data: bytes, fmt: str = "auto") -> Iterator[dict]:
    """Decode a capture of the Kobuki's output into one dict per valid packet.

    ``fmt`` is ``"raw"`` (the bytes as read from the port), ``"spy"`` (the text pyserial's
    ``spy://`` URL writes; only RX lines count) or ``"auto"``. Each dict has ``packet``
    (index), ``offset`` (byte offset of its header in the received stream) and
    ``subpayloads``; ``malformed`` appears when a sub-payload ended its decoding. The last
    dict is ``{"summary": {...}}`` with the format and the counters of
    :class:`ParserStats`.
    """
    if fmt == "auto":
        fmt = detect_capture_format(data)
    if fmt not in ("raw", "spy"):
        raise ValueError(f"unknown capture format {fmt!r}")
    stream = _spy_rx_bytes(data) if fmt == "spy" else data
    parser = PacketParser()
    stats = parser.stats
    index = 0
    chunk = 1 << 16
    for start in range(0, len(stream) + 1, chunk):
        last = start + chunk > len(stream)
        payloads = parser.feed(stream[start:start + chunk])
        offsets = parser.last_offsets
        if last:
            payloads += parser.finish()
            offsets = offsets + parser.last_offsets
        for offset, payload in zip(offsets, payloads):
            malformed = stats.malformed_subpayloads
            items = decode_feedback(payload, stats)
            record: dict = {"packet": index, "offset": offset,
                            "subpayloads": [_subpayload_dict(s) for s in items]}
            if stats.malformed_subpayloads != malformed:
                record["malformed"] = True
            index += 1
            yield record
    yield {"summary": {"format": fmt, **dataclasses.asdict(stats)}}


def add_decode_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the capture decoder's arguments to ``parser`` (for ``robotd kobuki decode``)."""
    parser.add_argument("capture", type=Path,
                        help="raw serial capture, or a pyserial spy:// hexdump")
    parser.add_argument("--out", type=Path, default=None,
                        help="write the JSON lines to this file (default: stdout)")
    parser.add_argument("--format", choices=("auto", "raw", "spy"), default="auto",
                        help="capture format (default: detect)")


def run_decode(args: argparse.Namespace, stdout: TextIO | None = None) -> int:
    """Decode ``args.capture`` to JSON lines; raises :class:`DriverError` on I/O errors."""
    try:
        data = args.capture.read_bytes()
    except OSError as exc:
        raise DriverError(f"cannot read capture {args.capture}: {exc.strerror}") from exc
    try:
        out = open(args.out, "w", encoding="utf-8") if args.out else (stdout or sys.stdout)
    except OSError as exc:
        raise DriverError(f"cannot write {args.out}: {exc.strerror}") from exc
    try:
        for record in decode_capture(data, args.format):
            out.write(json.dumps(record) + "\n")
    finally:
        if args.out:
            out.close()
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m drivers.kobuki CAPTURE [--out FILE]``: decode a capture to JSON lines."""
    parser = argparse.ArgumentParser(prog="robotd kobuki decode",
                                     description="Decode a Kobuki serial capture to JSON lines.")
    add_decode_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run_decode(args)
    except RobotdError as exc:
        print(f"robotd: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
