"""Recordings: MCAP round trip, what ROS tools see, damaged files, replay through two sources."""

from __future__ import annotations

import datetime
import errno
import math
import os
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer

from drivers.recording.reader import RecordingReader, read_recording
from drivers.recording.replay import ReplayDriver
from drivers.recording.schemas import PARTIAL_SUFFIX, camera_topic, schema_text
from drivers.recording.writer import RecordingTee, RecordingWriter
from robotd.base.camera import FloorCameraModel
from robotd.base.clock import ManualClock
from robotd.base.errors import DriverError, RecordingError
from robotd.base.geometry import wrap_angle
from robotd.base.messages import Frame, PoseStamped, WheelTicks, YawRate
from sim.cameras.floor import FloorRenderer, RenderParams
from sim.route import MotionLimits, build_route, plan_motion
from sim.emulators.kobuki import simulate_kobuki
from sim.sensors import BaseSensorParams
from sim.world.floor import ImageFloor

FLOOR_TOPIC = "/floor_camera/image/compressed"
FORWARD_TOPIC = "/forward_camera/image/compressed"
CONFIG_TOML = '[base]\ndriver = "kobuki"\n'
START = datetime.datetime(2024, 5, 6, 7, 8, 9, tzinfo=datetime.UTC)


def _spd(rng: np.random.Generator) -> np.ndarray:
    a = rng.normal(size=(3, 3))
    return a @ a.T + 1e-3 * np.eye(3)


class Run:
    """A few seconds of the virtual robot: what was written, in write order."""

    def __init__(self, duration_s: float = 4.0, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        motion = plan_motion(build_route("square"), MotionLimits()).truncated(duration_s)
        base = simulate_kobuki(motion, BaseSensorParams(), rng)
        self.base_msgs = base.messages()
        # A floor texture with structure at several scales, like a photographed floor.
        noise = rng.random((1600, 1600)).astype(np.float32)
        texture = cv2.normalize(cv2.GaussianBlur(noise, (0, 0), 3.0) + 0.3 * noise, None, 0, 255,
                                cv2.NORM_MINMAX).astype(np.uint8)
        floor = ImageFloor(texture, metres_per_px=0.001, origin_xy_m=(-0.5, 0.8))
        renderer = FloorRenderer(floor, FloorCameraModel.default(), RenderParams(), rng)
        self.frames = []
        for j, t in enumerate(np.arange(0.0, duration_s, 0.4)):
            v, w = motion.velocity_at(t)
            image = renderer.render(motion.pose_at(t), v, w, t)
            self.frames.append(Frame(int(round(t * 1e9)), "floor", image, j))
        # A colour forward frame, off the floor frames' times.
        self.forward = [Frame(1_234_567_891, "forward",
                              (rng.random((60, 80, 3)) * 255).astype(np.uint8), 3)]
        ticks = [m for m in self.base_msgs if isinstance(m, WheelTicks)]
        self.odom = [PoseStamped(m.stamp_ns, *base.true_pose[i, :2] + 0.01 * i,
                                 float(np.clip(base.true_pose[i, 2] + 0.3 * i, -3.0, 3.0)),
                                 _spd(rng)) for i, m in enumerate(ticks)]
        self.truth = [(int(s), *map(float, p)) for s, p in zip(base.stamp_ns, base.true_pose, strict=True)]
        # Write order as in the daemon: base and frames interleaved by arrival, odometry
        # later, ground truth at the very end (chunks overlap in time).
        self.written: list[tuple[str, object]] = []

    def write(self, path: Path, **kwargs: object) -> dict[str, int]:
        self.written = []
        kwargs.setdefault("chunk_size", 16 * 1024)
        with RecordingWriter(path, config_toml=CONFIG_TOML, start_time_utc=START, **kwargs) as w:
            model = FloorCameraModel.default()
            w.add_camera("floor", model.intrinsics, model.rotation_robot_from_camera,
                         model.position_robot_m)
            frames = list(self.frames)
            for m in self.base_msgs:
                while frames and frames[0].stamp_ns <= m.stamp_ns - 60_000_000:  # frames lag
                    f = frames.pop(0)
                    w.write_frame(f)
                    self.written.append((FLOOR_TOPIC, f))
                if isinstance(m, WheelTicks):
                    w.write_wheel_ticks(m)
                    self.written.append(("/wheel_ticks", m))
                else:
                    w.write_yaw_rate(m)
                    self.written.append(("/imu", m))
            for f in frames:
                w.write_frame(f)
                self.written.append((FLOOR_TOPIC, f))
            for f in self.forward:
                w.write_frame(f)
                self.written.append((FORWARD_TOPIC, f))
            for p in self.odom:
                w.write_odometry(p)
                self.written.append(("/odom", p))
            for s, x, y, yaw in self.truth:
                w.write_ground_truth(s, x, y, yaw)
                self.written.append(("/ground_truth", PoseStamped(s, x, y, yaw)))
            counts = dict(w.counts)
        return counts

    def expected(self) -> list[tuple[str, object]]:
        """Write order, stably sorted by stamp: the order a reader must give."""
        return sorted(self.written, key=lambda tm: tm[1].stamp_ns)


def assert_same(topic: str, got: object, want: object) -> None:
    assert type(got) is type(want), topic
    if isinstance(want, (WheelTicks, YawRate)):
        assert got == want
    elif isinstance(want, Frame):
        assert (got.stamp_ns, got.camera, got.seq) == (want.stamp_ns, want.camera, want.seq)
        assert got.image.dtype == np.uint8 and got.image.shape == want.image.shape
        assert np.array_equal(got.image, want.image)
    else:
        assert (got.stamp_ns, got.x_m, got.y_m) == (want.stamp_ns, want.x_m, want.y_m)
        assert abs(wrap_angle(got.yaw_rad - want.yaw_rad)) < 1e-12
        assert -math.pi <= got.yaw_rad <= math.pi
        assert np.array_equal(got.covariance, want.covariance)


@pytest.fixture(scope="module")
def run() -> Run:
    return Run()


@pytest.fixture(scope="module")
def recording(run: Run, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, int]]:
    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    counts = run.write(path)
    return path, counts


# -- round trip ------------------------------------------------------------------------

def test_every_message_reads_back_equal_in_stamp_order(run: Run, recording) -> None:
    path, _ = recording
    got = list(read_recording(path))
    want = run.expected()
    assert len(got) == len(want) == len(run.written)
    for (gt, gm), (wt, wm) in zip(got, want, strict=True):
        assert gt == wt
        assert_same(gt, gm, wm)
    stamps = [m.stamp_ns for _, m in got]
    assert stamps == sorted(stamps)
    # the recording really did interleave times across chunks: write order was not sorted
    assert [m.stamp_ns for _, m in run.written] != stamps


def test_topics_schemas_and_metadata(run: Run, recording) -> None:
    path, counts = recording
    with RecordingReader(path) as r:
        assert r.topics == {
            "/wheel_ticks": "robotd_msgs/msg/WheelTicks",
            "/imu": "sensor_msgs/msg/Imu",
            FLOOR_TOPIC: "sensor_msgs/msg/CompressedImage",
            FORWARD_TOPIC: "sensor_msgs/msg/CompressedImage",
            "/odom": "nav_msgs/msg/Odometry",
            "/ground_truth": "nav_msgs/msg/Odometry",
            "/tf": "tf2_msgs/msg/TFMessage",
            "/tf_static": "tf2_msgs/msg/TFMessage",
            "/floor_camera/camera_info": "sensor_msgs/msg/CameraInfo",
        }
        meta = r.metadata["robotd"]
        from robotd import __version__
        
        assert meta["robotd_version"] == __version__
        assert meta["config_toml"] == CONFIG_TOML
        assert meta["start_time_utc"] == "2024-05-06T07:08:09+00:00"
        assert meta["image_format"] == "png"
        assert r.metadata["robotd.end"]["completed"] == "true"
        assert meta["image_quality"] == "png_compression 1"
        # the ROS extras: one /tf per /odom, one CameraInfo per floor frame (the forward
        # camera was not described), /tf_static once (no camera added after the first write)
        extras = {"/tf": len(run.odom), "/floor_camera/camera_info": len(run.frames), "/tf_static": 1}
        assert {t: counts[t] for t in extras} == extras
        assert r.metadata["robotd.end"]["messages"] == str(len(run.written) + sum(extras.values()))
        assert r.yaw_source == "raw_gyro"
        assert r.time_range_ns == (0, max(m.stamp_ns for _, m in run.written))
        assert not r.damage.any
    assert counts["/wheel_ticks"] == sum(isinstance(m, WheelTicks) for m in run.base_msgs)
    assert counts[FLOOR_TOPIC] == len(run.frames)


def test_mcap_summary_shows_channels_and_counts(run: Run, recording) -> None:
    path, counts = recording
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
    assert summary is not None
    by_topic = {ch.topic: ch for ch in summary.channels.values()}
    assert set(by_topic) == set(counts)
    for topic, ch in by_topic.items():
        assert ch.message_encoding == "cdr"
        assert summary.schemas[ch.schema_id].encoding == "ros2msg"
        assert summary.statistics.channel_message_counts[ch.id] == counts[topic]
    assert summary.statistics.message_count == sum(counts.values())
    assert summary.statistics.message_start_time == 0
    assert summary.statistics.message_end_time == max(m.stamp_ns for _, m in run.written)
    assert len(summary.chunk_indexes) > 3  # small chunks: several, overlapping in time


def test_ros_fields_as_ros_tools_decode_them(run: Run, recording) -> None:
    path, _ = recording
    seen: dict[str, object] = {}
    yaw_msg = [m for m in run.base_msgs if isinstance(m, YawRate)][7]
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, channel, message, ros in reader.iter_decoded_messages():
            if (channel.topic == FORWARD_TOPIC or message.log_time == run.odom[7].stamp_ns
                    or (channel.topic == "/imu" and message.log_time == yaw_msg.stamp_ns)):
                seen.setdefault(channel.topic, (message, ros))
    msg, fwd = seen[FORWARD_TOPIC]
    assert (fwd.header.stamp.sec, fwd.header.stamp.nanosec) == (1, 234_567_891)
    assert msg.log_time == msg.publish_time == 1_234_567_891 and msg.sequence == 3
    assert fwd.header.frame_id == "forward_camera_optical_frame" and fwd.format == "png"
    assert fwd.data[:8] == b"\x89PNG\r\n\x1a\n"
    _, imu = seen["/imu"]
    assert imu.angular_velocity.z == yaw_msg.yaw_rate_radps
    assert imu.orientation_covariance[0] == -1.0 and imu.linear_acceleration_covariance[0] == -1.0
    assert imu.header.frame_id == "gyro_link"
    _, odom = seen["/odom"]
    assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "base_footprint")
    cov6 = np.asarray(odom.pose.covariance).reshape(6, 6)
    want = run.odom[7]
    assert np.array_equal(cov6[np.ix_((0, 1, 5), (0, 1, 5))], want.covariance)
    assert np.count_nonzero(cov6) == 9
    q = odom.pose.pose.orientation
    assert (q.x, q.y) == (0.0, 0.0) and math.isclose(q.z, math.sin(want.yaw_rad / 2), abs_tol=1e-15)
    _, ticks = seen["/wheel_ticks"]
    want_ticks = next(m for m in run.base_msgs if isinstance(m, WheelTicks) and m.stamp_ns == want.stamp_ns)
    assert (ticks.left_ticks, ticks.right_ticks, ticks.device_ms) == (
        want_ticks.left_ticks, want_ticks.right_ticks, want_ticks.device_ms)
    _, truth = seen["/ground_truth"]
    assert truth.header.frame_id == "world"


def test_schema_text_carries_every_dependency_once() -> None:
    text = schema_text("nav_msgs/msg/Odometry")
    deps = [line[5:] for line in text.splitlines() if line.startswith("MSG: ")]
    assert sorted(deps) == sorted([
        "std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/PoseWithCovariance",
        "geometry_msgs/Pose", "geometry_msgs/Point", "geometry_msgs/Quaternion",
        "geometry_msgs/TwistWithCovariance", "geometry_msgs/Twist", "geometry_msgs/Vector3"])
    assert text.count("=" * 80 + "\n") == len(deps)
    assert camera_topic("floor") == FLOOR_TOPIC
    with pytest.raises(ValueError):
        camera_topic("floor/../x")


def test_jpeg_frames_are_close_and_smaller(run: Run, tmp_path: Path) -> None:
    sizes = {}
    for fmt in ("png", "jpeg"):
        path = tmp_path / f"{fmt}.mcap"
        with RecordingWriter(path, image_format=fmt, jpeg_quality=90) as w:
            for f in run.frames[:3]:
                w.write_frame(f)
        sizes[fmt] = path.stat().st_size
        got = [m for _, m in read_recording(path)]
        assert [m.seq for m in got] == [0, 1, 2]
        for g, f in zip(got, run.frames[:3], strict=True):
            diff = np.abs(g.image.astype(int) - f.image.astype(int))
            if fmt == "png":
                assert diff.max() == 0
            else:
                assert 0 < diff.mean() < 6.0
    assert sizes["jpeg"] < sizes["png"]


# -- writer behaviour ------------------------------------------------------------------

def test_partial_name_until_close_and_readable_while_written(run: Run, tmp_path: Path) -> None:
    path = tmp_path / "live.mcap"
    w = RecordingWriter(path, chunk_size=4096)
    partial = Path(str(path) + PARTIAL_SUFFIX)
    assert partial.exists() and not path.exists()
    base = run.base_msgs[:200]
    for m in base:
        (w.write_wheel_ticks if isinstance(m, WheelTicks) else w.write_yaw_rate)(m)
    # A crash now: the file on disk holds the finished chunks, no summary.
    with RecordingReader(partial) as r:
        got = [m for _, m in r.messages()]
        assert r.damage.no_summary
        assert r.metadata["robotd"]["image_format"] == "png"
    assert 0 < len(got) < len(base)
    assert got == base[: len(got)]
    assert r.time_range_ns == (0, got[-1].stamp_ns)
    assert len(got) >= len(base) - 60  # at most one 4 kB chunk (~60 messages) in memory
    w.close()
    w.close()
    assert path.exists() and not partial.exists()
    assert [m for _, m in read_recording(path)] == base


class _DiskOf:
    """``os`` for the writer module with a disk that holds ``free_bytes`` more: past that,
    ``write`` writes what still fits and then raises ENOSPC, as a full file system does."""

    def __init__(self, free_bytes: int) -> None:
        self.free_bytes = free_bytes
        self.failures = 0

    def write(self, fd: int, data) -> int:
        if self.free_bytes <= 0:
            self.failures += 1
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = os.write(fd, bytes(data[: self.free_bytes]))
        self.free_bytes -= n
        return n

    def __getattr__(self, name: str):
        return getattr(os, name)


def test_full_disk_ends_the_recording_readably(run: Run, tmp_path: Path, monkeypatch) -> None:
    import drivers.recording.writer as writer_module

    disk = _DiskOf(6000)
    monkeypatch.setattr(writer_module, "os", disk)
    path = tmp_path / "full.mcap"
    partial = Path(str(path) + PARTIAL_SUFFIX)
    w = RecordingWriter(path, chunk_size=4096)
    offered = []  # the last one is the write that failed
    with pytest.raises(RecordingError, match="No space left on device") as failure:
        for m in run.base_msgs:
            offered.append(m)
            (w.write_wheel_ticks if isinstance(m, WheelTicks) else w.write_yaw_rate)(m)
    assert str(partial) in str(failure.value) and w.error is failure.value
    assert disk.failures == 1 and 100 < len(offered) < len(run.base_msgs)
    # the recording is over: later writes raise the same error without touching the disk
    with pytest.raises(RecordingError) as again:
        w.write_wheel_ticks(WheelTicks(10**9, 1, 2, 3))
    assert again.value is failure.value and disk.failures == 1
    w.close()  # closes the file, raises nothing, keeps the .partial name
    w.close()
    assert not path.exists() and partial.stat().st_size <= 6000
    with RecordingReader(partial) as r:
        got = [m for _, m in r.messages()]
        # cut back to its last complete record: nothing half-written at the end
        assert r.damage.no_summary and r.damage.unread_tail_bytes == 0
        assert r.damage.damaged_chunks == 0
    # every complete chunk is there: at most the chunk being filled (~60 messages) is lost
    assert len(got) >= len(offered) - 80 and got == offered[: len(got)]


def test_full_disk_at_close_keeps_a_readable_partial(run: Run, tmp_path: Path, monkeypatch) -> None:
    import drivers.recording.writer as writer_module

    path = tmp_path / "full.mcap"
    partial = Path(str(path) + PARTIAL_SUFFIX)
    disk = _DiskOf(10**9)
    monkeypatch.setattr(writer_module, "os", disk)
    w = RecordingWriter(path, chunk_size=4096)
    base = run.base_msgs[:300]
    for m in base:
        (w.write_wheel_ticks if isinstance(m, WheelTicks) else w.write_yaw_rate)(m)
    disk.free_bytes = 0  # full by the time the summary is written
    with pytest.raises(RecordingError, match=f"cannot finish the recording.*{partial.name}"):
        w.close()
    w.close()
    assert not path.exists()
    with RecordingReader(partial) as r:
        got = [m for _, m in r.messages()]
        assert r.damage.unread_tail_bytes == 0
    assert 0 < len(got) <= len(base) and got == base[: len(got)]


def test_tee_hands_over_what_it_read_then_raises_the_write_failure(tmp_path: Path,
                                                                   monkeypatch) -> None:
    import drivers.recording.writer as writer_module

    class Source:
        def __init__(self) -> None:
            self.n = 0

        def read(self, timeout_s: float):
            self.n += 1
            return [WheelTicks(self.n, self.n, self.n, self.n) for _ in range(50)]

        def close(self) -> None:
            pass

    disk = _DiskOf(4000)
    monkeypatch.setattr(writer_module, "os", disk)
    w = RecordingWriter(tmp_path / "tee.mcap", chunk_size=1024)
    tee = RecordingTee(Source(), w)
    reads = []
    with pytest.raises(RecordingError, match="No space left"):
        for _ in range(1000):
            reads.append(tee.read(0.1))
    # every read before the failure was handed over whole, the failing one too
    assert reads and all(len(r) == 50 for r in reads) and w.error is not None
    assert tee.stats()["errors"] == 0  # not a device error
    w.close()


def test_writer_rejects_bad_values_and_existing_files(tmp_path: Path) -> None:
    path = tmp_path / "x.mcap"
    with RecordingWriter(path) as w:
        with pytest.raises(ValueError, match="stamp_ns"):
            w.write_wheel_ticks(WheelTicks(-1, 0, 0))
        with pytest.raises(ValueError, match="left_ticks"):
            w.write_wheel_ticks(WheelTicks(0, 70000, 0))
        with pytest.raises(ValueError, match="uint8"):
            w.write_frame(Frame(0, "floor", np.zeros((4, 4), np.float32)))
        with pytest.raises(ValueError, match="covariance"):
            w.write_odometry(PoseStamped(0, 0.0, 0.0, 0.0, np.zeros((2, 2))))
        w.write_wheel_ticks(WheelTicks(5, 1, 2, 3))
        w.write_yaw_rate(YawRate(6, 0.25, "inertial"))
        w.write_yaw_rate(YawRate(7, 0.5, "raw_gyro"))  # a second source is stored as the first
        assert w.mixed_yaw_sources == 1
        w.write_yaw_rate(YawRate(8, 0.5, "inertial", yaw_rate_var_rad2ps2=2.5e-5))  # kept in covariance[8]
    with pytest.raises(ValueError, match="closed"):
        w.write_wheel_ticks(WheelTicks(6, 1, 2, 3))
    with pytest.raises(ValueError, match="closed"):
        w.write_yaw_rate(YawRate(9, 0.5, "raw_gyro"))
    with pytest.raises(DriverError, match="x.mcap"):
        RecordingWriter(path)
    with pytest.raises(DriverError, match="cannot create"):
        RecordingWriter(tmp_path / "no" / "dir.mcap")
    # The .partial of an interrupted recording is never overwritten silently.
    crashed = tmp_path / "crashed.mcap"
    Path(str(crashed) + PARTIAL_SUFFIX).write_bytes(b"precious")
    with pytest.raises(DriverError, match="interrupted recording"):
        RecordingWriter(crashed)
    assert Path(str(crashed) + PARTIAL_SUFFIX).read_bytes() == b"precious"
    RecordingWriter(crashed, overwrite=True).close()
    assert crashed.exists()
    assert [m for _, m in read_recording(path)] == [
        WheelTicks(5, 1, 2, 3), YawRate(6, 0.25, "inertial"), YawRate(7, 0.5, "inertial"),
        YawRate(8, 0.5, "inertial", 2.5e-5)]


def test_exception_in_with_block_still_finishes_the_file(tmp_path: Path) -> None:
    path = tmp_path / "int.mcap"
    with pytest.raises(KeyboardInterrupt):
        with RecordingWriter(path) as w:
            w.write_wheel_ticks(WheelTicks(1, 2, 3, 4))
            raise KeyboardInterrupt
    with RecordingReader(path) as r:
        assert not r.damage.any
        assert r.metadata["robotd.end"]["completed"] == "false"
        assert r.metadata["robotd.end"]["reason"].startswith("KeyboardInterrupt")
        assert [m for _, m in r.messages()] == [WheelTicks(1, 2, 3, 4)]


def test_tee_records_what_the_driver_reads(tmp_path: Path) -> None:
    class FakeDriver:
        def __init__(self) -> None:
            self.reads = [[WheelTicks(1, 10, 20, 30), YawRate(1, 0.5, "inertial")], None,
                          Frame(2, "floor", np.full((8, 8), 7, np.uint8), 0)]
            self.closed = 0

        def read(self, timeout_s: float):
            return self.reads.pop(0)

        def close(self) -> None:
            self.closed += 1

        def stats(self) -> dict[str, int]:
            return {"driver_reads": 3 - len(self.reads)}

    path = tmp_path / "tee.mcap"
    driver = FakeDriver()
    with RecordingWriter(path) as w:
        tee = RecordingTee(driver, w)
        got = [tee.read(0.1) for _ in range(3)]
        tee.close()
        tee.close()
        w.write_odometry(PoseStamped(3, 1.0, 2.0, 0.5, np.eye(3)))
        w.write_odometry(PoseStamped(3, 1.5, 2.5, 0.25), "/odom/wheel")
    assert got[0] == [WheelTicks(1, 10, 20, 30), YawRate(1, 0.5, "inertial")] and got[1] == []
    assert len(got[2]) == 1 and got[2][0].stamp_ns == 2
    assert driver.closed == 1 and tee.stats() == {"driver_reads": 3}
    out = list(read_recording(path))
    assert [t for t, _ in out] == ["/wheel_ticks", "/imu", FLOOR_TOPIC, "/odom", "/odom/wheel"]
    assert out[1][1] == YawRate(1, 0.5, "inertial")
    assert out[4][1].x_m == 1.5 and out[3][1].covariance[2, 2] == 1.0



def test_base_stream_reads_back_in_the_order_it_arrived(tmp_path: Path) -> None:
    # A Kobuki packet carries the gyro samples of the last few ms: one stamped before the
    # wheel reading received ahead of it must replay after that reading, as the daemon
    # saw it (odometry treats a late gyro sample differently from an early one).
    path = tmp_path / "base.mcap"
    arrived = [WheelTicks(100, 1, 2, 3), YawRate(90, 0.1), YawRate(100, 0.2), WheelTicks(120, 2, 3, 4),
               YawRate(110, 0.3), YawRate(120, 0.4)]
    with RecordingWriter(path) as w:
        for m in arrived:
            (w.write_wheel_ticks if isinstance(m, WheelTicks) else w.write_yaw_rate)(m)
        w.write_odometry(PoseStamped(95, 0.0, 0.0, 0.0))  # other topics keep log time = stamp
    out = list(read_recording(path))
    assert [m for t, m in out if t != "/odom"] == arrived
    assert [t for t, _ in out].index("/odom") == 0
    with open(path, "rb") as f:
        log_times = {(c.topic, m.publish_time): m.log_time
                     for _, c, m in make_reader(f).iter_messages(log_time_order=False)}
    assert log_times[("/imu", 90)] == 100 and log_times[("/imu", 110)] == 120
    assert log_times[("/odom", 95)] == 95

# -- damaged files ---------------------------------------------------------------------

def _summary_start(data: bytes) -> int:
    """Where the summary begins: the footer's first field (footer = the last record)."""
    footer = data[-8 - 29:-8]  # opcode u8, length u64, summary_start u64, offset u64, crc u32
    assert footer[0] == 0x02
    return struct.unpack_from("<Q", footer, 9)[0]


def test_truncated_files_give_every_intact_message(run: Run, recording, tmp_path: Path) -> None:
    path, _ = recording
    data = path.read_bytes()
    want = run.expected()
    size = len(data)
    data_end = _summary_start(data)
    cuts = [0, 5, 8, 20, size // 10, size // 4, size // 2, (3 * size) // 4, data_end - 30, data_end,
            size - 5]
    previous = -1
    for cut in cuts:
        cut_path = tmp_path / f"cut{cut}.mcap"
        cut_path.write_bytes(data[:cut])
        if cut < 8 + 9 + 10:  # magic, record head, header body: no recording to speak of
            with pytest.raises(DriverError, match=f"cut{cut}.mcap"):
                RecordingReader(cut_path)
            continue
        with RecordingReader(cut_path) as r:
            got = list(r.messages())
            assert r.damage.no_summary
        # what is recovered is a subset of what was written, each message intact, in order
        stamps = [m.stamp_ns for _, m in got]
        assert stamps == sorted(stamps)
        wanted = {(t, m.stamp_ns): m for t, m in want}
        for t, m in got:
            assert_same(t, m, wanted[(t, m.stamp_ns)])
        assert len(got) >= previous  # more file, never fewer messages
        previous = len(got)
        if cut >= data_end:
            assert len(got) == len(want)  # only the summary was lost
        elif cut <= size // 4:
            assert len(got) < len(want)
    assert previous == len(want)


def test_flipped_byte_in_a_chunk_skips_that_chunk_only(run: Run, recording, tmp_path: Path) -> None:
    path, _ = recording
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    victim = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)[2]
    data = bytearray(path.read_bytes())
    data[victim.chunk_start_offset + victim.chunk_length // 2] ^= 0x40
    bad = tmp_path / "flip.mcap"
    bad.write_bytes(bytes(data))
    with RecordingReader(bad) as r:
        assert not r.damage.no_summary
        got = list(r.messages())
        assert r.damage.damaged_chunks == 1
    assert 0 < len(got) < len(run.written)
    stamps = [m.stamp_ns for _, m in got]
    assert stamps == sorted(stamps)
    # the same through the scan (no summary): the same chunk is skipped, the rest is read
    cut = tmp_path / "flip-cut.mcap"
    cut.write_bytes(bytes(data[:-40]))
    with RecordingReader(cut) as r2:
        assert [m.stamp_ns for _, m in r2.messages()] == stamps
        assert r2.damage.no_summary and r2.damage.damaged_chunks == 1


def test_unchunked_copy_reads_the_same(run: Run, recording, tmp_path: Path) -> None:
    """Messages outside chunks (another tool's unchunked MCAP) are found by the scan."""
    from mcap.writer import Writer as McapWriter

    path, _ = recording
    copy = tmp_path / "unchunked.mcap"
    with RecordingReader(path) as r, open(copy, "wb") as f:
        w = McapWriter(f, use_chunking=False)
        w.start(profile="ros2")
        for name, data in r.metadata.items():
            w.add_metadata(name, data)
        schema_ids = {sid: w.register_schema(s.name, s.encoding, s.data) for sid, s in r.schemas.items()}
        channel_ids = {}
        for channel, msg in r.raw_messages():
            if channel.id not in channel_ids:
                channel_ids[channel.id] = w.register_channel(channel.topic, channel.message_encoding,
                                                             schema_ids[channel.schema_id])
            w.add_message(channel_ids[channel.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
        w.finish()
    with RecordingReader(copy) as r2:
        got = list(r2.messages())
        assert not r2.damage.any
    want = run.expected()
    assert len(got) == len(want)
    for (gt, gm), (wt, wm) in zip(got, want, strict=True):
        assert gt == wt
        assert_same(gt, gm, wm)


def test_unreadable_files_raise_driver_error_naming_the_path(tmp_path: Path) -> None:
    missing = tmp_path / "missing.mcap"
    with pytest.raises(DriverError, match="missing.mcap"):
        list(read_recording(missing))
    text = tmp_path / "notes.mcap"
    text.write_text("this is not a recording\n" * 10)
    with pytest.raises(DriverError, match="notes.mcap.*not an MCAP file"):
        RecordingReader(text)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(DriverError, match="empty"):
        ReplayDriver(empty, ManualClock())


def test_foreign_topics_are_skipped_and_bad_images_counted(tmp_path: Path) -> None:
    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as f:
        w = Ros2Writer(f)
        string = w.register_msgdef("std_msgs/msg/String", "string data\n")
        image = w.register_msgdef("sensor_msgs/msg/CompressedImage",
                                  schema_text("sensor_msgs/msg/CompressedImage"))
        ticks = w.register_msgdef("robotd_msgs/msg/WheelTicks", schema_text("robotd_msgs/msg/WheelTicks"))
        w.write_message("/chatter", string, {"data": "hello"}, log_time=1)
        w.write_message(FLOOR_TOPIC, image, {"header": {"stamp": {"sec": 0, "nanosec": 2}},
                                             "format": "png", "data": b"not a png"}, log_time=2)
        w.write_message("/wheel_ticks", ticks, {"header": {"stamp": {"sec": 0, "nanosec": 3}},
                                                "left_ticks": 1, "right_ticks": 2, "device_ms": 3},
                        log_time=3)
        w.finish()
    with RecordingReader(path) as r:
        got = list(r.messages())
        assert r.skipped == {"/chatter": 1}
        assert r.damage.undecodable_messages == 1
        assert r.yaw_source == "gyro"
    assert got == [("/wheel_ticks", WheelTicks(3, 1, 2, 3))]


# -- replay ----------------------------------------------------------------------------
