"""Keyframe selection and the stored keyframe image."""

from __future__ import annotations

import math

import numpy as np

from robotd.base.geometry import between
from robotd.keyframes import KeyframeSelector, downsample, relative_pose


def test_keyframe_selector_by_distance_and_rotation():
    sel = KeyframeSelector(distance_m=0.1, rotation_rad=math.radians(10))
    assert sel.offer(np.array([0.0, 0.0, 0.0]))  # the first frame is always a keyframe
    assert not sel.offer(np.array([0.09, 0.0, 0.0]))
    assert sel.offer(np.array([0.06, 0.08, 0.0]))  # 0.1 m away (3-4-5)
    assert not sel.offer(np.array([0.06, 0.08, math.radians(9.9)]))
    assert sel.offer(np.array([0.06, 0.08, math.radians(-10.5)]))


def test_relative_pose_is_between_bit_for_bit():
    """The selector's float version of ``between`` gives its values to the last bit (the
    keyframe decision compares them with the spacing, so one ulp could move a keyframe),
    across the whole angle range, through the +-pi wrap and far from the origin."""
    rng = np.random.default_rng(7)
    n = 20_000
    a = np.column_stack([rng.uniform(-200, 200, n), rng.uniform(-200, 200, n), rng.uniform(-4, 4, n)])
    b = a + np.column_stack([rng.normal(0, 0.2, n), rng.normal(0, 0.2, n), rng.normal(0, 0.5, n)])
    b[:2000, 2] = -np.sign(a[:2000, 2]) * math.pi + rng.normal(0, 1e-3, 2000)  # across the wrap
    for pa, pb in zip(a, b):
        expected = between(pa, pb)
        got = relative_pose(pa, pb)
        assert all(type(v) is float for v in got)
        assert np.array_equal(np.array(got), expected), (pa, pb)


def test_downsample_keeps_aspect():
    img = np.zeros((480, 640), np.uint8)
    assert downsample(img, 160).shape == (120, 160)
    assert downsample(img, 0) is None
    assert downsample(np.zeros((480, 640, 3), np.uint8), 160).shape == (120, 160)
    small = np.zeros((10, 20), np.uint8)
    assert downsample(small, 160) is small  # never enlarged
