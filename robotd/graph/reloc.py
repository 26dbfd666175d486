"""Relocalisation: where a trajectory that does not know its place lies in the map frame
(issue 14, item 7).

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
from dataclasses import dataclass, field

import numpy as np

from robotd.base.geometry import (
    between,
    compose,
    compose_jacobians,
    inverse,
    wrap_angle,
)

__all__ = ["RelocCandidate", "RelocDecision", "RelocParams", "Relocaliser", "chain_relative",
           "implied_transform", "pair_chi2"]

AGREE_CHI2_3DOF_999 = 16.27  # chi-square, 3 degrees of freedom, 99.9 %


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
    """

    min_agreeing: int = 2
    agree_chi2: float = AGREE_CHI2_3DOF_999
    min_separation_m: float = 0.5
    map_sigma_m: float = 0.05
    map_sigma_rad: float = math.radians(1.0)
    max_pending: int = 64

    def __post_init__(self) -> None:
        if self.min_agreeing < 1:
            raise ValueError(f"min_agreeing must be at least 1, got {self.min_agreeing}")
        if self.max_pending < 1:
            raise ValueError(f"max_pending must be at least 1, got {self.max_pending}")
        for name in ("agree_chi2", "map_sigma_m", "map_sigma_rad"):
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
    ``old_run``: the run the old keyframe belongs to (for the report).
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


@dataclass(frozen=True, eq=False)
class RelocDecision:
    """What one offered candidate decided.

    ``relocalised``: the agreement rule holds; then ``transform (3,)`` takes lost-frame poses
    into the map frame (``map = transform (+) lost``) and ``members`` are the agreeing
    candidates (the offered one first). ``dropped``: held candidates that will never count,
    each with the reason (disagreeing with the accepted group, or too old). ``detail``
    says in words and numbers why (not) relocalised.
    """

    relocalised: bool
    detail: str
    transform: np.ndarray | None = None
    members: tuple[RelocCandidate, ...] = ()
    dropped: tuple[tuple[RelocCandidate, str], ...] = field(default=())


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
    (:func:`robotd.base.geometry.compose_jacobians`), each edge independent.
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
        j_a, j_b = compose_jacobians(rel, delta)
        cov = j_a @ cov @ j_a.T + j_b @ np.linalg.inv(info) @ j_b.T
        rel = compose(rel, delta)
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
        trajectory) or not on one odometry chain."""
        if abs(a.travelled_m - b.travelled_m) < self.params.min_separation_m:
            return None
        first, second = (a, b) if a.query_id < b.query_id else (b, a)
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
        left_out = tuple((p, self._why_not(c, p)) for p in others)
        self.pending = []
        return RelocDecision(True, f"{len(group)} candidates agree (of {len(others) + len(group)} held)",
                             transform, tuple(group), left_out)

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
