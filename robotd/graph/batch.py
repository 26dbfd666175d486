"""Batch optimisation: LAGO initialisation, a robust Levenberg-Marquardt refinement, then
graduated non-convexity.

LAGO (Carlone et al., ICRA 2014) solves orientations linearly and then positions, giving a
guess near the optimum without iterating from odometry. The refinement is GTSAM's
Levenberg-Marquardt with odometry edges as plain Gaussians and loop edges under a robust
kernel, Dynamic Covariance Scaling (Agarwal et al., ICRA 2013): a loop edge whose chi2
exceeds ``kernel_width`` is scaled by ``s = 2 Phi / (Phi + chi2)``, so a wrong loop loses
most of its pull while a right one keeps full weight. By default (``kernel="gnc"``) that
solution is then the start of graduated non-convexity with the truncated least squares
loss (Yang et al., RA-L 2020; :func:`refine_gnc`), odometry edges known inliers, and a
local search on that loss one loop at a time by each loop's innovation and leave-one-out
chi2 (:meth:`_LoopSolver.local_search`); it ends at the least-squares optimum over the
odometry and the loops it keeps: a wrong loop has no pull left at all. DCS alone left
manhattan with 1000 wrong loops 0.026 m (APE aligned) from the outlier-free optimum; with
GNC see docs/benchmarks/posegraph.md (target: within 1 mm, in at most 10 times plain LM's
time).

Where DCS starts matters, and no one start is right for every graph, so by default
(``initialisation="auto"``) it starts from LAGO and, when that solve leaves some loop
down-weighted, once more from the odometry poses; the solution with the lower *robust*
cost wins. LAGO is not robust itself: wrong loops bend its linear orientation estimate.
Measured (bench/bench_posegraph.py, wrong loops carrying a true loop's information): on
manhattan with 1000 wrong loops DCS from LAGO ended 1.1 m (APE aligned) from the outlier-free
optimum with 96 of 1954 true loops down-weighted, from odometry 0.026 m with 4; on the
clean CSAIL and manhattan graphs with full information it is the other way round (from
odometry DCS stops in a local minimum at 144x and 9.7x LAGO's objective).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import Literal

import gtsam
import numpy as np

from robotd.base.geometry import compose, inverse
from robotd.graph.factors import (RobustKernel, anchor_factor, between_factor, factor_graph, from_values,
                                  robust_kernel, to_values)
from robotd.graph.model import Edge, PoseGraph, chi2, edge_chi2, isotropic_graph, isotropic_objective


log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class BatchParams:
    """Parameters of :func:`optimize_batch`.

    noise: "full" uses each edge's information matrix and scores with :func:`chi2`;
        "isotropic" uses SE-Sync's isotropic model and scores with the SE-Sync objective.
    initialisation: "auto" (default: LAGO, and also the odometry when the robust solve
        from LAGO down-weights some loop; the lower robust cost wins), "lago" or
        "odometry" (the graph's own poses); a graph of several connected components (say,
        two runs never linked) starts from odometry.
    robust: treat loop edges as possibly wrong (default True); False is plain least squares.
    kernel: "gnc" (default): graduated non-convexity with the truncated least squares loss
        (GTSAM's ``GncLMOptimizer``; Yang et al., RA-L 2020), odometry edges and anchors
        known inliers, started from the DCS solution below; "dcs" or "cauchy": that
        M-estimator on the loop edges under Levenberg-Marquardt, and nothing more.
    kernel_width: edge chi2 up to which a loop keeps full weight (DCS Phi), default 30:
        on manhattan with 1000 wrong loops, Phi = 10 also down-weighted 23-36 true loops
        (the largest true-loop chi2 at the optimum is 26 isotropic) and Phi = 100 kept wrong
        ones (18 m APE aligned with full information); 30 did neither.
    inlier_chi2: GNC's inlier threshold on a loop edge's chi2 (``e^T I e``; GTSAM's
        ``barcSq`` is half of it), default 30 for the same reason.
    max_iterations: Levenberg-Marquardt iterations, default 100.
    relative_tolerance: stop when the cost falls by less than this fraction, default 1e-5.
    """

    noise: Literal["full", "isotropic"] = "full"
    initialisation: Literal["auto", "lago", "odometry"] = "auto"
    robust: bool = True
    kernel: Literal["gnc", "dcs", "cauchy"] = "gnc"
    kernel_width: float = 30.0
    inlier_chi2: float = 30.0
    max_iterations: int = 100
    relative_tolerance: float = 1e-5

    def loop_kernel(self) -> RobustKernel | None:
        """The M-estimator on loop edges in Levenberg-Marquardt and iSAM2 (None when not
        robust): DCS for "gnc" (its start, and iSAM2 between full solves)."""
        if not self.robust:
            return None
        return robust_kernel("dcs" if self.kernel == "gnc" else self.kernel, self.kernel_width)


@dataclass(frozen=True, slots=True, eq=False)
class BatchResult:
    """What :func:`optimize_batch` found.

    ids: ``(N,) int64`` vertex ids; poses: ``(N, 3)`` optimised ``(x_m, y_m, yaw_rad)``.
    initial_objective: at the graph's own poses; start_objective: at the optimiser's start
    (after LAGO, or equal to initial); final_objective: at the result. All are the plain
    (non-robust) objective over every edge of the chosen noise model.
    iterations: Levenberg-Marquardt iterations (of the solve kept); time_s: wall time of
    initialisation plus refinement (every start tried); init_time_s: of LAGO alone.
    start: which start the result came from, "lago" or "odometry".
    loop_weights: ``(L,)`` the kernel's weight in [0, 1] of each loop edge at the result, in
    the order of the graph's loop edges (1 everywhere when not robust): a weight well below
    1 means "down-weighted by the optimiser". With GNC the weights are its own, 0 or 1 at
    convergence (truncated least squares: a loop is in or out).
    gnc_time_s: wall time of the GNC stage alone (0 without it).
    """

    ids: np.ndarray
    poses: np.ndarray
    initial_objective: float
    start_objective: float
    final_objective: float
    iterations: int
    time_s: float
    init_time_s: float
    loop_weights: np.ndarray
    start: str = "odometry"
    gnc_time_s: float = 0.0

    def pose_of(self) -> dict[int, np.ndarray]:
        """The poses keyed by vertex id."""
        return {int(k): p for k, p in zip(self.ids, self.poses)}


def objective(graph: PoseGraph, ids: np.ndarray, poses: np.ndarray,
              noise: Literal["full", "isotropic"]) -> float:
    """:func:`chi2` for "full", the SE-Sync objective for "isotropic"."""
    if noise == "isotropic":
        return isotropic_objective(graph, ids, poses)
    if noise == "full":
        return chi2(graph, ids, poses)
    raise ValueError(f"unknown noise model {noise!r} (full or isotropic)")


def lago_initialise(graph: PoseGraph) -> np.ndarray:
    """LAGO poses ``(N, 3)`` in :attr:`PoseGraph.ids` order.

    GTSAM's LAGO wants diagonal noise (each edge enters with ``1 / sqrt(diag(I))``), and its
    odometric spanning tree wants keys 0..N-1 anchored at 0, so the vertices are renumbered
    by rank with a prior on the smallest id; where the chain has gaps LAGO falls back to a
    minimum spanning tree. The result is moved rigidly so that the first anchor (fixed vertex)
    sits at its own pose.
    """
    ids = graph.ids
    if len(ids) == 0:
        return np.zeros((0, 3))
    rank = {int(k): n for n, k in enumerate(ids)}
    fg = gtsam.NonlinearFactorGraph()
    for e in graph.edges:
        fg.add(between_factor(dataclasses.replace(e, from_id=rank[e.from_id], to_id=rank[e.to_id]),
                              diagonal=True))
    fg.add(anchor_factor(0, graph.pose(int(ids[0]))))
    try:
        values = gtsam.lago.initialize(fg, True)
    except IndexError:  # no odometry edge between some id-adjacent vertices
        values = gtsam.lago.initialize(fg, False)
    poses = from_values(values, np.arange(len(ids)))
    anchor = graph.anchors()[0]
    shift = compose(graph.pose(anchor), inverse(poses[rank[anchor]]))
    return compose(shift, poses)


def loop_weights(graph: PoseGraph, ids: np.ndarray, poses: np.ndarray,
                 kernel: RobustKernel | None) -> np.ndarray:
    """Each loop edge's kernel weight at ``poses`` (``(L,)``, 1 without a kernel)."""
    is_loop = graph.is_loop
    if kernel is None or not is_loop.any():
        return np.ones(int(is_loop.sum()))
    c2 = edge_chi2(graph, ids, poses)[is_loop]
    return np.array([kernel.weight(math.sqrt(max(c, 0.0))) for c in c2])


def optimize_batch(graph: PoseGraph, params: BatchParams = BatchParams()) -> BatchResult:
    """Optimise ``graph``: LAGO (or odometry) start, robust Levenberg-Marquardt, then GNC.

    Fixed vertices (or, without any, the smallest id) are held at their poses. The graph
    is not modified.
    """
    ids = graph.ids
    work = isotropic_graph(graph) if params.noise == "isotropic" else graph
    initial = work.poses()
    t0 = time.perf_counter()
    # Without a loop the odometry chain is already the optimum: nothing for LAGO to do (and
    # GTSAM's LAGO can fail on a bare chain, "indeterminate linear system").
    has_loop = work.loop_count > 0
    use_lago = params.initialisation in ("auto", "lago") and has_loop and len(work.components()) == 1
    starts = [("odometry", initial)]
    if use_lago:
        try:
            starts = [("lago", lago_initialise(work))]
            if params.initialisation == "auto" and params.robust:
                starts.append(("odometry", initial))
        except RuntimeError as exc:  # GTSAM: e.g. an orientation LAGO cannot determine
            log.warning("LAGO initialisation failed (%s); starting from the odometry poses",
                        str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__)
    t1 = time.perf_counter()
    kernel = params.loop_kernel()
    factors = factor_graph(work, kernel)
    best: tuple[float, str, np.ndarray, np.ndarray, int, np.ndarray] | None = None
    for name, start in starts:
        values, iterations = _refine(factors, ids, start, params)
        cost = factors.error(values)
        poses = from_values(values, ids)
        weights = loop_weights(work, ids, poses, kernel)
        if best is None or cost < best[0]:
            best = (cost, name, start, poses, iterations, weights)
        if not (weights < 0.5).any():  # nothing down-weighted: no other start is needed
            break
    assert best is not None  # starts is never empty
    _cost, name, start, poses, iterations, weights = best
    t_gnc = time.perf_counter()
    gnc = params.robust and params.kernel == "gnc" and len(weights) > 0
    if gnc:
        poses, weights = refine_gnc(work, poses, params)
    t2 = time.perf_counter()
    return BatchResult(
        ids=ids, poses=poses,
        initial_objective=objective(graph, ids, initial, params.noise),
        start_objective=objective(graph, ids, start, params.noise),
        final_objective=objective(graph, ids, poses, params.noise),
        iterations=iterations, time_s=t2 - t0, init_time_s=t1 - t0,
        loop_weights=weights, start=name, gnc_time_s=t2 - t_gnc if gnc else 0.0,
    )


def _refine(factors: gtsam.NonlinearFactorGraph, ids: np.ndarray, start: np.ndarray,
            params: BatchParams) -> tuple[gtsam.Values, int]:
    """Levenberg-Marquardt on ``factors`` from ``start``: the values and the iterations."""
    lm_params = gtsam.LevenbergMarquardtParams()
    lm_params.setMaxIterations(params.max_iterations)
    lm_params.setRelativeErrorTol(params.relative_tolerance)
    optimizer = gtsam.LevenbergMarquardtOptimizer(factors, to_values(ids, start), lm_params)
    values = optimizer.optimize()
    return values, int(optimizer.iterations())


def tls_weights(chi2_values: np.ndarray, mu: float, inlier_chi2: float) -> np.ndarray:
    """Graduated non-convexity's weights for the truncated least squares loss (Yang et al.,
    RA-L 2020, eq. 14) of residuals with edge chi2 ``chi2_values`` ``(L,)``, at control
    parameter ``mu`` (small: nearly convex; large: the TLS loss itself), threshold
    ``inlier_chi2``: 1 below ``mu / (mu + 1)`` of the threshold, 0 above ``(mu + 1) / mu``
    of it, ``sqrt(c mu (mu + 1) / r) - mu`` between (``c`` the threshold, ``r`` the chi2)."""
    c = float(inlier_chi2)
    r = np.maximum(np.asarray(chi2_values, float), 1e-300)
    w = np.sqrt(c * mu * (mu + 1.0) / r) - mu
    w = np.where(r <= c * mu / (mu + 1.0), 1.0, w)
    w = np.where(r >= c * (mu + 1.0) / mu, 0.0, w)
    return np.clip(w, 0.0, 1.0)


def refine_gnc(graph: PoseGraph, start: np.ndarray, params: BatchParams) -> tuple[np.ndarray, np.ndarray]:
    """Graduated non-convexity with the truncated least squares loss from ``start``
    ``(N, 3)``: the poses ``(N, 3)`` and each loop edge's weight ``(L,)``.

    Odometry edges and anchors are known inliers; a loop edge is an inlier while its chi2
    stays within ``params.inlier_chi2``. The algorithm is GTSAM's ``GncLMOptimizer`` with
    TLS and the linear schedule (weights :func:`tls_weights`, ``mu`` from Remark 5 of the
    paper, times 1.4 per step, stop when the weights are binary or the weighted cost stops
    falling), with one difference that makes it fast: each inner Levenberg-Marquardt solve
    starts from the previous one's result, as in the paper's Algorithm 1, where GTSAM's
    restarts from the initial values every time. On manhattan with 1000 wrong loops GTSAM's
    own had not finished after 4 times plain LM's time from the odometry, nor after 7 from
    the DCS solution (see docs/benchmarks/posegraph.md for this one's). The schedule and
    the descents look at each loop's own chi2 at the solution; the end is a local search
    by what a loop would do to the cost if it came in or went out
    (:meth:`_LoopSolver.local_search`). At convergence the weights are 0 or 1 and the
    result is the least-squares optimum over the odometry and the loops kept.
    """
    ids = graph.ids
    sol = _LoopSolver(graph, params)
    c = sol.c
    # Start: the loops beyond the threshold at ``start`` left out (GTSAM's first solve
    # would weigh every loop fully: plain least squares, as slow and as far off as plain LM).
    weights = (sol.loop_chi2(start) <= c).astype(float)
    values, fg = sol.solve(weights, to_values(ids, start))
    poses = from_values(values, ids)
    r = sol.loop_chi2(poses)
    r_max = float(r.max()) if len(r) else 0.0
    if r_max <= c:  # every loop within the threshold: TLS is least squares
        return poses, np.ones(len(sol.loops))
    # Candidate A: truncated least squares descent straight from there (the loops the
    # start puts within the threshold, re-solved until the set stops changing). Where the
    # start is already good (DCS from the odometry on manhattan with 1000 wrong loops) this
    # keeps its right loops; the graduated schedule below (candidate B) can lose a cluster
    # of right loops on the way (there: 11, a corner of the map misplaced, 13 mm APE aligned). Where
    # the start is poor (DCS on CSAIL with 100 wrong loops, 3.5 m APE aligned) the schedule finds
    # what descent cannot. The lower truncated cost wins.
    cand_a = sol.descent((values, poses, weights, r))
    mu = max(c / (2.0 * r_max - c), 1e-6)
    prev_cost = fg.error(values)
    for _ in range(params.max_iterations):
        weights = tls_weights(r, mu, c)
        values, fg = sol.solve(weights, values)
        poses = from_values(values, ids)
        r = sol.loop_chi2(poses)
        cost = fg.error(values)
        binary = bool(np.all(np.minimum(weights, 1.0 - weights) < 1e-4))
        if binary or abs(cost - prev_cost) < 1e-5 * max(prev_cost, 1e-7):
            break
        prev_cost = cost
        mu *= 1.4
    # Truncated least squares itself from there: keep exactly the loops within the threshold
    # at the current solution, re-solve, until that set stops changing (each step lowers
    # the TLS cost). The schedule's last weights were set at the solution before the last
    # one, so a loop may sit just beyond or within the threshold of the final one.
    cand_b = sol.descent((values, poses, weights, r))
    cost_a, cost_b = sol.tls_cost(cand_a[1]), sol.tls_cost(cand_b[1])
    log.debug("GNC: truncated cost %.6g by descent from the start, %.6g after the schedule", cost_a, cost_b)
    best = sol.local_search(cand_a if cost_a < cost_b else cand_b)
    return best[1], best[2]


#: A solution of :class:`_LoopSolver`: GTSAM values, poses ``(N, 3)``, loop weights ``(L,)``
#: and loop chi2 ``(L,)``.
_Solution = tuple[gtsam.Values, np.ndarray, np.ndarray, np.ndarray]


class _LoopSolver:
    """Least squares over a graph's odometry edges and anchors (known inliers) and its loop
    edges, each loop weighted (0: left out); the truncated least squares steps of
    :func:`refine_gnc` on top."""

    def __init__(self, graph: PoseGraph, params: BatchParams) -> None:
        self.graph, self.ids = graph, graph.ids
        self.is_loop = graph.is_loop
        self.loops = [e for e in graph.edges if e.kind == "loop"]
        self.fixed = gtsam.NonlinearFactorGraph()
        for e in graph.edges:
            if e.kind != "loop":
                self.fixed.add(between_factor(e))
        for kid in graph.anchors():
            self.fixed.add(anchor_factor(kid, graph.pose(kid)))
        self.c = float(params.inlier_chi2)
        self.max_steps = params.max_iterations
        self.lm_params = gtsam.LevenbergMarquardtParams()
        self.lm_params.setMaxIterations(params.max_iterations)
        self.lm_params.setRelativeErrorTol(params.relative_tolerance)

    def build(self, weights: np.ndarray) -> gtsam.NonlinearFactorGraph:
        """The factor graph with each loop's information times its weight (0: left out)."""
        fg = gtsam.NonlinearFactorGraph(self.fixed)
        for e, w in zip(self.loops, weights):
            if w > 0.0:
                d = e.delta
                fg.add(gtsam.BetweenFactorPose2(
                    e.from_id, e.to_id, gtsam.Pose2(d[0], d[1], d[2]),
                    gtsam.noiseModel.Gaussian.Information(float(w) * np.asarray(e.information))))
        return fg

    def solve(self, weights: np.ndarray, values: gtsam.Values) -> tuple[gtsam.Values, gtsam.NonlinearFactorGraph]:
        """Levenberg-Marquardt from ``values`` on :meth:`build`'s graph: values and graph."""
        fg = self.build(weights)
        return gtsam.LevenbergMarquardtOptimizer(fg, values, self.lm_params).optimize(), fg

    def loop_chi2(self, poses: np.ndarray) -> np.ndarray:
        """Each loop edge's chi2 at ``poses`` ``(L,)``."""
        return edge_chi2(self.graph, self.ids, poses)[self.is_loop]

    def tls_cost(self, poses: np.ndarray) -> float:
        """The truncated least squares objective: every non-loop edge's chi2 plus each
        loop's chi2 capped at the threshold."""
        e = edge_chi2(self.graph, self.ids, poses)
        return float(e[~self.is_loop].sum() + np.minimum(e[self.is_loop], self.c).sum())

    def descent(self, sol: _Solution) -> _Solution:
        """Keep exactly the loops within the threshold at the current solution and re-solve,
        until the kept set stops changing."""
        values, poses, weights, r = sol
        for _ in range(self.max_steps):
            keep = (r <= self.c).astype(float)
            if np.array_equal(keep, weights):
                break
            weights = keep
            values, _fg = self.solve(weights, values)
            poses = from_values(values, self.ids)
            r = self.loop_chi2(poses)
        return values, poses, weights, r

    def local_search(self, best: _Solution, max_tries: int = 10) -> _Solution:
        """Truncated least squares descent one loop at a time, by what each loop would do
        to the least-squares part: a loop left out whose *innovation* chi2
        (:func:`innovation_chi2`) is within the threshold lowers the truncated cost if it
        comes back in (to first order the least-squares part rises by its innovation and
        the truncated part falls by the threshold), and a loop kept whose *leave-one-out*
        chi2 (:func:`leave_one_out_chi2`) is beyond it lowers the cost if it goes. Both can
        hold where the loop's own chi2 at the solution says the opposite, which is all
        :meth:`descent` looks at: a true loop whose poses the other loops tie only
        loosely, from which the solution moved away once it was out (manhattan with 1000
        wrong loops: four true loops beyond the threshold, their innovation within it); a
        kept loop that bends the solution towards itself. Each round tries the loops that
        qualify all together, then one by one (at most ``max_tries`` of each kind, most
        promising first), and keeps the first try whose truncated cost after re-solving
        and descending again is lower."""
        cost = self.tls_cost(best[1])
        for _ in range(self.max_steps):
            values, _poses, weights, _r = best
            fg = self.build(weights)
            out, kept = np.flatnonzero(weights < 0.5), np.flatnonzero(weights >= 0.5)
            try:
                marginals = gtsam.Marginals(fg, values)
            except RuntimeError as exc:  # e.g. a run tied to the rest by loops all left out
                log.debug("GNC: no local search (%s)", str(exc).strip().splitlines()[0] if str(exc).strip() else exc)
                break
            inn = _edge_statistic(marginals, values, [self.loops[n] for n in out], +1.0)
            loo = _edge_statistic(marginals, values, [self.loops[n] for n in kept], -1.0)
            back = out[np.argsort(inn)][:int((inn <= self.c).sum())]
            drop = kept[np.argsort(-loo)][:int((loo > self.c).sum())]
            tries: list[tuple[np.ndarray, float]] = []
            for group, w_to in ((back, 1.0), (drop, 0.0)):
                if len(group):
                    tries.append((group, w_to))
                    if len(group) > 1:
                        tries += [(group[n:n + 1], w_to) for n in range(min(len(group), max_tries))]
            improved = False
            for group, w_to in tries:
                w = weights.copy()
                w[group] = w_to
                v2, _fg = self.solve(w, values)
                p2 = from_values(v2, self.ids)
                cand = self.descent((v2, p2, w, self.loop_chi2(p2)))
                cost2 = self.tls_cost(cand[1])
                if cost2 < cost - 1e-9 * max(abs(cost), 1.0):
                    log.debug("GNC: %d loop(s) %s, truncated cost %.6g -> %.6g", len(group),
                              "back in" if w_to else "out", cost, cost2)
                    best, cost, improved = cand, cost2, True
                    break
            if not improved:
                break
        return best


def innovation_chi2(fg: gtsam.NonlinearFactorGraph, values: gtsam.Values, edges: list[Edge]) -> np.ndarray:
    """Each edge's innovation chi2 against the least-squares solution ``values`` of ``fg``
    (which lacks the edges), ``(len(edges),)``: ``e^T (Sigma + H P H^T)^-1 e``, ``e`` the
    edge's error, ``Sigma`` its covariance, ``H`` its Jacobian and ``P`` the joint marginal
    covariance of its two poses. To first order this is how much the least-squares cost
    ``sum e^T I e`` rises when the edge is added and the graph re-solved: never more than
    the edge's own chi2 at ``values``, much less where the solution ties its poses loosely."""
    if not edges:
        return np.zeros(0)
    return _edge_statistic(gtsam.Marginals(fg, values), values, edges, +1.0)


def leave_one_out_chi2(fg: gtsam.NonlinearFactorGraph, values: gtsam.Values, edges: list[Edge]) -> np.ndarray:
    """Each edge's leave-one-out chi2 at the least-squares solution ``values`` of ``fg``
    (which holds the edges), ``(len(edges),)``: ``e^T (Sigma - H P H^T)^-1 e`` (as in
    :func:`innovation_chi2`, ``P`` now with the edge in): to first order how much the
    least-squares cost falls when the edge is removed and the graph re-solved, never less
    than its own chi2 at ``values``."""
    if not edges:
        return np.zeros(0)
    return _edge_statistic(gtsam.Marginals(fg, values), values, edges, -1.0)


def _edge_statistic(marginals: gtsam.Marginals, values: gtsam.Values, edges: list[Edge],
                    sign: float) -> np.ndarray:
    """``e^T (Sigma + sign H P H^T)^-1 e`` of each edge (see :func:`innovation_chi2`)."""
    out = np.empty(len(edges))
    unit = gtsam.noiseModel.Unit.Create(3)
    for n, e in enumerate(edges):
        d = e.delta
        a, b = gtsam.BetweenFactorPose2(e.from_id, e.to_id, gtsam.Pose2(d[0], d[1], d[2]),
                                        unit).linearize(values).jacobian()
        joint = marginals.jointMarginalCovariance(gtsam.KeyVector([e.from_id, e.to_id]))
        p = np.block([[joint.at(e.from_id, e.from_id), joint.at(e.from_id, e.to_id)],
                      [joint.at(e.to_id, e.from_id), joint.at(e.to_id, e.to_id)]])
        s = np.linalg.inv(np.asarray(e.information, float)) + sign * (a @ p @ a.T)
        r = -np.asarray(b, float)
        # lstsq: with the edge in, Sigma - H P H^T may be near singular (an edge that alone
        # ties its poses), where its error is near zero too.
        out[n] = float(r @ np.linalg.lstsq(s, r, rcond=1e-12)[0])
    return out
