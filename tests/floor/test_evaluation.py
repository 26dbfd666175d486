"""Candidates judged against ground-truth overlap: hand-built cases."""

import numpy as np
import pytest

from robotd.floor.evaluation import candidate_report, overlap_matrix
from robotd.base.camera import CameraIntrinsics, FloorCameraModel


def test_overlap_matrix_of_a_forward_run():
    cam = FloorCameraModel(CameraIntrinsics(640, 480, 400.0, 400.0, 319.5, 239.5), height_m=0.40)
    poses = np.array([[0.0, 0, 0], [0.12, 0, 0], [0.24, 0, 0], [5.0, 0, 0]])
    m = overlap_matrix(cam, poses)
    assert np.allclose(m, m.T) and np.allclose(np.diag(m), 1.0)
    # footprint 0.48 m long in x: J = (0.48 - d) / (0.48 + d)
    assert m[1, 0] == pytest.approx(0.36 / 0.60, abs=1e-6)
    assert m[2, 0] == pytest.approx(0.24 / 0.72, abs=1e-6)
    assert m[3, 0] == 0.0 and m[3, 2] == 0.0


def test_candidate_report_counts():
    s = 1_000_000_000
    stamps = np.array([0, 1, 2, 30, 31, 60]) * s
    ov = np.zeros((6, 6))
    ov[3, 0] = ov[0, 3] = 0.5   # keyframe 3 revisits 0
    ov[4, 1] = ov[1, 4] = 0.2   # 4 is near 1 but below r
    ov[5, 4] = ov[4, 5] = 0.9   # 5 overlaps 4, but 4 is old enough (29 s > 20 s): eligible
    queries = [
        (3, [(0, 12.0), (2, 3.0)]),  # true revisit found, top-1 true
        (4, [(1, 9.0)]),             # no true revisit; top-1 false
        (5, [(0, 20.0)]),            # true revisit (4) missed; top-1 false
    ]
    rep = candidate_report(ov, stamps, queries, exclude_recent_s=20.0)
    assert (rep.queries, rep.queries_with_true_loop, rep.found) == (3, 2, 1)
    assert (rep.top1_true, rep.top1_total) == (1, 3)
    assert rep.recall == 0.5
    assert rep.precision_above(10.0) == (1, 2)   # scores 12 (true) and 20 (false)
    assert rep.precision_above(15.0) == (0, 1)
    # with a longer exclusion, keyframe 4 is too recent for 5: no true loop for 5
    rep2 = candidate_report(ov, stamps, queries, exclude_recent_s=40.0)
    assert rep2.queries_with_true_loop == 0  # 3's revisit of 0 is excluded too (30 s < 40 s)
