"""Calibration pairs: every pair that could overlap, plus weighted distant pairs."""

import numpy as np

from calibration.train import candidate_pairs, trusted_pairs
from robotd.base.camera import FloorCameraModel, overlap_ratios


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


def test_trusted_pairs_leave_out_what_drift_could_relabel():
    cam = FloorCameraModel.default()
    # A 4 m square driven twice, keyframes every 5 cm: the second lap revisits the first
    # 16 m of travel later, with a neighbour 5 cm behind and a far corner across the square.
    side = np.arange(0, 4, 0.05)
    lap = np.vstack([np.column_stack([side, np.zeros_like(side)]),
                     np.column_stack([np.full_like(side, 4.0), side]),
                     np.column_stack([4.0 - side, np.full_like(side, 4.0)]),
                     np.column_stack([np.zeros_like(side), 4.0 - side])])
    xy = np.vstack([lap, lap])
    poses = np.column_stack([xy, np.zeros(len(xy))])
    n_lap = len(lap)
    i = np.array([1, n_lap + 10, n_lap + 10, n_lap + 10])
    j = np.array([0, 10, 9, 2 * 80 + 10])  # neighbour; revisit; revisit's neighbour; opposite side
    fp = cam.footprint_robot(8)
    side_m = float(np.min(fp.max(axis=0) - fp.min(axis=0)))
    ok = trusted_pairs(poses, cam, i, j, drift=0.02, tolerance=0.1)
    # 16 m apart in travel: up to 0.32 m of drift, more than 10 % of the footprint; the
    # corner 8 m across the square is further than reach + drift whatever the drift.
    assert 0.02 * 16.0 > 0.1 * side_m
    assert ok.tolist() == [True, False, False, True]
    # A perfect odometry labels everything; a very loose tolerance too.
    assert trusted_pairs(poses, cam, i, j, drift=0.0, tolerance=0.1).all()
    assert trusted_pairs(poses, cam, i, j, drift=0.02, tolerance=10.0).all()
