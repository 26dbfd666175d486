"""g2o 2D pose-graph files: read and write ``VERTEX_SE2``, ``EDGE_SE2`` and ``FIX``.

Lines (whitespace-separated, ``#`` starts a comment, blank lines ignored)::

    VERTEX_SE2 id x_m y_m yaw_rad
    EDGE_SE2 i j dx_m dy_m dyaw_rad I11 I12 I13 I22 I23 I33
    FIX id [id ...]

The edge's information matrix is given by its upper triangle. Any other record, a missing
or extra field, a non-number, a non-finite value, a duplicate vertex, an edge to a vertex
without a ``VERTEX_SE2`` line (when the file has any), a ``FIX`` of an unknown vertex or an
information matrix that is not positive definite is a :class:`GraphError` naming the file
and line; nothing is skipped silently.

Files with edges but no vertices (the SE-Sync benchmark files) get their initial poses by
chaining: the smallest id at the origin, then odometry edges composed along the id order,
then loop edges for any vertex the chain does not reach (:func:`robotd.graph.chain_poses`);
a vertex no edge reaches is an error. An edge is odometry when it joins two vertices
adjacent in id order (the first such edge per pair; ids need not be consecutive) and a
loop otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from robotd.base.errors import GraphError
from robotd.base.files import write_text_replacing
from robotd.graph import PoseGraph, chain_poses, make_edge
from robotd.graph.model import Edge


MAX_VERTEX_ID = 2**63 - 1
"""The largest vertex id read (the map store's and numpy's signed 64-bit integers)."""


def _numbers(parts: list[str], where: str, kinds: str) -> list[float]:
    """Parse ``parts`` as ``kinds`` ('i' id, 'f' finite float), or raise naming ``where``."""
    out: list[float] = []
    for text, kind in zip(parts, kinds):
        try:
            if kind == "i":
                value: float = int(text)
                if value < 0:
                    raise GraphError(f"{where}: negative vertex id {text}")
                if value > MAX_VERTEX_ID:  # GTSAM keys are 64-bit; robotd's ids are signed 64-bit
                    raise GraphError(f"{where}: vertex id {text} is above the largest, 2^63 - 1")
            else:
                value = float(text)
                if not math.isfinite(value):
                    raise GraphError(f"{where}: non-finite value {text!r}")
        except ValueError:
            what = "vertex id" if kind == "i" else "number"
            raise GraphError(f"{where}: {text!r} is not a {what}") from None
        out.append(value)
    return out


def _expect(parts: list[str], count: int, where: str) -> None:
    if len(parts) != count:
        state = "truncated" if len(parts) < count else "too many fields"
        raise GraphError(f"{where}: {parts[0]} needs {count - 1} values, got {len(parts) - 1} ({state})")


def _information(upper: list[float]) -> np.ndarray:
    i11, i12, i13, i22, i23, i33 = upper
    return np.array([[i11, i12, i13], [i12, i22, i23], [i13, i23, i33]])


def parse_g2o(lines: Iterable[str], name: str = "<g2o>") -> PoseGraph:
    """Parse g2o text (one record per line) into a :class:`PoseGraph`; ``name`` labels errors."""
    vertices: dict[int, tuple[np.ndarray, int]] = {}
    raw_edges: list[tuple[int, int, list[float], int]] = []
    fixes: list[tuple[int, int]] = []
    for lineno, line in enumerate(lines, 1):
        where = f"{name}:{lineno}"
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        tag = parts[0]
        if tag == "VERTEX_SE2":
            _expect(parts, 5, where)
            vals = _numbers(parts[1:], where, "ifff")
            kid = int(vals[0])
            if kid in vertices:
                raise GraphError(f"{where}: duplicate vertex {kid} (first on line {vertices[kid][1]})")
            vertices[kid] = (np.array(vals[1:]), lineno)
        elif tag == "EDGE_SE2":
            _expect(parts, 12, where)
            vals = _numbers(parts[1:], where, "ii" + "f" * 9)
            raw_edges.append((int(vals[0]), int(vals[1]), vals[2:], lineno))
        elif tag == "FIX":
            if len(parts) < 2:
                raise GraphError(f"{where}: FIX needs at least one vertex id (truncated)")
            fixes += [(int(v), lineno) for v in _numbers(parts[1:], where, "i" * (len(parts) - 1))]
        else:
            raise GraphError(f"{where}: unsupported record {tag!r} (VERTEX_SE2, EDGE_SE2 or FIX)")
    return _assemble(vertices, raw_edges, fixes, name)


def _edge_kinds(ids: list[int], raw_edges: list[tuple[int, int, list[float], int]]) -> list[str]:
    """'odometry' for the first edge joining each pair of id-adjacent vertices, else 'loop'."""
    rank = {kid: n for n, kid in enumerate(ids)}
    seen: set[tuple[int, int]] = set()
    kinds = []
    for a, b, _, _ in raw_edges:
        pair = (min(a, b), max(a, b))
        if abs(rank[a] - rank[b]) == 1 and pair not in seen:
            seen.add(pair)
            kinds.append("odometry")
        else:
            kinds.append("loop")
    return kinds


def _assemble(vertices: dict[int, tuple[np.ndarray, int]],
              raw_edges: list[tuple[int, int, list[float], int]],
              fixes: list[tuple[int, int]], name: str) -> PoseGraph:
    if vertices:
        for a, b, _, lineno in raw_edges:
            for kid in (a, b):
                if kid not in vertices:
                    raise GraphError(f"{name}:{lineno}: edge {a} -> {b} refers to vertex {kid}, "
                                     f"which has no VERTEX_SE2 line")
    ids = sorted(vertices) if vertices else sorted({k for a, b, _, _ in raw_edges for k in (a, b)})
    kinds = _edge_kinds(ids, raw_edges)
    edges: list[Edge] = []
    for (a, b, vals, lineno), kind in zip(raw_edges, kinds):
        try:
            edges.append(make_edge(a, b, vals[:3], _information(vals[3:]), kind))  # type: ignore[arg-type]
        except GraphError as exc:
            raise GraphError(f"{name}:{lineno}: {exc}") from None
    if vertices:
        poses = {kid: p for kid, (p, _) in vertices.items()}
    else:
        try:
            poses = chain_poses(ids, edges)
        except GraphError as exc:
            raise GraphError(f"{name}: no VERTEX_SE2 lines, and {exc}") from None
    graph = PoseGraph()
    for kid in ids:
        graph.add_pose(kid, poses[kid])
    graph.add_edges(edges)
    for kid, lineno in fixes:
        if kid not in graph:
            raise GraphError(f"{name}:{lineno}: FIX of vertex {kid}, which does not exist")
        graph.fix(kid)
    return graph


def read_g2o(path: Path | str) -> PoseGraph:
    """Read a g2o 2D file (see the module docstring); GraphError names the file and line."""
    path = Path(path)
    try:
        with open(path, encoding="utf-8") as f:
            return parse_g2o(f, str(path))
    except UnicodeDecodeError as exc:
        raise GraphError(f"{path}: not a text file ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise GraphError(f"{path}: cannot read: {exc.strerror or exc}") from None


def format_g2o(graph: PoseGraph, poses: np.ndarray | None = None) -> str:
    """The graph as g2o text: every vertex (at ``poses`` ``(N, 3)`` in ``graph.ids`` order,
    or the graph's own), every edge, then one FIX line for the fixed vertices. Floats are
    written with 17 significant digits, so reading back gives the same numbers."""
    ids = graph.ids
    poses = graph.poses() if poses is None else np.asarray(poses, dtype=float).reshape(-1, 3)
    if len(poses) != len(ids):
        raise ValueError(f"poses must have {len(ids)} rows, got {len(poses)}")
    out = []
    for kid, p in zip(ids, poses):
        out.append(f"VERTEX_SE2 {kid} {p[0]:.17g} {p[1]:.17g} {p[2]:.17g}\n")
    for e in graph.edges:
        i = e.information
        nums = (*e.delta, i[0, 0], i[0, 1], i[0, 2], i[1, 1], i[1, 2], i[2, 2])
        out.append(f"EDGE_SE2 {e.from_id} {e.to_id} " + " ".join(f"{v:.17g}" for v in nums) + "\n")
    if graph.fixed:
        out.append("FIX " + " ".join(str(k) for k in sorted(graph.fixed)) + "\n")
    return "".join(out)


def write_g2o(path: Path | str, graph: PoseGraph, poses: np.ndarray | None = None) -> None:
    """Write :func:`format_g2o` to ``path``, replacing it atomically (a full disk or an
    interruption leaves the previous file as it was; :class:`OutputError`)."""
    write_text_replacing(Path(path), format_g2o(graph, poses), encoding="ascii")
