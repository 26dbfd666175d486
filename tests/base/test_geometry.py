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


def test_wrap_angle_scalars_by_hand():
    assert wrap_angle(math.pi) == -math.pi  # the interval is [-pi, pi)
    assert wrap_angle(-math.pi) == -math.pi
    assert wrap_angle(0.5) == 0.5
    assert wrap_angle(2 * math.pi + 0.25) == pytest.approx(0.25, abs=1e-15)
    assert wrap_angle(-2.5 * math.pi) == pytest.approx(-0.5 * math.pi, abs=1e-15)
    assert wrap_angle(7) == pytest.approx(7 - 2 * math.pi, abs=1e-15)  # an int
    # A NumPy scalar gives a plain float (the EKF stores it in its state array).
    out = wrap_angle(np.float64(4.0))
    assert type(out) is float and out == pytest.approx(4.0 - 2 * math.pi, abs=1e-15)


def test_wrap_angle_arrays_keep_shape_and_dtype():
    a = np.array([[3 * math.pi / 2, -3 * math.pi / 2], [0.1, -7.0]])
    out = wrap_angle(a)
    assert out.shape == (2, 2) and out.dtype == np.float64
    assert np.allclose(out, [[-math.pi / 2, math.pi / 2], [0.1, -7.0 + 2 * math.pi]], atol=1e-15)
    f32 = wrap_angle(np.array([4.0], dtype=np.float32))
    assert f32.dtype == np.float32 and f32[0] == pytest.approx(4.0 - 2 * math.pi, abs=1e-6)


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

