"""The relocalisation agreement rule: true candidates that agree relocalise; a single
look-alike, candidates of the same floor, or candidates that disagree do not."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.base.geometry import between, compose, inverse, wrap_angle
from robotd.graph.reloc import (
    Relocaliser,
    RelocCandidate,
    RelocParams,
    chain_relative,
    implied_transform,
    pair_chi2,
)

# The lost trajectory's frame in the map frame (what relocalisation must find).
T_TRUE = np.array([3.2, -1.4, math.radians(130.0)])
LOOP_SIGMA = np.array([0.004, 0.004, math.radians(0.3)])  # a floor loop's transform, 1 sigma
LOOP_INFO = np.diag(1.0 / LOOP_SIGMA**2)
ODO_SIGMA_PER_M = np.array([0.01, 0.01, math.radians(0.5)])  # odometry between queries


def _lost_path(n: int = 60) -> np.ndarray:
    """Query keyframes of the lost trajectory in its own frame: 0.1 m apart, curving."""
    poses = [np.zeros(3)]
    for _ in range(n - 1):
        poses.append(compose(poses[-1], np.array([0.1, 0.0, math.radians(2.0)])))
    return np.array(poses)


LOST = _lost_path()


def _relative(a: int, b: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Odometry between two queries (ids index LOST), covariance growing with distance."""
    if b <= a:
        return None
    dist = 0.1 * (b - a)
    return between(LOST[a], LOST[b]), np.diag((ODO_SIGMA_PER_M * math.sqrt(dist)) ** 2 + 1e-10)


def _candidate(q: int, rng: np.random.Generator, transform: np.ndarray = T_TRUE,
               old_offset: np.ndarray | None = None, old_id: int | None = None) -> RelocCandidate:
    """A candidate from query ``q`` to an old keyframe near the query's true map pose: the
    measured delta is the truth (under ``transform``) plus loop noise."""
    truth_map = compose(transform, LOST[q])
    off = np.array([0.05, -0.08, 0.1]) if old_offset is None else old_offset
    old_pose = compose(truth_map, inverse(off))  # the old keyframe sees the query at ``off``
    delta = off + rng.normal(0.0, LOOP_SIGMA)
    return RelocCandidate(old_id=1000 + q if old_id is None else old_id, query_id=q, score=95.0,
                          old_pose=old_pose, delta=delta, information=LOOP_INFO,
                          query_pose=LOST[q], travelled_m=0.1 * q, old_run=1)


def _look_alike(q: int, rng: np.random.Generator) -> RelocCandidate:
    """A false candidate: the old keyframe is elsewhere in the map (another floor patch
    that looks alike), so its implied transform is wrong."""
    wrong = compose(T_TRUE, np.array([0.0, 2.5, math.radians(-40.0)]))
    return _candidate(q, rng, transform=wrong)


def test_implied_transform_of_an_exact_candidate_is_the_truth():
    c = _candidate(10, np.random.default_rng(0))
    exact = RelocCandidate(c.old_id, c.query_id, c.score, c.old_pose, np.array([0.05, -0.08, 0.1]),
                           c.information, c.query_pose, c.travelled_m)
    assert np.allclose(implied_transform(exact), T_TRUE, atol=1e-12)


def test_true_pairs_pass_and_false_pairs_fail_the_chi2_test_as_expected():
    rng = np.random.default_rng(1)
    p = RelocParams()
    map_sigma = np.array([p.map_sigma_m, p.map_sigma_m, p.map_sigma_rad])

    def noisy_map(c: RelocCandidate) -> RelocCandidate:  # the map's own error, as modelled
        return RelocCandidate(c.old_id, c.query_id, c.score, c.old_pose + rng.normal(0.0, map_sigma),
                              c.delta, c.information, c.query_pose, c.travelled_m)

    true_d2, false_d2 = [], []
    for _ in range(300):
        qa, qb = sorted(rng.choice(np.arange(60), 2, replace=False))
        rel, cov = _relative(int(qa), int(qb))
        rel_noisy = rel + rng.multivariate_normal(np.zeros(3), cov)  # odometry error, as modelled
        true_d2.append(pair_chi2(noisy_map(_candidate(qa, rng)), noisy_map(_candidate(qb, rng)),
                                 rel_noisy, cov))
        false_d2.append(pair_chi2(_candidate(qa, rng), _look_alike(qb, rng), rel, cov))
    true_d2, false_d2 = np.array(true_d2), np.array(false_d2)
    # Truly agreeing pairs: chi-square with 3 dof, mean about 3 (noise within the model).
    assert 2.4 < np.mean(true_d2) < 3.6
    assert np.mean(true_d2 <= p.agree_chi2) >= 0.98
    # A look-alike 2.5 m and 40 deg away never agrees.
    assert np.min(false_d2) > 10 * p.agree_chi2


def test_two_independent_agreeing_candidates_relocalise():
    rng = np.random.default_rng(2)
    reloc = Relocaliser(_relative)
    first = reloc.offer(_candidate(5, rng))
    assert not first.relocalised and first.detail == "1 of 2 agreeing candidates"
    second = reloc.offer(_candidate(20, rng))
    assert second.relocalised
    assert [m.query_id for m in second.members] == [20, 5]
    t = second.transform
    assert np.hypot(*(t[:2] - T_TRUE[:2])) < 0.02
    assert abs(wrap_angle(t[2] - T_TRUE[2])) < math.radians(1.0)
    assert reloc.pending == []


def test_a_single_look_alike_does_not_relocalise_and_is_dropped_when_true_ones_agree():
    rng = np.random.default_rng(3)
    reloc = Relocaliser(_relative)
    assert not reloc.offer(_look_alike(3, rng)).relocalised
    assert not reloc.offer(_candidate(12, rng)).relocalised  # the look-alike disagrees
    d = reloc.offer(_candidate(30, rng))
    assert d.relocalised
    assert sorted(m.query_id for m in d.members) == [12, 30]
    assert [(c.query_id, why.startswith("relocalisation: disagrees")) for c, why in d.dropped] == [(3, True)]
    assert np.hypot(*(d.transform[:2] - T_TRUE[:2])) < 0.02


def test_candidates_of_the_same_floor_are_not_independent():
    rng = np.random.default_rng(4)
    reloc = Relocaliser(_relative)
    reloc.offer(_candidate(10, rng))
    # 0.2 m further along (under min_separation_m = 0.5 m), another old keyframe: not a second vote.
    d = reloc.offer(_candidate(12, rng, old_id=77))
    assert not d.relocalised
    # The same query against a second old keyframe is the same image: not a second vote either.
    assert not reloc.offer(_candidate(12, rng, old_offset=np.array([-0.1, 0.02, 0.0]), old_id=78)).relocalised
    assert reloc.offer(_candidate(16, rng)).relocalised


def test_disagreeing_candidates_do_not_relocalise():
    rng = np.random.default_rng(5)
    reloc = Relocaliser(_relative)
    shifts = [np.array([0.0, 2.5, -0.7]), np.array([-3.0, 0.5, 1.2]), np.array([1.5, -1.5, 2.5]),
              np.array([0.4, 0.0, 0.0])]
    for q, s in zip((5, 15, 25, 35), shifts):
        d = reloc.offer(_candidate(q, rng, transform=compose(T_TRUE, s)))
        assert not d.relocalised, d.detail
    assert len(reloc.pending) == 4


def test_two_look_alikes_of_one_wrong_place_would_agree():
    """The rule's known limit, stated as a test: two false candidates that imply the same
    wrong transform (a repeated region larger than min_separation_m) do relocalise."""
    rng = np.random.default_rng(6)
    reloc = Relocaliser(_relative)
    reloc.offer(_look_alike(5, rng))
    d = reloc.offer(_look_alike(20, rng))
    assert d.relocalised
    assert np.hypot(*(d.transform[:2] - T_TRUE[:2])) > 2.0


def test_more_agreeing_candidates_can_be_required():
    rng = np.random.default_rng(7)
    reloc = Relocaliser(_relative, RelocParams(min_agreeing=3))
    assert not reloc.offer(_candidate(5, rng)).relocalised
    assert not reloc.offer(_candidate(15, rng)).relocalised
    assert reloc.offer(_candidate(25, rng)).relocalised


def test_the_oldest_held_candidate_is_dropped_beyond_max_pending():
    rng = np.random.default_rng(8)
    reloc = Relocaliser(_relative, RelocParams(max_pending=2))
    wrong = [compose(T_TRUE, np.array([k, 0.0, 0.0])) for k in (3.0, 6.0, 9.0)]
    reloc.offer(_candidate(5, rng, transform=wrong[0]))
    reloc.offer(_candidate(15, rng, transform=wrong[1]))
    d = reloc.offer(_candidate(25, rng, transform=wrong[2]))
    assert [c.query_id for c, _ in d.dropped] == [5]
    assert [c.query_id for c in reloc.pending] == [15, 25]


def test_no_odometry_chain_means_no_agreement():
    rng = np.random.default_rng(9)
    reloc = Relocaliser(lambda a, b: None)
    reloc.offer(_candidate(5, rng))
    assert not reloc.offer(_candidate(25, rng)).relocalised


def test_chain_relative_composes_edges_and_their_covariance():
    info = np.diag([1e4, 1e4, 1e4])
    step = np.array([1.0, 0.0, math.pi / 2])
    edges = {2: (1, step, info), 3: (2, step, info), 4: (3, step, info)}
    rel, cov = chain_relative(edges, 1, 4)
    assert np.allclose(rel, [0.0, 1.0, -math.pi / 2], atol=1e-12)  # three quarter turns of a square
    # Three independent edges: the heading variance adds up exactly.
    assert cov[2, 2] == pytest.approx(3e-4)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert chain_relative(edges, 1, 1)[0] == pytest.approx(np.zeros(3))
    assert chain_relative({4: (3, step, info)}, 1, 4) is None  # broken chain
    assert chain_relative(edges, 4, 2) is None


def test_params_are_checked():
    with pytest.raises(ValueError, match="min_agreeing"):
        RelocParams(min_agreeing=0)
    with pytest.raises(ValueError, match="map_sigma_m"):
        RelocParams(map_sigma_m=0.0)


# -- forward loops: a heading change and a bearing, the range only from the floor ----------

MOUNT = np.array([0.1, 0.0, 0.0])  # the forward camera on the robot
BEARING_SIGMA = math.radians(1.0)
YAW_SIGMA = math.radians(0.5)


def _forward(q: int, rng: np.random.Generator, old_offset: np.ndarray, transform: np.ndarray = T_TRUE,
             range_sigma: float | None = None, old_id: int | None = None) -> RelocCandidate:
    """A forward loop from query ``q`` to an old keyframe that sees the query's camera at
    ``old_offset`` (robot frame): bearing and heading change with noise; the range measured
    on the floor with log-noise ``range_sigma``, or not at all."""
    from robotd.forward.planar import PlanarLoopParams, loop_edge

    truth_map = compose(transform, LOST[q])
    old_pose = compose(truth_map, inverse(old_offset))
    cam = compose(compose(inverse(MOUNT), old_offset), MOUNT)
    bearing = math.atan2(cam[1], cam[0]) + rng.normal(0.0, BEARING_SIGMA)
    dyaw = cam[2] + rng.normal(0.0, YAW_SIGMA)
    range_m = None if range_sigma is None else math.hypot(cam[0], cam[1]) * math.exp(rng.normal(0.0, range_sigma))
    params = PlanarLoopParams(sigma_bearing_rad=BEARING_SIGMA, sigma_yaw_rad=YAW_SIGMA)

    def edge(predicted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return loop_edge(predicted, dyaw, bearing, MOUNT, params, range_m=range_m)

    delta, info = edge(np.array([1.0, 0.0, 0.0]))
    return RelocCandidate(old_id=2000 + q if old_id is None else old_id, query_id=q, score=0.9, old_pose=old_pose,
                          delta=delta, information=info, query_pose=LOST[q], travelled_m=0.1 * q, old_run=1,
                          source="forward", edge=edge, measured_dims=2 if range_m is None else 3)


def test_one_forward_loop_cannot_relocalise_two_from_places_apart_fix_the_range():
    errors = []
    for seed in range(5):
        rng = np.random.default_rng(100 + seed)
        reloc = Relocaliser(_relative, RelocParams(min_forward_only=2))
        # Two old keyframes 1.6-1.8 m from queries 1.5 m apart, the bearings 54 deg apart in the map.
        first = reloc.offer(_forward(5, rng, np.array([1.8, 0.4, 0.2])))
        assert not first.relocalised
        d = reloc.offer(_forward(20, rng, np.array([0.5, 1.5, 0.8])))
        assert d.relocalised, d.detail
        assert [m.source for m in d.members] == ["forward", "forward"]
        errors.append(np.hypot(*(d.transform[:2] - T_TRUE[:2])))
        assert abs(wrap_angle(d.transform[2] - T_TRUE[2])) < math.radians(3.0)
        # The members' edges are re-evaluated at the fitted transform: their range is the fit's.
        m = d.members[0]
        pred = between(m.old_pose, compose(d.transform, m.query_pose))
        assert np.allclose(m.delta[:2], pred[:2], atol=0.2)
    # Without any range measured the two bearings alone place the robot to about a decimetre.
    assert np.median(errors) < 0.15 and max(errors) < 0.4


def test_a_forward_and_a_floor_loop_agree_and_a_forward_look_alike_does_not():
    rng = np.random.default_rng(11)
    reloc = Relocaliser(_relative)
    wrong = compose(T_TRUE, np.array([0.0, 2.5, math.radians(-40.0)]))
    assert not reloc.offer(_forward(3, rng, np.array([1.5, 0.3, 0.1]), transform=wrong)).relocalised
    assert not reloc.offer(_forward(12, rng, np.array([1.5, 0.3, 0.1]))).relocalised  # disagrees with it
    d = reloc.offer(_candidate(30, rng))
    assert d.relocalised, d.detail
    assert sorted(m.source for m in d.members) == ["floor", "forward"]
    assert [c.query_id for c, _ in d.dropped] == [3]
    assert np.hypot(*(d.transform[:2] - T_TRUE[:2])) < 0.05


def test_two_forward_loops_along_one_line_of_sight_do_not_fix_the_position():
    """Both queries on the line from the old keyframe, the robot driving along it: the two
    bearings coincide, the range is not fixed, and the group waits."""
    rng = np.random.default_rng(12)
    straight = np.array([[0.1 * k, 0.0, 0.0] for k in range(60)])

    def relative(a: int, b: int) -> tuple[np.ndarray, np.ndarray] | None:
        return (between(straight[a], straight[b]), np.diag([1e-4, 1e-4, 1e-6])) if b > a else None

    old = np.array([-1.0, 0.0, 0.0])  # in the lost frame: behind the queries, same heading
    cands = []
    for q in (5, 20):
        c = _forward(q, rng, between(old, straight[q]))
        cands.append(RelocCandidate(c.old_id, q, c.score, compose(T_TRUE, old), c.delta, c.information,
                                    straight[q], 0.1 * q, 1, "forward", c.edge, 2))
    reloc = Relocaliser(relative, RelocParams(min_forward_only=2))
    assert not reloc.offer(cands[0]).relocalised
    d = reloc.offer(cands[1])
    assert not d.relocalised
    assert "the position is not fixed" in d.detail


def _wrong_bearing(q: int, rng: np.random.Generator, old_offset: np.ndarray, off_rad: float) -> RelocCandidate:
    """A forward loop to the right old keyframe whose bearing came out ``off_rad`` wrong
    (the heading right): the kind the five-point motion gives at short baselines."""
    c = _forward(q, rng, old_offset)
    edge = c.edge
    assert edge is not None

    def wrong(predicted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        delta, info = edge(predicted)
        rng_m = float(np.hypot(delta[0], delta[1]))
        b = math.atan2(delta[1], delta[0]) + off_rad
        return np.array([rng_m * math.cos(b), rng_m * math.sin(b), delta[2]]), info

    return RelocCandidate(c.old_id, c.query_id, c.score, c.old_pose, *wrong(np.array([1.0, 0.0, 0.0])),
                          c.query_pose, c.travelled_m, c.old_run, "forward", wrong, 2)


def test_two_forward_loops_cannot_check_each_others_bearing_so_a_third_must_agree():
    """Two bearings from places apart always cross: with one of them 30 deg wrong, the two
    loops' fit still agrees and puts the robot 0.4-0.5 m off. By default a group of forward
    loops only waits for a third member (or a floor loop): the groups the wrong loop joins
    then either disagree, are ambiguous against the right ones, or stay within 0.3 m."""
    for seed in range(5):
        def cands(rng: np.random.Generator) -> list[RelocCandidate]:
            return [_forward(5, rng, np.array([1.8, 0.4, 0.2])),
                    _wrong_bearing(20, rng, np.array([0.8, 0.3, 0.2]), math.radians(30.0)),
                    _forward(40, rng, np.array([0.5, 1.5, 0.8])),
                    _forward(55, rng, np.array([1.6, -0.6, -0.3]))]

        two = Relocaliser(_relative, RelocParams(min_forward_only=2))
        c = cands(np.random.default_rng(300 + seed))
        assert not two.offer(c[0]).relocalised
        d = two.offer(c[1])
        assert d.relocalised, d.detail  # what two members allow: a wrong place
        assert np.hypot(*(d.transform[:2] - T_TRUE[:2])) > 0.4
        reloc = Relocaliser(_relative)
        c = cands(np.random.default_rng(300 + seed))
        assert not reloc.offer(c[0]).relocalised
        d = reloc.offer(c[1])
        assert not d.relocalised
        assert "2 forward loops only" in d.detail
        for k in (2, 3):
            d = reloc.offer(c[k])
            if d.relocalised:
                break
        if d.relocalised:
            assert np.hypot(*(d.transform[:2] - T_TRUE[:2])) < 0.3
        else:
            assert "ambiguous" in d.detail or "disagrees" in d.detail


def test_three_right_forward_loops_relocalise_together():
    rng = np.random.default_rng(41)
    reloc = Relocaliser(_relative)
    assert not reloc.offer(_forward(5, rng, np.array([1.8, 0.4, 0.2]))).relocalised
    assert not reloc.offer(_forward(20, rng, np.array([0.5, 1.5, 0.8]))).relocalised
    d = reloc.offer(_forward(40, rng, np.array([1.6, -0.6, -0.3])))
    assert d.relocalised, d.detail
    assert sorted(m.query_id for m in d.members) == [5, 20, 40]
    assert np.hypot(*(d.transform[:2] - T_TRUE[:2])) < 0.15
    with pytest.raises(ValueError, match="min_forward_only"):
        RelocParams(min_forward_only=0)
