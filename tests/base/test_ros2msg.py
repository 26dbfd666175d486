"""The ROS 2 message model against an independent implementation: rosbags' CDR
serialiser and type stores of ROS 2 Humble, Jazzy and Kilted (golden bytes)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Nodetype

from robotd.base import ros2msg as r

DISTROS = {"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY, "kilted": Stores.ROS2_KILTED}

_STORES: dict[str, object] = {}


def store(distro: str):
    ts = _STORES.get(distro)
    if ts is None:
        ts = get_typestore(DISTROS[distro])
        # robotd's own type: its definition text must be valid for rosbags' parser too.
        ts.register(get_types_from_msg(r.DEFINITIONS["robotd_msgs/msg/WheelTicks"],
                                       "robotd_msgs/msg/WheelTicks"))
        _STORES[distro] = ts
    return ts


_NUMPY = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
          "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
          "int64": np.int64, "uint64": np.uint64, "float32": np.float32, "float64": np.float64}


def to_rosbags(ts, typename: str, value: dict):
    """A rosbags message object from a complete dict tree (field names from rosbags' own
    definitions: a name robotd got wrong is a KeyError)."""
    cls = ts.types[typename]
    kwargs = {}
    for name, (kind, spec) in ts.fielddefs[typename][1]:
        v = value[name]
        if kind == Nodetype.BASE:
            kwargs[name] = v
        elif kind == Nodetype.NAME:
            kwargs[name] = to_rosbags(ts, spec, v)
        else:  # ARRAY or SEQUENCE
            (ekind, espec), _n = spec
            if ekind == Nodetype.BASE and espec[0] != "string":
                kwargs[name] = np.frombuffer(v, np.uint8).copy() if isinstance(v, bytes) \
                    else np.asarray(v, dtype=_NUMPY[espec[0]])
            elif ekind == Nodetype.BASE:
                kwargs[name] = list(v)
            else:
                kwargs[name] = [to_rosbags(ts, espec, e) for e in v]
    return cls(**kwargs)


def from_rosbags(obj) -> object:
    """A rosbags object (or value) as plain Python values, for comparison."""
    if hasattr(obj, "__dataclass_fields__"):
        return {k: from_rosbags(getattr(obj, k)) for k in obj.__dataclass_fields__
                if not k.isupper() and k != "__msgtype__"}
    if isinstance(obj, np.ndarray):
        return obj.tobytes() if obj.dtype == np.uint8 else obj.tolist()
    if isinstance(obj, list):
        return [from_rosbags(e) for e in obj]
    return obj


def samples(distro: str | None = None) -> dict[str, dict]:
    """One message of every top-level type robotd speaks, with odd-length strings (to move
    the alignment around) and values that are not zero (the discovery message with
    ``distro``'s GID size)."""
    rng = np.random.default_rng(7)
    cov = rng.normal(size=(3, 3))
    cov = cov @ cov.T
    stamp = 1_234_567_891_011
    tf = r.tf_message([r.planar_transform_msg(stamp, "map", "odom", (1.5, -2.25, 0.7)),
                       r.transform_msg(stamp + 1, "base_link", "floor_camera_optical_frame",
                                       (0.1, 0.0, 0.25), (0.5, -0.5, 0.5, -0.5))])
    odom = r.odometry_msg(stamp, 3.0, -1.0, -2.5, cov, "odom", "base_footprint",
                          v_mps=0.31, w_radps=-0.2, twist_cov3=np.diag([1e-3, 1e-3, 4e-3]))
    path = r.path_msg(stamp, "map", [stamp - 2, stamp - 1], rng.normal(size=(2, 3)))
    markers = {"markers": [
        r.line_list_marker(stamp, "map", "loops", 1, rng.normal(size=(3, 2, 2)), (1.0, 0.2, 0.1, 0.9), 0.03),
        r.line_list_marker(stamp, "map", "loops_rejected_x", 2, np.zeros((0, 2, 2)), (0.0, 0.0, 1.0, 1.0), 0.02)]}
    diag = {"header": r.header(stamp, ""), "status": [
        r.diagnostic_status(0, "robotd: odometry", "ok", "kobuki", {"wheel_msgs": 1234, "rate_hz": 49.5}),
        r.diagnostic_status(1, "robotd: floor camera", "gap 1.2 s", "", {})]}
    image = {"header": r.header(stamp, "floor_camera_optical_frame"), "height": 2, "width": 3,
             "encoding": "mono8", "is_bigendian": 0, "step": 3, "data": bytes(range(6))}
    info = {"header": r.header(stamp, "cam"), "height": 480, "width": 640,
            "distortion_model": "plumb_bob", "d": [0.1, -0.2, 0.0, 0.001, 0.05],
            "k": [500.0, 0, 320, 0, 500, 240, 0, 0, 1], "r": [1.0, 0, 0, 0, 1, 0, 0, 0, 1],
            "p": [500.0, 0, 320, 0, 0, 500, 240, 0, 0, 0, 1, 0], "binning_x": 1, "binning_y": 2,
            "roi": {"x_offset": 3, "y_offset": 4, "height": 5, "width": 6, "do_rectify": True}}
    return {
        "tf2_msgs/msg/TFMessage": tf,
        "nav_msgs/msg/Odometry": odom,
        "geometry_msgs/msg/PoseWithCovarianceStamped": r.pose_with_covariance_msg(stamp, "map", 1, 2, 3, cov),
        "nav_msgs/msg/Path": path,
        "visualization_msgs/msg/MarkerArray": markers,
        "diagnostic_msgs/msg/DiagnosticArray": diag,
        "sensor_msgs/msg/Imu": r.imu_yaw_rate_msg(stamp, "gyro_link", 0.125),
        "sensor_msgs/msg/CompressedImage": r.compressed_image_msg(stamp, "floor", "jpeg", b"\xff\xd8abc"),
        "sensor_msgs/msg/Image": image,
        "sensor_msgs/msg/CameraInfo": info,
        "robotd_msgs/msg/WheelTicks": {"header": r.header(stamp, "base_link"), "left_ticks": 65535,
                                       "right_ticks": 3, "device_ms": 777},
        "rmw_dds_common/msg/ParticipantEntitiesInfo": r.participant_entities_info(
            bytes(range(1, 17)), "/robot_1", "robotd", [bytes(range(20, 36))],
            [bytes(range(40, 56)), bytes(range(60, 76))], distro),
    }


SAMPLES = samples()


@pytest.mark.parametrize("distro", list(DISTROS))
@pytest.mark.parametrize("typename", list(SAMPLES))
def test_golden_bytes_match_rosbags(distro: str, typename: str) -> None:
    ts = store(distro)
    codec = r.Codec(typename, r.definitions(distro))
    ours = codec.encode(samples(distro)[typename])
    if distro != "humble" or "Gid" not in r.schema_text(typename):
        assert ours == r.encode(typename, samples(distro)[typename])  # the default model is theirs
    complete = codec.decode(ours)
    theirs = bytes(ts.serialize_cdr(to_rosbags(ts, typename, complete), typename))
    assert ours == theirs
    # and rosbags reads our bytes back as the message we meant (not only our decoding)
    back = from_rosbags(ts.deserialize_cdr(ours, typename))
    assert back == complete


@pytest.mark.parametrize("distro", list(DISTROS))
def test_every_definition_has_rosbags_layout(distro: str) -> None:
    """Field names, types and array kinds of every type equal the distro's own."""
    ts = store(distro)
    for typename, text in r.definitions(distro).items():
        ours = r.parse_definition(typename, text)
        theirs = ts.fielddefs[typename][1]
        assert [f.name for f in ours] == [n for n, _ in theirs], typename
        for f, (_n, (kind, spec)) in zip(ours, theirs):
            if kind == Nodetype.BASE:
                assert (f.array, f.type) == (None, spec[0]), (typename, f.name)
            elif kind == Nodetype.NAME:
                assert (f.array, f.type) == (None, spec), (typename, f.name)
            else:
                (ekind, espec), n = spec
                assert f.array == ("fixed" if kind == Nodetype.ARRAY else "sequence"), (typename, f.name)
                assert f.type == (espec[0] if ekind == Nodetype.BASE else espec), (typename, f.name)
                assert f.length == (n if kind == Nodetype.ARRAY else 0)


def test_round_trip_and_defaults() -> None:
    odom = r.decode("nav_msgs/msg/Odometry", r.encode("nav_msgs/msg/Odometry", {}))
    assert odom["pose"]["pose"]["orientation"] == {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
    assert odom["header"]["frame_id"] == "" and odom["pose"]["covariance"] == [0.0] * 36
    cov = np.array([[1.0, 0.1, 0.2], [0.1, 2.0, 0.3], [0.2, 0.3, 3.0]])
    m = r.decode("nav_msgs/msg/Odometry", r.encode(
        "nav_msgs/msg/Odometry", r.odometry_msg(5 * r.NS_PER_S + 7, 1.0, 2.0, 2.9, cov, "odom", "bf")))
    assert r.stamp_ns_of(m["header"]) == 5 * r.NS_PER_S + 7
    assert np.array_equal(r.covariance3(m["pose"]["covariance"]), cov)
    assert math.isclose(r.yaw_of_quaternion(m["pose"]["pose"]["orientation"]), 2.9, abs_tol=1e-12)


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="36 values"):
        r.encode("geometry_msgs/msg/PoseWithCovariance", {"covariance": [0.0] * 35})
    data = r.encode("sensor_msgs/msg/CompressedImage", r.compressed_image_msg(0, "f", "png", b"x" * 10))
    with pytest.raises(ValueError, match="CDR data end"):
        r.decode("sensor_msgs/msg/CompressedImage", data[:-3])
    with pytest.raises(ValueError, match="not plain CDR"):
        r.decode("sensor_msgs/msg/CompressedImage", b"\x00\x07\x00\x00" + data[4:])
    with pytest.raises(ValueError, match="ROS time"):
        r.check_stamp(-1)


def test_names() -> None:
    assert r.dds_type_name("tf2_msgs/msg/TFMessage") == "tf2_msgs::msg::dds_::TFMessage_"
    assert r.dds_topic_name("/tf") == "rt/tf"
    assert r.dds_topic_name("odometry", "/robotd") == "rt/robotd/odometry"
    assert r.dds_topic_name("robotd/path", "") == "rt/robotd/path"
    with pytest.raises(ValueError):
        r.dds_topic_name("bad topic")


def test_schema_text_parses_back() -> None:
    text = r.schema_text("visualization_msgs/msg/MarkerArray")
    defs = r.parse_schema_text("visualization_msgs/msg/MarkerArray", text)
    assert set(defs) == {"visualization_msgs/msg/MarkerArray", *r.dependencies("visualization_msgs/msg/MarkerArray")}
    c = r.Codec("visualization_msgs/msg/MarkerArray", defs)
    msg = SAMPLES["visualization_msgs/msg/MarkerArray"]
    assert c.encode(msg) == r.encode("visualization_msgs/msg/MarkerArray", msg)


def test_runs_of_fixed_fields_decode_as_rosbags_reads_them_wherever_they_start() -> None:
    """The decoder reads consecutive fixed-size fields with one ``struct`` call where their
    padding does not depend on where they start. A type that mixes sizes, shifted by a
    string of every length mod 8 before it, decodes to what rosbags reads from the same
    bytes: the runs break where a larger primitive follows a smaller one (``c`` after ``b``,
    ``a`` after ``c``; ``m``, whose ``y`` is larger than its ``x``, cannot start one), bytes,
    empty arrays and sequences are read one by one."""
    inner = "int8 x\nfloat64 y\n"
    mixed = ("string s\nint16 b\nint32 c\nfloat64 a\nuint16[3] u\nbool f\nfloat32[2] g\n"
             "robotd_test/msg/Inner n\nuint8[2] raw\nint32[0] none\nfloat64[] seq\n"
             "string s2\nrobotd_test/msg/Inner m\ngeometry_msgs/msg/Vector3 v\nint8 last\n")
    defs = {**r.DEFINITIONS, "robotd_test/msg/Mixed": mixed, "robotd_test/msg/Inner": inner}
    ts = get_typestore(Stores.ROS2_JAZZY)
    ts.register({**get_types_from_msg(inner, "robotd_test/msg/Inner"),
                 **get_types_from_msg(mixed, "robotd_test/msg/Mixed")})
    codec = r.Codec("robotd_test/msg/Mixed", defs)
    for k in range(9):
        msg = {"s": "x" * k, "a": 1.5 + k, "b": -3 - k, "c": 70000 + k, "u": [1, 2, 3 + k], "f": bool(k % 2),
               "g": [0.5, -0.25 * k], "n": {"x": -k, "y": 2.0 ** -k}, "raw": bytes([k, 255]),
               "none": [], "seq": [0.1 * k] * (k % 3), "s2": "y" * (k // 2), "m": {"x": k, "y": -1.0 / (k + 1)}, "v": {"x": 1.0, "y": -2.0, "z": 3.0 * k}, "last": k}
        data = codec.encode(msg)
        got = codec.decode(data)
        assert got == msg and list(got) == [line.split()[1] for line in mixed.splitlines()]
        assert got == from_rosbags(ts.deserialize_cdr(data, "robotd_test/msg/Mixed")), k
        with pytest.raises(ValueError, match="CDR data end"):
            codec.decode(data[:len(data) - 1])
