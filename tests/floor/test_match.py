"""Matching floor descriptors: the local score finds the geometric inliers of views with a
known rigid motion and dismisses unrelated floors with a reason; the global score is 1 for
identical images, about 0.5 for unrelated ones and higher for overlapping views."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
import skimage.data

from robotd.floor.descriptor import describe
from robotd.floor.match import (BELOW_MIN_SCORE, NO_GEOMETRIC_CONSISTENCY, TOO_FEW_FEATURES, TOO_FEW_MATCHES,
                                Matcher, MatchParams, _ransac_best, _hypotheses, _ransac_pairs, global_score,
                                local_score)
from robotd.base.camera import FloorCameraModel
from robotd.base.geometry import inverse, rigid_fit_2d, transform_points
from sim.world.floor import Floor
from sim.cameras.floor import FloorRenderer, RenderParams

PHOTOS = ("brick", "grass", "gravel")
DISMISSALS = {TOO_FEW_FEATURES, TOO_FEW_MATCHES, NO_GEOMETRIC_CONSISTENCY}
W, H = 640, 480
CENTRE = (600.0, 600.0)  # of the source textures, px


@pytest.fixture(scope="module")
def textures() -> dict[str, np.ndarray]:
    """``(1201, 1201) uint8`` of quilted floor (1 mm/px) per photo: room for any rotation
    of a 640 x 480 view up to 200 px off the centre, without black borders."""
    return {name: Floor.from_photos([getattr(skimage.data, name)()], seed=50 + i).patch(0.0, 0.0, 1.2, 1.2)[0]
            for i, name in enumerate(PHOTOS)}


def _view(texture: np.ndarray, theta_rad: float, centre: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """A 640 x 480 view whose centre sees ``centre`` (texture px), turned by ``theta_rad``.

    Returns the image and the ``(2, 3)`` affine from texture px to view px.
    """
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    m = np.array([[c, -s, 0.0], [s, c, 0.0]])
    m[:, 2] = np.array([(W - 1) / 2, (H - 1) / 2]) - m[:, :2] @ np.asarray(centre)
    return cv2.warpAffine(texture, m, (W, H), flags=cv2.INTER_LINEAR), m


def _a_to_b(m_a: np.ndarray, m_b: np.ndarray) -> np.ndarray:
    """``(2, 3)`` ground truth: view A px -> texture px -> view B px."""
    inv_a = cv2.invertAffineTransform(m_a)
    return np.column_stack([m_b[:, :2] @ inv_a[:, :2], m_b[:, :2] @ inv_a[:, 2] + m_b[:, 2]])


def _apply(t: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return np.asarray(xy, float) @ t[:, :2].T + t[:, 2]


GRID = np.array([[x, y] for x in (0.0, 320.0, 639.0) for y in (0.0, 240.0, 479.0)])


def _check_inliers_index_the_keypoints(r, a, b) -> None:
    k = r.n_inliers
    assert r.inliers_a.shape == r.inliers_b.shape == (k,) and r.inliers_a.dtype == np.int64
    assert r.xy_a.shape == r.xy_b.shape == (k, 2)
    assert np.array_equal(a.xy_px[r.inliers_a], r.xy_a) and np.array_equal(b.xy_px[r.inliers_b], r.xy_b)
    assert len(np.unique(r.inliers_a)) == k  # a keypoint of A is matched at most once
    assert k <= r.n_matches


def _check_dismissed(r, reason: str | None = None) -> None:
    assert r.score == 0.0 and r.n_inliers == 0 and r.transform is None and math.isnan(r.rotation_rad)
    assert r.reason in DISMISSALS if reason is None else r.reason == reason
    assert r.inliers_a.shape == r.inliers_b.shape == (0,) and r.xy_a.shape == r.xy_b.shape == (0, 2)


# ----------------------------------------------------------------------------- local score

@pytest.mark.parametrize("mode", [1, 4, 6])
def test_self_match_is_perfect(textures, mode):
    d = describe(_view(textures["brick"], 0.4, CENTRE)[0], mode)
    r = local_score(d, d)
    assert r.reason == ""
    assert r.n_inliers >= 0.9 * len(d) and r.score >= 0.9 * len(d)
    assert r.score <= r.n_inliers  # each inlier weighs at most 1
    assert np.mean(r.inliers_a == r.inliers_b) >= 0.95  # keypoints match themselves
    assert np.allclose(r.transform, [[1, 0, 0], [0, 1, 0]], atol=1e-6)
    _check_inliers_index_the_keypoints(r, d, d)


@pytest.mark.parametrize("photo", PHOTOS)
@pytest.mark.parametrize("theta_rad, offset_px", [(0.3, (40, -25)), (1.2, (100, 60)), (-2.5, (-150, 80)),
                                                  (3.0, (200, 0))])
@pytest.mark.parametrize("mode", [1, 3, 6])
def test_rotated_and_shifted_view_gives_the_true_transform(textures, photo, theta_rad, offset_px, mode):
    tex = textures[photo]
    img_a, m_a = _view(tex, 0.0, CENTRE)
    img_b, m_b = _view(tex, theta_rad, (CENTRE[0] + offset_px[0], CENTRE[1] + offset_px[1]))
    truth = _a_to_b(m_a, m_b)
    a, b = describe(img_a, mode), describe(img_b, mode)
    r = local_score(a, b)
    assert r.reason == "" and r.transform is not None
    # A quarter of A's keypoints that B sees (the views overlap by 80-100 % of them here).
    seen = _apply(truth, a.xy_px)
    visible = int(np.sum((seen[:, 0] >= 0) & (seen[:, 0] < W) & (seen[:, 1] >= 0) & (seen[:, 1] < H)))
    assert r.n_inliers >= max(15, 0.25 * visible), (r.n_inliers, visible, len(a))
    assert 0.5 * r.n_inliers <= r.score <= r.n_inliers
    _check_inliers_index_the_keypoints(r, a, b)
    # The inliers are true correspondences (positions are coded on a 2 px grid in each image;
    # a wrong match that happens to fall within inlier_px of the right place is rare).
    err = np.linalg.norm(_apply(truth, r.xy_a) - r.xy_b, axis=1)
    assert np.median(err) <= 1.5 and np.mean(err <= 3.0) >= 0.95, (np.median(err), np.mean(err <= 3.0))
    assert err.max() <= MatchParams().inlier_px + 2.0
    # ... and consistent with the returned transform within MatchParams.inlier_px.
    assert np.all(np.linalg.norm(_apply(r.transform, r.xy_a) - r.xy_b, axis=1) <= MatchParams().inlier_px)
    assert abs(math.remainder(r.rotation_rad - theta_rad, 2 * math.pi)) <= math.radians(2)
    assert np.allclose(r.transform[:, :2] @ r.transform[:, :2].T, np.eye(2), atol=1e-9)  # rigid
    assert np.abs(_apply(r.transform, GRID) - _apply(truth, GRID)).max() <= 2.0


def test_swapping_the_views_inverts_the_transform(textures):
    tex = textures["gravel"]
    a = describe(_view(tex, 0.0, CENTRE)[0], 4)
    b = describe(_view(tex, 0.9, (680.0, 560.0))[0], 4)
    ab, ba = local_score(a, b), local_score(b, a)
    assert abs(math.remainder(ab.rotation_rad + ba.rotation_rad, 2 * math.pi)) <= 0.01
    assert np.abs(_apply(ba.transform, _apply(ab.transform, GRID)) - GRID).max() <= 1.5


def test_local_score_is_deterministic(textures):
    tex = textures["grass"]
    a = describe(_view(tex, 0.0, CENTRE)[0], 2)
    b = describe(_view(tex, -1.0, (520.0, 640.0))[0], 2)
    r1, r2 = local_score(a, b), local_score(a, b)
    assert r1.score == r2.score and np.array_equal(r1.inliers_a, r2.inliers_a)
    assert np.array_equal(r1.transform, r2.transform)


def test_min_score_skips_only_pairs_that_cannot_reach_it(textures):
    """A pair whose score is at least ``min_score`` is scored exactly as without it; an
    unrelated pair below it is dismissed before the geometric check (BELOW_MIN_SCORE);
    :class:`Matcher` (one query, many stored) gives local_score's results."""
    tex = textures["gravel"]
    a = describe(_view(tex, 0.0, CENTRE)[0], 4)
    near = describe(_view(tex, 0.7, (660.0, 560.0))[0], 4)
    other = describe(_view(textures["brick"], 0.3, CENTRE)[0], 4)
    full = local_score(a, near)
    assert full.score > 20
    for min_score in (0.5 * full.score, full.score):
        r = local_score(a, near, min_score=min_score)
        assert r.score == full.score and np.array_equal(r.inliers_b, full.inliers_b)
    unrelated = local_score(a, other)
    assert unrelated.score < 0.1 * full.score
    skipped = local_score(a, other, min_score=full.score)
    assert skipped.reason == BELOW_MIN_SCORE and skipped.score == 0.0 and skipped.transform is None
    assert skipped.n_matches == unrelated.n_matches  # step 1 ran: its matches are counted
    m = Matcher(a)
    for b in (near, other):
        assert m.score(b).score == local_score(a, b).score
        assert m.score(b, full.score).reason == local_score(a, b, min_score=full.score).reason


@pytest.mark.parametrize("mode", [1, 3, 6])
def test_unrelated_floors_score_near_zero(textures, mode):
    def pair(pa, centre_a, pb, centre_b):
        return (describe(_view(textures[pa], 0.0, centre_a)[0], mode),
                describe(_view(textures[pb], 0.5, centre_b)[0], mode))

    true_pair = local_score(*pair("brick", CENTRE, "brick", (650.0, 580.0)))
    pairs = [pair(pa, CENTRE, pb, (500.0, 700.0)) for pa, pb in [("brick", "grass"), ("grass", "gravel"),
                                                                 ("gravel", "brick")]]
    # The same floor, but views that do not overlap (the texture's opposite corners).
    pairs.append(pair("brick", (330.0, 250.0), "brick", (900.0, 950.0)))
    results = [local_score(a, b) for a, b in pairs]
    for (a, b), r in zip(pairs, results):
        assert r.score <= 0.1 * true_pair.score, (r.score, true_pair.score)
        assert r.n_matches <= 0.5 * min(len(a), len(b))  # the ratio test drops most chance matches
        if r.score == 0.0:
            _check_dismissed(r)
    assert sum(r.score == 0.0 for r in results) >= 3  # most are dismissed outright


def test_empty_descriptor_is_too_few_features(textures):
    blank = describe(np.full((H, W), 90, np.uint8), 3)
    textured = describe(_view(textures["brick"], 0.0, CENTRE)[0], 3)
    assert len(blank) == 0
    for a, b in [(blank, textured), (textured, blank), (blank, blank)]:
        r = local_score(a, b)
        _check_dismissed(r, TOO_FEW_FEATURES)
        assert r.n_matches == 0


def test_dismissal_reasons_follow_the_steps(textures):
    tex = textures["gravel"]
    a = describe(_view(tex, 0.0, CENTRE)[0], 3)
    b = describe(_view(tex, 0.7, (620.0, 640.0))[0], 3)
    ok = local_score(a, b)
    assert ok.reason == "" and ok.n_matches >= 20
    # Step 1 as before, but more matches demanded than it finds.
    r = local_score(a, b, MatchParams(min_matches=ok.n_matches + 1))
    _check_dismissed(r, TOO_FEW_MATCHES)
    assert r.n_matches == ok.n_matches
    assert local_score(a, b, MatchParams(min_matches=ok.n_matches)).reason == ""
    # Steps 1-2 as before, but more inliers demanded than there are matches.
    r = local_score(a, b, MatchParams(min_inliers=ok.n_matches + 1))
    _check_dismissed(r, NO_GEOMETRIC_CONSISTENCY)
    assert r.n_matches == ok.n_matches  # the result still says how far it got
    # One inlier more than the refined transform has (min_inliers plays no part in RANSAC).
    assert local_score(a, b, MatchParams(min_inliers=ok.n_inliers)).n_inliers == ok.n_inliers
    r = local_score(a, b, MatchParams(min_inliers=ok.n_inliers + 1))
    _check_dismissed(r, NO_GEOMETRIC_CONSISTENCY)
    assert r.n_matches == ok.n_matches


def test_ambiguous_matches_fail_the_ratio_test(textures):
    """B with every keypoint twice: each nearest neighbour has an equal second, so Lowe's
    ratio test keeps none, although every descriptor has an exact match."""
    tex = textures["brick"]
    a = describe(_view(tex, 0.0, CENTRE)[0], 3)
    doubled = dataclasses.replace(a, **{f: np.concatenate([getattr(a, f)] * 2)
                                        for f in ("xy_px", "angle_rad", "local_pos", "local_neg")})
    assert len(doubled) == 2 * len(a)
    _check_dismissed(local_score(a, doubled), TOO_FEW_MATCHES)
    assert local_score(a, doubled, MatchParams(ratio=1.0)).n_matches == 0  # d1 < d2 is strict
    assert local_score(a, a).n_matches >= 0.9 * len(a)


def test_different_modes_are_refused(textures):
    img = _view(textures["brick"], 0.0, CENTRE)[0]
    a, b = describe(img, 2), describe(img, 3)
    with pytest.raises(ValueError, match="modes differ"):
        local_score(a, b)
    with pytest.raises(ValueError, match="modes differ"):
        global_score(a, b)


@pytest.mark.parametrize("field, value", [("ratio", 0.0), ("ratio", 1.5), ("max_distance", 0.0),
                                          ("iterations", 0), ("min_inliers", 1), ("min_matches", 1),
                                          ("inlier_px", -1.0), ("confidence", 1.0), ("confidence", -0.1)])
def test_match_params_out_of_range(field, value):
    with pytest.raises(ValueError, match="out of range"):
        MatchParams(**{field: value})


# ----------------------------------------------------------------------------- virtual robot

@pytest.fixture(scope="module")
def robot_views():
    """Frames of the virtual robot's floor camera at known poses on one floor."""
    cam = FloorCameraModel.default()
    floor = Floor.from_photos([skimage.data.gravel()], seed=11)
    renderer = FloorRenderer(floor, cam, RenderParams(), np.random.default_rng(3))
    poses = {"a": np.array([0.5, 0.2, 0.3]), "near": np.array([0.6, 0.15, 1.3]),
             "turned": np.array([0.42, 0.3, -2.0]), "far": np.array([2.5, -1.0, 0.3])}
    images = {k: renderer.render(p, 0.1, 0.0, i) for i, (k, p) in enumerate(poses.items())}
    return cam, poses, images


def _robot_truth(cam: FloorCameraModel, pose_a: np.ndarray, pose_b: np.ndarray, xy_a: np.ndarray) -> np.ndarray:
    """Where pixels of frame A see the floor in frame B, px (lens distortion included)."""
    world = transform_points(pose_a, cam.pixel_to_floor_robot(np.asarray(xy_a, float)))
    return cam.floor_robot_to_pixel(transform_points(inverse(pose_b), world))


@pytest.mark.parametrize("other", ["near", "turned"])
@pytest.mark.parametrize("mode", [1, 4, 6])
def test_overlapping_robot_frames_match_the_ground_truth(robot_views, other, mode):
    cam, poses, images = robot_views
    a, b = describe(images["a"], mode), describe(images[other], mode)
    r = local_score(a, b)
    assert r.reason == "" and r.n_inliers >= max(15, 0.25 * len(a))
    _check_inliers_index_the_keypoints(r, a, b)
    err = np.linalg.norm(_robot_truth(cam, poses["a"], poses[other], r.xy_a) - r.xy_b, axis=1)
    assert np.median(err) <= 2.0 and np.mean(err <= 4.0) >= 0.9, (np.median(err), err.max())
    # The image rotation, from the ground truth of a grid of pixels (whatever its sign convention).
    inner = GRID * 0.6 + [128, 96]
    _, _, true_rot = rigid_fit_2d(inner, _robot_truth(cam, poses["a"], poses[other], inner))
    assert abs(math.remainder(r.rotation_rad - true_rot, 2 * math.pi)) <= math.radians(2)
    far = local_score(a, describe(images["far"], mode))
    assert far.score <= 0.1 * r.score


# ----------------------------------------------------------------------------- global score

def test_global_score_identical_unrelated_and_overlapping(textures):
    mode = 4
    same, unrelated, overlapping = [], [], []
    for i, photo in enumerate(PHOTOS):
        tex = textures[photo]
        a = describe(_view(tex, 0.0, CENTRE)[0], mode)
        same.append(global_score(a, a))
        for theta, dx in [(0.4, 60.0), (2.0, -120.0)]:
            overlapping.append(global_score(a, describe(_view(tex, theta, (CENTRE[0] + dx, 620.0))[0], mode)))
        other = textures[PHOTOS[(i + 1) % 3]]
        for theta, centre in [(0.0, CENTRE), (1.0, (450.0, 700.0))]:
            unrelated.append(global_score(a, describe(_view(other, theta, centre)[0], mode)))
    assert same == [1.0] * 3
    assert all(0.3 <= s <= 0.7 for s in unrelated), unrelated
    assert 0.4 <= np.mean(unrelated) <= 0.6
    assert np.mean(overlapping) >= np.mean(unrelated) + 0.1, (overlapping, unrelated)
    assert min(overlapping) > max(unrelated) - 0.05


def test_global_score_counts_differing_bits(textures):
    """``1 - hamming / bits``, checked against bits flipped by hand."""
    d = describe(_view(textures["grass"], 0.0, CENTRE)[0], 1)  # 256 global bits
    bits = d.global_bits.copy()
    bits[0] ^= 0b1000_0001
    bits[5] ^= 0b0001_0000
    flipped = dataclasses.replace(d, global_bits=bits)
    assert global_score(d, flipped) == pytest.approx(1 - 3 / 256)
    inverted = dataclasses.replace(d, global_bits=~d.global_bits)
    assert global_score(d, inverted) == 0.0


@pytest.fixture(scope="module")
def plank_views() -> dict[str, np.ndarray]:
    """Virtual-robot frames on the printed plank floor (``sim.world.pattern``: 4 prints of
    the gravel photo on staggered 0.45 x 0.12 m planks): ``here``; ``lattice``, one plank
    row up (0.15 m along, 0.12 m across: where the stagger repeats the plank layout);
    ``near``, 5 cm ahead. At ``here`` most planks one lattice step away carry the same print."""
    from sim.world.pattern import PatternFloor, PatternParams

    floor = PatternFloor(skimage.data.gravel(), PatternParams(kind="planks"), 0.001, seed=1)
    renderer = FloorRenderer(floor, FloorCameraModel.default(), RenderParams(), np.random.default_rng(0))
    here = np.array([1.108, 0.255, -1.926])
    ahead = 0.05 * np.array([math.cos(here[2]), math.sin(here[2]), 0.0])
    return {name: renderer.render(here + d, 0.0, 0.0, 0.0)
            for name, d in (("here", np.zeros(3)), ("lattice", np.array([0.15, 0.12, 0.0])), ("near", ahead))}


@pytest.mark.parametrize("mode", [2, 3, 5])
def test_plank_views_a_lattice_step_apart_do_not_match_like_a_true_overlap(plank_views, mode):
    """Keypoints that repeat within their image are not coded, so the view a lattice step
    away scores under half the true 5 cm overlap. Coding them (``repeat_distance=0``), it
    matched at the identity with more inliers than the true overlap: the alias the plank
    floor's loop thresholds failed on."""
    from robotd.floor.descriptor import ExtractParams

    for params in (ExtractParams(repeat_distance=0.0), ExtractParams()):
        here = describe(plank_views["here"], mode, params)
        alias = local_score(here, describe(plank_views["lattice"], mode, params))
        true = local_score(here, describe(plank_views["near"], mode, params))
        assert np.linalg.norm(true.transform[:, 2]) == pytest.approx(50.0, abs=5.0)  # 5 cm at 1 mm/px
        if params.repeat_distance == 0.0:
            assert alias.score > true.score
            assert np.linalg.norm(alias.transform[:, 2]) < 5.0  # the identity; the truth is 192 px away
        else:
            assert alias.score < 0.5 * true.score


# ----------------------------------------------------------------------------- adaptive RANSAC

def _synthetic_matches(n: int, inlier_fraction: float, yaw_rad: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(n, 4)`` matches (x, y in A, then in B, px): the first ``inlier_fraction`` of them
    moved by one rigid motion (turned by ``yaw_rad``), the rest anywhere in B; and the
    ``(n,) bool`` truth of which are inliers."""
    rng = np.random.default_rng(seed)
    xa = rng.uniform((0, 0), (W, H), (n, 2))
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    xb = xa @ np.array([[c, -s], [s, c]]).T + (35.0, -20.0)
    truth = np.arange(n) < round(inlier_fraction * n)
    xb[~truth] = rng.uniform((0, 0), (W, H), (int(np.sum(~truth)), 2))
    return np.concatenate([xa, xb], axis=1), truth


def _adaptive(xab: np.ndarray, yaw_rad: float, p: MatchParams) -> tuple[np.ndarray | None, int]:
    m = len(xab)
    i, j = _ransac_pairs(p.seed, m, p.iterations)
    xa1 = np.vstack([xab[:, :2].T, np.ones(m)])
    return _ransac_best(xab, i, j, yaw_rad, xa1, xab[:, 2:], np.ones(m), p)


def _all_hypotheses(xab: np.ndarray, yaw_rad: float, p: MatchParams) -> int:
    i, j = _ransac_pairs(p.seed, len(xab), p.iterations)
    hyp = _hypotheses(xab, i, j, yaw_rad, p)
    return 0 if hyp is None else len(hyp[0])


@pytest.mark.parametrize("fraction, needed", [(1.0, 1), (0.8, 5), (0.6, 11)])
def test_adaptive_ransac_stops_when_the_inlier_fraction_says_enough(fraction, needed):
    """A 0.99 confidence asks for log(0.01) / log(1 - w**2) hypotheses at an inlier
    fraction w: 4.5 at 80 % (the first block decides), 10.3 at 60 % (a later block); the
    check stops at the first block that reaches it, fewer than all the draws give, and the
    mask is the true inliers."""
    p = MatchParams(confidence=0.99)
    xab, truth = _synthetic_matches(200, fraction, 0.6, seed=3)
    mask, scored = _adaptive(xab, 0.6, p)
    assert mask is not None and np.array_equal(mask, truth)
    assert needed <= scored < _all_hypotheses(xab, 0.6, p)
    assert fraction < 0.8 or scored <= 10


def test_adaptive_ransac_scores_every_hypothesis_without_a_consensus():
    """Matches without a common motion, or with too few inliers for the draws to give the
    hypotheses the confidence asks for: every draw's hypothesis is scored, as without the
    adaptive stop."""
    p = MatchParams(confidence=0.99)
    for fraction, seed in [(0.0, 4), (0.4, 3)]:  # at 40 % the draws give 17 hypotheses, 26.4 are asked for
        xab, truth = _synthetic_matches(200, fraction, 0.6, seed=seed)
        mask, scored = _adaptive(xab, 0.6, p)
        assert mask is not None and scored == _all_hypotheses(xab, 0.6, p) > 0
        assert np.count_nonzero(mask) < 0.1 * len(xab) if fraction == 0 else np.array_equal(mask, truth)


@pytest.mark.parametrize("mode", [1, 4])
def test_adaptive_ransac_finds_the_same_overlap(textures, mode):
    """A turned and shifted view: with the adaptive stop the pair is matched with the same
    inliers and transform as with every hypothesis scored (the first block holds a best
    hypothesis whose refinement converges to the same inliers)."""
    tex = textures["gravel"]
    a = describe(_view(tex, 0.0, CENTRE)[0], mode)
    b = describe(_view(tex, 0.7, (660.0, 560.0))[0], mode)
    full, adaptive = local_score(a, b), local_score(a, b, MatchParams(confidence=0.99))
    assert full.reason == adaptive.reason == "" and full.n_inliers >= 15
    assert adaptive.score == full.score and np.array_equal(adaptive.inliers_a, full.inliers_a)
    assert np.array_equal(adaptive.transform, full.transform)
