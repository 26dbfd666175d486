"""Kobuki feedback parsing speed against the serial line rate and a naive parser.

A seeded stream of realistic feedback (the sub-payloads a Kobuki streams by default at
50 Hz: basic sensor data, docking IR, inertial, cliff, current, 2-3 raw gyro samples,
general-purpose input) with about 10 % garbage runs, corrupted and truncated packets is
parsed by :class:`drivers.kobuki.protocol.PacketParser` (alone, in 64-byte reads as a 115200-baud
port delivers them, and with :func:`drivers.kobuki.protocol.decode_feedback`) and by a byte-at-a-time
state machine written here, the naive baseline. Reported: median bytes/s and spread over
repeats after a warm-up, the ratio to the line rate (115200 baud 8N1 = 11520 bytes/s) and
to the naive parser, and whether every valid packet was recovered.

Run: ``.venv/bin/python bench/bench_kobuki.py [--packets 20000] [--out FILE]``.
"""

from __future__ import annotations

import argparse
import random
import sys
from pathlib import Path

try:
    from bench.common import machine_info, print_table, time_repeats, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, time_repeats, write_json

from drivers.kobuki.protocol import (
    LINE_RATE_BYTES_PER_S,
    BasicSensorData,
    InertialData,
    PacketParser,
    RawGyroData,
    UnknownSubPayload,
    decode_feedback,
    encode_feedback,
)

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "kobuki.json"


def feedback_packet(rng: random.Random, ts_ms: int, left: int, right: int) -> bytes:
    """One packet of the Kobuki's default 50 Hz stream (79 or 85 bytes)."""
    return encode_feedback(
        BasicSensorData(ts_ms & 0xFFFF, 0, 0, 0, left & 0xFFFF, right & 0xFFFF,
                        rng.randint(-30, 30), rng.randint(-30, 30), 0, 0, 158, 0),
        UnknownSubPayload(3, bytes(3)),  # docking IR
        InertialData(rng.randint(-18000, 18000), rng.randint(-2000, 2000)),
        UnknownSubPayload(5, bytes(rng.randrange(256) for _ in range(6))),  # cliff ADC
        UnknownSubPayload(6, bytes(2)),  # motor current
        RawGyroData(rng.randrange(256), tuple(
            (rng.randint(-300, 300), rng.randint(-300, 300), rng.randint(-4000, 4000))
            for _ in range(rng.choice((2, 3))))),
        UnknownSubPayload(16, bytes(16)),  # general-purpose input
    )


def build_stream(n_packets: int, seed: int) -> tuple[bytes, list[bytes], dict[str, int]]:
    """The stream, its valid packets in order, and what was mixed in."""
    rng = random.Random(seed)
    out = bytearray()
    valid: list[bytes] = []
    mix = {"garbage_runs": 0, "garbage_run_bytes": 0, "corrupted": 0, "truncated": 0}
    left = right = 0
    for k in range(n_packets):
        left += rng.randint(0, 40)
        right += rng.randint(0, 40)
        packet = feedback_packet(rng, 20 * k, left, right)
        r = rng.random()
        if r < 0.06:
            run = bytes(rng.randrange(256) for _ in range(rng.randint(1, 150)))
            out += run
            mix["garbage_runs"] += 1
            mix["garbage_run_bytes"] += len(run)
        elif r < 0.08:
            k_bad = rng.randrange(3, len(packet))
            out += packet[:k_bad] + bytes([packet[k_bad] ^ rng.randint(1, 255)]) + packet[k_bad + 1:]
            mix["corrupted"] += 1
            continue
        elif r < 0.10:
            out += packet[:rng.randint(3, len(packet) - 2)]
            mix["truncated"] += 1
            continue
        out += packet
        valid.append(packet)
    return bytes(out), valid, mix


def naive_parse(data: bytes) -> list[bytes]:
    """The straightforward parser: a byte-at-a-time state machine (header, header, length,
    payload, checksum) that, like PacketParser, rescans from the byte after a rejected
    header. It trusts the 8-bit checksum alone, so about 1 in 256 cut-short packets passes
    and swallows the valid packet behind it (PacketParser checks for that overlap)."""
    out: list[bytes] = []
    n = len(data)
    i = 0
    state = 0
    start = length = cs = 0
    payload = bytearray()
    while i < n:
        b = data[i]
        if state == 0:
            if b == 0xAA:
                state, start = 1, i
        elif state == 1:
            if b == 0x55:
                state = 2
            elif b == 0xAA:
                start = i
            else:
                state = 0
        elif state == 2:
            if b < 3:
                state, i = 0, start + 2
                continue
            length, cs, payload, state = b, b, bytearray(), 3
        elif state == 3:
            payload.append(b)
            cs ^= b
            if len(payload) == length:
                state = 4
        else:
            state = 0
            if cs == b:
                out.append(bytes(payload))
            else:
                i = start + 2
                continue
        i += 1
    return out


def parse_whole(stream: bytes) -> list[bytes]:
    parser = PacketParser()
    return parser.feed(stream) + parser.finish()


def parse_chunks(stream: bytes, chunk: int) -> list[bytes]:
    parser = PacketParser()
    out: list[bytes] = []
    for k in range(0, len(stream), chunk):
        out += parser.feed(stream[k:k + chunk])
    return out + parser.finish()


def parse_and_decode(stream: bytes) -> int:
    parser = PacketParser()
    count = 0
    for payload in parser.feed(stream) + parser.finish():
        count += len(decode_feedback(payload, parser.stats))
    return count


def naive_and_decode(stream: bytes) -> int:
    return sum(len(decode_feedback(p)) for p in naive_parse(stream))


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--packets", type=int, default=20_000)
    ap.add_argument("--seed", type=int, default=2015)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--chunk", type=int, default=64, help="read size for the chunked run")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)

    stream, valid, mix = build_stream(args.packets, args.seed)
    expected = [p[3:-1] for p in valid]
    parser = PacketParser()
    got = parser.feed(stream) + parser.finish()
    for payload in got:
        decode_feedback(payload, parser.stats)
    recovered_all = got == expected
    naive = naive_parse(stream)
    naive_valid = len(set(naive) & set(expected))
    naive_bogus = len(naive) - naive_valid
    chunked_same = parse_chunks(stream, args.chunk) == got

    cases = [
        ("PacketParser", "framing", lambda: parse_whole(stream)),
        (f"PacketParser, {args.chunk}-byte reads", "framing",
         lambda: parse_chunks(stream, args.chunk)),
        ("naive byte-at-a-time", "framing", lambda: naive_parse(stream)),
        ("PacketParser + decode_feedback", "framing+decode", lambda: parse_and_decode(stream)),
        ("naive + decode_feedback", "framing+decode", lambda: naive_and_decode(stream)),
    ]
    results = []
    for name, stage, fn in cases:
        timing = time_repeats(fn, repeats=args.repeats, warmup=args.warmup)
        results.append({"name": name, "stage": stage, **timing,
                         "bytes_per_s": len(stream) / timing["median_s"]})
    naive_rate = {r["stage"]: r["bytes_per_s"] for r in results if r["name"].startswith("naive")}
    for r in results:
        r["x_line_rate"] = r["bytes_per_s"] / LINE_RATE_BYTES_PER_S
        r["x_naive"] = r["bytes_per_s"] / naive_rate[r["stage"]]

    print(f"stream: {len(stream)} bytes, {args.packets} packets "
          f"({len(valid)} valid, {mix['corrupted']} corrupted, {mix['truncated']} truncated, "
          f"{mix['garbage_runs']} garbage runs of {mix['garbage_run_bytes']} bytes); "
          f"{1 - sum(map(len, valid)) / len(stream):.1%} of the bytes are not valid packets")
    print_table(
        ["method", "stage", "median MB/s", "IQR ms", "x line rate", "x naive"],
        [[r["name"], r["stage"], round(r["bytes_per_s"] / 1e6, 2), round(r["iqr_s"] * 1e3, 2),
          round(r["x_line_rate"]), round(r["x_naive"], 1)] for r in results])
    print(f"PacketParser recovered every valid packet: {recovered_all} ({len(got)}/{len(valid)}),"
          f" same in {args.chunk}-byte reads: {chunked_same}; naive recovered {naive_valid}/"
          f"{len(valid)} and returned {naive_bogus} bogus packets")
    print(f"parser stats: {parser.stats}")

    path = write_json(args.out, {
        "benchmark": "kobuki_packet_parser",
        "machine": machine_info(),
        "config": {"packets": args.packets, "seed": args.seed, "repeats": args.repeats,
                   "warmup": args.warmup, "chunk_bytes": args.chunk,
                   "line_rate_bytes_per_s": LINE_RATE_BYTES_PER_S},
        "stream": {"bytes": len(stream), "valid_packets": len(valid),
                   "valid_bytes": sum(map(len, valid)), **mix},
        "results": results,
        "recovered_all_valid": recovered_all,
        "recovered_packets": len(got),
        "naive_recovered_packets": naive_valid,
        "naive_bogus_packets": naive_bogus,
        "chunked_same_packets": chunked_same,
        "parser_stats": {k: getattr(parser.stats, k) for k in parser.stats.__dataclass_fields__},
    })
    print(f"wrote {path}")
    return 0 if recovered_all and chunked_same else 1


if __name__ == "__main__":
    sys.exit(main())
