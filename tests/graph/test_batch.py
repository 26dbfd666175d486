"""Batch optimisation against hand-derived optima, a wrong loop, and the CSAIL benchmark."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.graph import BatchParams, PoseGraph, optimize_batch
from robotd.io.g2o import read_g2o


def _straight_chain_with_loop(loop_dx_m: float) -> PoseGraph:
    """0 -> 1 -> 2 -> 3 along x (odometry 1 m each) and a loop 0 -> 3 measuring loop_dx_m,
    all with information diag(w, w, w); the initial guess is off."""
    g = PoseGraph()
    for k in range(4):
        g.add_pose(k, (1.3 * k, 0.2 * k, 0.05 * k))
    for k in range(3):
        g.add_edge(k, k + 1, (1.0, 0.0, 0.0), np.eye(3) * 4.0, "odometry")
    g.add_edge(0, 3, (loop_dx_m, 0.0, 0.0), np.eye(3) * 4.0, "loop")
    return g


@pytest.mark.parametrize("init", ["lago", "odometry"])
def test_a_loop_disagreeing_by_0_3_m_spreads_equally_over_the_cycle(init):
    # With no rotation the problem is linear: the 0.3 m cycle error is split over the four
    # equally weighted edges, so each odometry edge stretches to 0.925 m and the loop edge
    # is off by 0.075 m; objective 4 edges * 4 * 0.075^2.
    g = _straight_chain_with_loop(2.7)
    r = optimize_batch(g, BatchParams(initialisation=init))
    # LM stops at a relative cost decrease of 1e-5: the result is exact to ~1e-5 m.
    assert np.allclose(r.poses[:, 0], [0.0, 0.925, 1.85, 2.775], atol=1e-4)
    assert np.allclose(r.poses[:, 1:], 0.0, atol=1e-4)
    assert r.final_objective == pytest.approx(4 * 4.0 * 0.075**2, rel=1e-5)
    assert r.initial_objective > r.final_objective
    assert np.allclose(r.loop_weights, [1.0])


def test_a_square_with_a_consistent_loop_closes_exactly():
    g = PoseGraph()
    rng = np.random.default_rng(3)
    corners = [(0, 0, 0), (2, 0, math.pi / 2), (2, 2, math.pi), (0, 2, -math.pi / 2)]
    for k, c in enumerate(corners):
        g.add_pose(k + 5 * k, np.array(c) + rng.normal(0, 0.2, 3) * (k > 0))  # ids 0, 6, 12, 18
    ids = [0, 6, 12, 18]
    for a, b in zip(ids, ids[1:] + ids[:1]):
        g.add_edge(a, b, (2.0, 0.0, math.pi / 2), np.diag([100.0, 100.0, 400.0]),
                   "odometry" if b else "loop")
    r = optimize_batch(g)
    assert np.allclose(r.poses[:, :2], np.array(corners)[:, :2], atol=1e-6)
    assert np.allclose(np.cos(r.poses[:, 2] - np.array(corners)[:, 2]), 1.0)
    assert r.final_objective < 1e-10


def _ring(n: int = 24) -> PoseGraph:
    """A closed polygon of n poses, odometry all around, plus two true loops across."""
    g = PoseGraph()
    step = 2 * math.pi / n
    for k in range(n):
        g.add_pose(k, (math.cos(k * step) * 5, math.sin(k * step) * 5, k * step + math.pi / 2))
    chord = 2 * 5 * math.sin(step / 2)
    info = np.diag([400.0, 400.0, 2500.0])
    for k in range(n - 1):
        g.add_edge(k, k + 1, (chord, 0.02, step), info, "odometry")
    g.add_edge(n - 1, 0, (chord, 0.0, step), info, "loop")
    g.add_edge(n // 4, 3 * n // 4, (0.0, 10.0, math.pi), info, "loop")
    return g


def test_a_wrong_loop_is_down_weighted_and_barely_moves_the_trajectory():
    clean = optimize_batch(_ring())
    g = _ring()
    g.add_edge(3, 15, (4.0, 3.0, 1.0), np.diag([400.0, 400.0, 2500.0]), "loop")  # wrong
    robust = optimize_batch(g)
    plain = optimize_batch(g, BatchParams(robust=False))
    assert np.all(robust.loop_weights[:2] == 1.0)
    assert robust.loop_weights[2] < 1e-3
    robust_err = np.max(np.linalg.norm(robust.poses[:, :2] - clean.poses[:, :2], axis=1))
    plain_err = np.max(np.linalg.norm(plain.poses[:, :2] - clean.poses[:, :2], axis=1))
    assert robust_err < 0.01 < plain_err


def test_fixed_vertex_stays_put():
    g = _straight_chain_with_loop(2.7)
    g.fix(2)
    r = optimize_batch(g)
    assert np.allclose(r.poses[2], g.pose(2), atol=1e-6)


def test_csail_isotropic_reaches_the_published_optimum(posegraph_file):
    # F* = 3.170e1 (SE-Sync, Table 1) is published to four digits, i.e. +-0.016 %; the true
    # optimum is 31.7037, which rounds to it.
    g = read_g2o(posegraph_file("CSAIL.g2o"))
    r = optimize_batch(g, BatchParams(noise="isotropic"))
    assert round(r.final_objective, 2) == 31.70
    assert abs(r.final_objective - 31.70) / 31.70 < 1.5e-4
    plain = optimize_batch(g, BatchParams(noise="isotropic", robust=False, initialisation="odometry"))
    assert r.final_objective == pytest.approx(plain.final_objective, rel=1e-8)
    assert r.initial_objective == pytest.approx(181208.56, rel=1e-6)
    assert np.all(r.loop_weights == 1.0)


def test_two_unlinked_components_are_each_anchored():
    g = _straight_chain_with_loop(2.7)
    g.add_pose(50, (10.0, 5.0, 1.0))
    g.add_pose(51, (11.0, 5.0, 1.0))
    g.add_edge(50, 51, (2.0, 0.0, 0.0), np.eye(3), "odometry")
    assert g.anchors() == [0, 50]
    r = optimize_batch(g)
    assert np.allclose(r.pose_of()[50], (10.0, 5.0, 1.0), atol=1e-6)
    assert np.allclose(r.pose_of()[51], (10.0 + 2 * math.cos(1.0), 5.0 + 2 * math.sin(1.0), 1.0), atol=1e-4)


def test_a_failing_lago_start_falls_back_to_odometry(monkeypatch, caplog):
    """GTSAM's LAGO can raise (it did once on a short demo: "underconstrained
    variables"); the solve then starts from the odometry poses and still converges."""
    import robotd.graph.batch as batch

    def broken(graph):
        raise RuntimeError("underconstrained variables")

    monkeypatch.setattr(batch, "lago_initialise", broken)
    g = _straight_chain_with_loop(0.3)
    r = optimize_batch(g, BatchParams(initialisation="lago", robust=False))
    assert r.start_objective == pytest.approx(r.initial_objective)  # started from odometry
    monkeypatch.undo()
    direct = optimize_batch(g, BatchParams(initialisation="odometry", robust=False))
    assert r.final_objective == pytest.approx(direct.final_objective, rel=1e-6)
    assert r.final_objective < 0.2 * r.initial_objective
    assert "LAGO initialisation failed" in caplog.text


def _laps_with_wrong_loops(seed: int = 1) -> PoseGraph:
    """Three laps of a 40-pose ring (drifting odometry start), a true loop each time a lap
    passes a pose of the lap before, and 40 wrong loops between random poses that claim the
    same confidence as the true ones."""
    rng = np.random.default_rng(seed)
    n, laps = 40, 3
    step = 2 * math.pi / n
    truth = [(5 * math.cos(k * step), 5 * math.sin(k * step), k * step + math.pi / 2) for k in range(n * laps)]
    g = PoseGraph()
    est = np.array(truth[0], float)
    d = 2 * 5 * math.sin(step / 2)
    for k in range(n * laps):
        g.add_pose(k, est)
        est = est + np.array([d * math.cos(est[2] + step / 2), d * math.sin(est[2] + step / 2), step + 0.004])
    info = np.diag([400.0, 400.0, 2500.0])
    for k in range(n * laps - 1):
        g.add_edge(k, k + 1, (d * math.cos(step / 2), d * math.sin(step / 2), step), info, "odometry")
    for k in range(n, n * laps, 4):
        g.add_edge(k - n, k, (0.0, 0.0, 0.0), info, "loop")
    for _ in range(40):
        a, b = rng.choice(n * laps, 2, replace=False)
        g.add_edge(int(a), int(b), (rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-math.pi, math.pi)),
                   info, "loop")
    return g


def test_auto_keeps_the_start_whose_robust_solve_costs_less():
    import gtsam

    from robotd.graph.factors import factor_graph, robust_kernel, to_values

    # Seed 3: the wrong loops bend LAGO's orientations enough that DCS from LAGO gives up
    # six true loops too (46 down-weighted, robust cost 2118); from odometry it keeps them (40, 1795).
    g = _laps_with_wrong_loops(3)
    params = BatchParams(kernel="dcs")
    kernel = robust_kernel(params.kernel, params.kernel_width)
    factors = factor_graph(g, kernel)

    def robust_cost(r):
        return factors.error(to_values(r.ids, r.poses))

    lago = optimize_batch(g, BatchParams(initialisation="lago", kernel="dcs"))
    odo = optimize_batch(g, BatchParams(initialisation="odometry", kernel="dcs"))
    auto = optimize_batch(g, params)
    assert isinstance(factors, gtsam.NonlinearFactorGraph)
    assert lago.start == "lago" and odo.start == "odometry"
    # Something is down-weighted from LAGO (the wrong loops), so auto tries both starts.
    assert (lago.loop_weights < 0.5).any()
    best = lago if robust_cost(lago) <= robust_cost(odo) else odo
    assert best is odo and robust_cost(odo) < 0.9 * robust_cost(lago)
    assert auto.start == "odometry"
    assert np.allclose(auto.poses, best.poses)
    assert robust_cost(auto) <= min(robust_cost(lago), robust_cost(odo)) + 1e-9


def test_auto_solves_once_when_nothing_is_down_weighted():
    g = _straight_chain_with_loop(2.7)
    r = optimize_batch(g)
    assert r.start == "lago"
    assert np.allclose(r.loop_weights, 1.0)


@pytest.mark.parametrize("seed", [3, 4])
def test_gnc_ends_at_the_least_squares_optimum_over_the_true_loops_alone(seed):
    # The laps graph with 40 wrong loops: GNC (truncated least squares) must reject exactly
    # the wrong ones and end where plain least squares ends on the graph without them;
    # DCS alone leaves their pull in the result (down-weighted, not removed).
    g = _laps_with_wrong_loops(seed)
    clean = PoseGraph()
    for k, p in zip(g.ids, g.poses()):
        clean.add_pose(int(k), p)
    n_true = sum(e.kind == "loop" for e in g.edges) - 40  # the wrong loops come last
    loops = 0
    for e in g.edges:
        loops += e.kind == "loop"
        if loops <= n_true:
            clean.add_edge(e.from_id, e.to_id, e.delta, e.information, e.kind)
    reference = optimize_batch(clean, BatchParams(robust=False))
    gnc = optimize_batch(g)
    dcs = optimize_batch(g, BatchParams(kernel="dcs"))
    assert gnc.gnc_time_s > 0.0
    assert np.all(gnc.loop_weights[:n_true] > 0.99) and np.all(gnc.loop_weights[n_true:] < 0.01)
    def err(r):
        d = r.poses - reference.poses
        d[:, 2] = np.remainder(d[:, 2] + math.pi, 2 * math.pi) - math.pi
        return np.abs(d).max()

    err_gnc, err_dcs = err(gnc), err(dcs)
    assert err_gnc < 1e-5
    assert err_dcs > 10 * err_gnc


def test_innovation_chi2_is_the_rise_of_the_least_squares_cost_when_the_edge_comes_in():
    # The straight chain is linear: without its loop the optimum is the odometry (cost 0)
    # and the loop is 0.3 m off (chi2 4 * 0.09 = 0.36); three odometry edges of variance
    # 1/4 each and the loop's own 1/4 give the innovation 0.09 / 1 = 0.09, the cost of the
    # optimum with the loop (test above: 4 edges * 4 * 0.075^2).
    from robotd.graph.batch import _LoopSolver, innovation_chi2
    from robotd.graph.factors import to_values

    g = _straight_chain_with_loop(2.7)
    sol = _LoopSolver(g, BatchParams())
    values, fg = sol.solve(np.zeros(1), to_values(g.ids, g.poses()))
    assert innovation_chi2(fg, values, sol.loops) == pytest.approx([0.09], rel=1e-6)
    # The ring: the closing loop's own chi2 on the open ring is far beyond the rise it
    # brings (the ring is loose between its ends); the rise, to first order.
    g = _ring()
    sol = _LoopSolver(g, BatchParams())
    values, fg = sol.solve(np.array([0.0, 1.0]), to_values(g.ids, g.poses()))
    open_cost = 2 * fg.error(values)
    closed, fg2 = sol.solve(np.ones(2), values)
    rise = 2 * fg2.error(closed) - open_cost
    innovation = innovation_chi2(fg, values, sol.loops[:1])[0]
    assert innovation == pytest.approx(rise, rel=0.05)
    assert _loop_chi2_at(sol, values)[0] > 30 * innovation


def _loop_chi2_at(sol, values):
    from robotd.graph.factors import from_values

    return sol.loop_chi2(from_values(values, sol.ids))


def test_gnc_takes_back_a_true_loop_whose_own_chi2_is_beyond_the_threshold_but_its_innovation_is_not():
    # The ring's closing loop left out: on the open ring its chi2 is 457, beyond the
    # threshold (30), so keeping "the loops within the threshold" never brings it back;
    # its innovation (11) says it would lower the truncated cost, and it does.
    from robotd.graph.batch import _LoopSolver
    from robotd.graph.factors import from_values, to_values

    g = _ring()
    sol = _LoopSolver(g, BatchParams())
    w = np.array([0.0, 1.0])
    values, _ = sol.solve(w, to_values(g.ids, g.poses()))
    poses = from_values(values, g.ids)
    start = (values, poses, w, sol.loop_chi2(poses))
    assert start[3][0] > sol.c
    stuck = sol.descent(start)
    assert np.array_equal(stuck[2], w)
    back = sol.local_search(start)
    assert np.array_equal(back[2], [1.0, 1.0])
    assert sol.tls_cost(back[1]) < sol.tls_cost(poses) - 10.0
    # and the result is the ring's least-squares optimum with both loops
    full = optimize_batch(g, BatchParams(robust=False))
    assert np.abs(back[1][:, :2] - full.poses[:, :2]).max() < 1e-4


def test_gnc_drops_a_kept_loop_whose_own_chi2_is_within_the_threshold_but_its_leave_one_out_is_not():
    # The straight chain's loop measuring -3 m (6 m off): in the least-squares optimum with
    # it each of the four edges takes a quarter of the 6 m, so its own chi2 is
    # 4 * 1.5^2 = 9, within the threshold (30), and keeping "the loops within the
    # threshold" keeps it; its leave-one-out chi2 is 36 (the whole cost it causes), and
    # without it the truncated cost is 30 instead of 36.
    from robotd.graph.batch import _LoopSolver, leave_one_out_chi2
    from robotd.graph.factors import from_values, to_values

    g = PoseGraph()
    for k in range(4):
        g.add_pose(k, (1.3 * k, 0.2 * k, 0.0))
    stiff = np.diag([4.0, 4.0, 1e8])  # headings held: the problem stays linear
    for k in range(3):
        g.add_edge(k, k + 1, (1.0, 0.0, 0.0), stiff, "odometry")
    g.add_edge(0, 3, (-3.0, 0.0, 0.0), stiff, "loop")
    sol = _LoopSolver(g, BatchParams())
    w = np.ones(1)
    values, fg = sol.solve(w, to_values(g.ids, g.poses()))
    poses = from_values(values, g.ids)
    assert sol.loop_chi2(poses) == pytest.approx([9.0], rel=1e-6)
    assert leave_one_out_chi2(fg, values, sol.loops) == pytest.approx([36.0], rel=1e-6)
    start = (values, poses, w, sol.loop_chi2(poses))
    assert np.array_equal(sol.descent(start)[2], w)
    out = sol.local_search(start)
    assert np.array_equal(out[2], [0.0])
    assert sol.tls_cost(out[1]) == pytest.approx(30.0, abs=1e-6)
    assert np.allclose(out[1][:, 0], [0.0, 1.0, 2.0, 3.0], atol=1e-6)

