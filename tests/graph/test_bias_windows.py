"""The bias windows in the daemon's graph (``IncrementalParams.odometry_model =
"bias_window"``): the live windows, the fold and the combine with a visual step keep the
bias model's marginals; dropping the terms or counting an edge twice would change them."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from robotd.graph.bias import (
    BiasEdge,
    bias_edge_factor,
    bias_factor_graph,
    bias_initial_values,
    bias_key,
    bias_prior_factor,
    bias_window_factor,
    span_edge,
)
from robotd.graph.factors import anchor_factor
from robotd.graph.incremental import IncrementalGraph, IncrementalParams
from robotd.odometry.history import EdgeBiasTerms
from robotd.odometry.increments import combine_bias_terms, combine_edges

N = 10  # one window


def _edges(n: int, start: int = 0, *, var: float = 1e-6, step_m: float = 0.05) -> list[BiasEdge]:
    """A turning chain whose edges share a large gyro bias share (jac on yaw and lateral),
    its covariances and bias variances in units of ``var``, each edge ``step_m`` forward
    (tests/graph/test_scale_variables.py takes it tighter and longer)."""
    out = []
    rng = np.random.default_rng(3)
    for k in range(start, start + n):
        cov = np.diag([3.0, 1.0, 2.0]) * var
        cov[1, 2] = cov[2, 1] = 0.4 * var
        jac = np.array([0.0, -0.01, -0.2]) * (1 + 0.1 * rng.standard_normal())
        p = (40.0 - (k - start)) * var
        out.append(BiasEdge(k, k + 1, np.array([step_m, 0.002, 0.08]), cov, jac, 0.003, p, 0.003, p - var,
                            p - 0.5 * var))
    return out


def _terms(e: BiasEdge) -> EdgeBiasTerms:
    return EdgeBiasTerms(e.cov_given_bias, e.jac_bias, e.bias_radps, e.bias_var, e.bias_end_radps,
                         e.bias_end_var, e.bias_cov)


def _marginal_cov(e: BiasEdge) -> np.ndarray:
    return e.cov_given_bias + e.bias_var * np.outer(e.jac_bias, e.jac_bias)


def _per_edge_marginal(edges: list[BiasEdge], key: int,
                       scale_sigmas: tuple[float, float] | None = None) -> np.ndarray:
    """The marginal of ``key`` in the per-edge model (with a scale variable of prior
    ``scale_sigmas`` when given)."""
    fg = bias_factor_graph(edges, scale_sigmas=scale_sigmas)
    values = bias_initial_values(edges, scales=scale_sigmas is not None)
    return np.asarray(gtsam.Marginals(fg, values).marginalCovariance(key))


def _live(edges: list[BiasEdge], model: str = "bias_window", fold: int = 10, **params) -> IncrementalGraph:
    g = IncrementalGraph(IncrementalParams(odometry_model=model, fold=fold, **params))
    g.add_first(0)
    for e in edges:
        g.add_keyframe(e.to_id, e.from_id, e.delta, np.linalg.inv(_marginal_cov(e)), _terms(e))
    return g


def test_a_closed_window_in_isam2_is_the_per_edge_bias_model():
    edges = _edges(N)
    want = _per_edge_marginal(edges, N)
    got = _live(edges).marginal_covariance(N)
    assert got == pytest.approx(want, rel=1e-5, abs=1e-14)
    # the terms dropped (independent edges with the same marginal covariances): not the model
    plain = _live(edges, "independent").marginal_covariance(N)
    assert abs(plain[2, 2] / want[2, 2] - 1) > 0.2


def test_the_open_windows_edges_are_replaced_not_counted_twice():
    edges = _edges(N + 3)
    g = _live(edges)
    stats = g.stats()
    # anchor + window factor + bias prior + the open window's 3 independent edges
    assert stats["factors"] == 1 + 2 + 3
    assert g.bias_windows == 1
    assert g.marginal_covariance(N) == pytest.approx(_per_edge_marginal(edges[:N], N), rel=1e-5, abs=1e-14)


def test_a_fold_span_is_the_window_with_its_inner_poses_eliminated():
    edges = _edges(N)
    s = span_edge(edges)
    fg = gtsam.NonlinearFactorGraph()
    fg.add(anchor_factor(0, np.zeros(3)))
    fg.add(bias_prior_factor(0, edges[0].bias_radps, edges[0].bias_var))
    fg.add(bias_edge_factor(s))
    values = gtsam.Values()
    values.insert(0, gtsam.Pose2())
    values.insert(N, gtsam.Pose2(*s.delta))
    values.insert(bias_key(0), np.array([edges[0].bias_radps]))
    got = np.asarray(gtsam.Marginals(fg, values).marginalCovariance(N))
    assert got == pytest.approx(_per_edge_marginal(edges, N), rel=1e-5, abs=1e-14)
    wf = bias_window_factor(edges)
    assert wf.dim() == 3 * N


def test_a_fold_keeps_the_bias_model():
    edges = _edges(2 * N + 5)
    g = _live(edges)
    before = {k: g.marginal_covariance(k) for k in (N, 2 * N)}
    g.resolve()
    assert g.stats()["folded"] > 0
    # keyframe 10 ends the first span (10 edges from the anchor): exactly the per-edge model
    assert g.marginal_covariance(N) == pytest.approx(before[N], rel=1e-5, abs=1e-14)
    assert g.marginal_covariance(N) == pytest.approx(_per_edge_marginal(edges[:N], N), rel=1e-5, abs=1e-14)
    # the next window's end: the windows' chain (its walk inside the window left out) against
    # the spans' chain: close, and not the independent edges' marginal
    assert g.marginal_covariance(2 * N) == pytest.approx(before[2 * N], rel=0.02)
    plain = _live(edges, "independent")
    plain.resolve()
    assert abs(plain.marginal_covariance(2 * N)[2, 2] / g.marginal_covariance(2 * N)[2, 2] - 1) > 0.2
    # the live windows go on after the fold
    more = _edges(12, start=2 * N + 5)
    for e in more:
        g.add_keyframe(e.to_id, e.from_id, e.delta, np.linalg.inv(_marginal_cov(e)), _terms(e))
    assert np.isfinite(g.marginal_covariance(more[-1].to_id)).all()


def test_the_full_solve_with_windows_closes_a_loop():
    edges = _edges(2 * N + 5)
    g = _live(edges)
    truth = bias_initial_values(edges)
    end = edges[-1].to_id
    p = truth.atPose2(end)
    g.add_loop(0, end, np.array([p.x(), p.y(), p.theta()]) + [0.002, -0.001, 0.001], np.eye(3) * 1e6)
    result = g.resolve()
    i = int(np.flatnonzero(result.ids == end)[0])
    assert result.poses[i] == pytest.approx([p.x() + 0.002, p.y() - 0.001, p.theta() + 0.001], abs=2e-4)
    assert g.pose(end) == pytest.approx(result.poses[i], abs=2e-5)


def test_an_edge_without_terms_breaks_the_bias_chain():
    edges = _edges(N)
    g = IncrementalGraph(IncrementalParams(odometry_model="bias_window"))
    g.add_first(0)
    for e in edges:
        g.add_keyframe(e.to_id, e.from_id, e.delta, np.linalg.inv(_marginal_cov(e)),
                       None if e.from_id == 4 else _terms(e))
    plain = _live(edges, "independent")
    # no window closed: all independent edges, as without the model
    assert g.marginal_covariance(N) == pytest.approx(plain.marginal_covariance(N), rel=1e-9)


def test_a_visual_step_keeps_the_bias_through_the_twins_share():
    """The combined edge's bias terms against GTSAM with the two measurements as separate
    factors on the same bias: the end pose's marginal and its covariance with the bias
    (the bias's own marginal: the filter's, see below)."""
    e = _edges(1)[0]
    cov_a = _marginal_cov(e)
    step = (e.delta + np.array([2e-5, -1e-5, 1e-5]), np.diag([1e-6, 2e-6, 4e-6]))
    combined = combine_edges((e.delta, cov_a), step)
    t = combine_bias_terms(cov_a, combined[1], _terms(e))

    def solve(factors: list[gtsam.NonlinearFactor], delta: np.ndarray) -> gtsam.Marginals:
        fg = gtsam.NonlinearFactorGraph()
        fg.add(anchor_factor(0, np.zeros(3)))
        fg.add(bias_prior_factor(0, e.bias_radps, e.bias_var))
        for f in factors:
            fg.add(f)
        values = gtsam.Values()
        values.insert(0, gtsam.Pose2())
        values.insert(1, gtsam.Pose2(*delta))
        values.insert(bias_key(0), np.array([e.bias_radps]))
        return gtsam.Marginals(fg, gtsam.LevenbergMarquardtOptimizer(fg, values).optimize())

    two = solve([bias_edge_factor(e), gtsam.BetweenFactorPose2(0, 1, gtsam.Pose2(*step[0]),
                                                               gtsam.noiseModel.Gaussian.Covariance(step[1]))],
                e.delta)
    one = solve([bias_edge_factor(BiasEdge(0, 1, combined[0], t.cov_given_bias, t.jac_bias, e.bias_radps,
                                           e.bias_var, e.bias_end_radps, e.bias_end_var, e.bias_cov))],
                combined[0])
    keys = gtsam.KeyVector([1, bias_key(0)])
    want = two.jointMarginalCovariance(keys).fullMatrix()
    got = one.jointMarginalCovariance(keys).fullMatrix()
    # the pose's marginal and its covariance with the bias as with the two factors
    assert got[:3, :] == pytest.approx(want[:3, :], rel=1e-3, abs=1e-11)
    # what the step teaches about the bias (the two disagree by the bias's share) is not
    # kept: the bias stays as the filter knew it, never tighter than the two factors make it
    assert got[3, 3] == pytest.approx(e.bias_var)
    assert want[3, 3] < got[3, 3]
    # the bias share is not the wheel + gyro edge's own: the step took part of it
    assert np.linalg.norm(t.jac_bias) < 0.9 * np.linalg.norm(e.jac_bias)


def test_a_rebuild_from_the_whole_graph_keeps_the_windows_and_goes_on():
    """What a relocalisation does (:meth:`IncrementalGraph.attach` rebuilds iSAM2 from the
    whole graph): the closed window stays the per-edge model, the open one's edges stay
    independent and are replaced when it closes, not counted twice."""
    edges = _edges(N + 4)
    g = _live(edges)
    g.attach([], np.zeros(3), [])
    assert g.marginal_covariance(N) == pytest.approx(_per_edge_marginal(edges[:N], N), rel=1e-5, abs=1e-14)
    assert g.stats()["factors"] == 1 + 2 + 4
    more = _edges(6, start=N + 4)
    for e in more:
        g.add_keyframe(e.to_id, e.from_id, e.delta, np.linalg.inv(_marginal_cov(e)), _terms(e))
    # the second window closed: its 9 independent edges out, one window factor and its chain in
    assert g.stats()["factors"] == 1 + 2 + 2 + 0
    assert g.bias_windows == 2
