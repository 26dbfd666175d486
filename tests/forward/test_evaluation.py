"""Precision, recall and recall at 100 % precision of loop decisions."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.forward.evaluation import positives, score_decisions


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
