"""Trajectory metrics: APE anchored at the origin or aligned by a rigid fit, RPE per step."""

import math

import numpy as np
import pytest

from robotd.base.geometry import compose
from robotd.evaluation.metrics import (
    Alignment,
    align_origin,
    ape_translation,
    ape_translation_rmse,
    odometry_errors,
    rpe_per_step,
)


def _route(n: int = 50) -> np.ndarray:
    """A curving path: ``(n, 3)`` poses starting away from the origin."""
    t = np.linspace(0.0, 3.0, n)
    return np.column_stack([2.0 + 3.0 * np.cos(t), -1.0 + 2.0 * np.sin(t), t + math.pi / 2])


def test_a_moved_copy_has_no_error_either_way():
    truth = _route()
    moved = compose(np.array([5.0, -3.0, 0.7]), truth)  # the same path in another frame
    assert ape_translation_rmse(truth, moved, Alignment.ALIGNED) == pytest.approx(0.0, abs=1e-9)
    assert ape_translation_rmse(truth, moved, Alignment.ORIGIN) == pytest.approx(0.0, abs=1e-9)
    back = align_origin(truth[0], moved)
    assert np.allclose(back[:, :2], truth[:, :2])
    assert np.allclose(np.cos(back[:, 2] - truth[:, 2]), 1.0)


def test_an_offset_is_fitted_away_only_when_aligned():
    truth = _route()
    shifted = truth + np.array([0.0, 0.1, 0.0])
    # Anchoring at the first pose keeps the shape: a pure shift disappears as well.
    assert ape_translation_rmse(truth, shifted, Alignment.ORIGIN) == pytest.approx(0.0, abs=1e-9)
    # A wrong heading at the first pose alone swings the whole trajectory when anchored
    # there (about 0.05 rad times the distance from the start); the rigid fit of the
    # positions ignores it.
    turned = truth.copy()
    turned[0, 2] += 0.05
    err = ape_translation(truth, turned, Alignment.ORIGIN)
    far = np.hypot(*(truth[:, :2] - truth[0, :2]).T)
    assert err[0] == pytest.approx(0.0, abs=1e-12)
    assert np.allclose(err, 2 * far * math.sin(0.025), atol=1e-9)
    assert ape_translation_rmse(truth, turned, Alignment.ALIGNED) == pytest.approx(0.0, abs=1e-9)


def test_drift_is_measured_in_full_when_anchored():
    truth = np.column_stack([np.linspace(0, 10, 11), np.zeros(11), np.zeros(11)])
    est = truth.copy()
    est[:, 1] = np.linspace(0, 1, 11)  # 0.1 m of lateral drift per metre
    e = odometry_errors(truth, est)
    assert e.distance_m == pytest.approx(10.0)
    assert e.end_position_error_m == pytest.approx(1.0)
    assert e.ape_origin_max_m == pytest.approx(1.0)
    assert e.ape_origin_rmse_m == pytest.approx(math.sqrt(np.mean(np.linspace(0, 1, 11) ** 2)))
    assert e.end_drift_per_100m == pytest.approx(10.0)
    # Aligned, the straight drifting line is rotated onto the truth: less error.
    assert ape_translation_rmse(truth, est, Alignment.ALIGNED) < 0.5 * e.ape_origin_rmse_m


def test_rpe_per_step():
    truth = np.column_stack([np.arange(5.0), np.zeros(5), np.zeros(5)])
    est = truth.copy()
    est[:, 0] *= 1.1  # every step 10 cm too long
    est[4, 2] = 0.02  # the last step turns 0.02 rad
    t, r = rpe_per_step(truth, est)
    assert t == pytest.approx(0.1)
    assert r == pytest.approx(math.sqrt(0.02**2 / 4))


def test_mismatched_shapes_are_refused():
    with pytest.raises(ValueError):
        ape_translation(_route(5), _route(6), Alignment.ORIGIN)
    with pytest.raises(ValueError):
        rpe_per_step(_route(1), _route(1))
