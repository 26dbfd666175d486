"""Two independent measurements of one pose-graph edge combined into one
(:func:`robotd.odometry.increments.combine_edges`), against GTSAM given both as factors."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from robotd.base.geometry import between_error_covariance
from robotd.odometry.increments import combine_edges


def _random_cov(rng: np.random.Generator, sigma_m: float, sigma_rad: float) -> np.ndarray:
    a = rng.normal(size=(3, 3)) * np.array([sigma_m, sigma_m, sigma_rad])[:, None]
    return a @ a.T + np.diag([sigma_m, sigma_m, sigma_rad]) ** 2 * 0.1


@pytest.mark.parametrize("seed", range(5))
def test_combined_edge_is_what_gtsam_makes_of_the_two_factors(seed: int) -> None:
    """A wheel-like edge (mm, mrad) and a visual one that differs from it by about its own
    uncertainty: the combination's mean is GTSAM's optimum of the two BetweenFactors to
    within 0.1 % of a standard deviation, its
    covariance GTSAM's marginal to 1 %."""
    rng = np.random.default_rng(seed)
    truth = np.array([0.05, 0.01, 0.2]) * rng.normal(size=3)
    cov_a = between_error_covariance(truth, _random_cov(rng, 2e-3, 4e-3))
    cov_b = between_error_covariance(truth, _random_cov(rng, 5e-4, 2e-3))
    a = truth + rng.multivariate_normal(np.zeros(3), cov_a)
    b = truth + rng.multivariate_normal(np.zeros(3), cov_b)
    delta, cov = combine_edges((a, cov_a), (b, cov_b))

    g = gtsam.NonlinearFactorGraph()
    g.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
    for z, c in ((a, cov_a), (b, cov_b)):
        g.add(gtsam.BetweenFactorPose2(0, 1, gtsam.Pose2(*z), gtsam.noiseModel.Gaussian.Covariance(c)))
    init = gtsam.Values()
    init.insert(0, gtsam.Pose2())
    init.insert(1, gtsam.Pose2(*a))
    result = gtsam.LevenbergMarquardtOptimizer(g, init).optimize()
    p = result.atPose2(1)
    marginal = gtsam.Marginals(g, result).marginalCovariance(1)
    off = gtsam.Pose2.Logmap(p.between(gtsam.Pose2(*delta)))
    assert float(off @ np.linalg.solve(marginal, off)) < 0.001 ** 2
    assert np.linalg.norm(delta - a) > 1e-4  # not simply one of the two
    assert cov == pytest.approx(marginal, rel=0.01, abs=1e-12)
    # Tighter than either alone.
    assert np.all(np.linalg.eigvalsh(cov_a - cov) > -1e-15)
    assert np.all(np.linalg.eigvalsh(cov_b - cov) > -1e-15)


def test_se2_exp_and_log_are_gtsams() -> None:
    from robotd.base.geometry import se2_exp, se2_log

    rng = np.random.default_rng(1)
    for xi in [np.array([0.3, -0.2, 1e-12]), *rng.normal(size=(20, 3)) * [1.0, 1.0, 1.5]]:
        p = gtsam.Pose2.Expmap(xi)
        assert se2_exp(xi) == pytest.approx([p.x(), p.y(), p.theta()], abs=1e-12)
        assert se2_log(se2_exp(xi)) == pytest.approx(gtsam.Pose2.Logmap(p), abs=1e-10)


def test_error_and_jacobian_on_floats_is_the_geometry_of_robotd_base() -> None:
    """The float arithmetic of the edge error is robotd.base.geometry's, bit for bit."""
    from robotd.base.geometry import between, compose, se2_exp, se2_log
    from robotd.odometry.increments import _error_and_jacobian

    rng = np.random.default_rng(5)
    for i in range(60):
        z = rng.normal(size=3) * [0.3, 0.3, 3.0]
        x = z + rng.normal(size=3) * 0.02
        eps = 1e-7 if i < 50 else 1e-6  # the default's perturbations are constants; another eps's made per call
        r, jac = _error_and_jacobian(z, x) if i < 50 else _error_and_jacobian(z, x, eps)
        assert np.array_equal(r, se2_log(between(z, x)))
        for k in range(3):
            d = np.zeros(3)
            d[k] = eps
            col = (se2_log(between(z, compose(x, se2_exp(d)))) - se2_log(between(z, compose(x, se2_exp(-d))))) / (2 * eps)
            assert np.array_equal(jac[:, k], col)
