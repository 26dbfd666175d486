"""The P(loop | score) curve and its threshold (paper 003 Sec. III-B and IV-C).

From a calibration run, every scored pair of keyframes gives a local score ``s`` and, from
the odometry and the footprints, a label ``J >= r``. The curve

    P(J >= r | score = s) = P(J >= r, score = s) / P(score = s)          (paper eq. 6)

is estimated per mode from those pairs: scores are binned with equal counts, each bin's
probability is the posterior mean of a Beta(1, 1) prior updated by its labels, and the
curve is made monotone non-decreasing by isotonic regression (pool adjacent violators,
weighted by bin counts), since a higher local score should never mean a less likely loop.
The threshold of a mode is the smallest score from which the curve, and a conservative
lower bound of it, stay at or above the confidence level (0.99 by default): the paper's
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
    posterior mean; ``lower (B,)`` a monotone lower credible bound (about the 5th percentile
    of the Beta posterior of the isotonic block the bin was pooled into); ``positives/count (B,)`` the (weighted) labels behind each bin.
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


def _pava_blocks(y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted isotonic (non-decreasing) regression by pool adjacent violators.

    Returns the fitted value per block and the number of inputs in each block."""
    vals: list[float] = []
    wts: list[float] = []
    sizes: list[int] = []
    for yi, wi in zip(y.astype(float), w.astype(float)):
        vals.append(yi)
        wts.append(wi)
        sizes.append(1)
        while len(vals) > 1 and vals[-2] >= vals[-1]:  # ties pooled too: same fit, pooled evidence
            wsum = wts[-2] + wts[-1]
            v = (vals[-2] * wts[-2] + vals[-1] * wts[-1]) / wsum if wsum > 0 else vals[-1]
            n = sizes[-2] + sizes[-1]
            vals[-2:], wts[-2:], sizes[-2:] = [v], [wsum], [n]
    return np.array(vals), np.array(sizes)


def _pava(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted isotonic regression, one fitted value per input."""
    vals, sizes = _pava_blocks(y, w)
    return np.repeat(vals, sizes)


def _beta_lower(a: np.ndarray, b: np.ndarray, q: float = 0.05) -> np.ndarray:
    """Approximate ``q`` quantile of Beta(a, b) (Wilson-style normal approximation on the
    logit scale; conservative enough for choosing a threshold, exact tests are not needed)."""
    mean = a / (a + b)
    var = a * b / ((a + b) ** 2 * (a + b + 1))
    z = 1.6448536  # the standard normal's 95th percentile: a one-sided 5 % bound
    logit = np.log(mean / (1 - mean))
    sd = np.sqrt(var) / (mean * (1 - mean))
    return 1.0 / (1.0 + np.exp(-(logit - z * sd)))


def fit_loop_curve(scores: np.ndarray, labels: np.ndarray, bins: int = 40,
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
    a, bb = pos + 1.0, count - pos + 1.0
    vals, sizes = _pava_blocks(a / (a + bb), count)
    prob = np.repeat(vals, sizes)
    # The lower bound of each monotone block uses all the pairs pooled in it: a long run
    # of bins that are all loops is strong evidence, one bin alone is not.
    ends = np.cumsum(sizes)
    starts = ends - sizes
    pooled_pos = np.array([pos[i:j].sum() for i, j in zip(starts, ends)])
    pooled_n = np.array([count[i:j].sum() for i, j in zip(starts, ends)])
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


def precision_recall(scores: np.ndarray, labels: np.ndarray, threshold: float) -> PrecisionRecall:
    """Precision and recall of declaring a loop when ``score >= threshold``."""
    s = np.asarray(scores, dtype=float)
    y = np.asarray(labels, dtype=bool)
    declared = s >= threshold
    return PrecisionRecall(float(threshold), int(np.sum(declared & y)), int(np.sum(declared & ~y)),
                           int(np.sum(~declared & y)))
