"""What the detector keeps per image: word ids, keypoints in 1/16 px,
binary descriptors; about 12 kB for 300 ORB keypoints."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.forward.features import Features, compact
from robotd.forward.verify import VerifyParams, verify_pair


def test_compact_features_keep_keypoints_to_a_32nd_of_a_pixel_in_12_kb():
    rng = np.random.default_rng(0)
    kp = rng.uniform(0, 639.9, (300, 2)).astype(np.float32)
    f = Features(kp, rng.integers(0, 256, (300, 32), dtype=np.uint8), (640, 480))
    c = compact(f, np.arange(300))
    assert np.abs(c.keypoints_px - kp).max() <= 1 / 32 + 1e-6
    assert c.nbytes == 300 * (4 + 4 + 32) == 12_000
    assert c.words.dtype == np.uint32 and len(c) == 300
    with pytest.raises(ValueError):
        compact(Features(kp, f.descriptors, (5000, 480)), np.arange(300))


def test_the_verification_takes_compact_features_as_it_takes_full_ones():
    """A synthetic two-view scene: the same decision and inliers from both forms."""
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-2, 2, 200), rng.uniform(-1, 1, 200), rng.uniform(3, 8, 200)]
    k = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])

    def project(p):
        x = (k @ p.T).T
        return (x[:, :2] / x[:, 2:]).astype(np.float32)

    desc = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    a = Features(project(pts), desc, (640, 480))
    b = Features(project(pts - np.array([0.3, 0.0, 0.5])), desc, (640, 480))
    full = verify_pair(a, b, VerifyParams(min_support_area=0.0), k)
    small = verify_pair(compact(a, np.arange(200)), b, VerifyParams(min_support_area=0.0), k)
    assert full.accepted and small.accepted
    assert abs(full.n_inliers - small.n_inliers) <= 2
