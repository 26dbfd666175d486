"""Kobuki (TurtleBot 2 base) serial protocol: sub-payloads, framing, parser, codecs.

Kobuki (TurtleBot 2 base) serial protocol and driver.

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
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import operator
import struct
from dataclasses import dataclass
from collections.abc import Callable, Mapping
from typing import ClassVar, Optional, TypeVar, Union

import numpy as np

HEADER = b"\xaa\x55"
BAUDRATE = 115200
LINE_RATE_BYTES_PER_S = BAUDRATE // 10  # 8N1: 10 bits on the wire per byte
MIN_PAYLOAD_LEN = 3  # the smallest sub-payload: id, len, one data byte
WHEELBASE_M = 0.23
GYRO_DPS_PER_DIGIT = 0.00875  # L3G4200D at 250 deg/s full scale
_DEG = math.pi / 180.0


def _pack(st: struct.Struct, *values: int | bytes) -> bytes:
    try:
        return st.pack(*values)
    except struct.error as exc:
        raise ValueError(f"value out of range for the Kobuki protocol: {exc}") from None


def _subpayload(sub_id: int, data: bytes) -> bytes:
    if len(data) > 255:
        raise ValueError(f"sub-payload {sub_id} data is {len(data)} bytes, at most 255 fit")
    return bytes((sub_id, len(data))) + data



logger = logging.getLogger(__name__)


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
_T = TypeVar("_T")
_Decoder = Callable[[bytes, int, int], Optional[_T]]


def _fixed(cls: Callable[..., _T], st: struct.Struct, size: int) -> _Decoder[_T]:
    """The decoder of a sub-payload of ``size`` bytes laid out as ``st`` (``cls._ST``)."""
    def decode(payload: bytes, start: int, length: int) -> _T | None:
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


_VersionT = TypeVar("_VersionT", HardwareVersion, FirmwareVersion)


def _decode_version(cls: type[_VersionT]) -> _Decoder[_VersionT]:
    def decode(payload: bytes, start: int, length: int) -> _VersionT | None:
        if length != 4:
            return None
        patch, minor, major = payload[start:start + 3]
        return cls(major, minor, patch)
    return decode


_FEEDBACK_DECODERS: dict[int, _Decoder[FeedbackSubPayload]] = {
    BasicSensorData.ID: _fixed(BasicSensorData, BasicSensorData._ST, 15),
    InertialData.ID: _fixed(InertialData, InertialData._ST, 7),
    RawGyroData.ID: _decode_raw_gyro,
    HardwareVersion.ID: _decode_version(HardwareVersion),
    FirmwareVersion.ID: _decode_version(FirmwareVersion),
    UniqueDeviceId.ID: _fixed(UniqueDeviceId, UniqueDeviceId._ST, 12),
}
_COMMAND_DECODERS: dict[int, _Decoder[CommandSubPayload]] = {
    BaseControl.ID: _fixed(BaseControl, BaseControl._ST, 4),
    RequestExtra.ID: _fixed(RequestExtra, RequestExtra._ST, 2),
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


def _decode_chain(payload: bytes, decoders: Mapping[int, _Decoder[_T]], unknown: Callable[[int, bytes], _T],
                  stats: ParserStats | None) -> list[_T]:
    out: list[_T] = []
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
            out.append(unknown(sub_id, payload[k + 2:k + 2 + length]))
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
    return _decode_chain(bytes(payload), _FEEDBACK_DECODERS, UnknownSubPayload, stats)


def decode_commands(payload: bytes, stats: ParserStats | None = None) -> list[CommandSubPayload]:
    """Decode a command payload (what the daemon sends) like :func:`decode_feedback`."""
    return _decode_chain(bytes(payload), _COMMAND_DECODERS, UnknownSubPayload, stats)


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


