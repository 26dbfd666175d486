"""Kobuki capture decoding (``robotd kobuki decode CAPTURE``): raw bytes or pyserial spy:// hex dumps.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import re
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TextIO

from drivers.kobuki.protocol import (
    FeedbackSubPayload,
    PacketParser,
    UnknownSubPayload,
    decode_feedback,
)
from robotd.base.errors import DriverError, RobotdError
from robotd.base.files import check_output_file, describe_path_kind, replacing

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------
# Capture decoding (``robotd kobuki decode CAPTURE``)
# --------------------------------------------------------------------------------------

_ANSI = re.compile(rb"\x1b\[[0-9;]*m")
_SPY_START = re.compile(rb"\d{6,}\.\d{3} \S")
# pyserial spy:// hexdump line: "{time:010.3f} RX   {offset:04X}  {16 x 'HH '}{' ' at 8} {ascii}"
_SPY_RX = re.compile(rb"\d+\.\d{3} RX   (.*)")
_SPY_RX_DATA = re.compile(rb"[0-9A-F]{4,}  (.*)")
_HEX_CELL = re.compile(rb"[0-9A-Fa-f]{2}")
_SPY_HEX_WIDTH = 16 * 3 + 1
_DETECT_LINES = 64


@dataclasses.dataclass
class SpyDamage:
    """Lines of a ``spy://`` hexdump that could not be read whole."""

    damaged_rx_lines: int = 0
    """RX lines whose hex column is cut or garbled: their bytes up to the damage are used."""
    unrecognised_lines: int = 0
    """Lines that are not pyserial's (blank lines and ``#`` comments are not counted)."""


def _is_comment(line: bytes) -> bool:
    stripped = line.strip()
    return not stripped or stripped.startswith(b"#")


def _spy_rx_bytes(text: bytes, damage: SpyDamage | None = None) -> bytes:
    """The received bytes of a pyserial ``spy://`` hexdump, in order (TX and control
    lines are skipped; the ASCII column is cut off by its fixed position).

    A damaged RX line (cut short, garbled, non-ASCII) gives its hex cells up to the
    damage and is counted in ``damage``, as is a line that is not pyserial's at all.
    """
    damage = damage if damage is not None else SpyDamage()
    chunks = []
    for raw_line in text.splitlines():
        line = _ANSI.sub(b"", raw_line)
        m = _SPY_RX.match(line)
        if m is None:
            if not (_SPY_START.match(line) or _is_comment(line)):
                damage.unrecognised_lines += 1
            continue
        rest = m.group(1).rstrip(b"\r")
        if rest == b"<empty>":
            continue
        data = _SPY_RX_DATA.match(rest)
        cells = data.group(1)[:_SPY_HEX_WIDTH].split() if data else []
        good = []
        for cell in cells:
            if not _HEX_CELL.fullmatch(cell):
                break
            good.append(cell)
        if data is None or not good or len(good) != len(cells):
            damage.damaged_rx_lines += 1
        chunks.append(bytes.fromhex(b"".join(good).decode("ascii")))
    return b"".join(chunks)


def detect_capture_format(data: bytes) -> str:
    """``"spy"`` when ``data`` reads like a pyserial ``spy://`` hexdump, else ``"raw"``:
    most of its first lines (blank lines and ``#`` comments aside) are pyserial's."""
    lines = [_ANSI.sub(b"", line) for line in data.splitlines()[:_DETECT_LINES]]
    lines = [line for line in lines if not _is_comment(line)]
    spy = sum(1 for line in lines if _SPY_START.match(line))
    return "spy" if lines and 2 * spy > len(lines) else "raw"


def _subpayload_dict(item: FeedbackSubPayload) -> dict[str, object]:
    d: dict[str, object] = {"type": item.NAME, "id": item.id if isinstance(item, UnknownSubPayload) else item.ID}
    for f in dataclasses.fields(item):
        value = getattr(item, f.name)
        if f.name != "id":
            d[f.name] = value.hex() if isinstance(value, bytes) else value
    return d


def decode_capture(data: bytes, fmt: str = "auto") -> Iterator[dict[str, object]]:
    """Decode a capture of the Kobuki's output into one dict per valid packet.

    ``fmt`` is ``"raw"`` (the bytes as read from the port), ``"spy"`` (the text pyserial's
    ``spy://`` URL writes; only RX lines count) or ``"auto"``. Each dict has ``packet``
    (index), ``offset`` (byte offset of its header in the received stream) and
    ``subpayloads``; ``malformed`` appears when a sub-payload ended its decoding. The last
    dict is ``{"summary": {...}}`` with the format and the counters of
    :class:`ParserStats`, and for a hexdump those of :class:`SpyDamage`
    (``spy_damaged_rx_lines``, ``spy_unrecognised_lines``).
    """
    if fmt == "auto":
        fmt = detect_capture_format(data)
    if fmt not in ("raw", "spy"):
        raise ValueError(f"unknown capture format {fmt!r}")
    damage = SpyDamage()
    stream = _spy_rx_bytes(data, damage) if fmt == "spy" else data
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
            record: dict[str, object] = {"packet": index, "offset": offset,
                            "subpayloads": [_subpayload_dict(s) for s in items]}
            if stats.malformed_subpayloads != malformed:
                record["malformed"] = True
            index += 1
            yield record
    summary = {"format": fmt, **dataclasses.asdict(stats)}
    if fmt == "spy":
        summary.update({f"spy_{k}": v for k, v in dataclasses.asdict(damage).items()})
    yield {"summary": summary}


def add_decode_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the capture decoder's arguments to ``parser`` (for ``robotd kobuki decode``)."""
    parser.add_argument("capture", type=Path,
                        help="raw serial capture, or a pyserial spy:// hexdump")
    parser.add_argument("--out", type=Path, default=None,
                        help="write the JSON lines to this file (default: stdout)")
    parser.add_argument("--format", choices=("auto", "raw", "spy"), default="auto",
                        help="capture format (default: detect)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing --out file")


def run_decode(args: argparse.Namespace, stdout: TextIO | None = None) -> int:
    """Decode ``args.capture`` to JSON lines; raises :class:`DriverError` on I/O errors.

    The capture must be a file: a serial port or ``/dev/zero`` would be read forever, so a
    device is refused (record the port first: ``robotd record``, or pyserial's ``spy://``).
    ``--out`` is checked before decoding (an existing file needs ``--force``; the capture
    itself is never overwritten) and replaced only when the decoding is complete.
    """
    kind = describe_path_kind(args.capture)
    if kind == "missing":
        raise DriverError(f"capture {args.capture}: no such file")
    if kind != "a regular file":
        raise DriverError(f"capture {args.capture} is {kind}, not a capture file: decode reads a "
                          "recorded file (capture a port with pyserial's spy:// URL, or record "
                          "the robot with `robotd record`)")
    if args.out is not None:
        check_output_file(args.out, force=getattr(args, "force", False), inputs=[args.capture])
    try:
        data = args.capture.read_bytes()
    except OSError as exc:
        raise DriverError(f"cannot read capture {args.capture}: {exc.strerror}") from exc
    with (replacing(args.out) if args.out else contextlib.nullcontext(stdout or sys.stdout)) as out:
        for record in decode_capture(data, args.format):
            out.write(json.dumps(record) + "\n")
    summary = record["summary"]  # the last record is always the summary
    assert isinstance(summary, dict)
    damaged, foreign = summary.get("spy_damaged_rx_lines", 0), summary.get("spy_unrecognised_lines", 0)
    if damaged or foreign:
        log.warning("%s: %d damaged RX lines (read up to the damage) and %d lines that are not "
                    "pyserial's (skipped)", args.capture, damaged, foreign)
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m drivers.kobuki.capture CAPTURE [--out FILE]``: decode a capture to JSON lines."""
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
