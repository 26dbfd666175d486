"""Epipolar verification on a synthetic scene with a known relative pose."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from robotd.forward.features import Features
from robotd.forward.verify import (
    ACCEPTED,
    NO_GEOMETRIC_CONSISTENCY,
    SMALL_SUPPORT,
    TOO_FEW_MATCHES,
    Verification,
    VerifyParams,
    camera_matrix_guess,
    match_indices,
    ransac_iterations,
    support_area,
    verify_pair,
)

K = camera_matrix_guess(640, 480)


def _rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _project(x_cam: np.ndarray) -> np.ndarray:
    p = (K @ x_cam.T).T
    return (p[:, :2] / p[:, 2:]).astype(np.float32)


def _scene(rng: np.random.Generator, n: int = 150):
    """Points 3-8 m in front of the old camera; the new camera turned 10 degrees and moved
    0.5 m (x_new = R x_old + t)."""
    x_old = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(3, 8, n)])
    r = _rot_y(np.radians(10))
    t = np.array([0.3, 0.0, -0.4])
    x_new = x_old @ r.T + t
    return x_old, x_new, r, t


def _features(xy: np.ndarray, desc: np.ndarray) -> Features:
    return Features(xy, desc, (640, 480))


def _angle_deg(r_est: np.ndarray, r: np.ndarray) -> float:
    """The angle of the rotation between ``r_est`` and ``r`` (deg)."""
    return float(np.degrees(np.arccos(np.clip((np.trace(r_est.T @ r) - 1) / 2, -1, 1))))


def _level_pair_with_shuffled(rng: np.random.Generator):
    """``_scene``'s pair with 0.3 px of noise in the new view and its first 40 matches
    shuffled among themselves (110 true matches): old and new features, R, t."""
    x_old, x_new, r, t = _scene(rng)
    desc = rng.standard_normal((150, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    px_new = _project(x_new) + rng.normal(0, 0.3, (150, 2)).astype(np.float32)
    px_new[:40] = px_new[:40][rng.permutation(40)]
    return _features(_project(x_old), desc), _features(px_new, desc), r, t


def test_a_true_pair_is_accepted_with_its_rotation_and_translation_direction():
    rng = np.random.default_rng(0)
    x_old, x_new, r, t = _scene(rng)
    desc = rng.standard_normal((150, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    px_new = _project(x_new) + rng.normal(0, 0.3, (150, 2)).astype(np.float32)
    v = verify_pair(_features(_project(x_old), desc), _features(px_new, desc))
    assert v.accepted and v.reason == ACCEPTED
    assert v.n_matches == 150 and v.n_inliers >= 130
    assert not v.planar and v.n_plane_inliers < 0.8 * v.n_inliers  # depths 3-8 m: parallax
    assert v.support_area > 0.3
    angle = _angle_deg(v.rotation, r)
    assert angle < 0.5
    assert np.dot(v.translation_dir, t / np.linalg.norm(t)) > 0.995  # within 6 degrees


def test_shuffled_points_fail_the_epipolar_check():
    rng = np.random.default_rng(1)
    x_old, x_new, _, _ = _scene(rng)
    desc = rng.standard_normal((150, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    px_new = _project(x_new)[rng.permutation(150)]  # right descriptors, wrong places
    v = verify_pair(_features(_project(x_old), desc), _features(px_new, desc))
    assert not v.accepted and v.reason == NO_GEOMETRIC_CONSISTENCY
    assert v.n_matches == 150 and v.n_inliers < 20


def test_too_few_matches_is_a_value_not_an_exception():
    rng = np.random.default_rng(2)
    a = rng.standard_normal((10, 128)).astype(np.float32)
    xy = rng.uniform(0, 400, (10, 2)).astype(np.float32)
    v = verify_pair(_features(xy, a), _features(xy, a), VerifyParams(min_inliers=20))
    assert not v.accepted and v.reason == TOO_FEW_MATCHES and v.n_matches == 10
    empty = Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), (640, 480))
    assert verify_pair(empty, _features(xy, a)).reason == TOO_FEW_MATCHES


def _plane_pair(rng: np.random.Generator, width_m: float, height_m: float, n: int = 80):
    """``n`` points on a fronto-parallel rectangle ``width_m`` x ``height_m`` 4 m in front of
    the old camera (a poster, or a whole wall), seen by both cameras of :func:`_scene`, with
    0.3 px of noise; the same random descriptors in both images."""
    x_old = np.column_stack([rng.uniform(-width_m / 2, width_m / 2, n) + 0.3,
                             rng.uniform(-height_m / 2, height_m / 2, n), np.full(n, 4.0)])
    r = _rot_y(np.radians(10))
    t = np.array([0.3, 0.0, -0.4])
    x_new = x_old @ r.T + t
    desc = rng.standard_normal((n, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    noise = lambda: rng.normal(0, 0.3, (n, 2)).astype(np.float32)
    return _features(_project(x_old) + noise(), desc), _features(_project(x_new) + noise(), desc)


def test_a_small_plane_passes_the_papers_check_but_not_the_support_check():
    # A 0.5 x 0.4 m poster at 4 m: every match fits one homography, so five-point RANSAC
    # finds an essential matrix that all of them satisfy (the paper's check accepts), but
    # they cover about 1.5 % of the image: a repeated poster elsewhere would look the same.
    old, new = _plane_pair(np.random.default_rng(3), 0.5, 0.4)
    paper = verify_pair(old, new, VerifyParams(min_support_area=0.0))
    assert paper.accepted and paper.n_inliers >= 60
    v = verify_pair(old, new)
    assert not v.accepted and v.reason == SMALL_SUPPORT
    assert 0.005 < v.support_area < 0.03
    # all the inliers cover under 3 %: refused without the homography (not fitted)
    assert not v.planar and v.n_plane_inliers == 0


def test_a_plane_that_fills_the_view_is_accepted():
    # The same geometry on a 3 x 2 m wall: one plane, but it covers a third of the image.
    old, new = _plane_pair(np.random.default_rng(4), 3.0, 2.0)
    v = verify_pair(old, new)
    assert v.accepted and v.reason == ACCEPTED and v.planar
    assert v.support_area > 0.2


def test_support_area_of_points():
    square = np.array([[0, 0], [64, 0], [64, 48], [0, 48], [32, 24]], np.float32)
    assert support_area(square, (640, 480)) == pytest.approx(0.01)
    assert support_area(square[:2], (640, 480)) == 0.0


@pytest.mark.parametrize("kw", [{"min_support_area": -0.1}, {"min_support_area": 1.0},
                                {"planar_fraction": 0.0}, {"homography_threshold_px": 0.0}])
def test_bad_support_parameters_are_refused(kw):
    with pytest.raises(ValueError):
        VerifyParams(**kw)


def test_ransac_stops_once_a_consensus_of_min_inliers_would_have_been_found():
    # log(1 - 0.999) / log(1 - (20/28)^5) = 33.7: 34 samples instead of OpenCV's 1000
    assert ransac_iterations(28, 20, 0.999) == 34
    assert ransac_iterations(40, 20, 0.999) == 218
    assert ransac_iterations(20, 20, 0.999) == 1       # every match must be an inlier
    assert ransac_iterations(300, 20, 0.999) == 1000   # a small consensus among many: the cap
    counts = [ransac_iterations(n, 20, 0.999) for n in range(20, 200)]
    assert counts == sorted(counts)                    # more matches, never fewer samples


@pytest.mark.parametrize("estimator", ["ransac", "usac"])
def test_both_estimators_accept_a_true_pair_and_refuse_shuffled_points(estimator):
    rng = np.random.default_rng(3)
    x_old, x_new, r, t = _scene(rng)
    desc = rng.standard_normal((150, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    params = VerifyParams(estimator=estimator)
    px_new = _project(x_new) + rng.normal(0, 0.3, (150, 2)).astype(np.float32)
    v = verify_pair(_features(_project(x_old), desc), _features(px_new, desc), params)
    assert v.accepted and v.n_inliers >= 130
    assert np.dot(v.translation_dir, t / np.linalg.norm(t)) > 0.995
    shuffled = px_new[rng.permutation(150)]
    assert not verify_pair(_features(_project(x_old), desc), _features(shuffled, desc), params).accepted


def test_an_unknown_estimator_is_refused():
    with pytest.raises(ValueError, match="estimator"):
        VerifyParams(estimator="lmeds")


def test_max_iterations_caps_the_sample_budget_and_must_be_positive() -> None:
    """VerifyParams.max_iterations bounds what ransac_iterations allows (few matches need
    fewer samples than the cap and keep their own bound); 0 is refused."""
    from robotd.forward.verify import VerifyParams, ransac_iterations

    assert ransac_iterations(200, 20, 0.999, cap=VerifyParams(max_iterations=200).max_iterations) == 200
    assert ransac_iterations(200, 20, 0.999) == 1000
    assert ransac_iterations(28, 20, 0.999, cap=200) == ransac_iterations(28, 20, 0.999) < 200
    with pytest.raises(ValueError, match="max_iterations"):
        VerifyParams(max_iterations=0)


def _tilted_scene(rng: np.random.Generator, tilt_deg: float, n: int = 150):
    """As :func:`_scene`, the new camera also rolled by ``tilt_deg`` about its optical axis
    (not a level camera's motion)."""
    x_old, _, r, t = _scene(rng, n)
    c, s = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    roll = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    r = roll @ r
    return x_old, x_old @ r.T + t, r, t


def test_the_planar_motion_model_recovers_a_level_motion_without_the_five_point_search(monkeypatch):
    """A level camera's motion: ``planar_motion`` finds it alone (the general search is never
    called) with the same rotation and translation direction as the truth."""
    import robotd.forward.verify as verify_mod

    def no_general(*args, **kwargs):
        raise AssertionError("the general model was tried")

    rng = np.random.default_rng(4)
    x_old, x_new, r, t = _scene(rng)
    desc = rng.standard_normal((150, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    px_new = _project(x_new) + rng.normal(0, 0.3, (150, 2)).astype(np.float32)
    monkeypatch.setattr(verify_mod, "essential_matrix", no_general)
    v = verify_pair(_features(_project(x_old), desc), _features(px_new, desc), VerifyParams(model="planar_motion"))
    assert v.accepted and v.n_inliers >= 130
    angle = _angle_deg(v.rotation, r)
    assert angle < 0.3
    assert np.dot(v.translation_dir, t / np.linalg.norm(t)) > 0.995
    assert v.planarity_chi2 == 0.0 and 0.0 < v.sigma_bearing_rad < np.radians(2.0)
    shuffled = px_new[rng.permutation(150)]
    refused = verify_pair(_features(_project(x_old), desc), _features(shuffled, desc),
                          VerifyParams(model="planar_motion", fallback_inliers=None))
    assert not refused.accepted and refused.reason == NO_GEOMETRIC_CONSISTENCY


def test_the_planar_model_searches_the_essential_matrix_among_the_level_motions_matches(monkeypatch):
    """``"planar"``: the five-point search runs once, on the matches near the level motion
    (the 40 shuffled ones left out), and gives the general model's motion and inliers."""
    import robotd.forward.verify as verify_mod

    old, new, r, t = _level_pair_with_shuffled(np.random.default_rng(6))
    searched: list[int] = []
    inner = verify_mod.essential_matrix

    def counted(p_old, p_new, k, params):
        searched.append(len(p_old))
        return inner(p_old, p_new, k, params)

    monkeypatch.setattr(verify_mod, "essential_matrix", counted)
    v = verify_pair(old, new, VerifyParams(model="planar"))
    assert v.accepted and v.n_inliers >= 100
    assert len(searched) == 1 and 100 <= searched[0] < 115   # the 110 true matches, few of the 40
    angle = _angle_deg(v.rotation, r)
    assert angle < 0.3 and np.dot(v.translation_dir, t / np.linalg.norm(t)) > 0.995
    general = verify_pair(old, new, VerifyParams(model="general"))
    assert abs(general.n_inliers - v.n_inliers) <= 3


def test_a_motion_out_of_the_plane_falls_back_to_the_general_model_only_when_allowed():
    """A 6 deg roll: no level motion explains 20 matches within 1 px, so the planar motion
    alone refuses the pair; with the fallback (its planar consensus reaches
    ``fallback_inliers``) the general model accepts it with the true rotation, and so does
    ``"planar"`` (its essential matrix found near the level motion or by the fallback)."""
    rng = np.random.default_rng(5)
    x_old, x_new, r, t = _tilted_scene(rng, 6.0)
    desc = rng.standard_normal((150, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    old, new = _features(_project(x_old), desc), _features(_project(x_new), desc)
    alone = verify_pair(old, new, VerifyParams(model="planar_motion", fallback_inliers=None))
    assert not alone.accepted
    for model in ("planar_motion", "planar"):
        v = verify_pair(old, new, VerifyParams(model=model, fallback_inliers=0))
        assert v.accepted and v.n_inliers >= 130
        angle = _angle_deg(v.rotation, r)
        assert angle < 0.3
    # A fallback threshold above any planar consensus here: refused as the planar motion alone.
    assert not verify_pair(old, new, VerifyParams(model="planar_motion", fallback_inliers=150)).accepted


def test_the_planar_models_searches_take_their_own_estimators(monkeypatch):
    """``guided_estimator`` is the five-point search's near the level motion,
    ``fallback_estimator`` the general search's over all the matches (at most
    ``fallback_max_iterations`` samples); ``Verification.fallback`` says the latter ran. A
    level pair needs no fallback; a 15 deg roll does. Each accepts with the true rotation."""
    import robotd.forward.verify as verify_mod

    calls: list[tuple[int, str, int]] = []
    inner = verify_mod.essential_matrix

    def counted(p_old, p_new, k, params):
        calls.append((len(p_old), params.estimator, params.max_iterations))
        return inner(p_old, p_new, k, params)

    monkeypatch.setattr(verify_mod, "essential_matrix", counted)
    old, new, r, _ = _level_pair_with_shuffled(np.random.default_rng(6))
    level = verify_pair(old, new, VerifyParams(model="planar", guided_estimator="usac", fallback_inliers=0))
    assert level.accepted and not level.fallback and level.n_inliers >= 100
    assert [c[1] for c in calls] == ["usac"] and calls[0][0] < 115
    angle = _angle_deg(level.rotation, r)
    assert angle < 0.3
    calls.clear()
    x_old, x_new, r, _ = _tilted_scene(np.random.default_rng(5), 15.0)
    desc = old.descriptors  # the level pair's descriptors again
    old, new = _features(_project(x_old), desc), _features(_project(x_new), desc)
    tilted = verify_pair(old, new, VerifyParams(model="planar", fallback_inliers=0, fallback_estimator="usac"))
    assert tilted.accepted and tilted.fallback and tilted.n_inliers >= 130
    assert calls[-1] == (150, "usac", 200) and all(c[1] == "ransac" for c in calls[:-1])
    angle = _angle_deg(tilted.rotation, r)
    assert angle < 0.3


@pytest.mark.parametrize("kw", [{"model": "affine"}, {"planar_max_samples": 0}, {"fallback_inliers": -1},
                                {"guide_threshold_px": 0.0}, {"fallback_max_iterations": 0},
                                {"guided_estimator": "lmeds"}, {"fallback_estimator": "prosac"},
                                {"fallback_screen": "ransac"}])
def test_bad_model_parameters_are_refused(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        VerifyParams(**kw)


def test_the_planar_model_carries_the_level_motions_heading(monkeypatch):
    """``level_yaw_rad``: the heading of the two-point search's best level motion (the one
    that guided the five-point search), the scene's 10 deg; carried through a fallback; NaN
    for the general model."""
    import math

    from robotd.forward.planefit import ransac_planar
    from robotd.forward.verify import match_features

    old, new, _, _ = _level_pair_with_shuffled(np.random.default_rng(6))
    params = VerifyParams(model="planar")
    v = verify_pair(old, new, params)
    p_old, p_new = match_features(old, new, params.ratio)
    _, search = ransac_planar(p_old, p_new, K, threshold_px=params.guide_threshold_px,
                              min_inliers=params.min_inliers, confidence=params.ransac_confidence,
                              max_samples=params.planar_max_samples, seed=params.seed, refine=False)
    assert v.accepted and v.level_yaw_rad == search.yaw_rad
    assert math.degrees(v.level_yaw_rad) == pytest.approx(10.0, abs=0.5)
    assert math.isnan(verify_pair(old, new, VerifyParams(model="general")).level_yaw_rad)
    # The search near the level motion made to fail: the fallback's verification keeps it.
    import robotd.forward.verify as verify_mod

    inner = verify_mod._general_motion
    calls: list[int] = []

    def first_fails(p_o, p_n, k, prm, n, near=None, half_inliers=True, normalised=None):
        calls.append(n)
        if len(calls) == 1:
            return verify_mod.Verification(False, NO_GEOMETRIC_CONSISTENCY, n, 0)
        return inner(p_o, p_n, k, prm, n, near, half_inliers, normalised)

    monkeypatch.setattr(verify_mod, "_general_motion", first_fails)
    for band in (None, 10.0):
        calls.clear()
        fell = verify_pair(old, new, VerifyParams(model="planar", fallback_inliers=0, fallback_band_px=band))
        assert len(calls) == 2 and fell.fallback and fell.accepted and fell.level_yaw_rad == search.yaw_rad


@pytest.mark.parametrize("model", ["planar", "general"])
def test_the_verification_returns_the_indices_of_the_matches_it_ran_on(model):
    """``match_index``: the matches as indices into the two images' keypoints, the pixels
    :func:`match_features` gives (the new image's features in another order than the old
    one's); the daemon's stage reads its planar refit's matches from them, through the
    detector's compact copy of the new image, where it matched that copy again before."""
    from robotd.forward.features import compact
    from robotd.forward.verify import match_features

    rng = np.random.default_rng(4)
    old, new, _, _ = _level_pair_with_shuffled(rng)
    perm = rng.permutation(len(new))
    new = Features(new.keypoints_px[perm], new.descriptors[perm], new.image_size_px)
    v = verify_pair(old, new, VerifyParams(model=model), K)
    assert v.accepted and v.match_index is not None
    ia, ib = v.match_index
    assert len(ia) == v.n_matches and not np.array_equal(ia, ib)
    p_old, p_new = match_features(old, new)
    assert np.array_equal(old.keypoints_px[ia], p_old) and np.array_equal(new.keypoints_px[ib], p_new)
    kept = compact(new, np.zeros(len(new), np.uint32))  # what the detector keeps of the new image
    c_old, c_new = match_features(old, kept)
    assert np.array_equal(old.keypoints_px[ia], c_old) and np.array_equal(kept.keypoints_px[ib], c_new)
    # too few matches: empty indices
    few = verify_pair(Features(old.keypoints_px[:3], old.descriptors[:3], (640, 480)), new)
    assert few.reason == TOO_FEW_MATCHES and few.match_index is not None and len(few.match_index[0]) <= 3


def _match_indices_reference(a, b, ratio=0.8, by_distance=False):
    """:func:`robotd.forward.verify.match_indices` as a loop over OpenCV's ``knnMatch``
    pairs (as it was before it read the two nearest as arrays): the reference it must equal
    (the same pairs, the same order)."""
    import cv2

    empty = np.zeros(0, np.int64)
    if len(a) < 2 or len(b) < 2:
        return empty, empty
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING if a.descriptors.dtype == np.uint8 else cv2.NORM_L2)
    best = {}
    for p in matcher.knnMatch(a.descriptors, b.descriptors, k=2):
        if len(p) == 2 and p[0].distance < ratio * p[1].distance:
            m = p[0]
            if m.trainIdx not in best or m.distance < best[m.trainIdx][0]:
                best[m.trainIdx] = (m.distance, m.queryIdx)
    if not best:
        return empty, empty
    ia = np.fromiter((v[1] for v in best.values()), np.int64, len(best))
    ib = np.fromiter(best.keys(), np.int64, len(best))
    if by_distance:
        order = np.argsort(np.fromiter((v[0] for v in best.values()), np.float64, len(best)), kind="stable")
        ia, ib = ia[order], ib[order]
    return ia, ib


@pytest.mark.parametrize("seed", range(3))
def test_the_ratio_test_loop_gives_the_reference_s_matches_in_its_order(seed):
    """Binary descriptors with many shared and tied ones (several old keypoints nearest to
    one new keypoint, equal distances) and float ones: the same index pairs in the same
    order as the loop before."""
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    a = base[rng.integers(0, 40, 300)].copy()
    a[rng.random(a.shape) < 0.02] ^= np.uint8(1)   # near copies: several old keypoints per new one
    b = base[rng.integers(0, 40, 250)].copy()
    b[rng.random(b.shape) < 0.01] ^= np.uint8(4)
    fa = Features(rng.uniform(0, 640, (300, 2)).astype(np.float32), a, (640, 480))
    fb = Features(rng.uniform(0, 640, (250, 2)).astype(np.float32), b, (640, 480))
    ff = Features(rng.uniform(0, 640, (80, 2)).astype(np.float32), rng.normal(size=(80, 16)).astype(np.float32),
                  (640, 480))
    for x, y in ((fa, fb), (fb, fa), (ff, ff)):
        for ratio in (0.8, 0.95, 1.0):
            for by_distance in (False, True):
                got = match_indices(x, y, ratio, by_distance)
                ref = _match_indices_reference(x, y, ratio, by_distance)
                assert len(ref[0]) > 0
                assert got[0].dtype == got[1].dtype == np.int64
                assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])


def _outcome(v) -> tuple:
    """Every field of a verification, arrays as bytes (the same to the bit or not)."""
    out = []
    for name in v.__dataclass_fields__:
        x = getattr(v, name)
        if isinstance(x, np.ndarray):
            x = (x.dtype.str, x.shape, x.tobytes())
        elif isinstance(x, tuple):
            x = tuple(a.tobytes() for a in x)
        out.append((name, x))
    return tuple(out)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("model", ["planar", "general"])
def test_the_matches_through_k_inverse_once_give_the_outcome_of_each_step_computing_its_own(monkeypatch, seed, model):
    """The verification computes the matches' normalised coordinates once and hands them
    (or the inliers' rows of them) to every step; the reference is each step computing its
    own from the pixels, as before: every field of the outcome the same to the bit, on level,
    tilted (the fallback in its band) and shuffled pairs."""
    import robotd.forward.planefit as planefit_mod
    import robotd.forward.verify as verify_mod

    rng = np.random.default_rng(100 + seed)
    cases = []
    old, new, _, _ = _level_pair_with_shuffled(rng)
    cases.append((old, new))
    x_old, x_new, _, _ = _tilted_scene(rng, 3.0 + seed)
    desc = rng.standard_normal((150, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    px_new = _project(x_new) + rng.normal(0, 0.5, (150, 2)).astype(np.float32)
    cases.append((_features(_project(x_old), desc), _features(px_new, desc)))
    cases.append((_features(_project(x_old), desc), _features(px_new[rng.permutation(150)], desc)))
    params = [VerifyParams(model=model, seed=seed),
              VerifyParams(model=model, seed=seed, guided_estimator="usac", fallback_band_px=10.0,
                           camera_height_m=0.3)]
    got = [_outcome(verify_pair(a, b, p)) for a, b in cases for p in params]

    def dropping(f):
        def call(*args, normalised=None, **kwargs):
            return f(*args, **kwargs)
        return call

    inliers = planefit_mod.PlanarSearch.inliers
    monkeypatch.setattr(verify_mod, "ransac_planar", dropping(verify_mod.ransac_planar))
    monkeypatch.setattr(verify_mod, "fit_motion", dropping(verify_mod.fit_motion))
    monkeypatch.setattr(planefit_mod.PlanarSearch, "inliers",
                        lambda self, a, b, k, thr, normalised=None: inliers(self, a, b, k, thr))
    mask = verify_mod._epipolar_mask
    monkeypatch.setattr(verify_mod, "_epipolar_mask", lambda a, b, k, e, thr, normalised=None: mask(a, b, k, e, thr))
    reference = [_outcome(verify_pair(a, b, p)) for a, b in cases for p in params]
    assert got == reference
    assert any(dict(g)["accepted"] for g in got) and not all(dict(g)["accepted"] for g in got)


def test_normalised_points_of_a_subset_are_the_rows_of_the_whole():
    """Each row of :func:`robotd.forward.planar.normalised_points` does not depend on the
    rows computed with it (the verification takes the inliers' rows of the whole)."""
    from robotd.forward.planar import normalised_points

    rng = np.random.default_rng(3)
    for n in (1, 2, 5, 17, 64, 65, 255, 256, 257, 300):
        p_old = (rng.random((n, 2)) * [640, 480]).astype(np.float32)
        p_new = (rng.random((n, 2)) * [640, 480]).astype(np.float32)
        xo, xn = normalised_points(p_old, p_new, K)
        keep = rng.random(n) < 0.5
        so, sn = normalised_points(p_old[keep], p_new[keep], K)
        assert xo[keep].tobytes() == so.tobytes() and xn[keep].tobytes() == sn.tobytes()
        kinv = np.linalg.inv(K)
        assert xo.tobytes() == (np.hstack([p_old, np.ones((n, 1))]) @ kinv.T).tobytes()


def _guided_fails(monkeypatch, verify_mod) -> list[int]:
    """The search near the level motion made to fail (the first ``_general_motion`` call of
    each verification), so the band fallback runs; the calls' ``half_inliers`` recorded."""
    inner = verify_mod._general_motion
    calls: list[int] = []

    def first_fails(p_o, p_n, k, prm, n, near=None, half_inliers=True, normalised=None):
        calls.append(int(half_inliers))
        if half_inliers:
            return verify_mod.Verification(False, NO_GEOMETRIC_CONSISTENCY, n, 0)
        return inner(p_o, p_n, k, prm, n, near, half_inliers, normalised)

    monkeypatch.setattr(verify_mod, "_general_motion", first_fails)
    return calls


def _same_outcome(a, b) -> bool:
    return (a.accepted, a.reason, a.n_matches, a.n_inliers, a.fallback) == (
        b.accepted, b.reason, b.n_matches, b.n_inliers, b.fallback) and (
        (a.rotation is None and b.rotation is None) or np.array_equal(a.rotation, b.rotation)) and (
        (a.translation_dir is None and b.translation_dir is None) or np.array_equal(a.translation_dir,
                                                                                      b.translation_dir))


def test_the_band_screen_passes_what_both_searches_find_and_the_general_search_decides(monkeypatch):
    """``fallback_screen``: a true pair whose consensus both USAC and RANSAC find in the band
    is not screened out, and the verification is RANSAC's own (the same motion to the bit
    as without the screen)."""
    import robotd.forward.verify as verify_mod

    old, new, r, _ = _level_pair_with_shuffled(np.random.default_rng(6))
    calls = _guided_fails(monkeypatch, verify_mod)
    base = VerifyParams(model="planar", fallback_inliers=0, fallback_band_px=10.0)
    without = verify_pair(old, new, base)
    assert calls == [1, 0]
    calls.clear()
    screened = verify_pair(old, new, VerifyParams(**{**base.__dict__, "fallback_screen": "usac"}))
    assert calls == [1, 0]  # the screen passed: the band's general search ran
    assert without.accepted and without.fallback and not without.screened
    assert screened.accepted and not screened.screened and _same_outcome(screened, without)
    assert _angle_deg(screened.rotation, r) < 0.3


def test_the_band_screen_can_only_refuse(monkeypatch):
    """The screen never accepts on its own: when it passes and the band's general search
    (RANSAC) refuses, the candidate is refused; when it refuses, RANSAC is not run."""
    import robotd.forward.verify as verify_mod

    old, new, _, _ = _level_pair_with_shuffled(np.random.default_rng(6))
    _guided_fails(monkeypatch, verify_mod)
    inner = verify_mod.essential_matrix
    estimators: list[str] = []

    def ransac_refuses(p_old, p_new, k, params):
        estimators.append(params.estimator)
        if params.estimator == "ransac":
            return None, None
        return inner(p_old, p_new, k, params)

    monkeypatch.setattr(verify_mod, "essential_matrix", ransac_refuses)
    params = VerifyParams(model="planar", fallback_inliers=0, fallback_band_px=10.0, fallback_screen="usac")
    v = verify_pair(old, new, params)
    assert estimators == ["usac", "ransac"]  # the screen found the consensus, RANSAC then decided
    assert not v.accepted and v.reason == NO_GEOMETRIC_CONSISTENCY and v.fallback and not v.screened
    # The screen finding nothing: refused as screened, RANSAC not run.
    estimators.clear()
    monkeypatch.setattr(verify_mod, "_screen_passes", lambda *args: False)
    v = verify_pair(old, new, params)
    assert estimators == [] and not v.accepted and v.fallback and v.screened


def test_the_band_screen_accepts_a_subset_of_what_ransac_accepts(monkeypatch):
    """Pairs near the acceptance threshold (16-34 true matches among 60, the rest shuffled):
    with the screen every accepted pair is accepted without it with the same motion, and
    every pair the screen lets through has the same outcome as without it."""
    import robotd.forward.verify as verify_mod

    _guided_fails(monkeypatch, verify_mod)
    rng = np.random.default_rng(100)
    base = VerifyParams(model="planar", fallback_inliers=0, fallback_band_px=10.0)
    on_params = VerifyParams(**{**base.__dict__, "fallback_screen": "usac"})
    accepted = screened = 0
    for n_true in [*range(16, 35, 2)] * 3:
        x_old, x_new, _, _ = _scene(rng, 60)
        desc = rng.standard_normal((60, 32)).astype(np.float32)
        desc /= np.linalg.norm(desc, axis=1, keepdims=True)
        px_new = _project(x_new) + rng.normal(0, 0.3, (60, 2)).astype(np.float32)
        shuffled = rng.permutation(np.arange(n_true, 60))
        px_new[n_true:] = px_new[shuffled]
        old, new = _features(_project(x_old), desc), _features(px_new, desc)
        off, on = verify_pair(old, new, base), verify_pair(old, new, on_params)
        assert not on.accepted or off.accepted
        if not on.screened:
            assert _same_outcome(on, off)
        accepted += on.accepted
        screened += on.screened
    assert accepted > 0 and screened > 0


@pytest.mark.parametrize("seed", [1, 2])  # scenes whose level search misses (the assertion on ``due`` below)
def test_a_fallback_run_later_gives_the_answer_of_the_fallback_at_once(seed):
    """``defer_fallback``: a planar check that fails near its level motion with its fallback
    due comes back as a :class:`~robotd.forward.verify.DueFallback` (the failed check's own
    fields, and the work); :func:`~robotd.forward.verify.fallback_verification` then gives
    every field of the verification run at once, to the bit. A check that passes, or has no
    fallback due, comes back as it would at once."""
    from robotd.forward.verify import DueFallback, fallback_verification

    rng = np.random.default_rng(seed)
    x_old, x_new, _, _ = _tilted_scene(rng, 22.0)
    desc = rng.standard_normal((150, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    tilted = (_features(_project(x_old), desc), _features(_project(x_new), desc))
    level = _level_pair_with_shuffled(rng)[:2]
    due = 0
    for old, new in (tilted, level):
        for p in (VerifyParams(model="planar", fallback_inliers=0, seed=seed),
                  VerifyParams(model="planar", fallback_inliers=0, guided_estimator="usac", fallback_band_px=10.0,
                               seed=seed)):
            at_once = verify_pair(old, new, p)
            later = verify_pair(old, new, replace(p, defer_fallback=True))
            if isinstance(later, DueFallback):
                due += 1
                assert not later.accepted and not later.fallback
                assert _outcome(later.checked()) == _outcome(verify_pair(old, new, replace(p, fallback_inliers=None)))
                later = fallback_verification(later)
                assert later.fallback
            assert type(later) is Verification and _outcome(later) == _outcome(at_once)
    assert due >= 2  # the tilted pair's fallback was due under both parameters
    with pytest.raises(ValueError):
        fallback_verification(DueFallback(False, NO_GEOMETRIC_CONSISTENCY, 0, 0))


def test_a_small_plane_among_scattered_inliers_is_judged_by_its_homography():
    """The support test's homography is fitted when all the inliers cover enough of the
    image: a small poster (80 matches) with 12 matches of points spread over the scene is
    one plane by the homography (at least 80 % of the inliers on it), so only the poster's
    inliers are support, and they cover too little; without the scattered points all the
    inliers already cover too little, refused without the homography. Either way the
    answer is the support test's."""
    rng = np.random.default_rng(7)
    old, new = _plane_pair(rng, 0.5, 0.4)
    x_far = np.column_stack([rng.uniform(-3, 3, 12), rng.uniform(-1.5, 1.5, 12), rng.uniform(4, 8, 12)])
    r = _rot_y(np.radians(10))
    t = np.array([0.3, 0.0, -0.4])
    desc = rng.standard_normal((12, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    old2 = _features(np.vstack([old.keypoints_px, _project(x_far)]), np.vstack([old.descriptors, desc]))
    new2 = _features(np.vstack([new.keypoints_px, _project(x_far @ r.T + t)]), np.vstack([new.descriptors, desc]))
    v = verify_pair(old2, new2)
    assert not v.accepted and v.reason == SMALL_SUPPORT
    assert v.planar and v.n_inliers > 80 and v.n_plane_inliers >= 0.8 * v.n_inliers
    assert 0.005 < v.support_area < 0.03
    alone = verify_pair(old, new)
    assert alone.reason == SMALL_SUPPORT and not alone.planar and alone.support_area < 0.03
