"""Precision, recall and recall at 100 % precision of loop decisions."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.forward.evaluation import positives, pr_curve, score_decisions


def _truth() -> np.ndarray:
    t = np.zeros((8, 8), bool)
    for i, j in [(4, 3), (5, 0), (6, 1), (7, 2)]:
        t[i, j] = t[j, i] = True
    return t


def test_positives_ignore_the_recent_images():
    # Image 4's only match (3) is within p = 2 of it: not a positive (nor is 3, whose
    # match comes later).
    assert list(np.flatnonzero(positives(_truth(), 2))) == [5, 6, 7]
    # With p = 6, image 7's hypotheses are 0 and 1 only.
    assert list(np.flatnonzero(positives(_truth(), 6))) == []
    assert list(np.flatnonzero(positives(_truth(), 5))) == [5, 6, 7]
    assert list(np.flatnonzero(positives(_truth(), 1))) == [4, 5, 6, 7]


def test_scores_by_hand():
    cand = np.array([-1, -1, -1, -1, -1, 0, 3, 2])
    conf = np.array([0, 0, 0, 0, 0, 0.9, 0.95, 0.85])
    decl = np.array([0, 0, 0, 0, 0, 1, 1, 1], bool)
    s = score_decisions(cand, conf, decl, _truth(), 2)
    assert (s.declared, s.true_positives, s.false_positives, s.positives) == (3, 2, 1, 3)
    assert s.precision == pytest.approx(2 / 3) and s.recall == pytest.approx(2 / 3)
    # The most confident (image 6 -> 3) is wrong: no threshold gives 100 % precision.
    assert s.recall_at_full_precision == 0.0 and s.threshold_at_full_precision is None
    conf2 = np.array([0, 0, 0, 0, 0, 0.9, 0.5, 0.85])
    s2 = score_decisions(cand, conf2, decl, _truth(), 2)
    assert s2.recall_at_full_precision == pytest.approx(2 / 3)
    assert s2.threshold_at_full_precision == pytest.approx(0.85)


def test_ties_with_a_false_positive_are_not_split():
    cand = np.array([-1, -1, -1, -1, -1, 0, 3, 2])
    conf = np.array([0, 0, 0, 0, 0, 0.9, 0.9, 0.9])
    s = score_decisions(cand, conf, np.ones(8, bool), _truth(), 2)
    assert s.recall_at_full_precision == 0.0


def test_nothing_declared_is_full_precision_and_no_recall():
    s = score_decisions(np.full(8, -1), np.zeros(8), np.zeros(8, bool), _truth(), 2)
    assert (s.precision, s.recall, s.declared) == (1.0, 0.0, 0)
    with pytest.raises(ValueError):
        score_decisions(np.full(7, -1), np.zeros(7), np.zeros(7, bool), _truth(), 2)


def test_a_frame_tolerance_accepts_a_neighbour_of_a_true_match():
    truth = np.zeros((20, 20), bool)
    truth[15, 3] = truth[3, 15] = True
    cand = np.full(20, -1)
    cand[15] = 5  # two images off the true match
    conf = np.where(cand >= 0, 1.0, 0.0)
    assert score_decisions(cand, conf, cand >= 0, truth, 10).true_positives == 0
    assert score_decisions(cand, conf, cand >= 0, truth, 10, tolerance=1).true_positives == 0
    s = score_decisions(cand, conf, cand >= 0, truth, 10, tolerance=2)
    assert (s.true_positives, s.positives, s.recall_at_full_precision) == (1, 1, 1.0)


def test_the_pr_curve_sweeps_the_confidence_from_the_top():
    truth = np.zeros((30, 30), bool)
    for q, j in ((20, 1), (21, 2), (22, 3), (23, 4)):
        truth[q, j] = truth[j, q] = True
    cand = np.full(30, -1)
    conf = np.zeros(30)
    cand[[20, 21, 22, 25]] = [1, 2, 9, 7]   # right, right, wrong, wrong
    conf[[20, 21, 22, 25]] = [0.9, 0.8, 0.7, 0.6]
    c = pr_curve(cand, conf, cand >= 0, truth, 10)
    assert c["threshold"] == [0.9, 0.8, 0.7, 0.6]
    assert c["precision"] == [1.0, 1.0, 2 / 3, 0.5]
    assert c["recall"] == [0.25, 0.5, 0.5, 0.5]
