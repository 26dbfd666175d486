"""Scoring loop decisions on an image sequence against a ground-truth matrix.

Per image t (a query), a method declares at most one loop with a past image j. With
``truth (N, N) bool`` symmetric (True where two images show the same place):

- a declared loop is a true positive when ``truth[t, j]``, else a false positive;
- image t is a positive when it has a true match among the hypotheses 0 .. t - p (the last
  p images are never hypotheses, so they cannot be asked for);
- precision = TP / declared, recall = TP / positives.

Recall at 100 % precision: each declared loop also has a confidence (the posterior, a vote
ratio, an inlier count); sweeping a threshold on it from the top, the largest recall
reached before the first false positive.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["Scores", "positives", "score_decisions"]


@dataclass(frozen=True)
class Scores:
    """Precision and recall of one method on one sequence.

    ``precision`` is 1.0 when nothing was declared (no false positive); ``recall_at_full_precision``
    and the confidence ``threshold_at_full_precision`` reaching it (None when the most
    confident declaration is already wrong, or none was made)."""

    declared: int
    true_positives: int
    false_positives: int
    positives: int
    precision: float
    recall: float
    recall_at_full_precision: float
    threshold_at_full_precision: float | None

    def as_dict(self) -> dict:
        return asdict(self)


def positives(truth: np.ndarray, recent_excluded: int) -> np.ndarray:
    """``(N,) bool``: images with a true match among their hypotheses 0 .. t - p."""
    t = np.asarray(truth, bool)
    n = len(t)
    eligible = np.arange(n)[None, :] <= (np.arange(n)[:, None] - recent_excluded)
    return (t & eligible).any(axis=1)


def score_decisions(candidates: np.ndarray, confidences: np.ndarray, declared: np.ndarray,
                    truth: np.ndarray, recent_excluded: int) -> Scores:
    """Score one method's decisions.

    ``candidates (N,) int``: the past image each query points at (-1: none);
    ``confidences (N,) float``: the confidence of that candidate; ``declared (N,) bool``:
    whether the method declared the loop (at its own operating point);
    ``truth (N, N) bool``: symmetric same-place matrix.
    """
    cand = np.asarray(candidates, np.int64)
    conf = np.asarray(confidences, np.float64)
    decl = np.asarray(declared, bool) & (cand >= 0)
    truth = np.asarray(truth, bool)
    n = len(truth)
    if not (len(cand) == len(conf) == len(decl) == n):
        raise ValueError(f"decisions for {len(cand)} images, ground truth for {n}")
    pos = positives(truth, recent_excluded)
    q = np.flatnonzero(decl)
    correct = truth[q, cand[q]]
    tp = int(correct.sum())
    fp = int(len(q) - tp)
    n_pos = int(pos.sum())
    # Sweep the confidence from the top; ties are taken together.
    order = np.argsort(-conf[q], kind="stable")
    c_sorted, ok_sorted = conf[q][order], correct[order]
    best_recall, best_thr = 0.0, None
    i = 0
    tp_run = 0
    while i < len(order):
        j = i
        while j < len(order) and c_sorted[j] == c_sorted[i]:
            j += 1
        if not ok_sorted[i:j].all():
            break
        tp_run += j - i
        best_recall, best_thr = tp_run / n_pos if n_pos else 0.0, float(c_sorted[i])
        i = j
    return Scores(
        declared=int(len(q)), true_positives=tp, false_positives=fp, positives=n_pos,
        precision=tp / len(q) if len(q) else 1.0, recall=tp / n_pos if n_pos else 0.0,
        recall_at_full_precision=best_recall, threshold_at_full_precision=best_thr)
