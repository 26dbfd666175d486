"""The discrete Bayes filter over loop-closure hypotheses (paper 000 Sec. IV, IV-A, IV-C).

The state is the full posterior p(S_t | z^t) as one array: index 0 is the hypothesis
S_t = -1 (no loop), index k >= 1 the hypothesis S_t = k - 1 (image k - 1 closes the loop).
At time t the image hypotheses are 0 .. t - p: the last p images are never hypotheses
(they look like the current one because they were just taken, Sec. IV).

The filter is a pair of functions of that state (prediction, then the likelihood update,
Eq. 4), so it can be checked against a hand-derived answer:

- :func:`predict`, the time evolution model p(S_t | S_t-1) of Sec. IV-A:
  p(-1 | -1) = 0.9; p(i | -1) = 0.1 / ((t - p) + 1) for each of the (t - p) + 1 images;
  p(-1 | j) = 0.1; p(i | j) a Gaussian in i - j, non-zero for i = j - 2 .. j + 2 only,
  whose coefficients sum to 0.9. Near the ends of the hypothesis range (j within 2 of 0
  or of t - p) some of those neighbours do not exist; the paper does not say what
  happens there. We spread the 0.9 over the neighbours that do exist (the Gaussian
  renormalised on them), which keeps p(S_t >= -1 | S_t-1 = j) = 1 as the paper requires.
  With no image hypothesis yet (t < p) the no-loop state keeps all its mass.
- :func:`update`: posterior = normalised likelihood x prior (Eq. 2-4); the likelihood
  comes from :func:`robotd.forward.likelihood.adjust_likelihood`.
- :func:`select_candidate` (Sec. IV-C): the posterior summed over each image's
  neighbourhood (the same +-2 images); when the largest sum exceeds the threshold (0.8)
  the most probable image of that neighbourhood is the loop candidate.

A later working memory (issue 14 item 4) would keep only some images as hypotheses; the
functions then need the neighbours of each hypothesis as explicit lists instead of
"index +- 2". Until then hypotheses are the dense range 0 .. t - p.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FilterParams", "diffusion_weights", "neighbourhood_sums", "predict",
           "select_candidate", "transition_matrix", "update"]


@dataclass(frozen=True)
class FilterParams:
    """Parameters of the filter (paper 000 Sec. IV-A, IV-C).

    Fields:
        p_no_loop_stays: p(S_t = -1 | S_t-1 = -1) (0.9).
        p_loop_ends: p(S_t = -1 | S_t-1 = j) for an image j (0.1); the Gaussian over j's
            neighbours carries the rest, 1 - p_loop_ends = 0.9.
        neighbours: the Gaussian is non-zero for i = j - neighbours .. j + neighbours (2),
            which is also the neighbourhood of the candidate selection.
        sigma_images: standard deviation of that Gaussian, in images (the paper gives only
            its support; with 1.0 the weights of offsets 0, 1, 2 are 1 : 0.61 : 0.14).
        loop_threshold: a candidate when the posterior summed over an image's
            neighbourhood exceeds this (0.8).
    """

    p_no_loop_stays: float = 0.9
    p_loop_ends: float = 0.1
    neighbours: int = 2
    sigma_images: float = 1.0
    loop_threshold: float = 0.8

    def __post_init__(self) -> None:
        for name in ("p_no_loop_stays", "p_loop_ends", "loop_threshold"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        if self.neighbours < 0:
            raise ValueError(f"neighbours must be >= 0, got {self.neighbours}")
        if not self.sigma_images > 0:
            raise ValueError(f"sigma_images must be positive, got {self.sigma_images}")


def diffusion_weights(params: FilterParams = FilterParams()) -> np.ndarray:
    """The Gaussian over offsets -neighbours .. +neighbours, ``(2 * neighbours + 1,)``,
    summing to 1 (the transition multiplies it by 1 - p_loop_ends)."""
    k = np.arange(-params.neighbours, params.neighbours + 1, dtype=np.float64)
    g = np.exp(-0.5 * (k / params.sigma_images) ** 2)
    return g / g.sum()


def _spread(n_prev: int, n_new: int, params: FilterParams) -> tuple[np.ndarray, np.ndarray]:
    """Offsets and, per previous image j, the Gaussian's sum over j's existing neighbours."""
    g = diffusion_weights(params)
    offsets = np.arange(-params.neighbours, params.neighbours + 1)
    j = np.arange(n_prev)
    valid = (j[:, None] + offsets[None, :] >= 0) & (j[:, None] + offsets[None, :] < n_new)
    norm = (valid * g[None, :]).sum(axis=1)
    return offsets, norm


def predict(posterior: np.ndarray, n_new: int, params: FilterParams = FilterParams()) -> np.ndarray:
    """The prior p(S_t | z^t-1) from the posterior at t - 1 (Eq. 4's sum; Sec. IV-A).

    ``posterior (1 + n_prev,)``: no-loop first, then images 0 .. n_prev - 1;
    ``n_new >= n_prev``: image hypotheses at t. Returns ``(1 + n_new,)`` summing to the
    posterior's sum. O(n) (the transition matrix is banded).
    """
    post = np.asarray(posterior, np.float64)
    n_prev = len(post) - 1
    if n_new < n_prev:
        raise ValueError(f"hypotheses cannot disappear: {n_prev} -> {n_new}")
    prior = np.zeros(1 + n_new, np.float64)
    p0 = post[0]
    img = post[1:]
    if n_new == 0:
        prior[0] = p0
        return prior
    prior[0] = params.p_no_loop_stays * p0 + params.p_loop_ends * img.sum()
    prior[1:] = (1.0 - params.p_no_loop_stays) / n_new * p0
    if n_prev:
        g = diffusion_weights(params)
        offsets, norm = _spread(n_prev, n_new, params)
        mass = (1.0 - params.p_loop_ends) * img / norm
        for o, w in zip(offsets.tolist(), g.tolist()):
            lo = max(0, -o)            # first j whose j + o >= 0
            hi = min(n_prev, n_new - o)  # j + o < n_new
            if hi > lo:
                prior[1 + lo + o:1 + hi + o] += w * mass[lo:hi]
    return prior


def transition_matrix(n_prev: int, n_new: int, params: FilterParams = FilterParams()) -> np.ndarray:
    """The dense ``(1 + n_new, 1 + n_prev)`` matrix T[i, j] = p(S_t = i | S_t-1 = j) (index 0
    = no loop), for tests and plots; each column sums to 1. :func:`predict` is its product
    with the posterior, without building it."""
    cols = [predict(np.eye(1 + n_prev)[j], n_new, params) for j in range(1 + n_prev)]
    return np.stack(cols, axis=1)


def update(prior: np.ndarray, likelihood: np.ndarray) -> np.ndarray:
    """The normalised product ``likelihood * prior`` (Eq. 2), ``(M,)``."""
    post = np.asarray(prior, np.float64) * np.asarray(likelihood, np.float64)
    total = post.sum()
    if not total > 0:
        raise ValueError("the posterior vanished (every hypothesis has zero prior or likelihood)")
    return post / total


def neighbourhood_sums(posterior: np.ndarray, params: FilterParams = FilterParams()) -> np.ndarray:
    """For each image hypothesis i, the posterior summed over images i - neighbours ..
    i + neighbours that exist, ``(n,)`` (the no-loop entry excluded)."""
    img = np.asarray(posterior, np.float64)[1:]
    if not len(img):
        return img
    k = params.neighbours
    c = np.concatenate([[0.0], np.cumsum(img)])
    i = np.arange(len(img))
    return c[np.minimum(i + k + 1, len(img))] - c[np.maximum(i - k, 0)]


def select_candidate(posterior: np.ndarray,
                     params: FilterParams = FilterParams()) -> tuple[int | None, float]:
    """The loop candidate of Sec. IV-C: ``(image, probability)``.

    ``probability`` is the largest neighbourhood sum; ``image`` the most probable image in
    that neighbourhood when the sum exceeds ``loop_threshold``, else None.
    """
    sums = neighbourhood_sums(posterior, params)
    if not len(sums):
        return None, 0.0
    best = int(np.argmax(sums))
    prob = float(sums[best])
    if prob <= params.loop_threshold:
        return None, prob
    img = np.asarray(posterior, np.float64)[1:]
    lo = max(0, best - params.neighbours)
    hi = min(len(img), best + params.neighbours + 1)
    return lo + int(np.argmax(img[lo:hi])), prob
