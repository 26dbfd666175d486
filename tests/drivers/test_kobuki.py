"""Kobuki protocol and driver: byte-exact frames, resynchronisation, stamping, transports.

Expected bytes are written by hand from the protocol description (AA 55 LEN payload CS,
CS = XOR of LEN and the payload, little-endian fields); the virtual transports are
pyserial's ``loop://``, ``spy://`` and a real pseudo-terminal.
"""

from __future__ import annotations

import json
import math
import os
import random
import select
import tty

import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.kobuki.capture import decode_capture, detect_capture_format, main
from drivers.kobuki.driver import KobukiDriver
from drivers.kobuki.protocol import (
    BaseControl,
    BasicSensorData,
    FirmwareVersion,
    HardwareVersion,
    InertialData,
    PacketParser,
    RawGyroData,
    RequestExtra,
    UniqueDeviceId,
    UnknownSubPayload,
    base_control_from_twist,
    decode_commands,
    decode_feedback,
    encode_base_control,
    encode_commands,
    encode_feedback,
    encode_packet,
    encode_request_extra,
    twist_from_base_control,
)
from robotd.base.clock import ManualClock
from robotd.base.errors import DriverError
from robotd.base.messages import WheelTicks, YawRate

MS = 1_000_000  # ns

# --------------------------------------------------------------------------------------
# Hand-built frames
# --------------------------------------------------------------------------------------

# A feedback packet with basic sensor data, inertial data and two raw gyro samples.
HAND_FEEDBACK = bytes.fromhex(
    "aa 55"  # header
    " 2a"  # LEN = 17 + 9 + 16 = 42
    # basic sensor data: id 1, len 15
    " 01 0f"
    " 34 12"  # timestamp 0x1234 = 4660 ms
    " 02 00 04"  # bumper centre, no wheel drop, left cliff
    " ff ff 01 00"  # left encoder 65535, right encoder 1
    " ff 7f"  # left PWM -1, right PWM 127
    " 01 06 a7 00"  # button 0, charger 6 (docking, charging), battery 167 = 16.7 V, no overcurrent
    # inertial: id 4, len 7
    " 04 07"
    " d8 dc"  # angle -9000 = 0xdcd8 -> -90.00 deg
    " dc 05"  # rate 1500 = 0x05dc -> 15.00 deg/s
    " 00 00 00"  # unused
    # raw gyro: id 13, len 2 + 6 * 2 = 14
    " 0d 0e"
    " 2a 06"  # frame id 42, followed data length 3N = 6
    " 01 00 fe ff e8 03"  # x 1, y -2, z 1000
    " 00 00 00 00 18 fc"  # x 0, y 0, z -1000 (0xfc18)
    # CS: XOR per sub-payload, by hand:
    #   basic   01^0f=0e ^34=3a ^12=28 ^02=2a ^04=2e ^ff=d1 ^ff=2e ^01=2f ^ff=d0 ^7f=af
    #           ^01=ae ^06=a8 ^a7=0f                                      -> 0f
    #   inertial 04^07=03 ^d8=db ^dc=07 ^dc=db ^05=de                     -> de
    #   gyro    0d^0e=03 ^2a=29 ^06=2f ^01=2e ^fe=d0 ^ff=2f ^e8=c7 ^03=c4 ^18=dc ^fc=20 -> 20
    #   LEN 2a ^ 0f = 25, ^ de = fb, ^ 20 = db
    " db"
)
HAND_ITEMS = [
    BasicSensorData(4660, 0x02, 0, 0x04, 65535, 1, -1, 127, 0x01, 6, 167, 0),
    InertialData(-9000, 1500),
    RawGyroData(42, ((1, -2, 1000), (0, 0, -1000))),
]


def test_encode_base_control_straight_is_byte_exact():
    # payload 01 04 | 64 00 (100 mm/s) | 00 00 (radius 0); CS = 06^01^04^64 = 67
    assert encode_base_control(100, 0) == bytes.fromhex("aa 55 06 01 04 64 00 00 00 67")


def test_encode_base_control_negative_speed_is_byte_exact():
    # -200 = 0xff38 -> 38 ff; radius 1 -> 01 00
    # CS = 06^01=07 ^04=03 ^38=3b ^ff=c4 ^01=c5
    assert encode_base_control(-200, 1) == bytes.fromhex("aa 55 06 01 04 38 ff 01 00 c5")


def test_encode_request_extra_is_byte_exact():
    # flags 0x01 | 0x02 | 0x08 = 0x0b; CS = 04^09=0d ^02=0f ^0b=04
    assert encode_request_extra() == bytes.fromhex("aa 55 04 09 02 0b 00 04")
    # hardware only: flags 0x01; CS = 04^09=0d ^02=0f ^01=0e
    assert encode_request_extra(True, False, False) == bytes.fromhex("aa 55 04 09 02 01 00 0e")


def test_hand_built_feedback_decodes_and_reencodes():
    parser = PacketParser()
    payloads = parser.feed(HAND_FEEDBACK)
    assert payloads == [HAND_FEEDBACK[3:-1]]
    assert decode_feedback(payloads[0]) == HAND_ITEMS
    assert encode_feedback(*HAND_ITEMS) == HAND_FEEDBACK
    assert parser.stats.packets == 1
    assert parser.stats.garbage_bytes == 0


def test_version_answers_are_byte_exact_and_round_trip():
    hw = HardwareVersion(1, 0, 4)
    fw = FirmwareVersion(1, 2, 0)
    udid = UniqueDeviceId(0x11223344, 1, 0xFFFFFFFF)
    assert hw.encode() == bytes.fromhex("0a 04 04 00 01 00")  # patch, minor, major, 0
    assert fw.encode() == bytes.fromhex("0b 04 00 02 01 00")
    assert udid.encode() == bytes.fromhex("13 0c 44 33 22 11 01 00 00 00 ff ff ff ff")
    packet = encode_feedback(hw, fw, udid)
    assert decode_feedback(PacketParser().feed(packet)[0]) == [hw, fw, udid]


def test_commands_decode():
    packet = encode_commands(BaseControl(-300, 1), RequestExtra(0x0B))
    (payload,) = PacketParser().feed(packet)
    commands = decode_commands(payload)
    assert commands == [BaseControl(-300, 1), RequestExtra(0x0B)]
    assert (commands[1].hardware_version, commands[1].firmware_version, commands[1].udid) == (
        True, True, True)
    assert RequestExtra(0x02).hardware_version is False


def test_encoders_reject_out_of_range_values():
    with pytest.raises(ValueError):
        encode_base_control(40000, 0)
    with pytest.raises(ValueError):
        encode_packet(b"\x01\x00")  # shorter than the 3-byte minimum payload


# --------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------

u8 = st.integers(0, 255)
u16 = st.integers(0, 65535)
s8 = st.integers(-128, 127)
s16 = st.integers(-32768, 32767)
basic_st = st.builds(BasicSensorData, u16, u8, u8, u8, u16, u16, s8, s8, u8, u8, u8, u8)
inertial_st = st.builds(InertialData, s16, s16, st.binary(min_size=3, max_size=3))
gyro_st = st.builds(RawGyroData, u8, st.lists(st.tuples(s16, s16, s16), max_size=4).map(tuple))
unknown_st = st.builds(UnknownSubPayload, st.sampled_from([2, 3, 5, 6, 16, 200]),
                       st.binary(min_size=1, max_size=20))


@settings(derandomize=True, max_examples=200, deadline=None)
@given(st.lists(st.one_of(basic_st, inertial_st, gyro_st, unknown_st), min_size=1, max_size=5))
def test_feedback_round_trip(items):
    packet = encode_feedback(*items)
    parser = PacketParser()
    # A packet whose bytes hold AA 55 is settled only by the next packet or the stream's
    # end (PacketParser._scan: "cannot tell before the next packet is complete").
    (payload,) = parser.feed(packet) + parser.finish()
    assert decode_feedback(payload, parser.stats) == items
    assert parser.stats.unknown_subpayloads == sum(type(i) is UnknownSubPayload for i in items)
    assert parser.stats.malformed_subpayloads == 0


@settings(derandomize=True, max_examples=300, deadline=None)
@given(st.binary(max_size=600))
def test_arbitrary_bytes_never_crash_and_every_byte_is_accounted(data):
    parser = PacketParser()
    payloads = parser.feed(data) + parser.finish()
    for p in payloads:
        decode_feedback(p, parser.stats)
    s = parser.stats
    assert s.bytes_in == len(data)
    assert s.packet_bytes + s.garbage_bytes == len(data)
    assert s.packet_bytes == sum(len(p) + 4 for p in payloads)


# --------------------------------------------------------------------------------------
# Sub-payload chains: unknown and malformed
# --------------------------------------------------------------------------------------

BASIC = BasicSensorData(1000, 0, 0, 0, 10, 20, 0, 0, 0, 0, 160, 0)
INERTIAL = InertialData(100, -200)


def test_unknown_subpayloads_are_skipped_by_length():
    payload = BASIC.encode() + bytes([200, 3]) + b"abc" + bytes([201, 0]) + INERTIAL.encode()
    parser = PacketParser()
    items = decode_feedback(payload, parser.stats)
    assert items == [BASIC, UnknownSubPayload(200, b"abc"), UnknownSubPayload(201, b""), INERTIAL]
    assert parser.stats.unknown_subpayloads == 2
    assert parser.stats.malformed_subpayloads == 0


@pytest.mark.parametrize("bad, tail", [
    (bytes([4, 6]) + bytes(6), INERTIAL.encode()),  # inertial must be 7 bytes
    (bytes([1, 16]) + bytes(16), INERTIAL.encode()),  # basic sensor data must be 15 bytes
    (bytes([13, 8, 0, 4]) + bytes(6), INERTIAL.encode()),  # raw gyro: 4 values is not 3N
    (bytes([13, 8, 0, 6]) + bytes(6), INERTIAL.encode()),  # raw gyro: 3N = 6 needs len 14
    (bytes([10, 2, 104, 0]), INERTIAL.encode()),  # 2-byte version of the oldest firmware
    (bytes([200, 10, 1, 2]), b""),  # runs past the payload
    (bytes([7]), b""),  # a dangling id without a length
])
def test_malformed_subpayload_drops_the_rest_of_the_packet(bad, tail):
    parser = PacketParser()
    items = decode_feedback(BASIC.encode() + bad + tail, parser.stats)
    assert items == [BASIC]
    assert parser.stats.malformed_subpayloads == 1
    assert parser.stats.unknown_subpayloads == 0


# --------------------------------------------------------------------------------------
# Resynchronisation
# --------------------------------------------------------------------------------------


def realistic_packet(rng: random.Random, ts_ms: int, embed_header: bool = False) -> bytes:
    """Feedback as the base streams it: basic sensor data, inertial, 2-3 raw gyro samples."""
    left = 0x55AA if embed_header else rng.randrange(65536)  # 0x55aa encodes as AA 55
    basic = BasicSensorData(ts_ms & 0xFFFF, 0, 0, 0, left, rng.randrange(65536),
                            rng.randint(-20, 20), rng.randint(-20, 20), 0, 0, 160, 0)
    inertial = InertialData(rng.randint(-18000, 18000), rng.randint(-3000, 3000))
    gyro = RawGyroData(rng.randrange(256), tuple(
        (rng.randint(-500, 500), rng.randint(-500, 500), rng.randint(-3000, 3000))
        for _ in range(rng.choice((2, 3)))))
    return encode_feedback(basic, inertial, gyro)


def _clean(packet: bytes) -> bool:
    """No header inside the packet other than its own."""
    return packet.find(b"\xaa\x55", 1) < 0


def build_stream(rng: random.Random, n_packets: int, garbage_values: list[int]):
    """A stream of valid packets with garbage runs, corrupted and truncated packets.

    Returns the stream, the valid packets in order, and the numbers of corrupted (one
    payload or CS byte changed) and truncated (cut, then directly followed by a valid
    packet) packets. Corrupted and truncated packets hold no header but their own, so
    every rejection is known in advance.
    """
    out = bytearray()
    valid: list[bytes] = []
    corrupted = truncated = 0
    ts = 0
    force_valid = False
    for _ in range(n_packets):
        ts += 20
        if not force_valid and rng.random() < 0.2:
            out += bytes(rng.choice(garbage_values) for _ in range(rng.randint(1, 40)))
        r = rng.random()
        if force_valid or r >= 0.08:
            packet = realistic_packet(rng, ts, embed_header=rng.random() < 0.02)
            valid.append(packet)
            out += packet
            force_valid = False
            continue
        packet = realistic_packet(rng, ts)
        while not _clean(packet):
            packet = realistic_packet(rng, ts)
        if r < 0.04:
            while True:
                k = rng.randrange(3, len(packet))  # a payload or CS byte, never LEN
                bad = packet[:k] + bytes([packet[k] ^ rng.randint(1, 255)]) + packet[k + 1:]
                if _clean(bad):
                    break
            out += bad
            corrupted += 1
        else:
            out += packet[:rng.randint(3, len(packet) - 2)]
            truncated += 1
            force_valid = True
    if force_valid:
        packet = realistic_packet(rng, ts + 20)
        valid.append(packet)
        out += packet
    return bytes(out), valid, corrupted, truncated


CLEAN_GARBAGE = [b for b in range(256) if b not in (0xAA, 0x55)]


def test_parser_recovers_every_packet_with_exact_rejection_counts():
    rng = random.Random(20240611)
    stream, valid, corrupted, truncated = build_stream(rng, 2000, CLEAN_GARBAGE)
    valid_bytes = sum(map(len, valid))
    assert 0.08 < 1 - valid_bytes / len(stream) < 0.25  # the premise: ~10-20 % is bad
    assert corrupted > 50 and truncated > 50
    assert sum(p.find(b"\xaa\x55", 1) > 0 for p in valid) > 10  # some hold AA 55 inside
    parser = PacketParser()
    payloads = parser.feed(stream) + parser.finish()
    assert payloads == [p[3:-1] for p in valid]
    s = parser.stats
    assert (s.packets, s.bad_checksums, s.truncated) == (len(valid), corrupted, truncated)
    assert s.garbage_bytes == len(stream) - valid_bytes
    assert s.packet_bytes == valid_bytes
    for p in payloads:
        assert len(decode_feedback(p, s)) == 3
    assert (s.unknown_subpayloads, s.malformed_subpayloads) == (0, 0)


def test_parser_recovers_every_packet_from_fully_random_garbage():
    rng = random.Random(7)
    stream, valid, corrupted, truncated = build_stream(rng, 2000, list(range(256)))
    parser = PacketParser()
    payloads = parser.feed(stream) + parser.finish()
    assert payloads == [p[3:-1] for p in valid]
    s = parser.stats
    assert s.garbage_bytes == len(stream) - sum(map(len, valid))
    # garbage may hold false headers, so rejections are at least the known ones
    assert s.bad_checksums + s.truncated >= corrupted + truncated


def feed_all(parser: PacketParser, chunks) -> tuple[list[bytes], list[int]]:
    payloads, offsets = [], []
    for chunk in chunks:
        payloads += parser.feed(chunk)
        offsets += parser.last_offsets
    payloads += parser.finish()
    offsets += parser.last_offsets
    return payloads, offsets


def test_chunked_feeding_matches_one_feed():
    rng = random.Random(99)
    stream, valid, _, _ = build_stream(rng, 300, list(range(256)))
    whole = PacketParser()
    payloads, offsets = feed_all(whole, [stream])
    assert payloads == [p[3:-1] for p in valid]
    # offsets point at the headers of the returned packets in the stream
    assert [stream[o + 3:o + 3 + len(p)] for o, p in zip(offsets, payloads)] == payloads
    cuts = sorted(rng.sample(range(1, len(stream)), 400))
    chunks = [stream[a:b] for a, b in zip([0] + cuts, cuts + [len(stream)])]
    chunked = PacketParser()
    assert feed_all(chunked, chunks) == (payloads, offsets)
    assert chunked.stats == whole.stats
    single = PacketParser()
    assert feed_all(single, [stream[k:k + 1] for k in range(len(stream))]) == (payloads, offsets)
    assert single.stats == whole.stats


def test_header_split_across_feeds():
    packet = encode_feedback(BASIC)
    parser = PacketParser()
    assert parser.feed(packet[:1]) == []  # a lone 0xAA waits for its 0x55
    assert parser.feed(packet[1:2]) == []
    assert parser.feed(packet[2:]) == [packet[3:-1]]
    assert parser.stats.garbage_bytes == 0


def test_bad_checksum_is_counted_and_the_next_packet_kept():
    good = encode_feedback(BASIC)
    bad = bytearray(encode_feedback(INERTIAL))
    bad[5] ^= 0x01  # one payload bit
    parser = PacketParser()
    assert parser.feed(bytes(bad) + good) == [good[3:-1]]
    s = parser.stats
    assert (s.packets, s.bad_checksums, s.truncated) == (1, 1, 0)
    assert s.garbage_bytes == len(bad)


def test_packet_cut_short_by_a_new_header_is_truncated():
    first = encode_feedback(BASIC, INERTIAL)
    second = encode_feedback(INERTIAL)
    parser = PacketParser()
    assert parser.feed(first[:12] + second + second) == [second[3:-1]] * 2
    s = parser.stats
    assert (s.packets, s.bad_checksums, s.truncated) == (2, 0, 1)
    assert s.garbage_bytes == 12


def test_packet_cut_short_by_end_of_data_is_truncated_at_finish():
    packet = encode_feedback(BASIC)
    parser = PacketParser()
    assert parser.feed(packet + packet[:10]) == [packet[3:-1]]
    assert parser.stats.truncated == 0  # it may still complete
    assert parser.finish() == []
    assert (parser.stats.truncated, parser.stats.garbage_bytes) == (1, 10)


def test_valid_packet_behind_a_false_long_header_is_not_lost():
    packet = encode_feedback(BASIC)  # 21 bytes
    false_header = b"\x01\xaa\x55\xff"  # declares 255 + 4 bytes
    parser = PacketParser()
    assert parser.feed(false_header + packet) == []  # waits for the 259 bytes
    assert parser.finish() == [packet[3:-1]]
    s = parser.stats
    assert (s.packets, s.truncated, s.garbage_bytes) == (1, 1, 4)
    # with enough data behind it, the false header is settled without finish()
    parser = PacketParser()
    assert parser.feed(false_header + packet * 13) == [packet[3:-1]] * 13
    assert (parser.stats.truncated, parser.stats.garbage_bytes) == (1, 4)


def test_truncated_packet_passing_the_checksum_by_chance_is_rejected():
    # A declares 4 + 59 bytes: basic (17) + an unknown id 200 with 40 bytes (42).
    a = encode_feedback(BASIC, UnknownSubPayload(200, bytes(range(40))))
    b = encode_feedback(INERTIAL)  # 13 bytes
    kept = a[:23]
    filler = bytearray(b"\x11" * (len(a) - len(kept) - len(b)))
    x = 0
    for byte in (kept + b + filler)[2:]:
        x ^= byte
    filler[-1] ^= x  # make A's declared span XOR to zero: the checksum passes
    assert filler[-1] not in (0xAA, 0x55)
    stream = kept + b + bytes(filler)
    chk = 0
    for byte in stream[2:len(a)]:
        chk ^= byte
    assert chk == 0  # the premise
    parser = PacketParser()
    assert parser.feed(stream) + parser.finish() == [b[3:-1]]
    s = parser.stats
    assert (s.packets, s.truncated, s.bad_checksums) == (1, 1, 0)
    assert s.garbage_bytes == len(kept) + len(filler)


def test_length_below_minimum_is_not_a_header():
    packet = encode_feedback(BASIC)
    parser = PacketParser()
    assert parser.feed(b"\xaa\x55\x02" + packet) == [packet[3:-1]]
    s = parser.stats
    assert (s.garbage_bytes, s.bad_checksums, s.truncated) == (3, 0, 0)


# --------------------------------------------------------------------------------------
# Kinematics
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("v, w, expected", [
    (0.3, 0.0, (300, 0)),  # straight
    (0.0, 1.0, (115, 1)),  # on the spot: 1 rad/s * 0.23 m / 2 = 115 mm/s
    (0.0, -2.0, (-230, 1)),
    (0.0005, 1.0, (115, 1)),  # radius 0.5 mm <= 1 mm: on the spot
    (0.2, 0.4, (246, 500)),  # radius 500 mm, outer wheel (500 + 115) * 0.4
    (0.2, -0.4, (246, -500)),
    (-0.2, 0.4, (-246, -500)),
    (40.0, 0.0, (32767, 0)),  # bounded to int16
])
def test_base_control_from_twist(v, w, expected):
    assert base_control_from_twist(v, w) == expected


@pytest.mark.parametrize("speed, radius, v, w", [
    (300, 0, 0.3, 0.0), (115, 1, 0.0, 1.0), (246, 500, 0.2, 0.4), (-246, -500, -0.2, 0.4),
])
def test_twist_from_base_control(speed, radius, v, w):
    assert twist_from_base_control(speed, radius) == pytest.approx((v, w), abs=1e-12)


# --------------------------------------------------------------------------------------
# Driver over loop://
# --------------------------------------------------------------------------------------

T0 = 5_000_000_000


def fb(ts_ms: int, left: int = 0, right: int = 0, gyro_z=(100, 200), rate_cdegps: int = 0) -> bytes:
    items = [BasicSensorData(ts_ms, 0, 0, 0, left, right, 0, 0, 0, 0, 160, 0),
             InertialData(0, rate_cdegps)]
    if gyro_z is not None:
        items.append(RawGyroData(0, tuple((7, -7, z) for z in gyro_z)))
    return encode_feedback(*items)


def ticks(messages):
    return [(m.stamp_ns, m.left_ticks, m.right_ticks, m.device_ms)
            for m in messages if isinstance(m, WheelTicks)]


def test_driver_maps_wrapping_device_time_to_the_clock():
    clock = ManualClock(T0)
    with KobukiDriver("loop://", clock) as drv:
        # device time and encoders wrap at 65536 inside one batch
        for ts, left, right in ((65500, 65534, 1), (65520, 65535, 0), (4, 0, 65535), (24, 1, 65534)):
            drv.port.write(fb(ts, left, right))
        messages = drv.read(0.0)
        # the last packet of the batch travelled fastest: it sets the offset
        assert ticks(messages) == [
            (T0 - 60 * MS, 65534, 1, 65500), (T0 - 40 * MS, 65535, 0, 65520),
            (T0 - 20 * MS, 0, 65535, 4), (T0, 1, 65534, 24)]
        yaw = [m for m in messages if isinstance(m, YawRate)]
        # The mean of the samples taken since the previous packet: the middle of the 20 ms
        # between packets (the first packet: half the nominal 20 ms period).
        assert [m.stamp_ns for m in yaw] == [T0 - 70 * MS, T0 - 50 * MS, T0 - 30 * MS, T0 - 10 * MS]
        assert yaw[0].source == "raw_gyro"
        assert yaw[0].yaw_rate_radps == pytest.approx(math.radians(150 * 0.00875), rel=1e-12)
        # in time order: each packet's yaw rate before its wheel message
        assert [type(m) for m in messages[:2]] == [YawRate, WheelTicks]
        assert [m.stamp_ns for m in messages] == sorted(m.stamp_ns for m in messages)

        # a slower packet later does not move the offset: stamp = device time + best offset
        clock.advance_ns(25 * MS)
        drv.port.write(fb(44))
        assert ticks(drv.read(0.0)) == [(T0 + 20 * MS, 0, 0, 44)]

        # 11 s later the old best offsets have left the 10 s window: this packet sets it
        clock.advance_ns(11_005 * MS)
        drv.port.write(fb((65580 + 11_000) & 0xFFFF))
        assert ticks(drv.read(0.0))[0][0] == T0 + 11_030 * MS

        # a silence of 65.556 s: the raw counter moved only 20 ms, the host clock says one wrap
        clock.advance_ns(65_556 * MS)
        drv.port.write(fb((65580 + 11_000 + 65_556) & 0xFFFF))
        assert ticks(drv.read(0.0))[0][0] == T0 + (11_030 + 65_556) * MS
        stats = drv.stats()
        assert stats["clock_clamps"] == 0
        assert stats["messages_out"] == 14
        assert stats["packets"] == 7


def test_driver_clamps_stamps_that_would_go_back():
    clock = ManualClock(T0)
    with KobukiDriver("loop://", clock) as drv:
        drv.port.write(fb(1000))
        assert ticks(drv.read(0.0))[0][0] == T0
        clock.advance_ns(20 * MS)
        # the device clock ran ahead: 1050 arrives only 20 ms after 1000
        drv.port.write(fb(1001) + fb(1050))
        stamps = [t[0] for t in ticks(drv.read(0.0))]
        # 1001 maps to T0 + 20 - 49 = T0 - 29 ms < T0: clamped; 1050 maps to its receipt
        assert stamps == [T0, T0 + 20 * MS]
        assert drv.stats()["clock_clamps"] == 1


def test_driver_yaw_sources():
    clock = ManualClock(T0)
    with KobukiDriver("loop://", clock) as drv:
        drv.port.write(fb(0, gyro_z=None, rate_cdegps=1500) + fb(20, gyro_z=(), rate_cdegps=-300))
        yaw = [m for m in drv.read(0.0) if isinstance(m, YawRate)]
        # no raw gyro samples: fall back to the inertial rate, 0.01 deg/s units
        assert [(m.source, m.yaw_rate_radps) for m in yaw] == [
            ("inertial", pytest.approx(math.radians(15.0))),
            ("inertial", pytest.approx(math.radians(-3.0)))]
    with KobukiDriver("loop://", clock, yaw_source="inertial") as drv:
        drv.port.write(fb(0, gyro_z=(5000,), rate_cdegps=250))
        (yaw,) = [m for m in drv.read(0.0) if isinstance(m, YawRate)]
        assert (yaw.source, yaw.yaw_rate_radps) == ("inertial", pytest.approx(math.radians(2.5)))
    with pytest.raises(ValueError):
        KobukiDriver("loop://", clock, yaw_source="compass")


def test_driver_packet_without_basic_data_has_no_ticks():
    clock = ManualClock(T0)
    with KobukiDriver("loop://", clock) as drv:
        drv.port.write(encode_feedback(HardwareVersion(1, 0, 4)) + encode_feedback(INERTIAL))
        (yaw,) = drv.read(0.0)
        assert (type(yaw), yaw.stamp_ns, yaw.source) == (YawRate, T0, "inertial")
        assert yaw.yaw_rate_radps == pytest.approx(math.radians(-2.0), rel=1e-12)
        assert drv.stats()["untimed_packets"] == 2
        assert drv.read(0.0) == []  # nothing waiting, no timeout


def test_driver_sends_commands():
    with KobukiDriver("loop://", ManualClock()) as drv:
        drv.send_base_control(0.2, 0.4)
        drv.request_extra(hardware_version=True, firmware_version=False, udid=True)
        sent = drv.port.read(drv.port.in_waiting)
        # speed 246 = 0x00f6, radius 500 = 0x01f4; CS = 06^01=07 ^04=03 ^f6=f5 ^f4=01 ^01=00
        assert sent[:10] == bytes.fromhex("aa 55 06 01 04 f6 00 f4 01 00")
        parser = PacketParser()
        assert [decode_commands(p) for p in parser.feed(sent)] == [
            [BaseControl(246, 500)], [RequestExtra(0x09)]]
        assert drv.stats()["commands_sent"] == 2


def test_driver_missing_port_names_it():
    path = "/nonexistent/dir/ttyKobuki9"
    with pytest.raises(DriverError, match="ttyKobuki9") as info:
        KobukiDriver(path, ManualClock())
    assert path in str(info.value)


def test_driver_busy_port_names_it():
    master, slave = os.openpty()
    try:
        path = os.ttyname(slave)
        with KobukiDriver(path, ManualClock()):
            with pytest.raises(DriverError) as info:
                KobukiDriver(path, ManualClock())  # the first driver holds the exclusive lock
            assert path in str(info.value)
    finally:
        os.close(master)
        os.close(slave)


def test_driver_close_twice_and_read_after_close():
    drv = KobukiDriver("loop://", ManualClock())
    drv.close()
    drv.close()
    with pytest.raises(DriverError, match="closed"):
        drv.read(0.0)


# --------------------------------------------------------------------------------------
# Driver over a real pseudo-terminal
# --------------------------------------------------------------------------------------


def test_driver_over_pty():
    master, slave = os.openpty()
    try:
        tty.setraw(slave)
        clock = ManualClock(T0)
        with KobukiDriver(os.ttyname(slave), clock) as drv:
            os.write(master, b"\x00\x13")
            got = []
            for ts, left, right in ((100, 7, 8), (120, 9, 10), (140, 11, 12)):
                os.write(master, fb(ts, left, right))
                messages = []
                for _ in range(100):  # each read returns as soon as bytes are there
                    messages += drv.read(1.0)
                    if len(messages) == 2:
                        break
                got += ticks(messages)
                clock.advance_ns(20 * MS)
            assert got == [(T0, 7, 8, 100), (T0 + 20 * MS, 9, 10, 120), (T0 + 40 * MS, 11, 12, 140)]
            assert drv.stats()["garbage_bytes"] == 2
            drv.send_base_control(0.0, 1.0)
            ready, _, _ = select.select([master], [], [], 5.0)
            assert ready
            # 115 = 0x73; CS = 06^01=07 ^04=03 ^73=70 ^01=71
            assert os.read(master, 64) == bytes.fromhex("aa 55 06 01 04 73 00 01 00 71")
    finally:
        os.close(master)
        os.close(slave)


# --------------------------------------------------------------------------------------
# Capture decoding
# --------------------------------------------------------------------------------------


def capture_stream() -> tuple[bytes, list[bytes]]:
    rng = random.Random(3)
    packets = [realistic_packet(rng, 20 * k) for k in range(12)]
    packets.append(encode_feedback(FirmwareVersion(1, 2, 0), UnknownSubPayload(5, bytes(6))))
    stream = bytearray()
    for k, p in enumerate(packets):
        stream += p
        if k % 4 == 1:
            stream += b"AB CD EF 12 "  # printable garbage that looks like hex in the dump
    return bytes(stream), packets


def test_spy_capture_is_decoded_from_rx_only(tmp_path):
    # pyserial's spy:// wraps native ports only (spy://loop:// cannot open), so spy on a pty
    stream, packets = capture_stream()
    cap = tmp_path / "kobuki.spy"
    master, slave = os.openpty()
    try:
        tty.setraw(slave)
        port = serial.serial_for_url(f"spy://{os.ttyname(slave)}?file={cap}", timeout=1.0)
        try:
            port.write(encode_base_control(100, 0) * 3)  # logged as TX lines: must not count
            os.write(master, stream)
            got = b""
            for _ in range(1000):  # each read returns once 37 bytes (or the rest) are there
                got += port.read(min(37, len(stream) - len(got)))
                if len(got) == len(stream):
                    break
        finally:
            port.close()
            port.formatter.output.close()
    finally:
        os.close(master)
        os.close(slave)
    assert got == stream
    text = cap.read_bytes()
    assert b" TX " in text and b" RX " in text
    assert detect_capture_format(text) == "spy"
    records = list(decode_capture(text))
    assert len(records) == len(packets) + 1
    assert [r["packet"] for r in records[:-1]] == list(range(len(packets)))
    assert [stream[r["offset"]:r["offset"] + len(p)] for r, p in zip(records, packets)] == packets
    summary = records[-1]["summary"]
    assert (summary["format"], summary["bytes_in"], summary["packets"]) == ("spy", len(stream), 13)
    assert summary["garbage_bytes"] == 3 * len(b"AB CD EF 12 ")
    assert records[-2]["subpayloads"] == [
        {"type": "firmware_version", "id": 11, "major": 1, "minor": 2, "patch": 0},
        {"type": "unknown", "id": 5, "data": "000000000000"}]

    out = tmp_path / "decoded.jsonl"
    assert main([str(cap), "--out", str(out)]) == 0
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    assert lines == json.loads(json.dumps(records))


def test_spy_text_written_by_hand():
    # pyserial's hexdump: time, label padded to 4, offset, 16 "HH " cells with an extra space
    # after the 8th, a space, the ASCII column; colour mode puts escape codes before lines
    packet = encode_request_extra()  # aa 55 04 09 02 0b 00 04, sent: TX must be skipped
    feedback = encode_feedback(HardwareVersion(1, 0, 4))
    # CS = 06^0a=0c ^04=08 ^04=0c ^00 ^01=0d ^00 -> 0d
    assert feedback.hex(" ") == "aa 55 06 0a 04 04 00 01 00 0d"
    text = (
        "000000.001 TX   0000  AA 55 04 09 02 0B 00 04                           .U......        \n"
        "\x1b[32m000000.015 RX   <empty>\n"
        "\x1b[32m000000.020 RX   0000  41 42 20 43 44 20 45 46  AA 55 06 0A 04 04 00 01  AB CD EF.U......\n"
        "000000.020 RX   0010  00 0D                                             ..              \n"
        "000000.030 RTS  inactive\n"
    ).encode()
    assert packet.hex(" ").upper() in text.decode()
    assert detect_capture_format(text) == "spy"
    records = list(decode_capture(text))
    assert records[0] == {"packet": 0, "offset": 8, "subpayloads": [
        {"type": "hardware_version", "id": 10, "major": 1, "minor": 0, "patch": 4}]}
    summary = records[1]["summary"]
    assert (summary["bytes_in"], summary["packets"], summary["garbage_bytes"]) == (18, 1, 8)


_SPY_OK = (  # the hand-written dump above: one hardware_version packet after 8 garbage bytes
    b"000000.020 RX   0000  41 42 20 43 44 20 45 46  AA 55 06 0A 04 04 00 01  AB CD EF.U......\n"
    b"000000.020 RX   0010  00 0D                                             ..              \n"
)
_SECOND = (  # the same packet again, in a second read of the port
    b"000000.040 RX   0000  AA 55 06 0A 04 04 00 01  00 0D                    .U........      \n"
)


@pytest.mark.parametrize(("name", "text", "packets", "damaged", "foreign"), [
    # it used to raise ValueError from bytes.fromhex
    ("cut line", _SPY_OK + _SECOND + b"000000.050 RX   0000  AA 55 06 0", 2, 1, 0),
    ("junk in the hex column", _SPY_OK + b"000000.030 RX   0000  zz 55 06 0A\n" + _SECOND, 2, 1, 0),
    # it used to raise UnicodeDecodeError
    # (its AA is read, one byte of garbage before the second packet)
    ("non-ASCII bytes", _SPY_OK + b"000000.030 RX   0000  AA \xc3\xa9 06\n" + _SECOND, 2, 1, 0),
    ("a junk line", _SPY_OK + b"\x00\xff garbage \xe2\x82\xac\n" + _SECOND, 2, 0, 1),
    # it used to be read as raw bytes: 0 packets
    ("a leading comment", b"# captured on the robot, 2024-05-06\n\n" + _SPY_OK + _SECOND, 2, 0, 0),
    ("a leading junk line", b"Kobuki capture\n" + _SPY_OK + _SECOND, 2, 0, 1),
])
def test_damaged_spy_dumps_decode_what_is_intact(tmp_path, capsys, caplog, name, text, packets,
                                                 damaged, foreign):
    assert detect_capture_format(text) == "spy"
    records = list(decode_capture(text))
    summary = records[-1]["summary"]
    assert (summary["format"], summary["packets"]) == ("spy", packets)
    assert (summary["spy_damaged_rx_lines"], summary["spy_unrecognised_lines"]) == (damaged, foreign)
    assert [r["offset"] for r in records[:-1]] == [8, 19 if name == "non-ASCII bytes" else 18]
    assert all(r["subpayloads"] == records[0]["subpayloads"] for r in records[:-1])
    cap = tmp_path / "kobuki.spy"
    cap.write_bytes(text)
    assert main([str(cap)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert json.loads(out[-1]) == json.loads(json.dumps(records[-1]))
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    if damaged or foreign:
        assert warnings == [f"{cap}: {damaged} damaged RX lines (read up to the damage) and "
                            f"{foreign} lines that are not pyserial's (skipped)"]
    else:
        assert warnings == []


def test_raw_bytes_are_not_taken_for_a_dump():
    assert detect_capture_format(HAND_FEEDBACK * 40) == "raw"
    assert detect_capture_format(b"# only a comment\n") == "raw"
    assert detect_capture_format(b"") == "raw"


def test_raw_capture_through_main(tmp_path, capsys):
    cap = tmp_path / "kobuki.bin"
    cap.write_bytes(b"\x00" + HAND_FEEDBACK + HAND_FEEDBACK[:20])
    assert detect_capture_format(cap.read_bytes()) == "raw"
    assert main([str(cap)]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(lines) == 2
    assert lines[0]["packet"] == 0 and lines[0]["offset"] == 1
    basic, inertial, gyro = lines[0]["subpayloads"]
    assert basic == {"type": "basic_sensor_data", "id": 1, "timestamp_ms": 4660, "bumper": 2,
                     "wheel_drop": 0, "cliff": 4, "left_encoder": 65535, "right_encoder": 1,
                     "left_pwm": -1, "right_pwm": 127, "buttons": 1, "charger": 6,
                     "battery_decivolts": 167, "overcurrent": 0}
    assert inertial == {"type": "inertial", "id": 4, "angle_centideg": -9000,
                        "angle_rate_centidegps": 1500, "unused": "000000"}
    assert gyro == {"type": "raw_gyro", "id": 13, "frame_id": 42,
                    "samples": [[1, -2, 1000], [0, 0, -1000]]}
    summary = lines[1]["summary"]
    assert (summary["format"], summary["packets"], summary["truncated"]) == ("raw", 1, 1)
    assert summary["garbage_bytes"] == 21


def test_main_missing_capture_is_one_line_error(tmp_path, capsys):
    missing = tmp_path / "nope.bin"
    assert main([str(missing)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0]


def test_raw_gyro_stamp_is_half_the_device_interval_at_most_half_a_period():
    clock = ManualClock(T0)
    with KobukiDriver("loop://", clock) as drv:
        # 12 ms apart (a faster firmware), then a 60 ms gap (packets lost: the samples still
        # cover only the last nominal period)
        for ts in (1000, 1012, 1072):
            drv.port.write(fb(ts))
        messages = drv.read(0.0)
        wheel = [m.stamp_ns for m in messages if isinstance(m, WheelTicks)]
        yaw = [m.stamp_ns for m in messages if isinstance(m, YawRate)]
        assert [w - y for w, y in zip(wheel, yaw)] == [10 * MS, 6 * MS, 10 * MS]


def test_driver_reports_wheel_drop_changes_before_that_packets_wheels():
    """The wheel-drop bits (0x01 right, 0x02 left) of the basic sensor data become a
    WheelDrop when they change: lifted, still lifted (nothing), put down."""
    from robotd.base.messages import WheelDrop

    def drop_fb(ts_ms: int, bits: int) -> bytes:
        return encode_feedback(BasicSensorData(ts_ms, 0, bits, 0, 10, 20, 0, 0, 0, 0, 160, 0),
                               InertialData(0, 0))

    clock = ManualClock(T0)
    with KobukiDriver("loop://", clock) as drv:
        for ts, bits in ((0, 0), (20, 0), (40, 2), (60, 3), (80, 3), (100, 0), (120, 0)):
            drv.port.write(drop_fb(ts, bits))
        messages = drv.read(0.0)
        drops = [m for m in messages if isinstance(m, WheelDrop)]
        assert [(m.lifted, m.left, m.right) for m in drops] == [
            (True, True, False), (True, True, True), (False, False, False)]
        wheels = [m for m in messages if isinstance(m, WheelTicks)]
        assert [m.stamp_ns for m in drops] == [wheels[2].stamp_ns, wheels[3].stamp_ns, wheels[5].stamp_ns]
        i = messages.index(drops[0])
        assert messages[i + 1] is wheels[2]
        assert drv.stats()["wheel_drops"] == 1


def test_driver_reports_a_base_that_starts_lifted():
    from robotd.base.messages import WheelDrop

    clock = ManualClock(T0)
    with KobukiDriver("loop://", clock) as drv:
        drv.port.write(encode_feedback(BasicSensorData(0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 160, 0)))
        [drop] = [m for m in drv.read(0.0) if isinstance(m, WheelDrop)]
        assert (drop.lifted, drop.left, drop.right) == (True, False, True)
