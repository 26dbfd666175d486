"""The local score's fast paths give exactly the results of the implementation they
replaced: a frozen copy of that ``_score`` (kept here only) against
:class:`robotd.floor.match.Matcher` on descriptors of rendered floor views (overlapping,
turned, unrelated; two modes; with and without a ``min_score``): the same reason, score,
match and inlier counts, inlier indices, matched points and transform, bit for bit."""

from __future__ import annotations

import math
import struct
import zlib

import cv2
import numpy as np
import pytest
import skimage.data

from robotd.base.errors import DescriptorError
from robotd.base.geometry import wrap_angle
from robotd.floor.descriptor import FloorDescriptor, decode, decode_local, extract
from robotd.floor.match import (BELOW_MIN_SCORE, NO_GEOMETRIC_CONSISTENCY, TOO_FEW_FEATURES, TOO_FEW_MATCHES,
                                Matcher, MatchParams, MatchReason, MatchResult, _augmented, _dismissed,
                                _ransac_pairs, _ransac_rng, _rigid, _augmented_a, _augmented_b)
from sim.world.floor import Floor

_PREV_BIN = np.roll(np.arange(32), 1)
_NEXT_BIN = np.roll(np.arange(32), -1)


def _old_score(a: FloorDescriptor, b: FloorDescriptor, p: MatchParams, aug_a: np.ndarray | None,
           norm_a: np.ndarray, min_score: float) -> MatchResult:
    if a.length != b.length:
        raise ValueError(f"descriptors of different lengths ({a.length} and {b.length} trits): modes differ")
    if len(a) < 2 or len(b) < 2 or aug_a is None:
        return _dismissed(TOO_FEW_FEATURES)
    # Squared distance of ternary vectors: |ta|^2 + |tb|^2 - 2 ta.tb, where |t|^2 counts the
    # non-zero trits. |ta|^2 is the same along a row, so the search needs only the rest,
    # |tb|^2 - 2 ta.tb = [ta, 1] . [-2 tb, |tb|^2]: one matrix product (integers, exact in
    # float32), which is most of the time in mode 6.
    dist = aug_a @ _augmented(b, -2.0, b.nonzero_trits()).T
    rows = np.arange(len(a))
    nn = np.argmin(dist, axis=1)
    d1 = dist[rows, nn] + norm_a
    dist[rows, nn] = np.inf
    d2 = dist.min(axis=1) + norm_a
    d1 *= 1.0 / a.length
    d2 *= 1.0 / a.length
    keep = (d1 <= p.max_distance) & (d1 < p.ratio * p.ratio * d2)
    ia, ib, dm = rows[keep], nn[keep], d1[keep]
    if len(ia) < p.min_matches:
        return _dismissed(TOO_FEW_MATCHES, len(ia))
    # The bound, with room for the rounding of a sum taken in another order.
    if min_score > 0 and float(np.maximum(0.0, 1.0 - dm / p.weight_distance).sum()) * (1 + 1e-6) + 1e-6 < min_score:
        return _dismissed(BELOW_MIN_SCORE, len(ia))
    # Step 2: dominant orientation change (histogram over the 2**ANGLE_BITS levels).
    dth = (b.angle_rad[ib] - a.angle_rad[ia]) % (2 * math.pi)
    nbins = len(_PREV_BIN)
    hist = np.bincount((dth * (nbins / (2 * math.pi))).astype(np.intp) % nbins, minlength=nbins).astype(float)
    hist = hist + 0.5 * (hist[_PREV_BIN] + hist[_NEXT_BIN])
    peak = (np.argmax(hist) + 0.5) * (2 * math.pi / nbins)
    near = np.abs(wrap_angle(dth - peak)) <= p.angle_tol_rad + math.pi / nbins
    ka, kb, kd = ia[near], ib[near], dm[near]
    n_matches = len(ia)
    if len(ka) < p.min_inliers:
        return _dismissed(NO_GEOMETRIC_CONSISTENCY, n_matches)
    xa, xb = a.xy_px[ka].astype(np.float64), b.xy_px[kb].astype(np.float64)
    weight = np.maximum(0.0, 1.0 - kd / p.weight_distance)
    # Step 3: RANSAC over 2-point rigid hypotheses.
    rng = _ransac_rng(p.seed)
    m = len(ka)
    i = rng.integers(m, size=p.iterations)
    j = (i + 1 + rng.integers(m - 1, size=p.iterations)) % m
    va, vb = xa[j] - xa[i], xb[j] - xb[i]
    la, lb = np.hypot(va[:, 0], va[:, 1]), np.hypot(vb[:, 0], vb[:, 1])
    phi = np.arctan2(vb[:, 1], vb[:, 0]) - np.arctan2(va[:, 1], va[:, 0])
    ok = (la >= p.min_sample_px) & (np.abs(np.log(np.maximum(lb, 1e-9) / np.maximum(la, 1e-9))) <= p.max_log_scale)
    ok &= np.abs(wrap_angle(phi - peak)) <= p.angle_tol_rad + math.pi / nbins
    if not np.any(ok):
        return _dismissed(NO_GEOMETRIC_CONSISTENCY, n_matches)
    i, j, phi = i[ok], j[ok], phi[ok]
    c, s = np.cos(phi), np.sin(phi)
    ca, cb = 0.5 * (xa[i] + xa[j]), 0.5 * (xb[i] + xb[j])
    tx = cb[:, 0] - (c * ca[:, 0] - s * ca[:, 1])
    ty = cb[:, 1] - (s * ca[:, 0] + c * ca[:, 1])
    # Residuals of every hypothesis at every match: rows of [R | t] times [x; y; 1].
    xa1 = np.vstack([xa.T, np.ones(m)])
    rx = np.stack([c, -s, tx], axis=1) @ xa1
    rx -= xb[:, 0]
    ry = np.stack([s, c, ty], axis=1) @ xa1
    ry -= xb[:, 1]
    inl = rx * rx + ry * ry <= p.inlier_px**2
    best = int(np.argmax(inl @ (weight + 1e-6)))
    mask = inl[best]
    # Refine on all descriptor matches (not only those near the orientation peak).
    fa, fb = a.xy_px[ia].astype(np.float64), b.xy_px[ib].astype(np.float64)
    sel = np.flatnonzero(near)[mask]
    transform = None
    for _ in range(2):
        if len(sel) < 2:
            break
        transform = _rigid(fa[sel], fb[sel])
        res = fa @ transform[:, :2].T + transform[:, 2] - fb
        sel = np.flatnonzero((res * res).sum(1) <= p.inlier_px**2)
    if len(sel) < p.min_inliers or transform is None:
        return _dismissed(NO_GEOMETRIC_CONSISTENCY, n_matches)
    score = float(np.maximum(0.0, 1.0 - dm[sel] / p.weight_distance).sum())
    return MatchResult(score, n_matches, len(sel), ia[sel].astype(np.int64), ib[sel].astype(np.int64),
                       a.xy_px[ia[sel]], b.xy_px[ib[sel]], transform, MatchReason.OK)



W, H = 640, 480


def _view(texture: np.ndarray, theta_rad: float, centre: tuple[float, float]) -> np.ndarray:
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    m = np.array([[c, -s, 0.0], [s, c, 0.0]])
    m[:, 2] = np.array([(W - 1) / 2, (H - 1) / 2]) - m[:, :2] @ np.asarray(centre)
    return cv2.warpAffine(texture, m, (W, H), flags=cv2.INTER_LINEAR)


@pytest.fixture(scope="module")
def views() -> list[np.ndarray]:
    """Eight views: five of one quilted floor (shifted and turned), three of two others."""
    tex = [Floor.from_photos([getattr(skimage.data, n)()], seed=70 + i).patch(0.0, 0.0, 1.2, 1.2)[0]
           for i, n in enumerate(("brick", "gravel", "grass"))]
    poses = [(0.0, (600.0, 600.0)), (0.2, (640.0, 590.0)), (-0.5, (560.0, 630.0)), (math.pi, (610.0, 600.0)),
             (1.3, (700.0, 660.0))]
    return ([_view(tex[0], th, c) for th, c in poses] + [_view(tex[1], 0.0, (600.0, 600.0)),
                                                          _view(tex[2], 0.4, (600.0, 600.0)),
                                                          _view(tex[2], 0.6, (630.0, 610.0))])


def _same(new: MatchResult, old: MatchResult) -> None:
    assert new.reason == old.reason
    assert new.score == old.score and new.n_matches == old.n_matches and new.n_inliers == old.n_inliers
    for f in ("inliers_a", "inliers_b", "xy_a", "xy_b"):
        x, y = getattr(new, f), getattr(old, f)
        assert x.dtype == y.dtype and np.array_equal(x, y), f
    assert (new.transform is None) == (old.transform is None)
    if old.transform is not None:
        assert new.transform is not None and np.array_equal(new.transform, old.transform)


@pytest.mark.parametrize("mode", [4, 6])
def test_matcher_equals_the_frozen_score(views: list[np.ndarray], mode: int) -> None:
    descs = [decode(extract(v, mode)) for v in views]
    p = MatchParams()
    reasons = []
    for a in descs:
        matcher = Matcher(a, p)
        for b in descs:
            for min_score in (0.0, 20.0, 60.0):
                old = _old_score(a, b, p, _augmented(a, 1.0, None), a.nonzero_trits(), min_score)
                _same(matcher.score(b, min_score), old)
                reasons.append(old.reason)
    # The comparison covers accepted pairs and each early dismissal, not one path only.
    assert MatchReason.OK in reasons and BELOW_MIN_SCORE in reasons
    assert {TOO_FEW_MATCHES, NO_GEOMETRIC_CONSISTENCY} & set(reasons)


def test_candidate_side_equals_the_augmented_trits(views: list[np.ndarray]) -> None:
    for mode in (1, 4, 6):
        d = decode(extract(views[1], mode))
        assert np.array_equal(_augmented_b(d), _augmented(d, -2.0, d.nonzero_trits()))


def test_query_side_equals_the_augmented_trits(views: list[np.ndarray]) -> None:
    for mode in (1, 4, 6):
        d = decode(extract(views[2], mode))
        got, want = _augmented_a(d), _augmented(d, 1.0, None)
        assert got.dtype == want.dtype == np.float32 and np.array_equal(got, want)
        assert set(np.unique(got[:, :-1]).tolist()) == {-1.0, 0.0, 1.0}


@pytest.mark.parametrize("m", [2, 3, 57, 186])
def test_ransac_pairs_are_the_seeded_draws(m: int) -> None:
    """The kept sample pairs are those a generator seeded afresh draws (as the previous
    ``_score`` drew them), also after other counts and seeds were asked for."""
    for seed in (0, 7):
        rng = np.random.default_rng(seed)
        i = rng.integers(m, size=100)
        j = (i + 1 + rng.integers(m - 1, size=100)) % m
        _ransac_pairs(seed, m + 1, 100)
        for _ in range(2):
            got_i, got_j = _ransac_pairs(seed, m, 100)
            assert np.array_equal(got_i, i) and np.array_equal(got_j, j)
            assert not np.any(got_i == got_j)


def test_too_few_features_unchanged() -> None:
    empty = decode(extract(np.zeros((H, W), np.uint8), 4))
    assert len(empty) < 2
    assert Matcher(empty).score(empty).reason == TOO_FEW_FEATURES


def _bad_positions(data: bytes) -> bytes:
    """``data`` with one more zero in the Rice unary parts, its checksum recomputed: every
    section but the positions' still reads (as tests/floor/test_readback.py forges it)."""
    b = bytearray(data)
    b[-1] = 0x00
    b[16:20] = struct.pack("<I", zlib.crc32(bytes(b[20:]), zlib.crc32(bytes(b[:16]))))
    return bytes(b)


@pytest.mark.parametrize("mode", [4, 6])
@pytest.mark.parametrize("confidence", [0.0, 0.99])
def test_score_many_equals_scoring_one_by_one(views: list[np.ndarray], mode: int, confidence: float) -> None:
    """``Matcher.score_many`` gives, pair for pair, what ``Matcher.score`` gives (and, at
    confidence 0, the frozen ``_score``), bit for bit, whatever else is in the batch: every
    view against every other, a descriptor without features, read-back descriptors (one
    whose positions do not decode, which gives its error in its place) and the batch cut
    into pieces of every size."""
    blobs = [extract(v, mode) for v in views] + [extract(np.zeros((H, W), np.uint8), mode)]
    descs = [decode(b) for b in blobs]
    p = MatchParams(confidence=confidence)
    reasons = set()
    for a in descs[:-1]:
        matcher = Matcher(a, p)
        for min_score in (0.0, 20.0, 60.0):
            want = [matcher.score(b, min_score) for b in descs]
            if confidence == 0.0:
                for w, b in zip(want, descs):
                    _same(w, _old_score(a, b, p, _augmented(a, 1.0, None), a.nonzero_trits(), min_score))
            reasons |= {w.reason for w in want}
            for size in (1, 2, 3, len(descs)):
                got = []
                for k in range(0, len(descs), size):
                    got += matcher.score_many(descs[k:k + size], min_score)
                assert len(got) == len(want)
                for g, w in zip(got, want):
                    assert isinstance(g, MatchResult)
                    _same(g, w)
            # Read back: the same results, and a forged positions code fails alone.
            parts = [decode_local(b) for b in blobs]
            forged = len(descs) // 2
            parts[forged] = decode_local(_bad_positions(blobs[forged]))
            got = matcher.score_many(parts, min_score)
            for i, (g, w) in enumerate(zip(got, want)):
                if i == forged and w.reason in (MatchReason.OK, NO_GEOMETRIC_CONSISTENCY):
                    assert isinstance(g, DescriptorError)  # its positions were needed
                else:
                    assert isinstance(g, MatchResult)
                    _same(g, w)
    assert {MatchReason.OK, BELOW_MIN_SCORE, TOO_FEW_FEATURES} <= reasons
    assert {TOO_FEW_MATCHES, NO_GEOMETRIC_CONSISTENCY} & reasons


def test_score_many_refuses_another_mode(views: list[np.ndarray]) -> None:
    a, b = decode(extract(views[0], 4)), decode(extract(views[1], 6))
    with pytest.raises(ValueError, match="lengths"):
        Matcher(a).score_many([a, b])
    assert Matcher(a).score_many([]) == []


@pytest.mark.parametrize("k", [1, 2, 3])
def test_a_query_scores_what_one_by_one_would(views: list[np.ndarray], k: int) -> None:
    """A query stopping at ``k`` loops scores its shortlist in batches: the same keyframes
    as scoring them one at a time until ``k`` reach ``min_score``, with the same results."""
    from robotd.floor.index import FloorIndex, IndexParams

    descs = [decode(extract(v, 4)) for v in views]
    index = FloorIndex(IndexParams(shortlist=len(descs)))
    for i, d in enumerate(descs):
        index.add(i, d)
    for q, query in enumerate(descs):
        for min_score in (5.0, 20.0):
            before = index.local_matches
            got = index.query(query, k=k, exclude_ids=[q], min_score=min_score)
            matcher, scored, reached = Matcher(query), [], 0
            for kf, _g in index.shortlist(query, exclude_ids=[q]):
                if reached >= k:
                    break
                r = matcher.score(descs[kf], min_score)
                scored.append((kf, r))
                reached += r.score >= min_score
            assert index.local_matches - before == len(scored)
            by_id = dict(scored)
            assert {c.keyframe_id for c in got} <= set(by_id)
            for c in got:
                _same(c.local, by_id[c.keyframe_id])
