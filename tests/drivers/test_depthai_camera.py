"""Tests of drivers.depthai_camera, without a device.

What runs on real depthai objects: a host-only ``dai.Pipeline`` whose ``ReplayVideo`` node
plays a small video into a real ``MessageQueue`` (:func:`replay_stream_opener`), read by
the real driver: frame types and sizes, sequence numbers, timestamps, the stream closing
(a lost device) and reopening with backoff. What is faked at the boundary: depthai's
reconnection statuses, which only a device dropping off the bus produces; the test hands
depthai's own ``dai.Device.ReconnectionStatus`` values to the driver's callback. The
device opener (:func:`open_device_stream`) runs against a fake ``dai.Device``,
``dai.Pipeline`` and Camera node that record its calls and hand real ``dai.ImgFrame``
objects through a fake queue (the calls it makes are checked, not that a real device
accepts them), and against depthai's real (empty) device list.
"""

from __future__ import annotations

import datetime
import logging
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

dai = pytest.importorskip("depthai")

from drivers.depthai_camera import (
    DepthAICamera,
    DepthAISettings,
    _find_device,
    replay_stream_opener,
)
from robotd.base.clock import ManualClock, MonotonicClock
from robotd.base.errors import DriverError

S = 1_000_000_000
N_FRAMES = 6
STATUS = dai.Device.ReconnectionStatus


@pytest.fixture()
def video(tmp_path: Path) -> Path:
    """A 64x48 MJPG video of N_FRAMES flat frames: frame i has every pixel at 40 * i."""
    path = tmp_path / "floor.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 30, (64, 48))
    for i in range(N_FRAMES):
        writer.write(np.full((48, 64, 3), 40 * i, np.uint8))
    writer.release()
    return path


def _settings(**kw) -> DepthAISettings:
    return DepthAISettings(**{"width_px": 32, "height_px": 24, "fps": 60.0,
                              "queue_size": 16, **kw})


def _read_frames(camera: DepthAICamera, n: int, budget_s: float = 10.0) -> list:
    """Up to ``n`` frames, reading until they came or the real-time budget ran out."""
    frames: list = []
    end = time.monotonic() + budget_s
    while len(frames) < n and time.monotonic() < end:
        frames += camera.read(0.2)
    return frames


def test_mono_frames_at_the_set_size_with_device_timestamps(video: Path) -> None:
    clock = MonotonicClock()
    with DepthAICamera(_settings(), opener=replay_stream_opener(video), clock=clock) as camera:
        frames = _read_frames(camera, N_FRAMES)
        now_ns = clock.now_ns()
        stats = camera.stats()
    assert [f.seq for f in frames] == list(range(N_FRAMES))
    assert all(f.image.shape == (24, 32) and f.image.dtype == np.uint8 for f in frames)
    means = [float(f.image.mean()) for f in frames]
    assert means == pytest.approx([40.0 * i for i in range(N_FRAMES)], abs=3.0)  # MJPG is lossy
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(set(stamps))  # strictly increasing
    assert 0 < now_ns - stamps[-1] < 5 * S  # the host's monotonic time base
    assert stats["clock_stamps"] == 0 and stats["frames_skipped"] == 0
    assert all(f.camera == "floor" for f in frames)


def test_colour_frames_are_bgr_or_grey_as_asked(video: Path) -> None:
    with DepthAICamera(_settings(colour=True), opener=replay_stream_opener(video)) as camera:
        colour = _read_frames(camera, 3)
    with DepthAICamera(_settings(colour=True), opener=replay_stream_opener(video),
                       grey=True) as camera:
        grey = _read_frames(camera, 3)
    assert [f.image.shape for f in colour] == [(24, 32, 3)] * 3
    assert [f.image.shape for f in grey] == [(24, 32)] * 3
    assert float(colour[2].image.mean()) == pytest.approx(80.0, abs=4.0)
    assert float(grey[2].image.mean()) == pytest.approx(80.0, abs=4.0)


def test_stamps_far_from_the_clock_are_replaced_and_counted(video: Path) -> None:
    clock = ManualClock(5 * S)  # nowhere near the host's monotonic time
    with DepthAICamera(_settings(), opener=replay_stream_opener(video), clock=clock) as camera:
        frames = _read_frames(camera, 3)
        assert camera.stats()["clock_stamps"] == 3
    assert [f.stamp_ns for f in frames] == [5 * S] * 3


def test_an_unplugged_camera_is_reopened_with_backoff_and_the_gap_is_counted(
        video: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The video's end closes the stream (the device is lost); the file moved away is a
    device that cannot be opened; moved back, the camera comes back. The backoff and the
    gap run on a manual clock, so the gap is exactly the time the clock was moved."""
    clock = ManualClock(100 * S)
    away = video.with_suffix(".unplugged")
    camera = DepthAICamera(_settings(), opener=replay_stream_opener(video), clock=clock,
                           initial_backoff_s=0.5, max_backoff_s=8.0)
    assert len(_read_frames(camera, N_FRAMES)) == N_FRAMES
    video.rename(away)  # unplugged
    end = time.monotonic() + 10.0
    while camera.connected and time.monotonic() < end:  # the stream closes at the video's end
        assert camera.read(0.2) == []
    stats = camera.stats()
    assert stats["losses"] == 1 and stats["connected"] == 0 and stats["gaps"] == 0

    clock.advance_ns(S // 2)
    assert camera.read(0.2) == []  # first attempt, 0.5 s after the loss: fails
    clock.advance_ns(S)
    assert camera.read(0.2) == []  # second, 1 s later: fails
    assert camera.stats()["reopen_failures"] == 2
    assert camera.stats()["away_s"] == 1.5
    away.rename(video)  # plugged back in
    clock.advance_ns(2 * S - 1)
    assert camera.read(0.2) == [] and not camera.connected  # the next try is 2 s later
    clock.advance_ns(1)
    with caplog.at_level(logging.WARNING, logger="drivers.base"):
        frames = _read_frames(camera, 2)
    stats = camera.stats()
    camera.close()
    assert [f.seq for f in frames] == [N_FRAMES, N_FRAMES + 1]  # numbering goes on
    assert stats["reconnects"] == 1 and stats["connected"] == 1 and stats["losses"] == 1
    assert stats["gaps"] == 1 and stats["last_gap_s"] == 3.5 and stats["gap_s_total"] == 3.5
    assert stats["away_s"] == 0.0
    assert any("back after 3.500 s without data (gap 1; 3.500 s in all)" in r.message
               for r in caplog.records)


def test_depthai_reconnecting_by_itself_is_a_gap_and_giving_up_reopens(video: Path) -> None:
    """depthai's own reconnection, reported through the callback: RECONNECTING begins a
    gap (frames queued from before are discarded), RECONNECTED lets frames end it;
    RECONNECT_FAILED makes the driver reopen everything with its own backoff."""
    clock = ManualClock(100 * S)
    camera = DepthAICamera(_settings(fps=30.0), opener=replay_stream_opener(video, loop=True),
                           clock=clock, initial_backoff_s=0.5)
    try:
        assert len(_read_frames(camera, 2)) == 2
        camera._on_status(STATUS.RECONNECTING)  # what depthai's thread calls
        assert camera.read(0.2) == []
        clock.advance_ns(1_200_000_000)
        assert camera.stats()["away_s"] == 1.2 and camera.stats()["losses"] == 1
        camera._on_status(STATUS.RECONNECTED)
        assert len(_read_frames(camera, 1)) == 1
        stats = camera.stats()
        assert stats["gaps"] == 1 and stats["last_gap_s"] == 1.2
        assert stats["depthai_reconnecting"] == 1 and stats["depthai_reconnected"] == 1
        assert stats["reconnects"] == 0  # depthai reconnected it, not the driver

        camera._on_status(STATUS.RECONNECTING)
        camera._on_status(STATUS.RECONNECT_FAILED)
        assert camera.read(0.2) == []
        stats = camera.stats()
        assert stats["depthai_gave_up"] == 1 and not camera.connected
        assert stats["losses"] == 2  # one loss: the failure continues the gap it began in
        clock.advance_ns(S // 2)
        assert len(_read_frames(camera, 1)) == 1  # reopened by the driver, 0.5 s later
        stats = camera.stats()
        assert stats["reconnects"] == 1 and stats["gaps"] == 2 and stats["last_gap_s"] == 0.5
    finally:
        camera.close()


def test_a_missing_video_at_start_is_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(DriverError, match="nothing.avi does not exist"):
        DepthAICamera(_settings(), opener=replay_stream_opener(tmp_path / "nothing.avi"))


def test_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="socket must be one of CAM_A"):
        DepthAISettings(socket="LEFT")
    with pytest.raises(ValueError, match="positive"):
        DepthAISettings(fps=0.0)


def test_no_device_is_one_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    """The device opener's first step, with depthai's device list as this host has it
    (empty) and with one device present under another id."""
    monkeypatch.setattr(dai.Device, "getAllAvailableDevices", staticmethod(list))
    with pytest.raises(DriverError, match="no DepthAI device found"):
        _find_device("")
    other = dai.DeviceInfo("1.3")
    monkeypatch.setattr(dai.Device, "getAllAvailableDevices", staticmethod(lambda: [other]))
    assert _find_device("") is other
    assert _find_device("1.3") is other
    with pytest.raises(DriverError, match="DepthAI device 14442C10D13EABCE00 not found; present:"):
        _find_device("14442C10D13EABCE00")


# -- the device path, with a fake device at depthai's boundary ---------------------------


class _FakeQueue:
    """A ``dai.MessageQueue`` stand-in holding real ``dai.ImgFrame`` objects."""

    def __init__(self) -> None:
        self.frames: list = []
        self.closed = False

    def get(self, timeout):
        if self.closed:
            raise dai.MessageQueue.QueueException("MessageQueue was closed")
        return self.frames.pop(0) if self.frames else None

    def tryGetAll(self):
        out, self.frames = self.frames, []
        return out


class _FakeDevicePath:
    """``dai.Device``, ``dai.Pipeline`` and the Camera node as :func:`open_device_stream`
    uses them, recording the calls; everything else is the real depthai."""

    def __init__(self) -> None:
        self.calls: list = []
        self.queues: list[_FakeQueue] = []
        self.status_callbacks: list = []
        self.fail_start = False
        fake = self

        class Device:
            ReconnectionStatus = dai.Device.ReconnectionStatus

            @staticmethod
            def getAllAvailableDevices():
                return [dai.DeviceInfo("1.3")]

            def __init__(self, info) -> None:
                fake.calls.append(("Device", info.name))

            def setMaxReconnectionAttempts(self, n, callback):
                fake.calls.append(("setMaxReconnectionAttempts", n))
                fake.status_callbacks.append(callback)

            def close(self) -> None:
                fake.calls.append(("Device.close",))

        class Output:
            def createOutputQueue(self, maxSize, blocking):
                fake.calls.append(("createOutputQueue", maxSize, blocking))
                queue = _FakeQueue()
                fake.queues.append(queue)
                return queue

        class CameraNode:
            def build(self, socket):
                fake.calls.append(("build", socket))
                return self

            def requestOutput(self, size, type, fps):
                fake.calls.append(("requestOutput", size, type, fps))
                return Output()

        class Pipeline:
            def __init__(self, device) -> None:
                fake.calls.append(("Pipeline",))

            def create(self, node_type):
                assert node_type is dai.node.Camera
                return CameraNode()

            def start(self) -> None:
                if fake.fail_start:
                    raise RuntimeError("camera CAM_C not connected")
                fake.calls.append(("start",))

            def isRunning(self) -> bool:
                return True

            def stop(self) -> None:
                fake.calls.append(("stop",))
                fake.queues[-1].closed = True

        self.dai = type("dai", (), {
            "Device": Device, "Pipeline": Pipeline, "node": dai.node,
            "CameraBoardSocket": dai.CameraBoardSocket, "ImgFrame": dai.ImgFrame,
            "MessageQueue": dai.MessageQueue})

    def push(self, seq: int, stamp_s: float, value: int) -> None:
        frame = dai.ImgFrame()
        frame.setType(dai.ImgFrame.Type.GRAY8)
        frame.setWidth(4)
        frame.setHeight(3)
        frame.setData(np.full(12, value, np.uint8))
        frame.setSequenceNum(seq)
        frame.setTimestamp(datetime.timedelta(seconds=stamp_s))
        self.queues[-1].frames.append(frame)


def test_the_device_path_with_a_fake_device(monkeypatch: pytest.MonkeyPatch) -> None:
    """open_device_stream's calls (socket, size, type, fps, queue, depthai's reconnection
    with the driver's callback), frames and device stamps through it, a sequence gap
    counted, and depthai's statuses arriving through the callback it was given."""
    import drivers.depthai_camera as module

    fake = _FakeDevicePath()
    monkeypatch.setattr(module, "dai", fake.dai)
    clock = ManualClock(10 * S)
    settings = DepthAISettings(socket="CAM_B", width_px=4, height_px=3, fps=15.0, queue_size=2,
                               reconnection_attempts=5)
    camera = DepthAICamera(settings, clock=clock, initial_backoff_s=1.0)
    assert fake.calls == [
        ("Device", "1.3"), ("setMaxReconnectionAttempts", 5), ("Pipeline",),
        ("build", dai.CameraBoardSocket.CAM_B),
        ("requestOutput", (4, 3), dai.ImgFrame.Type.GRAY8, 15.0),
        ("createOutputQueue", 2, False), ("start",)]
    fake.push(seq=3, stamp_s=10.0, value=9)
    fake.push(seq=6, stamp_s=10.2, value=11)  # 4 and 5 never reached the host
    first, second = camera.read(0.0) + camera.read(0.0)
    assert (first.stamp_ns, second.stamp_ns) == (10 * S, 10_200_000_000)
    assert first.image.tolist() == [[9] * 4] * 3 and second.image.shape == (3, 4)
    assert camera.stats()["frames_skipped"] == 2 and camera.stats()["clock_stamps"] == 0

    (callback,) = fake.status_callbacks
    fake.push(seq=7, stamp_s=10.3, value=12)  # queued before the device dropped off
    callback(STATUS.RECONNECTING)
    assert camera.read(0.0) == [] and camera.stats()["frames_discarded"] == 1
    clock.advance_ns(2 * S)
    callback(STATUS.RECONNECTED)
    fake.push(seq=0, stamp_s=12.0, value=13)  # the device restarted its numbering
    assert [f.image[0, 0] for f in camera.read(0.0)] == [13]
    stats = camera.stats()
    assert stats["last_gap_s"] == 2.0 and stats["frames_skipped"] == 2 and stats["losses"] == 1

    callback(STATUS.RECONNECT_FAILED)  # depthai gave up: the driver closes everything
    assert camera.read(0.0) == [] and fake.calls[-2:] == [("stop",), ("Device.close",)]
    fake.fail_start = True
    clock.advance_ns(S)
    assert camera.read(0.0) == []  # reopening fails: the device is closed again
    assert fake.calls[-1] == ("Device.close",) and camera.stats()["reopen_failures"] == 1
    camera.close()


def test_a_camera_that_does_not_start_is_one_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    import drivers.depthai_camera as module

    fake = _FakeDevicePath()
    fake.fail_start = True
    monkeypatch.setattr(module, "dai", fake.dai)
    with pytest.raises(DriverError, match=r"^DepthAI device .*: cannot start the CAM_C camera at "
                                          r"640x400, 30 fps: camera CAM_C not connected$"):
        DepthAICamera(DepthAISettings(socket="CAM_C"))
    assert fake.calls[-1] == ("Device.close",)
