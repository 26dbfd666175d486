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

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Literal, overload

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

    Stored as a few growing arrays (poses ``(N, 3)``, edge ends, deltas and informations),
    about 150 bytes per keyframe and 120 per edge, not a Python object per pose and edge
    (a long map's graph held 10 MB so at 10,000 keyframes); :attr:`edges` builds the
    :class:`Edge` objects when asked.
    """

    def __init__(self) -> None:
        self._row: dict[int, int] = {}  # vertex id -> row of _pose
        self._pose = np.zeros((0, 3))
        self._ends = np.zeros((0, 2), np.int64)  # per edge: from_id, to_id
        self._delta = np.zeros((0, 3))
        self._info = np.zeros((0, 3, 3))
        self._loop = np.zeros(0, bool)  # per edge: kind == "loop"
        self._n_edges = 0
        self._fixed: set[int] = set()

    def add_pose(self, keyframe_id: int, pose: Iterable[float]) -> None:
        """Add vertex ``keyframe_id`` at ``pose`` ``(x_m, y_m, yaw_rad)``; a duplicate
        id is a GraphError."""
        kid = int(keyframe_id)
        if kid < 0:
            raise GraphError(f"vertex id must be non-negative, got {kid}")
        if kid in self._row:
            raise GraphError(f"duplicate vertex {kid}")
        p = _triple(pose, f"pose of vertex {kid}")
        row = len(self._row)
        if row == len(self._pose):
            self._pose = _grown(self._pose, row)
        self._pose[row] = p
        self._row[kid] = row

    def set_pose(self, keyframe_id: int, pose: Iterable[float]) -> None:
        """Replace the initial guess of an existing vertex."""
        if int(keyframe_id) not in self._row:
            raise GraphError(f"no vertex {keyframe_id}")
        self._pose[self._row[int(keyframe_id)]] = _triple(pose, f"pose of vertex {keyframe_id}")

    def add_edge(self, from_id: int, to_id: int, delta: Iterable[float],
                 information: np.ndarray | Iterable[Iterable[float]], kind: EdgeKind) -> Edge:
        """Add an edge between two existing vertices; returns it."""
        edge = self.check_edge(from_id, to_id, delta, information, kind)
        self._append(edge)
        return edge

    def check_edge(self, from_id: int, to_id: int, delta: Iterable[float],
                   information: np.ndarray | Iterable[Iterable[float]], kind: EdgeKind) -> Edge:
        """The edge :meth:`add_edge` would add (the same GraphErrors), not added."""
        a, b = int(from_id), int(to_id)
        for kid in (a, b):
            if kid not in self._row:
                raise GraphError(f"edge {a} -> {b}: no vertex {kid}")
        return make_edge(a, b, delta, information, kind)

    def add_edges(self, edges: Iterable[Edge]) -> None:
        """Add already-checked edges (from :func:`make_edge`) between existing vertices."""
        for e in edges:
            for kid in (e.from_id, e.to_id):
                if kid not in self._row:
                    raise GraphError(f"edge {e.from_id} -> {e.to_id}: no vertex {kid}")
            self._append(e)

    def _append(self, e: Edge) -> None:
        n = self._n_edges
        if n == len(self._ends):
            self._ends, self._delta, self._info, self._loop = (
                _grown(self._ends, n), _grown(self._delta, n), _grown(self._info, n), _grown(self._loop, n))
        self._ends[n] = (e.from_id, e.to_id)
        self._delta[n] = e.delta
        self._info[n] = e.information
        self._loop[n] = e.kind == "loop"
        self._n_edges = n + 1

    def fix(self, keyframe_id: int) -> None:
        """Hold vertex ``keyframe_id`` at its pose (a prior); without any fixed vertex the
        optimisers anchor the smallest id."""
        if int(keyframe_id) not in self._row:
            raise GraphError(f"cannot fix vertex {keyframe_id}: no such vertex")
        self._fixed.add(int(keyframe_id))

    def unfix(self, keyframe_id: int) -> None:
        """Let vertex ``keyframe_id`` move again (a relocalised trajectory's first keyframe,
        now held by its loops to the map instead)."""
        self._fixed.discard(int(keyframe_id))

    @property
    def ids(self) -> np.ndarray:
        """Vertex ids in increasing order, ``(N,) int64``."""
        return np.array(sorted(self._row), dtype=np.int64)

    def poses(self) -> np.ndarray:
        """Initial poses in :attr:`ids` order, ``(N, 3) float64`` (m, m, rad)."""
        rows = [self._row[k] for k in sorted(self._row)]
        return self._pose[np.array(rows, dtype=np.int64)].reshape(-1, 3)

    def pose(self, keyframe_id: int) -> np.ndarray:
        """The initial pose of one vertex, ``(3,)`` (read-only; KeyError if there is none)."""
        p = self._pose[self._row[int(keyframe_id)]].copy()
        p.setflags(write=False)
        return p

    def __contains__(self, keyframe_id: object) -> bool:
        return keyframe_id in self._row

    def __len__(self) -> int:
        return len(self._row)

    @property
    def edges(self) -> EdgeList:
        """Every edge in insertion order, as they are now: a sequence whose :class:`Edge`
        objects are built as they are read (edges added later are not in it)."""
        n = self._n_edges
        return EdgeList(self._ends, self._delta, self._info, self._loop, n)

    def edge_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every edge as arrays, in insertion order: ``from_id (M,) int64``, ``to_id (M,)
        int64``, deltas ``(M, 3)`` and informations ``(M, 3, 3)`` (read-only views)."""
        n = self._n_edges
        out = (self._ends[:n, 0], self._ends[:n, 1], self._delta[:n], self._info[:n])
        for a in out:
            a.flags.writeable = False
        return out

    @property
    def edge_count(self) -> int:
        """How many edges the graph holds (without building them)."""
        return self._n_edges

    @property
    def is_loop(self) -> np.ndarray:
        """Per edge, in insertion order, whether it is a loop: ``(M,) bool`` (a copy)."""
        return self._loop[:self._n_edges].copy()

    @property
    def loop_count(self) -> int:
        """How many of the edges are loops."""
        return int(np.count_nonzero(self._loop[:self._n_edges]))

    @property
    def fixed(self) -> frozenset[int]:
        return frozenset(self._fixed)

    def components(self) -> list[list[int]]:
        """Connected components (vertex ids, each sorted), ordered by their smallest id."""
        parent = {k: k for k in self._row}

        def root(k: int) -> int:
            while parent[k] != k:
                parent[k] = parent[parent[k]]
                k = parent[k]
            return k

        for a, b in self._ends[:self._n_edges].tolist():
            ra, rb = root(a), root(b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
        groups: dict[int, list[int]] = {}
        for k in sorted(self._row):
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
        n = self._n_edges
        out._ends, out._delta, out._info, out._loop = (
            self._ends[:n].copy(), self._delta[:n].copy(), self._info[:n].copy(), self._loop[:n].copy())
        out._n_edges = n
        out._fixed = set(self._fixed)
        return out

    def without_edges(self) -> PoseGraph:
        """A copy with the same poses and fixed set and no edge."""
        out = PoseGraph()
        out._row, out._pose = dict(self._row), self._pose[:len(self._row)].copy()
        out._fixed = set(self._fixed)
        return out


class EdgeList(Sequence[Edge]):
    """:attr:`PoseGraph.edges`: the first ``n`` rows of the graph's edge arrays as
    :class:`Edge` objects (read-only copies of each delta and information), built on
    indexing and iteration. The graph only appends rows, and a grown array is a new one,
    so the rows stay what they were when it was made."""

    __slots__ = ("_ends", "_delta", "_info", "_loop", "_n")

    def __init__(self, ends: np.ndarray, delta: np.ndarray, info: np.ndarray, loop: np.ndarray, n: int) -> None:
        self._ends, self._delta, self._info, self._loop, self._n = ends, delta, info, loop, n

    def __len__(self) -> int:
        return self._n

    def _edge(self, i: int) -> Edge:
        d, info = self._delta[i].copy(), self._info[i].copy()
        d.setflags(write=False)
        info.setflags(write=False)
        a, b = self._ends[i].tolist()
        return Edge(a, b, d, info, "loop" if self._loop[i] else "odometry")

    @overload
    def __getitem__(self, i: int) -> Edge: ...

    @overload
    def __getitem__(self, i: slice) -> list[Edge]: ...

    def __getitem__(self, i: int | slice) -> Edge | list[Edge]:
        if isinstance(i, slice):
            return [self._edge(k) for k in range(*i.indices(self._n))]
        k = int(i) + self._n if int(i) < 0 else int(i)
        if not 0 <= k < self._n:
            raise IndexError(f"edge {i} of {self._n}")
        return self._edge(k)

    def __iter__(self) -> Iterator[Edge]:
        for k in range(self._n):
            yield self._edge(k)


def _grown(a: np.ndarray, used: int) -> np.ndarray:
    """``a`` with room for at least one more row (capacity doubled, 64 at least)."""
    out = np.zeros((max(64, 2 * used),) + a.shape[1:], a.dtype)
    out[:used] = a[:used]
    return out


def isotropic_weights(information: np.ndarray) -> tuple[float, float]:
    """SE-Sync's ``(kappa, tau)`` of one edge: ``kappa = I33`` (1/rad^2) and
    ``tau = 2 / trace(inv(I[:2, :2]))`` (1/m^2)."""
    info = np.asarray(information, dtype=float)
    return float(info[2, 2]), float(2.0 / np.trace(np.linalg.inv(info[:2, :2])))


def isotropic_graph(graph: PoseGraph) -> PoseGraph:
    """The same graph with each edge's information replaced by ``diag(tau, tau, 2 kappa)``
    (see the module docstring for why 2 kappa)."""
    out = graph.without_edges()
    for e in graph.edges:
        kappa, tau = isotropic_weights(e.information)
        out.add_edge(e.from_id, e.to_id, e.delta, np.diag([tau, tau, 2.0 * kappa]), e.kind)
    return out


def _endpoints(ids: np.ndarray, poses: np.ndarray, src: np.ndarray, dst: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    ids = np.asarray(ids, dtype=np.int64)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    order = np.argsort(ids)
    sorted_ids = ids[order]
    pos_i = np.searchsorted(sorted_ids, src)
    pos_j = np.searchsorted(sorted_ids, dst)
    if np.any(pos_i >= len(ids)) or np.any(pos_j >= len(ids)) or \
            np.any(sorted_ids[np.minimum(pos_i, len(ids) - 1)] != src) or \
            np.any(sorted_ids[np.minimum(pos_j, len(ids) - 1)] != dst):
        raise GraphError("poses do not cover every edge's endpoints")
    return poses[order[pos_i]], poses[order[pos_j]]


def _edge_arrays(graph: PoseGraph, edges: Sequence[Edge] | None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(src (M,), dst (M,), deltas (M, 3), informations (M, 3, 3))`` of ``edges``, or of
    every edge of ``graph`` (read from its arrays, no :class:`Edge` built)."""
    if edges is None:
        return graph.edge_arrays()
    src = np.array([e.from_id for e in edges], dtype=np.int64)
    dst = np.array([e.to_id for e in edges], dtype=np.int64)
    deltas = np.array([e.delta for e in edges], dtype=np.float64).reshape(-1, 3)
    info = np.array([e.information for e in edges], dtype=np.float64).reshape(-1, 3, 3)
    return src, dst, deltas, info


def edge_errors(graph: PoseGraph, ids: np.ndarray, poses: np.ndarray,
                edges: Sequence[Edge] | None = None) -> np.ndarray:
    """Each edge's error ``(M, 3)`` (m, m, rad) at ``poses`` (aligned with ``ids``): the
    measured delta's inverse composed with the estimated relative pose."""
    src, dst, d, _info = _edge_arrays(graph, edges)
    if not len(src):
        return np.zeros((0, 3))
    pi, pj = _endpoints(ids, poses, src, dst)
    return compose(inverse(d), compose(inverse(pi), pj))


def edge_chi2(graph: PoseGraph, ids: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """``e^T I e`` of every edge, ``(M,)``, dimensionless."""
    err = edge_errors(graph, ids, poses)
    info = graph.edge_arrays()[3]
    return np.einsum("mi,mij,mj->m", err, info, err)


def chi2(graph: PoseGraph, ids: np.ndarray, poses: np.ndarray) -> float:
    """The full-information objective ``sum_edges e^T I e`` (twice GTSAM's graph error)."""
    return float(np.sum(edge_chi2(graph, ids, poses)))


def isotropic_objective(graph: PoseGraph, ids: np.ndarray, poses: np.ndarray) -> float:
    """The SE-Sync objective of data/README.md at ``poses`` (aligned with ``ids``)."""
    src, dst, d, info = graph.edge_arrays()
    if not len(src):
        return 0.0
    pi, pj = _endpoints(ids, poses, src, dst)
    w = np.array([isotropic_weights(i) for i in info])
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
