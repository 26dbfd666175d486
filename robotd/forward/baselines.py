"""The two baselines the forward detector is measured against.

- :func:`best_score`: the detector's own likelihoods without the Bayes filter. Among the
  hypotheses -1, 0 .. t - p the highest tf-idf vote wins; a loop is declared when a past
  image beats the virtual no-loop image. Its confidence is the ratio of the two votes (so a
  threshold can be swept; 1 is the default rule). It may be followed by the same epipolar
  verification (the app layer runs both variants).
- :class:`BruteForceMatcher`: no vocabulary at all. Each image's SIFT descriptors are
  matched against every past image's (0 .. t - p) and each pair checked with the same
  five-point RANSAC as the detector; the image with the most inliers wins, and it is a loop
  when those inliers reach the verification's ``min_inliers``. Its time grows linearly with
  the run; it is the accuracy the vocabulary and the filter trade for speed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from robotd.forward.features import Features
from robotd.forward.verify import VerifyParams, verify_pair

__all__ = ["BruteForceMatcher", "BruteForceResult", "best_score"]


def best_score(scores: np.ndarray, virtual_score: float, n_hypotheses: int) -> tuple[int | None, float]:
    """The best-scoring image hypothesis and its vote relative to the virtual image's.

    ``scores (t,)``: the votes of past images 0 .. t - 1; only the first ``n_hypotheses``
    (0 .. t - p) compete. Returns ``(image, ratio)`` with ratio = best / virtual (inf when
    the virtual image got no vote and the best did); ``(None, 0.0)`` when no image got a
    vote. A loop by the default rule when ratio > 1.
    """
    s = np.asarray(scores, np.float64)[:n_hypotheses]
    if not len(s) or not s.max() > 0:
        return None, 0.0
    best = int(np.argmax(s))
    ratio = float(s[best] / virtual_score) if virtual_score > 0 else float("inf")
    return best, ratio


@dataclass(frozen=True, eq=False)
class BruteForceResult:
    """One image against every eligible past image: the best ``candidate_id`` (None when
    nothing could be compared), its ``n_inliers``, whether that makes a ``loop``, the pairs
    compared and the seconds it took (``time_s``, feature extraction excluded)."""

    image_id: int
    candidate_id: int | None
    n_inliers: int
    loop: bool
    pairs: int
    time_s: float


class BruteForceMatcher:
    """Match each new image against every past image (bar the last ``recent_excluded``)."""

    def __init__(self, verify: VerifyParams = VerifyParams(), recent_excluded: int = 10,
                 camera_matrix: np.ndarray | None = None,
                 timer: Callable[[], float] = time.perf_counter) -> None:
        self.verify = verify
        self.recent_excluded = recent_excluded
        self.camera_matrix = camera_matrix
        self._timer = timer
        self._features: list[Features] = []

    def process_features(self, feats: Features) -> BruteForceResult:
        t0 = self._timer()
        t = len(self._features)
        n = max(0, t - self.recent_excluded + 1)
        best, best_inl = None, -1
        for j in range(n):
            v = verify_pair(self._features[j], feats, self.verify, self.camera_matrix)
            if v.n_inliers > best_inl:
                best, best_inl = j, v.n_inliers
        self._features.append(feats)
        inl = max(best_inl, 0)
        return BruteForceResult(t, best, inl, best is not None and inl >= self.verify.min_inliers,
                                n, self._timer() - t0)
