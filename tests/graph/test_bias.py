"""The pose graph's bias-sharing odometry edges (:mod:`robotd.graph.bias`): the factors'
Jacobians against finite differences, and a chain's marginal covariance against the linear
model they stand for."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from robotd.graph.bias import (
    BiasEdge,
    bias_chain_factor,
    bias_edge_factor,
    bias_factor_graph,
    bias_initial_values,
    bias_key,
    bias_window_factor,
    scale_jacobian,
    scale_key,
    window_chain_edge,
)


def _edge(i: int, delta: tuple[float, float, float], jac: tuple[float, float, float],
          b: float, p: float, b_end: float, p_end: float, c: float) -> BiasEdge:
    cov = np.diag([4e-6, 1e-6, 2e-6])
    cov[0, 2] = cov[2, 0] = 5e-7
    return BiasEdge(i, i + 1, np.array(delta), cov, np.array(jac), b, p, b_end, p_end, c)


def _numeric(factor: gtsam.CustomFactor, values: gtsam.Values, keys: list[int], eps: float = 1e-7) -> list[np.ndarray]:
    out = []
    for key in keys:
        dim = 2 if key >= scale_key(0) else 1 if key >= bias_key(0) else 3
        cols = []
        for n in range(dim):
            d = np.zeros(dim)
            d[n] = eps
            vp, vm = gtsam.Values(values), gtsam.Values(values)
            if dim == 3:
                vp.update(key, values.atPose2(key).retract(d))
                vm.update(key, values.atPose2(key).retract(-d))
            else:
                vp.update(key, values.atVector(key) + d)
                vm.update(key, values.atVector(key) - d)
            cols.append((factor.unwhitenedError(vp) - factor.unwhitenedError(vm)) / (2 * eps))
        out.append(np.column_stack(cols))
    return out


def test_factor_jacobians_match_finite_differences():
    e = _edge(0, (0.3, 0.05, 0.4), (0.01, -0.02, -0.15), 0.003, 1e-8, 0.0031, 1.1e-8, 0.9e-8)
    values = gtsam.Values()
    values.insert(0, gtsam.Pose2(1.0, -2.0, 0.7))
    values.insert(1, gtsam.Pose2(1.25, -1.7, 1.2))
    values.insert(bias_key(0), np.array([0.0045]))
    values.insert(bias_key(1), np.array([0.0021]))
    values.insert(scale_key(3), np.array([0.004, -0.002]))
    for factor, keys in ((bias_edge_factor(e), [0, 1, bias_key(0)]), (bias_chain_factor(e), [bias_key(0), bias_key(1)]),
                         (bias_edge_factor(e, 3), [0, 1, bias_key(0), scale_key(3)])):
        lin = factor.linearize(values)
        # The whitened Jacobian blocks, unwhitened by the model's square-root information.
        r = factor.noiseModel().R()
        a = np.linalg.solve(r, lin.jacobian()[0])
        dims = [2 if k >= scale_key(0) else 1 if k >= bias_key(0) else 3 for k in keys]
        got = np.split(a, np.cumsum(dims)[:-1], axis=1)
        for g, n in zip(got, _numeric(factor, values, keys)):
            assert g == pytest.approx(n, abs=1e-6)


def test_chain_marginal_is_the_linear_model():
    """Two edges from an anchored pose: the marginal covariance of the end pose equals the
    edges' conditional covariances plus the bias errors' share, ``Var(J1 db1 carried + J2
    db2)`` with ``Var db1 = P1``, ``Var db2 = P2``, ``Cov = c`` (what the bench computes for
    long chains), and the bias variables' marginals are the filter's."""
    e1 = _edge(0, (0.05, 0.0, 0.1), (0.0, -0.01, -0.2), 0.003, 4e-5, 0.0031, 3e-5, 3.3e-5)
    e2 = _edge(1, (0.04, 0.01, -0.3), (0.002, -0.008, -0.15), 0.0031, 3e-5, 0.0030, 2e-5, 2.4e-5)
    fg = bias_factor_graph([e1, e2])
    values = bias_initial_values([e1, e2])
    result = gtsam.LevenbergMarquardtOptimizer(fg, values).optimize()
    marg = gtsam.Marginals(fg, result)
    ad2 = gtsam.Pose2(*e2.delta).inverse().AdjointMap()  # carries a tangent error at x1 to x2
    u1, u2 = ad2 @ e1.jac_bias, e2.jac_bias
    expect = (ad2 @ e1.cov_given_bias @ ad2.T + e2.cov_given_bias
              + e1.bias_var * np.outer(u1, u1) + e2.bias_var * np.outer(u2, u2)
              + e1.bias_cov * (np.outer(u1, u2) + np.outer(u2, u1)))
    got = marg.marginalCovariance(2)
    assert got == pytest.approx(expect, rel=1e-4, abs=1e-14)
    assert marg.marginalCovariance(bias_key(0))[0, 0] == pytest.approx(e1.bias_var, rel=1e-6)
    assert marg.marginalCovariance(bias_key(1))[0, 0] == pytest.approx(e1.bias_end_var, rel=1e-6)
    # Without the bias's share the chain is the independent edges' (what it must exceed).
    indep = ad2 @ e1.cov_given_bias @ ad2.T + e2.cov_given_bias
    assert got[2, 2] > 1.5 * indep[2, 2]


def test_chain_marginal_with_a_shared_scale():
    """The same chain with one scale variable shared by both edges: the end pose's
    marginal gains ``U diag(sigma^2) U^T``, ``U`` the edges' scale Jacobians carried to it."""
    e1 = _edge(0, (0.05, 0.0, 0.1), (0.0, -0.01, -0.2), 0.003, 4e-5, 0.0031, 3e-5, 3.3e-5)
    e2 = _edge(1, (0.04, 0.01, -0.3), (0.002, -0.008, -0.15), 0.0031, 3e-5, 0.0030, 2e-5, 2.4e-5)
    sig = (0.003, 0.002)
    fg_plain = bias_factor_graph([e1, e2])
    fg = bias_factor_graph([e1, e2], scale_sigmas=sig)
    plain = gtsam.Marginals(fg_plain, bias_initial_values([e1, e2])).marginalCovariance(2)
    got = gtsam.Marginals(fg, bias_initial_values([e1, e2], scales=True)).marginalCovariance(2)
    ad2 = gtsam.Pose2(*e2.delta).inverse().AdjointMap()
    u = ad2 @ scale_jacobian(e1.delta) + scale_jacobian(e2.delta)
    assert got == pytest.approx(plain + u @ np.diag(np.square(sig)) @ u.T, rel=1e-4, abs=1e-14)


def _chain3() -> list[BiasEdge]:
    return [_edge(0, (0.05, 0.0, 0.1), (0.0, -0.01, -0.2), 0.003, 4e-5, 0.0031, 3e-5, 3.3e-5),
            _edge(1, (0.04, 0.01, -0.3), (0.002, -0.008, -0.15), 0.0031, 3e-5, 0.0030, 2e-5, 2.4e-5),
            _edge(2, (0.06, -0.01, 0.2), (0.001, 0.01, -0.25), 0.0030, 2e-5, 0.0029, 2.5e-5, 1.9e-5)]


def test_window_factor_jacobians_match_finite_differences():
    edges = _chain3()
    values = gtsam.Values()
    for k, p in enumerate([(1.0, -2.0, 0.7), (1.04, -1.96, 0.81), (1.07, -1.93, 0.5), (1.13, -1.9, 0.72)]):
        values.insert(k, gtsam.Pose2(*p))
    values.insert(bias_key(0), np.array([0.0045]))
    factor = bias_window_factor(edges)
    keys = [0, 1, 2, 3, bias_key(0)]
    a = np.linalg.solve(factor.noiseModel().R(), factor.linearize(values).jacobian()[0])
    got = np.split(a, np.cumsum([3, 3, 3, 3, 1])[:-1], axis=1)
    for g, n in zip(got, _numeric(factor, values, keys)):
        assert g == pytest.approx(n, abs=1e-6)


def test_one_window_gives_the_per_edge_factors_marginals():
    """A window factor over the whole chain is the per-edge model with the biases inside
    the window marginalised: the end pose's marginal covariance is the same."""
    edges = _chain3()
    per_edge = bias_factor_graph(edges)
    values = bias_initial_values(edges)
    a = gtsam.Marginals(per_edge, gtsam.LevenbergMarquardtOptimizer(per_edge, values).optimize())
    win = gtsam.NonlinearFactorGraph()
    win.add(per_edge.at(0))  # the anchor
    win.add(per_edge.at(1))  # the first bias's prior
    win.add(bias_window_factor(edges))
    wv = gtsam.Values()
    for k in range(4):
        wv.insert(k, values.atPose2(k))
    wv.insert(bias_key(0), values.atVector(bias_key(0)))
    b = gtsam.Marginals(win, gtsam.LevenbergMarquardtOptimizer(win, wv).optimize())
    assert b.marginalCovariance(3) == pytest.approx(a.marginalCovariance(3), rel=1e-6, abs=1e-14)
    assert b.marginalCovariance(bias_key(0)) == pytest.approx(a.marginalCovariance(bias_key(0)), rel=1e-6)
    # The chain over windows: the step's coefficient is the product of the edges'.
    step = window_chain_edge(edges)
    alpha = np.prod([e.chain_step()[0] for e in edges])
    assert step.chain_step()[0] == pytest.approx(alpha)
    assert (step.from_id, step.to_id) == (0, 3)
