"""The CDR codec of the ROS 2 message model (:mod:`robotd.base.ros2msg`): one encoder and
decoder per type, compiled from its ``.msg`` text in :mod:`robotd.base.ros2msg_types`.

Encoding (what ROS 2's ``rmw`` implementations put on the wire, and ``rosbag2`` into a
file): the 4-byte encapsulation header ``00 01 00 00`` (plain CDR, little endian; XCDR1),
then the fields in order, each primitive aligned to its own size (at most 8) counted from
the end of the header; ``string`` as a ``uint32`` length including the terminating NUL,
the bytes, and the NUL; ``T[]`` as a ``uint32`` count and the elements; ``T[N]`` as the N
elements alone; nested messages inline, with no alignment of their own. All structs are
``final`` (no ``@appendable``/``@mutable`` headers), which is how ROS 2 defines them.

Messages are plain ``dict`` trees keyed by field name. A field missing from a dict encodes
as its default: the literal default of the definition when it has one (``Quaternion.w``
is 1), otherwise zero, ``""``, an empty sequence, or a zero-filled fixed array.
``uint8[]``/``uint8[N]`` fields take and give ``bytes``. Decoding gives dicts with every
field, lists for arrays and ``bytes`` for byte arrays.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from robotd.base.ros2msg_types import _PRIMITIVES, _STRINGS, DEFINITIONS, Field, parse_definition

CDR_LE_HEADER = b"\x00\x01\x00\x00"
"""Encapsulation header of plain CDR, little endian (XCDR1)."""


class _Writer:
    __slots__ = ("buf",)

    def __init__(self) -> None:
        self.buf = bytearray(CDR_LE_HEADER)

    def align(self, n: int) -> None:
        pad = -(len(self.buf) - 4) % n
        if pad:
            self.buf += b"\x00" * pad


class _Reader:
    __slots__ = ("data", "pos")

    def __init__(self, data: bytes | memoryview) -> None:
        self.data = memoryview(data)
        self.pos = 4

    def align(self, n: int) -> None:
        self.pos += -(self.pos - 4) % n

    def take(self, n: int) -> memoryview:
        end = self.pos + n
        if end > len(self.data):
            raise ValueError(f"CDR data end at byte {len(self.data)}, {end} needed")
        out = self.data[self.pos:end]
        self.pos = end
        return out


_U32 = struct.Struct("<I")
Encode = Callable[[_Writer, Any], None]
Decode = Callable[[_Reader], Any]


def _default_value(f: Field) -> Any:
    if f.default is None:
        return None
    if f.type in _STRINGS:
        return f.default.strip("'\"")
    if f.type == "bool":
        return f.default.lower() in ("true", "1")
    if f.type in ("float32", "float64"):
        return float(f.default)
    return int(f.default, 0)


class Codec:
    """Encoder and decoder of one message type, compiled from its definition and those of
    its dependencies (``definitions``: full name -> ``.msg`` text)."""

    def __init__(self, full_name: str, definitions: Mapping[str, str] = DEFINITIONS) -> None:
        self.full_name = full_name
        self._defs = definitions
        self._enc: dict[str, Encode] = {}
        self._dec: dict[str, Decode] = {}
        self._encode = self._struct_encoder(full_name)
        self._decode = self._struct_decoder(full_name)

    def encode(self, msg: Mapping[str, Any]) -> bytes:
        """The CDR bytes of ``msg`` (a dict tree), with the encapsulation header."""
        w = _Writer()
        self._encode(w, msg)
        return bytes(w.buf)

    def decode(self, data: bytes | memoryview) -> dict[str, Any]:
        """The dict tree of the CDR bytes ``data`` (with their encapsulation header).
        Raises ``ValueError`` for data that is short or not little-endian plain CDR."""
        if len(data) < 4 or bytes(data[:2]) not in (b"\x00\x01", b"\x00\x00"):
            raise ValueError(f"{self.full_name}: not plain CDR data")
        if bytes(data[:2]) == b"\x00\x00":
            raise ValueError(f"{self.full_name}: big-endian CDR is not supported")
        return self._decode(_Reader(data))

    # -- compilation ---------------------------------------------------------------------

    def _fields(self, name: str) -> list[Field]:
        if name not in self._defs:
            raise ValueError(f"no definition of {name} (needed by {self.full_name})")
        return parse_definition(name, self._defs[name])

    def _flat_layout(self, name: str) -> list[tuple[tuple[str, ...], str, int, Any]] | None:
        """The scalar fields of ``name`` in order, nested messages flattened, as (path,
        struct code, size, default), when every field is a fixed-size scalar (no string,
        no array); None otherwise."""
        out: list[tuple[tuple[str, ...], str, int, Any]] = []
        for f in self._fields(name):
            if f.array is not None or f.type in _STRINGS:
                return None
            if f.type in _PRIMITIVES:
                code, size = _PRIMITIVES[f.type]
                out.append(((f.name,), code, size, _default_value(f)))
                continue
            sub = self._flat_layout(f.type)
            if sub is None:
                return None
            out += [((f.name, *path), code, size, d) for path, code, size, d in sub]
        return out

    def _flat_encoder(self, name: str) -> Encode | None:
        """One ``struct.pack`` for a message of fixed-size scalars (Time, Point, Pose, ...)
        whose first field has the largest alignment: aligned to it, the padding between
        the fields no longer depends on where the message starts, so it is computed once."""
        layout = self._flat_layout(name)
        if not layout or layout[0][2] != max(size for _p, _c, size, _d in layout):
            return None
        fmt, pos = "<", 0
        for _path, code, size, _d in layout:
            pad = -pos % size
            fmt += "x" * pad + code
            pos += pad + size
        packer = struct.Struct(fmt)
        first = layout[0][2]
        paths = [(p, 0 if d is None else d) for p, _c, _s, d in layout]

        def value(msg: Any, path: tuple[str, ...], default: Any) -> Any:
            for key in path:
                if msg is None:
                    return default
                msg = msg.get(key)
            return default if msg is None else msg

        def enc(w: _Writer, msg: Any) -> None:
            w.align(first)
            w.buf += packer.pack(*[value(msg, p, d) for p, d in paths])
        return enc

    def _struct_encoder(self, name: str) -> Encode:
        if name in self._enc:
            return self._enc[name]
        flat = self._flat_encoder(name)
        if flat is not None:
            self._enc[name] = flat
            return flat
        parts: list[tuple[str, Encode, Any]] = []

        def enc(w: _Writer, msg: Any) -> None:
            get = msg.get if msg is not None else (lambda _k: None)
            for fname, fenc, default in parts:
                v = get(fname)
                fenc(w, default if v is None else v)

        self._enc[name] = enc
        for f in self._fields(name):
            parts.append((f.name, self._field_encoder(f), _default_value(f)))
        return enc

    def _field_encoder(self, f: Field) -> Encode:
        if f.type in _PRIMITIVES:
            code, size = _PRIMITIVES[f.type]
            if f.array is None:
                one = struct.Struct("<" + code)

                def enc_prim(w: _Writer, v: Any) -> None:
                    w.align(size)
                    w.buf += one.pack(v if v is not None else 0)
                return enc_prim
            byte_like = f.type in ("uint8", "byte", "char")
            n_fixed = f.length if f.array == "fixed" else None

            def enc_prims(w: _Writer, v: Any) -> None:
                if v is None:
                    v = b"" if n_fixed is None else [0] * n_fixed
                if n_fixed is None:
                    w.align(4)
                    w.buf += _U32.pack(len(v))
                elif len(v) != n_fixed:
                    raise ValueError(f"field {f.name}: {n_fixed} values needed, got {len(v)}")
                if byte_like and isinstance(v, bytes | bytearray | memoryview):
                    w.buf += v
                    return
                if len(v):
                    w.align(size)
                    if isinstance(v, np.ndarray):
                        w.buf += np.ascontiguousarray(v, dtype="<" + code).tobytes()
                    else:
                        w.buf += struct.pack(f"<{len(v)}{code}", *v)
            return enc_prims
        if f.type in _STRINGS:
            def enc_str(w: _Writer, v: Any) -> None:
                b = (v or "").encode()
                w.align(4)
                w.buf += _U32.pack(len(b) + 1)
                w.buf += b
                w.buf += b"\x00"
            if f.array is None:
                return enc_str
            return self._array_encoder(f, enc_str)
        sub = self._struct_encoder(f.type)
        if f.array is None:
            return lambda w, v: sub(w, v or {})
        return self._array_encoder(f, sub)

    @staticmethod
    def _array_encoder(f: Field, one: Encode) -> Encode:
        n_fixed = f.length if f.array == "fixed" else None

        def enc(w: _Writer, v: Any) -> None:
            items = list(v or ())
            if n_fixed is None:
                w.align(4)
                w.buf += _U32.pack(len(items))
            elif len(items) != n_fixed:
                raise ValueError(f"field {f.name}: {n_fixed} values needed, got {len(items)}")
            for item in items:
                one(w, item)
        return enc

    def _struct_decoder(self, name: str) -> Decode:
        """The decoder of a struct: its fields in order, each run of consecutive fixed-size
        fields (scalars, fixed arrays of numbers, nested messages of those) read by one
        ``struct`` call (:class:`_Run`) where the padding inside the run does not depend on
        where it starts; the other fields one by one. The values, and the dict's key order,
        are those of a field-by-field decoding."""
        if name in self._dec:
            return self._dec[name]
        steps: list[tuple[str, Decode] | _Run] = []

        def dec(r: _Reader) -> dict[str, Any]:
            out: dict[str, Any] = {}
            for step in steps:
                if type(step) is _Run:
                    step.read(r, out)
                else:
                    out[step[0]] = step[1](r)  # type: ignore[index]
            return out

        self._dec[name] = dec
        run: _Run | None = None
        for f in self._fields(name):
            shape = self._fixed_shape(f)
            if shape is not None and run is not None and run.takes(shape[0]):
                run.add(f.name, shape)
                continue
            if run is not None:
                steps.append(run.close())
                run = None
            if shape is not None and shape[0] and max(size for _c, size in shape[0]) == shape[0][0][1]:
                run = _Run()
                run.add(f.name, shape)
                continue
            steps.append((f.name, self._field_decoder(f)))
        if run is not None:
            steps.append(run.close())
        return dec

    def _fixed_shape(self, f: Field) -> tuple[list[tuple[str, int]], Any] | None:
        """A fixed-size field as ``(elements, shape)``: the ``(struct code, size)`` of each
        primitive in wire order and how their values make the field's value (``None``: one
        scalar; an int: a list of that many; a list of ``(name, shape)``: a dict). None for a
        field of variable size, bytes (``uint8[N]``), an empty array or an array of
        messages, which decode one by one."""
        if f.type in _STRINGS or f.array == "sequence":
            return None
        if f.type in _PRIMITIVES:
            code, size = _PRIMITIVES[f.type]
            if f.array is None:
                return [(code, size)], None
            if f.type in ("uint8", "byte", "char") or f.length <= 0:
                return None
            return [(code, size)] * f.length, f.length
        if f.array is not None:
            return None
        elements: list[tuple[str, int]] = []
        fields: list[tuple[str, Any]] = []
        for sub in self._fields(f.type):
            got = self._fixed_shape(sub)
            if got is None:
                return None
            elements += got[0]
            fields.append((sub.name, got[1]))
        return elements, fields

    def _field_decoder(self, f: Field) -> Decode:
        if f.type in _PRIMITIVES:
            code, size = _PRIMITIVES[f.type]
            if f.array is None:
                one = struct.Struct("<" + code)

                def dec_prim(r: _Reader) -> Any:
                    r.align(size)
                    return one.unpack(r.take(size))[0]
                return dec_prim
            byte_like = f.type in ("uint8", "byte", "char")
            n_fixed = f.length if f.array == "fixed" else None

            def dec_prims(r: _Reader) -> Any:
                if n_fixed is None:
                    r.align(4)
                    n = _U32.unpack(r.take(4))[0]
                else:
                    n = n_fixed
                if byte_like:
                    return bytes(r.take(n))
                if not n:
                    return []
                r.align(size)
                return list(struct.unpack(f"<{n}{code}", r.take(n * size)))
            return dec_prims
        if f.type in _STRINGS:
            def dec_str(r: _Reader) -> str:
                r.align(4)
                n = _U32.unpack(r.take(4))[0]
                raw = bytes(r.take(n))
                return raw[:-1].decode() if raw.endswith(b"\x00") else raw.decode()
            return dec_str if f.array is None else self._array_decoder(f, dec_str)
        sub = self._struct_decoder(f.type)
        return sub if f.array is None else self._array_decoder(f, sub)

    @staticmethod
    def _array_decoder(f: Field, one: Decode) -> Decode:
        n_fixed = f.length if f.array == "fixed" else None

        def dec(r: _Reader) -> list[Any]:
            if n_fixed is None:
                r.align(4)
                n = _U32.unpack(r.take(4))[0]
                if n > len(r.data):
                    raise ValueError(f"field {f.name}: a sequence of {n} elements cannot fit")
            else:
                n = n_fixed
            return [one(r) for _ in range(n)]
        return dec


class _Run:
    """Consecutive fixed-size fields of a struct read by one ``struct`` call.

    Each primitive of CDR is aligned to its own size (1, 2, 4 or 8) from the end of the
    encapsulation header. A run starts with the field decoding would align first, to
    ``align`` bytes, and takes only primitives no larger than that: every later one's
    padding is then the same wherever the run starts, so it is written into the format once.
    """

    __slots__ = ("align", "fmt", "pos", "fields", "unpack", "size")

    def __init__(self) -> None:
        self.align = 0
        self.fmt = "<"
        self.pos = 0
        self.fields: list[tuple[str, Any]] = []
        self.unpack: Callable[[Any], tuple[Any, ...]] = struct.Struct("<").unpack
        self.size = 0

    def takes(self, elements: list[tuple[str, int]]) -> bool:
        """Whether a field of these elements can join the run."""
        return bool(elements) and all(size <= self.align for _c, size in elements)

    def add(self, name: str, shape: tuple[list[tuple[str, int]], Any]) -> None:
        elements, how = shape
        if not self.align:
            self.align = elements[0][1]
        for code, size in elements:
            pad = -self.pos % size
            self.fmt += "x" * pad + code
            self.pos += pad + size
        self.fields.append((name, how))

    def close(self) -> _Run:
        packer = struct.Struct(self.fmt)
        self.unpack, self.size = packer.unpack, packer.size
        return self

    def read(self, r: _Reader, out: dict[str, Any]) -> None:
        r.align(self.align)
        values = self.unpack(r.take(self.size))
        i = 0
        for name, how in self.fields:
            out[name], i = _made(how, values, i)


def _made(how: Any, values: tuple[Any, ...], i: int) -> tuple[Any, int]:
    """The value of one field of a :class:`_Run` from ``values[i:]`` and the index after it."""
    if how is None:
        return values[i], i + 1
    if type(how) is int:
        return list(values[i:i + how]), i + how
    out: dict[str, Any] = {}
    for name, sub in how:
        out[name], i = _made(sub, values, i)
    return out, i


_CODECS: dict[str, Codec] = {}


def codec(full_name: str) -> Codec:
    """The (cached) codec of one of the types of :data:`DEFINITIONS`."""
    c = _CODECS.get(full_name)
    if c is None:
        if full_name not in DEFINITIONS:
            raise ValueError(f"robotd does not define the ROS 2 type {full_name}")
        c = _CODECS[full_name] = Codec(full_name)
    return c


def encode(full_name: str, msg: Mapping[str, Any]) -> bytes:
    """CDR bytes (with the encapsulation header) of ``msg``, a ``full_name`` dict tree."""
    return codec(full_name).encode(msg)


def decode(full_name: str, data: bytes | memoryview) -> dict[str, Any]:
    """The ``full_name`` dict tree of CDR bytes ``data``."""
    return codec(full_name).decode(data)
