"""From voting scores to the likelihood the Bayes filter multiplies in (paper 000 Sec. IV-B).

The scores themselves are the tf-idf votes of :meth:`robotd.forward.vocabulary.InvertedIndex.vote`
(one per past image, and one for the virtual "no loop" image I_-1). Only the hypotheses whose
score stands out are believed:

    paper (default):  L_i = (s_i - mean) / mean   when s_i > mean + std,   else 1

with mean and (population) standard deviation over the scores of every hypothesis,
I_-1 included (the paper treats I_-1 "as for the true images"), and L = 1 everywhere when
no hypothesis got a vote.

RTAB-Map (Labbe and Michaud, the ``adjustLikelihood`` step of its ``Rtabmap.cpp``) departs
from the paper, and :func:`adjust_likelihood` offers its variant as ``method="rtabmap"``:
mean and std are taken over the *non-zero* scores of the real images only (I_-1 left out),
a standing-out score becomes ``(s - std) / mean`` instead of ``(s - mean) / mean``, and the
no-loop hypothesis gets ``mean / std + 1`` instead of its own vote (RTAB-Map has no virtual
image of frequent words). The paper's version stays the default.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

__all__ = ["LikelihoodMethod", "adjust_likelihood"]

LikelihoodMethod = Literal["paper", "rtabmap"]


def adjust_likelihood(scores: np.ndarray, method: LikelihoodMethod = "paper") -> np.ndarray:
    """The likelihood factors of the hypotheses from their voting scores.

    ``scores (M,) float``: index 0 is the virtual image I_-1 (hypothesis S_t = -1), index
    k >= 1 the past image k - 1 (hypothesis S_t = k - 1). Returns ``(M,) float64`` factors,
    1 for a hypothesis that does not stand out (the paper's "non-selected hypotheses
    multiply the posterior by 1").
    """
    s = np.asarray(scores, np.float64)
    out = np.ones(len(s), np.float64)
    if method == "paper":
        if not len(s):
            return out
        mean = float(s.mean())
        std = float(s.std())
        if mean <= 0.0:
            return out
        high = s > mean + std
        out[high] = (s[high] - mean) / mean
        return out
    if method == "rtabmap":
        real = s[1:]
        values = real[real > 0]
        if not len(values):
            return out
        mean = float(values.mean())
        std = float(values.std())
        high = real > mean + std
        out[1:][high] = (real[high] - std) / mean
        if std > 0:
            out[0] = mean / std + 1.0
        return out
    raise ValueError(f"likelihood method must be 'paper' or 'rtabmap', got {method!r}")
