"""drivers.recording.replay.ReplayDriver: a recording read back as one deterministic driver."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.recording.replay import ReplayConfig, ReplayDriver
from drivers.recording.writer import RecordingWriter
from drivers.registry import open_driver
from robotd.base.clock import ManualClock
from robotd.base.errors import DriverError
from robotd.base.messages import Frame, PoseStamped, WheelTicks, YawRate

MS = 1_000_000
T0 = 2_000 * MS
FLOOR = "/floor_camera/image/compressed"


def _frame(k: int) -> Frame:
    image = np.full((12, 16), k % 256, np.uint8)
    image[k % 12, k % 16] = 255  # every frame different
    return Frame(T0 + 100 * MS * k + 7 * MS, "floor", image, k)


def _expected() -> list[tuple[str, object]]:
    """What the daemon received, in order: base messages every 20 ms, with the gyro of
    every 5th packet stamped 3 ms before the wheel reading received ahead of it, and a
    floor frame every 100 ms (7 ms after a base packet)."""
    out: list[tuple[str, object]] = []
    for i in range(150):
        t = T0 + 20 * MS * i
        out.append(("/wheel_ticks", WheelTicks(t, (65530 + i) % 65536, 2 * i, (40 + 20 * i) % 65536)))
        out.append(("/imu", YawRate(t - (3 * MS if i % 5 == 0 else 0), 0.01 * i, "raw_gyro")))
        if i % 5 == 0:
            out.append((FLOOR, _frame(i // 5)))
    return out


def _write(path: Path, chunk_size: int = 256 * 1024) -> list[tuple[str, object]]:
    expected = _expected()
    with RecordingWriter(path, chunk_size=chunk_size) as w:
        for _, msg in expected:
            if isinstance(msg, WheelTicks):
                w.write_wheel_ticks(msg)
                w.write_odometry(PoseStamped(msg.stamp_ns, 0.0, 0.0, 0.0, np.eye(3)))
            elif isinstance(msg, YawRate):
                w.write_yaw_rate(msg)
            else:
                w.write_frame(msg)
    return expected


def _key(msg: object) -> tuple:
    if isinstance(msg, Frame):
        return ("frame", msg.stamp_ns, msg.camera, msg.seq, msg.image.tobytes())
    return (type(msg).__name__, msg)


def _replay_all(drv: ReplayDriver, clock: ManualClock) -> list[list[object]]:
    batches: list[list[object]] = []
    last_clock = clock.now_ns()
    for _ in range(10_000):
        if drv.done:
            break
        batch = drv.read(0.0)
        assert batch, "an unpaced replay that is not done always has something"
        assert len(batch) <= drv.max_batch
        assert sum(isinstance(m, Frame) for m in batch) <= 1
        now = clock.now_ns()
        assert now >= last_clock
        assert now == max(last_clock, max(m.stamp_ns for m in batch))
        last_clock = now
        batches.append(batch)
    return batches


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[tuple[str, object]]]:
    path = tmp_path_factory.mktemp("replay") / "run.mcap"
    return path, _write(path)


def test_every_message_in_the_order_received_with_the_clock_following(recording) -> None:
    path, expected = recording
    clock = ManualClock(0)
    with ReplayDriver(path, clock, max_batch=8) as drv:
        assert drv.time_range_ns == (T0, T0 + 20 * MS * 149)  # the last packet, 2.98 s
        batches = _replay_all(drv, clock)
        got = [m for b in batches for m in b]
        assert [_key(m) for m in got] == [_key(m) for _, m in expected]
        assert drv.done and drv.read(0.0) == []
        # the clock is the latest stamp handed out: the last packet's (frames end at 2.907 s)
        assert clock.now_ns() == T0 + 2980 * MS == got[-1].stamp_ns
        assert drv.counts == {"/wheel_ticks": 150, "/imu": 150, FLOOR: 30}
        assert drv.skipped == {"/odom": 150}
        assert not drv.damage.any
        stats = drv.stats()
        assert (stats["messages_out"], stats["done"], stats["skipped"]) == (330, 1, 150)
    assert max(len(b) for b in batches) == 8  # 13 between two frames, cut at 8


def test_two_replays_give_identical_sequences(recording) -> None:
    path, _ = recording
    runs = []
    for _ in range(2):
        clock = ManualClock(0)
        with ReplayDriver(path, clock) as drv:
            runs.append([[_key(m) for m in b] for b in _replay_all(drv, clock)])
    assert runs[0] == runs[1]
    assert sum(map(len, runs[0])) == 330


def test_a_clock_already_later_is_not_moved_back(recording) -> None:
    path, _ = recording
    start = T0 + 1_000 * MS
    clock = ManualClock(start)
    with ReplayDriver(path, clock, max_batch=1) as drv:
        (first,) = drv.read(0.0)
        assert first.stamp_ns == T0 and clock.now_ns() == start


def test_paced_replay_waits_on_the_injected_wall_clock(recording) -> None:
    path, _ = recording
    wall = [100.0]
    sleeps: list[float] = []

    def sleep(s: float) -> None:
        sleeps.append(s)
        wall[0] += s

    clock = ManualClock(0)
    with ReplayDriver(path, clock, speed=2.0, wall_clock=lambda: wall[0], sleep=sleep) as drv:
        # the first packet is due at once: wheel ticks, its gyro and the first frame
        # (log times T0, T0 - 3 ms -> T0, T0 + 7 ms) are not all due: the frame is 7 ms
        # of recording = 3.5 ms of wall time later
        assert [type(m) for m in drv.read(1.0)] == [WheelTicks, YawRate]
        assert sleeps == []
        (frame,) = drv.read(1.0)
        assert isinstance(frame, Frame) and sleeps == [pytest.approx(0.0035)]
        # next packet 20 ms of recording after T0 = 10 ms of wall time after the start;
        # a 1 ms timeout is not enough: the read waits 1 ms and returns nothing
        assert drv.read(0.001) == []
        assert sleeps[-1] == pytest.approx(0.001)
        assert clock.now_ns() == T0 + 7 * MS
        got = drv.read(1.0)
        assert [m.stamp_ns for m in got] == [T0 + 20 * MS, T0 + 20 * MS]
        assert wall[0] == pytest.approx(100.010)
    with pytest.raises(ValueError, match="speed"):
        ReplayDriver(path, ManualClock(), speed=0.0)


def test_a_damaged_recording_replays_what_is_intact_then_is_done(tmp_path: Path) -> None:
    path = tmp_path / "whole.mcap"
    expected = _write(path, chunk_size=4 * 1024)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    clock = ManualClock(0)
    with ReplayDriver(cut, clock) as drv:
        assert drv.damage.no_summary
        got = [m for b in _replay_all(drv, clock) for m in b]
        assert drv.done
    assert 0 < len(got) < len(expected)
    # what came out is a prefix of what was received: nothing reordered, nothing invented
    assert [_key(m) for m in got] == [_key(m) for _, m in expected[: len(got)]]


def test_registered_as_replay_mcap_and_refuses_a_non_recording(recording, tmp_path: Path) -> None:
    path, _ = recording
    clock = ManualClock(0)
    with open_driver("replay", "mcap", ReplayConfig(str(path)), clock) as drv:
        assert isinstance(drv, ReplayDriver) and drv.name == "replay"
        # up to the second frame: packet 0 and its frame, packets 1-4, packet 5
        assert len(drv.read(0.0)) == 3 + 4 * 2 + 2
    assert drv.done is False  # closed before the end
    with pytest.raises(DriverError, match="closed"):
        drv.read(0.0)
    bogus = tmp_path / "bogus.mcap"
    bogus.write_bytes(b"not a recording")
    with pytest.raises(DriverError, match="bogus.mcap"):
        ReplayDriver(bogus, ManualClock())


def test_messages_that_are_not_driver_output_go_to_on_other(tmp_path: Path) -> None:
    """A calibration run keeps the virtual robot's ground truth this way; the driver's
    own output is unchanged and ``finished``/``handed_out`` tell a watcher it is done."""
    from drivers.recording.writer import RecordingWriter
    from robotd.base.messages import WheelTicks

    path = tmp_path / "gt.mcap"
    with RecordingWriter(path) as w:
        for k in range(5):
            w.write_wheel_ticks(WheelTicks(k * 20_000_000, k, k, k))
            w.write_ground_truth(k * 20_000_000 + 1, 0.1 * k, 0.0, 0.0)
    others: list[tuple[str, float]] = []
    clock = ManualClock()
    with ReplayDriver(path, clock, on_other=lambda t, m: others.append((t, m.x_m))) as drv:
        got = []
        while not drv.finished:
            got += drv.read(0.0)
        assert drv.handed_out == len(got) == 5
        assert drv.read(0.0) == []
    assert [m.left_ticks for m in got] == [0, 1, 2, 3, 4]
    assert others == [("/ground_truth", pytest.approx(0.1 * k)) for k in range(5)]
    assert drv.skipped == {"/ground_truth": 5}


def test_jpeg_frames_decode_when_read_and_damaged_ones_are_still_counted(tmp_path: Path) -> None:
    """A replay defers the decoding of a JPEG frame to its first use (most frames never
    become keyframes); the pixels are those an eager read gives, a frame whose data does
    not decode is counted and skipped at read time as before, and a deferred frame pickles
    as a plain Frame."""
    import pickle

    from drivers.recording.reader import EncodedFrame, RecordingReader
    from drivers.recording.schemas import schema_text
    from mcap_ros2.writer import Writer as Ros2Writer

    rng = np.random.default_rng(3)
    frames = [Frame(T0 + k * MS, "floor", rng.integers(0, 255, (48, 64), np.uint8), k) for k in range(3)]
    good = tmp_path / "good.mcap"
    with RecordingWriter(good, image_format="jpeg") as w:
        for f in frames:
            w.write_frame(f)
    with RecordingReader(good) as r:
        eager = [m for _, m in r.messages()]
    with ReplayDriver(good, ManualClock()) as drv:
        lazy = [m for _ in range(5) for m in drv.read(0.0)]
    assert [type(m) for m in eager] == [Frame] * 3 and [type(m) for m in lazy] == [EncodedFrame] * 3
    for a, b in zip(eager, lazy):
        assert (b.stamp_ns, b.camera, b.seq) == (a.stamp_ns, a.camera, a.seq)
        assert np.array_equal(b.image, a.image) and b.image is b.image  # decoded once
    back = pickle.loads(pickle.dumps(lazy[1]))
    assert type(back) is Frame and np.array_equal(back.image, eager[1].image)
    # dataclasses.replace treats it as any Frame (a looping replay restamps frames so).
    with ReplayDriver(good, ManualClock()) as drv:
        fresh = [m for _ in range(5) for m in drv.read(0.0)]
    moved = dataclasses.replace(fresh[2], stamp_ns=fresh[2].stamp_ns + 7, seq=9)
    assert (moved.stamp_ns, moved.seq) == (eager[2].stamp_ns + 7, 9)
    assert np.array_equal(moved.image, eager[2].image)
    later = fresh[0].restamped(fresh[0].stamp_ns + 5)
    assert later._decoded is None and np.array_equal(later.image, eager[0].image)
    with pytest.raises(TypeError):
        EncodedFrame(T0, "floor")

    # A JPEG cut in its entropy-coded data, and one that is not an image at all.
    jpeg = cv2.imencode(".jpg", frames[0].image)[1].tobytes()
    bad = tmp_path / "bad.mcap"
    with open(bad, "wb") as f:
        w2 = Ros2Writer(f)
        image = w2.register_msgdef("sensor_msgs/msg/CompressedImage", schema_text("sensor_msgs/msg/CompressedImage"))
        for k, data in enumerate((jpeg[:len(jpeg) // 3], b"\xff\xd8 not a jpeg", jpeg)):
            w2.write_message(FLOOR, image, {"header": {"stamp": {"sec": 0, "nanosec": k + 1}},
                                            "format": "jpeg", "data": data}, log_time=k + 1)
        w2.finish()
    with ReplayDriver(bad, ManualClock()) as drv:
        got = [m for _ in range(5) for m in drv.read(0.0)]
        assert drv.damage.undecodable_messages == 2
    assert [m.stamp_ns for m in got] == [3] and got[0].image.shape == (48, 64)
