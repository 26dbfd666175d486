"""Keyframe selection and the stored keyframe image."""

from __future__ import annotations

import math

import numpy as np

from robotd.keyframes import KeyframeSelector, downsample


def test_keyframe_selector_by_distance_and_rotation():
    sel = KeyframeSelector(distance_m=0.1, rotation_rad=math.radians(10))
    assert sel.offer(np.array([0.0, 0.0, 0.0]))  # the first frame is always a keyframe
    assert not sel.offer(np.array([0.09, 0.0, 0.0]))
    assert sel.offer(np.array([0.06, 0.08, 0.0]))  # 0.1 m away (3-4-5)
    assert not sel.offer(np.array([0.06, 0.08, math.radians(9.9)]))
    assert sel.offer(np.array([0.06, 0.08, math.radians(-10.5)]))


def test_downsample_keeps_aspect():
    img = np.zeros((480, 640), np.uint8)
    assert downsample(img, 160).shape == (120, 160)
    assert downsample(img, 0) is None
    assert downsample(np.zeros((480, 640, 3), np.uint8), 160).shape == (120, 160)
    small = np.zeros((10, 20), np.uint8)
    assert downsample(small, 160) is small  # never enlarged
