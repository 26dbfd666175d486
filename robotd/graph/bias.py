"""Odometry edges that share the gyro bias: the bias as a variable of the pose graph.

The wheel + gyro filter's keyframe edges are not independent: the filter's bias error
``db = b_hat - b`` turns every edge's heading the same way until a standstill teaches the
filter the bias again, so a chain of independent edges is overconfident over long
horizons (``docs/benchmarks/nees.md``). Here each keyframe ``k`` gets a bias variable
``b_k`` (rad/s, a 1-vector, key :func:`bias_key`) and each odometry edge the factor

    e = Log(delta^-1 (+) x_i^-1 (+) x_j) + J (b_hat_i - b_i),     e ~ N(0, C_given_bias)

with ``J`` and ``C_given_bias`` from the filter's joint covariance of the edge and its
bias at the start (:class:`robotd.odometry.history.EdgeBiasTerms`): the edge's error
given the bias error is ``J db`` plus what the bias does not explain. Consecutive bias
variables are tied by the filter's own model of its bias error, an AR(1) sequence

    (b_j - b_hat_j) - a (b_i - b_hat_i) ~ N(0, P_j - a^2 P_i),    a = Cov(db_i, db_j) / P_i

(``a`` about 1 while driving, where the bias is a random walk the filter cannot see; near
0 over a standstill, where the filter learns it afresh), and the first one by the filter's
``N(b_hat_0, P_0)``. Marginalised over the bias variables, a chain of edges then has the
covariance the filter's joint covariance gives it (up to the speed and yaw-rate states'
share, which the edges keep inside ``C_given_bias``), and a loop that corrects a heading
also corrects the bias of the edges around it.

The factors are GTSAM ``CustomFactor`` s (their error and Jacobians in Python); the bias
chain's is linear. :func:`bias_factor_graph` builds a whole graph of them for the batch
solve and the benchmarks. Per edge they cost iSAM2 18-41 times its time per keyframe;
:func:`bias_window_factor` takes ``W`` consecutive edges (iSAM2's fold, 10) as one factor
with one bias variable at the window's start, the walk inside the window marginalised into
the window's joint noise (:func:`window_covariance`; over one window the end pose's
marginal is the per-edge model's exactly), and the window starts chained by
:func:`window_chain_edge`: about 3 times the time of independent edges. The daemon's graph
uses the windows with ``[pose_graph] odometry_model = "bias_window"``
(:class:`robotd.graph.incremental.IncrementalParams`: :class:`WindowChain` groups the live
edges, :func:`span_edge` and :func:`span_factors` keep them through iSAM2's fold), and
independent edges (:func:`robotd.graph.factors.between_factor`) by default: see
``docs/concepts.md``, "The bias windows in the daemon".
"""

from __future__ import annotations

from collections.abc import Sequence
import math
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from robotd.graph.factors import anchor_factor

__all__ = ["BIAS_VAR_FLOOR", "BiasEdge", "WindowChain", "bias_chain_factor", "bias_edge", "bias_edge_factor",
           "bias_factor_graph", "span_edge", "span_factors",
           "bias_initial_values", "bias_key", "bias_prior_factor", "bias_window_factor", "scale_jacobian",
           "scale_key", "scale_prior_factor", "window_chain_edge", "window_covariance"]

#: Smallest variance (rad/s)^2 of a bias-chain step: keeps a step the filter took as
#: exact (a = 1, no walk) factorable. (1e-7 rad/s)^2, far below any bias walk over a keyframe.
BIAS_VAR_FLOOR = 1e-14


def bias_key(keyframe_id: int) -> int:
    """The GTSAM key of keyframe ``keyframe_id``'s bias variable (symbol ``b``; the poses
    are keyed by their ids, far below)."""
    return int(gtsam.symbol("b", int(keyframe_id)))


@dataclass(frozen=True, slots=True)
class BiasEdge:
    """An odometry edge with its bias terms.

    from_id, to_id: the keyframes. delta: ``(3,)`` the edge (``to`` in ``from``'s frame).
    cov_given_bias: ``(3, 3)`` its covariance given the bias at ``from``. jac_bias: ``(3,)``
    the edge's error per rad/s of bias error at ``from`` (m, rad per rad/s). bias_radps,
    bias_var: the filter's bias estimate at ``from`` and its variance. bias_end_radps,
    bias_end_var: at ``to``. bias_cov: covariance of the two bias errors, (rad/s)^2.
    jac_scale: ``(3, 2)`` the edge's error per unit relative scale error of the wheels'
    distance and of the gyro (:func:`scale_jacobian`, through the edge's ``scale_gain``
    when it was combined with a visual step); None: the edge's own :func:`scale_jacobian`.
    """

    from_id: int
    to_id: int
    delta: np.ndarray
    cov_given_bias: np.ndarray
    jac_bias: np.ndarray
    bias_radps: float
    bias_var: float
    bias_end_radps: float
    bias_end_var: float
    bias_cov: float
    jac_scale: np.ndarray | None = None

    def scale_jac(self) -> np.ndarray:
        """``(3, 2)`` :attr:`jac_scale`, or the delta's own :func:`scale_jacobian`."""
        return scale_jacobian(self.delta) if self.jac_scale is None else np.asarray(self.jac_scale, float)

    def chain_step(self) -> tuple[float, float]:
        """``(a, var)`` of the AR(1) step from the bias error at ``from`` to ``to``."""
        a = self.bias_cov / self.bias_var
        return a, max(self.bias_end_var - a * a * self.bias_var, BIAS_VAR_FLOOR)


def scale_key(segment: int) -> int:
    """The GTSAM key of the scale variable ``(s_wheel, s_gyro)`` of ``segment`` (symbol ``s``)."""
    return int(gtsam.symbol("s", int(segment)))


def scale_jacobian(delta: np.ndarray) -> np.ndarray:
    """``(3, 2)`` an edge's error per unit relative scale error of the wheels' distance
    (first column) and of the gyro's rate (second), in the frame of the edge's end (as its
    covariance). A wheel scale error ``s`` stretches the translation by ``s``; a gyro scale
    error ``s`` turns the yaw by ``s dyaw`` and, the heading drifting through the edge, the
    translation by about ``s dyaw / 2`` sideways. The wheels' yaw rate, which the filter
    barely weighs while driving (:mod:`robotd.odometry.ekf`), is left out."""
    d = np.asarray(delta, float)
    c, s = math.cos(float(d[2])), math.sin(float(d[2]))
    rt = np.array([[c, s], [-s, c]])
    j = np.zeros((3, 2))
    j[:2, 0] = rt @ d[:2]
    j[:2, 1] = rt @ (0.5 * d[2] * np.array([-d[1], d[0]]))
    j[2, 1] = d[2]
    return j


def scale_prior_factor(segment: int, sigmas: tuple[float, float]) -> gtsam.PriorFactorVector:
    """Zero-mean prior ``(sigma_wheel, sigma_gyro)`` on a segment's scale errors (what the
    base is known to within: its tolerances uncalibrated, the calibration's uncertainty)."""
    return gtsam.PriorFactorVector(scale_key(segment), np.zeros(2),
                                   gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, float)))


def _pose(values: gtsam.Values, key: int) -> gtsam.Pose2:
    return values.atPose2(key)


def bias_edge_factor(edge: BiasEdge, segment: int | None = None) -> gtsam.CustomFactor:
    """The edge's factor on ``(x_from, x_to, b_from)`` (see the module doc), and on the
    scale variable of ``segment`` when given: ``+ J_s s`` (:func:`scale_jacobian`)."""
    d = np.asarray(edge.delta, float)
    j_s = edge.scale_jac()
    meas_inv = gtsam.Pose2(float(d[0]), float(d[1]), float(d[2])).inverse()
    jac = np.asarray(edge.jac_bias, float).reshape(3, 1)
    b_hat = float(edge.bias_radps)
    model = gtsam.noiseModel.Gaussian.Covariance(np.asarray(edge.cov_given_bias, float))
    ki, kj, kb = int(edge.from_id), int(edge.to_id), bias_key(edge.from_id)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[np.ndarray] | None) -> np.ndarray:
        xi, xj = _pose(values, ki), _pose(values, kj)
        h = xi.between(xj)
        err_pose = meas_inv.compose(h)
        e = gtsam.Pose2.Logmap(err_pose)
        b = float(values.atVector(kb)[0])
        out = e + jac[:, 0] * (b_hat - b)
        if segment is not None:
            out = out + j_s @ values.atVector(ks)
        if jacobians is not None:
            jr_inv = gtsam.Pose2.LogmapDerivative(e)
            jacobians[0] = -jr_inv @ h.inverse().AdjointMap()
            jacobians[1] = jr_inv
            jacobians[2] = -jac
            if segment is not None:
                jacobians[3] = j_s
        return out

    keys = [ki, kj, kb]
    if segment is not None:
        ks = scale_key(segment)
        keys.append(ks)
    return gtsam.CustomFactor(model, keys, error)


def bias_chain_factor(edge: BiasEdge) -> gtsam.CustomFactor:
    """The AR(1) factor between the bias variables at the edge's two keyframes."""
    a, var = edge.chain_step()
    ki, kj = bias_key(edge.from_id), bias_key(edge.to_id)
    bi_hat, bj_hat = float(edge.bias_radps), float(edge.bias_end_radps)
    model = gtsam.noiseModel.Isotropic.Sigma(1, float(np.sqrt(var)))
    ja, jb = np.array([[-a]]), np.array([[1.0]])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[np.ndarray] | None) -> np.ndarray:
        bi, bj = float(values.atVector(ki)[0]), float(values.atVector(kj)[0])
        if jacobians is not None:
            jacobians[0], jacobians[1] = ja, jb
        return np.array([(bj - bj_hat) - a * (bi - bi_hat)])

    return gtsam.CustomFactor(model, [ki, kj], error)


def bias_prior_factor(keyframe_id: int, bias_radps: float, bias_var: float) -> gtsam.PriorFactorVector:
    """The filter's belief ``N(bias_radps, bias_var)`` on one keyframe's bias (the first one's)."""
    return gtsam.PriorFactorVector(bias_key(keyframe_id), np.array([float(bias_radps)]),
                                   gtsam.noiseModel.Isotropic.Sigma(1, float(np.sqrt(bias_var))))


def bias_factor_graph(edges: Sequence[BiasEdge], anchor_pose: np.ndarray | None = None,
                      loops: gtsam.NonlinearFactorGraph | None = None,
                      scale_sigmas: tuple[float, float] | None = None) -> gtsam.NonlinearFactorGraph:
    """A chain of odometry edges (in order, each starting where the one before ended) as
    bias-sharing factors, the bias chain, the first bias's prior and the first pose's anchor
    (at ``anchor_pose``, default the origin); ``loops``: further factors (loop edges) added
    as they are. ``scale_sigmas``: one scale variable (segment 0) shared by every edge,
    with this prior (:func:`scale_prior_factor`); None: no scale variable."""
    fg = gtsam.NonlinearFactorGraph()
    if not edges:
        return fg
    first = edges[0]
    fg.add(anchor_factor(first.from_id, np.zeros(3) if anchor_pose is None else np.asarray(anchor_pose, float)))
    fg.add(bias_prior_factor(first.from_id, first.bias_radps, first.bias_var))
    segment = None if scale_sigmas is None else 0
    if scale_sigmas is not None:
        fg.add(scale_prior_factor(0, scale_sigmas))
    for e in edges:
        fg.add(bias_edge_factor(e, segment))
        fg.add(bias_chain_factor(e))
    if loops is not None:
        fg.push_back(loops)
    return fg


def bias_initial_values(edges: Sequence[BiasEdge], anchor_pose: np.ndarray | None = None,
                        scales: bool = False) -> gtsam.Values:
    """Initial values of :func:`bias_factor_graph`: the edges composed from the anchor, each
    bias at the filter's estimate (and the scale errors at zero, ``scales``)."""
    values = gtsam.Values()
    if not edges:
        return values
    if scales:
        values.insert(scale_key(0), np.zeros(2))
    p = gtsam.Pose2(*map(float, np.zeros(3) if anchor_pose is None else anchor_pose))
    values.insert(int(edges[0].from_id), p)
    values.insert(bias_key(edges[0].from_id), np.array([float(edges[0].bias_radps)]))
    for e in edges:
        p = p.compose(gtsam.Pose2(*map(float, e.delta)))
        values.insert(int(e.to_id), p)
        values.insert(bias_key(e.to_id), np.array([float(e.bias_end_radps)]))
    return values


# --------------------------------------------------------------------------------------
# A window of edges, one factor: the bias variable at the window's start only.
# --------------------------------------------------------------------------------------


def window_covariance(edges: Sequence[BiasEdge]) -> tuple[np.ndarray, np.ndarray]:
    """The stacked errors of ``W`` consecutive edges given the bias error ``db_0`` at the
    first one's start: ``(jac (3W,), cov (3W, 3W))`` with ``eps = jac db_0 + n``,
    ``n ~ N(0, cov)``. Edge ``k``'s bias error is ``db_k = alpha_k db_0 + nu_k`` (the AR(1)
    steps of :meth:`BiasEdge.chain_step`, ``alpha_k`` their product, ``nu_k`` the walk
    since the window's start), so ``jac_k = J_k alpha_k`` and ``cov`` is the edges' own
    ``C_given_bias`` on the diagonal blocks plus ``J_k Cov(nu_k, nu_l) J_l^T``."""
    w = len(edges)
    jac = np.zeros(3 * w)
    cov = np.zeros((3 * w, 3 * w))
    alpha = 1.0
    nu_var = np.zeros(w)  # Var(nu_k)
    for k, e in enumerate(edges):
        jk = np.asarray(e.jac_bias, float)
        jac[3 * k:3 * k + 3] = jk * alpha
        cov[3 * k:3 * k + 3, 3 * k:3 * k + 3] = np.asarray(e.cov_given_bias, float)
        a, var = e.chain_step()
        alpha *= a
        if k + 1 < w:
            nu_var[k + 1] = a * a * nu_var[k] + var
    # Cov(nu_k, nu_l) = (prod of a from k to l) Var(nu_k), k <= l
    for k in range(w):
        c = nu_var[k]
        jk = np.asarray(edges[k].jac_bias, float)
        for m in range(k, w):
            if c != 0.0:
                jm = np.asarray(edges[m].jac_bias, float)
                block = c * np.outer(jk, jm)
                cov[3 * k:3 * k + 3, 3 * m:3 * m + 3] += block
                if m != k:
                    cov[3 * m:3 * m + 3, 3 * k:3 * k + 3] += block.T
            c *= edges[m].chain_step()[0]
    return jac, 0.5 * (cov + cov.T)


def window_chain_edge(edges: Sequence[BiasEdge]) -> BiasEdge:
    """The window as one :class:`BiasEdge` for the bias chain between window starts
    (:func:`bias_chain_factor`): the AR(1) step over the whole window (the product of the
    edges' coefficients, the variance left at its end). The walk inside the window also
    enters the window's own errors (:func:`window_covariance`); that shared part is left
    out of the chain (it is below 1 % of an edge's bias variance while driving)."""
    first, last = edges[0], edges[-1]
    alpha = 1.0
    for e in edges:
        alpha *= e.chain_step()[0]
    return BiasEdge(first.from_id, last.to_id, np.zeros(3), np.eye(3), np.zeros(3), first.bias_radps,
                    first.bias_var, last.bias_end_radps, last.bias_end_var, alpha * first.bias_var)


def bias_window_factor(edges: Sequence[BiasEdge], segment: int | None = None) -> gtsam.CustomFactor:
    """One factor over ``W`` consecutive edges (keyframes ``x_0 .. x_W`` and the bias
    variable at ``x_0``): the edges' errors stacked, each ``Log(delta_k^-1 (+) x_{k-1}^-1
    (+) x_k)``, plus ``jac (b_hat_0 - b_0)``, with the joint noise of
    :func:`window_covariance`. What :func:`bias_edge_factor` and :func:`bias_chain_factor`
    give per edge, with one Python call (and one bias variable) per window instead of two
    calls per edge. ``segment``: the edges also share that segment's scale variable
    (``+ J_s s`` on each edge's error, :attr:`BiasEdge.jac_scale`)."""
    w = len(edges)
    jac, cov = window_covariance(edges)
    js = None if segment is None else np.vstack([e.scale_jac() for e in edges])
    ks = None if segment is None else scale_key(segment)
    meas_inv = [gtsam.Pose2(*map(float, e.delta)).inverse() for e in edges]
    b_hat = float(edges[0].bias_radps)
    keys = [int(edges[0].from_id)] + [int(e.to_id) for e in edges]
    kb = bias_key(edges[0].from_id)
    jb = -jac.reshape(3 * w, 1)
    model = gtsam.noiseModel.Gaussian.Covariance(cov)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[np.ndarray] | None) -> np.ndarray:
        xs = [values.atPose2(k) for k in keys]
        db = b_hat - float(values.atVector(kb)[0])
        out = jac * db
        if js is not None and ks is not None:
            out = out + js @ values.atVector(ks)
        if jacobians is not None:
            blocks = [np.zeros((3 * w, 3)) for _ in range(w + 1)]
        for k in range(w):
            h = xs[k].between(xs[k + 1])
            e = gtsam.Pose2.Logmap(meas_inv[k].compose(h))
            out[3 * k:3 * k + 3] += e
            if jacobians is not None:
                jr_inv = gtsam.Pose2.LogmapDerivative(e)
                blocks[k][3 * k:3 * k + 3] = -jr_inv @ h.inverse().AdjointMap()
                blocks[k + 1][3 * k:3 * k + 3] = jr_inv
        if jacobians is not None:
            for i, b in enumerate(blocks):
                jacobians[i] = b
            jacobians[w + 1] = jb
            if js is not None:
                jacobians[w + 2] = js
        return out

    return gtsam.CustomFactor(model, keys + [kb] + ([] if ks is None else [ks]), error)


# --------------------------------------------------------------------------------------
# The daemon's graph: edges with bias terms grouped into windows, spans for the fold.
# --------------------------------------------------------------------------------------


def bias_edge(from_id: int, to_id: int, delta: np.ndarray, terms: Sequence[Any]) -> BiasEdge:
    """A :class:`BiasEdge` from an edge and the filter's terms (the fields of
    :class:`robotd.odometry.history.EdgeBiasTerms`, in its order; its ``scale_gain``, when
    given, turns the delta's :func:`scale_jacobian` into the edge's)."""
    cov_given, jac, b, p, b_end, p_end, c = terms[:7]
    gain = terms[7] if len(terms) > 7 else None
    d = np.asarray(delta, float)
    js = None if gain is None else np.asarray(gain, float) @ scale_jacobian(d)
    return BiasEdge(int(from_id), int(to_id), d, np.asarray(cov_given, float),
                    np.asarray(jac, float), float(b), float(p), float(b_end), float(p_end), float(c), js)


def span_edge(edges: Sequence[BiasEdge]) -> BiasEdge:
    """Consecutive edges composed into one :class:`BiasEdge` from the first one's start to
    the last one's end, given the bias at the start: the composed delta, and the stacked
    errors of :func:`window_covariance` carried to the end's frame (an error at edge ``k``'s
    end moves to the span's end through the adjoint of the inverse of the rest of the
    span, as iSAM2's fold composes covariances): ``jac = A jac_w``, ``cov = A cov_w A^T``.
    Its factor on the span's two ends and the start's bias is the window's factor with
    the inner poses eliminated (to first order); its chain step, :func:`window_chain_edge`'s;
    its scale Jacobian, the edges' carried to the end the same way (``A J_s``)."""
    w = len(edges)
    if w == 1:
        return edges[0]
    jac_w, cov_w = window_covariance(edges)
    a = np.zeros((3, 3 * w))
    rest = gtsam.Pose2()  # the span after edge k
    for k in range(w - 1, -1, -1):
        a[:, 3 * k:3 * k + 3] = rest.inverse().AdjointMap()
        rest = gtsam.Pose2(*map(float, edges[k].delta)).compose(rest)
    total = rest
    chain = window_chain_edge(edges)
    cov = a @ cov_w @ a.T
    js = a @ np.vstack([e.scale_jac() for e in edges])
    return BiasEdge(edges[0].from_id, edges[-1].to_id, np.array([total.x(), total.y(), total.theta()]),
                    0.5 * (cov + cov.T), a @ jac_w, chain.bias_radps, chain.bias_var, chain.bias_end_radps,
                    chain.bias_end_var, chain.bias_cov, js)


@dataclass
class WindowChain:
    """The live grouping of odometry edges with bias terms into windows of ``size`` edges
    (:func:`bias_window_factor`), as the daemon's iSAM2 takes them: each edge first as an
    independent edge (its own, marginal covariance; ``slot`` the caller's handle of that
    factor), and when ``size`` consecutive edges are in, the window's factor replaces them.

    open: the open window's edges and their slots. previous: the last closed window's (or
    fold span's) edges, whose start has a bias variable: the next window chains to it.
    segment: the scale variable the windows share (:func:`scale_key`), None for none.
    """

    size: int = 10
    open: list[tuple[BiasEdge, int]] = field(default_factory=list)
    previous: list[BiasEdge] | None = None
    segment: int | None = None

    def reset(self) -> None:
        """The bias chain ends here (an edge without terms, a broken odometry chain)."""
        self.open, self.previous = [], None

    def continues(self, edge: BiasEdge) -> bool:
        """Whether ``edge`` extends the open window (or starts one at the previous one's end)."""
        if self.open:
            return self.open[-1][0].to_id == edge.from_id
        return self.previous is None or self.previous[-1].to_id == edge.from_id

    def offer(self, edge: BiasEdge) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[int]] | None:
        """Take ``edge`` (which must :meth:`continues`). None: it goes in as an independent
        edge (call :meth:`placed` with its slot). Else the window closed: ``(factors,
        bias values, slots to remove)``: the window's factor (which includes ``edge``), the
        bias variable at its start with its chain factor or prior."""
        if len(self.open) + 1 < self.size:
            self.open.append((edge, -1))
            return None
        edges = [e for e, _ in self.open] + [edge]
        remove = [s for _, s in self.open]
        fg = gtsam.NonlinearFactorGraph()
        fg.add(bias_window_factor(edges, self.segment))
        values = gtsam.Values()
        start = edges[0]
        values.insert(bias_key(start.from_id), np.array([start.bias_radps]))
        if self.previous is not None:
            fg.add(bias_chain_factor(window_chain_edge(self.previous)))
        else:
            fg.add(bias_prior_factor(start.from_id, start.bias_radps, start.bias_var))
        self.open, self.previous = [], edges
        return fg, values, remove

    def placed(self, slot: int) -> None:
        """The slot of the open window's newest edge's independent factor."""
        edge, _ = self.open[-1]
        self.open[-1] = (edge, int(slot))


def span_factors(span: Sequence[BiasEdge], previous: Sequence[BiasEdge] | None,
                 values: gtsam.Values, segment: int | None = None) -> gtsam.NonlinearFactorGraph:
    """A fold span of consecutive edges as factors: its :func:`span_edge` factor on its two
    ends and the bias at its start, and that bias's chain factor to ``previous`` (the span
    before it on its chain, ending where it starts) or, without one, the filter's prior;
    the bias value goes into ``values``. ``segment``: the span shares that scale variable."""
    fg = gtsam.NonlinearFactorGraph()
    s = span_edge(span)
    fg.add(bias_edge_factor(s, segment))
    if not values.exists(bias_key(s.from_id)):
        values.insert(bias_key(s.from_id), np.array([s.bias_radps]))
    if previous is not None and previous[-1].to_id == s.from_id:
        fg.add(bias_chain_factor(window_chain_edge(previous)))
    else:
        fg.add(bias_prior_factor(s.from_id, s.bias_radps, s.bias_var))
    return fg
