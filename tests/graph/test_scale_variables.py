"""The base's scale errors as a variable of the daemon's graph (``IncrementalParams.
odometry_model = "bias_scale_window"``): the windows, the fold spans and the combine with
a visual step keep the per-edge model with one scale variable, and loops between places
along the route estimate a wheel scale error the edges carry."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from robotd.base.geometry import between, compose
from robotd.graph.bias import (
    BiasEdge,
    bias_edge,
    bias_edge_factor,
    bias_key,
    bias_prior_factor,
    scale_key,
    scale_prior_factor,
)
from robotd.graph.factors import anchor_factor
from robotd.graph.incremental import IncrementalGraph, IncrementalParams
from robotd.odometry.history import EdgeBiasTerms
from robotd.odometry.increments import combine_bias_terms, combine_edges
from tests.graph.test_bias_windows import _edges as bias_window_edges
from tests.graph.test_bias_windows import _live as bias_window_live
from tests.graph.test_bias_windows import _marginal_cov, _terms
from tests.graph.test_bias_windows import _per_edge_marginal as bias_window_marginal

N = 10  # one window
SIGMAS = (0.003, 0.0005)


def _edges(n: int, start: int = 0) -> list[BiasEdge]:
    """tests/graph/test_bias_windows.py's turning chain with tight covariances and 15 cm
    edges, so that the scale's share of the chain is large."""
    return bias_window_edges(n, start, var=1e-8, step_m=0.15)


def _per_edge_marginal(edges: list[BiasEdge], key: int) -> np.ndarray:
    return bias_window_marginal(edges, key, SIGMAS)


def _live(edges: list[BiasEdge], model: str = "bias_scale_window") -> IncrementalGraph:
    return bias_window_live(edges, model, scale_sigmas=SIGMAS)


def test_a_closed_window_with_the_scale_is_the_per_edge_model():
    edges = _edges(N)
    want = _per_edge_marginal(edges, N)
    g = _live(edges)
    assert g.marginal_covariance(N) == pytest.approx(want, rel=1e-5, abs=1e-16)
    assert g.scale_estimate() == pytest.approx([0.0, 0.0], abs=1e-12)
    # without the scale variable the chain is far tighter along the track
    plain = _live(edges, "bias_window").marginal_covariance(N)
    assert plain[0, 0] < 0.5 * want[0, 0]
    assert _live(edges, "bias_window").scale_estimate() is None


def test_a_fold_keeps_the_scale_model():
    edges = _edges(2 * N + 5)
    g = _live(edges)
    before = {k: g.marginal_covariance(k) for k in (N, 2 * N)}
    g.resolve()
    assert g.stats()["folded"] > 0
    # the first span (the anchor's 10 edges) is the per-edge model with the scale
    assert g.marginal_covariance(N) == pytest.approx(_per_edge_marginal(edges[:N], N), rel=1e-4, abs=1e-16)
    assert g.marginal_covariance(2 * N) == pytest.approx(before[2 * N], rel=0.02)
    # the spans share the one scale variable: dropping it would halve the along-track variance
    nos = _live(edges, "bias_window")
    nos.resolve()
    assert nos.marginal_covariance(2 * N)[0, 0] < 0.5 * g.marginal_covariance(2 * N)[0, 0]
    more = _edges(12, start=2 * N + 5)
    for e in more:
        g.add_keyframe(e.to_id, e.from_id, e.delta, np.linalg.inv(_marginal_cov(e)), _terms(e))
    assert np.isfinite(g.marginal_covariance(more[-1].to_id)).all()


def _square_laps(model: str, scale: float) -> tuple[IncrementalGraph, float, list[float]]:
    """Two laps of a 3 m square at 15 cm keyframes whose edges are ``scale`` too long, with
    loops on the second lap to the first lap's keyframes 1.5 m behind (the truth); returns
    the graph after a full solve, the largest position error (m) and the loops' chi-square."""
    g = IncrementalGraph(IncrementalParams(odometry_model=model, scale_sigmas=(0.003, 1e-4)))
    g.add_first(0)
    cov = np.diag([0.2e-3 ** 2, 0.2e-3 ** 2, 1e-4 ** 2])
    terms = EdgeBiasTerms(cov, np.zeros(3), 0.0, 1e-10, 0.0, 1e-10, 1e-10)
    truth = [np.zeros(3)]
    chi2 = []
    info = np.eye(3) * 1e6
    for lap in range(2):
        for _side in range(4):
            for k in range(20):
                d = np.array([0.15, 0.0, np.pi / 2 if k == 19 else 0.0])
                truth.append(compose(truth[-1], d))
                meas = d * [1 + scale, 1 + scale, 1]
                kid = len(truth) - 1
                g.add_keyframe(kid, kid - 1, meas, np.linalg.inv(cov), terms)
                if lap == 1 and k % 5 == 0:
                    old = kid - 70
                    loop = between(truth[old], truth[kid])
                    chi2.append(g.loop_chi2(old, kid, loop, info, joint=True))
                    g.add_loop(old, kid, loop, info)
    g.resolve()
    ids, est = g.estimate()
    err = float(np.abs(est[:, :2] - np.array(truth)[ids][:, :2]).max())
    return g, err, chi2


def test_loops_along_the_route_estimate_a_wheel_scale_error():
    g, err, chi2 = _square_laps("bias_scale_window", 0.005)
    s = g.scale_estimate()
    assert s is not None
    assert s[0] == pytest.approx(0.005, rel=0.05)
    assert abs(s[1]) < 1e-5
    assert err < 1e-3
    assert max(chi2) < 16.27
    # the same drive without the scale variable: the edges keep their error
    _, err_plain, chi2_plain = _square_laps("bias_window", 0.005)
    assert err_plain > 0.01
    assert max(chi2_plain) > 16.27


def test_a_visual_step_passes_on_its_share_of_the_scale():
    """The combined edge's scale Jacobian (``scale_gain`` times the twin's) and covariance
    given the scale against GTSAM with the twin's edge and the step as separate factors
    sharing the scale variable (the combination weighs the twin by its marginal over the
    scale, as the visual odometry stage does with the scale variable on)."""
    e = _edges(1)[0]  # covariances above the edges' floor (robotd.odometry.increments.floor_covariance)
    e = BiasEdge(0, 1, e.delta, np.diag([3e-6, 1e-6, 2e-6]), e.jac_bias * 10, e.bias_radps, 4e-5, e.bias_radps,
                 3.9e-5, 3.95e-5)
    sigmas = (0.01, 0.005)
    js = e.scale_jac()
    share = js @ np.diag(np.square(sigmas)) @ js.T
    cov_a = _marginal_cov(e) + share  # the twin's edge, marginal over the bias and the scale
    step = (e.delta + np.array([2e-5, -1e-5, 1e-5]), np.diag([1e-6, 2e-6, 4e-6]))
    combined = combine_edges((e.delta, cov_a), step)
    t = combine_bias_terms(cov_a, combined[1], _terms(e), share)
    assert t.scale_gain is not None
    one_edge = bias_edge(0, 1, combined[0], tuple(t))

    def solve(factors: list[gtsam.NonlinearFactor], delta: np.ndarray) -> gtsam.Marginals:
        fg = gtsam.NonlinearFactorGraph()
        fg.add(anchor_factor(0, np.zeros(3)))
        fg.add(bias_prior_factor(0, e.bias_radps, e.bias_var))
        fg.add(scale_prior_factor(0, sigmas))
        for f in factors:
            fg.add(f)
        values = gtsam.Values()
        values.insert(0, gtsam.Pose2())
        values.insert(1, gtsam.Pose2(*delta))
        values.insert(bias_key(0), np.array([e.bias_radps]))
        values.insert(scale_key(0), np.zeros(2))
        return gtsam.Marginals(fg, gtsam.LevenbergMarquardtOptimizer(fg, values).optimize())

    two = solve([bias_edge_factor(e, 0), gtsam.BetweenFactorPose2(0, 1, gtsam.Pose2(*step[0]),
                                                                  gtsam.noiseModel.Gaussian.Covariance(step[1]))],
                e.delta)
    one = solve([bias_edge_factor(one_edge, 0)], combined[0])
    keys = gtsam.KeyVector([1, scale_key(0)])
    want = two.jointMarginalCovariance(keys).fullMatrix()
    got = one.jointMarginalCovariance(keys).fullMatrix()
    # the pose's marginal and its covariance with the scale as with the two factors
    assert got[:3, :] == pytest.approx(want[:3, :], rel=2e-3, abs=1e-13)
    # the step took most of the along-track share: the combined edge's Jacobian is not the twin's
    assert abs(one_edge.scale_jac()[0, 0]) < 0.5 * abs(e.scale_jac()[0, 0])
