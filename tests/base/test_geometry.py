"""SE(2) helpers against hand-derived answers."""

import math

import numpy as np
import pytest

from robotd.base.geometry import (between, between_error_covariance, compose, interpolate_poses, inverse,
                                   quaternion_from_rotation, rigid_fit_2d, rigid_fit_2d_covariance,
                                   transform_points, wrap_angle)


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


def test_interpolate_poses_by_hand_across_the_yaw_wrap():
    track_ns = np.array([0, 10, 20])
    track = np.array([[0.0, 0.0, math.pi - 0.1], [1.0, 2.0, -math.pi + 0.1], [2.0, 2.0, -math.pi + 0.3]])
    out = interpolate_poses(track_ns, track, np.array([5, 10, 15, 2]))
    assert out.shape == (4, 3)
    assert np.allclose(out[:, :2], [[0.5, 1.0], [1.0, 2.0], [1.5, 2.0], [0.2, 0.4]], rtol=0, atol=1e-15)
    # Halfway from pi - 0.1 to -pi + 0.1 is +-pi (the short way, through 0.2 rad), not 0;
    # a fifth of the way is pi - 0.1 + 0.04 = pi - 0.06.
    assert abs(out[0, 2]) == pytest.approx(math.pi, abs=1e-12)
    assert out[1, 2] == pytest.approx(-math.pi + 0.1, abs=1e-12)
    assert out[2, 2] == pytest.approx(-math.pi + 0.2, abs=1e-12)
    assert out[3, 2] == pytest.approx(math.pi - 0.06, abs=1e-12)


def test_interpolate_poses_at_the_ends_and_outside_clamps():
    track_ns = np.array([100, 200])
    track = np.array([[1.0, -1.0, -3.0], [3.0, 1.0, 3.0]])  # the short arc from -3 to 3 passes through pi
    out = interpolate_poses(track_ns, track, np.array([100, 200, 0, 99, 201, 10**6, 150]))
    np.testing.assert_allclose(out[0], track[0], rtol=0, atol=1e-15)  # at the ends: the end poses
    np.testing.assert_allclose(out[1], track[1], rtol=0, atol=1e-15)
    # Before the first stamp and after the last: the end pose, not an extrapolation.
    np.testing.assert_allclose(out[2:4], [track[0], track[0]], rtol=0, atol=1e-15)
    np.testing.assert_allclose(out[4:6], [track[1], track[1]], rtol=0, atol=1e-15)
    # Midway, -3 and 3 meet at pi (0.283 rad the short way), not at 0 (6 rad the long way).
    assert out[6, :2] == pytest.approx([2.0, 0.0], abs=1e-15)
    assert abs(out[6, 2]) == pytest.approx(math.pi, abs=1e-12)


def test_interpolate_poses_one_pose_track_and_epoch_stamps():
    out = interpolate_poses(np.array([7]), np.array([[1.0, 2.0, 0.5]]), np.array([0, 7, 9]))
    np.testing.assert_array_equal(out, [[1.0, 2.0, 0.5]] * 3)
    # Epoch nanoseconds (~1.7e18) are beyond float64's integer resolution (2**53 ~ 9e15):
    # 1 ns after the first stamp of a 4 ns step is a quarter of the way, exactly.
    t0 = 1_700_000_000_123_456_789
    out = interpolate_poses(np.array([t0, t0 + 4]), np.array([[0.0, 0.0, 0.0], [4.0, 8.0, 0.4]]),
                            np.array([t0 + 1, t0 + 3]))
    np.testing.assert_allclose(out, [[1.0, 2.0, 0.1], [3.0, 6.0, 0.3]], rtol=0, atol=1e-12)


def test_interpolate_poses_rejects_bad_tracks():
    with pytest.raises(ValueError, match="non-decreasing"):
        interpolate_poses(np.array([0, 20, 10]), np.zeros((3, 3)), np.array([5]))
    with pytest.raises(ValueError, match="as many track stamps as poses"):
        interpolate_poses(np.array([0, 10]), np.zeros((3, 3)), np.array([5]))
    with pytest.raises(ValueError, match="at least one"):
        interpolate_poses(np.array([], dtype=np.int64), np.zeros((0, 3)), np.array([5]))


def test_rigid_fit_covariance_matches_monte_carlo():
    """The Gauss-Newton covariance of the rigid fit against the spread of 2000 fits of
    noisy copies of 15 points off-centre (the yaw couples with the translation)."""
    from robotd.base.geometry import rigid_fit_2d, rigid_fit_2d_covariance
    rng = np.random.default_rng(3)
    src = rng.uniform(-0.1, 0.1, (15, 2)) + [0.3, 0.1]
    pose = np.array([0.05, -0.02, 0.3])
    clean = transform_points(pose, src)
    fits, covs = [], []
    for _ in range(2000):
        dst = clean + rng.normal(0, 1e-3, clean.shape)
        est = rigid_fit_2d(src, dst)
        fits.append(est)
        covs.append(rigid_fit_2d_covariance(src, dst, est)[0])
    emp = np.cov(np.array(fits).T)
    mean_cov = np.mean(covs, axis=0)
    assert np.diag(mean_cov) == pytest.approx(np.diag(emp), rel=0.15)
    assert mean_cov[0, 2] == pytest.approx(emp[0, 2], rel=0.2)  # strongly coupled: not 0
    assert abs(emp[0, 2]) > 0.5 * math.sqrt(emp[0, 0] * emp[2, 2])
    cov, sigma = rigid_fit_2d_covariance(src, clean, pose, min_sigma_m=2e-3)
    assert sigma == 2e-3  # exact fit: the floor applies


def test_rigid_from_two_pairs_recovers_exact_transforms():
    from robotd.base.geometry import rigid_from_two_pairs
    rng = np.random.default_rng(4)
    poses = np.column_stack([rng.uniform(-1, 1, (5, 2)), rng.uniform(-3, 3, 5)])
    a_i, a_j = rng.uniform(-1, 1, (5, 2)), rng.uniform(-1, 1, (5, 2))
    b_i = np.array([transform_points(p, q[None])[0] for p, q in zip(poses, a_i)])
    b_j = np.array([transform_points(p, q[None])[0] for p, q in zip(poses, a_j)])
    got = rigid_from_two_pairs(a_i, a_j, b_i, b_j)
    assert got[:, :2] == pytest.approx(poses[:, :2], abs=1e-12)
    assert np.abs(wrap_angle(got[:, 2] - poses[:, 2])).max() < 1e-12


def _matrix_of(q: tuple[float, float, float, float]) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_quaternion_from_rotation_by_hand_and_round_trip():
    # By hand: 90 degrees about z; 180 degrees about x (trace -1, where the trace formula fails).
    assert quaternion_from_rotation(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])) == pytest.approx(
        (0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)))
    assert quaternion_from_rotation(np.diag([1.0, -1.0, -1.0])) == pytest.approx((1.0, 0.0, 0.0, 0.0))
    assert quaternion_from_rotation(np.diag([-1.0, 1.0, -1.0])) == pytest.approx((0.0, 1.0, 0.0, 0.0))
    assert quaternion_from_rotation(np.diag([-1.0, -1.0, 1.0])) == pytest.approx((0.0, 0.0, 1.0, 0.0))
    rng = np.random.default_rng(3)
    for _ in range(200):
        axis = rng.normal(size=3)
        angle = rng.uniform(0.0, math.pi) if _ % 2 else math.pi - rng.uniform(0.0, 1e-6)
        rot = rodrigues(axis / np.linalg.norm(axis) * angle)
        q = quaternion_from_rotation(rot)
        assert math.isclose(sum(c * c for c in q), 1.0, abs_tol=1e-12) and q[3] >= 0.0
        np.testing.assert_allclose(_matrix_of(q), rot, atol=1e-9)
    with pytest.raises(ValueError):
        quaternion_from_rotation(np.eye(2))


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis times angle), Rodrigues' formula."""
    angle = float(np.linalg.norm(rvec))
    k = rvec / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def test_between_error_covariance_is_that_of_the_graphs_edge_error():
    """A rigid fit turned by 2.5 rad, points 5-35 cm ahead of the origin (the yaw couples
    with the translation): the pose graph's edge error ``between(fit, truth)`` (GTSAM's
    and g2o's, in the frame of the edge's end) has NEES 3 against the fit's covariance
    turned by :func:`between_error_covariance`, and about 17 against the fit's own (errors
    added in the start's frame), which the graph and its gate used before."""
    rng = np.random.default_rng(5)
    src = rng.uniform([0.05, -0.1], [0.35, 0.1], size=(40, 2))
    true = np.array([0.12, -0.05, 2.5])
    turned, raw = [], []
    for _ in range(1000):
        dst = transform_points(true, src) + 0.001 * rng.standard_normal(src.shape)
        fit = rigid_fit_2d(src, dst)
        cov, _ = rigid_fit_2d_covariance(src, dst, fit)
        e = between(fit, true)
        e[2] = wrap_angle(e[2])
        turned.append(e @ np.linalg.solve(between_error_covariance(fit, cov), e))
        raw.append(e @ np.linalg.solve(cov, e))
    assert np.mean(turned) == pytest.approx(3.0, abs=0.25)  # 1000 draws: sd of the mean ~0.08
    assert np.mean(raw) > 10.0
    # A yaw of 0 leaves the covariance as it is.
    c = np.array([[4.0, 1.0, 0.5], [1.0, 2.0, -0.3], [0.5, -0.3, 1.0]])
    assert between_error_covariance(np.array([0.3, 0.1, 0.0]), c) == pytest.approx(c)
