"""Calibration pairs: every pair that could overlap, plus weighted distant pairs."""

import numpy as np

from calibration.train import candidate_pairs
from robotd.floorcam import FloorCameraModel, overlap_ratios


def test_near_pairs_complete_and_far_pairs_weighted():
    cam = FloorCameraModel.default()
    # Two parallel 6 m passes 3 m apart, keyframes every 5 cm: nothing across the passes overlaps.
    s = np.arange(0, 6, 0.05)
    poses = np.vstack([np.column_stack([s, np.zeros_like(s), np.zeros_like(s)]),
                       np.column_stack([s[::-1], np.full_like(s, 3.0), np.full_like(s, np.pi)])])
    n = len(poses)
    i, j, w = candidate_pairs(poses, cam, far_per_keyframe=2.0, rng=np.random.default_rng(0))
    assert np.all(i > j)
    assert len(set(zip(i.tolist(), j.tolist()))) == len(i)  # no pair twice
    # Every pair with J > 0 is among the weight-1 (near) pairs.
    ai, aj = np.tril_indices(n, -1)
    j_all = overlap_ratios(cam, poses[ai], poses[aj])
    near = set(zip(i[w == 1].tolist(), j[w == 1].tolist()))
    assert {(a, b) for a, b, x in zip(ai.tolist(), aj.tolist(), j_all) if x > 0} <= near
    # The sampled distant pairs stand for all distant pairs.
    far = w != 1
    assert far.sum() == int(2.0 * n)
    assert np.isclose(w[far].sum(), n * (n - 1) / 2 - (w == 1).sum())
