"""The loop-corrected pose's covariance: iSAM2 keyframe marginals (grow along a chain,
shrink with a loop) and their composition with the odometry since the keyframe."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.graph import IncrementalGraph
from robotd.graph.covariance import corrected_pose, odometry_increment_covariance, tangent_to_world

SIG_XY, SIG_YAW = 0.01, 0.005
INFO = np.diag([1 / SIG_XY**2, 1 / SIG_XY**2, 1 / SIG_YAW**2])


def _chain(n: int) -> IncrementalGraph:
    g = IncrementalGraph()
    g.add_first(0)
    for k in range(1, n):
        g.add_keyframe(k, k - 1, (1.0, 0.0, 0.0), INFO)
    return g


def test_marginals_grow_along_a_chain_and_a_loop_shrinks_them() -> None:
    g = _chain(11)
    yaw_var = [g.marginal_covariance(k)[2, 2] for k in range(11)]
    # a straight chain: the yaw variance adds up edge by edge (the anchor's 1e-8 aside)
    assert yaw_var == pytest.approx([k * SIG_YAW**2 for k in range(11)], abs=1e-12)
    # sideways: each edge's own 1e-4 m^2 plus the yaw error swinging the j m behind it
    lateral = [g.marginal_covariance(k)[1, 1] for k in range(11)]
    expected = [k * SIG_XY**2 + SIG_YAW**2 * sum(j * j for j in range(k)) for k in range(11)]
    assert lateral == pytest.approx(expected, rel=1e-6, abs=1e-12)
    assert np.all(np.diff(lateral) > 0)
    before = g.marginal_covariance(10)
    # back to the start: keyframe 10 seen from keyframe 0, as a loop closure would
    g.add_loop(0, 10, (10.0, 0.0, 0.0), INFO)
    after = g.marginal_covariance(10)
    assert after[2, 2] < 0.2 * before[2, 2] and after[1, 1] < 0.05 * before[1, 1]
    # keyframe 0 is fixed, so the loop measures keyframe 10's pose directly: information adds
    # (the loop agrees with the chain, so its robust kernel weighs it fully)
    assert after == pytest.approx(np.linalg.inv(np.linalg.inv(before) + INFO), rel=1e-4, abs=1e-12)
    # the middle of the loop gains less than its end
    mid = g.marginal_covariance(5)[1, 1]
    assert mid < lateral[5] and mid > after[1, 1]


def test_tangent_to_world_turns_the_axes() -> None:
    body = np.diag([4.0, 1.0, 0.5])
    assert tangent_to_world(np.array([3.0, 2.0, 0.0]), body) == pytest.approx(body)
    assert tangent_to_world(np.array([3.0, 2.0, np.pi / 2]), body) == pytest.approx(np.diag([1.0, 4.0, 0.5]))


def test_increment_covariance_undoes_dead_reckoning() -> None:
    odom_k = np.array([1.0, 2.0, 0.3])
    cov_k = np.array([[2e-4, 5e-5, 1e-5], [5e-5, 3e-4, 2e-5], [1e-5, 2e-5, 1e-4]])
    now = np.array([2.5, 2.4, 0.6])
    q = np.diag([1e-4, 2e-4, 4e-5])
    j = np.array([[1, 0, -(now[1] - odom_k[1])], [0, 1, now[0] - odom_k[0]], [0, 0, 1]])
    cov_now = j @ cov_k @ j.T + q  # how a dead-reckoning covariance grows
    assert odometry_increment_covariance(odom_k, cov_k, now, cov_now) == pytest.approx(q, abs=1e-15)
    # a covariance that shrank (a visual update) gives no negative variance
    inc = odometry_increment_covariance(odom_k, cov_k, now, 0.5 * cov_k)
    assert np.linalg.eigvalsh(inc).min() >= -1e-18


def test_corrected_pose_composes_the_keyframe_and_the_increment() -> None:
    map_k, cov_map_k = np.array([5.0, 1.0, np.pi / 2]), np.diag([1e-3, 2e-3, 1e-4])
    odom_k = np.array([0.0, 0.0, 0.0])
    zero = np.zeros((3, 3))
    # at the keyframe: its own pose and marginal
    pose, cov = corrected_pose(map_k, cov_map_k, odom_k, zero, odom_k, zero)
    assert pose == pytest.approx(map_k) and cov == pytest.approx(cov_map_k)
    # 1 m ahead in odom (x), which is +y in the map (odom turned 90 deg in the map):
    # the odometry's x variance becomes the map's y variance, and the keyframe's yaw
    # variance swings the 1 m lever sideways (map x)
    q = np.diag([4e-4, 1e-4, 0.0])
    pose, cov = corrected_pose(map_k, cov_map_k, odom_k, zero, np.array([1.0, 0.0, 0.0]), q)
    assert pose == pytest.approx([5.0, 2.0, np.pi / 2])
    assert cov[0, 0] == pytest.approx(1e-3 + 1e-4 * 1.0 + 1e-4)
    assert cov[1, 1] == pytest.approx(2e-3 + 4e-4)
    assert cov[2, 2] == pytest.approx(1e-4)
    assert cov[0, 2] == pytest.approx(-1e-4)
