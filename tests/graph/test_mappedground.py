"""Localisation over mapped ground (robotd.graph.mappedground): the edge algebra, and the
state machine against a small graph of known poses."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from robotd.graph.mappedground import MappedGround, MappedGroundParams, compose_edges, invert_edge
from robotd.base.geometry import between, compose, inverse


def _p(v: np.ndarray) -> gtsam.Pose2:
    return gtsam.Pose2(float(v[0]), float(v[1]), float(v[2]))


def _right_jacobian(f, *poses: np.ndarray, h: float = 1e-6) -> list[np.ndarray]:
    """Numeric Jacobians of ``f(*poses)`` under right perturbations ``p exp(xi)`` of each
    argument, the result's error taken the same way (``log(f0^-1 f)``), with GTSAM's
    Expmap and Logmap: the pose graph's convention, computed independently of the code."""
    f0 = _p(f(*poses))
    out = []
    for k in range(len(poses)):
        cols = []
        for i in range(3):
            xi = np.zeros(3)
            xi[i] = h
            plus = list(poses)
            minus = list(poses)
            pk = _p(poses[k])
            for sign, args in ((1, plus), (-1, minus)):
                q = pk.compose(gtsam.Pose2.Expmap(sign * xi))
                args[k] = np.array([q.x(), q.y(), q.theta()])
            e_plus = gtsam.Pose2.Logmap(f0.between(_p(f(*plus))))
            e_minus = gtsam.Pose2.Logmap(f0.between(_p(f(*minus))))
            cols.append((e_plus - e_minus) / (2 * h))
        out.append(np.column_stack(cols))
    return out


def test_the_inverse_edge_propagates_the_covariance_in_the_graphs_convention() -> None:
    d = np.array([0.4, -0.25, 2.7])
    cov = np.diag([1e-4, 4e-4, 1e-3])
    inv, cov_inv = invert_edge((d, cov))
    np.testing.assert_allclose(inv, inverse(d))
    (j,) = _right_jacobian(inverse, d)
    np.testing.assert_allclose(cov_inv, j @ cov @ j.T, atol=1e-9)
    # Inverting twice gives the edge back, covariance included.
    back, cov_back = invert_edge((inv, cov_inv))
    np.testing.assert_allclose(back, d, atol=1e-12)
    np.testing.assert_allclose(cov_back, cov, atol=1e-12)


def test_composed_edges_add_their_deltas_and_propagate_both_covariances() -> None:
    a = (np.array([1.0, 0.2, 2.5]), np.diag([1e-4, 1e-4, 1e-3]))
    b = (np.array([0.3, -0.1, -0.2]), np.diag([4e-4, 1e-4, 2e-3]))
    d, cov = compose_edges(a, b)
    np.testing.assert_allclose(d, compose(a[0], b[0]))
    ja, jb = _right_jacobian(compose, a[0], b[0])
    np.testing.assert_allclose(cov, ja @ a[1] @ ja.T + jb @ b[1] @ jb.T, atol=1e-9)


class Corridor:
    """A graph of 11 nodes every 0.1 m along x (ids 100..110), heading 0, each with the
    same marginal covariance; ``chi2`` as the graph's gate computes it, for two nodes."""

    def __init__(self, sigma_m: float = 0.01) -> None:
        self.poses = {100 + i: np.array([0.1 * i, 0.0, 0.0]) for i in range(11)}
        self.p = np.diag([sigma_m**2, sigma_m**2, (sigma_m / 2) ** 2])

    def pose(self, i: int) -> np.ndarray:
        return self.poses[i]

    def positions(self) -> np.ndarray:
        return np.array([p[:2] for p in self.poses.values()])

    def chi2(self, a: int, b: int, delta: np.ndarray, information: np.ndarray) -> float:
        e = between(between(self.poses[a], self.poses[b]), np.asarray(delta, float))
        s = 2 * self.p + np.linalg.inv(information)
        return float(e @ np.linalg.solve(s, e))


GATE = 16.27
LOOP_COV = np.diag([1e-5, 1e-5, 1e-4])
STEP_COV = np.diag([1e-6, 1e-6, 1e-6])


def _localised_at(node: int, graph: Corridor, **kw) -> MappedGround:
    """A robot that stored keyframe ``node`` (odometry pose = the node's pose) and had a
    loop accepted for it."""
    m = MappedGround(MappedGroundParams(**kw), graph.pose, graph.positions, graph.chi2)
    m.stored(node, graph.pose(node))
    m.loop_accepted(node)
    assert m.localised and m.entered == 1
    return m


def test_not_localised_every_keyframe_is_stored() -> None:
    g = Corridor()
    m = MappedGround(MappedGroundParams(), g.pose, g.positions, g.chi2)
    m.stored(100, g.pose(100))
    assert not m.is_transient(np.array([0.1, 0.0, 0.0]))
    # A loop accepted for an older keyframe than the newest does not localise the robot.
    m.stored(101, g.pose(101))
    m.loop_accepted(100)
    assert not m.localised
    # Nothing in between: the stored keyframe's edge is its own odometry edge.
    edge = (np.array([0.1, 0.0, 0.0]), STEP_COV)
    assert m.edge_for_stored(101, edge)[0] == 101


def test_a_transient_match_re_anchors_and_the_next_stored_keyframe_links_from_it() -> None:
    g = Corridor()
    m = _localised_at(105, g)
    step = (np.array([0.1, 0.0, 0.0]), STEP_COV)
    odom = g.pose(105).copy()
    for _ in range(2):  # two keyframes over mapped ground, 0.1 m apart
        odom = compose(odom, step[0])
        assert m.is_transient(odom)
        m.extend(step, odom)
    # The second transient (at x = 0.7 by odometry) sees node 107 from 2 cm behind it.
    ok, d2 = m.match(107, np.array([0.02, 0.0, 0.0]), np.linalg.inv(LOOP_COV), GATE)
    assert ok, d2
    assert m.node == 107 and m.matches_accepted == 1
    # Driving on to x = 1.2 (0.2 m past the last node) leaves mapped ground...
    odom2 = compose(odom, np.array([0.48, 0.0, 0.0]))
    assert not m.is_transient(odom2)
    assert m.left_new_ground == 1 and not m.localised
    # ...and that keyframe is stored with its edge from node 107, through the match.
    edge = (np.array([0.48, 0.0, 0.0]), STEP_COV)
    from_id, delta, cov = m.edge_for_stored(None, edge)
    assert from_id == 107
    np.testing.assert_allclose(delta, [0.50, 0.0, 0.0], atol=1e-12)
    assert np.all(np.linalg.eigvalsh(cov) > 0) and cov[0, 0] > LOOP_COV[0, 0]
    m.stored(111, compose(g.pose(107), delta))
    assert m.node == 111 and m.edge_for_stored(111, edge)[0] == 111


def test_a_match_that_disagrees_with_the_prediction_is_refused_and_changes_nothing() -> None:
    g = Corridor()
    m = _localised_at(105, g)
    step = (np.array([0.1, 0.0, 0.0]), STEP_COV)
    odom = compose(g.pose(105), step[0])
    assert m.is_transient(odom)
    m.extend(step, odom)
    # A look-alike: the transient (really at x = 0.6) claimed to be 0.3 m from node 110.
    ok, d2 = m.match(110, np.array([-0.3, 0.05, 0.0]), np.linalg.inv(LOOP_COV), GATE)
    assert not ok and d2 > GATE
    assert m.node == 105 and m.matches_failed_gate == 1 and m.localised
    # The true match is still accepted afterwards.
    ok, _ = m.match(106, np.array([0.0, 0.0, 0.0]), np.linalg.inv(LOOP_COV), GATE)
    assert ok


def test_too_far_without_an_accepted_match_the_robot_maps_again() -> None:
    g = Corridor()
    m = _localised_at(100, g, max_unlocalised_m=0.35)
    step = (np.array([0.1, 0.0, 0.0]), STEP_COV)
    odom = g.pose(100).copy()
    transient = []
    for _ in range(5):
        odom = compose(odom, step[0])
        t = m.is_transient(odom)
        transient.append(t)
        if t:
            m.extend(step, odom)
    assert transient == [True, True, True, False, False]
    assert m.left_unlocalised == 1 and m.left_new_ground == 0
    # The stored keyframe is linked from node 100 by the whole chain (0.4 m).
    from_id, delta, _ = m.edge_for_stored(None, step)
    assert from_id == 100
    np.testing.assert_allclose(delta, [0.4, 0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("sigma_m", [0.01, 0.05])
def test_a_match_to_the_anchor_node_itself_is_gated_on_the_chain_alone(sigma_m: float) -> None:
    g = Corridor(sigma_m)
    m = _localised_at(105, g)
    step = (np.array([0.05, 0.0, 0.0]), STEP_COV)
    odom = compose(g.pose(105), step[0])
    assert m.is_transient(odom)
    m.extend(step, odom)
    ok, _ = m.match(105, np.array([0.05, 0.0, 0.0]), np.linalg.inv(LOOP_COV), GATE)
    assert ok
    ok, d2 = m.match(105, np.array([0.30, 0.0, 0.0]), np.linalg.inv(LOOP_COV), GATE)
    assert not ok and d2 > GATE
