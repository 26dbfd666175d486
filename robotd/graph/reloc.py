"""Relocalisation: where a trajectory that does not know its place lies in the map frame.

After a restart on a stored map, or after the robot was carried while blind (a kidnapping),
the daemon runs on odometry in a frame of its own: the *lost trajectory* (this run's
keyframes since the restart, or since the robot was put down). The chi-square gate of the
live graph cannot judge a loop from the lost trajectory to a keyframe of the map, because
there is no prediction of where the one is relative to the other. Instead each loop
candidate implies a transform from the lost frame to the map frame,

    T = M_old (+) delta (+) X_query^-1

(``M_old``: the old keyframe's optimised pose in the map frame; ``delta``: the query in the
old keyframe's frame, measured from the floor; ``X_query``: the query in the lost frame),
and the trajectory is relocalised only when candidates **agree**. The rule chosen:

* at least ``min_agreeing`` (2) candidates;
* from query keyframes at least ``min_separation_m`` (0.5 m) apart along the lost
  trajectory: two floor images taken further apart than the camera's footprint (about
  0.3 x 0.2 m on the robot, DESIGN.md) see different floor, so one look-alike patch cannot
  vote twice (candidates of the same or nearly the same query are one piece of evidence,
  not two). The virtual robot's camera sees more (0.64 x 0.48 m): there two queries 0.5 m
  apart may still share a strip of floor;
* pairwise agreeing: for candidates ``a`` and ``b`` the relative pose of their queries in the
  lost frame (odometry between them, ``r``) must match the relative pose the two loops
  imply, ``(M_a (+) d_a)^-1 (+) (M_b (+) d_b)``. The residual's covariance is propagated
  (first order, numerically) from both loops' covariances, the odometry's covariance between
  the queries and an uncertainty of the map's own poses (``map_sigma_m``,
  ``map_sigma_rad``); its Mahalanobis distance must be under ``agree_chi2`` (the 99.9 %
  point of chi-square with 3 degrees of freedom, as the live gate);
* and unambiguous: no second group of agreeing candidates (two or more, separated) among
  the held ones that disagrees with the first.

**Forward loops** (the forward camera, :mod:`robotd.forward.planar`) take part too. One
measures the heading change and the bearing of the query as seen from the old keyframe,
and the range only when the floor gave it (``measured_dims`` 3, else 2): its edge is a
function of the predicted relative pose (:attr:`RelocCandidate.edge`), the range being the
prediction's when not measured. A candidate alone cannot place the robot then; two
candidates can, when odometry has moved the robot between their queries: the two bearings
intersect (the range is fixed by the triangulation), or a floor loop gives the rest. For a
group with a forward loop the transform is not one candidate's implied transform but the
least-squares fit of all members (:func:`fit_transform`: Gauss-Newton over the transform,
each member's residual whitened by its edge's covariance, the odometry between the queries
and the map's own error). The group agrees when the fit's chi-square is under the 99.9 %
point (the probability of ``agree_chi2`` at 3 degrees of freedom, taken at the fit's own
degrees of freedom: the members' measured components minus the transform's 3), and the fit
must fix the robot's position (1-sigma at most ``max_position_sigma_m``): two bearings
along one line of sight do not. A group of forward loops only then enters the pose graph
as one edge, the fit's pose of its earliest query with the fit's covariance
(:func:`group_constraint`), not as its members' edges: each member measured little (a ridge
loop's heading and bearing are as uncertain as the ridge is wide), and the fit is what the
group fixed together. A group of forward loops only needs ``min_forward_only`` (3)
members: two bearings from places apart always cross, so a wrong bearing among two forward
loops moves the fitted position without showing in the fit; a third loop (or a floor loop)
over-determines it. When the whole group's fit disagrees, its subsets are fitted (one
wrong member must not keep the right ones from agreeing), and two subsets that agree on
different places leave the trajectory lost, as an ambiguous group does.

Why this rule: a false floor candidate above the trained threshold is rare (none in the
demo's runs), and two independent false ones that imply the *same* map pose within their
covariance are rarer still, because a false candidate's transform is effectively random. A
single look-alike, or several that disagree, leave the trajectory lost. Requiring more
candidates would cost distance driven before relocalisation; requiring fewer (one) would
let any single look-alike put the robot in the wrong place, which nothing would undo.

Nothing here does I/O: the caller gives candidates and the odometry between two query
keyframes (:func:`chain_relative`), and gets a :class:`RelocDecision`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from robotd.base.geometry import (
    between,
    compose,
    compose_with_covariance,
    information_from_covariance,
    inverse,
    wrap_angle,
)

__all__ = ["RelocCandidate", "RelocDecision", "RelocParams", "Relocaliser", "TransformFit", "chain_relative",
           "fit_transform", "group_constraint", "implied_transform", "pair_chi2"]

AGREE_CHI2_3DOF_999 = 16.27  # chi-square, 3 degrees of freedom, 99.9 %
MAX_GROUP_FITS = 32  # subsets of a group with a forward loop fitted per offered candidate

ForwardEdge = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""A forward loop's edge ``(delta (3,), information (3, 3))`` given the predicted relative
pose (3,) of its two keyframes (:func:`robotd.forward.planar.loop_edge`)."""


@dataclass(frozen=True)
class RelocParams:
    """Parameters of :class:`Relocaliser` (see the module notes for the rule).

    min_agreeing: candidates that must agree, default 2.
    agree_chi2: a pair agrees when its residual's Mahalanobis distance squared is at most
        this (dimensionless), default 16.27 (chi-square, 3 dof, 99.9 %).
    min_separation_m: queries of agreeing candidates are at least this far apart along the
        lost trajectory (odometry distance driven), default 0.5 m.
    map_sigma_m, map_sigma_rad: 1-sigma error of an old keyframe's optimised map pose
        (position per axis, heading), default 0.05 m and 1 deg: the map's relative error
        between two nearby keyframes, not its global error.
    max_pending: candidates held while waiting for agreement; the oldest is dropped (and
        reported) beyond this, default 64.
    max_position_sigma_m: a group with a forward loop relocalises only when its fit fixes
        the robot's position to this (1-sigma, the larger axis), default 0.3 m: about the
        distance at which the gate's later loops still find their places.
    min_forward_only: a group of forward loops only (no floor loop) relocalises with at
        least this many members, default 3: two bearings from places apart always cross
        somewhere, so the fit of two forward loops has no freedom left to show that one
        bearing is wrong (only their heading changes are compared); a third loop, or a
        floor loop, over-determines the position.
    forward_group_as_one: a group of forward loops only enters the pose graph as one
        edge, its fitted transform with the fit's covariance (:func:`group_constraint`),
        and none of its members as a loop edge, default True; False: each member an edge at
        the fitted transform (as a group with a floor loop always does).
    """

    min_agreeing: int = 2
    agree_chi2: float = AGREE_CHI2_3DOF_999
    min_separation_m: float = 0.5
    map_sigma_m: float = 0.05
    map_sigma_rad: float = math.radians(1.0)
    max_pending: int = 64
    max_position_sigma_m: float = 0.3
    min_forward_only: int = 3
    forward_group_as_one: bool = True

    def __post_init__(self) -> None:
        if self.min_agreeing < 1:
            raise ValueError(f"min_agreeing must be at least 1, got {self.min_agreeing}")
        if self.min_forward_only < 1:
            raise ValueError(f"min_forward_only must be at least 1, got {self.min_forward_only}")
        if self.max_pending < 1:
            raise ValueError(f"max_pending must be at least 1, got {self.max_pending}")
        for name in ("agree_chi2", "map_sigma_m", "map_sigma_rad", "max_position_sigma_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be positive and finite, got {v}")
        if not (math.isfinite(self.min_separation_m) and self.min_separation_m >= 0.0):
            raise ValueError(f"min_separation_m must be non-negative, got {self.min_separation_m}")


@dataclass(frozen=True, eq=False)
class RelocCandidate:
    """A loop candidate from the lost trajectory to a keyframe with a map pose.

    ``old_pose (3,)``: the old keyframe's pose in the map frame (m, m, rad); ``delta (3,)``
    the query keyframe in the old keyframe's frame, ``information (3, 3)`` its inverse
    covariance; ``query_pose (3,)``: the query keyframe in the lost trajectory's own frame;
    ``travelled_m``: odometry distance driven along the lost trajectory up to the query;
    ``old_run``: the run the old keyframe belongs to (for the report); ``source``: the
    camera (``"floor"``, ``"forward"``). A forward loop has ``edge``: its ``(delta,
    information)`` given the predicted relative pose, ``delta`` and ``information`` being
    those at a first guess until the group's fit replaces them; ``measured_dims``: the
    components the loop measures (3; 2 for a forward loop without a range of its own);
    ``unsettled``: a forward loop on a heading-bearing ridge no prior heading settled (the
    gate never takes it, :mod:`robotd.graph.gate`).
    """

    old_id: int
    query_id: int
    score: float
    old_pose: np.ndarray
    delta: np.ndarray
    information: np.ndarray
    query_pose: np.ndarray
    travelled_m: float
    old_run: int = 0
    source: str = "floor"
    edge: ForwardEdge | None = None
    measured_dims: int = 3
    unsettled: bool = False


@dataclass(frozen=True, eq=False)
class RelocDecision:
    """What one offered candidate decided.

    ``relocalised``: the agreement rule holds; then ``transform (3,)`` takes lost-frame poses
    into the map frame (``map = transform (+) lost``) and ``members`` are the agreeing
    candidates (the offered one first); for a group with a forward loop, ``covariance (3,
    3)`` is the transform's from the group's fit (:class:`TransformFit`), None for floor
    loops alone. ``dropped``: held candidates that will never count, each with the reason
    (disagreeing with the accepted group, or too old). ``detail`` says in words and
    numbers why (not) relocalised.
    """

    relocalised: bool
    detail: str
    transform: np.ndarray | None = None
    members: tuple[RelocCandidate, ...] = ()
    dropped: tuple[tuple[RelocCandidate, str], ...] = field(default=())
    covariance: np.ndarray | None = None


def implied_transform(c: RelocCandidate) -> np.ndarray:
    """``(3,)`` the lost frame in the map frame implied by one candidate:
    ``old_pose (+) delta (+) query_pose^-1``."""
    return compose(compose(c.old_pose, c.delta), inverse(c.query_pose))


def chain_relative(edges_into: Mapping[int, tuple[int, np.ndarray, np.ndarray]], from_id: int,
                   to_id: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The odometry chain from ``from_id`` to ``to_id``: ``(delta (3,), covariance (3, 3))``,
    or None when the chain is broken (a kidnapping) or ``to_id`` is not after ``from_id``.

    ``edges_into``: keyframe id -> ``(previous id, delta (3,), information (3, 3))`` of its
    odometry edge. The covariance of the composed delta is propagated edge by edge
    (:func:`robotd.base.geometry.compose_with_covariance`), each edge independent.
    """
    steps = []
    k = int(to_id)
    while k != from_id:
        if k not in edges_into or k < from_id:
            return None
        prev, delta, info = edges_into[k]
        steps.append((delta, info))
        k = prev
    rel = np.zeros(3)
    cov = np.zeros((3, 3))
    for delta, info in reversed(steps):
        rel, cov = compose_with_covariance(rel, cov, delta, np.linalg.inv(info))
    return rel, 0.5 * (cov + cov.T)


def _residual(x: np.ndarray) -> np.ndarray:
    """The pair residual of the stacked ``(d_a, d_b, r, m_a, m_b)``, each (3,): the
    odometry's relative pose against the one the two loops imply."""
    d_a, d_b, r, m_a, m_b = x.reshape(5, 3)
    implied = between(compose(m_a, d_a), compose(m_b, d_b))
    e = between(r, implied)
    return np.array([e[0], e[1], float(wrap_angle(e[2]))])


def pair_chi2(a: RelocCandidate, b: RelocCandidate, relative: np.ndarray, relative_cov: np.ndarray,
              params: RelocParams = RelocParams()) -> float:
    """Mahalanobis distance squared between two candidates' implied transforms
    (dimensionless): see the module notes. ``relative (3,)``, ``relative_cov (3, 3)``: the
    query of ``b`` in the frame of the query of ``a`` by odometry, and its covariance."""
    x0 = np.concatenate([a.delta, b.delta, np.asarray(relative, float), a.old_pose, b.old_pose])
    e0 = _residual(x0)
    jac = np.zeros((3, 15))
    for k in range(15):
        h = 1e-6
        xp, xm = x0.copy(), x0.copy()
        xp[k] += h
        xm[k] -= h
        jac[:, k] = (_residual(xp) - _residual(xm)) / (2.0 * h)
    m = np.diag([params.map_sigma_m ** 2, params.map_sigma_m ** 2, params.map_sigma_rad ** 2])
    blocks = [np.linalg.inv(a.information), np.linalg.inv(b.information),
              np.asarray(relative_cov, float), m, m]
    cov = np.zeros((15, 15))
    for n, blk in enumerate(blocks):
        cov[3 * n:3 * n + 3, 3 * n:3 * n + 3] = blk
    s = jac @ cov @ jac.T
    return float(e0 @ np.linalg.solve(s, e0))


@dataclass(frozen=True, eq=False)
class TransformFit:
    """The least-squares transform of a group (:func:`fit_transform`): ``transform (3,)``
    (``map = transform (+) lost``), its ``covariance (3, 3)``, the fit's ``chi2``
    (dimensionless) at ``dof`` degrees of freedom, and the members with their edges at the
    fitted transform (a forward loop's ``delta`` and ``information`` replaced)."""

    transform: np.ndarray
    covariance: np.ndarray
    chi2: float
    dof: int
    members: tuple[RelocCandidate, ...]

    @property
    def position_sigma_m(self) -> float:
        """1-sigma of the position along its worst axis, metres."""
        return math.sqrt(max(float(np.max(np.linalg.eigvalsh(self.covariance[:2, :2]))), 0.0))


def _member_edge(c: RelocCandidate, predicted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return c.edge(predicted) if c.edge is not None else (c.delta, c.information)


def _error(delta: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    e = between(delta, predicted)
    return np.array([e[0], e[1], float(wrap_angle(e[2]))])


def _numeric_jacobian(f: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, h: float = 1e-6) -> np.ndarray:
    cols = []
    for k in range(len(x0)):
        xp, xm = x0.copy(), x0.copy()
        xp[k] += h
        xm[k] -= h
        cols.append((f(xp) - f(xm)) / (2.0 * h))
    return np.stack(cols, axis=1)


def _starts(c: RelocCandidate) -> list[np.ndarray]:
    """First guesses of the transform from one candidate: its implied transform, or for a
    forward loop without a range of its own, one per range from 0.3 to 6 m."""
    if c.edge is None:
        return [implied_transform(c)]
    ranges = (1.0,) if c.measured_dims >= 3 else (0.3, 0.7, 1.5, 3.0, 6.0)
    out = []
    for r in ranges:
        delta, _info = c.edge(np.array([r, 0.0, 0.0]))
        out.append(compose(compose(c.old_pose, delta), inverse(c.query_pose)))
    return out


def fit_transform(members: Iterable[RelocCandidate],
                  relative: Callable[[int, int], tuple[np.ndarray, np.ndarray] | None],
                  params: RelocParams = RelocParams(), iterations: int = 15) -> TransformFit | None:
    """The transform (lost frame -> map frame) that best explains all ``members`` (module
    notes), or None when two of them are not on one odometry chain. Each member's error is
    ``between(delta, predicted)`` with ``predicted = old_pose^-1 (+) transform (+) query_pose``
    and ``delta`` its edge at that prediction; its covariance is the edge's plus the
    odometry's from the first query (``relative``) and the map pose's error (``map_sigma_m``,
    ``map_sigma_rad``), propagated to first order. Gauss-Newton from each member's first
    guess that explains them best (:func:`_starts`)."""
    group = list(members)
    ref = min(group, key=lambda m: m.query_id)
    odo: list[tuple[np.ndarray, np.ndarray]] = []
    for m in group:
        if m is ref:
            odo.append((np.zeros(3), np.zeros((3, 3))))
            continue
        chain = relative(ref.query_id, m.query_id)
        if chain is None:
            return None
        odo.append((np.asarray(chain[0], float), np.asarray(chain[1], float)))
    mcov = np.diag([params.map_sigma_m ** 2, params.map_sigma_m ** 2, params.map_sigma_rad ** 2])

    def whitened(t: np.ndarray, sqrt_infos: list[np.ndarray]) -> np.ndarray:
        out = []
        for m, (rel, _cov), w in zip(group, odo, sqrt_infos):
            q = compose(ref.query_pose, rel)
            pred = between(m.old_pose, compose(t, q))
            out.append(w @ _error(_member_edge(m, pred)[0], pred))
        return np.concatenate(out)

    def noise(t: np.ndarray) -> list[np.ndarray]:
        """Each member's whitening matrix at ``t`` (``L^T`` with ``L L^T = S^-1``)."""
        out = []
        for m, (rel, cov) in zip(group, odo):
            pred0 = between(m.old_pose, compose(t, compose(ref.query_pose, rel)))
            delta, info = _member_edge(m, pred0)

            def err_of(x: np.ndarray, delta: np.ndarray = delta, rel: np.ndarray = rel) -> np.ndarray:
                return _error(delta, between(x[:3], compose(t, compose(ref.query_pose, rel + x[3:]))))

            jac = _numeric_jacobian(err_of, np.concatenate([np.asarray(m.old_pose, float), np.zeros(3)]))
            s = np.linalg.inv(info) + jac[:, :3] @ mcov @ jac[:, :3].T + jac[:, 3:] @ cov @ jac[:, 3:].T
            out.append(np.linalg.cholesky(np.linalg.inv(0.5 * (s + s.T))).T)
        return out

    def cost_at(t: np.ndarray) -> float:
        r = whitened(t, noise(t))
        return float(r @ r)

    # Gauss-Newton from the first guess that explains the members best.
    t = np.asarray(min((s for m in group for s in _starts(m)), key=cost_at), float).copy()
    w = noise(t)
    r = whitened(t, w)
    cost = float(r @ r)
    for _ in range(iterations):
        jac = _numeric_jacobian(lambda x: whitened(x, w), t)
        try:
            step = -np.linalg.solve(jac.T @ jac + 1e-9 * np.eye(3), jac.T @ r)
        except np.linalg.LinAlgError:
            break
        t_new = t + step
        t_new[2] = float(wrap_angle(t_new[2]))
        w_new = noise(t_new)
        r_new = whitened(t_new, w_new)
        cost_new = float(r_new @ r_new)
        if not cost_new < cost:
            break
        done = cost - cost_new < 1e-6 * max(cost, 1.0)
        t, w, r, cost = t_new, w_new, r_new, cost_new
        if done:
            break
    jac = _numeric_jacobian(lambda x: whitened(x, w), t)
    jtj = jac.T @ jac
    if np.linalg.cond(jtj) > 1e12:  # an unobservable direction: not fixed at all
        cov = np.linalg.pinv(jtj) + np.diag([1e6, 1e6, 1e6])
    else:
        cov = np.linalg.inv(jtj)
    fitted = []
    for m, (rel_q, _cov) in zip(group, odo):
        if m.edge is None:
            fitted.append(m)
            continue
        delta, info = m.edge(between(m.old_pose, compose(t, compose(ref.query_pose, rel_q))))
        fitted.append(replace(m, delta=np.asarray(delta, float), information=np.asarray(info, float)))
    dof = sum(m.measured_dims for m in group) - 3
    return TransformFit(t, 0.5 * (cov + cov.T), cost, dof, tuple(fitted))


def group_constraint(members: Iterable[RelocCandidate], transform: np.ndarray,
                     covariance: np.ndarray) -> tuple[int, int, np.ndarray, np.ndarray]:
    """A relocalising group as one edge: ``(old_id, query_id, delta (3,), information (3,
    3))`` from the old keyframe of the member with the earliest query to that query, its
    ``delta`` the query's pose the fitted ``transform`` gives (``old_pose^-1 (+)
    transform (+) query_pose``) and its covariance the transform's (``covariance``, the
    group's fit, :class:`TransformFit`) carried to that delta to first order.

    The fit holds the earliest query's pose in the lost frame as given and the odometry
    from it to the later queries as noise (:func:`fit_transform`), so its covariance is
    the uncertainty of that query's place in the map: one constraint on it stands for the
    group, the graph's own odometry edges carry it to the others. No member's own
    measurement enters the graph: a member that agrees with the group only within its
    own (wide) noise places the segment no more than the fit lets it."""
    ref = min(members, key=lambda m: m.query_id)
    t0 = np.asarray(transform, float)

    def delta_at(t: np.ndarray) -> np.ndarray:
        return between(ref.old_pose, compose(t, ref.query_pose))

    delta = delta_at(t0)
    jac = _numeric_jacobian(lambda t: _error(delta, delta_at(t)), t0)
    cov = jac @ np.asarray(covariance, float) @ jac.T
    return ref.old_id, ref.query_id, np.asarray(delta, float), information_from_covariance(cov)


def agreement_threshold(dof: int, params: RelocParams) -> float:
    """The chi-square bound of a fit with ``dof`` degrees of freedom at the probability
    ``params.agree_chi2`` has at 3 (99.9 % by default)."""
    from scipy.stats import chi2

    if dof <= 0:
        return 0.0
    return float(chi2.ppf(chi2.cdf(params.agree_chi2, 3), dof))


class Relocaliser:
    """Holds the lost trajectory's candidates until enough of them agree (module notes).

    ``relative(query_a, query_b)`` gives the odometry from one query keyframe to a later one
    in the lost frame, ``(delta (3,), covariance (3, 3))``, or None when they are not on one
    unbroken chain (then the pair cannot agree).
    """

    def __init__(self, relative: Callable[[int, int], tuple[np.ndarray, np.ndarray] | None],
                 params: RelocParams = RelocParams()) -> None:
        self.params = params
        self.relative = relative
        self.pending: list[RelocCandidate] = []

    def _chi2(self, a: RelocCandidate, b: RelocCandidate) -> float | None:
        """The pair's agreement distance, None when not independent (too close along the
        trajectory) or not on one odometry chain. Two floor loops: :func:`pair_chi2`; with a
        forward loop, the pair's :func:`fit_transform` chi-square, scaled to the 3-dof
        bound (``agree_chi2``) so that one threshold judges both."""
        if abs(a.travelled_m - b.travelled_m) < self.params.min_separation_m:
            return None
        first, second = (a, b) if a.query_id < b.query_id else (b, a)
        if first.edge is not None or second.edge is not None:
            fit = fit_transform((first, second), self.relative, self.params)
            if fit is None:
                return None
            bound = agreement_threshold(fit.dof, self.params)
            return fit.chi2 / bound * self.params.agree_chi2 if bound > 0.0 else 0.0
        rel = self.relative(first.query_id, second.query_id)
        if rel is None:
            return None
        return pair_chi2(first, second, rel[0], rel[1], self.params)

    def _group(self, seed: RelocCandidate, pool: Iterable[RelocCandidate]) -> list[RelocCandidate]:
        """``seed`` and the candidates of ``pool`` that agree with it and with each other,
        greedily from the best agreeing."""
        scored = []
        for p in pool:
            d2 = self._chi2(seed, p)
            if d2 is not None and d2 <= self.params.agree_chi2:
                scored.append((d2, p))
        group = [seed]
        for _d2, p in sorted(scored, key=lambda t: t[0]):
            ok = True
            for m in group[1:]:
                d2 = self._chi2(m, p)
                if d2 is None or d2 > self.params.agree_chi2:
                    ok = False
                    break
            if ok:
                group.append(p)
        return group

    def offer(self, c: RelocCandidate) -> RelocDecision:
        """Consider one more candidate; see :class:`RelocDecision`."""
        need = self.params.min_agreeing
        group = self._group(c, self.pending)
        if len(group) < need:
            self.pending.append(c)
            dropped = []
            while len(self.pending) > self.params.max_pending:
                old = self.pending.pop(0)
                why = f"relocalisation: no agreeing candidate among the next {self.params.max_pending}"
                dropped.append((old, why))
            return RelocDecision(False, f"{len(group)} of {need} agreeing candidates", dropped=tuple(dropped))
        members = {id(m) for m in group}
        others = [p for p in self.pending if id(p) not in members]
        transform = implied_transform(c)
        covariance = None
        detail = f"{len(group)} candidates agree (of {len(others) + len(group)} held)"
        if any(m.edge is not None for m in group):  # with a forward loop: the group's own fit
            fit, why = self._forward_fit(group)
            if fit is None:
                self.pending.append(c)
                return RelocDecision(False, f"{len(group)} candidates agree pairwise, but {why}")
            if len(fit.members) < len(group):  # a member the others' fit disagrees with stays out
                kept = {(m.old_id, m.query_id) for m in fit.members}
                others += [m for m in group if (m.old_id, m.query_id) not in kept]
            group = list(fit.members)  # in the group's order, forward edges at the fitted transform
            transform, covariance = fit.transform, fit.covariance
            detail = (f"{len(group)} candidates agree (of {len(others) + len(group)} held), "
                      f"position 1-sigma {fit.position_sigma_m:.2f} m")
        left_out = tuple((p, self._why_not(c, p)) for p in others)
        self.pending = []
        return RelocDecision(True, detail, transform, tuple(group), left_out, covariance)

    def _forward_fit(self, group: list[RelocCandidate]) -> tuple[TransformFit | None, str]:
        """The fit of a pairwise-agreeing group with a forward loop, or None and why not.

        The group's fit must agree (chi-square), fix the position, and, with forward loops
        only, have ``min_forward_only`` members (:class:`RelocParams`). When the whole
        group's fit disagrees, its subsets with the offered candidate (first), one member
        fewer at a time down to the size the rule needs, are tried (the largest size at
        which one agrees; when two of that size agree on different places, none is taken,
        as for the unambiguous rule of the module notes): pairs of forward loops
        agree almost always (their bearings cross), so one wrong bearing among them shows
        only in the group's fit, and must not keep the right ones from ever agreeing (at most
        :data:`MAX_GROUP_FITS` fits per offered candidate)."""
        from itertools import combinations

        p = self.params
        first, rest = group[0], group[1:]
        why = ""
        tries = 0
        for size in range(len(group), max(p.min_agreeing, 2) - 1, -1):
            passing: list[tuple[float, TransformFit]] = []
            for others in combinations(rest, size - 1):
                members = [first, *others]
                forward_only = all(m.source == "forward" for m in members)
                if forward_only and len(members) < p.min_forward_only:
                    why = why or (f"{len(members)} forward loops only: two bearings always cross, so a third "
                                  f"forward loop or a floor loop must confirm")
                    continue
                tries += 1
                if tries > MAX_GROUP_FITS:
                    break
                fit = fit_transform(members, self.relative, p)
                if fit is None:
                    why = why or "not on one odometry chain"
                    continue
                bound = agreement_threshold(fit.dof, p)
                if fit.chi2 > bound:
                    why = why or f"the group's fit disagrees (chi2 {fit.chi2:.1f} > {bound:.2f})"
                    continue
                if fit.position_sigma_m > p.max_position_sigma_m:
                    why = why or (f"the position is not fixed yet (1-sigma {fit.position_sigma_m:.2f} m > "
                                  f"{p.max_position_sigma_m:.2f} m)")
                    continue
                passing.append((fit.chi2 / bound if bound > 0.0 else 0.0, fit))
            if passing:  # the largest agreeing subsets: one place, or none
                for (_s, f1), (_s2, f2) in combinations(passing, 2):
                    d = f1.transform - f2.transform
                    d[2] = float(wrap_angle(d[2]))
                    if float(d @ np.linalg.solve(f1.covariance + f2.covariance, d)) > p.agree_chi2:
                        return None, (f"ambiguous: subsets of {size} agree on places "
                                      f"{float(np.hypot(d[0], d[1])):.2f} m apart")
                return min(passing, key=lambda t: t[0])[1], ""
        return None, why

    def _why_not(self, c: RelocCandidate, p: RelocCandidate) -> str:
        """Why a held candidate ``p`` is not in the group that relocalised with ``c``."""
        d2 = self._chi2(c, p)
        if d2 is None:
            return "relocalisation: not independent of the agreeing candidates (same floor, or another trajectory)"
        if d2 > self.params.agree_chi2:
            return f"relocalisation: disagrees with the agreeing candidates (chi2 {d2:.1f} > {self.params.agree_chi2:.2f})"
        return "relocalisation: disagrees with another member of the agreeing group"

    def reset(self) -> list[RelocCandidate]:
        """Forget the held candidates (a new lost trajectory began); returns them."""
        out, self.pending = self.pending, []
        return out
