"""Camera sources behind one small base class.

:class:`Camera` is a :class:`~drivers.base.Driver` (which does the counting, logging, the
closed check, and reconnection with exponential backoff when the device is lost) that
adds what every camera needs: stamping (the device's timestamp, else the injected clock),
frame numbering and grey conversion. A camera backend implements only
``_open_internal()``, ``_grab_internal(timeout_s)`` and ``_release_internal()``, in the
style of python-can's ``BusABC``. :class:`V4L2Camera` is the OpenCV/V4L2 backend;
:mod:`drivers.depthai_camera` holds the DepthAI one.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import stat
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np

from drivers.base import Driver, StatValue
from drivers.timesync import SkewCheck
from robotd.base.clock import Clock
from robotd.base.config import FloorCameraConfig
from robotd.base.errors import DriverError
from robotd.base.messages import Frame

__all__ = [
    "Camera",
    "CameraFormat",
    "V4L2Camera",
    "check_video_device",
    "open_v4l2",
]

_log = logging.getLogger(__name__)

VIDEO4LINUX_MAJOR = 81
"""Character-device major number of every ``/dev/videoN`` (Linux ``VIDEO_MAJOR``)."""


@dataclass(frozen=True, slots=True)
class CameraFormat:
    """A capture format: FOURCC (e.g. ``"YUYV"``), size in pixels, frame rate in Hz,
    number of driver buffers (the config's ``[floor_camera]`` names). None means "the
    driver's choice" (or "unknown")."""

    fourcc: str | None = None
    width_px: int | None = None
    height_px: int | None = None
    fps: float | None = None
    buffer_size: int | None = None


_CAMERA_COUNTERS = ("no_frame_reads", "clock_stamps", "bad_frames")


class Camera(Driver):
    """Base class of camera sources; a reconnecting :class:`~drivers.base.Driver`.

    :meth:`read` returns ``[frame]``, or ``[]`` if no frame came within the timeout or
    the device is away (it is then reopened with backoff, and the time without frames is
    counted as a gap: see :mod:`drivers.base`).

    ``name`` becomes :attr:`Frame.camera <robotd.base.messages.Frame.camera>` (``"floor"``,
    ``"forward"``). ``grey=True`` converts colour images to ``(H, W) uint8``.
    ``clock`` stamps frames that carry no device timestamp and times reconnection
    (default: the host monotonic clock). Only with a real
    :class:`~robotd.base.clock.MonotonicClock` does ``read`` sleep (up to its timeout) while
    waiting for the next reconnection attempt, so a reading thread does not spin; with
    any other clock (a ManualClock in a replay or a test) it returns ``[]`` at once.
    After a loss, attempts are made ``initial_backoff_s`` later, then at doubling
    intervals up to ``max_backoff_s``.

    :meth:`stats` adds to the base counters (which include ``losses``,
    ``reopen_failures``, ``reconnects`` and the gaps) ``no_frame_reads`` (reads with the
    device present that gave no frame: a timeout or a dropped frame) and
    ``clock_stamps`` (frames stamped with the injected clock because the device gave no
    usable stamp) and ``bad_frames`` (images of a shape that cannot be made grey,
    skipped).
    """

    def __init__(
        self,
        name: str,
        *,
        grey: bool = False,
        clock: Clock | None = None,
        initial_backoff_s: float = 0.5,
        max_backoff_s: float = 8.0,
    ) -> None:
        super().__init__(name, clock=clock, initial_backoff_s=initial_backoff_s,
                         max_backoff_s=max_backoff_s)
        self.grey = grey
        self._seq = 0
        self._counts = dict.fromkeys(_CAMERA_COUNTERS, 0)

    # -- what a backend implements ---------------------------------------------------

    def _grab_internal(self, timeout_s: float) -> tuple[np.ndarray, int | None] | None:
        """Wait up to ``timeout_s`` for one image.

        Return ``(image, stamp_ns)`` with ``stamp_ns`` None if the device has no usable
        timestamp, None if no frame came but the device is still there, or raise
        :class:`DriverError` if the device is lost (the base then reconnects).
        """
        raise NotImplementedError

    # -- public API ------------------------------------------------------------------

    def _read_internal(self, timeout_s: float) -> Frame | None:
        """The next frame, or None if none came within ``timeout_s``; raises
        :class:`DriverError` when the device is lost (the base reconnects)."""
        result = self._grab_internal(timeout_s)
        if result is None:
            self._counts["no_frame_reads"] += 1
            return None
        image, stamp_ns = result
        if stamp_ns is None:
            stamp_ns = self._clock.now_ns()
            self._counts["clock_stamps"] += 1
        if self.grey:
            try:
                image = _to_grey(image)
            except ValueError as exc:  # a bad image, not a lost device: skip it
                self._counts["bad_frames"] += 1
                log = _log.warning if self._counts["bad_frames"] == 1 else _log.debug
                log("%s: frame skipped: %s", self, exc)
                return None
        frame = Frame(stamp_ns=stamp_ns, camera=self.name, image=image, seq=self._seq)
        self._seq += 1
        return frame

    def _stats_internal(self) -> dict[str, StatValue]:
        return dict(self._counts)

    def __str__(self) -> str:
        return f"{self.name} camera"


def _to_grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    raise ValueError(f"cannot convert an image of shape {image.shape} to grey")


# -- V4L2 ------------------------------------------------------------------------------


class VideoCaptureLike(Protocol):
    """The part of ``cv2.VideoCapture`` that :class:`V4L2Camera` uses."""

    def isOpened(self) -> bool: ...  # noqa: N802 - OpenCV's name
    def set(self, prop: int, value: float) -> bool: ...
    def get(self, prop: int) -> float: ...
    def read(self) -> tuple[bool, Any]: ...
    def release(self) -> None: ...


def _file_kind(mode: int) -> str:
    for test, kind in (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return kind
    return "not a device"


def _describe_open_error(path: str, exc: OSError) -> str:
    """One line saying why ``open(path)`` failed and what to do about it."""
    code = exc.errno
    if code == errno.EBUSY:
        return (f"camera device {path} is busy: another process is using it"
                f" (see `fuser -v {path}`)")
    if code == errno.EACCES:
        return (f"camera device {path}: permission denied; the service user needs the"
                f" 'video' group (SupplementaryGroups=video)")
    if code == errno.EPERM:
        return (f"camera device {path}: operation not permitted; under systemd check"
                f" DeviceAllow=char-video4linux in the unit")
    if code in (errno.ENODEV, errno.ENXIO, errno.ENOENT):
        return (f"camera device {path} has no device behind it (unplugged, or its driver"
                f" is not loaded)")
    name = errno.errorcode.get(code or 0, str(code))
    return f"camera device {path} cannot be opened: {exc.strerror} ({name})"


def check_video_device(path: str) -> None:
    """Raise :class:`DriverError` with a specific message unless ``path`` is a
    video4linux character device that this process can open now."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise DriverError(
            f"camera device {path} does not exist (is the camera plugged in?"
            f" `v4l2-ctl --list-devices` lists the video devices)"
        ) from None
    except OSError as exc:
        raise DriverError(_describe_open_error(path, exc)) from exc
    if not stat.S_ISCHR(st.st_mode):
        raise DriverError(
            f"camera device {path} is {_file_kind(st.st_mode)}, not a character device"
        )
    major, minor = os.major(st.st_rdev), os.minor(st.st_rdev)
    if major != VIDEO4LINUX_MAJOR:
        raise DriverError(
            f"camera device {path} is a character device ({major}:{minor}) but not a"
            f" video4linux device (major {VIDEO4LINUX_MAJOR})"
        )
    try:
        fd = os.open(path, os.O_RDWR | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise DriverError(_describe_open_error(path, exc)) from exc
    os.close(fd)


def open_v4l2(section: FloorCameraConfig, clock: Clock, *, name: str = "floor") -> V4L2Camera:
    """The registry's factory of ``("floor_camera", "v4l2")``: the floor camera, grey."""
    return V4L2Camera(section.device, name=name, fourcc=section.fourcc,
                      width_px=section.width_px, height_px=section.height_px, fps=section.fps,
                      buffer_size=section.buffer_size, grey=True, clock=clock)


def open_v4l2_forward(section: Any, clock: Clock) -> V4L2Camera:
    """The registry's factory of ``("forward_camera", "v4l2")``: the forward camera, grey
    (its frames are named ``"forward"``). ``section``: ``[forward_camera]``, which holds
    its size too (see :func:`robotd.app.service.open_sources`)."""
    return open_v4l2(section, clock, name="forward")


def _fourcc_code(fourcc: str) -> int:
    if len(fourcc) != 4 or not fourcc.isascii():
        raise ValueError(f"fourcc must be 4 ASCII characters, got {fourcc!r}")
    return int(cv2.VideoWriter.fourcc(*fourcc))


def _fourcc_str(code: float) -> str | None:
    value = int(code)
    if value <= 0:
        return None
    return value.to_bytes(4, "little").decode("ascii", errors="replace")


class V4L2Camera(Camera):
    """A V4L2 camera read through OpenCV (``cv2.VideoCapture(path, cv2.CAP_V4L2)``).

    ``device`` is a path (``/dev/video0``, ``/dev/v4l/by-id/...``) or an index ``N`` for
    ``/dev/videoN``. ``fourcc``, ``width_px``, ``height_px``, ``fps`` (Hz) and
    ``buffer_size`` (driver buffers) are requested in that order (the format decides which sizes and
    rates exist); None leaves the driver's value. What the driver accepted is in
    :attr:`negotiated`, and every difference is logged as a warning. OpenCV converts each
    format to BGR; ``grey=True`` then gives ``(H, W) uint8``.

    Frames are stamped with the V4L2 buffer timestamp (``CAP_PROP_POS_MSEC``, the
    kernel's ``CLOCK_MONOTONIC`` for UVC and most capture drivers, i.e. the same base as
    :class:`~robotd.base.clock.MonotonicClock`). A stamp that is missing or further than
    ``max_stamp_skew_s`` from the clock (a driver on another time base) is replaced by the
    clock's time, and counted (``clock_stamps`` in :meth:`stats`).

    A failed read is a dropped frame unless the device node has gone or
    ``max_consecutive_failures`` reads failed in a row; then the device counts as lost and
    is reopened with backoff (see :class:`Camera`).

    ``capture_factory(path, api)`` builds the capture object (default
    ``cv2.VideoCapture``) and ``device_check(path)`` vets the node before each open
    (default :func:`check_video_device`); tests replace both at this boundary.
    """

    def __init__(
        self,
        device: str | int = "/dev/video0",
        *,
        name: str = "floor",
        fourcc: str | None = "YUYV",
        width_px: int | None = 640,
        height_px: int | None = 480,
        fps: float | None = 30.0,
        buffer_size: int | None = 4,
        grey: bool = False,
        clock: Clock | None = None,
        max_consecutive_failures: int = 3,
        max_stamp_skew_s: float = 2.0,
        initial_backoff_s: float = 0.5,
        max_backoff_s: float = 8.0,
        capture_factory: Callable[[str, int], VideoCaptureLike] = cv2.VideoCapture,
        device_check: Callable[[str], None] = check_video_device,
    ) -> None:
        super().__init__(
            name,
            grey=grey,
            clock=clock,
            initial_backoff_s=initial_backoff_s,
            max_backoff_s=max_backoff_s,
        )
        if isinstance(device, bool) or not isinstance(device, str | int):
            raise TypeError(f"device must be a path or an index, got {device!r}")
        self.path = f"/dev/video{device}" if isinstance(device, int) else device
        if fourcc is not None:
            _fourcc_code(fourcc)  # validate now, not at the first (re)open
        if max_consecutive_failures < 1:
            raise ValueError("max_consecutive_failures must be >= 1")
        self.requested = CameraFormat(fourcc, width_px, height_px, fps, buffer_size)
        self.negotiated = CameraFormat()
        """What the driver accepted at the last (re)open."""
        self._max_failures = max_consecutive_failures
        self._skew = SkewCheck(int(max_stamp_skew_s * 1e9))
        self._capture_factory = capture_factory
        self._device_check = device_check
        self._cap: VideoCaptureLike | None = None
        self._timeout_ms: int | None = None
        self._failures_in_row = 0
        self._start()

    def __str__(self) -> str:
        return f"{self.name} camera {self.path}"

    def _open_internal(self) -> None:
        self._device_check(self.path)
        cap = self._capture_factory(self.path, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise DriverError(
                f"camera device {self.path}: OpenCV's V4L2 backend could not open it"
                f" (busy with another process, or not a capture device?)"
            )
        try:
            self.negotiated = self._configure(cap)
        except BaseException:
            cap.release()
            raise
        self._cap = cap
        self._timeout_ms = None
        self._failures_in_row = 0
        _log.info("%s open: %s", self, self.negotiated)

    def _configure(self, cap: VideoCaptureLike) -> CameraFormat:
        want = self.requested
        # Order matters: the pixel format decides which sizes exist, the size which rates.
        if want.fourcc is not None:
            cap.set(cv2.CAP_PROP_FOURCC, _fourcc_code(want.fourcc))
        if want.width_px is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, want.width_px)
        if want.height_px is not None:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, want.height_px)
        if want.fps is not None:
            cap.set(cv2.CAP_PROP_FPS, want.fps)
        if want.buffer_size is not None:
            cap.set(cv2.CAP_PROP_BUFFERSIZE, want.buffer_size)

        fps = cap.get(cv2.CAP_PROP_FPS)
        got = CameraFormat(
            fourcc=_fourcc_str(cap.get(cv2.CAP_PROP_FOURCC)),
            width_px=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            height_px=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            fps=float(fps) if fps > 0 else None,
            buffer_size=int(cap.get(cv2.CAP_PROP_BUFFERSIZE)),
        )
        differences = []
        if want.fourcc is not None and got.fourcc != want.fourcc:
            differences.append(f"format {got.fourcc} instead of {want.fourcc}")
        if (want.width_px is not None and got.width_px != want.width_px) or (
            want.height_px is not None and got.height_px != want.height_px
        ):
            differences.append(
                f"size {got.width_px}x{got.height_px} instead of"
                f" {want.width_px}x{want.height_px}"
            )
        if want.fps is not None and (got.fps is None or abs(got.fps - want.fps) > 0.5):
            differences.append(f"{got.fps} fps instead of {want.fps}")
        if want.buffer_size is not None and got.buffer_size != want.buffer_size:
            differences.append(f"{got.buffer_size} buffers instead of {want.buffer_size}")
        if differences:
            _log.warning("%s: the driver chose %s", self, "; ".join(differences))
        return got

    def _grab_internal(self, timeout_s: float) -> tuple[np.ndarray, int | None] | None:
        cap = self._cap
        assert cap is not None
        if timeout_s is not None:
            timeout_ms = max(1, math.ceil(timeout_s * 1000))
            if timeout_ms != self._timeout_ms:
                cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms)
                self._timeout_ms = timeout_ms
        ok, image = cap.read()
        if not ok or image is None:
            self._failures_in_row += 1
            try:
                self._device_check(self.path)
            except DriverError as exc:
                raise DriverError(f"device gone: {exc}") from exc
            if self._failures_in_row >= self._max_failures:
                raise DriverError(f"no frame in {self._failures_in_row} reads in a row")
            return None
        self._failures_in_row = 0
        return image, self._driver_stamp_ns(cap.get(cv2.CAP_PROP_POS_MSEC))

    def _driver_stamp_ns(self, pos_msec: float) -> int | None:
        if not (math.isfinite(pos_msec) and pos_msec > 0):
            return None
        stamp_ns = round(pos_msec * 1e6)
        if not self._skew.accept(stamp_ns, self._clock.now_ns()):
            if self._skew.rejected == 1:
                _log.warning(
                    "%s: driver timestamps are %.3f s off the clock; stamping with the clock",
                    self, self._skew.last_skew_ns / 1e9,
                )
            return None
        return stamp_ns

    def _release_internal(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()
