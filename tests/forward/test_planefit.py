"""The planar two-view motion fit (robotd.forward.planefit) against synthetic views of a
level camera whose motion is known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.forward.planar import planar_motion
from robotd.forward.planefit import fit_planar, planar_pose

K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def _views(yaw_deg: float, bearing_deg: float, dist_m: float, seed: int = 0, outliers: int = 20,
           noise_px: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of random points seen by a camera and by the same camera turned by ``yaw_deg``
    and moved ``dist_m`` towards ``bearing_deg`` (planar frame: x forward, y left)."""
    rng = np.random.default_rng(seed)
    yaw, b = math.radians(yaw_deg), math.radians(bearing_deg)
    centre = np.array([-math.sin(b), 0.0, math.cos(b)]) * dist_m
    r, _ = planar_pose(yaw, 0.0)
    t = -r @ centre
    x = np.column_stack([rng.uniform(-3, 3, 200), rng.uniform(-1, 0.6, 200), rng.uniform(2, 8, 200)])
    xn = x @ r.T + t
    keep = xn[:, 2] > 0.5
    x, xn = x[keep], xn[keep]
    po = x @ K.T
    pn = xn @ K.T
    po, pn = po[:, :2] / po[:, 2:], pn[:, :2] / pn[:, 2:]
    pn = pn + rng.normal(0.0, noise_px, pn.shape)
    pn[:outliers] = rng.uniform(0, 600, (outliers, 2))
    return po, pn


@pytest.mark.parametrize("yaw_deg,bearing_deg,dist_m", [(10, 30, 0.5), (-20, -100, 0.4), (0, 180, 0.3),
                                                        (5, 10, 1.0)])
def test_the_planar_motion_is_recovered(yaw_deg, bearing_deg, dist_m):
    po, pn = _views(yaw_deg, bearing_deg, dist_m)
    fit = fit_planar(po, pn, K, math.radians(yaw_deg + 3.0))  # a guess 3 deg off
    assert fit is not None
    assert math.degrees(fit.dyaw_rad) == pytest.approx(yaw_deg, abs=0.2)
    assert abs(math.degrees(math.remainder(fit.bearing_rad - math.radians(bearing_deg), math.tau))) < 2.0
    # The outliers are not inliers; (almost) all the rest are.
    assert not fit.inliers[:20].any() and fit.n_inliers >= 0.95 * (len(po) - 20)
    # The same motion as planar_motion reads it from the rotation and translation given.
    dyaw, bearing, tilt = planar_motion(fit.rotation, fit.translation_dir)
    assert (dyaw, bearing, tilt) == pytest.approx((fit.dyaw_rad, fit.bearing_rad, 0.0), abs=1e-9)
    assert 0.0 < fit.sigma_yaw_rad < math.radians(1.0) and 0.0 < fit.sigma_bearing_rad < math.radians(5.0)


def test_the_bearing_is_uncertain_without_parallax():
    """A 2 cm move: the heading change is still fixed, the bearing is not."""
    po, pn = _views(8, 60, 0.02, outliers=0, noise_px=0.3)
    fit = fit_planar(po, pn, K, math.radians(8.0))
    assert fit is not None and math.degrees(fit.dyaw_rad) == pytest.approx(8, abs=0.3)
    far = _views(8, 60, 0.5, outliers=0, noise_px=0.3)
    assert fit.sigma_bearing_rad > 5 * fit_planar(*far, K, math.radians(8.0)).sigma_bearing_rad


def test_too_few_matches():
    assert fit_planar(np.zeros((4, 2)), np.zeros((4, 2)), K, 0.0) is None


def _scan_one_by_one(p_old: np.ndarray, p_new: np.ndarray, yaw_guess: float) -> tuple[float, float]:
    """The heading scan of :func:`fit_planar` written as a loop over headings and candidate
    directions (as it was before it was batched): ``(yaw, psi)`` of the best candidate."""
    from robotd.forward.planefit import _sampson

    kinv = np.linalg.inv(K)
    focal = 0.5 * (K[0, 0] + K[1, 1])
    x_old = np.hstack([p_old, np.ones((len(p_old), 1))]) @ kinv.T
    x_new = np.hstack([p_new, np.ones((len(p_new), 1))]) @ kinv.T
    best = None
    step, bins = math.radians(0.2), 360
    for i in range(-40, 41):
        yaw = round(yaw_guess / step) * step + i * step  # the scan's lattice
        r, _ = planar_pose(yaw, 0.0)
        u = np.cross(x_old @ r.T, x_new)
        psis = np.mod(np.arctan2(-u[:, 2], u[:, 0]), math.pi)
        hist = np.bincount((psis / math.pi * bins).astype(np.int64) % bins, minlength=bins)
        hist = hist + np.roll(hist, 1) + np.roll(hist, -1)
        for b in np.argsort(-hist)[:2].tolist():
            centre = (b + 0.5) * math.pi / bins
            for cand in (centre - 0.5 * math.pi / bins, centre, centre + 0.5 * math.pi / bins):
                d = np.abs(_sampson(x_old, x_new, *planar_pose(yaw, cand), focal))
                score = (int((d < 1.0).sum()), -float(np.minimum(d, 1.0) @ np.minimum(d, 1.0)))
                if best is None or score > best[:2]:
                    best = (*score, yaw, cand)
    assert best is not None
    return best[2], best[3]


@pytest.mark.parametrize("seed", range(4))
def test_the_batched_heading_scan_picks_what_the_loop_over_headings_picks(seed):
    from robotd.forward.planefit import _sampson

    po, pn = _views(8.0 - 5 * seed, 40.0 * seed - 60.0, 0.3 + 0.2 * seed, seed=seed)
    guess = math.radians(8.0 - 5 * seed) + 0.03
    yaw, psi = _scan_one_by_one(po, pn, guess)
    fit = fit_planar(po, pn, K, guess)
    assert fit is not None
    # the batched scan's best candidate, refined: it starts from the loop's (yaw, psi)
    x = np.hstack([po, np.ones((len(po), 1))]) @ np.linalg.inv(K).T
    xn = np.hstack([pn, np.ones((len(pn), 1))]) @ np.linalg.inv(K).T
    start = np.abs(_sampson(x, xn, *planar_pose(yaw, psi), 525.0)) < 1.0
    assert fit.n_inliers >= start.sum() - 2
    assert abs(math.remainder(fit.dyaw_rad - yaw, math.tau)) < math.radians(0.5)


@pytest.mark.parametrize("seed", range(3))
def test_the_heading_scan_lies_on_one_lattice_whatever_the_guess_within_a_step(seed):
    """Two guesses that round to the same multiple of the scan step (two estimators'
    headings a hundredth of a degree apart) scan the same headings and give the same
    inlier profile; the scanned headings are multiples of the step."""
    po, pn = _views(1.5 + seed, 170.0 - 40 * seed, 0.3, seed=seed, noise_px=0.8)
    step = math.radians(0.2)
    a = fit_planar(po, pn, K, math.radians(1.62 + seed))
    b = fit_planar(po, pn, K, math.radians(1.63 + seed))
    assert a is not None and b is not None
    assert np.array_equal(a.scan_yaw_rad, b.scan_yaw_rad) and np.array_equal(a.scan_inliers, b.scan_inliers)
    assert np.allclose(np.asarray(a.scan_yaw_rad) / step, np.round(np.asarray(a.scan_yaw_rad) / step), atol=1e-9)
    assert (a.dyaw_rad, a.bearing_rad, a.n_inliers) == (b.dyaw_rad, b.bearing_rad, b.n_inliers)
    # a fixed heading is held where it is given, not rounded
    held = fit_planar(po, pn, K, math.radians(1.63 + seed), fix_yaw=True)
    assert held is not None and held.dyaw_rad == pytest.approx(math.radians(1.63 + seed), abs=1e-12)


@pytest.mark.parametrize("yaw_deg,bearing_deg,dist_m", [(10, 30, 0.5), (-20, -100, 0.4), (0, 180, 0.3),
                                                        (25, 10, 1.0)])
def test_two_point_ransac_finds_the_planar_motion_without_a_guess(yaw_deg, bearing_deg, dist_m):
    from robotd.forward.planefit import ransac_planar

    po, pn = _views(yaw_deg, bearing_deg, dist_m, outliers=60)
    fit, search = ransac_planar(po, pn, K)
    assert fit is not None
    assert math.degrees(fit.dyaw_rad) == pytest.approx(yaw_deg, abs=0.2)
    assert abs(math.degrees(math.remainder(fit.bearing_rad - math.radians(bearing_deg), math.tau))) < 2.0
    # (a random outlier may fall within 1 px of its epipolar line by chance)
    assert fit.inliers[:60].sum() <= 2 and fit.n_inliers >= 0.9 * (len(po) - 60)
    # The adaptive stop: a large consensus is found in the first batch of 64 samples.
    assert search.samples == 64 and search.best_inliers >= fit.n_inliers - 5
    assert planar_motion(fit.rotation, fit.translation_dir) == pytest.approx(
        (fit.dyaw_rad, fit.bearing_rad, 0.0), abs=1e-9)


def test_two_point_ransac_draws_at_most_its_cap_on_matches_without_consensus():
    from robotd.forward.planefit import ransac_planar

    rng = np.random.default_rng(2)
    po, pn = rng.uniform(0, 600, (300, 2)), rng.uniform(0, 600, (300, 2))
    fit, search = ransac_planar(po, pn, K, max_samples=200)
    assert search.samples == 200 and search.hypotheses <= 400
    assert fit is None or fit.n_inliers < 20
    assert ransac_planar(po[:4], pn[:4], K)[0] is None


@pytest.mark.parametrize("seed", range(3))
def test_the_scores_by_the_linear_terms_are_those_of_the_sampson_distances(seed):
    """:func:`_scores` (the distances squared from two matrix products) counts the inliers
    the Sampson distances of each pose count, and its cost is theirs to rounding; also with
    matches not at unit depth."""
    from robotd.forward.planefit import _linear_terms, _sampson, _sampson_linear, _scores

    po, pn = _views(6.0 - 4 * seed, 50.0 * seed - 40.0, 0.4, seed=seed)
    kinv = np.linalg.inv(K)
    x = np.hstack([po, np.ones((len(po), 1))]) @ kinv.T
    xn = np.hstack([pn, np.ones((len(pn), 1))]) @ kinv.T
    rng = np.random.default_rng(seed)
    yaws, psis = rng.uniform(-0.4, 0.4, 300), rng.uniform(0.0, math.pi, 300)
    for xo in (x, 2.0 * x):
        inl_n, cost = _scores(_linear_terms(xo, xn), yaws, psis, 525.0, 1.0)
        rows = _sampson_linear(*_linear_terms(xo, xn), list(zip(yaws.tolist(), psis.tolist())), 525.0)
        for m in range(300):
            d = _sampson(xo, xn, *planar_pose(float(yaws[m]), float(psis[m])), 525.0)
            assert np.allclose(rows[m], d, rtol=1e-9, atol=1e-9)
            near = np.abs(np.abs(d) - 1.0) < 1e-9  # a match within rounding of the threshold may go either way
            assert abs(int(inl_n[m]) - int((np.abs(d) < 1.0).sum())) <= int(near.sum())
            dm = np.minimum(np.abs(d), 1.0)
            assert cost[m] == pytest.approx(-float(dm @ dm), rel=1e-9, abs=1e-9)


def _same_fit(a, b) -> bool:
    return (a.dyaw_rad == b.dyaw_rad and a.bearing_rad == b.bearing_rad and np.array_equal(a.inliers, b.inliers)
            and a.sigma_yaw_rad == b.sigma_yaw_rad and a.sigma_bearing_rad == b.sigma_bearing_rad
            and np.array_equal(a.rotation, b.rotation) and np.array_equal(a.translation_dir, b.translation_dir)
            and np.array_equal(a.scan_yaw_rad, b.scan_yaw_rad) and np.array_equal(a.scan_inliers, b.scan_inliers))


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("offset_deg", [0.0, 0.1, 0.3, 2.9, 15.8, 16.2, 40.0])
def test_the_scans_around_several_guesses_are_each_guess_s_own_fit(seed, offset_deg):
    """:func:`fit_planar_scans`, which scores the headings two windows share once and
    refines a best candidate they share once, gives each guess the fit :func:`fit_planar`
    gives it alone, to the bit: windows that overlap in part, round to one lattice
    heading, touch (16 deg apart: one shared heading) or lie apart."""
    from robotd.forward.planefit import fit_planar_scans

    po, pn = _views(4.0 - 3 * seed, 150.0 - 55 * seed, 0.15 + 0.15 * seed, seed=seed, outliers=10 + 15 * seed,
                    noise_px=0.4 + 0.2 * seed)
    g1 = math.radians(4.0 - 3 * seed + 1.3 - 0.6 * seed)
    g2 = g1 + math.radians(offset_deg)
    both = fit_planar_scans(po, pn, K, [g1, g2])
    alone = [fit_planar(po, pn, K, g1), fit_planar(po, pn, K, g2)]
    assert all(f is not None for f in both + alone)
    assert all(_same_fit(a, b) for a, b in zip(both, alone))
    assert fit_planar_scans(po[:4], pn[:4], K, [g1, g2]) == [None, None]


@pytest.mark.parametrize("seed", range(4))
def test_the_written_out_directions_are_those_of_the_rotated_cross_product(seed):
    """The scan's translation directions per heading, written out from the rotation's
    entries, give the inlier profile of rotating the rays and taking their cross product
    with ``numpy`` (the scan before), to the bit."""
    from robotd.forward.planefit import _sampson

    po, pn = _views(6.0 - 4 * seed, 30.0 + 50 * seed, 0.3 + 0.1 * seed, seed=seed, outliers=30)
    guess = math.radians(6.0 - 4 * seed + 2.0)
    step, bins = math.radians(0.2), 360
    kinv = np.linalg.inv(K)
    x_old = np.hstack([po, np.ones((len(po), 1))]) @ kinv.T
    x_new = np.hstack([pn, np.ones((len(pn), 1))]) @ kinv.T
    yaws = round(guess / step) * step + np.arange(-40, 41) * step
    c, s = np.cos(yaws), np.sin(yaws)
    rots = np.zeros((len(yaws), 3, 3))
    rots[:, 0, 0], rots[:, 0, 2], rots[:, 1, 1], rots[:, 2, 0], rots[:, 2, 2] = c, s, 1.0, -s, c
    u = np.cross(np.einsum("yij,nj->yni", rots, x_old), x_new[None])
    psis = np.mod(np.arctan2(-u[..., 2], u[..., 0]), math.pi)
    idx = (psis / math.pi * bins).astype(np.int64) % bins + bins * np.arange(len(yaws))[:, None]
    hist = np.bincount(idx.ravel(), minlength=bins * len(yaws)).reshape(len(yaws), bins)
    hist = hist + np.roll(hist, 1, axis=1) + np.roll(hist, -1, axis=1)
    top = np.argsort(-hist, axis=1)[:, :2]
    cands = ((top + 0.5) * math.pi / bins)[..., None] + np.array([-0.5, 0.0, 0.5]) * math.pi / bins
    d = np.abs([_sampson(x_old, x_new, *planar_pose(float(y), float(p)), 525.0)
                for y, p in zip(np.repeat(yaws, 6), cands.ravel())])
    profile = (d < 1.0).sum(axis=1).reshape(len(yaws), -1).max(axis=1)
    fit = fit_planar(po, pn, K, guess)
    assert fit is not None
    assert np.array_equal(fit.scan_yaw_rad, yaws) and np.array_equal(fit.scan_inliers, profile)


@pytest.mark.parametrize("fix_yaw", [False, True])
def test_without_sigmas_the_fit_is_the_same_motion(fix_yaw):
    """``sigmas=False`` (the ridge's side fits, whose bearing alone is read) leaves the
    sigmas out and the motion, its inliers and its scan as they are with them."""
    po, pn = _views(3.0, 120.0, 0.4, seed=2, outliers=30)
    a = fit_planar(po, pn, K, math.radians(4.1), fix_yaw=fix_yaw)
    b = fit_planar(po, pn, K, math.radians(4.1), fix_yaw=fix_yaw, sigmas=False)
    assert a is not None and b is not None
    assert math.isfinite(a.sigma_bearing_rad) and b.sigma_bearing_rad == b.sigma_yaw_rad == math.inf
    assert (a.dyaw_rad, a.bearing_rad) == (b.dyaw_rad, b.bearing_rad)
    assert np.array_equal(a.inliers, b.inliers) and np.array_equal(a.translation_dir, b.translation_dir)
    assert np.array_equal(a.scan_inliers, b.scan_inliers)


def test_the_smoothed_histogram_is_the_rolled_one():
    from robotd.forward.planefit import _with_neighbours

    hist = np.random.default_rng(0).integers(0, 50, (7, 360))
    expected = hist + np.roll(hist, 1, axis=1) + np.roll(hist, -1, axis=1)
    assert np.array_equal(_with_neighbours(hist), expected)


def test_the_condition_number_falls_on_the_svd_s_side_of_the_limit():
    """The cheap condition number decides as ``np.linalg.cond`` does, down to matrices
    whose condition number is within a part in a million of the limit."""
    from robotd.forward.planefit import _COND_LIMIT, _cond

    rng = np.random.default_rng(1)
    mats = [np.array([[rng.normal() * 10 ** rng.uniform(-8, 8)]]) for _ in range(50)]
    for _ in range(2000):
        # symmetric positive semi-definite 2 x 2 (a J^T J), condition numbers 1 .. 1e16
        q, _ = np.linalg.qr(rng.normal(size=(2, 2)))
        big = 10 ** rng.uniform(-6, 6)
        mats.append(q @ np.diag([big, big / 10 ** rng.uniform(0, 16)]) @ q.T)
    for c in (1e12 * (1 - 1e-6), 1e12 * (1 + 1e-6), 1e11, 1e11 * 1.01):  # at the lines
        mats.append(np.diag([1.0, 1.0 / c]))
    mats += [np.zeros((2, 2)), np.array([[1.0, 2.0], [2.0, 4.0]]), np.array([[0.0]])]
    for m in mats:
        with np.errstate(all="ignore"):
            ref = float(np.linalg.cond(m))
            got = _cond(m)
        assert (got > _COND_LIMIT) == (ref > _COND_LIMIT) and (got < _COND_LIMIT) == (ref < _COND_LIMIT), m


@pytest.mark.parametrize("seed", range(3))
def test_the_sampson_distances_of_several_poses_at_once_are_each_pose_s(seed):
    from robotd.forward.planefit import _linear_terms, _sampson, _sampson_linear

    rng = np.random.default_rng(seed)
    po, pn = _views(5.0 - 4 * seed, 30.0 + 50 * seed, 0.4, seed=seed)
    kinv = np.linalg.inv(K)
    x = np.hstack([po, np.ones((len(po), 1))]) @ kinv.T
    xn = np.hstack([pn, np.ones((len(pn), 1))]) @ kinv.T
    for n in (len(x), 7, 0):
        thetas = [tuple(rng.normal(size=2).tolist()) for _ in range(5)]
        got = _sampson_linear(*_linear_terms(x[:n], xn[:n]), thetas, 525.0)
        assert got.shape == (5, n)
        for k, th in enumerate(thetas):
            want = _sampson(x[:n], xn[:n], *planar_pose(th[0], th[1]), 525.0)
            assert np.allclose(got[k], want, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("seed", range(12))
def test_the_batched_refinement_is_the_reference_s(seed):
    """The refinement with its residuals from the matches' linear terms (one call per point
    and its neighbours, stopping once a step is below a nanoradian) gives the fit of the
    one-evaluation-at-a-time reference (five steps at most, no such stop): the same inliers,
    heading and bearing within 1e-7 rad (the fits' sigmas are 1e-3 rad and more), sigmas
    within a part in a million, with the
    heading fitted or held, with and without sigmas."""
    from robotd.forward.planefit import _refine

    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-25, 25)
    po, pn = _views(yaw, rng.uniform(-180, 180), rng.uniform(0.05, 1.0), seed=seed,
                    outliers=int(rng.integers(0, 80)), noise_px=rng.uniform(0.2, 2.0))
    kinv = np.linalg.inv(K)
    x = np.hstack([po, np.ones((len(po), 1))]) @ kinv.T
    xn = np.hstack([pn, np.ones((len(pn), 1))]) @ kinv.T
    for fix_yaw in (False, True):
        for sigmas in (True, False):
            start = (math.radians(yaw) + rng.normal(0, 0.02), rng.uniform(0, math.pi))
            args = (x, xn, 525.0, *start, 1.0, fix_yaw, np.zeros(0), np.zeros(0, np.int64), sigmas)
            a, b = _refine(*args), _refine_reference(*args)
            assert a.dyaw_rad == pytest.approx(b.dyaw_rad, abs=1e-7)
            assert abs(math.remainder(a.bearing_rad - b.bearing_rad, math.tau)) < 1e-7
            assert np.array_equal(a.inliers, b.inliers)
            for sa, sb in ((a.sigma_yaw_rad, b.sigma_yaw_rad), (a.sigma_bearing_rad, b.sigma_bearing_rad)):
                assert (sa == sb) if not (math.isfinite(sa) and math.isfinite(sb)) else sa == pytest.approx(sb, rel=1e-6)


def test_a_one_by_one_solve_is_the_division():
    """The held-heading refinement divides where it solved a 1 x 1 system: the same number."""
    rng = np.random.default_rng(3)
    for _ in range(2000):
        a, b = rng.normal(size=2) * 10 ** rng.uniform(-8, 8, size=2)
        assert float(np.linalg.solve(np.array([[a]]), np.array([b]))[0]) == b / a

def _refine_reference(x_old, x_new, focal, yaw, psi, threshold_px, fix_yaw, yaws, scan_n, sigmas=True):
    """:func:`robotd.forward.planefit._refine` one Sampson evaluation at a time (the
    reference it is tested against: the same fit; the module's code before it batched the
    evaluations)."""
    from robotd.forward.planefit import (
        _COND_LIMIT, INLIER_NOISE_FACTOR, PlanarFit, _bearing, _cond, _sampson, front_mask, planar_pose)

    def _in_front(xo, xn, r, t):
        return int(np.count_nonzero(front_mask(xo, xn, r, t)))

    # Refine (yaw, psi) by Gauss-Newton on the inliers' Sampson distances.
    r, t = planar_pose(yaw, psi)
    inl = np.abs(_sampson(x_old, x_new, r, t, focal)) < threshold_px
    theta = np.array([yaw, psi])
    xo_in, xn_in = x_old[inl], x_new[inl]  # the inliers' rows, taken once per inlier set

    def res(th: np.ndarray) -> np.ndarray:  # the Sampson distances of the current inliers
        rr, tt = planar_pose(float(th[0]), float(th[1]))
        return _sampson(xo_in, xn_in, rr, tt, focal)

    h = 1e-6
    free = [1] if fix_yaw else [0, 1]  # the parameters fitted: (yaw, psi) or psi alone
    jac = np.zeros((int(inl.sum()), len(free)))
    r0 = None  # the residuals at theta, kept from the step that moved there
    for _ in range(5):
        if inl.sum() < 3:
            break
        if r0 is None:
            r0 = res(theta)
        for col, j in enumerate(free):
            dth = np.zeros(2)
            dth[j] = h
            jac[:, col] = (res(theta + dth) - res(theta - dth)) / (2 * h)
        jtj = jac.T @ jac
        if not np.all(np.isfinite(jtj)) or _cond(jtj) > _COND_LIMIT:
            break
        step = np.zeros(2)
        step[free] = -np.linalg.solve(jtj, jac.T @ r0)
        trial = res(theta + step)
        if not float(trial @ trial) < float(r0 @ r0):
            break
        theta, r0 = theta + step, trial
    yaw, psi = float(theta[0]), float(theta[1])
    r, t = planar_pose(yaw, psi)
    inl = np.abs(_sampson(x_old, x_new, r, t, focal)) < threshold_px
    xo_in, xn_in = x_old[inl], x_new[inl]
    # The sign of the translation: the points in front of both cameras.
    if _in_front(xo_in, xn_in, r, -t) > _in_front(xo_in, xn_in, r, t):
        psi += math.pi
        r, t = planar_pose(yaw, psi)
    m = int(inl.sum())
    sig_y = sig_b = math.inf
    if sigmas and m > len(free):
        rr = res(np.array([yaw, psi]))
        noise = math.sqrt(float(rr @ rr) / (m - len(free))) * INLIER_NOISE_FACTOR
        jac = np.zeros((m, 2))
        for j in range(2):
            dth = np.zeros(2)
            dth[j] = h
            jac[:, j] = (res(np.array([yaw, psi]) + dth) - res(np.array([yaw, psi]) - dth)) / (2 * h)
        jtj = jac.T @ jac
        cov: np.ndarray | None = None
        if fix_yaw:  # the heading known: psi's variance alone, the heading's none
            if math.isfinite(float(jtj[1, 1])) and jtj[1, 1] > 0:
                cov = noise ** 2 * np.diag([0.0, 1.0 / jtj[1, 1]])
        elif np.all(np.isfinite(jtj)) and _cond(jtj) < _COND_LIMIT:
            cov = noise ** 2 * np.linalg.inv(jtj)
        if cov is not None:
            g = np.array([[1.0, 0.0],
                          [(_bearing(yaw + h, psi) - _bearing(yaw - h, psi)) / (2 * h),
                           math.remainder(_bearing(yaw, psi + h) - _bearing(yaw, psi - h), math.tau) / (2 * h)]])
            var = np.einsum("ij,jk,ik->i", g, cov, g)
            sig_y, sig_b = math.sqrt(max(float(var[0]), 0.0)), math.sqrt(max(float(var[1]), 0.0))
    return PlanarFit(yaw, _bearing(yaw, psi), r, t, inl, sig_y, sig_b, yaws, scan_n)


@pytest.mark.parametrize("seed", range(4))
def test_the_fixed_heading_fits_in_one_call_are_each_heading_s_own(seed):
    """:func:`fit_planar_fixed` (the ridge's fit and its side fits together) gives at each
    heading the fit :func:`fit_planar` with ``fix_yaw`` gives there alone: the same inliers,
    the bearing to rounding, sigmas where asked for."""
    from robotd.forward.planefit import fit_planar_fixed

    po, pn = _views(3.0 - 2 * seed, 120.0 - 50 * seed, 0.2 + 0.2 * seed, seed=seed, outliers=20 + 10 * seed)
    yaw = math.radians(3.0 - 2 * seed + 0.4)
    yaws = [yaw, yaw - math.radians(0.5), yaw + math.radians(0.5)]
    got = fit_planar_fixed(po, pn, K, yaws, [True, False, False])
    alone = [fit_planar(po, pn, K, y, fix_yaw=True, sigmas=i == 0) for i, y in enumerate(yaws)]
    for g, a in zip(got, alone):
        assert g is not None and a is not None
        assert np.array_equal(g.inliers, a.inliers) and g.dyaw_rad == a.dyaw_rad
        assert abs(math.remainder(g.bearing_rad - a.bearing_rad, math.tau)) < 1e-9
    assert math.isfinite(got[0].sigma_bearing_rad) and got[0].sigma_bearing_rad == pytest.approx(
        alone[0].sigma_bearing_rad, rel=1e-9)
    assert got[1].sigma_bearing_rad == got[2].sigma_bearing_rad == math.inf
    assert fit_planar_fixed(po[:4], pn[:4], K, yaws, [True, False, False]) == [None, None, None]
