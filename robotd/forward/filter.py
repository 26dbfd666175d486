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

With a working memory (:mod:`robotd.forward.memory`) the hypotheses are
only some of the past images; :func:`predict_ids`, :func:`neighbourhood_sums_ids` and
:func:`select_candidate_ids` take them as sorted image ids (see the note above them). The
detector uses the dense functions as long as no place has left the working memory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FilterParams", "diffusion_weights", "neighbourhood_sums", "neighbourhood_sums_ids",
           "predict", "predict_ids", "select_candidate", "select_candidate_ids",
           "transition_matrix", "update"]


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
            neighbourhood exceeds this (0.8), or, with ``rule = "total"``, when the total
            loop probability does.
        rule: ``"neighbourhood"`` (the paper, Sec. IV-C) or ``"total"``: the total loop
            probability 1 - p(S_t = -1) against the threshold, as RTAB-Map thresholds it
            (``Rtabmap/LoopThr``), so that a place seen in several images far
            apart in time does not split its probability below the threshold; the
            candidate is the same (the most probable image of the best neighbourhood).
    """

    p_no_loop_stays: float = 0.9
    p_loop_ends: float = 0.1
    neighbours: int = 2
    sigma_images: float = 1.0
    loop_threshold: float = 0.8
    rule: str = "neighbourhood"

    def __post_init__(self) -> None:
        if self.rule not in ("neighbourhood", "total"):
            raise ValueError(f"rule must be 'neighbourhood' or 'total', got {self.rule!r}")
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
    """Offsets and, per previous image j, the Gaussian's sum over j's existing neighbours.

    Only the images within ``neighbours`` of either end lack a neighbour: their sums are
    taken over their own neighbours, every other image's is the sum over all of them,
    summed the same way (one row of the same reduction), so each is the value a sum per
    image would give while the work stays at the ends and not the whole history."""
    g = diffusion_weights(params)
    k = params.neighbours
    offsets = np.arange(-k, k + 1)
    if n_prev <= 3 * k + 1:  # a short history: every image near an end
        edge = np.arange(n_prev)
    else:
        edge = np.concatenate([np.arange(k), np.arange(n_prev - 2 * k - 1, n_prev)])
    valid = (edge[:, None] + offsets[None, :] >= 0) & (edge[:, None] + offsets[None, :] < n_new)
    whole = np.ones((1, len(offsets)), bool)
    norm = np.full(n_prev, (whole * g[None, :]).sum(axis=1)[0])
    norm[edge] = (valid * g[None, :]).sum(axis=1)
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

    ``probability`` is the largest neighbourhood sum (``rule = "total"``: 1 - p(no loop));
    ``image`` the most probable image in
    that neighbourhood when the sum exceeds ``loop_threshold``, else None.
    """
    if params.rule == "total":  # the threshold first: the sums only for a candidate
        if len(posterior) < 2:
            return None, 0.0
        prob = 1.0 - float(posterior[0])
        if prob <= params.loop_threshold:
            return None, prob
    sums = neighbourhood_sums(posterior, params)
    if not len(sums):
        return None, 0.0
    best = int(np.argmax(sums))
    prob = float(sums[best]) if params.rule == "neighbourhood" else 1.0 - float(posterior[0])
    if prob <= params.loop_threshold:
        return None, prob
    img = np.asarray(posterior, np.float64)[1:]
    lo = max(0, best - params.neighbours)
    hi = min(len(img), best + params.neighbours + 1)
    return lo + int(np.argmax(img[lo:hi])), prob


# --- Hypotheses that are a subset of the past images (a working memory) -----------------
#
# With a working memory (:mod:`robotd.forward.memory`) the image hypotheses are the places in
# it, ``ids`` (sorted image ids, not 0 .. n - 1): places leave it (to long-term memory) and
# come back (retrieval). The paper's model carries over with "neighbours" meaning the
# images within +-neighbours *ids* that are hypotheses now:
#
# - p(-1 | -1) = 0.9 and p(i | -1) = 0.1 / n for each of the n hypotheses;
# - p(-1 | j) = 0.1 and the Gaussian over j's neighbours among the hypotheses now,
#   renormalised on those, carrying 0.9; j itself is one of them unless it left;
# - a hypothesis j that left with none of its neighbours still there gives its 0.9 to no
#   loop (the place cannot be represented any more), so every column still sums to 1;
# - a new or retrieved place gets 0.1 / n of the no-loop mass plus whatever its neighbours'
#   Gaussians send it (a retrieved neighbour of a recognised place inherits mass at once).
#
# When the ids are exactly 0 .. n - 1 these are :func:`predict`, :func:`neighbourhood_sums`
# and :func:`select_candidate` (tests check it).

def _neighbour_slots(ids_from: np.ndarray, ids_to: np.ndarray, params: FilterParams
                     ) -> tuple[np.ndarray, np.ndarray]:
    """For each offset o in -neighbours .. +neighbours and each id j of ``ids_from``, the
    position of j + o in the sorted ``ids_to`` (``(2k + 1, len(ids_from))``) and whether it
    is there."""
    offsets = np.arange(-params.neighbours, params.neighbours + 1)
    target = ids_from[None, :] + offsets[:, None]
    pos = np.searchsorted(ids_to, target)
    found = pos < len(ids_to)
    found[found] = ids_to[pos[found]] == target[found]
    return np.where(found, pos, 0), found


def _check_ids(ids: np.ndarray, n: int, what: str) -> np.ndarray:
    a = np.asarray(ids, np.int64)
    if a.ndim != 1 or len(a) != n:
        raise ValueError(f"{what}: expected {n} ids, got shape {a.shape}")
    if len(a) > 1 and not (np.diff(a) > 0).all():
        raise ValueError(f"{what}: ids must be strictly increasing")
    return a


def predict_ids(posterior: np.ndarray, ids_prev: np.ndarray, ids_new: np.ndarray,
                params: FilterParams = FilterParams()) -> np.ndarray:
    """The prior over the hypotheses ``ids_new`` from the posterior over ``ids_prev``
    (both sorted image ids; ``posterior (1 + len(ids_prev),)``, no loop first). Returns
    ``(1 + len(ids_new),)`` summing to the posterior's sum. O(n log n)."""
    post = np.asarray(posterior, np.float64)
    prev = _check_ids(ids_prev, len(post) - 1, "ids_prev")
    new = _check_ids(ids_new, len(np.asarray(ids_new)), "ids_new")
    n_new = len(new)
    prior = np.zeros(1 + n_new, np.float64)
    p0 = post[0]
    img = post[1:]
    if n_new == 0:
        prior[0] = p0 + img.sum()
        return prior
    prior[0] = params.p_no_loop_stays * p0 + params.p_loop_ends * img.sum()
    prior[1:] = (1.0 - params.p_no_loop_stays) / n_new * p0
    if len(prev):
        g = diffusion_weights(params)
        pos, found = _neighbour_slots(prev, new, params)
        norm = (found * g[:, None]).sum(axis=0)
        orphan = norm == 0
        prior[0] += (1.0 - params.p_loop_ends) * img[orphan].sum()
        mass = np.where(orphan, 0.0, (1.0 - params.p_loop_ends) * img / np.where(orphan, 1.0, norm))
        for k, w in enumerate(g.tolist()):
            f = found[k]
            prior[1:] += np.bincount(pos[k][f], weights=w * mass[f], minlength=n_new)
    return prior


def neighbourhood_sums_ids(posterior: np.ndarray, ids: np.ndarray,
                           params: FilterParams = FilterParams()) -> np.ndarray:
    """For each hypothesis, the posterior summed over the hypotheses within +-neighbours
    ids, ``(n,)``."""
    img = np.asarray(posterior, np.float64)[1:]
    a = _check_ids(ids, len(img), "ids")
    if not len(img):
        return img
    c = np.concatenate([[0.0], np.cumsum(img)])
    hi = np.searchsorted(a, a + params.neighbours, side="right")
    lo = np.searchsorted(a, a - params.neighbours, side="left")
    return c[hi] - c[lo]


def select_candidate_ids(posterior: np.ndarray, ids: np.ndarray,
                         params: FilterParams = FilterParams()) -> tuple[int | None, float, int | None]:
    """:func:`select_candidate` over hypotheses named by ``ids``: ``(image id or None,
    probability, best)`` where ``best`` is the most probable image of the best
    neighbourhood whether or not it passes the threshold (None without hypotheses): the
    place a working memory retrieves around."""
    sums = neighbourhood_sums_ids(posterior, ids, params)
    if not len(sums):
        return None, 0.0, None
    a = np.asarray(ids, np.int64)
    img = np.asarray(posterior, np.float64)[1:]
    b = int(np.argmax(sums))
    prob = float(sums[b]) if params.rule == "neighbourhood" else 1.0 - float(posterior[0])
    lo = int(np.searchsorted(a, a[b] - params.neighbours, side="left"))
    hi = int(np.searchsorted(a, a[b] + params.neighbours, side="right"))
    best = int(a[lo + int(np.argmax(img[lo:hi]))])
    return (best if prob > params.loop_threshold else None), prob, best
