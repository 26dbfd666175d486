"""A simulated camera device: frames rendered at their times, read like a real camera.

:class:`VirtualCamera` is one camera part of :class:`~sim.robot.VirtualRobot`: it lists its
frame times (``event_times_s``), renders and hands over frame ``i`` when the robot calls
``emit(i)``, and is read like :class:`drivers.camera.V4L2Camera` (``read(timeout_s)``
returns a :class:`~robotd.base.messages.Frame` or ``None``; ``close()``). The hand-over is a
:class:`~robotd.base.queues.BoundedQueue`: lossless (the robot waits for the reader) when
the robot runs as fast as the CPU allows, ``drop="newest"`` in real time, as a camera
whose reader is late refuses new frames.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from robotd.base.messages import Frame
from robotd.base.queues import BoundedQueue

__all__ = ["VirtualCamera"]


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
