"""Tests of drivers.camera.

Device checks run against real file system objects (a missing path, a regular file, a
directory, /dev/null, a video4linux node with no driver behind it). Streaming, format
negotiation and reconnection run against a scripted stand-in for ``cv2.VideoCapture``
injected at the ``capture_factory``/``device_check`` boundary, with a ManualClock.
"""

from __future__ import annotations

import errno
import logging
import os
import re
import stat
from collections import deque
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.camera import CameraFormat, V4L2Camera, _describe_open_error, check_video_device
from robotd.base.clock import ManualClock
from robotd.base.errors import DriverError

S = 1_000_000_000
DEV = "/dev/video0"


# -- real device checks ----------------------------------------------------------------


def _never_called(path: str, api: int):
    raise AssertionError("the capture must not be created when the device check fails")


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda tmp: str(tmp / "video0"), r"does not exist"),
        (lambda tmp: (tmp / "f").write_bytes(b"x") and str(tmp / "f"),
         r"is a regular file, not a character device"),
        (lambda tmp: str(tmp), r"is a directory, not a character device"),
        (lambda tmp: "/dev/null", r"character device \(1:3\) but not a video4linux device"),
    ],
    ids=["missing", "regular-file", "directory", "dev-null"],
)
def test_a_path_that_is_not_a_camera_is_refused_with_the_reason(
    tmp_path: Path, make, message: str
) -> None:
    path = make(tmp_path)
    with pytest.raises(DriverError, match=message) as info:
        V4L2Camera(path, capture_factory=_never_called)
    assert path in str(info.value)


def test_a_video4linux_node_without_a_driver_is_refused(tmp_path: Path) -> None:
    node = tmp_path / "video9"
    try:
        os.mknod(node, stat.S_IFCHR | 0o660, os.makedev(81, 9))
    except PermissionError:
        pytest.skip("creating a device node needs CAP_MKNOD")
    with pytest.raises(DriverError, match="has no device behind it"):
        check_video_device(str(node))


@pytest.mark.parametrize(
    ("code", "message"),
    [
        (errno.EBUSY, "is busy: another process"),
        (errno.EACCES, "'video' group"),
        (errno.EPERM, "DeviceAllow=char-video4linux"),
        (errno.ENODEV, "has no device behind it"),
        (errno.EIO, r"cannot be opened: .* \(EIO\)"),
    ],
)
def test_open_errors_are_explained(code: int, message: str) -> None:
    # Running as root, without a real camera, these errnos cannot be provoked here.
    text = _describe_open_error(DEV, OSError(code, os.strerror(code)))
    assert DEV in text
    assert re.search(message, text)


# -- a scripted capture ----------------------------------------------------------------


class FakeDevice:
    """A camera that can be unplugged, with a queue of scripted reads.

    Each queued read is ``(ok, pos_msec)``; a successful read returns a fresh BGR image
    whose pixels all equal the read's index, so a test can tell frames apart.
    """

    def __init__(self, accept: dict[int, float] | None = None) -> None:
        self.plugged = True
        self.reads: deque[tuple[bool, float]] = deque()
        self.accept = accept or {}  # property -> the value the "driver" settles on
        self.opened: list[tuple[str, int]] = []
        self.checks = 0
        self.captures: list[FakeCapture] = []
        self.served = 0

    def check(self, path: str) -> None:
        self.checks += 1
        if not self.plugged:
            raise DriverError(f"camera device {path} does not exist")

    def factory(self, path: str, api: int) -> FakeCapture:
        self.opened.append((path, api))
        cap = FakeCapture(self)
        self.captures.append(cap)
        return cap


class FakeCapture:
    def __init__(self, device: FakeDevice) -> None:
        self.device = device
        self.props: dict[int, float] = {cv2.CAP_PROP_POS_MSEC: 0.0}
        self.sets: list[tuple[int, float]] = []
        self.released = 0

    def isOpened(self) -> bool:  # noqa: N802 - OpenCV's name
        return self.device.plugged

    def set(self, prop: int, value: float) -> bool:
        self.sets.append((prop, value))
        self.props[prop] = self.device.accept.get(prop, value)
        return True

    def get(self, prop: int) -> float:
        return float(self.props.get(prop, 0.0))

    def read(self):
        if not self.device.plugged or not self.device.reads:
            return False, None
        ok, pos_msec = self.device.reads.popleft()
        if not ok:
            return False, None
        self.device.served += 1
        self.props[cv2.CAP_PROP_POS_MSEC] = pos_msec
        image = np.full((6, 8, 3), self.device.served, dtype=np.uint8)
        image[0, 0] = (255, 0, 0)  # blue in BGR: grey conversion must weight it as blue
        return True, image

    def release(self) -> None:
        self.released += 1


def _camera(device: FakeDevice, clock: ManualClock, **kwargs) -> V4L2Camera:
    return V4L2Camera(
        DEV, clock=clock, capture_factory=device.factory, device_check=device.check, **kwargs
    )


# -- opening and negotiation -----------------------------------------------------------


def test_an_index_names_dev_video_n_and_the_v4l2_backend_is_requested() -> None:
    device = FakeDevice()
    V4L2Camera(7, clock=ManualClock(), capture_factory=device.factory,
               device_check=device.check).close()
    assert device.opened == [("/dev/video7", cv2.CAP_V4L2)]


def test_settings_are_requested_in_order_and_differences_are_reported(
    caplog: pytest.LogCaptureFixture,
) -> None:
    device = FakeDevice(accept={
        cv2.CAP_PROP_FRAME_WIDTH: 320,
        cv2.CAP_PROP_FRAME_HEIGHT: 240,
        cv2.CAP_PROP_FPS: 15,
    })
    with caplog.at_level(logging.WARNING, logger="drivers.camera"):
        camera = _camera(device, ManualClock(), fourcc="GREY", width_px=640, height_px=480,
                         fps=30, buffer_size=2)
    cap = device.captures[0]
    assert [prop for prop, _ in cap.sets] == [
        cv2.CAP_PROP_FOURCC, cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT,
        cv2.CAP_PROP_FPS, cv2.CAP_PROP_BUFFERSIZE,
    ]
    assert cap.sets[0][1] == cv2.VideoWriter.fourcc(*"GREY")
    assert camera.negotiated == CameraFormat("GREY", 320, 240, 15.0, 2)
    assert camera.requested == CameraFormat("GREY", 640, 480, 30, 2)
    assert "size 320x240 instead of 640x480" in caplog.text
    assert "15.0 fps instead of 30" in caplog.text
    assert "format" not in caplog.text  # the format was accepted


def test_a_capture_that_does_not_open_raises_and_is_released() -> None:
    device = FakeDevice()
    device.plugged = False
    with pytest.raises(DriverError, match="does not exist"):
        _camera(device, ManualClock())
    assert device.opened == []  # the check stopped it before OpenCV
    # Device node present but OpenCV refuses it (e.g. busy streaming elsewhere):
    device = FakeDevice()
    device.check = lambda path: None  # type: ignore[method-assign]
    device.plugged = False
    with pytest.raises(DriverError, match="could not open it"):
        _camera(device, ManualClock())
    assert device.captures[0].released == 1


# -- frames ----------------------------------------------------------------------------


def test_frames_carry_the_driver_stamp_a_sequence_number_and_grey_pixels() -> None:
    device = FakeDevice()
    device.reads.extend([(True, 10_000.5), (True, 10_033.25)])
    clock = ManualClock(10 * S)
    with _camera(device, clock, name="forward", grey=True) as camera:
        (f0,) = camera.read(timeout_s=0.25)
        (f1,) = camera.read(timeout_s=0.25)
    assert (f0.camera, f0.seq, f0.stamp_ns) == ("forward", 0, 10_000_500_000)
    assert (f1.seq, f1.stamp_ns) == (1, 10_033_250_000)
    assert f0.image.shape == (6, 8) and f0.image.dtype == np.uint8
    assert f0.image[1, 1] == 1 and f1.image[1, 1] == 2
    assert f0.image[0, 0] == round(0.114 * 255)  # BGR blue -> grey with Rec. 601 weights
    assert camera.stats()["messages_out"] == 2 and camera.stats()["clock_stamps"] == 0
    # The read timeout was passed to OpenCV once, in ms.
    timeout_sets = [v for p, v in device.captures[0].sets if p == cv2.CAP_PROP_READ_TIMEOUT_MSEC]
    assert timeout_sets == [250]


def test_missing_or_foreign_driver_stamps_fall_back_to_the_clock() -> None:
    device = FakeDevice()
    device.reads.extend([(True, 0.0), (True, 1.7e12)])  # none yet; then a wall-clock stamp
    clock = ManualClock(50 * S)
    with _camera(device, clock) as camera:
        (first,) = camera.read(0.0)
        clock.advance_ns(S // 30)
        (second,) = camera.read(0.0)
    assert first.stamp_ns == 50 * S
    assert second.stamp_ns == 50 * S + S // 30
    assert first.image.shape == (6, 8, 3)  # colour unless grey=True
    assert camera.stats()["clock_stamps"] == 2


# -- loss and reconnection -------------------------------------------------------------


def test_a_vanished_device_is_reopened_with_backoff_driven_by_the_clock() -> None:
    device = FakeDevice()
    device.reads.append((True, 1_000.0))
    clock = ManualClock(1 * S)
    camera = _camera(device, clock, initial_backoff_s=0.5, max_backoff_s=1.5)
    assert len(camera.read(0.0)) == 1

    device.plugged = False  # unplugged mid-stream
    assert camera.read(0.0) == []
    assert camera.stats()["losses"] == 1 and not camera.connected
    assert device.captures[0].released == 1
    opens = len(device.opened)

    def attempts_at(offsets_ns: list[int]) -> list[bool]:
        """For each time (from now), whether read() tried to reopen then."""
        start, tried = clock.now_ns(), []
        for offset in offsets_ns:
            clock.set_ns(start + offset)
            before = device.checks
            assert camera.read(0.0) == []
            tried.append(device.checks > before)
        return tried

    # Retries 0.5 s after the loss, then 1 s later, then capped at 1.5 s.
    assert attempts_at([0, S // 2 - 1, S // 2]) == [False, False, True]
    assert attempts_at([S - 1, S]) == [False, True]
    assert attempts_at([3 * S // 2 - 1, 3 * S // 2]) == [False, True]
    assert attempts_at([3 * S // 2 - 1, 3 * S // 2]) == [False, True]
    assert camera.stats()["reopen_failures"] == 4
    assert len(device.opened) == opens  # the failing check kept OpenCV out of it

    device.plugged = True
    device.reads.append((True, 7_000.0))
    clock.advance_ns(3 * S // 2)
    (frame,) = camera.read(0.0)  # reconnects and reads in the same call
    assert frame.stamp_ns == 7 * S and frame.seq == 1
    assert camera.stats()["reconnects"] == 1 and camera.connected
    # The gap: from the loss to this frame, on the camera's clock (0.5+1+1.5+1.5+1.5 s).
    assert camera.stats()["gaps"] == 1 and camera.stats()["last_gap_s"] == 6.0

    # The backoff starts again from its initial value after a good reconnection.
    device.plugged = False
    assert camera.read(0.0) == []
    assert attempts_at([S // 2 - 1, S // 2]) == [False, True]
    camera.close()


def test_dropped_frames_are_tolerated_until_too_many_in_a_row() -> None:
    device = FakeDevice()
    device.reads.extend([(False, 0), (False, 0), (True, 1.0), (False, 0), (False, 0), (False, 0)])
    clock = ManualClock(0)
    camera = _camera(device, clock, max_consecutive_failures=3, max_stamp_skew_s=10)
    results = [camera.read(0.0) for _ in range(6)]
    assert [len(r) for r in results] == [0, 0, 1, 0, 0, 0]
    stats = camera.stats()
    assert stats["no_frame_reads"] == 4
    assert stats["losses"] == 1  # the third failure in a row, device still plugged
    assert stats["empty_reads"] == 5  # the read that lost the device returned nothing too
    assert device.captures[0].released == 1
    camera.close()


def test_close_is_safe_twice_and_read_after_close_raises() -> None:
    device = FakeDevice()
    camera = _camera(device, ManualClock())
    camera.close()
    camera.close()
    assert device.captures[0].released == 1
    with pytest.raises(DriverError, match="closed"):
        camera.read(0.0)
