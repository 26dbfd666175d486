"""iSAM2 updates agree with the batch solver; a re-solve restarts from the batch result."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from robotd.base.errors import GraphError
from robotd.base.geometry import between, compose, compose_jacobians, rot2
from robotd.graph import BatchParams, IncrementalGraph, optimize_batch
from robotd.graph.incremental import IncrementalParams
from robotd.odometry.relative import relative_pose_jacobians

INFO = np.diag([400.0, 400.0, 2500.0])


def _drive(inc: IncrementalGraph, n: int = 24, seed: int = 1) -> None:
    """A noisy ring of n keyframes, closing back on keyframe 0 and once across."""
    rng = np.random.default_rng(seed)
    step = 2 * math.pi / n
    chord = 2 * 5 * math.sin(step / 2)
    inc.add_first(100)
    for k in range(1, n):
        inc.add_keyframe(100 + 2 * k, 100 + 2 * (k - 1),
                         (chord + rng.normal(0, 0.05), rng.normal(0, 0.05), step + rng.normal(0, 0.02)),
                         INFO)
    inc.add_loop(100 + 2 * (n - 1), 100, (chord, 0.0, step), INFO)
    inc.add_loop(100 + 2 * (n // 4), 100 + 2 * (3 * n // 4), (0.0, 10.0, math.pi), INFO)


def test_incremental_matches_batch_on_a_small_graph():
    inc = IncrementalGraph()
    _drive(inc)
    batch = optimize_batch(inc.graph, BatchParams(robust=False))
    ids, poses = inc.estimate()
    assert np.array_equal(ids, batch.ids)
    assert np.allclose(poses[:, :2], batch.poses[:, :2], atol=5e-4)  # iSAM2 relinearises above its threshold only
    assert np.allclose(np.cos(poses[:, 2] - batch.poses[:, 2]), 1.0, atol=1e-7)
    assert np.allclose(poses[0], 0.0)


def test_resolve_returns_the_batch_result_and_keeps_going():
    inc = IncrementalGraph(IncrementalParams(fold=1))  # every keyframe stays in iSAM2
    _drive(inc)
    result = inc.resolve()
    ids, poses = inc.estimate()
    assert np.allclose(poses, result.poses, atol=1e-4)  # one iSAM2 step past LM's stop
    last = inc.add_keyframe(999, int(ids[-1]), (1.0, 0.0, 0.0), INFO)
    assert np.allclose(last[:2], poses[-1, :2] + [math.cos(poses[-1, 2]), math.sin(poses[-1, 2])], atol=1e-6)


def test_the_estimate_follows_every_change_of_the_graph():
    """estimate() is computed once per change (the mapped-ground test asks for it at every
    keyframe): after each kind of change it is iSAM2's estimate again, and a caller that
    writes into the returned arrays does not change the next answer."""
    inc = IncrementalGraph()
    inc.add_first(0)
    inc.add_keyframe(1, 0, (1.0, 0.0, 0.0), INFO)
    ids, poses = inc.estimate()
    poses[:] = 99.0
    assert inc.estimate()[1][1] == pytest.approx([1.0, 0.0, 0.0], abs=1e-9)
    inc.add_keyframe(2, 1, (1.0, 0.0, math.pi / 2), INFO)
    assert list(inc.estimate()[0]) == [0, 1, 2]
    inc.add_loop(2, 0, (-2.0, 0.2, -math.pi / 2), INFO)  # pulls keyframe 2 sideways
    moved = inc.estimate()[1][2]
    assert moved[1] != pytest.approx(0.0, abs=1e-3) and moved == pytest.approx(inc.pose(2), abs=1e-12)
    result = inc.resolve()
    assert inc.estimate()[1] == pytest.approx(result.poses, abs=1e-4)


def test_odometry_from_an_unknown_keyframe_is_an_error():
    inc = IncrementalGraph()
    inc.add_first(0)
    with pytest.raises(GraphError, match="unknown keyframe 5"):
        inc.add_keyframe(6, 5, (1, 0, 0), INFO)


def _branch(inc: IncrementalGraph, first_id: int, n: int, rng: np.random.Generator
            ) -> tuple[int, np.ndarray, np.ndarray]:
    """A chain of ``n`` odometry edges from the anchor (keyframe 0), each with its own full
    covariance, which GTSAM applies to the error ``log(delta^-1 (+) a^-1 (+) b)`` in the
    frame of the edge's end. Returns the last id, its pose in the anchor's frame and that
    pose's covariance of errors added in the anchor's frame, propagated by hand."""
    pose, cov, prev = np.zeros(3), np.zeros((3, 3)), 0
    for k in range(n):
        d = np.array([0.05, 0.0, 0.3 * rng.standard_normal()])
        a = rng.standard_normal((3, 3)) * np.array([1e-3, 1e-3, 2e-3])
        c = a @ a.T + 1e-8 * np.eye(3)
        inc.add_keyframe(first_id + k, prev, d, np.linalg.inv(c))
        prev = first_id + k
        turn = np.eye(3)
        turn[:2, :2] = rot2(d[2])  # the edge's end frame -> its start frame
        j_pose, j_delta = compose_jacobians(pose, d)
        cov = j_pose @ cov @ j_pose.T + j_delta @ turn @ c @ turn.T @ j_delta.T
        pose = compose(pose, d)
    return prev, pose, cov


def test_the_gate_covariance_is_the_relative_poses_when_the_poses_are_uncorrelated():
    """Two branches from the fixed anchor, so their ends' errors are independent and the
    gate's ``S = Ad P_a Ad^T + P_b + R`` (iSAM2's marginals in each pose's own frame, the
    adjoint of the predicted relative pose) is exact: a loop measured 3 sigma off along each
    principal axis of the relative pose's covariance (propagated by hand through both
    branches) has exactly the chi-square that covariance gives. The adjoint of the relative
    pose instead of its inverse's is 15-45 % off here, and so is the hand propagation by
    2-6 % if it takes each edge's covariance in the edge's start frame: GTSAM applies it
    in the frame of the edge's end (``between_error_covariance``)."""
    rng = np.random.default_rng(3)
    inc = IncrementalGraph()
    inc.add_first(0, (1.0, 2.0, 0.7))
    a, pose_a, cov_a = _branch(inc, 1, 30, rng)
    b, pose_b, cov_b = _branch(inc, 100, 40, rng)
    h, j_b, j_a = relative_pose_jacobians(pose_a, pose_b)
    rel = j_b @ cov_b @ j_b.T + j_a @ cov_a @ j_a.T
    turn = np.eye(3)
    turn[:2, :2] = rot2(h[2]).T
    rel = turn @ rel @ turn.T  # in the frame of the relative pose's end, as the gate's error
    loop_cov = np.diag([1e-6, 2e-6, 1e-5])
    predicted = gtsam.Pose2(*between(inc.pose(a), inc.pose(b)))
    for axis in np.linalg.eigh(rel)[1].T:
        off = 3.0 * axis * math.sqrt(axis @ rel @ axis)
        m = predicted.compose(gtsam.Pose2.Expmap(off))  # log(predicted^-1 measured) = off
        measured = np.array([m.x(), m.y(), m.theta()])
        want = off @ np.linalg.solve(rel + loop_cov, off)
        assert inc.loop_chi2(a, b, measured, np.linalg.inv(loop_cov)) == pytest.approx(want, rel=1e-3)


def _laps(inc: IncrementalGraph, laps: int, n: int = 20, seed: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A ring of ``n`` keyframes driven ``laps`` times with noisy odometry; every keyframe
    of a later lap loops (exact measurements) to the keyframe at the same place in each
    earlier lap, as repeated passes over mapped ground do. Returns the true and the dead
    reckoned positions ``(laps * n, 2)`` of the keyframes (ids ``0 .. laps * n - 1``)."""
    rng = np.random.default_rng(seed)
    step = 2 * math.pi / n
    chord = 2 * 5 * math.sin(step / 2)
    truth, odo = [np.zeros(3)], [np.zeros(3)]
    inc.add_first(0)
    for kid in range(1, laps * n):
        d = np.array([chord + rng.normal(0, 0.03), rng.normal(0, 0.03), step + rng.normal(0, 0.01)])
        inc.add_keyframe(kid, kid - 1, d, INFO)
        truth.append(compose(truth[-1], (chord, 0.0, step)))
        odo.append(compose(odo[-1], d))
        for earlier in range(kid - n, -1, -n):
            inc.add_loop(earlier, kid, (0.0, 0.0, 0.0), INFO)
    return np.array(truth)[:, :2], np.array(odo)[:, :2]


def test_loops_near_a_loop_in_the_graph_are_left_out():
    """Four laps of a ring of 20: 120 loops, each later keyframe to every earlier lap. With
    ``loop_spacing`` 2 every other keyframe's loops enter (all of them: their older ends
    are a lap apart); with ``loops_per_keyframe`` 1 a keyframe adds only its first (to the
    lap before). The graph with half the loops is about as close to the truth, and the
    full solve and iSAM2 after it agree on it."""
    every = IncrementalGraph(IncrementalParams(loop_spacing=0, loops_per_keyframe=0, loops_per_place=0))
    truth, odo = _laps(every, 4)
    thin = IncrementalGraph(IncrementalParams(loop_spacing=2, loops_per_keyframe=0, fold=1, loops_per_place=0))
    _laps(thin, 4)
    one = IncrementalGraph(IncrementalParams(loop_spacing=0, loops_per_keyframe=1, loops_per_place=0))
    _laps(one, 4)
    loops = 20 * (1 + 2 + 3)
    assert every.stats()["loops"] == loops and every.held_loops == 0
    assert every.stats()["factors"] == len(every.graph.edges) + 1  # and the anchor
    assert thin.stats()["loops"] == 10 * (1 + 2 + 3) and thin.held_loops == loops - 60
    assert all(e.to_id % 2 == 0 for e in thin.graph.edges if e.kind == "loop")
    assert thin.stats()["factors"] == len(thin.graph.edges) + 1
    kept_one = [e for e in one.graph.edges if e.kind == "loop"]
    assert len(kept_one) == 60 and all(e.to_id - e.from_id == 20 for e in kept_one)

    def rms(xy: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((xy - truth) ** 2, axis=1))))

    err_all, err_thin, err_odo = rms(every.estimate()[1][:, :2]), rms(thin.estimate()[1][:, :2]), rms(odo)
    assert err_thin < 1.3 * err_all and err_all < 0.25 * err_odo
    result = thin.resolve()
    assert rms(result.poses[:, :2]) < 1.3 * err_all
    assert thin.stats()["factors"] == len(thin.graph.edges) + 1
    assert np.allclose(thin.estimate()[1], result.poses, atol=1e-4)


def test_one_loop_per_place_chains_the_laps():
    """With ``loops_per_place`` 1 a place's keyframe receives one loop in iSAM2: each lap
    ties to the lap before (the first offered to each older place) and the later laps'
    loops to that place are left out, so the tree stays smaller than with every pass tied
    to every earlier one, and the estimate about as close to the truth."""
    every = IncrementalGraph(IncrementalParams(loop_spacing=0, loops_per_keyframe=0, loops_per_place=0))
    truth, _odo = _laps(every, 5)
    chained = IncrementalGraph(IncrementalParams(loop_spacing=0, loops_per_keyframe=0, loops_per_place=1))
    _laps(chained, 5)
    loops = [e for e in chained.graph.edges if e.kind == "loop"]
    assert len(loops) == 20 * 4 and all(e.to_id - e.from_id == 20 for e in loops)
    assert chained.held_loops == 20 * (1 + 2 + 3 + 4) - 80
    assert chained.stats()["tree_nnz"] < every.stats()["tree_nnz"]

    def rms(xy: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((xy - truth) ** 2, axis=1))))

    assert rms(chained.estimate()[1][:, :2]) < 1.5 * rms(every.estimate()[1][:, :2])
    with pytest.raises(ValueError, match="loops_per_place"):
        IncrementalParams(loops_per_place=-1)


def test_a_left_out_loop_is_checked_as_any_edge():
    inc = IncrementalGraph(IncrementalParams(loop_spacing=5))
    inc.add_first(0)
    for k in range(1, 10):
        inc.add_keyframe(k, k - 1, (1.0, 0.0, 0.0), INFO)
    assert inc.add_loop(0, 8, (8.0, 0.0, 0.0), INFO)
    assert not inc.add_loop(1, 9, (8.0, 0.0, 0.0), INFO)  # one keyframe after the last in
    with pytest.raises(GraphError, match="no vertex 42"):
        inc.add_loop(2, 42, (8.0, 0.0, 0.0), INFO)
    with pytest.raises(GraphError, match="not positive definite"):
        inc.add_loop(2, 9, (8.0, 0.0, 0.0), -INFO)
    assert inc.held_loops == 1


def test_holding_loops_out_shrinks_the_bayes_tree():
    """The point of leaving loops out: over repeated laps, the tree's conditionals (and so
    iSAM2's memory) grow with the loops it holds."""
    every = IncrementalGraph(IncrementalParams(loop_spacing=0, loops_per_keyframe=0, loops_per_place=0))
    _laps(every, 5)
    thin = IncrementalGraph()  # the defaults
    _laps(thin, 5)
    assert thin.stats()["tree_nnz"] < 0.6 * every.stats()["tree_nnz"]


def test_a_failed_restart_after_a_full_solve_leaves_the_graph_as_it_was(monkeypatch):
    """resolve() lets the old iSAM2 go before building the new one: if the new one fails,
    iSAM2 is rebuilt at the estimate from before the solve and the error is raised (the
    graph stage logs it and goes on)."""
    inc = IncrementalGraph()
    _drive(inc)
    inc.rejected_loops = {len(inc.graph.edges) - 1}  # as if the last solve had rejected the cross loop
    inc.attach([], (0.0, 0.0, 0.0), [])  # iSAM2 rebuilt without it
    before = inc.estimate()[1]
    real = inc._new_isam
    calls = []

    class Failing:
        def update(self, *args: object) -> None:
            raise RuntimeError("indeterminate system")

    def new_isam() -> object:
        calls.append(1)
        return Failing() if len(calls) == 1 else real()

    monkeypatch.setattr(inc, "_new_isam", new_isam)
    with pytest.raises(RuntimeError, match="indeterminate"):
        inc.resolve()
    assert len(calls) == 2
    assert np.allclose(inc.estimate()[1], before, atol=1e-3)  # one iSAM2 step from it
    assert inc.rejected_loops == {len(inc.graph.edges) - 1}
    assert inc.stats()["factors"] == len(inc.graph.edges)  # the anchor, without the rejected loop
    ids = inc.estimate()[0]
    inc.add_keyframe(999, int(ids[-1]), (1.0, 0.0, 0.0), INFO)
    assert inc.pose(999) == pytest.approx(compose(inc.pose(int(ids[-1])), (1.0, 0.0, 0.0)), abs=1e-6)


def test_the_newest_loop_left_out_joins_the_graph_at_a_full_solve():
    """The keyframes after the last loop in would end on odometry alone: a full solve
    (periodic, and at the end of a run) first adds the newest loop left out, if no loop
    entered after it."""
    inc = IncrementalGraph(IncrementalParams(loop_spacing=5, fold=1))
    inc.add_first(0)
    for k in range(1, 12):
        inc.add_keyframe(k, k - 1, (1.0, 0.0, 0.0), INFO)
    assert inc.add_loop(0, 6, (6.0, 0.0, 0.0), INFO)
    assert not inc.add_loop(1, 8, (7.0, 0.0, 0.0), INFO)
    assert not inc.add_loop(2, 9, (6.5, 0.0, 0.0), INFO)  # the newest left out
    inc.resolve()
    assert [(e.from_id, e.to_id) for e in inc.graph.edges if e.kind == "loop"] == [(0, 6), (2, 9)]
    assert inc.held_loops == 1 and inc.stats()["factors"] == len(inc.graph.edges) + 1
    assert not inc.add_loop(3, 11, (8.0, 0.0, 0.0), INFO)  # spaced from the one that joined


LONG_CHAIN_INFO = np.diag([1e8, 1e8, 2e6])
LONG_CHAIN = [(0.15, 0.0, 0.02 * np.sin(k / 40)) for k in range(1, 1000)]


def _long_chain(params: IncrementalParams) -> IncrementalGraph:
    g = IncrementalGraph(params)
    g.add_first(0)
    for k, step in enumerate(LONG_CHAIN, start=1):
        g.add_keyframe(k, k - 1, step, LONG_CHAIN_INFO)
    return g


def _chain_end() -> np.ndarray:
    expected = np.zeros(3)
    for step in LONG_CHAIN:
        expected = compose(expected, np.array(step))
    return expected


def test_a_long_drive_without_loops_stays_solvable():
    """A winding 150 m chain with no loop: the newest pose's marginal information becomes
    the small difference of large edge informations. iSAM2's Cholesky loses it and GTSAM
    raises an indeterminate system (here GTSAM's own iSAM2, fed as IncrementalGraph feeds
    it); the default QR goes on and keeps the chain's own composition, without a failure."""
    p = gtsam.ISAM2Params()
    p.setRelinearizeThreshold(0.01)
    p.setFactorization("CHOLESKY")
    isam = gtsam.ISAM2(p)
    fg = gtsam.NonlinearFactorGraph()
    fg.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-8)))
    v = gtsam.Values()
    v.insert(0, gtsam.Pose2())
    isam.update(fg, v)
    pose = np.zeros(3)
    with pytest.raises(RuntimeError, match="[Ii]ndeterminate"):
        for k, step in enumerate(LONG_CHAIN, start=1):
            fg = gtsam.NonlinearFactorGraph()
            fg.add(gtsam.BetweenFactorPose2(k - 1, k, gtsam.Pose2(*step),
                                            gtsam.noiseModel.Gaussian.Information(LONG_CHAIN_INFO)))
            pose = compose(pose, np.array(step))
            v = gtsam.Values()
            v.insert(k, gtsam.Pose2(*pose))
            isam.update(fg, v)
    g = _long_chain(IncrementalParams())
    np.testing.assert_allclose(g.pose(len(LONG_CHAIN)), _chain_end(), atol=1e-6)
    assert g.isam_failures == 0


def test_an_isam2_failure_is_recovered_from_the_whole_graph(caplog):
    """When iSAM2 raises (the chain above under Cholesky), the graph is re-solved whole and
    iSAM2 rebuilt from it by QR: counted, logged, the chain's own composition kept, every
    keyframe still in the graph, and the updates go on (a loop after it enters and moves
    the estimate as in a graph that never failed)."""
    with caplog.at_level("WARNING", logger="robotd.graph.incremental"):
        g = _long_chain(IncrementalParams(factorization="CHOLESKY"))
    assert g.isam_failures == 1 and g.factorization == "QR"
    assert "iSAM2 failed" in caplog.text and "rebuilt from a full solve, QR from now on" in caplog.text
    assert len(g.graph) == len(LONG_CHAIN) + 1
    np.testing.assert_allclose(g.pose(len(LONG_CHAIN)), _chain_end(), atol=1e-6)
    ok = _long_chain(IncrementalParams())
    for graph in (g, ok):  # the chain's end tied back near its start
        end = len(LONG_CHAIN)
        graph.add_loop(end - 500, end, tuple(between(ok.pose(end - 500), ok.pose(end)) + [0.05, 0.0, 0.0]),
                       np.diag([1e4, 1e4, 1e4]))
    np.testing.assert_allclose(g.estimate()[1], ok.estimate()[1], atol=1e-6)
    assert g.isam_failures == 1


class _Failing:
    """iSAM2 raising GTSAM's indeterminate system on a call of ``what``."""

    def __init__(self, isam, what):
        self.isam, self.what = isam, what

    def __getattr__(self, name):
        if name == self.what:
            raise RuntimeError("\nIndeterminate linear system detected while working near variable\n140")
        return getattr(self.isam, name)


def test_a_failing_relocalisation_rebuild_is_recovered(monkeypatch):
    """A segment attached (relocalised) while iSAM2's rebuild raises: recovered from the
    whole graph, the segment moved and tied as without the failure."""
    graphs = []
    for fail in (False, True):
        g = IncrementalGraph()
        g.add_first(0)
        for k in range(1, 6):
            g.add_keyframe(k, k - 1, (1.0, 0.0, 0.0), INFO)
        g.add_segment(10, (0.0, 0.0, 0.0))
        for k in range(11, 14):
            g.add_keyframe(k, k - 1, (1.0, 0.0, 0.0), INFO)
        if fail:
            real, made = g._new_isam, []

            def failing_once():  # the attach's rebuild fails, the recovery's does not
                made.append(1)
                return _Failing(real(), "update") if len(made) == 1 else real()

            monkeypatch.setattr(g, "_new_isam", failing_once)
            g.attach([10, 11, 12, 13], (5.0, 0.0, 0.0), [(5, 10, np.zeros(3), INFO)])
            monkeypatch.undo()
        else:
            g.attach([10, 11, 12, 13], (5.0, 0.0, 0.0), [(5, 10, np.zeros(3), INFO)])
        graphs.append(g)
    ok, bad = graphs
    assert ok.isam_failures == 0 and bad.isam_failures == 1
    np.testing.assert_allclose(bad.estimate()[1], ok.estimate()[1], atol=1e-6)
    np.testing.assert_allclose(bad.pose(13), (8.0, 0.0, 0.0), atol=1e-6)


def test_a_failing_update_keeps_its_edge_and_the_marginals_recover(monkeypatch):
    """Any iSAM2 failure, a loop's update or the gate's marginals: the edge that was being
    added is in the rebuilt iSAM2 (the estimate equals a graph that took it without a
    failure) and the gate gets its chi2."""
    ok, bad = IncrementalGraph(IncrementalParams(loops_per_place=0)), IncrementalGraph(
        IncrementalParams(loops_per_place=0))
    _drive(ok)
    _drive(bad)
    a, b = 100 + 2 * 2, 100 + 2 * 13
    loop = (a, b, tuple(between(ok.pose(a), ok.pose(b)) + [0.1, -0.1, 0.02]), INFO)

    expected = ok.loop_chi2(*loop)
    bad._isam = _Failing(bad._isam, "marginalCovariance")
    assert bad.loop_chi2(*loop) == pytest.approx(expected, rel=1e-3)
    assert bad.isam_failures == 1
    assert ok.add_loop(*loop)
    bad._isam = _Failing(bad._isam, "update")
    assert bad.add_loop(*loop)
    assert bad.isam_failures == 2 and bad.factorization == "QR"
    assert bad.graph.loop_count == ok.graph.loop_count
    np.testing.assert_allclose(bad.estimate()[1], ok.estimate()[1], atol=2e-3)


def test_a_full_solve_folds_the_keyframes_without_loops_into_their_odometry():
    """After a full solve iSAM2 keeps the anchor, the loops' ends, the newest ``fold``
    keyframes and one in ``fold`` along the chain; the others follow the kept keyframe
    before them, as the full solve placed them relative to it. The estimate stays that of
    the same graph with every keyframe in iSAM2 (within a few mm on this noisy ring), a
    folded keyframe's covariance is at least its own, loops to folded keyframes are gated
    and enter as with every keyframe kept, and the full solve still has every keyframe."""
    full = IncrementalGraph(IncrementalParams(fold=1, loops_per_place=0))
    folded = IncrementalGraph(IncrementalParams(fold=4, loops_per_place=0))
    for inc in (full, folded):
        _laps(inc, 3)
    want, got = full.resolve(), folded.resolve()
    assert np.array_equal(want.ids, got.ids) and np.allclose(want.poses, got.poses, atol=1e-9)
    st = folded.stats()
    loop_ends = {k for e in folded.graph.edges if e.kind == "loop" for k in (e.from_id, e.to_id)}
    assert st["folded"] > 15 and st["factors"] < full.stats()["factors"] - 15
    assert full.stats()["folded"] == 0 and not loop_ends & set(folded._fold_ids.tolist())
    ids, est_full = full.estimate()
    assert np.array_equal(folded.estimate()[0], ids)
    assert np.allclose(folded.estimate()[1][:, :2], est_full[:, :2], atol=5e-3)
    k = int(folded._fold_ids[0])
    a = int(folded._fold_anchor[0])
    assert np.allclose(folded.pose(k), compose(folded.pose(a), between(want.poses[a], want.poses[k])), atol=1e-9)
    assert np.all(np.linalg.eigvalsh(folded.marginal_covariance(k) - full.marginal_covariance(k)) > -1e-9)
    # New keyframes and a loop from the newest to a folded one: both graphs move alike.
    for inc in (full, folded):
        for kid in range(60, 76):  # past loop_spacing from the last loop in
            inc.add_keyframe(kid, kid - 1, (2 * 5 * math.sin(math.pi / 20), 0.0, 2 * math.pi / 20), INFO)
    old = int(next(i for i in folded._fold_ids.tolist() if i % 20 == 75 % 20))
    chi = [inc.loop_chi2(old, 75, (0.0, 0.0, 0.0), INFO) for inc in (full, folded)]
    assert chi[1] <= chi[0] * 1.05  # the folded keyframe's larger covariance: as lenient at least
    for inc in (full, folded):
        assert inc.add_loop(old, 75, (0.0, 0.0, 0.0), INFO)
    assert np.allclose(folded.pose(75)[:2], full.pose(75)[:2], atol=5e-3)
    assert np.allclose(folded.pose(old)[:2], full.pose(old)[:2], atol=5e-3)
    assert len(folded.graph) == len(full.graph) == 76


def test_fold_must_be_positive():
    with pytest.raises(ValueError):
        IncrementalParams(fold=0)


def test_the_joint_gate_covariance_is_the_relative_poses_on_one_chain():
    """Two poses on one chain from the anchor share the chain's first part: their relative
    pose's covariance is that of the edges between them alone. With ``joint`` the gate's
    ``S`` is exactly that (the same chi-square as in a graph anchored at the first pose);
    the marginals alone count the shared part twice and judge the same loop far more
    leniently."""
    rng = np.random.default_rng(5)
    inc = IncrementalGraph()
    inc.add_first(0)
    a, _pose_a, _cov_a = _branch(inc, 1, 40, rng)  # the shared part
    ref = IncrementalGraph()  # the same edges from ``a`` on, anchored at ``a``'s estimate
    ref.add_first(a, inc.pose(a))
    prev = a
    for k in range(30):
        d = np.array([0.05, 0.0, 0.3 * rng.standard_normal()])
        c = np.diag([1e-6, 2e-6, 4e-6])
        inc.add_keyframe(500 + k, prev, d, np.linalg.inv(c))
        ref.add_keyframe(500 + k, prev, d, np.linalg.inv(c))
        prev = 500 + k
    b = prev
    assert inc.pose(b) == pytest.approx(ref.pose(b), abs=1e-9)
    rel = ref.marginal_covariance(b)  # the relative pose's covariance, in b's frame
    loop_cov = np.diag([1e-6, 1e-6, 1e-5])
    predicted = gtsam.Pose2(*between(inc.pose(a), inc.pose(b)))
    for axis in np.linalg.eigh(rel + loop_cov)[1].T:
        off = 3.0 * axis * math.sqrt(axis @ (rel + loop_cov) @ axis)
        m = predicted.compose(gtsam.Pose2.Expmap(off))
        measured = np.array([m.x(), m.y(), m.theta()])
        want = ref.loop_chi2(a, b, measured, np.linalg.inv(loop_cov))
        assert want == pytest.approx(9.0, rel=0.02)  # 3 sigma (the anchor's own prior is tiny)
        assert inc.loop_chi2(a, b, measured, np.linalg.inv(loop_cov), joint=True) == pytest.approx(want, rel=1e-3)
        assert inc.loop_chi2(a, b, measured, np.linalg.inv(loop_cov)) < 0.7 * want


def _three_passes(params: IncrementalParams) -> list[tuple[int, int]]:
    """Three passes over 30 places (ids 0-29, 30-59, 60-89), each later pass offering, at
    every tenth keyframe, a loop to the pass before and then to the first; the loops that
    entered iSAM2, as (newer, older)."""
    g = IncrementalGraph(params)
    g.add_first(0)
    for k in range(1, 90):
        g.add_keyframe(k, k - 1, (0.1, 0.0, 0.0) if k % 30 else (-2.9, 0.0, 0.0), INFO)
        if k >= 30 and k % 10 == 0:
            for older in sorted({k - 30, k % 30}, reverse=True):
                g.add_loop(older, k, (0.0, 0.0, 0.0), INFO)
    return sorted((e.to_id, e.from_id) for e in g.graph.edges if e.kind == "loop")


def test_later_passes_tie_to_the_previous_pass_or_to_the_first():
    """``tie_to="previous"`` (with one loop per place): the third pass ties to the second
    (the first's places are taken); ``"first"``: every pass ties to the first, the second
    pass's keyframes being newer ends of loops themselves."""
    second = [(30, 0), (40, 10), (50, 20)]
    assert _three_passes(IncrementalParams(loops_per_place=1)) == second + [(60, 30), (70, 40), (80, 50)]
    assert _three_passes(IncrementalParams(tie_to="first")) == second + [(60, 0), (70, 10), (80, 20)]
    with pytest.raises(ValueError):
        IncrementalParams(tie_to="nearest")


def test_a_relocalised_segment_is_held_by_its_loops_alone():
    """A new segment is held at its first keyframe until it relocalises; after that only
    the map's first keyframe is held (a prior left on the segment would claim a pose it
    does not know): its heading relative to the map is then as uncertain as its loops
    leave it, and a full solve moves its first keyframe."""
    inc = IncrementalGraph(IncrementalParams(loop_spacing=0, loops_per_place=0))
    inc.add_first(0)
    for k in range(1, 10):
        inc.add_keyframe(k, k - 1, [0.1, 0.0, 0.0], INFO)
    inc.add_segment(10, [0.0, 0.0, 0.0])
    for k in range(11, 20):
        inc.add_keyframe(k, k - 1, [0.1, 0.0, 0.0], INFO)
    assert inc.graph.anchors() == [0, 10]
    assert inc.marginal_covariance(10)[2, 2] < 1e-8  # held in iSAM2 until it relocalises
    # put down 0.5 m along: keyframe 10 is where 5 was; the loops say 2 mm and 0.2 deg more
    loop = np.array([0.002, 0.0, math.radians(0.2)])
    inc.attach(range(10, 20), [0.5, 0.0, 0.0], [(5, 10, loop, INFO), (7, 12, loop, INFO)])
    assert inc.graph.anchors() == [0]
    assert inc.stats()["factors"] == 18 + 2 + 1  # odometry, the two loops, the first keyframe's anchor
    yaw_sigma = math.sqrt(inc.marginal_covariance(10)[2, 2])
    assert yaw_sigma > math.sqrt(1 / INFO[2, 2])  # at least one loop's and the chain's
    result = inc.resolve()
    first = result.poses[list(result.ids).index(10)]
    assert abs(first[2] - math.radians(0.2)) < math.radians(0.05)  # the loops placed it, no prior
