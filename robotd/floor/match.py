"""Matching two floor descriptors: the local score and the global score (paper 003, Sec. II-B).

**Local score** (CDVS: a sum over the matches that survive a geometric consistency check
of a weight that falls with descriptor distance). Steps of :func:`local_score`:

1. Nearest neighbours of A's ternary descriptors among B's, by the squared Euclidean
   distance of the trit vectors (one float32 matrix product: ``|a|^2 + |b|^2 - 2 a.b``),
   kept when the nearest is clearly nearer than the second (Lowe's ratio test) and not
   farther than ``max_distance``. Distances are normalised by the descriptor length
   (independent random trits are 4/3 apart on average).
2. Orientation consistency: a rigid motion turns every keypoint by the same angle, so
   the differences of the matched keypoints' orientations pile up in one bin of their
   histogram; matches farther than ``angle_tol_rad`` from that peak are dropped.
3. RANSAC (Fischler and Bolles 1981) on a 2-D rigid transform from 2-point samples. A
   sample is accepted only if the distance between its two points is the same in both
   images within ``max_log_scale`` (the downward camera sees the floor at one scale: the
   log distance ratio of inlier pairs is about 0, the observation DISTRAT (Lepsoy et al.
   2011) builds its outlier test on). The best hypothesis is refined by least squares
   (:func:`robotd.base.geometry.rigid_fit_2d`) on its inliers, twice.
4. ``score = sum over inliers of max(0, 1 - distance / weight_distance)``; zero when
   fewer than ``min_inliers`` survive (the result then says why, as DLoopDetector does).
   A caller that only needs scores of at least ``min_score`` (the loop threshold) skips
   steps 2-3 when even the sum over every descriptor match of step 1 stays below it: the
   score sums the same weights over a subset of those matches (``BELOW_MIN_SCORE``).

Scores are comparable within a mode (the descriptor length and feature count are fixed
by the mode), not across modes.

**Global score**: ``1 - hamming / bits`` of the binary global descriptors (SimHash of the
VLAD: about 0.5 for unrelated images, 1 for identical ones).
"""

from __future__ import annotations

import itertools
import math
import threading
from dataclasses import dataclass
from functools import lru_cache
from enum import StrEnum

import numpy as np

from robotd.base.errors import DescriptorError
from robotd.base.geometry import wrap_angle
from robotd.floor.desccoding import trit_table
from robotd.floor.descriptor import FloorDescriptor, PartialDescriptor

__all__ = ["MatchReason", "Matcher", "MatchParams", "MatchResult", "global_score", "local_score"]

class MatchReason(StrEnum):
    """Why a pair was dismissed (a :class:`~enum.StrEnum`: equal to its text; ``OK``, the
    empty text, is false)."""

    OK = ""
    TOO_FEW_FEATURES = "TOO_FEW_FEATURES"
    TOO_FEW_MATCHES = "TOO_FEW_MATCHES"
    NO_GEOMETRIC_CONSISTENCY = "NO_GEOMETRIC_CONSISTENCY"
    BELOW_MIN_SCORE = "BELOW_MIN_SCORE"


TOO_FEW_FEATURES = MatchReason.TOO_FEW_FEATURES
TOO_FEW_MATCHES = MatchReason.TOO_FEW_MATCHES
NO_GEOMETRIC_CONSISTENCY = MatchReason.NO_GEOMETRIC_CONSISTENCY
BELOW_MIN_SCORE = MatchReason.BELOW_MIN_SCORE


@dataclass(frozen=True)
class MatchParams:
    """Parameters of :func:`local_score`.

    Fields:
        ratio: Lowe's ratio test on descriptor distances (nearest / second nearest).
        max_distance: largest normalised squared trit distance of a match (per element;
            independent random descriptors are 4/3 apart).
        angle_tol_rad: largest difference between a match's orientation change and the
            dominant one, radians (covers the 5-bit orientation quantisation).
        inlier_px: largest distance between a point mapped by the transform and its match,
            pixels (generous: lens distortion bends a rigid floor motion by a few pixels).
        max_log_scale: largest |log(distance in B / distance in A)| of a RANSAC sample.
        min_sample_px: smallest distance between the two points of a RANSAC sample, px.
        iterations: RANSAC hypotheses.
        min_matches: fewer matches after steps 1-2 dismiss the pair (TOO_FEW_MATCHES).
        min_inliers: fewer inliers dismiss the pair (NO_GEOMETRIC_CONSISTENCY).
        weight_distance: distance at which an inlier's weight in the score reaches 0.
        seed: seed of RANSAC's sampling (results are deterministic).
        confidence: 0 scores every hypothesis (the default). In (0, 1): RANSAC stops
            early, adaptively (Fischler and Bolles 1981; Hartley and Zisserman, Sec. 4.7.1):
            the hypotheses are scored in blocks (10 draws, then 3 times as many in all
            each time: 30, 90, ``iterations``) and the check stops once
            ``log(1 - confidence) / log(1 - w**2)`` have been scored, ``w`` the best
            hypothesis's inlier fraction so far. A true loop (nearly every match an
            inlier) stops after the first block; the best hypothesis is then the first
            block's, which may differ from the best of all (and so may the refined inliers).
    """

    ratio: float = 0.9
    max_distance: float = 1.0
    angle_tol_rad: float = 0.35
    inlier_px: float = 8.0
    max_log_scale: float = 0.1
    min_sample_px: float = 20.0
    iterations: int = 100
    min_matches: int = 4
    min_inliers: int = 4
    weight_distance: float = 1.2
    seed: int = 0
    confidence: float = 0.0

    def __post_init__(self) -> None:
        if not (0 < self.ratio <= 1 and self.max_distance > 0 and self.angle_tol_rad > 0 and self.inlier_px > 0
                and self.max_log_scale > 0 and self.min_sample_px >= 0 and self.iterations >= 1
                and self.min_matches >= 2 and self.min_inliers >= 2 and self.weight_distance > 0
                and 0 <= self.confidence < 1):
            raise ValueError(f"match parameters out of range: {self}")


@dataclass(frozen=True, eq=False)
class MatchResult:
    """The local match of descriptor A against descriptor B.

    Fields:
        score: the local score (0 when dismissed).
        n_matches: descriptor matches before the geometric check.
        n_inliers: matches consistent with ``transform``.
        inliers_a, inliers_b: ``(K,) int64`` keypoint indices of the inlier matches.
        xy_a, xy_b: ``(K, 2) float32`` their positions, pixels of image A, resp. B.
        transform: ``(2, 3) float64`` rigid transform ``xy_b ~ R xy_a + t`` (pixels), or
            None when dismissed.
        reason: '' on success, else why the pair was dismissed (TOO_FEW_FEATURES,
            TOO_FEW_MATCHES, BELOW_MIN_SCORE, NO_GEOMETRIC_CONSISTENCY).
    """

    score: float
    n_matches: int
    n_inliers: int
    inliers_a: np.ndarray
    inliers_b: np.ndarray
    xy_a: np.ndarray
    xy_b: np.ndarray
    transform: np.ndarray | None
    reason: MatchReason

    @property
    def rotation_rad(self) -> float:
        """Rotation of the transform, radians (NaN when dismissed)."""
        return math.nan if self.transform is None else math.atan2(self.transform[1, 0], self.transform[0, 0])


_NO_INDEX = np.zeros(0, np.int64)
_NO_XY = np.zeros((0, 2), np.float32)
_NO_INDEX.flags.writeable = _NO_XY.flags.writeable = False


def _dismissed(reason: MatchReason, n_matches: int = 0) -> MatchResult:
    return MatchResult(0.0, n_matches, 0, _NO_INDEX, _NO_INDEX, _NO_XY, _NO_XY, None, reason)


_PREV_BIN = np.roll(np.arange(32), 1)  # the orientation histogram's 32 bins, circularly
_NEXT_BIN = np.roll(np.arange(32), -1)


def _augmented(d: FloorDescriptor, scale: float, last: np.ndarray | None) -> np.ndarray:
    """``(N, length + 1) float32``: ``scale`` times the trits, then ``last`` (or ones)."""
    out = np.empty((len(d), d.length + 1), np.float32)
    out[:, :-1] = d.ternary()
    if scale != 1.0:
        out[:, :-1] *= scale
    out[:, -1] = 1.0 if last is None else last
    return out


def _augmented_a(a: FloorDescriptor) -> np.ndarray:
    """``_augmented(a, 1.0, None)``, the query's side of every local score: its trits built
    from the bit planes in int8 and cast once (the same float32 values)."""
    out = np.empty((len(a), a.length + 1), np.float32)
    pos = np.unpackbits(np.ascontiguousarray(a.local_pos).astype("<u8", copy=False).view(np.uint8), axis=1,
                        bitorder="little")
    neg = np.unpackbits(np.ascontiguousarray(a.local_neg).astype("<u8", copy=False).view(np.uint8), axis=1,
                        bitorder="little")
    np.subtract(pos.view(np.int8)[:, :a.length], neg.view(np.int8)[:, :a.length], out=out[:, :-1], casting="unsafe")
    out[:, -1] = 1.0
    return out


@lru_cache(maxsize=1)
def _minus_two_trits() -> np.ndarray:
    """``(256, 5) float32``: per stored trit byte (5 base-3 digits, element + 1), its 5
    elements times -2; bytes above 242 (refused by the decoder) give zeros."""
    out = np.zeros((256, 5), np.float32)
    out[:243] = -2.0 * (trit_table().astype(np.float32) - 1.0)
    return out


def _augmented_b(d: FloorDescriptor | PartialDescriptor, out: np.ndarray | None = None) -> np.ndarray:
    """``_augmented(d, -2.0, d.nonzero_trits())``, built from the bit planes in int8 (the
    trits times -2 are exact there) and cast once: the candidate's side of every local score.
    A :class:`~robotd.floor.descriptor.PartialDescriptor`'s straight from its stored trit
    bytes (one table look-up; the squared norms from the same floats, exact: each element
    is -2, 0 or 2), without its bit planes. ``out``: a ``(N, length + 1) float32`` array
    to write it into (returned)."""
    n, length = len(d), d.length
    if out is None:
        out = np.empty((n, length + 1), np.float32)
    if isinstance(d, PartialDescriptor):
        t = _minus_two_trits().take(d.trits, axis=0).reshape(-1)[: n * length].reshape(n, length)
        out[:, :-1] = t
        out[:, -1] = np.einsum("ij,ij->i", t, t) * np.float32(0.25)
        return out
    pos = np.unpackbits(np.ascontiguousarray(d.local_pos).astype("<u8", copy=False).view(np.uint8), axis=1,
                        bitorder="little")
    neg = np.unpackbits(np.ascontiguousarray(d.local_neg).astype("<u8", copy=False).view(np.uint8), axis=1,
                        bitorder="little")
    t = neg.view(np.int8)[:, :length] - pos.view(np.int8)[:, :length]
    t += t
    out[:, :-1] = t
    out[:, -1] = d.nonzero_trits()
    return out


_add_reduce = np.add.reduce  # ndarray.sum's own reduction (the same sums), without its wrapper's cost


def _rigid(xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """``[R | t]`` (2 x 3) of the least-squares rigid fit ``xb ~ R xa + t`` (as
    :func:`robotd.base.geometry.rigid_fit_2d`, from raw sums: this runs twice per match)."""
    n = len(xa)
    (sax, say), (sbx, sby) = _add_reduce(xa, axis=0).tolist(), _add_reduce(xb, axis=0).tolist()
    (h00, h01), (h10, h11) = (xa.T @ xb).tolist()
    # The cross-covariance's corrections in Python floats: the same IEEE operations as the
    # array expression h - sa[:, None] * sb[None, :] / n, element by element.
    h00, h01, h10, h11 = h00 - sax * sbx / n, h01 - sax * sby / n, h10 - say * sbx / n, h11 - say * sby / n
    yaw = math.atan2(h01 - h10, h00 + h11)
    c, s = math.cos(yaw), math.sin(yaw)
    cax, cay, cbx, cby = sax / n, say / n, sbx / n, sby / n
    return np.array([[c, -s, cbx - (c * cax - s * cay)], [s, c, cby - (s * cax + c * cay)]])


def _ransac_rng(seed: int) -> np.random.Generator:
    """A generator in the state ``default_rng(seed)`` starts in (same draws), without the
    cost of seeding it afresh on every match: one per thread and seed, rewound."""
    cache = getattr(_RNGS, "by_seed", None)
    if cache is None:
        cache = _RNGS.by_seed = {}
    entry = cache.get(seed)
    if entry is None:
        g = np.random.default_rng(seed)
        entry = cache[seed] = (g, g.bit_generator.state)
    g, start = entry
    g.bit_generator.state = start
    return g


def _ransac_draws(seed: int, m: int, iterations: int) -> np.ndarray:
    """RANSAC's sample indices among ``m`` matches as one ``(2, iterations) int64`` array,
    ``i`` then ``j`` (``i != j``): the draws of a generator started at ``seed``, which depend
    only on ``m`` and ``iterations``, so they are kept per thread (read-only)."""
    cache = getattr(_RNGS, "draws", None)
    if cache is None:
        cache = _RNGS.draws = {}
    key = (seed, m, iterations)
    hit = cache.get(key)
    if hit is None:
        rng = _ransac_rng(seed)
        i = rng.integers(m, size=iterations)
        j = (i + 1 + rng.integers(m - 1, size=iterations)) % m
        hit = np.stack((i, j))
        hit.flags.writeable = False
        if len(cache) >= 4096:
            cache.clear()
        cache[key] = hit
    return hit


def _ransac_pairs(seed: int, m: int, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_ransac_draws` as ``(i, j)``, ``(iterations,) int64`` each (read-only views)."""
    draws = _ransac_draws(seed, m, iterations)
    return draws[0], draws[1]


_BLOCK = 10  # RANSAC's first draws when it stops adaptively (MatchParams.confidence), then 3x as many each time
_NBINS = len(_PREV_BIN)


def _enough(scored: int, frac: float, log_miss: float) -> bool:
    """Whether ``scored`` hypotheses are enough at the best inlier fraction ``frac`` so far
    for the adaptive stop (``log_miss``: ``log(1 - confidence)``; :class:`MatchParams`)."""
    return frac >= 1.0 or (frac > 0 and scored >= log_miss / math.log(1.0 - frac * frac))


def _hypotheses(xab: np.ndarray, i: np.ndarray, j: np.ndarray, peak: float,
                p: MatchParams) -> tuple[np.ndarray, np.ndarray] | None:
    """RANSAC's rigid hypotheses from the samples ``(i, j)`` of the ``(m, 4)`` matches
    ``xab`` (x, y in A, then in B) that pass the sample tests (length, scale, rotation near
    the orientation ``peak``): the ``(h, 3)`` rows ``[c, -s, tx]`` and ``[s, c, ty]`` of
    each ``[R | t]`` (None when no sample passes). One pair's case of
    :func:`_hypotheses_many` (a scalar peak broadcasts: the same arithmetic)."""
    out = _hypotheses_many(xab, i, j, np.asarray(peak, np.float64), p)
    return None if out is None else (out[0], out[1])


def _ransac_best(xab: np.ndarray, i: np.ndarray, j: np.ndarray, peak: float, xa1: np.ndarray, xb: np.ndarray,
                   weight: np.ndarray, p: MatchParams) -> tuple[np.ndarray | None, int]:
    """``(m,) bool`` the inliers of RANSAC's best hypothesis (the first of the highest
    weighted inlier count) and how many hypotheses were scored; None when no draw makes a
    hypothesis. With ``p.confidence`` 0 every draw ``(i, j)`` is scored at once; otherwise
    the draws are taken in blocks (the first ``_BLOCK``, then up to 3, 9, ... times as many
    in all) until as many hypotheses have been scored as ``p.confidence`` asks for the best
    inlier fraction so far (:class:`MatchParams`)."""
    m = xa1.shape[1]
    w = weight + 1e-6
    adaptive = p.confidence > 0
    log_miss = math.log(1.0 - p.confidence) if adaptive else 0.0
    tol2 = p.inlier_px**2
    best_count, best_inliers, scored = -1.0, 0, 0
    best_mask: np.ndarray | None = None
    b0, b1 = 0, (_BLOCK if adaptive else len(i))
    while b0 < len(i):
        hyp = _hypotheses(xab, i[b0:b1], j[b0:b1], peak, p)
        b0, b1 = b1, 3 * b1
        if hyp is None:
            continue
        rows_x, rows_y = hyp
        h = len(rows_x)
        # Residuals of every hypothesis at every match, in scratch buffers and in place.
        rx = np.matmul(rows_x, xa1, out=_scratch("rx", (h, m), np.float64))
        rx -= xb[:, 0]
        ry = np.matmul(rows_y, xa1, out=_scratch("ry", (h, m), np.float64))
        ry -= xb[:, 1]
        np.multiply(rx, rx, out=rx)
        np.multiply(ry, ry, out=ry)
        rx += ry
        inl = np.less_equal(rx, tol2, out=_scratch("inl", (h, m), np.bool_))
        counts = inl @ w
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_count, best_mask = float(counts[k]), inl[k].copy()  # the scratch is reused by the next block
            best_inliers = int(np.count_nonzero(best_mask))
        scored += h
        if adaptive and _enough(scored, best_inliers / m, log_miss):
            break
    return best_mask, scored


_RNGS = threading.local()

_SCRATCH = threading.local()


def _scratch(name: str, shape: tuple[int, int], dtype: type) -> np.ndarray:
    """A C-contiguous ``shape`` array of ``dtype`` (contents undefined) over a buffer kept
    per thread and name, grown as needed: the local score's large temporaries (a few
    hundred kB in mode 4), valid until the thread's next call for the same name."""
    bufs = getattr(_SCRATCH, "bufs", None)
    if bufs is None:
        bufs = _SCRATCH.bufs = {}
    size = shape[0] * shape[1]
    buf = bufs.get(name)
    if buf is None or buf.size < size or buf.dtype != dtype:
        buf = bufs[name] = np.empty(max(size, 1), dtype)
    return buf[:size].reshape(shape)


def local_score(a: FloorDescriptor, b: FloorDescriptor, params: MatchParams | None = None,
                min_score: float = 0.0) -> MatchResult:
    """Match descriptor ``a`` against ``b`` (same mode) and score the geometric inliers.

    ``min_score``: a pair whose score cannot reach it is dismissed after step 1
    (``BELOW_MIN_SCORE``, score 0) without the geometric check. The score sums, over a
    subset of the descriptor matches, a weight each match has before any geometry, so
    the sum over all matches bounds it: nothing that could reach ``min_score`` is lost.
    """
    return Matcher(a, params).score(b, min_score)


class Matcher:
    """:func:`local_score` of one descriptor ``a`` against many: ``a``'s side of the
    descriptor distance (its trits as floats and their norms) is prepared once."""

    def __init__(self, a: FloorDescriptor, params: MatchParams | None = None) -> None:
        self.a = a
        self.params = params or MatchParams()
        self._aug = _augmented_a(a) if len(a) >= 2 else None
        self._norm = a.nonzero_trits()

    def score(self, b: FloorDescriptor | PartialDescriptor, min_score: float = 0.0) -> MatchResult:
        """``local_score(a, b, params, min_score)``; ``b`` may be a
        :class:`~robotd.floor.descriptor.PartialDescriptor`, whose positions are then decoded
        only if the pair passes the ``min_score`` bound (the same result as for ``b.full()``)."""
        return _score(self.a, b, self.params, self._aug, self._norm, min_score)

    def score_many(self, bs: list[FloorDescriptor | PartialDescriptor],
                   min_score: float = 0.0) -> list[MatchResult | DescriptorError]:
        """``[self.score(b, min_score) for b in bs]``, the same results bit for bit, the
        pairs' per-match work done for all of them at once (fewer, larger array operations:
        a query's few candidates cost less than one by one). A read-back descriptor whose
        positions do not decode gives the :class:`~robotd.base.errors.DescriptorError`
        :meth:`score` would raise, in its place (the others are scored)."""
        return _score_many(self.a, list(bs), self.params, self._aug, self._norm, min_score)


def _score(a: FloorDescriptor, b: FloorDescriptor | PartialDescriptor, p: MatchParams, aug_a: np.ndarray | None,
           norm_a: np.ndarray, min_score: float) -> MatchResult:
    if a.length != b.length:
        raise ValueError(f"descriptors of different lengths ({a.length} and {b.length} trits): modes differ")
    if len(a) < 2 or len(b) < 2 or aug_a is None:
        return _dismissed(TOO_FEW_FEATURES)
    # Squared distance of ternary vectors: |ta|^2 + |tb|^2 - 2 ta.tb, where |t|^2 counts the
    # non-zero trits. |ta|^2 is the same along a row, so the search needs only the rest,
    # |tb|^2 - 2 ta.tb = [ta, 1] . [-2 tb, |tb|^2]: one matrix product (integers, exact in
    # float32), which is most of the time in mode 6.
    aug_b = _augmented_b(b)
    # Into a scratch buffer of this thread (the same product, BLAS's, written in place):
    # a fresh array of this size is mapped and faulted in afresh on every pair.
    dist = np.matmul(aug_a, aug_b.T, out=_scratch("dist", (len(aug_a), len(aug_b)), np.float32))
    nn = np.argmin(dist, axis=1)
    flat = dist.reshape(-1)  # the nearest's entries by flat index: cheaper than a 2-D gather
    at = np.arange(0, flat.size, dist.shape[1]) + nn
    d1 = flat.take(at) + norm_a
    flat.put(at, np.inf)
    d2 = dist.min(axis=1) + norm_a
    d1 *= 1.0 / a.length
    d2 *= 1.0 / a.length
    keep = (d1 <= p.max_distance) & (d1 < p.ratio * p.ratio * d2)
    ia = np.flatnonzero(keep)
    ib, dm = nn[ia], d1[ia]
    if len(ia) < p.min_matches:
        return _dismissed(TOO_FEW_MATCHES, len(ia))
    # The bound, with room for the rounding of a sum taken in another order.
    if min_score > 0 and float(np.maximum(0.0, 1.0 - dm / p.weight_distance).sum()) * (1 + 1e-6) + 1e-6 < min_score:
        return _dismissed(BELOW_MIN_SCORE, len(ia))
    # b's positions and orientations, read from here on (a read-back descriptor's decoded now)
    xy_b, angle_b = b.positions() if isinstance(b, PartialDescriptor) else (b.xy_px, b.angle_rad)
    # Step 2: dominant orientation change (histogram over the 2**ANGLE_BITS levels).
    dth = (angle_b[ib] - a.angle_rad[ia]) % (2 * math.pi)
    nbins = len(_PREV_BIN)
    hist = np.bincount((dth * (nbins / (2 * math.pi))).astype(np.intp) % nbins, minlength=nbins).astype(float)
    hist = hist + 0.5 * (hist[_PREV_BIN] + hist[_NEXT_BIN])
    peak = (np.argmax(hist) + 0.5) * (2 * math.pi / nbins)
    near = np.abs(wrap_angle(dth - peak)) <= p.angle_tol_rad + math.pi / nbins
    ka, kb, kd = ia[near], ib[near], dm[near]
    n_matches = len(ia)
    if len(ka) < p.min_inliers:
        return _dismissed(NO_GEOMETRIC_CONSISTENCY, n_matches)
    xa, xb = a.xy_px[ka].astype(np.float64), xy_b[kb].astype(np.float64)
    weight = np.maximum(0.0, 1.0 - kd / p.weight_distance)
    # Step 3: RANSAC over 2-point rigid hypotheses.
    m = len(ka)
    i, j = _ransac_pairs(p.seed, m, p.iterations)
    xab = np.concatenate([xa, xb], axis=1)  # (m, 4): x, y in A, then in B
    # Residuals of every hypothesis at every match: rows of [R | t] times [x; y; 1].
    xa1 = np.empty((3, m))
    xa1[:2] = xa.T
    xa1[2] = 1.0
    mask = _ransac_best(xab, i, j, peak, xa1, xb, weight, p)[0]
    if mask is None:
        return _dismissed(NO_GEOMETRIC_CONSISTENCY, n_matches)
    return _refined(a, ia, ib, a.xy_px[ia].astype(np.float64), xy_b[ib].astype(np.float64),
                    np.maximum(0.0, 1.0 - dm / p.weight_distance), xy_b, np.flatnonzero(near)[mask], n_matches, p)


def _refined(a: FloorDescriptor, ia: np.ndarray, ib: np.ndarray, fa: np.ndarray, fb: np.ndarray, wm: np.ndarray,
             xy_b: np.ndarray, sel: np.ndarray, n_matches: int, p: MatchParams) -> MatchResult:
    """The end of a local score: the rigid fit refined on all ``n_matches`` descriptor
    matches ``(ia, ib)`` (``fa``, ``fb``: their points as float64; ``wm``: their weights in
    the score; not only those near the orientation peak) from RANSAC's inliers ``sel``
    (rows of the matches), twice, and the result (:func:`_refined_many` of one pair)."""
    assert n_matches == len(ia)
    return _refined_many(a, ia, ib, fa, fb, wm, [(0, 0, n_matches, sel, xy_b)], p)[0][1]


_PAD_NORM = np.float32(1e30)  # a padding row's |tb|^2: farther than any keypoint, finite


def _score_many(a: FloorDescriptor, bs: list[FloorDescriptor | PartialDescriptor], p: MatchParams,
                aug_a: np.ndarray | None, norm_a: np.ndarray,
                min_score: float) -> list[MatchResult | DescriptorError]:
    """``[_score(a, b, p, aug_a, norm_a, min_score) for b in bs]``, the same results bit
    for bit, with the per-pair work done for all pairs at once wherever that leaves every
    value as it was: one product for all the descriptor distances (integers, exact in
    float32 in any order), the nearest neighbours, histograms, RANSAC's samples and the
    residuals' element-wise steps over the pairs' matches stacked (each pair's rows at an
    offset). What sums floats in an order that depends on the array's shape stays one
    call per pair, on arrays shaped as :func:`_score`'s: the bound's sum, the hypotheses'
    products and weighted counts, and the refinement. A read-back descriptor whose
    positions do not decode gives its :class:`DescriptorError` in its place."""
    out: list[MatchResult | DescriptorError | None] = [None] * len(bs)
    for b in bs:
        if a.length != b.length:
            raise ValueError(f"descriptors of different lengths ({a.length} and {b.length} trits): modes differ")
    live = [c for c, b in enumerate(bs) if len(a) >= 2 and len(b) >= 2 and aug_a is not None]
    for c in set(range(len(bs))) - set(live):
        out[c] = _dismissed(TOO_FEW_FEATURES)
    if not live:
        return out  # type: ignore[return-value]
    assert aug_a is not None
    n_live = len(live)
    na, width = aug_a.shape
    nbs = [len(bs[c]) for c in live]
    nbmax = max(nbs)
    # Step 1 for every pair: each candidate's side in its block of rows, padded to the
    # longest with rows no keypoint is near (never the nearest, nor the second nearest:
    # every candidate has at least two real rows).
    big = _scratch("aug_many", (n_live * nbmax, width), np.float32)
    for r, c in enumerate(live):
        lo = r * nbmax
        _augmented_b(bs[c], big[lo: lo + nbs[r]])
        if nbs[r] < nbmax:
            big[lo + nbs[r]: lo + nbmax] = 0.0
            big[lo + nbs[r]: lo + nbmax, -1] = _PAD_NORM
    dist = np.matmul(aug_a, big.T, out=_scratch("dist", (na, n_live * nbmax), np.float32)).reshape(na, n_live, nbmax)
    nn = np.argmin(dist, axis=2)
    flat = dist.reshape(-1)  # the nearest's entries by flat index, as in _score
    at = np.arange(0, flat.size, nbmax).reshape(na, n_live) + nn
    d1 = flat.take(at) + norm_a[:, None]
    flat.put(at, np.inf)
    d2 = dist.min(axis=2) + norm_a[:, None]
    d1 *= 1.0 / a.length
    d2 *= 1.0 / a.length
    keep = (d1 <= p.max_distance) & (d1 < p.ratio * p.ratio * d2)
    seg, ia = np.nonzero(keep.T)  # by pair, then by A's keypoint: each pair's matches as _score orders them
    at = ia * n_live
    at += seg
    ib, dm = nn.take(at), d1.take(at)  # nn[ia, seg], d1[ia, seg]
    n_of = np.bincount(seg, minlength=n_live).tolist()
    starts = [0, *itertools.accumulate(n_of)]
    bound = np.maximum(0.0, 1.0 - dm / p.weight_distance) if min_score > 0 else None
    go: list[int] = []  # rows of live that go on to the geometric check
    xys, angles = [], []
    for r, c in enumerate(live):
        n = n_of[r]
        if n < p.min_matches:
            out[c] = _dismissed(TOO_FEW_MATCHES, n)
            continue
        if bound is not None and float(_add_reduce(bound[starts[r]: starts[r + 1]])) * (1 + 1e-6) + 1e-6 < min_score:
            out[c] = _dismissed(BELOW_MIN_SCORE, n)
            continue
        b = bs[c]
        if isinstance(b, PartialDescriptor):
            try:
                xy_b, angle_b = b.positions()
            except DescriptorError as exc:
                out[c] = exc
                continue
        else:
            xy_b, angle_b = b.xy_px, b.angle_rad
        go.append(r)
        xys.append(xy_b)
        angles.append(angle_b)
    if not go:
        return out  # type: ignore[return-value]
    n_go = len(go)
    # The matches of the pairs that go on, stacked; s: their pair, 0 .. n_go - 1.
    slot = np.full(n_live, -1, np.intp)
    slot[go] = np.arange(n_go)
    s_all = slot[seg]
    take = s_all >= 0
    if not take.all():
        ia, ib, dm, s_all = ia[take], ib[take], dm[take], s_all[take]
    b_off = np.zeros(n_go, np.intp)
    np.cumsum([len(x) for x in xys[:-1]], out=b_off[1:])
    xy_all = np.concatenate(xys) if n_go > 1 else xys[0]
    angle_all = np.concatenate(angles) if n_go > 1 else angles[0]
    ib_all = ib + b_off[s_all]
    # Step 2 for every pair: the histograms side by side.
    dth = (angle_all[ib_all] - a.angle_rad[ia]) % (2 * math.pi)
    nbins = _NBINS
    bins = (dth * (nbins / (2 * math.pi))).astype(np.intp) % nbins
    bins += nbins * s_all
    hist = np.bincount(bins, minlength=nbins * n_go).reshape(n_go, nbins).astype(float)
    hist = hist + 0.5 * (hist.take(_PREV_BIN, axis=1) + hist.take(_NEXT_BIN, axis=1))
    peaks = (np.argmax(hist, axis=1) + 0.5) * (2 * math.pi / nbins)
    near = np.abs(wrap_angle(dth - peaks[s_all])) <= p.angle_tol_rad + math.pi / nbins
    m_of = np.bincount(s_all[near], minlength=n_go).tolist()
    n_match = [n_of[r] for r in go]
    go_starts = [0, *itertools.accumulate(n_match)]
    check = [g for g in range(n_go) if m_of[g] >= p.min_inliers]
    for g in range(n_go):
        if m_of[g] < p.min_inliers:
            out[live[go[g]]] = _dismissed(NO_GEOMETRIC_CONSISTENCY, n_match[g])
    if not check:
        return out  # type: ignore[return-value]
    # Step 3 for the pairs checked: their matches near the peak, stacked (offset per pair).
    inc = near & np.isin(s_all, check) if len(check) < n_go else near
    fa_all, fb_all = a.xy_px.take(ia, axis=0).astype(np.float64), xy_all.take(ib_all, axis=0).astype(np.float64)
    # The weights as _score computes them, over every match (the bound's when there is one).
    if bound is None:
        wm_all = np.maximum(0.0, 1.0 - dm / p.weight_distance)
    else:
        wm_all = bound if bound.shape == dm.shape else bound[take]
    xa, xb, weight = fa_all.compress(inc, axis=0), fb_all.compress(inc, axis=0), wm_all[inc]
    w_all = weight + 1e-6
    xab = np.concatenate([xa, xb], axis=1)
    n_check = len(check)
    ms = [m_of[g] for g in check]
    m_off = [0, *itertools.accumulate(ms)]
    # Each pair's [x; y; 1] as the C-ordered (3, m) block _score builds, one after the other.
    xa1_all = np.empty(3 * m_off[-1])
    for q in range(n_check):
        blk = xa1_all[3 * m_off[q]: 3 * m_off[q + 1]].reshape(3, ms[q])
        blk[:2] = xa[m_off[q]: m_off[q + 1]].T
        blk[2] = 1.0
    draws = np.stack([_ransac_draws(p.seed, m, p.iterations) for m in ms])  # (pairs, 2, iterations)
    draws += np.asarray(m_off[:-1], np.intp)[:, None, None]
    peak_of = peaks[check]
    masks = _ransac_many(xab, draws, peak_of, xa1_all, xb, w_all, ms, m_off, p)
    near_rows = inc.nonzero()[0]
    todo = []  # (result slot, first and last match row, RANSAC's inliers as rows of the pair's matches)
    for q, g in enumerate(check):
        c = live[go[g]]
        if masks[q] is None:
            out[c] = _dismissed(NO_GEOMETRIC_CONSISTENCY, n_match[g])
            continue
        lo, hi = go_starts[g], go_starts[g + 1]
        sel = near_rows[m_off[q]: m_off[q + 1]][masks[q]]
        sel -= lo
        todo.append((c, lo, hi, sel, xys[g]))
    for c, result in _refined_many(a, ia, ib, fa_all, fb_all, wm_all, todo, p):
        out[c] = result
    return out  # type: ignore[return-value]


def _refined_many(a: FloorDescriptor, ia: np.ndarray, ib: np.ndarray, fa_all: np.ndarray, fb_all: np.ndarray,
                  wm_all: np.ndarray, todo: list[tuple[int, int, int, np.ndarray, np.ndarray]],
                  p: MatchParams) -> list[tuple[int, MatchResult]]:
    """The end of several pairs' local scores (:func:`_refined` is one pair's): ``ia``, ``ib``,
    ``fa_all``, ``fb_all``, ``wm_all`` their descriptor matches stacked, and per pair in
    ``todo`` its result slot, its rows ``lo:hi`` of the stack, RANSAC's inliers (rows of the
    pair's matches) and its keypoints' positions. Each fit and each residual product is
    one call per pair; the residuals' element-wise
    steps (the translation, the difference, the squares and their sums over x and y, the
    test) run over the stack at once."""
    tol2 = p.inlier_px**2
    sels = [t[3] for t in todo]
    transforms: list[np.ndarray | None] = [None] * len(todo)
    active = list(range(len(todo)))
    res_all = np.zeros_like(fa_all)  # finite everywhere: rows of pairs done are computed on, unread
    t_all = np.zeros_like(fa_all)
    for _ in range(2):
        active = [q for q in active if len(sels[q]) >= 2]
        if not active:
            break
        for q in active:
            lo, hi = todo[q][1], todo[q][2]
            fa, fb = fa_all[lo:hi], fb_all[lo:hi]
            transform = transforms[q] = _rigid(fa.take(sels[q], axis=0), fb.take(sels[q], axis=0))
            np.matmul(fa, transform[:, :2].T, out=res_all[lo:hi])
            t_all[lo:hi] = transform[:, 2]
        lo_all, hi_all = todo[active[0]][1], todo[active[-1]][2]  # rows between belong to pairs done: unused
        res = res_all[lo_all:hi_all]
        res += t_all[lo_all:hi_all]
        res -= fb_all[lo_all:hi_all]
        np.multiply(res, res, out=res)
        inl = _add_reduce(res, axis=1) <= tol2
        still = []
        for q in active:
            _c, lo, hi, _s, _xy = todo[q]
            fitted = sels[q]
            sel = sels[q] = inl[lo - lo_all: hi - lo_all].nonzero()[0]
            if not (len(sel) == len(fitted) and sel.tobytes() == fitted.tobytes()):
                still.append(q)  # not yet a fixed point (where a further step would fit these inliers again)
        active = still
    results = []
    for q, (c, lo, hi, _s, xy_b) in enumerate(todo):
        sel, fit = sels[q], transforms[q]
        if len(sel) < p.min_inliers or fit is None:
            results.append((c, _dismissed(NO_GEOMETRIC_CONSISTENCY, hi - lo)))
            continue
        ia_sel, ib_sel = ia[lo:hi][sel], ib[lo:hi][sel]
        results.append((c, MatchResult(float(_add_reduce(wm_all[lo:hi][sel])), hi - lo, len(sel),
                                       ia_sel.astype(np.int64, copy=False), ib_sel.astype(np.int64, copy=False),
                                       a.xy_px.take(ia_sel, axis=0), xy_b.take(ib_sel, axis=0), fit,
                                       MatchReason.OK)))
    return results


def _ransac_many(xab: np.ndarray, draws: np.ndarray, peaks: np.ndarray, xa1_all: np.ndarray, xb: np.ndarray,
                 w_all: np.ndarray, ms: list[int], m_off: list[int], p: MatchParams) -> list[np.ndarray | None]:
    """:func:`_ransac_best`'s masks for several pairs at once: ``xab``, ``xb``, ``w_all``
    their matches stacked (pair ``q``'s rows ``m_off[q]:m_off[q + 1]``), ``draws``
    ``(pairs, 2, iterations)`` their samples as rows of the stack, ``xa1_all`` each pair's
    ``(3, m)`` block in turn. Each pair is scored in the same blocks and stops where
    :func:`_ransac_best` does; the hypotheses' element-wise steps run over every pair's at
    once, the products and counts per pair (as :func:`_ransac_best` shapes them)."""
    n = len(ms)
    adaptive = p.confidence > 0
    log_miss = math.log(1.0 - p.confidence) if adaptive else 0.0
    tol2 = p.inlier_px**2
    best_count = [-1.0] * n
    best_inliers = [0] * n
    scored = [0] * n
    best: list[np.ndarray | None] = [None] * n
    active = list(range(n))
    iterations = draws.shape[2]
    b0, b1 = 0, (_BLOCK if adaptive else iterations)
    while b0 < iterations and active:
        blk = draws[:, :, b0:b1] if len(active) == n else draws[active, :, b0:b1]
        hyp_of = np.repeat(np.asarray(active, np.intp), blk.shape[2])
        b0, b1 = b1, 3 * b1
        hyp = _hypotheses_many(xab, blk[:, 0].ravel(), blk[:, 1].ravel(), peaks[hyp_of], p)
        if hyp is None:
            continue
        rows_x, rows_y, ok = hyp
        h_of = np.bincount(hyp_of[ok], minlength=n).tolist()
        sizes = [h_of[q] * ms[q] for q in active]
        total = sum(sizes)
        # Each pair's residuals in its own C-ordered (h, m) block of one buffer, by the
        # product _ransac_best makes (the same shapes: the same sums); the rest at once.
        rx_all = _scratch("rx", (1, total), np.float64)[0]
        ry_all = _scratch("ry", (1, total), np.float64)[0]
        e0, h0 = 0, 0
        spans = []
        for q, size in zip(active, sizes):
            h, m = h_of[q], ms[q]
            spans.append((e0, h, m))
            if h:
                xa1 = xa1_all[3 * m_off[q]: 3 * m_off[q + 1]].reshape(3, m)
                rx = np.matmul(rows_x[h0: h0 + h], xa1, out=rx_all[e0: e0 + size].reshape(h, m))
                rx -= xb[m_off[q]: m_off[q + 1], 0]
                ry = np.matmul(rows_y[h0: h0 + h], xa1, out=ry_all[e0: e0 + size].reshape(h, m))
                ry -= xb[m_off[q]: m_off[q + 1], 1]
            e0 += size
            h0 += h
        np.multiply(rx_all, rx_all, out=rx_all)
        np.multiply(ry_all, ry_all, out=ry_all)
        rx_all += ry_all
        inl_all = np.less_equal(rx_all, tol2, out=_scratch("inl", (1, total), np.bool_)[0])
        still = []
        for q, (e0, h, m) in zip(active, spans):
            if h:
                inl = inl_all[e0: e0 + h * m].reshape(h, m)
                counts = inl @ w_all[m_off[q]: m_off[q + 1]]
                k = int(np.argmax(counts))
                if counts[k] > best_count[q]:
                    best_count[q], best[q] = float(counts[k]), inl[k].copy()
                    best_inliers[q] = int(np.count_nonzero(inl[k]))
                scored[q] += h
                if adaptive and _enough(scored[q], best_inliers[q] / m, log_miss):
                    continue
            still.append(q)
        active = still
    return best


def _hypotheses_many(xab: np.ndarray, i: np.ndarray, j: np.ndarray, peak: np.ndarray,
                     p: MatchParams) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """:func:`_hypotheses` of several pairs' samples at once (``peak`` per sample, or one
    for all): the rows of the samples that pass, and the ``(len(i),) bool`` mask of those."""
    xi, xj = xab.take(i, axis=0), xab.take(j, axis=0)
    v = xj - xi
    lab = np.hypot(v[:, 0::2], v[:, 1::2])
    la, lb = lab[:, 0], lab[:, 1]
    ang = np.arctan2(v[:, 1::2], v[:, 0::2])
    phi = ang[:, 1] - ang[:, 0]
    ok = (la >= p.min_sample_px) & (np.abs(np.log(np.maximum(lb, 1e-9) / np.maximum(la, 1e-9))) <= p.max_log_scale)
    ok &= np.abs(wrap_angle(phi - peak)) <= p.angle_tol_rad + math.pi / _NBINS
    if not np.any(ok):
        return None
    i, j, phi = i[ok], j[ok], phi[ok]
    h = len(phi)
    # C-ordered as np.stack(..., axis=1) gives them (the products see the same layout).
    rows_x, rows_y = np.empty((h, 3)), np.empty((h, 3))
    c, s = np.cos(phi, out=rows_x[:, 0]), np.sin(phi, out=rows_y[:, 0])
    np.negative(s, out=rows_x[:, 1])
    rows_y[:, 1] = c
    mid = xab.take(i, axis=0)
    mid += xab.take(j, axis=0)
    mid *= 0.5  # sample midpoints: x, y in A, then in B
    np.subtract(mid[:, 2], c * mid[:, 0] - s * mid[:, 1], out=rows_x[:, 2])
    np.subtract(mid[:, 3], s * mid[:, 0] + c * mid[:, 1], out=rows_y[:, 2])
    return rows_x, rows_y, ok


def global_score(a: FloorDescriptor, b: FloorDescriptor) -> float:
    """Similarity of the global descriptors in [0, 1]: ``1 - hamming / bits``."""
    ga, gb = np.asarray(a.global_bits, np.uint8), np.asarray(b.global_bits, np.uint8)
    if ga.shape != gb.shape:
        raise ValueError(f"global descriptors of different sizes ({ga.size} and {gb.size} bytes): modes differ")
    if ga.size == 0:
        return 0.0
    return 1.0 - float(np.bitwise_count(ga ^ gb).sum()) / (8 * ga.size)
