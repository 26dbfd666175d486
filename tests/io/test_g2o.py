"""g2o files: round trips, chaining of vertex-less files, and errors that name the line."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robotd.base.errors import GraphError
from robotd.graph import PoseGraph
from robotd.io.g2o import format_g2o, parse_g2o, read_g2o, write_g2o
from tests.shared_data import require

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "posegraphs"

TEXT = """\
# a comment line
VERTEX_SE2 2 0 0 0
VERTEX_SE2 5 1.5 0 0.1   # trailing comment

VERTEX_SE2 9 3 0.25 -0.2
EDGE_SE2 2 5 1.5 0 0.1 1e12 0 0 1e12 0 1e12
EDGE_SE2 5 9 1.5 0.25 -0.3 100 1 0 100 0 400
EDGE_SE2 9 2 -3 0 0.2 50 0 0 50 0 200
FIX 2
"""


def test_parse_reads_vertices_edges_fix_and_kinds():
    g = parse_g2o(TEXT.splitlines())
    assert list(g.ids) == [2, 5, 9]
    assert np.allclose(g.pose(9), (3, 0.25, -0.2))
    kinds = [(e.from_id, e.to_id, e.kind) for e in g.edges]
    assert kinds == [(2, 5, "odometry"), (5, 9, "odometry"), (9, 2, "loop")]
    assert g.edges[0].information[0, 0] == 1e12
    assert g.edges[1].information[0, 1] == g.edges[1].information[1, 0] == 1.0
    assert g.fixed == {2}


def test_write_then_read_gives_the_same_graph(tmp_path: Path):
    g = parse_g2o(TEXT.splitlines())
    poses = g.poses() + np.array([0.1, -0.2, 0.3]) / 3.0
    path = tmp_path / "out.g2o"
    write_g2o(path, g, poses)
    back = read_g2o(path)
    assert np.array_equal(back.ids, g.ids)
    assert np.array_equal(back.poses(), poses)
    assert back.fixed == g.fixed
    for a, b in zip(g.edges, back.edges):
        assert (a.from_id, a.to_id, a.kind) == (b.from_id, b.to_id, b.kind)
        assert np.array_equal(a.delta, b.delta) and np.array_equal(a.information, b.information)


def test_edges_without_vertices_are_chained_from_the_smallest_id():
    text = ("EDGE_SE2 10 11 1 0 1.5707963267948966 1 0 0 1 0 1\n"
            "EDGE_SE2 11 13 1 0 0 1 0 0 1 0 1\n"
            "EDGE_SE2 13 10 0 1 0 1 0 0 1 0 1\n")
    g = parse_g2o(text.splitlines())
    assert list(g.ids) == [10, 11, 13]
    assert np.allclose(g.poses(), [[0, 0, 0], [1, 0, math.pi / 2], [1, 1, math.pi / 2]])
    assert [e.kind for e in g.edges] == ["odometry", "odometry", "loop"]


@pytest.mark.parametrize("text, message", [
    ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 3 1 0 0 1 0 0 1 0 1\n", r"<g2o>:2: edge 0 -> 3 refers to vertex 3"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1\n",
     r"<g2o>:3: .*not positive definite"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0\n", r"<g2o>:2: VERTEX_SE2 needs 4 values, got 3 \(truncated\)"),
    ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0\n", r"<g2o>:1: EDGE_SE2 needs 11 values, got 10 \(truncated\)"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n", r"<g2o>:2: duplicate vertex 0 \(first on line 1\)"),
    ("VERTEX_SE2 0 0 x 0\n", r"<g2o>:1: 'x' is not a number"),
    ("VERTEX_SE2 0.5 0 0 0\n", r"<g2o>:1: '0.5' is not a vertex id"),
    ("VERTEX_SE2 0 0 nan 0\n", r"<g2o>:1: non-finite value"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n", r"<g2o>:1: unsupported record 'VERTEX_SE3:QUAT'"),
    ("VERTEX_SE2 0 0 0 0\nFIX 4\n", r"<g2o>:2: FIX of vertex 4"),
    ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 5 6 1 0 0 1 0 0 1 0 1\n", r"vertex 5 is not connected"),
])
def test_malformed_files_name_the_line(text, message):
    with pytest.raises(GraphError, match=message):
        parse_g2o(text.splitlines())


def test_read_names_the_file(tmp_path: Path):
    path = tmp_path / "bad.g2o"
    path.write_text("VERTEX_SE2 0 0 0\n")
    with pytest.raises(GraphError, match=f"{path}:1:"):
        read_g2o(path)
    with pytest.raises(GraphError, match="cannot read"):
        read_g2o(tmp_path / "absent.g2o")


def test_shared_benchmark_files_read_with_chained_vertices():
    path = require(SHARED / "CSAIL.g2o", "shared benchmark graph")
    g = read_g2o(path)
    assert len(g) == 1045 and len(g.edges) == 1172
    assert sum(e.kind == "loop" for e in g.edges) == 1172 - 1044
    back = parse_g2o(format_g2o(g).splitlines())
    assert np.array_equal(back.poses(), g.poses())


_token = st.one_of(
    st.sampled_from(["VERTEX_SE2", "EDGE_SE2", "FIX", "#", "nan", "1e12", "-1", "0", "1", "2"]),
    st.integers(-3, 5).map(str), st.floats(allow_nan=False, width=32).map(repr),
    st.text(alphabet="abcxyz_.#-eE0123456789", min_size=1, max_size=6),
)
_line = st.lists(_token, max_size=13).map(" ".join)


@settings(max_examples=300, deadline=None)
@given(st.lists(_line, max_size=8))
def test_fuzzed_input_parses_or_raises_graph_error(lines):
    try:
        g = parse_g2o(lines)
    except GraphError:
        return
    assert isinstance(g, PoseGraph)
    assert len(g.poses()) == len(g.ids)
