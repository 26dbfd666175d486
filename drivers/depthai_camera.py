"""The DepthAI v3 camera (Luxonis OAK): one camera socket, mono or colour, at a set size
and frame rate, with the device's timestamps.

:class:`DepthAICamera` is a :class:`~drivers.camera.Camera`, so the base classes do the
counting, the grey conversion and the reconnection with backoff. Opening is one call at a
boundary, ``opener(settings, on_status) -> DepthAIStream``: a started depthai pipeline,
its output queue and the device. :func:`open_device_stream` (the default) builds what the
robot runs with depthai v3's API: ``dai.Device`` (found by id or name, or the first one
available), ``dai.Pipeline(device)``, a ``dai.node.Camera`` built on the board socket,
``requestOutput((width, height), GRAY8 or NV12, fps=...)`` and a non-blocking output queue.

Reconnection, in two layers that are one mechanism:

1. depthai's own: ``Device.setMaxReconnectionAttempts(n, callback)``. When the device
   drops off the bus, depthai reconnects it and reports ``RECONNECTING`` then
   ``RECONNECTED``, or ``RECONNECT_FAILED`` once the ``n`` attempts are spent. The
   callback (on depthai's thread) only queues the status; the reading thread handles it:
   ``RECONNECTING`` begins a gap (:meth:`~drivers.base.Driver._device_away`), the next
   frame ends it.
2. When depthai gives up, or the stream closes or its pipeline stops, the grab raises
   :class:`~robotd.base.errors.DriverError` and :mod:`drivers.base` releases everything
   and reopens from scratch (a new device and pipeline) with exponential backoff. The gap
   runs on until frames flow again.

Timestamps: ``ImgFrame.getTimestamp()``, the device's capture time that depthai maps onto
the host's steady clock (``CLOCK_MONOTONIC`` on Linux, the time base of
:class:`~robotd.base.clock.MonotonicClock`) by its own time synchronisation.
``getTimestampDevice()`` (the raw device clock) is not used: it restarts with the device.
A stamp further than ``max_stamp_skew_s`` from the injected clock is replaced by the
clock's time and counted (``clock_stamps``), as for V4L2.

What is tested without a device (``tests/drivers/test_depthai_camera.py``):

- on real depthai objects, through :func:`replay_stream_opener` (a host-only depthai
  pipeline whose ``dai.node.ReplayVideo`` node plays a video file into a real
  ``MessageQueue``): frame conversion (GRAY8, and NV12 to BGR), size, numbering,
  timestamps, the queue closing (a lost device), and reopening with backoff;
- with a fake device at depthai's boundary (fake ``dai.Device``, ``dai.Pipeline`` and
  Camera node that record the calls and hand real ``dai.ImgFrame`` objects through a
  fake queue): :func:`open_device_stream`'s calls (socket, size, type, fps, queue,
  reconnection attempts with the driver's callback), device stamps, sequence gaps, and
  depthai's reconnection statuses arriving through that callback. That a real device
  accepts these calls is not tested here (no device); on a host without one the
  opener's first step gives the one-line "no DepthAI device found" error, which is
  tested against depthai's real (empty) device list.
"""

from __future__ import annotations

import collections
import datetime
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import depthai as dai
import numpy as np

from drivers.base import StatValue
from drivers.camera import Camera
from drivers.timesync import SkewCheck
from robotd.base.clock import Clock
from robotd.base.errors import DriverError

__all__ = [
    "SOCKETS",
    "DepthAICamera",
    "DepthAISettings",
    "DepthAIStream",
    "open_depthai",
    "open_device_stream",
    "replay_stream_opener",
]

_log = logging.getLogger(__name__)

SOCKETS = ("CAM_A", "CAM_B", "CAM_C", "CAM_D", "CAM_E", "CAM_F", "CAM_G", "CAM_H")
"""Board sockets a camera can be on (``dai.CameraBoardSocket`` names). On an OAK-D,
CAM_A is the colour camera and CAM_B/CAM_C the mono pair."""


@dataclass(frozen=True, slots=True)
class DepthAISettings:
    """What to open: ``device_id`` (a device id such as ``14442C10D13EABCE00``, an IP
    address or a USB port name; ``""`` = the first device found), the board ``socket``
    (one of :data:`SOCKETS`), the output size in pixels and rate in Hz, ``colour``
    (NV12 from the ISP, converted to BGR on the host) or mono (GRAY8), the host queue's
    length in frames (older frames are dropped when the reader is late), and how many
    times depthai itself tries to reconnect a lost device (0: never, the driver then
    reopens it at once)."""

    device_id: str = ""
    socket: str = "CAM_A"
    width_px: int = 640
    height_px: int = 400
    fps: float = 30.0
    colour: bool = False
    queue_size: int = 4
    reconnection_attempts: int = 3

    def __post_init__(self) -> None:
        if self.socket not in SOCKETS:
            raise ValueError(f"socket must be one of {', '.join(SOCKETS)}, got {self.socket!r}")
        if self.width_px < 1 or self.height_px < 1 or not self.fps > 0:
            raise ValueError("width_px, height_px and fps must be positive")
        if self.queue_size < 1 or self.reconnection_attempts < 0:
            raise ValueError("queue_size must be >= 1 and reconnection_attempts >= 0")

    @property
    def frame_type(self) -> Any:
        """The requested ``dai.ImgFrame.Type``: NV12 (colour) or GRAY8 (mono)."""
        return dai.ImgFrame.Type.NV12 if self.colour else dai.ImgFrame.Type.GRAY8


@dataclass(slots=True)
class DepthAIStream:
    """A started depthai pipeline, the output queue of the camera's frames, and the device
    it runs on (None for a host-only pipeline)."""

    pipeline: Any
    queue: Any
    device: Any = None

    def close(self) -> None:
        """Stop the pipeline and close the device (each safe to call twice)."""
        try:
            self.pipeline.stop()
        finally:
            if self.device is not None:
                self.device.close()


StreamOpener = Callable[[DepthAISettings, Callable[[Any], None]], DepthAIStream]
"""``(settings, on_status) -> DepthAIStream``; ``on_status`` takes a
``dai.Device.ReconnectionStatus``. Raises :class:`DriverError` when it cannot open."""


def _find_device(device_id: str) -> Any:
    """The ``dai.DeviceInfo`` of ``device_id`` (or of the first device when empty).

    Looks among the devices present first (about 0.5 s), so a missing camera is one clear
    error at once rather than depthai's 10 s search for it.
    """
    try:
        found = dai.Device.getAllAvailableDevices()
    except RuntimeError as exc:
        raise DriverError(f"cannot list DepthAI devices: {exc}") from exc
    if not found:
        raise DriverError("no DepthAI device found (is the camera plugged in? "
                          "for a PoE camera, is it on this network?)")
    if not device_id:
        return found[0]
    for info in found:
        if device_id in (info.getDeviceId(), info.name):
            return info
    names = ", ".join(f"{i.getDeviceId()} ({i.name})" for i in found)
    raise DriverError(f"DepthAI device {device_id} not found; present: {names}")


def open_device_stream(settings: DepthAISettings, on_status: Callable[[Any], None]) -> DepthAIStream:
    """Open the camera on a real device (see the module): the default opener."""
    info = _find_device(settings.device_id)
    try:
        device = dai.Device(info)
    except RuntimeError as exc:
        raise DriverError(f"DepthAI device {info.getDeviceId()} cannot be opened: {exc}") from exc
    try:
        device.setMaxReconnectionAttempts(settings.reconnection_attempts, on_status)
        pipeline = dai.Pipeline(device)
        socket = getattr(dai.CameraBoardSocket, settings.socket)
        camera = pipeline.create(dai.node.Camera).build(socket)
        output = camera.requestOutput((settings.width_px, settings.height_px),
                                      settings.frame_type, fps=settings.fps)
        queue = output.createOutputQueue(maxSize=settings.queue_size, blocking=False)
        pipeline.start()
    except RuntimeError as exc:
        device.close()
        raise DriverError(f"DepthAI device {info.getDeviceId()}: cannot start the "
                          f"{settings.socket} camera at {settings.width_px}x{settings.height_px}, "
                          f"{settings.fps:g} fps: {exc}") from exc
    return DepthAIStream(pipeline, queue, device)


def replay_stream_opener(video_path: str | os.PathLike[str], *, loop: bool = False) -> StreamOpener:
    """An opener that plays ``video_path`` through depthai's ``ReplayVideo`` node on a
    host-only pipeline, at the settings' size, rate and frame type: the camera without a
    device. The video's end closes the stream (a lost device, to the driver); a missing
    file is a device that cannot be opened, so moving the file away and back is an
    unplug and a replug."""
    path = os.fspath(video_path)

    def open_replay(settings: DepthAISettings, on_status: Callable[[Any], None]) -> DepthAIStream:
        if not os.path.isfile(path):
            raise DriverError(f"replayed DepthAI camera: {path} does not exist")
        pipeline = dai.Pipeline(False)
        replay = pipeline.create(dai.node.ReplayVideo)
        replay.setReplayVideoFile(Path(path))
        replay.setOutFrameType(settings.frame_type)
        replay.setSize(settings.width_px, settings.height_px)
        replay.setFps(settings.fps)
        replay.setLoop(loop)
        queue = replay.out.createOutputQueue(maxSize=settings.queue_size, blocking=False)
        pipeline.start()
        return DepthAIStream(pipeline, queue, None)

    return open_replay


def open_depthai(section: Any, clock: Clock, *, name: str = "floor") -> DepthAICamera:
    """The registry's factory of ``("floor_camera", "depthai")``: the floor camera, grey,
    from a ``[floor_camera]`` section (``depthai_device``, ``depthai_socket``, size,
    ``fps``, ``colour``, ``buffer_size`` as the host queue, ``depthai_reconnection_attempts``)."""
    settings = DepthAISettings(
        device_id=section.depthai_device, socket=section.depthai_socket,
        width_px=section.width_px, height_px=section.height_px, fps=section.fps,
        colour=section.colour, queue_size=section.buffer_size,
        reconnection_attempts=section.depthai_reconnection_attempts)
    return DepthAICamera(settings, name=name, grey=True, clock=clock)


def open_depthai_forward(section: Any, clock: Clock) -> DepthAICamera:
    """The registry's factory of ``("forward_camera", "depthai")``: as
    :func:`open_depthai`, frames named ``"forward"``."""
    return open_depthai(section, clock, name="forward")


def _timedelta_ns(td: datetime.timedelta) -> int:
    return (td.days * 86_400 + td.seconds) * 1_000_000_000 + td.microseconds * 1_000


class DepthAICamera(Camera):
    """A DepthAI camera (see the module).

    ``settings`` says which camera and how; ``opener`` opens it (default
    :func:`open_device_stream`; tests pass :func:`replay_stream_opener`). ``grey``,
    ``clock`` and the backoff are :class:`~drivers.camera.Camera`'s.

    :meth:`stats` adds ``frames_skipped`` (frames the device numbered but the host never
    got: the queue overflowed while the reader was late), ``frames_discarded`` (frames
    still queued when depthai reported the device lost), ``other_messages`` (messages
    that were not images, ignored), and depthai's own reconnection as it reported it:
    ``depthai_reconnecting``, ``depthai_reconnected``, ``depthai_gave_up``.
    """

    def __init__(self, settings: DepthAISettings | None = None, *, name: str = "floor",
                 grey: bool = False, clock: Clock | None = None, max_stamp_skew_s: float = 2.0,
                 initial_backoff_s: float = 0.5, max_backoff_s: float = 8.0,
                 opener: StreamOpener = open_device_stream) -> None:
        super().__init__(name, grey=grey, clock=clock, initial_backoff_s=initial_backoff_s,
                         max_backoff_s=max_backoff_s)
        self.settings = DepthAISettings() if settings is None else settings
        self._opener = opener
        self._skew = SkewCheck(int(max_stamp_skew_s * 1e9))
        self._stream: DepthAIStream | None = None
        self._statuses: collections.deque[Any] = collections.deque()
        self._last_seq: int | None = None
        self._dai_counts = dict.fromkeys(
            ("frames_skipped", "frames_discarded", "other_messages", "depthai_reconnecting", "depthai_reconnected",
             "depthai_gave_up"), 0)
        self._start()

    def __str__(self) -> str:
        s = self.settings
        return f"{self.name} camera DepthAI {s.device_id or '(first found)'} {s.socket}"

    def _on_status(self, status: Any) -> None:
        """depthai's reconnection callback (its own thread): queue the status only."""
        self._statuses.append(status)

    def _open_internal(self) -> None:
        self._statuses.clear()
        self._stream = self._opener(self.settings, self._on_status)
        self._last_seq = None
        s = self.settings
        _log.info("%s open: %dx%d %s at %g fps", self, s.width_px, s.height_px,
                  "colour" if s.colour else "mono", s.fps)

    def _release_internal(self) -> None:
        stream, self._stream = self._stream, None
        if stream is not None:
            try:
                stream.close()
            except RuntimeError as exc:
                _log.debug("%s: error while closing: %s", self, exc)

    def _handle_statuses(self) -> bool:
        """Handle depthai's queued reconnection statuses; True if the device just went
        away (the frames still queued from before are then discarded: they must not end
        the gap that has just begun)."""
        status_type = dai.Device.ReconnectionStatus
        went_away = False
        while self._statuses:
            status = self._statuses.popleft()
            if status == status_type.RECONNECTING:
                self._dai_counts["depthai_reconnecting"] += 1
                self._device_away("disconnected; depthai is reconnecting it")
                went_away = True
            elif status == status_type.RECONNECTED:
                self._dai_counts["depthai_reconnected"] += 1
                went_away = False
                _log.info("%s: depthai reconnected the device", self)
            elif status == status_type.RECONNECT_FAILED:
                self._dai_counts["depthai_gave_up"] += 1
                raise DriverError(f"depthai gave up reconnecting after "
                                  f"{self.settings.reconnection_attempts} attempts")
        return went_away

    def _grab_internal(self, timeout_s: float) -> tuple[np.ndarray, int | None] | None:
        stream = self._stream
        assert stream is not None
        try:
            if self._handle_statuses():
                self._dai_counts["frames_discarded"] += len(stream.queue.tryGetAll())
                return None
            msg = stream.queue.get(datetime.timedelta(seconds=timeout_s))
        except dai.MessageQueue.QueueException as exc:
            raise DriverError(f"the frame stream closed ({exc})") from exc
        if msg is None:
            if not stream.pipeline.isRunning():
                raise DriverError("its pipeline stopped")
            return None
        if not isinstance(msg, dai.ImgFrame):
            self._dai_counts["other_messages"] += 1
            return None
        seq = int(msg.getSequenceNum())
        if self._last_seq is not None and seq > self._last_seq + 1:
            self._dai_counts["frames_skipped"] += seq - self._last_seq - 1
        self._last_seq = seq
        image = msg.getCvFrame()  # GRAY8: (H, W) uint8; NV12: converted to BGR (H, W, 3)
        return image, self._stamp_ns(msg.getTimestamp())

    def _stamp_ns(self, timestamp: datetime.timedelta) -> int | None:
        stamp_ns = _timedelta_ns(timestamp)
        if stamp_ns <= 0 or not self._skew.accept(stamp_ns, self._clock.now_ns()):
            if self._skew.rejected == 1:
                _log.warning("%s: device timestamps are %.3f s off the clock; stamping with the "
                             "clock", self, self._skew.last_skew_ns / 1e9)
            return None
        return stamp_ns

    def _stats_internal(self) -> dict[str, StatValue]:
        out = super()._stats_internal()
        out.update(self._dai_counts)
        return out
