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

Frame tolerance (``tolerance = K``, as the literature scores Lip6, NewCollege and
CityCentre): a declared loop (t, j) is right when image t truly matches any of j - K ..
j + K. :func:`pr_curve` gives precision and recall over the whole sweep of the
confidence threshold.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["Scores", "positives", "pr_curve", "score_decisions", "tolerant_truth"]


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

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


def positives(truth: np.ndarray, recent_excluded: int) -> np.ndarray:
    """``(N,) bool``: images with a true match among their hypotheses 0 .. t - p."""
    t = np.asarray(truth, bool)
    n = len(t)
    eligible = np.arange(n)[None, :] <= (np.arange(n)[:, None] - recent_excluded)
    return np.any(t & eligible, axis=1)


def tolerant_truth(truth: np.ndarray, tolerance: int) -> np.ndarray:
    """``truth`` with each true (t, j) widened to (t, j - K .. j + K), for judging declared
    loops with a frame tolerance ``K`` (the positives are counted on the plain truth)."""
    t = np.asarray(truth, bool)
    if tolerance < 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    out = t.copy()
    for k in range(1, tolerance + 1):
        out[:, k:] |= t[:, :-k]
        out[:, :-k] |= t[:, k:]
    return out


def pr_curve(candidates: np.ndarray, confidences: np.ndarray, declared: np.ndarray,
             truth: np.ndarray, recent_excluded: int, tolerance: int = 0) -> dict[str, list[float]]:
    """Precision and recall as the confidence threshold sweeps down over the declared loops
    (ties together): ``{"threshold", "precision", "recall"}``, one entry per distinct
    confidence, highest first."""
    cand = np.asarray(candidates, np.int64)
    conf = np.asarray(confidences, np.float64)
    decl = np.asarray(declared, bool) & (cand >= 0)
    judge = tolerant_truth(truth, tolerance)
    n_pos = int(positives(truth, recent_excluded).sum())
    q = np.flatnonzero(decl)
    correct = judge[q, cand[q]]
    order = np.argsort(-conf[q], kind="stable")
    c, ok = conf[q][order], correct[order]
    out: dict[str, list[float]] = {"threshold": [], "precision": [], "recall": []}
    tp = 0
    i = 0
    while i < len(c):
        j = i
        while j < len(c) and c[j] == c[i]:
            j += 1
        tp += int(ok[i:j].sum())
        out["threshold"].append(float(c[i]))
        out["precision"].append(tp / j)
        out["recall"].append(tp / n_pos if n_pos else 0.0)
        i = j
    return out


def score_decisions(candidates: np.ndarray, confidences: np.ndarray, declared: np.ndarray,
                    truth: np.ndarray, recent_excluded: int, tolerance: int = 0) -> Scores:
    """Score one method's decisions.

    ``candidates (N,) int``: the past image each query points at (-1: none);
    ``confidences (N,) float``: the confidence of that candidate; ``declared (N,) bool``:
    whether the method declared the loop (at its own operating point);
    ``truth (N, N) bool``: symmetric same-place matrix; ``tolerance``: frame tolerance K
    (module notes; 0 = the exact image).
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
    correct = (tolerant_truth(truth, tolerance) if tolerance else truth)[q, cand[q]]
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
