"""The detector's levers beyond the paper: temporal consistency, the score
decision, the method presets."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from robotd.forward import (LOOP, LOW_POSTERIOR, NO_GEOMETRIC_CONSISTENCY, NOT_CONSISTENT_YET, DetectorParams, FilterParams, ForwardDetector,
                            method_params)
from robotd.forward.detector import OdometryParams, bounded_verification, odometry_factor, unbounded_verification
from robotd.forward.features import FeatureParams, Features
from robotd.forward.verify import VerifyParams


def _views(n_places: int, revisit: list[int], seed: int = 0) -> list[Features]:
    """Binary features of ``n_places`` distinct places, then revisits of the places in
    ``revisit`` (the same descriptors with a few bits flipped, the same keypoints)."""
    rng = np.random.default_rng(seed)
    places = [rng.integers(0, 256, (120, 32), dtype=np.uint8) for _ in range(n_places)]
    kps = [rng.uniform(0, 600, (120, 2)).astype(np.float32) for _ in range(n_places)]
    out = [Features(kps[i], places[i], (640, 480)) for i in range(n_places)]
    for i in revisit:
        d = places[i].copy()
        d[:, 0] ^= 0x03  # 2 bits of 256 flipped: well inside the word radius
        out.append(Features(kps[i], d, (640, 480)))
    return out


# No geometry in these views: verification accepts everything, so the decisions alone count.
ACCEPT_ALL = VerifyParams(min_inliers=0, min_support_area=0.0)


def _run(params: DetectorParams, views: list[Features], monkeypatch) -> list:
    import robotd.forward.detector as det_mod
    from robotd.forward.verify import ACCEPTED, Verification

    monkeypatch.setattr(det_mod, "verify_pair",
                        lambda old, new, p, k: Verification(True, ACCEPTED, 100, 100))
    det = ForwardDetector(params)
    return [det.process_features(v) for v in views]


def test_k_consistent_candidates_before_a_loop(monkeypatch):
    views = _views(30, [5, 6, 7, 8, 9])
    base = DetectorParams(features=FeatureParams(kind="orb"), decision="score", verify=ACCEPT_ALL)
    one = _run(base, views, monkeypatch)[30:]
    three = _run(replace(base, consistency=3), views, monkeypatch)[30:]
    assert [d.candidate_id for d in one] == [5, 6, 7, 8, 9]
    assert [d.status for d in one] == [LOOP] * 5
    # The same candidates; the first two wait for the run to reach three.
    assert [d.candidate_id for d in three] == [5, 6, 7, 8, 9]
    assert [d.status for d in three] == [NOT_CONSISTENT_YET] * 2 + [LOOP] * 3


def test_an_inconsistent_jump_restarts_the_run(monkeypatch):
    views = _views(30, [5, 6, 20, 21, 22])
    params = DetectorParams(features=FeatureParams(kind="orb"), decision="score", verify=ACCEPT_ALL,
                            consistency=2)
    got = _run(params, views, monkeypatch)[30:]
    assert [d.candidate_id for d in got] == [5, 6, 20, 21, 22]
    assert [d.status for d in got] == [NOT_CONSISTENT_YET, LOOP, NOT_CONSISTENT_YET, LOOP, LOOP]


def test_the_score_decision_needs_the_best_score_to_stand_out(monkeypatch):
    params = DetectorParams(features=FeatureParams(kind="orb"), decision="score", verify=ACCEPT_ALL)
    d = _run(params, _views(30, [4]), monkeypatch)[30]
    # Place 4's words are none of the virtual image's (the most frequent words: all seen
    # once, ties to the oldest, so place 0's): the ratio is unbounded.
    assert d.candidate_id == 4 and d.candidate_probability == float("inf") and d.status == LOOP
    # Place 0's words *are* the virtual image: its vote equals the virtual one, ratio 1.
    d0 = _run(params, _views(30, [0]), monkeypatch)[30]
    assert d0.candidate_probability == pytest.approx(1.0) and d0.candidate_id is None
    assert d0.status == LOW_POSTERIOR
    # Against the previous image (29, nothing in common) instead: unbounded too.
    d_prev = _run(replace(params, score_normalisation="previous"), _views(30, [0]), monkeypatch)[30]
    assert d_prev.candidate_id == 0 and d_prev.candidate_probability == float("inf")


def test_the_methods():
    paper = method_params("paper")
    assert paper == DetectorParams()
    assert (paper.features.kind, paper.filter.loop_threshold, paper.filter.rule) == ("sift", 0.8, "neighbourhood")
    default = method_params("default")
    assert default.verify_tries == 3 and default.consistency == 1
    # The odometry likelihood, with no support test for a candidate it agrees with; no other
    # metric lever.
    assert default.odometry.use and default.odometry.agree_min_support_area == 0.0
    assert not (default.odometry.merge_places or default.odometry.metric_neighbours or default.odometry.verify_place)
    assert (default.filter.rule, default.filter.loop_threshold) == ("total", 0.3)
    assert default.features.kind == "orb" and default.vocabulary.purge_after > 0
    # The planar verification with its work per image bounded: USAC near the level motion,
    # the general search within 10 px of it and once per image (the unbounded one is
    # selectable: RANSAC near the level motion, the general search over all the matches).
    v = default.verify
    assert (v.model, v.estimator, v.guided_estimator, v.fallback_estimator, v.fallback_band_px) == (
        "planar", "ransac", "usac", None, 10.0)
    assert default.verify_fallbacks == 1 and paper.verify_fallbacks is None and paper.verify.model == "general"
    assert bounded_verification(default) == default
    u = unbounded_verification(default)
    assert (u.verify.guided_estimator, u.verify.fallback_band_px, u.verify_fallbacks) == (None, None, None)
    assert bounded_verification(u) == default
    assert u.fallbacks_last is False and default.fallbacks_last is True
    assert replace(u, verify=default.verify, verify_fallbacks=1, fallbacks_last=True) == default
    assert not paper.odometry.use and paper.verify_tries == 1
    assert method_params("paper", recent_excluded=5).recent_excluded == 5
    with pytest.raises(ValueError):
        method_params("best")
    with pytest.raises(ValueError):
        DetectorParams(decision="vote")


def test_the_odometry_factor_by_hand():
    p = OdometryParams(use=True, place_sigma_m=1.0, place_sigma_yaw_rad=0.6)
    poses = np.array([[1.0, 0.0, 0.0],                     # 1 m ahead
                      [0.0, 0.0, 2 * np.pi - 0.1],        # 0.2 rad of heading, across the wrap
                      [3.0, 4.0, 0.0],                     # 5 m away, but more uncertain than now
                      [np.nan, np.nan, np.nan]])           # no pose
    var = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [9.0, 9.0, 0.0], [0.0, 0.0, 0.0]])
    f = odometry_factor(np.array([0.0, 0.0, 0.1]), np.array([0.25, 0.25, 0.0]), poses, var, p)
    # d^2 = 1 / (0.25 + 1) + 0.1^2 / 0.36; 0.2^2 / 0.36; (9 + 16) / 1 + 0.1^2 / 0.36 (the
    # accumulated variance is never negative); unknown: 1.
    assert f == pytest.approx(np.exp(-0.5 * np.array([1 / 1.25 + 0.01 / 0.36, 0.04 / 0.36, 25 + 0.01 / 0.36, 0.0])))


def test_the_odometry_turns_away_an_aliased_place(monkeypatch):
    """A revisit of place 5 seen where odometry puts the robot 20 m from it (an aliased
    corridor elsewhere) is no loop with the odometry lever; the same images at place 5's pose
    are one; without poses the lever changes nothing."""
    views = _views(30, [5, 6, 7, 8])
    along = [np.array([float(i), 0.0, 0.0]) for i in range(30)]
    cov = np.diag([0.01, 0.01, 0.001])
    base = DetectorParams(features=FeatureParams(kind="orb"), verify=ACCEPT_ALL,
                          filter=FilterParams(rule="total", loop_threshold=0.5))
    odo = replace(base, odometry=OdometryParams(use=True))

    def run(params, revisit_x, forget=False):
        import robotd.forward.detector as det_mod
        from robotd.forward.verify import ACCEPTED, Verification

        monkeypatch.setattr(det_mod, "verify_pair", lambda old, new, p, k: Verification(True, ACCEPTED, 100, 100))
        det = ForwardDetector(params)
        poses = along + [np.array([x, 0.0, 0.0]) for x in revisit_x]
        out = []
        for i, (v, q) in enumerate(zip(views, poses)):
            if forget and i == 30:
                det.forget_poses()  # carried: the old poses say nothing any more
            out.append(det.process_features(v, 0.0, q, cov))
        return out[30:]

    here, far = [5.0, 6.0, 7.0, 8.0], [25.0, 26.0, 27.0, 28.0]
    plain = run(base, far)
    assert [d.status for d in plain][-2:] == [LOOP, LOOP]  # appearance alone: a loop
    assert [d.status for d in run(odo, here)][-2:] == [LOOP, LOOP]
    assert all(d.status == LOW_POSTERIOR for d in run(odo, far))
    assert [d.status for d in run(odo, far, forget=True)][-2:] == [LOOP, LOOP]
    no_pose = ForwardDetector(odo)  # verify_pair is still the accepting one run() put in
    got = [no_pose.process_features(v) for v in views][30:]
    assert [d.candidate_id for d in got] == [d.candidate_id for d in plain]


def _same_image(a, b) -> bool:
    """Two images' features are the same (``features_of`` puts a past image together anew
    at each call: equal, not the same object)."""
    return (a.image_size_px == b.image_size_px and np.array_equal(a.keypoints_q, b.keypoints_q)
            and np.array_equal(a.descriptors, b.descriptors))


def test_the_next_hypotheses_are_verified_when_the_candidate_fails(monkeypatch):
    """A revisit that shares most words with place 5 and the rest with place 6: place 5 is
    the candidate; when only place 6 verifies, ``verify_tries = 2`` finds it, 1 does not.
    Only the candidate's neighbours are tried (with place 20 instead of 6, none, though
    odometry puts 20 there too), and only with odometry agreeing (without poses, none)."""
    import robotd.forward.detector as det_mod
    from robotd.forward.verify import ACCEPTED, NO_GEOMETRIC_CONSISTENCY as BAD, Verification

    views = _views(30, [])
    params = DetectorParams(features=FeatureParams(kind="orb"), decision="score", verify=ACCEPT_ALL,
                            odometry=OdometryParams(use=True))
    poses = [np.array([float(i) if i != 20 else 5.0, 0.0, 0.0]) for i in range(30)] + [np.array([5.5, 0.0, 0.0])]
    cov = np.diag([0.01, 0.01, 0.001])

    def run(p, other=6, with_poses=True):
        mixed = np.concatenate([views[5].descriptors[:70], views[other].descriptors[:50]])
        mixed[:, 0] ^= 0x03
        det = ForwardDetector(p)
        good = []
        monkeypatch.setattr(det_mod, "verify_pair", lambda old, new, vp, k: (
            Verification(True, ACCEPTED, 100, 100) if any(_same_image(old, g) for g in good) else Verification(False, BAD, 3, 3)))
        q = [(poses[i], cov) if with_poses else (None, None) for i in range(31)]
        out = [det.process_features(v, 0.0, *q[i]) for i, v in enumerate(views[:30])]
        good.append(det.features_of(other))
        return out + [det.process_features(Features(views[5].keypoints_px[:120], mixed, (640, 480)), 0.0, *q[30])]

    one = run(params)[30]
    assert one.status == NO_GEOMETRIC_CONSISTENCY and one.candidate_id == 5 and one.loop_id is None
    two = run(replace(params, verify_tries=2))[30]
    assert two.status == LOOP and two.loop_id == 6 and two.candidate_id == 6
    far = run(replace(params, verify_tries=3), other=20)[30]
    assert far.status == NO_GEOMETRIC_CONSISTENCY and far.candidate_id == 5
    blind = run(replace(params, verify_tries=3), with_poses=False)[30]
    assert blind.status == NO_GEOMETRIC_CONSISTENCY and blind.candidate_id == 5
    with pytest.raises(ValueError):
        DetectorParams(verify_tries=0)


def test_odometry_agreement_relaxes_the_verification(monkeypatch):
    """The verification a candidate gets: the detector's own, or with ``agree_min_inliers``
    when its odometry factor reaches ``agree_factor``."""
    import robotd.forward.detector as det_mod
    from robotd.forward.verify import ACCEPTED, Verification

    seen = []
    monkeypatch.setattr(det_mod, "verify_pair",
                        lambda old, new, vp, k: seen.append(vp.min_inliers) or Verification(True, ACCEPTED, 100, 100))
    views = _views(30, [5])
    odo = OdometryParams(use=True, agree_min_inliers=12)
    params = DetectorParams(features=FeatureParams(kind="orb"), decision="score", verify=ACCEPT_ALL, odometry=odo)
    cov = np.diag([0.01, 0.01, 0.001])
    for x in (5.0, 9.0):  # at place 5's pose: agrees; 4 m away (d = 4): factor 3e-4, does not
        det = ForwardDetector(params)
        for i, v in enumerate(views):
            det.process_features(v, 0.0, np.array([float(i) if i < 30 else x, 0.0, 0.0]), cov)
    assert seen == [12, ACCEPT_ALL.min_inliers]


def test_islands_pick_the_run_of_images_with_the_most_summed_score():
    """DLoopDetector's islands by hand: normalised scores above the threshold grouped into
    runs at most ``consistency_gap`` apart; the largest sum wins, its best image is the
    candidate, the sum its probability; without islands the single best image wins."""
    from robotd.forward.detector import _best_normalised

    scores = np.zeros(40)
    scores[[3, 4, 5]] = [0.5, 0.6, 0.5]     # island of 1.6 (normalised by 1)
    scores[30] = 0.9                         # the best single image, alone
    scores[[20, 24]] = [0.4, 0.4]            # 4 apart: two islands of 0.4 with gap 3
    p = DetectorParams(features=FeatureParams(kind="orb"), decision="score", score_normalisation="previous",
                       score_threshold=0.3, consistency_gap=3)
    # ref: the previous image's score (t - 1 = 39), 1.0
    scores[39] = 1.0
    assert _best_normalised(scores, 35, 0.2, 40, p) == (30, pytest.approx(0.9))
    cand, prob = _best_normalised(scores, 35, 0.2, 40, replace(p, islands=True))
    assert cand == 4 and prob == pytest.approx(1.6)
    # With a gap of 4 allowed, 20 and 24 join, but 0.8 < 1.6; nothing above 0.95: no candidate.
    assert _best_normalised(scores, 35, 0.2, 40, replace(p, islands=True, consistency_gap=4))[0] == 4
    assert _best_normalised(scores, 35, 0.2, 40, replace(p, islands=True, score_threshold=0.95)) == (
        None, pytest.approx(0.9))


def test_places_merged_by_pose_gather_the_views_of_one_spot_from_other_laps():
    """The posterior split between two laps' views of one spot (images 3 and 23, the same
    odometry pose) outweighs one image elsewhere with more mass alone (image 12); merged by
    time only (no poses), the single image wins."""
    from robotd.forward.detector import _merged_candidate

    n = 30
    post = np.zeros(1 + n)
    post[0] = 0.1
    post[1 + 12] = 0.4
    post[1 + 3] = 0.25
    post[1 + 23] = 0.25
    ids = np.arange(n)
    poses = np.array([[float(i), 0.0, 0.0] for i in range(n)])
    poses[23] = poses[3]  # the same spot on the next lap
    var = np.zeros((n, 3))
    p = DetectorParams(features=FeatureParams(kind="orb"), filter=FilterParams(rule="neighbourhood", loop_threshold=0.3),
                       odometry=OdometryParams(merge_places=True))
    cand, prob = _merged_candidate(post, ids, poses, var, p)
    assert cand in (3, 23) and prob == pytest.approx(0.5)
    cand, prob = _merged_candidate(post, ids, np.full((n, 3), np.nan), var, p)
    assert cand == 12 and prob == pytest.approx(0.4)
    # The total rule: the probability is 1 - p(no loop) whatever the place.
    cand, prob = _merged_candidate(post, ids, poses, var, replace(p, filter=FilterParams(rule="total",
                                                                                          loop_threshold=0.5)))
    assert cand in (3, 23) and prob == pytest.approx(0.9)


def test_a_refused_acceptance_tries_the_next_view(monkeypatch):
    """The detector's ``accept`` hook (the daemon's level-camera test): a verification it
    refuses is no loop, and with ``verify_tries`` the candidate's neighbour that odometry
    agrees with is verified next; the hook sees each image and its verification."""
    import robotd.forward.detector as det_mod
    from robotd.forward.detector import daemon_params
    from robotd.forward.verify import ACCEPTED, Verification

    monkeypatch.setattr(det_mod, "verify_pair", lambda old, new, vp, k: Verification(True, ACCEPTED, 100, 100))
    views = _views(30, [5, 6, 7])
    cov = np.diag([0.01, 0.01, 0.001])
    poses = [np.array([float(i), 0.0, 0.0]) for i in range(30)] + [np.array([x, 0.0, 0.0]) for x in (5., 6., 7.)]
    params = daemon_params(method_params("default"))
    assert params.odometry.use and params.verify_tries == 3 and params.consistency == 1
    assert params.odometry.agree_min_support_area == 0.0 and params.filter.loop_threshold == 0.5
    seen: list[int] = []

    def refuse_all(j, v):
        seen.append(j)
        return False

    for accept, want in ((None, LOOP), (refuse_all, NO_GEOMETRIC_CONSISTENCY)):
        det = ForwardDetector(replace(params, verify=ACCEPT_ALL, decision="score"), accept=accept)
        got = [det.process_features(v, 0.0, q, cov) for v, q in zip(views, poses)][30:]
        assert [d.status for d in got] == [want] * 3
    # Each refused image had its candidate and then its agreeing neighbours tried (3 in all).
    assert len(seen) == 9 and seen[:1] == [5] and all(abs(j - 5) <= 2 for j in seen[:3])


def test_neighbours_by_distance_move_mass_to_the_same_spot_on_another_lap():
    """The metric transition: image 3's mass goes to its time neighbours (2, 4) and to
    image 23, at image 3's pose on the next lap, which the paper's index transition never
    reaches; images without a pose diffuse by index only, and the total mass is kept."""
    from robotd.forward.detector import predict_metric
    from robotd.forward.filter import predict

    n = 30
    post = np.zeros(1 + n)
    post[0], post[1 + 3] = 0.2, 0.8
    poses = np.array([[0.4 * i, 0.0, 0.0] for i in range(n)])
    poses[23] = poses[3] + [0.05, 0.0, 0.0]
    var = np.zeros((n, 3))
    p = DetectorParams(features=FeatureParams(kind="orb"), odometry=OdometryParams(metric_neighbours=True))
    metric = predict_metric(post, n, poses, var, p)
    index = predict(post, n, p.filter)
    assert metric.sum() == pytest.approx(1.0) and metric[0] == pytest.approx(index[0])
    assert index[1 + 23] == pytest.approx(0.1 * 0.2 / n)  # only the no-loop share
    assert metric[1 + 23] > 0.1 and metric[1 + 3] > metric[1 + 23]
    assert metric[1 + 10] == pytest.approx(index[1 + 10])  # 2.8 m away: nothing more
    # Image 3 heading the other way on the next lap: not the same view, not a neighbour.
    poses[23, 2] = np.pi
    assert predict_metric(post, n, poses, var, p)[1 + 23] == pytest.approx(index[1 + 23])
    blind = predict_metric(post, n, np.full((n, 3), np.nan), var, p)
    assert np.allclose(blind, index)


def test_the_candidates_place_is_verified_when_the_candidate_fails(monkeypatch):
    """``verify_place``: when candidate 5 fails, the image at its pose on another lap (20)
    is tried next, though 20 is no time neighbour of 5; without poses only 5 is."""
    import robotd.forward.detector as det_mod
    from robotd.forward.verify import ACCEPTED, NO_GEOMETRIC_CONSISTENCY as BAD, Verification

    views = _views(30, [])
    params = DetectorParams(features=FeatureParams(kind="orb"), decision="score", verify=ACCEPT_ALL,
                            odometry=OdometryParams(verify_place=True), verify_tries=3)
    # 2 m apart (no image agrees with its time neighbours); 20 where 5 was, 0.1 m off.
    poses = [np.array([2.0 * i if i != 20 else 10.1, 0.0, 0.0]) for i in range(30)] + [np.array([9.0, 0.0, 0.0])]
    cov = np.diag([0.01, 0.01, 0.001])

    def run(p, with_poses=True):
        det = ForwardDetector(p)
        good = []
        monkeypatch.setattr(det_mod, "verify_pair", lambda old, new, vp, k: (
            Verification(True, ACCEPTED, 100, 100) if any(_same_image(old, g) for g in good) else Verification(False, BAD, 3, 3)))
        q = [(poses[i], cov) if with_poses else (None, None) for i in range(31)]
        for i, v in enumerate(views):
            det.process_features(v, 0.0, *q[i])
        good.append(det.features_of(20))
        d = views[5].descriptors.copy()
        d[:, 0] ^= 0x03
        return det.process_features(Features(views[5].keypoints_px, d, (640, 480)), 0.0, *q[30])

    got = run(params)
    assert got.status == LOOP and got.loop_id == 20
    assert run(replace(params, verify_tries=1)).status == NO_GEOMETRIC_CONSISTENCY
    blind = run(params, with_poses=False)
    assert blind.status == NO_GEOMETRIC_CONSISTENCY and blind.candidate_id == 5


def test_the_default_without_poses_is_the_default_without_odometry(monkeypatch):
    """The default's odometry levers act only when a pose comes with the image: without
    one (the real corridor, ``eval forward`` without ``--odometry``) every decision is the
    detector's without odometry; with poses that put the revisit far from its place, the
    odometry likelihood changes them."""
    views = _views(30, [5, 6, 7, 20])
    dflt = replace(method_params("default"), verify=ACCEPT_ALL)
    plain = replace(dflt, odometry=OdometryParams())
    a = _run(dflt, views, monkeypatch)
    b = _run(plain, views, monkeypatch)
    assert [(d.status, d.candidate_id, d.candidate_probability) for d in a] == [
        (d.status, d.candidate_id, d.candidate_probability) for d in b]
    assert [d.loop_id for d in a[30:33]] == [5, 6, 7]
    det = ForwardDetector(dflt)
    cov = np.diag([0.01, 0.01, 0.001])
    far = [det.process_features(v, 0.0, np.array([float(i) if i < 30 else 100.0, 0.0, 0.0]), cov)
           for i, v in enumerate(views)][30:]
    assert [d.candidate_probability for d in far] != [d.candidate_probability for d in a[30:]]


def test_the_fallbacks_per_image_are_bounded(monkeypatch):
    """``verify_fallbacks``: of the three views a failed candidate's image verifies, only
    the first may run the general search after the planar one (the later ones get
    ``fallback_inliers = None``); None: each may; 0: none."""
    import robotd.forward.detector as det_mod
    from robotd.forward.verify import NO_GEOMETRIC_CONSISTENCY as BAD, Verification

    views = _views(30, [])
    params = DetectorParams(features=FeatureParams(kind="orb"), decision="score",
                            verify=replace(ACCEPT_ALL, model="planar", fallback_inliers=10),
                            odometry=OdometryParams(use=True), verify_tries=3)
    poses = [np.array([0.3 * i, 0.0, 0.0]) for i in range(30)] + [np.array([1.5, 0.0, 0.0])]
    cov = np.diag([0.01, 0.01, 0.001])

    def run(p):
        seen: list[int | None] = []

        def refused(old, new, vp, k):
            seen.append(vp.fallback_inliers)
            return replace(Verification(False, BAD, 50, 12), fallback=vp.fallback_inliers is not None)

        monkeypatch.setattr(det_mod, "verify_pair", refused)
        det = ForwardDetector(p)
        for i, v in enumerate(views):
            det.process_features(v, 0.0, poses[i], cov)
        seen.clear()
        d = views[5].descriptors.copy()
        d[:, 0] ^= 0x03
        got = det.process_features(Features(views[5].keypoints_px, d, (640, 480)), 0.0, poses[30], cov)
        assert got.candidate_id == 5 and got.status == NO_GEOMETRIC_CONSISTENCY
        return seen

    assert run(params) == [10, 10, 10]
    assert run(replace(params, verify_fallbacks=1)) == [10, None, None]
    assert run(replace(params, verify_fallbacks=0)) == [None, None, None]
    with pytest.raises(ValueError, match="verify_fallbacks"):
        DetectorParams(verify_fallbacks=-1)


@pytest.mark.parametrize("rule", ["accept", "refuse", "second"])
def test_a_deferred_acceptance_test_gives_the_answer_of_the_test_at_once(monkeypatch, rule):
    """``defer_accept``: the image stops at its first view whose check passes
    (``ACCEPT_PENDING``, the ``accept`` test not run); :meth:`ForwardDetector.resume`, called
    after the next images went through, runs the test and the views after a refused one, and
    gives the loop, the views tested and their order that the test run at once gave."""
    import robotd.forward.detector as det_mod
    from robotd.forward.detector import ACCEPT_PENDING, daemon_params
    from robotd.forward.verify import ACCEPTED, Verification

    monkeypatch.setattr(det_mod, "verify_pair", lambda old, new, vp, k: Verification(True, ACCEPTED, 100, 100))
    views = _views(30, [5, 6, 7, 8])
    cov = np.diag([0.01, 0.01, 0.001])
    poses = [np.array([float(i), 0.0, 0.0]) for i in range(30)] + [np.array([float(x), 0.0, 0.0]) for x in (5, 6, 7, 8)]
    params = replace(daemon_params(method_params("default")), verify=ACCEPT_ALL, decision="score")

    def run(defer: bool) -> tuple[list, list]:
        seen: list[tuple[int, int]] = []
        det = ForwardDetector(params)

        def accept(j, v):
            seen.append((len(seen), j))
            return rule == "accept" or (rule == "second" and len(seen) % 2 == 0)

        det.accept = accept
        answers, waiting = [], []
        for v, q in zip(views, poses):
            n_seen = len(seen)
            d = det.process_features(v, 0.0, q, cov, defer_accept=defer)
            assert not defer or len(seen) == n_seen  # no test run inside the image's own call
            if waiting:  # the previous image's test, after this image went through
                job = waiting.pop()
                status, j, _ = det.resume(job)
                answers.append((job.image_id, status, j if status == LOOP else None))
            if d.status == ACCEPT_PENDING:
                assert d.pending is not None and d.loop_id is None and d.verification is not None
                waiting.append(d.pending)
            elif d.image_id >= 30:
                answers.append((d.image_id, d.status, d.loop_id))
        for job in waiting:
            status, j, _ = det.resume(job)
            answers.append((job.image_id, status, j if status == LOOP else None))
        return answers, seen

    at_once, seen_at_once = run(False)
    deferred, seen_deferred = run(True)
    assert deferred == at_once and seen_deferred == seen_at_once
    assert len(at_once) == 4 and len(seen_at_once) == {"accept": 4, "refuse": 12, "second": 8}[rule]
    assert {a[1] for a in at_once} == ({NO_GEOMETRIC_CONSISTENCY} if rule == "refuse" else {LOOP})


def test_resume_needs_a_view_awaiting_its_test():
    from robotd.forward.detector import PendingVerification

    det = ForwardDetector(DetectorParams(features=FeatureParams(kind="orb")))
    job = PendingVerification(0, 0, Features(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), (640, 480)),
                              [], frozenset())
    with pytest.raises(ValueError):
        det.resume(job)


@pytest.mark.parametrize("budget", [1, 2])
@pytest.mark.parametrize("rule", ["accept", "refuse", "second", "checks"])
def test_a_verification_split_by_a_check_budget_gives_the_answer_of_the_verification_at_once(monkeypatch, rule,
                                                                                                   budget):
    """``max_checks``: an image's epipolar checks stop after the budget (``VERIFY_PENDING``,
    its views left in :attr:`Detection.pending`); :meth:`ForwardDetector.resume` with the same
    budget goes on with them call after call, interleaved with the next images, each call
    within the budget (a call that runs an awaiting ``accept`` test included), and gives the
    loops, the views checked and tested and their order that the verification at once gave."""
    import robotd.forward.detector as det_mod
    from robotd.forward.detector import ACCEPT_PENDING, VERIFY_PENDING, PendingVerification, daemon_params
    from robotd.forward.verify import ACCEPTED, NO_GEOMETRIC_CONSISTENCY as NGC, Verification

    checked: list[tuple[bytes, bytes]] = []  # (the view's descriptors, the new image's) per check

    def verify(old, new, vp, k):
        checked.append((np.asarray(old.descriptors).tobytes(), np.asarray(new.descriptors).tobytes()))
        if rule == "checks" and (int(np.asarray(old.descriptors)[:, 2].sum()) + int(np.asarray(new.descriptors)[:, 3].sum())) % 3:
            return Verification(False, NGC, 50, 0)  # about two of three views fail: several checks per image
        return Verification(True, ACCEPTED, 100, 100)

    monkeypatch.setattr(det_mod, "verify_pair", verify)
    # The revisits, then new places far away (nothing to verify: the waiting work goes on there).
    views = _views(30, [5, 6, 7, 8]) + _views(6, [], seed=1)
    cov = np.diag([0.01, 0.01, 0.001])
    poses = ([np.array([float(i), 0.0, 0.0]) for i in range(30)] + [np.array([float(x), 0.0, 0.0]) for x in (5, 6, 7, 8)]
             + [np.array([200.0 + i, 0.0, 0.0]) for i in range(6)])
    params = replace(daemon_params(method_params("default")), verify=ACCEPT_ALL, decision="score")

    def run(split: bool) -> tuple[list, list, list, list]:
        seen: list[tuple[int, int]] = []
        checked.clear()
        det = ForwardDetector(params)

        def accept(j, v):
            seen.append((len(seen), j))
            return rule in ("accept", "checks") or (rule == "second" and len(seen) % 2 == 0)

        det.accept = accept
        answers: list[tuple] = []
        queue: list[PendingVerification] = []
        per_call: list[int] = []  # checks + tests per call

        def call(f):
            n0, s0 = len(checked), len(seen)
            out = f()
            per_call.append(len(checked) - n0 + len(seen) - s0)
            return out

        for v, q in zip(views, poses):
            if not split:
                d = call(lambda: det.process_features(v, 0.0, q, cov))
                if 30 <= d.image_id < 34:
                    answers.append((d.image_id, d.status, d.loop_id))
                continue
            d = call(lambda: det.process_features(v, 0.0, q, cov, defer_accept=True, max_checks=budget))
            assert d.checks == per_call[-1] <= budget
            if d.status in (ACCEPT_PENDING, VERIFY_PENDING):
                assert d.pending is not None and d.loop_id is None
                assert (d.status == VERIFY_PENDING) == (d.pending.view is None)
                queue.append(d.pending)
            elif 30 <= d.image_id < 34:
                answers.append((d.image_id, d.status, d.loop_id))
            if queue and d.status not in (ACCEPT_PENDING, VERIFY_PENDING):  # one step of the oldest
                job = queue[0]
                out = call(lambda: det.resume(job, max_checks=budget - (job.view is not None), defer_accept=True))
                if not isinstance(out, PendingVerification):
                    queue.pop(0)
                    answers.append((job.image_id, out[0], out[1] if out[0] == LOOP else None))
        for job in queue:  # the end: each to its answer
            out = det.resume(job)
            assert not isinstance(out, PendingVerification)
            answers.append((job.image_id, out[0], out[1] if out[0] == LOOP else None))
        by_image: dict[bytes, list[bytes]] = {}  # each new image's views checked, in order
        for old, new in checked:
            by_image.setdefault(new, []).append(old)
        return sorted(answers), seen, by_image, per_call

    at_once, seen_at_once, checked_at_once, per_image = run(False)
    split, seen_split, checked_split, per_call = run(True)
    assert split == at_once and seen_split == seen_at_once and checked_split == checked_at_once
    assert len(at_once) == 4 and max(per_call) <= budget
    n_checks = {"accept": 4, "refuse": 12, "second": 8, "checks": 10}[rule]
    assert sum(map(len, checked_at_once.values())) == n_checks
    # The budget bound something: at once an image ran more checks and tests in its call.
    assert max(per_image) > budget or (rule, budget) == ("accept", 2)


@pytest.mark.parametrize("second_passes", [True, False])
def test_the_fallbacks_run_after_every_view_is_checked_near_its_level_motion(monkeypatch, second_passes):
    """``fallbacks_last``: the candidate (place 5) fails near its level motion with its
    fallback due (a :class:`~robotd.forward.verify.DueFallback`), place 6 is checked next;
    when place 6 passes it is the loop and the fallback never runs; when it fails, the
    fallback runs after it (one check more) and decides. Without ``fallbacks_last`` the
    candidate's fallback runs first. At most ``verify_fallbacks`` fallbacks run either way."""
    import robotd.forward.detector as det_mod
    from robotd.forward.verify import ACCEPTED, NO_GEOMETRIC_CONSISTENCY as BAD, DueFallback, Verification

    views = _views(30, [])
    poses = [np.array([float(i), 0.0, 0.0]) for i in range(30)] + [np.array([5.5, 0.0, 0.0])]
    cov = np.diag([0.01, 0.01, 0.001])
    work = object()  # what the fallback would need: only passed through here

    def run(p: DetectorParams) -> tuple[object, list[str]]:
        log: list[str] = []
        det = ForwardDetector(p)
        places: dict[int, object] = {}

        def verify(old, new, vp, k):
            place = next(i for i, f in places.items() if _same_image(old, f))
            log.append(f"check {place}")
            if place == 6:
                return Verification(True, ACCEPTED, 100, 100) if second_passes else Verification(False, BAD, 40, 5)
            if vp.fallback_inliers is None:  # no fallback left for this image
                return Verification(False, BAD, 60, 12)
            if vp.defer_fallback:
                return DueFallback(False, BAD, 60, 12, work=work)  # type: ignore[arg-type]
            log.append(f"fallback {place}")
            return Verification(True, ACCEPTED, 60, 30, fallback=True)

        def fallback(v):
            assert isinstance(v, DueFallback) and v.work is work
            log.append("fallback due")
            return Verification(True, ACCEPTED, 60, 30, fallback=True)

        monkeypatch.setattr(det_mod, "verify_pair", verify)
        monkeypatch.setattr(det_mod, "fallback_verification", fallback)
        for i, v in enumerate(views[:30]):
            det.process_features(v, 0.0, poses[i], cov)
        places.update({5: det.features_of(5), 6: det.features_of(6)})
        mixed = np.concatenate([views[5].descriptors[:70], views[6].descriptors[:50]])
        mixed[:, 0] ^= 0x03
        return det.process_features(Features(views[5].keypoints_px[:120], mixed, (640, 480)), 0.0, poses[30], cov), log

    params = DetectorParams(features=FeatureParams(kind="orb"), decision="score", verify=ACCEPT_ALL,
                            odometry=OdometryParams(use=True), verify_tries=2, verify_fallbacks=1)
    at_once, log_at_once = run(params)
    assert log_at_once == ["check 5", "fallback 5"] and at_once.loop_id == 5 and at_once.checks == 1
    last, log_last = run(replace(params, fallbacks_last=True))
    assert last.status == LOOP
    if second_passes:
        assert log_last == ["check 5", "check 6"] and last.loop_id == 6 and last.checks == 2
    else:
        assert log_last == ["check 5", "check 6", "fallback due"] and last.loop_id == 5 and last.checks == 3
        assert last.verification.fallback and not isinstance(last.verification, DueFallback)
    none, log_none = run(replace(params, fallbacks_last=True, verify_fallbacks=0))
    assert log_none == ["check 5", "check 6"] and (none.status == LOOP) == second_passes
