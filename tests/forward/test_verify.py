"""Epipolar verification on a synthetic scene with a known relative pose."""

from __future__ import annotations

import numpy as np

from robotd.forward.features import Features
from robotd.forward.verify import (ACCEPTED, NO_GEOMETRIC_CONSISTENCY, TOO_FEW_MATCHES,
                                   VerifyParams, camera_matrix_guess, verify_pair)

K = camera_matrix_guess(640, 480)


def _rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _project(x_cam: np.ndarray) -> np.ndarray:
    p = (K @ x_cam.T).T
    return (p[:, :2] / p[:, 2:]).astype(np.float32)


def _scene(rng: np.random.Generator, n: int = 150):
    """Points 3-8 m in front of the old camera; the new camera turned 10 degrees and moved
    0.5 m (x_new = R x_old + t)."""
    x_old = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(3, 8, n)])
    r = _rot_y(np.radians(10))
    t = np.array([0.3, 0.0, -0.4])
    x_new = x_old @ r.T + t
    return x_old, x_new, r, t


def _features(xy: np.ndarray, desc: np.ndarray) -> Features:
    return Features(xy, desc, (640, 480))


def test_a_true_pair_is_accepted_with_its_rotation_and_translation_direction():
    rng = np.random.default_rng(0)
    x_old, x_new, r, t = _scene(rng)
    desc = rng.standard_normal((150, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    px_new = _project(x_new) + rng.normal(0, 0.3, (150, 2)).astype(np.float32)
    v = verify_pair(_features(_project(x_old), desc), _features(px_new, desc))
    assert v.accepted and v.reason == ACCEPTED
    assert v.n_matches == 150 and v.n_inliers >= 130
    angle = np.degrees(np.arccos(np.clip((np.trace(v.rotation.T @ r) - 1) / 2, -1, 1)))
    assert angle < 0.5
    assert np.dot(v.translation_dir, t / np.linalg.norm(t)) > 0.995  # within 6 degrees


def test_shuffled_points_fail_the_epipolar_check():
    rng = np.random.default_rng(1)
    x_old, x_new, _, _ = _scene(rng)
    desc = rng.standard_normal((150, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    px_new = _project(x_new)[rng.permutation(150)]  # right descriptors, wrong places
    v = verify_pair(_features(_project(x_old), desc), _features(px_new, desc))
    assert not v.accepted and v.reason == NO_GEOMETRIC_CONSISTENCY
    assert v.n_matches == 150 and v.n_inliers < 20


def test_too_few_matches_is_a_value_not_an_exception():
    rng = np.random.default_rng(2)
    a = rng.standard_normal((10, 128)).astype(np.float32)
    xy = rng.uniform(0, 400, (10, 2)).astype(np.float32)
    v = verify_pair(_features(xy, a), _features(xy, a), VerifyParams(min_inliers=20))
    assert not v.accepted and v.reason == TOO_FEW_MATCHES and v.n_matches == 10
    empty = Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), (640, 480))
    assert verify_pair(empty, _features(xy, a)).reason == TOO_FEW_MATCHES
