"""A simulated camera device: frames rendered at their times, read like a real camera.

:class:`VirtualCamera` is one camera part of :class:`~sim.robot.VirtualRobot`: it lists its
frame times (``event_times_s``), renders and hands over frame ``i`` when the robot calls
``emit(i)``, and is read like :class:`drivers.camera.V4L2Camera` (``read(timeout_s)``
returns a :class:`~robotd.base.messages.Frame` or ``None``; ``close()``). The hand-over is a
:class:`~robotd.base.queues.BoundedQueue`: lossless (the robot waits for the reader) when
the robot runs as fast as the CPU allows, ``drop="newest"`` in real time, as a camera
whose reader is late refuses new frames.

:class:`PluggableV4L2Device` is a V4L2 camera on the real clock as
:class:`drivers.camera.V4L2Camera` sees it through its boundary (``capture_factory`` and
``device_check``), which can be unplugged and plugged back in: for fault tests of the
real driver and the daemon.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from robotd.base.errors import DriverError
from robotd.base.messages import Frame
from robotd.base.queues import BoundedQueue

__all__ = ["PluggableV4L2Device", "VirtualCamera"]


class VirtualCamera:
    """Frames of ``render(t_s) -> image`` at ``frame_times_s`` (``(F,) float64``, s), named
    ``name`` (:attr:`Frame.camera <robotd.base.messages.Frame.camera>`).

    ``capacity`` frames wait for the reader; ``lossless`` chooses the queue's mode (see
    the module). A lossless hand-over gives up when ``stop`` is set. ``exhausted`` is set
    by the robot after the last frame; ``dropped`` counts refused frames.
    """

    def __init__(self, name: str, frame_times_s: np.ndarray,
                 render: Callable[[float], np.ndarray], *, capacity: int, lossless: bool,
                 stop: threading.Event | None = None) -> None:
        self.name = name
        self.event_times_s = np.asarray(frame_times_s, dtype=float)
        self._render = render
        self._queue: BoundedQueue[Frame] = BoundedQueue(capacity, lossless=lossless,
                                                        drop="newest", name=f"camera-{name}")
        self._stop = stop if stop is not None else threading.Event()
        self.lossless = lossless
        self.frames_emitted = 0
        self.exhausted = threading.Event()
        self.closed = False

    @property
    def dropped(self) -> int:
        """Frames refused because the reader was late (real-time mode only)."""
        return self._queue.dropped

    def emit(self, i: int) -> None:
        """Render frame ``i`` at its time and hand it over."""
        t_s = float(self.event_times_s[i])
        frame = Frame(int(round(t_s * 1e9)), self.name, self._render(t_s), i)
        self._queue.put(frame, self._stop)
        self.frames_emitted += 1

    def read(self, timeout_s: float) -> Frame | None:
        """The next frame, waiting up to ``timeout_s``; ``None`` when none came."""
        return self._queue.get(timeout_s)

    def close(self) -> None:
        """Mark the camera closed (the robot owns its frames); safe to call twice."""
        self.closed = True


class PluggableV4L2Device:
    """A V4L2 camera delivering ``render(i)`` (frame ``i``, an image) at ``fps`` Hz of the
    host's monotonic clock, stamped like a UVC driver (``CAP_PROP_POS_MSEC`` = the
    monotonic time of the frame, ms).

    Pass :meth:`check` as ``device_check`` and :meth:`capture` as ``capture_factory`` to
    :class:`drivers.camera.V4L2Camera`. :meth:`unplug` makes the node vanish (reads fail,
    the check raises "does not exist", captures do not open); :meth:`replug` brings it
    back. A read waits (real time, up to the driver's read timeout) for the next frame;
    frames due while nobody read are skipped, as a driver with few buffers drops them.
    """

    def __init__(self, render: Callable[[int], np.ndarray], fps: float) -> None:
        if not fps > 0:
            raise ValueError("fps must be > 0")
        self._render = render
        self.period_s = 1.0 / fps
        self._plugged = threading.Event()
        self._plugged.set()
        self._start_s = time.monotonic()
        self.frames_served = 0
        self.opens = 0

    @property
    def plugged(self) -> bool:
        """True while the device is there."""
        return self._plugged.is_set()

    def unplug(self) -> None:
        """The device vanishes (reads in progress fail)."""
        self._plugged.clear()

    def replug(self) -> None:
        """The device is back; it must be opened again."""
        self._plugged.set()

    def check(self, path: str) -> None:
        """``device_check``: raises :class:`DriverError` while unplugged."""
        if not self.plugged:
            raise DriverError(f"camera device {path} does not exist (unplugged)")

    def capture(self, path: str, api: int) -> _PluggableCapture:
        """``capture_factory``: a capture on this device."""
        self.opens += 1
        return _PluggableCapture(self)

    def _next_frame(self, timeout_s: float) -> tuple[np.ndarray, float] | None:
        """The next frame and its stamp (ms), waiting up to ``timeout_s``; None when
        unplugged or none came in time."""
        now = time.monotonic()
        index = int((now - self._start_s) / self.period_s) + 1
        due = self._start_s + index * self.period_s
        if due - now > timeout_s:
            time.sleep(timeout_s)
            return None
        time.sleep(max(0.0, due - now))
        if not self.plugged:
            return None
        self.frames_served += 1
        return self._render(index), due * 1000.0


class _PluggableCapture:
    """The ``cv2.VideoCapture`` look-alike of :class:`PluggableV4L2Device`."""

    def __init__(self, device: PluggableV4L2Device) -> None:
        self._device = device
        self._open = device.plugged
        self._props: dict[int, float] = {cv2.CAP_PROP_READ_TIMEOUT_MSEC: 1000.0}

    def isOpened(self) -> bool:  # noqa: N802 - OpenCV's name
        return self._open

    def set(self, prop: int, value: float) -> bool:
        self._props[prop] = float(value)
        return True

    def get(self, prop: int) -> float:
        if prop == cv2.CAP_PROP_FPS:
            return 1.0 / self._device.period_s
        return self._props.get(prop, 0.0)

    def read(self) -> tuple[bool, Any]:
        if not (self._open and self._device.plugged):
            return False, None
        got = self._device._next_frame(self._props[cv2.CAP_PROP_READ_TIMEOUT_MSEC] / 1000.0)
        if got is None:
            return False, None
        image, stamp_ms = got
        self._props[cv2.CAP_PROP_POS_MSEC] = stamp_ms
        return True, image

    def release(self) -> None:
        self._open = False
