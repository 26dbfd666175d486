"""The pose graph as data, and the objectives it is scored by.

A :class:`PoseGraph` holds SE(2) poses ``(x_m, y_m, yaw_rad)`` keyed by keyframe id (any
non-negative integers, not necessarily consecutive), edges that each say where pose ``to_id``
is in the frame of pose ``from_id`` (``delta (3,)``: ``dx_m, dy_m, dyaw_rad``) with a
``(3, 3)`` information matrix over the same coordinates, and optional fixed vertices.

Two objectives (both are sums over every edge, without GTSAM's factor of 1/2):

* :func:`chi2`, the full-information one: ``sum e^T I e`` with the edge error
  ``e = (R_ij^T (R_i^T (t_j - t_i) - t_ij), wrap(yaw_j - yaw_i - yaw_ij))``, which is exactly
  the error of GTSAM's ``BetweenFactor<Pose2>`` (its local chart keeps translation as is).
* :func:`isotropic_objective`, the SE-Sync objective (Rosen et al., IJRR 2019, eq. 9 with the
  2D g2o conversion of their reader): ``sum kappa ||R_j - R_i R_ij||_F^2
  + tau ||t_j - t_i - R_i t_ij||^2`` with ``kappa = I33`` and
  ``tau = 2 / trace(inv(I[:2, :2]))``. ``||R_j - R_i R_ij||_F^2 = 4 (1 - cos e_yaw)``, which is
  ``2 e_yaw^2`` to second order, so :func:`isotropic_graph` gives each edge the information
  ``diag(tau, tau, 2 kappa)``: its :func:`chi2` is the SE-Sync objective up to the
  ``kappa e_yaw^4 / 6`` term.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from robotd.base.errors import GraphError
from robotd.base.geometry import compose, inverse, wrap_angle

EdgeKind = Literal["odometry", "loop"]


@dataclass(frozen=True, slots=True, eq=False)
class Edge:
    """One pose-graph edge: pose ``to_id`` in the frame of pose ``from_id``.

    ``delta`` is ``(3,) float64`` ``(dx_m, dy_m, dyaw_rad)``; ``information`` is the
    ``(3, 3) float64`` symmetric positive-definite inverse covariance over the same
    coordinates (units 1/m^2, 1/(m rad), 1/rad^2). Both arrays are read-only.
    """

    from_id: int
    to_id: int
    delta: np.ndarray
    information: np.ndarray
    kind: EdgeKind


def check_information(information: np.ndarray | Iterable[Iterable[float]],
                      what: str = "information") -> np.ndarray:
    """Return ``information`` as a read-only ``(3, 3)`` float64 array, or raise GraphError
    when it is not finite, not symmetric or not positive definite (a Cholesky test)."""
    info = np.array(information, dtype=np.float64)
    if info.shape != (3, 3):
        raise GraphError(f"{what} must be 3x3, got shape {info.shape}")
    if not np.all(np.isfinite(info)):
        raise GraphError(f"{what} is not finite")
    scale = max(float(np.max(np.abs(info))), 1e-300)
    if not np.allclose(info, info.T, rtol=0.0, atol=1e-12 * scale):
        raise GraphError(f"{what} is not symmetric")
    try:
        np.linalg.cholesky(info / scale)
    except np.linalg.LinAlgError:
        raise GraphError(f"{what} is not positive definite") from None
    info.setflags(write=False)
    return info


def make_edge(from_id: int, to_id: int, delta: Iterable[float],
              information: np.ndarray | Iterable[Iterable[float]], kind: EdgeKind) -> Edge:
    """A checked :class:`Edge` (GraphError for a self-loop, a bad kind, a non-finite delta
    or a non-positive-definite information matrix)."""
    a, b = int(from_id), int(to_id)
    if a == b:
        raise GraphError(f"edge {a} -> {b} joins a vertex to itself")
    if kind not in ("odometry", "loop"):
        raise GraphError(f"edge kind must be 'odometry' or 'loop', got {kind!r}")
    return Edge(a, b, _triple(delta, f"edge {a} -> {b} delta"),
                check_information(information, f"edge {a} -> {b} information"), kind)


def _triple(values: Iterable[float], what: str) -> np.ndarray:
    arr = np.array(values, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise GraphError(f"{what} must be 3 finite numbers, got {arr}")
    arr.setflags(write=False)
    return arr


class PoseGraph:
    """SE(2) poses keyed by keyframe id, odometry and loop edges, fixed vertices.

    Poses added here are the initial guess (odometry) an optimiser starts from. Edges may be
    added only between existing poses; ids are non-negative integers (GTSAM keys).
    """

    def __init__(self) -> None:
        self._poses: dict[int, np.ndarray] = {}
        self._edges: list[Edge] = []
        self._fixed: set[int] = set()

    def add_pose(self, keyframe_id: int, pose: Iterable[float]) -> None:
        """Add vertex ``keyframe_id`` at ``pose`` ``(x_m, y_m, yaw_rad)``; a duplicate
        id is a GraphError."""
        kid = int(keyframe_id)
        if kid < 0:
            raise GraphError(f"vertex id must be non-negative, got {kid}")
        if kid in self._poses:
            raise GraphError(f"duplicate vertex {kid}")
        self._poses[kid] = _triple(pose, f"pose of vertex {kid}")

    def set_pose(self, keyframe_id: int, pose: Iterable[float]) -> None:
        """Replace the initial guess of an existing vertex."""
        if int(keyframe_id) not in self._poses:
            raise GraphError(f"no vertex {keyframe_id}")
        self._poses[int(keyframe_id)] = _triple(pose, f"pose of vertex {keyframe_id}")

    def add_edge(self, from_id: int, to_id: int, delta: Iterable[float],
                 information: np.ndarray | Iterable[Iterable[float]], kind: EdgeKind) -> Edge:
        """Add an edge between two existing vertices; returns it."""
        edge = self.check_edge(from_id, to_id, delta, information, kind)
        self._edges.append(edge)
        return edge

    def check_edge(self, from_id: int, to_id: int, delta: Iterable[float],
                   information: np.ndarray | Iterable[Iterable[float]], kind: EdgeKind) -> Edge:
        """The edge :meth:`add_edge` would add (the same GraphErrors), not added."""
        a, b = int(from_id), int(to_id)
        for kid in (a, b):
            if kid not in self._poses:
                raise GraphError(f"edge {a} -> {b}: no vertex {kid}")
        return make_edge(a, b, delta, information, kind)

    def add_edges(self, edges: Iterable[Edge]) -> None:
        """Add already-checked edges (from :func:`make_edge`) between existing vertices."""
        for e in edges:
            for kid in (e.from_id, e.to_id):
                if kid not in self._poses:
                    raise GraphError(f"edge {e.from_id} -> {e.to_id}: no vertex {kid}")
            self._edges.append(e)

    def fix(self, keyframe_id: int) -> None:
        """Hold vertex ``keyframe_id`` at its pose (a prior); without any fixed vertex the
        optimisers anchor the smallest id."""
        if int(keyframe_id) not in self._poses:
            raise GraphError(f"cannot fix vertex {keyframe_id}: no such vertex")
        self._fixed.add(int(keyframe_id))

    def unfix(self, keyframe_id: int) -> None:
        """Let vertex ``keyframe_id`` move again (a relocalised trajectory's first keyframe,
        now held by its loops to the map instead)."""
        self._fixed.discard(int(keyframe_id))

    @property
    def ids(self) -> np.ndarray:
        """Vertex ids in increasing order, ``(N,) int64``."""
        return np.array(sorted(self._poses), dtype=np.int64)

    def poses(self) -> np.ndarray:
        """Initial poses in :attr:`ids` order, ``(N, 3) float64`` (m, m, rad)."""
        return np.array([self._poses[k] for k in sorted(self._poses)], dtype=np.float64).reshape(-1, 3)

    def pose(self, keyframe_id: int) -> np.ndarray:
        return self._poses[int(keyframe_id)]

    def __contains__(self, keyframe_id: object) -> bool:
        return keyframe_id in self._poses

    def __len__(self) -> int:
        return len(self._poses)

    @property
    def edges(self) -> list[Edge]:
        """Every edge in insertion order (a copy of the list)."""
        return list(self._edges)

    @property
    def fixed(self) -> frozenset[int]:
        return frozenset(self._fixed)

    def components(self) -> list[list[int]]:
        """Connected components (vertex ids, each sorted), ordered by their smallest id."""
        parent = {k: k for k in self._poses}

        def root(k: int) -> int:
            while parent[k] != k:
                parent[k] = parent[parent[k]]
                k = parent[k]
            return k

        for e in self._edges:
            ra, rb = root(e.from_id), root(e.to_id)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
        groups: dict[int, list[int]] = {}
        for k in sorted(self._poses):
            groups.setdefault(root(k), []).append(k)
        return [groups[r] for r in sorted(groups)]

    def anchors(self) -> list[int]:
        """The vertices held at their poses: the fixed ones, plus the smallest id of every
        connected component without a fixed vertex (so that each has a gauge)."""
        out = set(self._fixed)
        for comp in self.components():
            if not out.intersection(comp):
                out.add(comp[0])
        return sorted(out)

    def with_poses(self, ids: np.ndarray, poses: np.ndarray) -> PoseGraph:
        """A copy with the same edges and fixed set whose poses are ``poses`` (``(N, 3)``,
        aligned with ``ids``)."""
        out = PoseGraph()
        for kid, p in zip(ids, poses):
            out.add_pose(int(kid), p)
        out._edges = list(self._edges)
        out._fixed = set(self._fixed)
        return out


def isotropic_weights(information: np.ndarray) -> tuple[float, float]:
    """SE-Sync's ``(kappa, tau)`` of one edge: ``kappa = I33`` (1/rad^2) and
    ``tau = 2 / trace(inv(I[:2, :2]))`` (1/m^2)."""
    info = np.asarray(information, dtype=float)
    return float(info[2, 2]), float(2.0 / np.trace(np.linalg.inv(info[:2, :2])))


def isotropic_graph(graph: PoseGraph) -> PoseGraph:
    """The same graph with each edge's information replaced by ``diag(tau, tau, 2 kappa)``
    (see the module docstring for why 2 kappa)."""
    out = graph.with_poses(graph.ids, graph.poses())
    out._edges = []
    for e in graph.edges:
        kappa, tau = isotropic_weights(e.information)
        out.add_edge(e.from_id, e.to_id, e.delta, np.diag([tau, tau, 2.0 * kappa]), e.kind)
    return out


def _endpoints(graph: PoseGraph, ids: np.ndarray, poses: np.ndarray,
               edges: list[Edge]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ids = np.asarray(ids, dtype=np.int64)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    order = np.argsort(ids)
    sorted_ids = ids[order]
    src = np.array([e.from_id for e in edges], dtype=np.int64)
    dst = np.array([e.to_id for e in edges], dtype=np.int64)
    pos_i = np.searchsorted(sorted_ids, src)
    pos_j = np.searchsorted(sorted_ids, dst)
    if np.any(pos_i >= len(ids)) or np.any(pos_j >= len(ids)) or \
            np.any(sorted_ids[np.minimum(pos_i, len(ids) - 1)] != src) or \
            np.any(sorted_ids[np.minimum(pos_j, len(ids) - 1)] != dst):
        raise GraphError("poses do not cover every edge's endpoints")
    deltas = np.array([e.delta for e in edges], dtype=np.float64).reshape(-1, 3)
    return poses[order[pos_i]], poses[order[pos_j]], deltas


def edge_errors(graph: PoseGraph, ids: np.ndarray, poses: np.ndarray,
                edges: list[Edge] | None = None) -> np.ndarray:
    """Each edge's error ``(M, 3)`` (m, m, rad) at ``poses`` (aligned with ``ids``): the
    measured delta's inverse composed with the estimated relative pose."""
    edges = graph.edges if edges is None else edges
    if not edges:
        return np.zeros((0, 3))
    pi, pj, d = _endpoints(graph, ids, poses, edges)
    return compose(inverse(d), compose(inverse(pi), pj))


def edge_chi2(graph: PoseGraph, ids: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """``e^T I e`` of every edge, ``(M,)``, dimensionless."""
    err = edge_errors(graph, ids, poses)
    info = np.array([e.information for e in graph.edges]).reshape(-1, 3, 3)
    return np.einsum("mi,mij,mj->m", err, info, err)


def chi2(graph: PoseGraph, ids: np.ndarray, poses: np.ndarray) -> float:
    """The full-information objective ``sum_edges e^T I e`` (twice GTSAM's graph error)."""
    return float(np.sum(edge_chi2(graph, ids, poses)))


def isotropic_objective(graph: PoseGraph, ids: np.ndarray, poses: np.ndarray) -> float:
    """The SE-Sync objective of data/README.md at ``poses`` (aligned with ``ids``)."""
    edges = graph.edges
    if not edges:
        return 0.0
    pi, pj, d = _endpoints(graph, ids, poses, edges)
    w = np.array([isotropic_weights(e.information) for e in edges])
    c, s = np.cos(pi[:, 2]), np.sin(pi[:, 2])
    rt = np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]], axis=1)
    t_err = pj[:, :2] - pi[:, :2] - rt
    yaw_err = wrap_angle(pj[:, 2] - pi[:, 2] - d[:, 2])
    return float(np.sum(w[:, 0] * 4.0 * (1.0 - np.cos(yaw_err)) + w[:, 1] * np.sum(t_err**2, axis=1)))


def chain_poses(ids: Iterable[int], edges: list[Edge]) -> dict[int, np.ndarray]:
    """Initial poses for vertices ``ids`` from the edges alone (g2o files without VERTEX lines).

    The smallest id sits at the origin; odometry edges are composed along the chain (either
    direction), then any edge from an initialised vertex reaches the rest (a spanning tree
    that prefers odometry). A vertex no edge reaches is a GraphError.
    """
    todo = sorted(set(int(k) for k in ids))
    if not todo:
        return {}
    known: dict[int, np.ndarray] = {todo[0]: np.zeros(3)}
    ordered = sorted((e for e in edges if e.kind == "odometry"), key=lambda e: min(e.from_id, e.to_id))
    ordered += [e for e in edges if e.kind != "odometry"]
    progress = True
    while progress and len(known) < len(todo):
        progress = False
        for e in ordered:
            a, b = e.from_id, e.to_id
            if a in known and b not in known:
                known[b] = compose(known[a], e.delta)
                progress = True
            elif b in known and a not in known:
                known[a] = compose(known[b], inverse(e.delta))
                progress = True
    missing = [k for k in todo if k not in known]
    if missing:
        raise GraphError(f"vertex {missing[0]} is not connected to vertex {todo[0]} by any edge "
                         f"({len(missing)} unreachable vertices)")
    return known
