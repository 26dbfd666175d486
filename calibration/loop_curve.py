"""The P(loop | score) curve and its threshold (paper 003 Sec. III-B and IV-C).

From a calibration run, every scored pair of keyframes gives a local score ``s`` and, from
the odometry and the footprints, a label ``J >= r``. The curve

    P(J >= r | score = s) = P(J >= r, score = s) / P(score = s)          (paper eq. 6)

is estimated per mode from those pairs: scores are binned with equal counts and the curve is
the isotonic (monotone non-decreasing) fit of the bins' loop rates by pool adjacent
violators, since a higher local score should never mean a less likely loop (a run of bins
that are all loops is one block, whatever the bins' sizes). Each block of
bins that the fit pools is one estimate: its probability is the posterior mean of a
Beta(1, 1) prior updated by all the (weighted) labels pooled in it, and its lower bound
the 5th percentile of that posterior. Pooling the evidence matters: a bin of 100 pairs
that are all loops only shows P >= 0.97 or so, the 1000 pairs of ten such bins in a row
show P >= 0.997. The threshold of a mode is the smallest score from which the curve and
its lower bound stay at or above the confidence level (0.99 by default): the paper's
"minimum value of local score that guarantees loop detection" (Table III).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class LoopCurve:
    """A monotone estimate of P(loop | score) on bins of the score.

    ``score_lo/score_hi (B,)``: each bin's score range; ``probability (B,)`` the monotone
    posterior mean of the isotonic block the bin was pooled into; ``lower (B,)`` a monotone
    lower credible bound (the 5th percentile of that block's Beta posterior, carried
    forward to higher scores); ``positives/count (B,)`` the (weighted) labels behind each bin.
    """

    score_lo: np.ndarray
    score_hi: np.ndarray
    probability: np.ndarray
    lower: np.ndarray
    positives: np.ndarray
    count: np.ndarray

    def at(self, score: float | np.ndarray) -> np.ndarray:
        """P(loop | score) by the bin the score falls in (scores above the last bin: the last)."""
        idx = np.clip(np.searchsorted(self.score_hi, score, side="left"), 0, len(self.score_hi) - 1)
        return self.probability[idx]


def _pava_blocks(pos: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Isotonic regression by pool adjacent violators on (weighted) Bernoulli counts.

    ``pos (B,)``, ``count (B,)``: loops and pairs per bin, in score order. Adjacent blocks
    are pooled while the earlier one's loop rate ``pos / count`` is not below the later
    one's (ties are pooled too: same fit, pooled evidence), so a run of bins that are all
    loops becomes one block whatever their sizes. A second pass pools the blocks whose
    Beta(1, 1) posterior means ``(pos + 1) / (count + 2)`` (the curve's values) would still
    decrease (a small block's mean is pulled towards 1/2). Returns the number of bins in
    each block; the blocks' posterior means are strictly increasing.
    """
    blocks = [[p, n, 1] for p, n in zip(np.asarray(pos, float), np.asarray(count, float))]
    for value in (_rate, _posterior_mean):
        pooled: list[list[float]] = []  # [pooled positives, pooled count, bins]
        for b in blocks:
            pooled.append(list(b))
            while len(pooled) > 1 and value(*pooled[-2][:2]) >= value(*pooled[-1][:2]):
                p2, n2, k2 = pooled.pop()
                pooled[-1][0] += p2
                pooled[-1][1] += n2
                pooled[-1][2] += k2
        blocks = pooled
    return np.array([int(b[2]) for b in blocks])


def _rate(pos: float, count: float) -> float:
    return pos / count if count > 0 else 0.0


def _posterior_mean(pos: float, count: float) -> float:
    return (pos + 1.0) / (count + 2.0)


def _beta_lower(a: np.ndarray, b: np.ndarray, q: float = 0.05) -> np.ndarray:
    """The ``q`` quantile of Beta(a, b) (exact, by the inverse regularised incomplete beta)."""
    from scipy.special import betaincinv

    return np.asarray(betaincinv(np.asarray(a, float), np.asarray(b, float), q), dtype=float)


def fit_loop_curve(scores: np.ndarray, labels: np.ndarray, bins: int = 200,
                   min_per_bin: int = 20, weights: np.ndarray | None = None) -> LoopCurve:
    """Estimate the monotone P(loop | score) from ``scores (N,)`` and boolean ``labels (N,)``.

    Bins have about equal counts (at least ``min_per_bin`` pairs each, so fewer bins for
    small samples); ties in score never straddle two bins. ``weights (N,)``: how many
    pairs of the whole population each scored pair stands for (1 / sampling rate), so a
    subsample of distant pairs still counts with its true share of non-loops.
    """
    s = np.asarray(scores, dtype=float)
    y = np.asarray(labels, dtype=bool)
    w = np.ones(len(s)) if weights is None else np.asarray(weights, dtype=float)
    if s.shape != y.shape or s.ndim != 1 or len(s) == 0 or w.shape != s.shape:
        raise ValueError("scores, labels (and weights) must be non-empty 1-D arrays of one length")
    if np.any(~np.isfinite(s)) or np.any(~(w > 0)):
        raise ValueError("scores must be finite and weights positive")
    order = np.argsort(s, kind="stable")
    s, y, w = s[order], y[order], w[order]
    n_bins = max(1, min(bins, len(s) // max(1, min_per_bin)))
    edges = np.unique(np.quantile(s, np.linspace(0, 1, n_bins + 1)[1:-1]))
    idx = np.searchsorted(edges, s, side="right")  # bin of each score; equal scores together
    b = idx.max() + 1
    n_in = np.bincount(idx, minlength=b)
    keep = n_in > 0
    pos = np.bincount(idx, weights=w * y, minlength=b)[keep]
    count = np.bincount(idx, weights=w, minlength=b)[keep]
    lo = np.array([s[idx == k].min() for k in np.flatnonzero(keep)])
    hi = np.array([s[idx == k].max() for k in np.flatnonzero(keep)])
    sizes = _pava_blocks(pos, count)
    ends = np.cumsum(sizes)
    starts = ends - sizes
    pooled_pos = np.array([pos[i:j].sum() for i, j in zip(starts, ends)])
    pooled_n = np.array([count[i:j].sum() for i, j in zip(starts, ends)])
    prob = np.repeat((pooled_pos + 1.0) / (pooled_n + 2.0), sizes)
    # A lower bound at one score is one at every higher score too (the curve is monotone),
    # so the bound carries forward; it never exceeds the estimate itself.
    block_lower = _beta_lower(pooled_pos + 1.0, pooled_n - pooled_pos + 1.0)
    lower = np.minimum(np.repeat(np.maximum.accumulate(block_lower), sizes), prob)
    return LoopCurve(lo, hi, prob, lower, pos, count)


def pick_threshold(curve: LoopCurve, confidence: float = 0.99) -> float | None:
    """The smallest score from which both the curve and its lower bound reach
    ``confidence`` and stay there; None when no bin is that certain."""
    ok = (curve.probability >= confidence) & (curve.lower >= confidence)
    # Both curves are monotone, so the good bins are a suffix.
    if not ok[-1]:
        return None
    first = int(np.flatnonzero(~ok)[-1] + 1) if np.any(~ok) else 0
    return float(curve.score_lo[first])


@dataclass(frozen=True)
class PrecisionRecall:
    """Declared loops (score >= threshold) against true loops."""

    threshold: float
    true_positives: int
    false_positives: int
    false_negatives: int

    @property
    def precision(self) -> float:
        d = self.true_positives + self.false_positives
        return self.true_positives / d if d else math.nan

    @property
    def recall(self) -> float:
        d = self.true_positives + self.false_negatives
        return self.true_positives / d if d else math.nan


def precision_recall(scores: np.ndarray, labels: np.ndarray, threshold: float,
                     weights: np.ndarray | None = None) -> PrecisionRecall:
    """Precision and recall of declaring a loop when ``score >= threshold``.

    ``weights (N,)``: how many pairs each scored pair stands for (see
    :func:`fit_loop_curve`); weighted counts are rounded to whole pairs.
    """
    s = np.asarray(scores, dtype=float)
    y = np.asarray(labels, dtype=bool)
    w = np.ones(len(s)) if weights is None else np.asarray(weights, dtype=float)
    declared = s >= threshold
    return PrecisionRecall(float(threshold), int(round(w[declared & y].sum())),
                           int(round(w[declared & ~y].sum())), int(round(w[~declared & y].sum())))
