"""The pose graph's data checks and objectives, against values computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.base.errors import GraphError
from robotd.graph import (PoseGraph, chain_poses, check_information, chi2, isotropic_graph,
                          isotropic_objective, isotropic_weights, make_edge)


def _two_pose_graph(info: np.ndarray) -> PoseGraph:
    g = PoseGraph()
    g.add_pose(3, (0.0, 0.0, 0.0))
    g.add_pose(7, (1.0, 0.0, math.pi / 2))
    g.add_edge(3, 7, (1.0, 0.5, 0.25), info, "odometry")
    return g


def test_isotropic_weights_follow_the_readme():
    info = np.array([[4.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 9.0]])
    kappa, tau = isotropic_weights(info)
    # inv([[4,1],[1,2]]) = [[2,-1],[-1,4]] / 7, trace 6/7, tau = 2 / (6/7) = 7/3
    assert kappa == 9.0
    assert tau == pytest.approx(7.0 / 3.0)


def test_isotropic_objective_on_a_tiny_graph_by_hand():
    info = np.array([[4.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 9.0]])
    g = _two_pose_graph(info)
    # t_j - t_i - R_i t_ij = (1, 0) - (1, 0.5) = (0, -0.5): tau * 0.25
    # yaw error pi/2 - 0.25: kappa * 4 * (1 - cos(pi/2 - 0.25))
    expected = 7.0 / 3.0 * 0.25 + 9.0 * 4.0 * (1.0 - math.cos(math.pi / 2 - 0.25))
    assert isotropic_objective(g, g.ids, g.poses()) == pytest.approx(expected, rel=1e-12)


def test_chi2_uses_the_error_in_the_measured_frame():
    info = np.diag([2.0, 3.0, 5.0])
    g = _two_pose_graph(info)
    # delta^-1 (+) between: rotate (0, -0.5) by -0.25 rad -> (-0.5 sin 0.25, -0.5 cos 0.25)
    ex, ey, eyaw = -0.5 * math.sin(0.25), -0.5 * math.cos(0.25), math.pi / 2 - 0.25
    expected = 2.0 * ex**2 + 3.0 * ey**2 + 5.0 * eyaw**2
    assert chi2(g, g.ids, g.poses()) == pytest.approx(expected, rel=1e-12)


def test_isotropic_graph_chi2_matches_the_objective_to_second_order():
    info = np.array([[4.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 9.0]])
    g = _two_pose_graph(info)
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.25 + 1e-3]])
    iso = isotropic_graph(g)
    assert chi2(iso, g.ids, poses) == pytest.approx(isotropic_objective(g, g.ids, poses), rel=1e-6)
    assert np.allclose(iso.edges[0].information, np.diag([7 / 3, 7 / 3, 18.0]))


@pytest.mark.parametrize("info, why", [
    (np.diag([1.0, 1.0, 0.0]), "positive definite"),
    (np.diag([1.0, -1.0, 1.0]), "positive definite"),
    (np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "positive definite"),
    (np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "symmetric"),
    (np.diag([1.0, np.nan, 1.0]), "finite"),
])
def test_bad_information_is_refused(info, why):
    with pytest.raises(GraphError, match=why):
        check_information(info)


def test_information_up_to_1e12_is_accepted():
    assert check_information(np.diag([1e12, 1e12, 1e12]))[0, 0] == 1e12


def test_duplicate_vertex_and_missing_endpoint_are_errors():
    g = PoseGraph()
    g.add_pose(0, (0, 0, 0))
    with pytest.raises(GraphError, match="duplicate vertex 0"):
        g.add_pose(0, (1, 0, 0))
    with pytest.raises(GraphError, match="no vertex 5"):
        g.add_edge(0, 5, (1, 0, 0), np.eye(3), "loop")


def test_chain_poses_composes_odometry_then_reaches_the_rest_by_loops():
    eye = np.eye(3)
    edges = [make_edge(10, 20, (1.0, 0.0, math.pi / 2), eye, "odometry"),
             make_edge(30, 20, (0.0, -1.0, 0.0), eye, "loop")]   # 20 reached only backwards
    poses = chain_poses([10, 20, 30], edges)
    assert np.allclose(poses[10], 0.0)
    assert np.allclose(poses[20], (1.0, 0.0, math.pi / 2))
    # 30 (+) (0, -1, 0) = 20  =>  30 = (0, 0, pi/2) shifted: x30 - (-1)*(-1)... by inverse
    assert np.allclose(poses[30], (0.0, 0.0, math.pi / 2))


def test_chain_poses_names_an_unreachable_vertex():
    with pytest.raises(GraphError, match="vertex 9 is not connected"):
        chain_poses([1, 2, 9], [make_edge(1, 2, (1, 0, 0), np.eye(3), "odometry")])


def test_edges_read_back_as_added_and_a_taken_list_does_not_change():
    """The graph keeps its edges in arrays: what :attr:`PoseGraph.edges` builds equals what
    was added, in order, and a sequence taken before more edges (and a growth of the
    arrays past their first 64 rows) still holds exactly the edges it had."""
    g = PoseGraph()
    rng = np.random.default_rng(3)
    for k in range(100):
        g.add_pose(10 + k, rng.normal(size=3))
    added = []
    for k in range(1, 50):
        a = rng.normal(size=(3, 3))
        added.append(g.add_edge(10 + k - 1, 10 + k, rng.normal(size=3), a @ a.T + np.eye(3),
                                "loop" if k % 7 == 0 else "odometry"))
    before = g.edges
    for k in range(50, 100):
        added.append(g.add_edge(10 + k - 1, 10 + k, (0.1, 0.0, 0.0), np.eye(3), "odometry"))
    assert len(before) == 49 and len(g.edges) == 99 == g.edge_count
    assert g.loop_count == 7 and np.flatnonzero(g.is_loop).tolist() == [k - 1 for k in range(7, 50, 7)]
    for got, want in zip(list(before) + g.edges[49:], added):
        assert (got.from_id, got.to_id, got.kind) == (want.from_id, want.to_id, want.kind)
        assert np.array_equal(got.delta, want.delta) and np.array_equal(got.information, want.information)
        assert not got.delta.flags.writeable and not got.information.flags.writeable
    assert before[-1].to_id == 59 and g.edges[-1].to_id == 109
    with pytest.raises(IndexError):
        before[49]
    p = g.pose(12)
    assert not p.flags.writeable
    g.set_pose(12, (1.0, 2.0, 0.5))
    assert np.array_equal(g.pose(12), [1.0, 2.0, 0.5]) and not np.array_equal(p, g.pose(12))
    assert g.poses()[2].tolist() == [1.0, 2.0, 0.5] and g.ids[2] == 12
