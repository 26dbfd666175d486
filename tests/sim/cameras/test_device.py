"""The simulated camera device: frames at their times, lossless or dropping the newest."""

from __future__ import annotations

import threading

import numpy as np

from sim.cameras.device import VirtualCamera


def _camera(lossless: bool, capacity: int = 2, stop: threading.Event | None = None) -> VirtualCamera:
    times = np.array([0.0, 0.1, 0.2, 0.3])
    return VirtualCamera("floor", times, lambda t: np.full((2, 3), int(t * 100), np.uint8),
                         capacity=capacity, lossless=lossless, stop=stop)


def test_frames_carry_their_time_index_and_rendered_image():
    cam = _camera(lossless=True)
    cam.emit(0)
    cam.emit(2)
    first, second = cam.read(0.0), cam.read(0.0)
    assert (first.stamp_ns, first.camera, first.seq) == (0, "floor", 0)
    assert (second.stamp_ns, second.seq) == (200_000_000, 2)
    assert second.image.shape == (2, 3) and second.image[0, 0] == 20
    assert cam.read(0.0) is None
    assert cam.frames_emitted == 2 and cam.dropped == 0


def test_real_time_mode_refuses_new_frames_when_the_reader_is_late():
    cam = _camera(lossless=False, capacity=2)
    for i in range(4):
        cam.emit(i)
    assert cam.dropped == 2 and cam.frames_emitted == 4
    assert [cam.read(0.0).seq, cam.read(0.0).seq] == [0, 1]  # the newest were refused


def test_a_lossless_hand_over_gives_up_when_stopped():
    stop = threading.Event()
    cam = _camera(lossless=True, capacity=1, stop=stop)
    cam.emit(0)
    stop.set()
    cam.emit(1)  # the queue is full: returns once it sees the stop event
    assert cam.read(0.0).seq == 0 and cam.read(0.0) is None and cam.dropped == 0
    cam.close()
    cam.close()
    assert cam.closed
