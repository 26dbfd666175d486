"""SE(2) helpers against hand-derived answers."""

import math

import numpy as np
import pytest

from robotd.base.geometry import between, compose, inverse, rigid_fit_2d, transform_points, wrap_angle


def test_compose_inverse_between_by_hand():
    a = np.array([1.0, 2.0, math.pi / 2])
    b = np.array([1.0, 0.0, 0.0])
    assert np.allclose(compose(a, b), [1.0, 3.0, math.pi / 2])  # 1 m forward while facing +y
    assert np.allclose(compose(a, inverse(a)), [0, 0, 0])
    assert np.allclose(between(a, compose(a, b)), b)
    assert wrap_angle(3 * math.pi) == pytest.approx(-math.pi)


def test_rigid_fit_recovers_a_known_motion_with_noise():
    rng = np.random.default_rng(0)
    src = rng.uniform(-0.3, 0.3, (40, 2))
    pose = np.array([0.12, -0.05, 0.7])
    dst = transform_points(pose, src) + rng.normal(0, 1e-4, src.shape)
    est = rigid_fit_2d(src, dst)
    assert np.allclose(est[:2], pose[:2], atol=1e-4) and est[2] == pytest.approx(0.7, abs=1e-3)
    # A mirrored set is not a rotation: the fit stays a proper rotation anyway.
    est2 = rigid_fit_2d(src, src * [1, -1])
    assert np.isfinite(est2).all()
