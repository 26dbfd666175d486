"""The ROS 2 message types robotd speaks: their ``.msg`` text, parsed, and the names and
schema text derived from it (part of the message model, :mod:`robotd.base.ros2msg`).

:data:`DEFINITIONS` holds every type's ``.msg`` body, once. From it come the fields
(:func:`parse_definition`), the self-contained ``ros2msg`` schema that MCAP files and the
Foxglove server carry (:func:`schema_text`, :func:`parse_schema_text`), and the DDS type
and topic names ROS 2's middlewares expect (:func:`dds_type_name`, :func:`dds_topic_name`).
The CDR codec compiled from the same text is :mod:`robotd.base.ros2msg_cdr`.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass

# --------------------------------------------------------------------------------------
# Definitions (ROS 2 Humble, Jazzy and Kilted agree on every one of them but
# rmw_dds_common/msg/Gid, see DISTRO_DEFINITIONS; checked against the rosbags type stores
# of the three in tests/base/test_ros2msg.py)
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
    "rmw_dds_common/msg/Gid": "char[16] data\n",
    "rmw_dds_common/msg/NodeEntitiesInfo": (
        "string<=256 node_namespace\n"
        "string<=256 node_name\n"
        "Gid[] reader_gid_seq\n"
        "Gid[] writer_gid_seq\n"
    ),
    "rmw_dds_common/msg/ParticipantEntitiesInfo": "Gid gid\nNodeEntitiesInfo[] node_entities_info_seq\n",
    "robotd_msgs/msg/WheelTicks": (
        "# Raw wheel encoder counters of a differential-drive base, as the base reports them.\n"
        "# The counters wrap at 16 bits; consumers unwrap consecutive differences.\n"
        "std_msgs/Header header\n"
        "uint16 left_ticks   # left wheel encoder counter, ticks, 0..65535, wrapping\n"
        "uint16 right_ticks  # right wheel encoder counter, ticks, 0..65535, wrapping\n"
        "uint16 device_ms    # the base's own millisecond clock, 0..65535, wrapping\n"
    ),
}

DISTROS = ("humble", "jazzy", "kilted")
"""The ROS 2 distributions robotd's definitions are checked against."""

DISTRO_DEFINITIONS: dict[str, dict[str, str]] = {
    # A participant's GID was 24 bytes until Humble, the 16 of the DDS GUID since Iron.
    "humble": {"rmw_dds_common/msg/Gid": "char[24] data\n"},
}
"""Where a distribution's definition differs from :data:`DEFINITIONS` (which is Jazzy's
and Kilted's)."""


def definitions(distro: str | None = None) -> dict[str, str]:
    """Every definition as ``distro`` (one of :data:`DISTROS`; None: Jazzy) has it."""
    if distro is not None and distro not in DISTROS:
        raise ValueError(f"ROS 2 distribution {distro!r} is not one of {', '.join(DISTROS)}")
    return {**DEFINITIONS, **DISTRO_DEFINITIONS.get(distro or "jazzy", {})}


def gid_size(distro: str | None = None) -> int:
    """Bytes of ``rmw_dds_common/msg/Gid.data`` in ``distro`` (24 in Humble, else 16)."""
    return 24 if distro == "humble" else 16


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
