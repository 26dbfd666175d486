"""The P(loop | score) curve: monotone, calibrated, and its threshold where it should be."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from calibration.loop_curve import _pava_blocks, fit_loop_curve, pick_threshold, precision_recall


def test_pava_blocks_by_hand():
    # Loop rates 0, 3/4, 1/4, 1: the second and third bins violate and pool into one block
    # of 4 loops in 8 pairs (posterior mean 5/10); the last stays alone.
    assert _pava_blocks(np.array([0.0, 3.0, 1.0, 4.0]), np.array([1.0, 4.0, 4.0, 4.0])).tolist() == [1, 2, 1]
    # Equal estimates are pooled (same fit, pooled evidence).
    assert _pava_blocks(np.array([5.0, 5.0]), np.array([5.0, 5.0])).tolist() == [2]
    # Bins that are all loops pool whatever their sizes (their posterior means 140/141 <
    # 141/142 < 142/143 differ, their rates do not), and not with the bin below that has a
    # miss (299 in 300: posterior mean 0.9934 < 421/422).
    assert _pava_blocks(np.array([299.0, 139.0, 140.0, 141.0]),
                        np.array([300.0, 139.0, 140.0, 141.0])).tolist() == [1, 3]
    # ... unless the pure block is so small that its posterior mean (121/122 = 0.9918) is
    # below its predecessor's: then the curve's monotonicity pools them.
    assert _pava_blocks(np.array([299.0, 39.0, 40.0, 41.0]),
                        np.array([300.0, 39.0, 40.0, 41.0])).tolist() == [4]
    # A tiny block whose posterior mean would fall below its predecessor's is pooled.
    assert _pava_blocks(np.array([1.0, 0.0]), np.array([100.0, 1.0])).tolist() == [2]


def test_pure_top_bins_of_unequal_sizes_give_a_threshold():
    # Non-loops below 100, loops from 100 on but one miss at 150, and above it 750 loops
    # at 150 distinct scores (five each, so the equal-count bins differ in size).
    s = np.concatenate([np.arange(0, 100.0), np.arange(100, 150.0), [150.0], np.repeat(np.arange(151, 301.0), 5)])
    y = np.concatenate([np.zeros(100, bool), np.ones(50, bool), [False], np.ones(750, bool)])
    c = fit_loop_curve(s, y, bins=40, min_per_bin=20)
    pure = np.arange(len(c.count)) > np.flatnonzero(c.positives < c.count)[-1]
    assert len(np.unique(c.count[pure])) > 1  # the pure bins differ in size
    n = c.count[pure].sum()
    assert n >= 740
    # One block: every pure bin carries the evidence of all of them (0.05 ** (1 / 741) = 0.996).
    assert np.allclose(c.lower[pure], 0.05 ** (1 / (n + 1)))
    assert pick_threshold(c, 0.99) == c.score_lo[pure][0] > 150.0


def test_pooled_bins_count_all_their_evidence():
    # 2000 pairs, all loops above 50, 1 in 2 below: ten bins of 100 loops each, every one of
    # which alone only shows P >= 0.97; pooled they show P >= 0.05 ** (1 / 1001) = 0.997.
    s = np.arange(2000, dtype=float) / 20.0
    y = np.where(s >= 50, True, np.arange(2000) % 2 == 0)
    c = fit_loop_curve(s, y, bins=20, min_per_bin=100)
    top = c.score_lo >= 50
    assert top.sum() == 10
    assert np.allclose(c.probability[top], 1001 / 1002)
    assert np.allclose(c.lower[top], 0.05 ** (1 / 1001))
    assert pick_threshold(c, 0.99) == 50.0
    # Half the evidence is not enough for a 0.995 lower bound (0.05 ** (1 / 501) = 0.994).
    half = fit_loop_curve(s[1000:1500], y[1000:1500], bins=5, min_per_bin=100)
    assert half.lower[-1] == pytest.approx(0.05 ** (1 / 501))
    assert pick_threshold(half, 0.995) is None


def test_curve_recovers_a_step_and_the_threshold():
    rng = np.random.default_rng(0)
    # Below 20 a loop one time in ten; from 20 on always a loop.
    s = rng.uniform(0, 40, 20000)
    y = np.where(s >= 20, True, rng.random(len(s)) < 0.1)
    curve = fit_loop_curve(s, y, bins=40)
    assert np.all(np.diff(curve.probability) >= 0) and np.all(np.diff(curve.lower) >= 0)
    assert np.all(curve.lower <= curve.probability)
    assert curve.at(5.0) == pytest.approx(0.1, abs=0.03)
    assert curve.at(35.0) > 0.99
    t = pick_threshold(curve, 0.99)
    assert t is not None and 19.0 <= t <= 21.5
    pr = precision_recall(s, y, t)
    assert pr.precision > 0.995 and pr.recall > 0.7


def test_weights_count_a_subsample_with_its_true_share():
    rng = np.random.default_rng(2)
    # 1000 high-scoring pairs: 990 loops and 10 distant look-alikes; keep 1 in 10 of the
    # distant ones with weight 10: the estimate must still be about 0.99, not 0.999.
    s = np.concatenate([rng.uniform(30, 40, 990), rng.uniform(30, 40, 10)])
    y = np.concatenate([np.ones(990, bool), np.zeros(10, bool)])
    keep = np.concatenate([np.ones(990, bool), np.arange(10) % 10 == 0])
    w = np.where(y, 1.0, 10.0)[keep]
    c = fit_loop_curve(s[keep], y[keep], bins=1, min_per_bin=1, weights=w)
    assert c.probability[0] == pytest.approx(991 / 1002, abs=1e-6)  # Beta(1,1) posterior mean
    unweighted = fit_loop_curve(s[keep], y[keep], bins=1, min_per_bin=1)
    assert unweighted.probability[0] > 0.997


def test_no_threshold_when_never_certain():
    rng = np.random.default_rng(1)
    s = rng.uniform(0, 10, 5000)
    y = rng.random(len(s)) < 0.5
    assert pick_threshold(fit_loop_curve(s, y), 0.99) is None


def test_precision_recall_counts():
    pr = precision_recall(np.array([1, 5, 7, 9.0]), np.array([False, True, False, True]), 6.0)
    assert (pr.true_positives, pr.false_positives, pr.false_negatives) == (1, 1, 1)
    assert pr.precision == 0.5 and pr.recall == 0.5


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.lists(st.tuples(st.floats(0, 100), st.booleans()), min_size=1, max_size=400))
def test_curve_is_always_monotone_and_a_probability(pairs):
    s = np.array([p[0] for p in pairs])
    y = np.array([p[1] for p in pairs])
    c = fit_loop_curve(s, y, bins=10, min_per_bin=5)
    assert np.all(np.diff(c.probability) >= -1e-12)
    assert np.all((c.probability > 0) & (c.probability < 1))
    assert c.count.sum() == len(s) and c.positives.sum() == y.sum()
