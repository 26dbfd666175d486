"""Recordings as ROS 2 tools see them: read by an independent reader (rosbags), the /tf
and /tf_static frames, CameraInfo beside each camera, and compact (JPEG) copies."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag2.storage_mcap import McapReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from drivers.recording.reader import RecordingReader, read_recording
from drivers.recording.replay import ReplayDriver
from drivers.recording.transcode import transcode
from drivers.recording.writer import RecordingWriter
from robotd.base.camera import CameraIntrinsics, FloorCameraModel
from robotd.base.clock import ManualClock
from robotd.base.errors import DriverError
from robotd.base.messages import Frame, PoseStamped, WheelTicks
from tests.drivers.test_recording import FLOOR_TOPIC, FORWARD_TOPIC, Run

# A forward camera: level, looking along the robot's x axis, 0.6 m up, 0.1 m ahead.
FORWARD_K = CameraIntrinsics(80, 60, 70.0, 71.0, 39.5, 29.5)
FORWARD_R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
FORWARD_T = np.array([0.1, 0.0, 0.6])
FLOOR = FloorCameraModel(CameraIntrinsics(640, 480, 400.0, 401.0, 319.5, 239.5, (-0.05, 0.01, 0.001, -0.002, 0.0)),
                         height_m=0.4, tilt_rad=math.radians(10.0), offset_x_m=-0.05, offset_y_m=0.02,
                         yaw_rad=math.radians(30.0))


@pytest.fixture(scope="module")
def run() -> Run:
    return Run(duration_s=2.0)


@pytest.fixture(scope="module")
def recording(run: Run, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, int]]:
    """The run written with both cameras described (floor: tilted, turned, offset)."""
    path = tmp_path_factory.mktemp("ros") / "run.mcap"
    with RecordingWriter(path, image_format="jpeg", jpeg_quality=50, chunk_size=16 * 1024) as w:
        w.add_camera("floor", FLOOR.intrinsics, FLOOR.rotation_robot_from_camera, FLOOR.position_robot_m)
        w.add_camera("forward", FORWARD_K, FORWARD_R, FORWARD_T)
        for m in run.base_msgs:
            (w.write_wheel_ticks if isinstance(m, WheelTicks) else w.write_yaw_rate)(m)
        for f in run.frames + run.forward:
            w.write_frame(f)
        for p in run.odom:
            w.write_odometry(p)
            w.write_odometry(p, "/odom/wheel")
        for s, x, y, yaw in run.truth:
            w.write_ground_truth(s, x, y, yaw)
        counts = dict(w.counts)
    return path, counts


def read_with_rosbags(path: Path) -> dict[str, list[object]]:
    """Every message of ``path`` as rosbags decodes it, per topic: its own MCAP reader,
    its own CDR deserialiser, the types built from the definitions the file carries."""
    store = get_typestore(Stores.EMPTY)
    reader = McapReader(path)
    reader.open()
    try:
        for conn in reader.connections:
            store.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
        out: dict[str, list[object]] = {c.topic: [] for c in reader.connections}
        for conn, _t, raw in reader.messages(reader.connections):
            out[conn.topic].append(store.deserialize_cdr(raw, conn.msgtype))
    finally:
        reader.close()
    return out


def assert_same_picture(decoded: np.ndarray, original: np.ndarray, min_corr: float) -> None:
    """Lossy (not equal) but the same picture: pixel correlation at least ``min_corr``.
    The test frames are harsh for JPEG (pixel-level noise; the forward frame is pure
    noise, correlating 0.43 with itself at quality 30 and about 0 with anything else)."""
    assert decoded.shape == original.shape and decoded.dtype == np.uint8
    assert not np.array_equal(decoded, original)
    assert np.corrcoef(decoded.ravel(), original.ravel())[0, 1] >= min_corr


def quat_matrix(q: object) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w  # type: ignore[attr-defined]
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def test_every_topic_decodes_with_an_independent_reader(recording) -> None:
    path, counts = recording
    got = read_with_rosbags(path)
    assert set(got) == set(counts) == {
        "/wheel_ticks", "/imu", FLOOR_TOPIC, FORWARD_TOPIC, "/floor_camera/camera_info",
        "/forward_camera/camera_info", "/odom", "/odom/wheel", "/tf", "/tf_static", "/ground_truth"}
    assert {t: len(m) for t, m in got.items()} == counts
    # The standard types also decode with the official ROS 2 definitions (rosbags' own
    # Humble store): our embedded definitions lay out the same bytes.
    humble = get_typestore(Stores.ROS2_HUMBLE)
    reader = McapReader(path)
    reader.open()
    try:
        official = {c.topic: c.msgtype for c in reader.connections if not c.msgtype.startswith("robotd_msgs/")}
        decoded = {t: 0 for t in official}
        for conn, _t, raw in reader.messages([c for c in reader.connections if c.topic in official]):
            humble.deserialize_cdr(raw, conn.msgtype)
            decoded[conn.topic] += 1
    finally:
        reader.close()
    assert decoded == {t: counts[t] for t in official}


def test_images_and_odometry_read_by_rosbags_match_what_was_written(run: Run, recording) -> None:
    path, _ = recording
    got = read_with_rosbags(path)
    floor = got[FLOOR_TOPIC]
    assert [m.format for m in floor] == ["jpeg"] * len(run.frames)
    for msg, frame in zip(floor, run.frames, strict=True):
        image = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED)
        assert image.shape == frame.image.shape
        assert_same_picture(image, frame.image, min_corr=0.8)
    odom = got["/odom"]
    for msg, want in zip(odom, run.odom, strict=True):
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == want.stamp_ns
        assert (msg.pose.pose.position.x, msg.pose.pose.position.y) == (want.x_m, want.y_m)


def test_tf_carries_odom_to_base_footprint_at_every_odometry(run: Run, recording) -> None:
    path, _ = recording
    tfs = read_with_rosbags(path)["/tf"]
    assert len(tfs) == len(run.odom)  # /odom only, not /odom/wheel
    for msg, want in zip(tfs, run.odom, strict=True):
        (t,) = msg.transforms
        assert (t.header.frame_id, t.child_frame_id) == ("odom", "base_footprint")
        assert t.header.stamp.sec * 10**9 + t.header.stamp.nanosec == want.stamp_ns
        tr = t.transform.translation
        assert (tr.x, tr.y, tr.z) == (want.x_m, want.y_m, 0.0)
        r = quat_matrix(t.transform.rotation)
        assert math.isclose(math.atan2(r[1, 0], r[0, 0]), want.yaw_rad, abs_tol=1e-12)


def test_tf_static_places_each_camera_where_its_model_says(recording) -> None:
    path, _ = recording
    (static,) = read_with_rosbags(path)["/tf_static"]  # both cameras added before the first write
    by_child = {t.child_frame_id: t for t in static.transforms}
    assert {c: t.header.frame_id for c, t in by_child.items()} == {
        "base_link": "base_footprint", "gyro_link": "base_link",
        "floor_camera_optical_frame": "base_link", "forward_camera_optical_frame": "base_link"}
    floor = by_child["floor_camera_optical_frame"].transform
    rot = quat_matrix(floor.rotation)
    np.testing.assert_allclose(rot, FLOOR.rotation_robot_from_camera, atol=1e-12)
    tr = floor.translation
    assert (tr.x, tr.y, tr.z) == (-0.05, 0.02, 0.4)
    # The floor camera looks down, leaning 10 degrees forward: its optical axis in the robot frame.
    np.testing.assert_allclose(rot[:, 2], [math.sin(math.radians(10)), 0.0, -math.cos(math.radians(10))],
                               atol=1e-12)
    fwd = quat_matrix(by_child["forward_camera_optical_frame"].transform.rotation)
    np.testing.assert_allclose(fwd, FORWARD_R, atol=1e-12)
    # A floor point seen by the model at a pixel lies on that pixel's ray through the
    # /tf_static pose: the transform is the model's, not merely some rotation.
    uv = np.array([[100.0, 50.0], [600.0, 400.0]])
    floor_xy = FLOOR.pixel_to_floor_robot(uv)
    k = FLOOR.intrinsics
    for (u, v), (x, y) in zip(uv, floor_xy, strict=True):
        p_cam = rot.T @ (np.array([x, y, 0.0]) - np.array([tr.x, tr.y, tr.z]))
        undist = cv2.undistortPoints(np.array([[[u, v]]]), k.camera_matrix(), k.distortion_array())[0, 0]
        np.testing.assert_allclose(p_cam[:2] / p_cam[2], undist, atol=1e-6)


def test_static_transforms_are_written_again_when_a_camera_is_added_later(tmp_path: Path) -> None:
    path = tmp_path / "late.mcap"
    with RecordingWriter(path) as w:
        w.write_wheel_ticks(WheelTicks(5, 1, 2, 3))
        w.add_camera("forward", FORWARD_K, FORWARD_R, FORWARD_T)
        w.write_frame(Frame(7, "forward", np.zeros((60, 80), np.uint8), 0))
    statics = read_with_rosbags(path)["/tf_static"]
    assert [sorted(t.child_frame_id for t in m.transforms) for m in statics] == [
        ["base_link", "gyro_link"], ["base_link", "forward_camera_optical_frame", "gyro_link"]]
    assert [m.transforms[0].header.stamp.nanosec for m in statics] == [5, 7]


def test_camera_info_beside_every_frame(run: Run, recording) -> None:
    path, counts = recording
    got = read_with_rosbags(path)
    for camera, k, frames in (("floor", FLOOR.intrinsics, run.frames), ("forward", FORWARD_K, run.forward)):
        infos = got[f"/{camera}_camera/camera_info"]
        images = got[f"/{camera}_camera/image/compressed"]
        assert len(infos) == len(images) == len(frames)
        for info, image in zip(infos, images, strict=True):
            assert info.header == image.header  # same stamp, same frame_id
            assert info.header.frame_id == f"{camera}_camera_optical_frame"
            assert (info.width, info.height, info.distortion_model) == (k.width_px, k.height_px, "plumb_bob")
            np.testing.assert_array_equal(info.k.reshape(3, 3), k.camera_matrix())
            np.testing.assert_array_equal(info.d, k.distortion)
            np.testing.assert_array_equal(info.p.reshape(3, 4)[:, :3], k.camera_matrix())


def test_tf_static_is_latched_for_ros2_bag_play(recording) -> None:
    path, _ = recording
    reader = McapReader(path)
    reader.open()
    try:
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
    finally:
        reader.close()
    (profile,) = qos["/tf_static"]
    assert (profile.durability.name, profile.reliability.name, profile.depth) == ("TRANSIENT_LOCAL", "RELIABLE", 1)
    assert qos["/tf"] == []


def test_add_camera_rejects_what_is_not_a_mount(tmp_path: Path) -> None:
    with RecordingWriter(tmp_path / "x.mcap") as w:
        with pytest.raises(ValueError, match="rotation"):
            w.add_camera("floor", FORWARD_K, 2.0 * FORWARD_R, FORWARD_T)
        with pytest.raises(ValueError, match="rotation"):
            w.add_camera("floor", FORWARD_K, -FORWARD_R, FORWARD_T)  # a reflection
        with pytest.raises(ValueError, match="position"):
            w.add_camera("floor", FORWARD_K, FORWARD_R, [0.0, math.nan, 0.0])
        with pytest.raises(ValueError, match="topic"):
            w.add_camera("floor/x", FORWARD_K, FORWARD_R, FORWARD_T)


# -- compact copies --------------------------------------------------------------------

def test_transcode_keeps_every_message_and_reencodes_only_frames(run: Run, tmp_path: Path) -> None:
    png = tmp_path / "png.mcap"
    run.write(png)
    jpeg = tmp_path / "jpeg.mcap"
    res = transcode(png, jpeg, image_format="jpeg", jpeg_quality=30)
    assert (res.frames, res.undecodable_frames) == (len(run.frames) + len(run.forward), 0)
    assert res.bytes_out < res.bytes_in / 2 and res.bytes_out == jpeg.stat().st_size
    with RecordingReader(png) as a, RecordingReader(jpeg) as b:
        raw_a, raw_b = list(a.raw_messages()), list(b.raw_messages())
        assert res.messages == len(raw_a) == len(raw_b)
        for (ca, ma), (cb, mb) in zip(raw_a, raw_b, strict=True):
            assert (ca.topic, ma.log_time, ma.publish_time, ma.sequence) == (
                cb.topic, mb.log_time, mb.publish_time, mb.sequence)
            if "/image/" not in ca.topic:
                assert ma.data == mb.data
        assert b.metadata["robotd"]["image_format"] == "jpeg"
        assert b.metadata["robotd"]["image_quality"] == "jpeg_quality 30"
        assert b.metadata["robotd"]["config_toml"] == a.metadata["robotd"]["config_toml"]
        assert b.metadata["robotd.transcoded"]["source"] == "png.mcap"
        assert b.yaw_source == a.yaw_source
    # Our reader gives the same messages back, frames within JPEG's error.
    got_a, got_b = list(read_recording(png)), list(read_recording(jpeg))
    assert [(t, type(m), m.stamp_ns) for t, m in got_a] == [(t, type(m), m.stamp_ns) for t, m in got_b]
    for (_, ma), (_, mb) in zip(got_a, got_b, strict=True):
        if isinstance(ma, Frame):
            assert (ma.camera, ma.seq, ma.image.shape) == (mb.camera, mb.seq, mb.image.shape)
            assert_same_picture(mb.image, ma.image, min_corr=0.4 if ma.camera == "forward" else 0.8)
        elif isinstance(ma, PoseStamped):
            assert (ma.x_m, ma.y_m, ma.yaw_rad) == (mb.x_m, mb.y_m, mb.yaw_rad)
        else:
            assert ma == mb
    # The very bytes a JPEG recording of the same run at that quality holds.
    direct = tmp_path / "direct.mcap"
    run.write(direct, image_format="jpeg", jpeg_quality=30)
    with RecordingReader(direct) as d, RecordingReader(jpeg) as b:
        frames_d = [m.data for c, m in d.raw_messages() if "/image/" in c.topic]
        frames_b = [m.data for c, m in b.raw_messages() if "/image/" in c.topic]
    assert frames_d == frames_b and len(frames_d) == res.frames
    # And back to PNG: lossless from the JPEG pixels on.
    back = tmp_path / "back.mcap"
    transcode(jpeg, back, image_format="png")
    for (_, mb), (_, mc) in zip(read_recording(jpeg), read_recording(back), strict=True):
        if isinstance(mb, Frame):
            assert np.array_equal(mb.image, mc.image)
    assert set(read_with_rosbags(back)) == set(read_with_rosbags(png))


def test_transcode_refuses_an_existing_target_and_a_non_recording(run: Run, tmp_path: Path) -> None:
    src = tmp_path / "a.mcap"
    with RecordingWriter(src) as w:
        w.write_frame(run.frames[0])
    (tmp_path / "b.mcap").write_bytes(b"keep")
    with pytest.raises(DriverError, match="already exists"):
        transcode(src, tmp_path / "b.mcap", image_format="jpeg")
    assert (tmp_path / "b.mcap").read_bytes() == b"keep"
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(DriverError, match="not a readable recording"):
        transcode(tmp_path / "junk.mcap", tmp_path / "c.mcap", image_format="jpeg")
    with pytest.raises(ValueError):
        transcode(src, tmp_path / "d.mcap", image_format="webp")


def test_replay_of_a_recording_with_ros_extras_hands_out_the_same_driver_messages(
        run: Run, recording, tmp_path: Path) -> None:
    """The extras (/tf, /tf_static, CameraInfo) are not driver output: a replay skips and
    counts them and hands out exactly the base messages and frames, in log-time order."""
    path, counts = recording
    clock = ManualClock()
    with ReplayDriver(path, clock) as replay:
        out = []
        while not replay.done:
            out.extend(replay.read(0.0))
    kinds = [type(m).__name__ for m in out]
    assert sum(isinstance(m, Frame) for m in out) == len(run.frames) + len(run.forward)
    assert kinds.count("WheelTicks") + kinds.count("YawRate") == len(run.base_msgs)
    stamps = [m.stamp_ns for m in out if not isinstance(m, Frame)]
    assert stamps == [m.stamp_ns for m in run.base_msgs]
    with RecordingReader(path) as reader:
        assert sum(1 for _ in reader.messages()) == len(out) + len(run.odom) * 2 + len(run.truth)
        assert reader.skipped == {t: counts[t] for t in (
            "/tf", "/tf_static", "/floor_camera/camera_info", "/forward_camera/camera_info")}


def test_an_old_png_recording_without_ros_extras_still_replays(tmp_path: Path) -> None:
    """A file as robotd wrote it before /tf, CameraInfo and ``image_quality`` existed."""
    from mcap_ros2.writer import Writer as Ros2Writer

    from drivers.recording.schemas import schema_text

    rng = np.random.default_rng(4)
    image = (rng.random((48, 64)) * 255).astype(np.uint8)
    path = tmp_path / "old.mcap"
    with open(path, "wb") as f:
        w = Ros2Writer(f)
        w.add_metadata("robotd", {"robotd_version": "0.1", "config_toml": "", "image_format": "png",
                                  "start_time_utc": "2024-01-01T00:00:00+00:00", "stamp_time_base": "x"})
        ticks = w.register_msgdef("robotd_msgs/msg/WheelTicks", schema_text("robotd_msgs/msg/WheelTicks"))
        img = w.register_msgdef("sensor_msgs/msg/CompressedImage", schema_text("sensor_msgs/msg/CompressedImage"))
        for i in range(3):
            stamp = {"sec": 0, "nanosec": 10 * i}
            w.write_message("/wheel_ticks", ticks, {"header": {"stamp": stamp, "frame_id": "base_link"},
                                                    "left_ticks": i, "right_ticks": 2 * i, "device_ms": i},
                            log_time=10 * i)
            w.write_message(FLOOR_TOPIC, img, {"header": {"stamp": stamp, "frame_id": "floor_camera_optical_frame"},
                                               "format": "png", "data": cv2.imencode(".png", image + i)[1].tobytes()},
                            log_time=10 * i, sequence=i)
        w.finish()
    with ReplayDriver(path, ManualClock()) as replay:
        out = []
        while not replay.done:
            out.extend(replay.read(0.0))
    frames = [m for m in out if isinstance(m, Frame)]
    assert [f.seq for f in frames] == [0, 1, 2]
    for i, f in enumerate(frames):
        assert np.array_equal(f.image, image + i)
    assert [(m.left_ticks, m.right_ticks) for m in out if isinstance(m, WheelTicks)] == [(0, 0), (1, 2), (2, 4)]
    assert set(read_with_rosbags(path)) == {"/wheel_ticks", FLOOR_TOPIC}
