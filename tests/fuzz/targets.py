"""The fuzzing targets: robotd's readers of outside bytes, each with its input strategy and
the one error type it documents.

A *crash* is any exception other than the target's documented error (:attr:`Target.allowed`;
none for the Kobuki parser and the capture decoder, which never raise on bad bytes), or a
result that breaks the target's own promise (:func:`check_kobuki`: every payload the parser
returns is a valid packet of the stream).

The strategies do not only throw random bytes, which the first check of each reader
rejects: they mutate valid inputs (encoded Kobuki packets, pyserial ``spy://`` lines, g2o
records, real floor descriptors whose checksum is then made right again so the decoder
reads past it). Used by ``tests/fuzz/test_fuzz.py`` (fast in the default suite, larger
under ``-m slow``) and ``bench/bench_fuzz.py`` (inputs tried and crashes per target).
"""

from __future__ import annotations

import functools
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from hypothesis import strategies as st

from drivers.kobuki import protocol
from robotd.base.errors import DescriptorError, GraphError

# --------------------------------------------------------------------------------------
# Kobuki packets (drivers/kobuki/protocol.py)
# --------------------------------------------------------------------------------------

_u8 = st.integers(0, 255)
_u16 = st.integers(0, 0xFFFF)
_s16 = st.integers(-0x8000, 0x7FFF)

_subpayloads = st.one_of(
    st.builds(protocol.BasicSensorData, _u16, _u8, _u8, _u8, _u16, _u16, st.integers(-128, 127),
              st.integers(-128, 127), _u8, _u8, _u8, _u8),
    st.builds(protocol.InertialData, _s16, _s16),
    st.builds(protocol.RawGyroData, _u8, st.lists(st.tuples(_s16, _s16, _s16), max_size=4).map(tuple)),
    st.builds(protocol.UnknownSubPayload, st.integers(20, 255), st.binary(max_size=12)),
)


@st.composite
def kobuki_stream(draw: st.DrawFn) -> tuple[bytes, list[int]]:
    """A byte stream of valid packets, garbage, and damaged packets (a byte changed, cut
    short, header alone), and the chunk sizes it is fed in."""
    parts: list[bytes] = []
    for _ in range(draw(st.integers(0, 8))):
        kind = draw(st.sampled_from(["packet", "garbage", "flipped", "cut", "header"]))
        if kind == "garbage":
            parts.append(draw(st.binary(max_size=40)))
            continue
        if kind == "header":
            parts.append(b"\xaa\x55" + draw(st.binary(max_size=3)))
            continue
        subs = draw(st.lists(_subpayloads, min_size=1, max_size=4))
        if sum(len(sp.encode()) for sp in subs) < protocol.MIN_PAYLOAD_LEN:
            subs.append(protocol.UnknownSubPayload(99, b"\x00"))  # a payload has 3 bytes at least
        packet = protocol.encode_feedback(*subs)
        if kind == "flipped":
            i = draw(st.integers(0, len(packet) - 1))
            packet = packet[:i] + bytes([draw(_u8)]) + packet[i + 1:]
        elif kind == "cut":
            packet = packet[:draw(st.integers(0, len(packet) - 1))]
        parts.append(packet)
    stream = b"".join(parts)
    chunks = draw(st.lists(st.integers(1, 64), max_size=12))
    return stream, chunks


def check_kobuki(example: tuple[bytes, list[int]]) -> None:
    """Feed the stream in the drawn chunks, decode every payload both ways; every payload
    returned must be a whole, valid packet of the stream (its re-encoding is in it)."""
    stream, chunks = example
    parser = protocol.PacketParser()
    payloads: list[bytes] = []
    pos = 0
    for size in chunks:
        payloads += parser.feed(stream[pos:pos + size])
        pos += size
    payloads += parser.feed(stream[pos:])
    payloads += parser.finish()
    for payload in payloads:
        if protocol.encode_packet(payload) not in stream:
            raise AssertionError(f"payload {payload.hex()} is no packet of the stream")
        protocol.decode_feedback(payload, parser.stats)
        protocol.decode_commands(payload)


# --------------------------------------------------------------------------------------
# pyserial spy:// captures (drivers/kobuki/capture.py)
# --------------------------------------------------------------------------------------

_hex_cells = st.lists(_u8, max_size=16).map(lambda bs: " ".join(f"{b:02X}" for b in bs).encode())


@st.composite
def spy_line(draw: st.DrawFn) -> bytes:
    """One line as pyserial's spy:// writes it (RX/TX data, control lines), often damaged."""
    t = draw(st.floats(0, 1e6, allow_nan=False)).__format__("010.3f").encode()
    kind = draw(st.sampled_from([b"RX", b"TX", b"BRK", b"RTS"]))
    offset = f"{draw(_u16):04X}".encode()
    line = t + b" " + kind + b"   " + offset + b"  " + draw(_hex_cells) + b"  " + draw(st.binary(max_size=16))
    damage = draw(st.sampled_from(["none", "cut", "byte", "ansi", "junk"]))
    if damage == "cut":
        line = line[:draw(st.integers(0, len(line)))]
    elif damage == "byte" and line:
        i = draw(st.integers(0, len(line) - 1))
        line = line[:i] + bytes([draw(_u8)]) + line[i + 1:]
    elif damage == "ansi":
        line = b"\x1b[1;32m" + line + b"\x1b[0m"
    elif damage == "junk":
        line = draw(st.binary(max_size=60))
    return line


capture_input = st.tuples(
    st.one_of(st.lists(spy_line(), max_size=20).map(b"\n".join),
              st.lists(st.one_of(spy_line(), st.just(b"# comment"), st.just(b"")), max_size=20)
              .map(b"\r\n".join),
              st.binary(max_size=300)),
    st.sampled_from(["auto", "raw", "spy"]))


def check_capture(example: tuple[bytes, str]) -> None:
    """Decode the capture to the end (the summary is its last record)."""
    from drivers.kobuki.capture import decode_capture

    data, fmt = example
    records = list(decode_capture(data, fmt))
    if "summary" not in records[-1]:
        raise AssertionError("the last record is not the summary")


# --------------------------------------------------------------------------------------
# g2o files (robotd/io/g2o.py)
# --------------------------------------------------------------------------------------

_number = st.one_of(
    st.integers(-3, 40).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["nan", "inf", "-inf", "1e400", "-0", "0x10", "1_000", "99999999999999999999999",
                     "", "abc", "1.5.2", "+", "-"]),
)


@st.composite
def g2o_line(draw: st.DrawFn) -> str:
    tag = draw(st.sampled_from(["VERTEX_SE2"] * 6 + ["EDGE_SE2"] * 8 + ["FIX", "VERTEX_XY", "", "#"]))
    count = {"VERTEX_SE2": 4, "EDGE_SE2": 11, "FIX": 1}.get(tag, 2) + draw(st.integers(-2, 2))
    fields = [draw(_number) for _ in range(max(0, count))]
    if tag == "EDGE_SE2" and draw(st.booleans()):  # a plausible edge: small ids, PD information
        fields = [str(draw(st.integers(0, 6))), str(draw(st.integers(0, 6)))] + [
            repr(draw(st.floats(-5, 5))) for _ in range(3)] + ["1", "0", "0", "1", "0", "1"]
    if tag == "VERTEX_SE2" and draw(st.booleans()):
        fields = [str(draw(st.integers(0, 6)))] + [repr(draw(st.floats(-5, 5))) for _ in range(3)]
    line = " ".join([tag, *fields])
    if draw(st.booleans()):
        line += " # " + draw(st.text(max_size=8))
    return line


g2o_input = st.one_of(st.lists(g2o_line(), max_size=14), st.lists(st.text(max_size=40), max_size=6))


def check_g2o(lines: list[str]) -> None:
    from robotd.io.g2o import parse_g2o

    parse_g2o(lines, "fuzz.g2o")


# --------------------------------------------------------------------------------------
# Floor descriptors (robotd/floor/descriptor.py)
# --------------------------------------------------------------------------------------

_CRC = struct.Struct("<I")


@functools.lru_cache(maxsize=1)
def seed_descriptors() -> tuple[bytes, ...]:
    """Real descriptors of one small floor image in every mode (made once)."""
    import numpy as np
    import skimage.data

    from robotd.floor.descriptor import MODES, extract

    image = np.ascontiguousarray(skimage.data.gravel()[:240, :320])
    return tuple(extract(image, mode) for mode in sorted(MODES))


def with_checksum(data: bytes) -> bytes:
    """``data`` with its CRC field (header bytes 16..19) made right for its content."""
    if len(data) < 20:
        return data
    crc = zlib.crc32(data[20:], zlib.crc32(data[:16]))
    return data[:16] + _CRC.pack(crc) + data[20:]


@st.composite
def descriptor_bytes(draw: st.DrawFn) -> bytes:
    """A real descriptor with a few bytes changed, cut or extended, mostly with a valid
    checksum again (so the body's codes are read); or random bytes."""
    if draw(st.integers(0, 9)) == 0:
        return draw(st.binary(max_size=64))
    data = bytearray(draw(st.sampled_from(seed_descriptors())))
    for _ in range(draw(st.integers(0, 4))):
        i = draw(st.integers(0, len(data) - 1))
        data[i] = draw(_u8)
    if draw(st.booleans()):
        data = data[:draw(st.integers(0, len(data)))]
    if draw(st.integers(0, 4)) == 0:
        data += draw(st.binary(max_size=8))
    return with_checksum(bytes(data)) if draw(st.integers(0, 4)) else bytes(data)


def check_descriptor(data: bytes) -> None:
    from robotd.floor.descriptor import decode

    decode(data)


# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Target:
    """A fuzzing target: its input strategy, its check, and the error it may raise."""

    name: str
    strategy: st.SearchStrategy[Any]
    check: Callable[[Any], None]
    allowed: tuple[type[BaseException], ...]


TARGETS: tuple[Target, ...] = (
    Target("kobuki_parser", kobuki_stream(), check_kobuki, ()),
    Target("spy_capture", capture_input, check_capture, ()),
    Target("g2o_reader", g2o_input, check_g2o, (GraphError,)),
    Target("floor_descriptor_decode", descriptor_bytes(), check_descriptor, (DescriptorError,)),
)


def run_one(target: Target, example: Any) -> BaseException | None:
    """Run one input; the crash (an exception not in ``target.allowed``), else None."""
    try:
        target.check(example)
    except target.allowed:
        return None
    except Exception as exc:  # a crash, reported by the caller
        return exc
    return None
