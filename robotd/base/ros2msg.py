"""The ROS 2 message model: the message types robotd speaks, defined once, and their CDR.

Every ROS 2 message robotd writes or reads (to DDS, into MCAP recordings, to Foxglove,
from ROS 2 topics) is defined here by its ``.msg`` text (:data:`DEFINITIONS`) and encoded
or decoded by one codec compiled from that text (:func:`encode`, :func:`decode`). The
same text, with its dependencies appended, is the ``ros2msg`` schema that MCAP files and
the Foxglove server carry (:func:`schema_text`), and names the DDS type
(:func:`dds_type_name`) that ROS 2's DDS middlewares expect.

Why here, in the base layer: the drivers (the MCAP recorder, the ROS 2 input drivers) may
import only :mod:`robotd.base`, and the outputs (the app's ROS 2 and Foxglove sinks) need
the same bytes, so the one model sits where both can reach it. It does no I/O.

Encoding (what ROS 2's ``rmw`` implementations put on the wire, and ``rosbag2`` into a
file): the 4-byte encapsulation header ``00 01 00 00`` (plain CDR, little endian; XCDR1),
then the fields in order, each primitive aligned to its own size (at most 8) counted from
the end of the header; ``string`` as a ``uint32`` length including the terminating NUL,
the bytes, and the NUL; ``T[]`` as a ``uint32`` count and the elements; ``T[N]`` as the N
elements alone; nested messages inline, with no alignment of their own. All structs are
``final`` (no ``@appendable``/``@mutable`` headers), which is how ROS 2 defines them.

Messages are plain ``dict`` trees keyed by field name (what ``mcap-ros2-support`` and
most ROS 2 Python tools use). A field missing from a dict encodes as its default: the
literal default of the definition when it has one (``Quaternion.w`` is 1), otherwise
zero, ``""``, an empty sequence, or a zero-filled fixed array. ``uint8[]``/``uint8[N]``
fields take and give ``bytes``. Decoding gives dicts with every field, lists for arrays
and ``bytes`` for byte arrays.

The builder functions at the end turn robotd's own values (stamps in ns, planar poses,
3x3 covariances) into these dicts, so every output writes a pose or a transform the same
way (REP 103: x forward, y left, yaw counter-clockwise; REP 105 frames).
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

NS_PER_S = 1_000_000_000
MAX_STAMP_NS = (1 << 31) * NS_PER_S
"""``builtin_interfaces/Time.sec`` is an ``int32``: stamps must be below 2^31 s."""

CDR_LE_HEADER = b"\x00\x01\x00\x00"
"""Encapsulation header of plain CDR, little endian (XCDR1)."""

# --------------------------------------------------------------------------------------
# Definitions (ROS 2 Humble, Jazzy and Kilted agree on every one of them; checked against
# the rosbags type stores of the three in tests/base/test_ros2msg.py)
# --------------------------------------------------------------------------------------

DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "builtin_interfaces/msg/Duration": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "std_msgs/msg/ColorRGBA": "float32 r\nfloat32 g\nfloat32 b\nfloat32 a\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/msg/PoseStamped": "std_msgs/Header header\nPose pose\n",
    "geometry_msgs/msg/PoseWithCovariance": "Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "std_msgs/Header header\nPoseWithCovariance pose\n",
    "geometry_msgs/msg/Twist": "Vector3 linear\nVector3 angular\n",
    "geometry_msgs/msg/TwistWithCovariance": "Twist twist\nfloat64[36] covariance\n",
    "geometry_msgs/msg/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/msg/TransformStamped": (
        "std_msgs/Header header\n"
        "string child_frame_id\n"
        "Transform transform\n"
    ),
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "nav_msgs/msg/Odometry": (
        "std_msgs/Header header\n"
        "string child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\n"
        "geometry_msgs/TwistWithCovariance twist\n"
    ),
    "nav_msgs/msg/Path": "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n",
    "sensor_msgs/msg/Imu": (
        "std_msgs/Header header\n"
        "geometry_msgs/Quaternion orientation\n"
        "float64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\n"
        "float64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\n"
        "float64[9] linear_acceleration_covariance\n"
    ),
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "sensor_msgs/msg/Image": (
        "std_msgs/Header header\n"
        "uint32 height\n"
        "uint32 width\n"
        "string encoding\n"
        "uint8 is_bigendian\n"
        "uint32 step\n"
        "uint8[] data\n"
    ),
    "sensor_msgs/msg/RegionOfInterest": (
        "uint32 x_offset\n"
        "uint32 y_offset\n"
        "uint32 height\n"
        "uint32 width\n"
        "bool do_rectify\n"
    ),
    "sensor_msgs/msg/CameraInfo": (
        "std_msgs/Header header\n"
        "uint32 height\n"
        "uint32 width\n"
        "string distortion_model\n"
        "float64[] d\n"
        "float64[9] k\n"
        "float64[9] r\n"
        "float64[12] p\n"
        "uint32 binning_x\n"
        "uint32 binning_y\n"
        "RegionOfInterest roi\n"
    ),
    "visualization_msgs/msg/UVCoordinate": "float32 u\nfloat32 v\n",
    "visualization_msgs/msg/MeshFile": "string filename\nuint8[] data\n",
    "visualization_msgs/msg/Marker": (
        "int32 ARROW=0\nint32 CUBE=1\nint32 SPHERE=2\nint32 CYLINDER=3\nint32 LINE_STRIP=4\n"
        "int32 LINE_LIST=5\nint32 CUBE_LIST=6\nint32 SPHERE_LIST=7\nint32 POINTS=8\n"
        "int32 TEXT_VIEW_FACING=9\nint32 MESH_RESOURCE=10\nint32 TRIANGLE_LIST=11\n"
        "int32 ARROW_STRIP=12\n"
        "int32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\nint32 DELETEALL=3\n"
        "std_msgs/Header header\n"
        "string ns\n"
        "int32 id\n"
        "int32 type\n"
        "int32 action\n"
        "geometry_msgs/Pose pose\n"
        "geometry_msgs/Vector3 scale\n"
        "std_msgs/ColorRGBA color\n"
        "builtin_interfaces/Duration lifetime\n"
        "bool frame_locked\n"
        "geometry_msgs/Point[] points\n"
        "std_msgs/ColorRGBA[] colors\n"
        "string texture_resource\n"
        "sensor_msgs/CompressedImage texture\n"
        "UVCoordinate[] uv_coordinates\n"
        "string text\n"
        "string mesh_resource\n"
        "MeshFile mesh_file\n"
        "bool mesh_use_embedded_materials\n"
    ),
    "visualization_msgs/msg/MarkerArray": "Marker[] markers\n",
    "diagnostic_msgs/msg/KeyValue": "string key\nstring value\n",
    "diagnostic_msgs/msg/DiagnosticStatus": (
        "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\n"
        "byte level\n"
        "string name\n"
        "string message\n"
        "string hardware_id\n"
        "KeyValue[] values\n"
    ),
    "diagnostic_msgs/msg/DiagnosticArray": "std_msgs/Header header\nDiagnosticStatus[] status\n",
    "robotd_msgs/msg/WheelTicks": (
        "# Raw wheel encoder counters of a differential-drive base, as the base reports them.\n"
        "# The counters wrap at 16 bits; consumers unwrap consecutive differences.\n"
        "std_msgs/Header header\n"
        "uint16 left_ticks   # left wheel encoder counter, ticks, 0..65535, wrapping\n"
        "uint16 right_ticks  # right wheel encoder counter, ticks, 0..65535, wrapping\n"
        "uint16 device_ms    # the base's own millisecond clock, 0..65535, wrapping\n"
    ),
}

# struct format and size of each primitive
_PRIMITIVES: dict[str, tuple[str, int]] = {
    "bool": ("?", 1), "byte": ("B", 1), "char": ("B", 1), "int8": ("b", 1), "uint8": ("B", 1),
    "int16": ("h", 2), "uint16": ("H", 2), "int32": ("i", 4), "uint32": ("I", 4),
    "int64": ("q", 8), "uint64": ("Q", 8), "float32": ("f", 4), "float64": ("d", 8),
}
_STRINGS = frozenset({"string", "wstring"})
_FIELD = re.compile(r"^([A-Za-z][\w/]*)(<=\d+)?(\[(<=)?(\d*)\])?\s+([A-Za-z]\w*)\s*(.*)$")


@dataclass(frozen=True)
class Field:
    """One field of a message definition.

    ``type``: a primitive name, ``"string"``, or a full message name
    (``"pkg/msg/Name"``); ``array``: ``None`` (a single value), ``"fixed"`` (``length``
    elements) or ``"sequence"`` (any number); ``default``: the literal default, or None.
    """

    name: str
    type: str
    array: str | None = None
    length: int = 0
    default: str | None = None


def parse_definition(full_name: str, text: str) -> list[Field]:
    """The fields of ``text`` (a ``.msg`` body) for the type ``full_name``; constants and
    comments are skipped. Raises ``ValueError`` naming the line it cannot read."""
    pkg = full_name.split("/")[0]
    fields: list[Field] = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        m = _FIELD.match(line)
        if m is None:
            raise ValueError(f"{full_name}: cannot read the field line {raw!r}")
        ftype, _bound, arr, _upper, length, name, rest = m.groups()
        if rest.startswith("="):
            continue  # a constant
        if ftype not in _PRIMITIVES and ftype not in _STRINGS:
            parts = ftype.split("/")
            if len(parts) == 1:
                ftype = f"{pkg}/msg/{parts[0]}"
            elif len(parts) == 2:
                ftype = f"{parts[0]}/msg/{parts[1]}"
        array = None if arr is None else ("fixed" if length and not _upper else "sequence")
        fields.append(Field(name, ftype, array, int(length) if array == "fixed" else 0,
                            rest.strip() or None))
    return fields


def dependencies(full_name: str, definitions: Mapping[str, str] = DEFINITIONS) -> list[str]:
    """Full names of the message types ``full_name`` uses, depth first, each once."""
    out: list[str] = []
    for f in parse_definition(full_name, definitions[full_name]):
        if f.type in _PRIMITIVES or f.type in _STRINGS:
            continue
        for d in (f.type, *dependencies(f.type, definitions)):
            if d not in out:
                out.append(d)
    return out


def schema_text(full_name: str) -> str:
    """The self-contained ``ros2msg`` definition of ``full_name`` (e.g.
    ``"nav_msgs/msg/Odometry"``): its text, then each dependency after a line of 80 ``=``
    and ``MSG: pkg/Name``, as rosbag2, MCAP and Foxglove expect it."""
    parts = [DEFINITIONS[full_name].rstrip("\n")]
    for dep in dependencies(full_name):
        pkg, _, msg = dep.split("/")
        parts.append("=" * 80 + f"\nMSG: {pkg}/{msg}\n" + DEFINITIONS[dep].rstrip("\n"))
    return "\n".join(parts) + "\n"


def parse_schema_text(full_name: str, text: str) -> dict[str, str]:
    """Split a self-contained ``ros2msg`` schema (as :func:`schema_text` writes it, or any
    rosbag2 file holds it) into ``{full name: .msg text}``."""
    out: dict[str, str] = {}
    blocks = re.split(r"^={10,}\s*$", text, flags=re.MULTILINE)
    out[full_name] = blocks[0]
    for block in blocks[1:]:
        block = block.strip("\n")
        head, _, body = block.partition("\n")
        m = re.match(r"^MSG:\s*(\S+)$", head.strip())
        if m is None:
            raise ValueError(f"schema of {full_name}: a block does not start with 'MSG: pkg/Name'")
        name = m.group(1)
        if name.count("/") == 1:
            pkg, msg = name.split("/")
            name = f"{pkg}/msg/{msg}"
        out[name] = body
    return out


def dds_type_name(full_name: str) -> str:
    """The DDS type name ROS 2 gives ``full_name``: ``nav_msgs/msg/Odometry`` ->
    ``nav_msgs::msg::dds_::Odometry_``."""
    pkg, kind, name = full_name.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def dds_topic_name(topic: str, namespace: str = "") -> str:
    """The DDS topic of ROS 2 topic ``topic``: ``rt`` + the fully qualified name.

    A relative ``topic`` (no leading ``/``) is resolved in ``namespace``: ``odometry`` in
    ``/robotd`` -> ``rt/robotd/odometry``; an absolute one (``/tf``) ignores it.
    """
    return "rt" + ros_topic_name(topic, namespace)


def ros_topic_name(topic: str, namespace: str = "") -> str:
    """The fully qualified ROS 2 name of ``topic`` in ``namespace`` (``/ns/topic``)."""
    if not re.fullmatch(r"/?[A-Za-z~][\w/]*", topic) or "//" in topic or topic.endswith("/"):
        raise ValueError(f"{topic!r} is not a valid ROS 2 topic name")
    if topic.startswith("/"):
        return topic
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{ns}/{topic}"


# --------------------------------------------------------------------------------------
# The codec
# --------------------------------------------------------------------------------------


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
        if name in self._dec:
            return self._dec[name]
        parts: list[tuple[str, Decode]] = []

        def dec(r: _Reader) -> dict[str, Any]:
            return {fname: fdec(r) for fname, fdec in parts}

        self._dec[name] = dec
        for f in self._fields(name):
            parts.append((f.name, self._field_decoder(f)))
        return dec

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


# --------------------------------------------------------------------------------------
# Builders: robotd's values -> message dicts
# --------------------------------------------------------------------------------------


def check_stamp(stamp_ns: int) -> int:
    """``stamp_ns`` as an int, or ``ValueError`` when ROS time cannot hold it."""
    s = int(stamp_ns)
    if not 0 <= s < MAX_STAMP_NS:
        raise ValueError(f"stamp_ns {stamp_ns} is outside 0 .. 2^31 s (ROS time)")
    return s


def time_msg(stamp_ns: int) -> dict[str, int]:
    """``builtin_interfaces/Time`` of ``stamp_ns``."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return {"sec": sec, "nanosec": nanosec}


def stamp_ns_of(header: Mapping[str, Any]) -> int:
    """The stamp of a decoded ``std_msgs/Header``, ns."""
    t = header["stamp"]
    return int(t["sec"]) * NS_PER_S + int(t["nanosec"])


def header(stamp_ns: int, frame_id: str) -> dict[str, Any]:
    """``std_msgs/Header``."""
    return {"stamp": time_msg(stamp_ns), "frame_id": frame_id}


def yaw_quaternion(yaw_rad: float) -> dict[str, float]:
    """``geometry_msgs/Quaternion`` of a rotation by ``yaw_rad`` about z."""
    half = 0.5 * float(yaw_rad)
    return {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)}


def yaw_of_quaternion(q: Mapping[str, float]) -> float:
    """The yaw (rad, about z) of a ``geometry_msgs/Quaternion`` dict."""
    x, y, z, w = (float(q[k]) for k in ("x", "y", "z", "w"))
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def planar_pose(x_m: float, y_m: float, yaw_rad: float) -> dict[str, Any]:
    """``geometry_msgs/Pose`` of a planar pose (z = 0)."""
    return {"position": {"x": float(x_m), "y": float(y_m), "z": 0.0},
            "orientation": yaw_quaternion(yaw_rad)}


def covariance6(cov3: np.ndarray) -> list[float]:
    """A ``(3, 3)`` ``(x, y, yaw)`` covariance as the 36 values of a ROS pose covariance
    (rows and columns 0, 1 and 5; z, roll and pitch are fixed on a flat floor: 0)."""
    c = np.asarray(cov3, dtype=np.float64)
    if c.shape != (3, 3):
        raise ValueError(f"pose covariance must be (3, 3), got {c.shape}")
    cov6 = np.zeros((6, 6))
    cov6[np.ix_((0, 1, 5), (0, 1, 5))] = c
    return cov6.ravel().tolist()


def covariance3(cov36: Sequence[float]) -> np.ndarray:
    """The ``(3, 3)`` ``(x, y, yaw)`` block of a ROS 36-value pose or twist covariance."""
    c = np.asarray(cov36, dtype=np.float64).reshape(6, 6)
    return c[np.ix_((0, 1, 5), (0, 1, 5))].copy()


def odometry_msg(stamp_ns: int, x_m: float, y_m: float, yaw_rad: float, cov3: np.ndarray,
                 frame_id: str, child_frame_id: str, *, v_mps: float = 0.0, w_radps: float = 0.0,
                 twist_cov3: np.ndarray | None = None) -> dict[str, Any]:
    """``nav_msgs/Odometry`` of a planar pose (``frame_id``) with its ``(3, 3)``
    covariance, and the body velocity in ``child_frame_id`` (zero with zero covariance
    when not estimated)."""
    return {
        "header": header(stamp_ns, frame_id),
        "child_frame_id": child_frame_id,
        "pose": {"pose": planar_pose(x_m, y_m, yaw_rad), "covariance": covariance6(cov3)},
        "twist": {"twist": {"linear": {"x": float(v_mps)}, "angular": {"z": float(w_radps)}},
                  "covariance": covariance6(np.zeros((3, 3)) if twist_cov3 is None else twist_cov3)},
    }


def pose_with_covariance_msg(stamp_ns: int, frame_id: str, x_m: float, y_m: float, yaw_rad: float,
                             cov3: np.ndarray) -> dict[str, Any]:
    """``geometry_msgs/PoseWithCovarianceStamped`` of a planar pose."""
    return {"header": header(stamp_ns, frame_id),
            "pose": {"pose": planar_pose(x_m, y_m, yaw_rad), "covariance": covariance6(cov3)}}


def transform_msg(stamp_ns: int, parent: str, child: str, xyz: Sequence[float],
                  quat_xyzw: Sequence[float]) -> dict[str, Any]:
    """``geometry_msgs/TransformStamped``: frame ``child`` in frame ``parent``."""
    return {"header": header(stamp_ns, parent), "child_frame_id": child, "transform": {
        "translation": {"x": float(xyz[0]), "y": float(xyz[1]), "z": float(xyz[2])},
        "rotation": {"x": float(quat_xyzw[0]), "y": float(quat_xyzw[1]),
                     "z": float(quat_xyzw[2]), "w": float(quat_xyzw[3])}}}


def planar_transform_msg(stamp_ns: int, parent: str, child: str, pose_xyyaw: Sequence[float]) -> dict[str, Any]:
    """``geometry_msgs/TransformStamped`` of a planar pose ``(x_m, y_m, yaw_rad)``."""
    q = yaw_quaternion(pose_xyyaw[2])
    return transform_msg(stamp_ns, parent, child, (pose_xyyaw[0], pose_xyyaw[1], 0.0),
                         (q["x"], q["y"], q["z"], q["w"]))


def path_msg(stamp_ns: int, frame_id: str, stamps_ns: Sequence[int], poses_xyyaw: np.ndarray) -> dict[str, Any]:
    """``nav_msgs/Path`` of ``(N, 3)`` planar poses with their stamps (ns)."""
    poses = np.asarray(poses_xyyaw, dtype=np.float64).reshape(-1, 3)
    return {"header": header(stamp_ns, frame_id), "poses": [
        {"header": header(int(s), frame_id), "pose": planar_pose(*p)} for s, p in zip(stamps_ns, poses)]}


def line_list_marker(stamp_ns: int, frame_id: str, ns: str, marker_id: int,
                     segments_xy: np.ndarray, rgba: Sequence[float], width_m: float) -> dict[str, Any]:
    """A ``visualization_msgs/Marker`` ``LINE_LIST``: ``(N, 2, 2)`` segments (start and end
    x, y, metres) at z = 0, ``width_m`` wide, colour ``rgba`` (0..1). With no segment it is
    a ``DELETE`` of that id (RViz refuses an empty line list)."""
    seg = np.asarray(segments_xy, dtype=np.float64).reshape(-1, 2, 2)
    points = [{"x": float(x), "y": float(y), "z": 0.0} for x, y in seg.reshape(-1, 2)]
    return {"header": header(stamp_ns, frame_id), "ns": ns, "id": int(marker_id),
            "type": 5, "action": 0 if len(points) else 2,
            "pose": {"orientation": {"w": 1.0}}, "scale": {"x": float(width_m)},
            "color": {"r": rgba[0], "g": rgba[1], "b": rgba[2], "a": rgba[3]},
            "points": points}


def key_values(values: Mapping[str, Any]) -> list[dict[str, str]]:
    """``diagnostic_msgs/KeyValue`` list of a mapping (values as text)."""
    return [{"key": str(k), "value": str(v)} for k, v in values.items()]


def diagnostic_status(level: int, name: str, message: str, hardware_id: str,
                      values: Mapping[str, Any]) -> dict[str, Any]:
    """``diagnostic_msgs/DiagnosticStatus`` (``level``: 0 OK, 1 WARN, 2 ERROR, 3 STALE)."""
    if level not in (0, 1, 2, 3):
        raise ValueError(f"diagnostic level must be 0..3, got {level}")
    return {"level": level, "name": name, "message": message, "hardware_id": hardware_id,
            "values": key_values(values)}


def compressed_image_msg(stamp_ns: int, frame_id: str, image_format: str, data: bytes) -> dict[str, Any]:
    """``sensor_msgs/CompressedImage`` (``image_format``: ``"jpeg"`` or ``"png"``)."""
    return {"header": header(stamp_ns, frame_id), "format": image_format, "data": data}


def imu_yaw_rate_msg(stamp_ns: int, frame_id: str, yaw_rate_radps: float) -> dict[str, Any]:
    """``sensor_msgs/Imu`` holding only a yaw rate: ``angular_velocity.z`` (rad/s); the
    orientation and linear acceleration are "not provided" (covariance[0] = -1) and the
    angular velocity covariance is all zero ("unknown")."""
    return {
        "header": header(stamp_ns, frame_id),
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        "orientation_covariance": [-1.0] + [0.0] * 8,
        "angular_velocity": {"x": 0.0, "y": 0.0, "z": float(yaw_rate_radps)},
        "angular_velocity_covariance": [0.0] * 9,
        "linear_acceleration": {"x": 0.0, "y": 0.0, "z": 0.0},
        "linear_acceleration_covariance": [-1.0] + [0.0] * 8,
    }


def tf_message(transforms: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """``tf2_msgs/TFMessage`` of ``TransformStamped`` dicts."""
    return {"transforms": list(transforms)}
