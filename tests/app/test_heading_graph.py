"""The forward stage's heading graph solves the yaw part of the pose graph's links exactly,
and stays bounded as the map grows: links among the last ``window`` keyframes are solved,
wholly older ones forgotten (robotd.app.stages.forward_loops.HeadingGraph)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.app.stages.forward_loops import HeadingGraph, tree_yaws
from robotd.base.messages import Link


def _feed(g: HeadingGraph, n: int, lap: int, seed: int = 0) -> list[tuple[int, int, float, float]]:
    """A chain of ``n`` keyframes turning 0.01 rad each, with loops to the same place of the
    earlier laps; returns the links ``(from, to, dyaw, variance)``."""
    rng = np.random.default_rng(seed)
    out = []
    g.add_keyframe(0, 0.0, 0.0)
    for k in range(1, n):
        d = 0.01 + rng.normal(0.0, 1e-3)
        g.add_link(Link("odometry", k - 1, k, np.array([0.1, 0.0, d]), np.diag([1e4, 1e4, 1e4])))
        out.append((k - 1, k, d, 1e-4))
        if k >= lap and k % 3 == 0:
            old = k - lap
            dy = math.remainder(0.01 * lap + rng.normal(0.0, 3e-3), math.tau)
            g.add_link(Link("loop", old, k, np.array([0.0, 0.0, dy]), np.diag([1e4, 1e4, 1e5])))
            out.append((old, k, dy, 1e-5))
        g.add_link(Link("loop", k - 1, k, np.zeros(3), np.eye(3), source="forward"))  # never taken
        g.add_keyframe(k, 0.01 * k, 1e-4 * k)
    return out


def _dense(links: list[tuple[int, int, float, float]], a: int, b: int) -> tuple[float, float]:
    """The weighted least squares of the yaws, unwrapped about the true turn (0.01 rad per keyframe)."""
    nodes = sorted({i for e in links for i in e[:2]})
    idx = {v: i for i, v in enumerate(nodes)}
    y0 = 0.01 * np.array(nodes, float)
    h, g = np.zeros((len(nodes), len(nodes))), np.zeros(len(nodes))
    for f, t, d, v in links:
        i, j = idx[f], idx[t]
        r = math.remainder(d - (y0[j] - y0[i]), math.tau)
        h[i, i] += 1 / v; h[j, j] += 1 / v; h[i, j] -= 1 / v; h[j, i] -= 1 / v  # noqa: E702
        g[j] += r / v; g[i] -= r / v  # noqa: E702
    free = [i for i in range(len(nodes)) if i != idx[a]]
    cov = np.linalg.inv(h[np.ix_(free, free)])
    dy = np.zeros(len(nodes))
    dy[free] = cov @ g[free]
    jb = free.index(idx[b])
    return math.remainder(y0[idx[b]] + dy[idx[b]] - y0[idx[a]], math.tau), math.sqrt(cov[jb, jb])


def test_inside_its_window_it_is_the_exact_least_squares():
    g = HeadingGraph(window=2000)
    links = _feed(g, 400, lap=150)
    for a, b in [(5, 390), (150, 399), (0, 1)]:
        got = g.relative(a, b)
        assert got is not None
        want = _dense(links, a, b)
        assert got[0] == pytest.approx(want[0], abs=1e-9) and got[1] == pytest.approx(want[1], rel=1e-6)


def test_both_orderings_of_the_solve_give_the_exact_least_squares():
    new, old = HeadingGraph(), HeadingGraph(ordering="COLAMD")
    links = _feed(new, 400, lap=150)
    _feed(old, 400, lap=150)
    for a, b in [(5, 390), (150, 399), (37, 211)]:
        got, before, want = new.relative(a, b), old.relative(a, b), _dense(links, a, b)
        assert got is not None and before is not None
        assert got[0] == pytest.approx(want[0], abs=1e-9) and got[1] == pytest.approx(want[1], rel=1e-6)
        assert got[0] == pytest.approx(before[0], abs=1e-12) and got[1] == pytest.approx(before[1], rel=1e-9)


def test_a_keyframe_the_links_have_not_reached_is_joined_by_the_odometry():
    g = HeadingGraph()
    _feed(g, 50, lap=1000)
    g.add_keyframe(60, 0.7, 1e-4 * 49 + 4e-4)  # 0.21 rad on from keyframe 49 (odometry yaw 0.49), 0.02 sigma
    yaw, sigma = g.relative(49, 60)
    assert yaw == pytest.approx(0.21) and sigma == pytest.approx(0.02)


def test_it_keeps_a_bounded_number_of_links_and_answers_within_its_window_only():
    g = HeadingGraph(window=100)
    _feed(g, 3000, lap=60)
    assert len(g) > 3900  # every link counted ...
    assert g._n <= 2 * 100 * 2 + 1024 + 64  # ... but only those of the last two windows (and a block) held
    assert len(g._odom) <= 4 * 100 + 1
    assert g.relative(2999 - 150, 2999) is None  # beyond the window: no graph heading
    got = g.relative(2999 - 90, 2999)
    assert got is not None and got[0] == pytest.approx(math.remainder(0.9, math.tau), abs=0.02)


def _tree_yaws_before(fi, ti, d, order, pred, nn):
    """The spanning tree's yaws as the graph computed them before (a dictionary of every
    link both ways, first link wins): the frozen reference of :func:`tree_yaws`."""
    step: dict[tuple[int, int], float] = {}
    for x, y, dd in zip(fi.tolist(), ti.tolist(), d.tolist()):
        step.setdefault((x, y), dd)
        step.setdefault((y, x), -dd)
    y0 = np.zeros(nn)
    for u in order[1:].tolist():
        p = int(pred[u])
        y0[u] = y0[p] + step[(p, u)]
    return y0


def test_the_tree_yaws_are_those_of_the_dictionary_before_to_the_bit():
    import scipy.sparse as sp
    from scipy.sparse.csgraph import breadth_first_order

    from robotd.app.stages.forward_loops import tree_yaws

    rng = np.random.default_rng(3)
    for nn, m in [(2, 1), (30, 80), (400, 1500)]:
        fi, ti = rng.integers(0, nn, m), rng.integers(0, nn, m)
        fi[: nn - 1], ti[: nn - 1] = np.arange(nn - 1), np.arange(1, nn)  # connected
        swap = rng.random(m) < 0.3  # links both ways, repeated pairs with other yaws
        fi[swap], ti[swap] = ti[swap].copy(), fi[swap].copy()
        d = rng.normal(0.0, 1.0, m)
        adj = sp.coo_matrix((np.ones(m), (fi, ti)), shape=(nn, nn)).tocsr()
        root = int(rng.integers(0, nn))
        order, pred = breadth_first_order((adj + adj.T).tocsr(), root, directed=False, return_predecessors=True)
        got, want = tree_yaws(fi, ti, d, order, pred, nn), _tree_yaws_before(fi, ti, d, order, pred, nn)
        assert got[root] == 0.0 and np.array_equal(got, want)

def _relative_before(self: HeadingGraph, a: int, b: int, upto: int | None = None) -> tuple[float, float] | None:
    """``HeadingGraph.relative`` as it was before its solve was cut (the frozen reference
    of the part that changed: the adjacency added to its transpose, the components found
    apart, the gradient by ``np.add.at``; the links gathered and the step after the
    gradient are the class's own, which the cut did not touch)."""
    links = self._links(a, b, upto)
    if links is None:
        return None
    nodes, fi, ti, d, w, ia, ib = links
    import scipy.sparse as sp
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    nn = len(nodes)
    adj = sp.coo_matrix((np.ones(len(fi)), (fi, ti)), shape=(nn, nn)).tocsr()
    _, comp = connected_components(adj, directed=False)
    if comp[ia] != comp[ib]:
        return None
    keep = comp == comp[ia]
    sym = (adj + adj.T).tocsr()
    order, pred = breadth_first_order(sym, ia, directed=False, return_predecessors=True)
    y0 = tree_yaws(fi, ti, d, order, pred, nn)
    ok = keep[fi] & keep[ti]
    fi, ti, d, w = fi[ok], ti[ok], d[ok], w[ok]
    r = np.remainder(d - (y0[ti] - y0[fi]) + math.pi, math.tau) - math.pi
    g = np.zeros(nn)
    np.add.at(g, ti, w * r)
    np.add.at(g, fi, -w * r)
    return self._step(fi, ti, w, g, y0, keep, ia, ib)


@pytest.mark.parametrize("seed", range(4))
def test_the_solve_gives_the_headings_and_sigmas_before_to_the_bit(seed):
    """The solve with the components read from the tree's search and the gradient by one
    ``bincount`` against the solve before it (:func:`_relative_before`): the same headings
    and sigmas to the bit, the same None outside a's component or the window."""
    rng = np.random.default_rng(seed)
    g = HeadingGraph(window=300)
    _feed(g, 700, lap=120 + 7 * seed, seed=seed)
    for k in range(700, 720, 3):  # a part the links do not join: its own component
        g.add_link(Link("odometry", k, k + 1, np.array([0.1, 0.0, 0.02]), np.diag([1e4, 1e4, 1e4])))
    g.add_keyframe(730, 7.3, 0.08)  # joined by the odometry only
    pairs = [(int(a), int(b)) for a, b in rng.integers(350, 700, (25, 2))]
    pairs += [(650, 730), (690, 701), (703, 704), (701, 710), (400, 699), (699, 699), (10, 699)]
    answered = 0
    for a, b in pairs:
        for upto in (None, len(g) - 50):
            got, want = g.relative(a, b, upto), _relative_before(g, a, b, upto)
            assert (got is None) == (want is None), (a, b, upto)
            if got is not None:
                answered += 1
                assert got[0].hex() == want[0].hex() and got[1].hex() == want[1].hex(), (a, b, upto)
    assert answered >= 40
    assert g.relative(690, 701) is None and g.relative(703, 704) is not None


def test_a_keyframe_s_further_views_are_answered_from_its_solve_as_a_new_solve_answers():
    """The stage asks once per view of a forward keyframe, all against that keyframe with the
    same links: the second and later answers come from the first's solve (one more
    back-substitution) and equal a new solve's to rounding; the first is the new solve's
    to the bit. A keyframe outside the solve's component, an unlinked one and another
    newer keyframe or link count are solved anew."""
    g = HeadingGraph()
    links = _feed(g, 400, lap=150)
    g.add_keyframe(420, 0.3, 1e-4 * 420)  # not yet linked: joined by the odometry
    upto = len(g)
    for b in (399, 420):
        answers = [g.relative(a, b, upto=upto) for a in (5, 150, 37, 211, 398)]
        assert g._key is not None and g._key[0] == b
        for a, got in zip((5, 150, 37, 211, 398), answers):
            g._last = None  # a new solve
            want = g.relative(a, b, upto=upto)
            assert got is not None and want is not None
            assert got[0] == pytest.approx(want[0], abs=1e-12) and got[1] == pytest.approx(want[1], rel=1e-9)
            if b == 399:
                exact = _dense(links, a, b)
                assert got[0] == pytest.approx(exact[0], abs=1e-9) and got[1] == pytest.approx(exact[1], rel=1e-6)
    first = g.relative(5, 399, upto=upto)
    g._last = None
    assert first == g.relative(5, 399, upto=upto)
    g.relative(5, 399, upto=upto)
    assert g.relative(7, 399, upto=upto - 1) is not None and g._key[2] == upto - 1 - g._dropped  # other links: anew
    assert g.relative(1000, 399, upto=upto) is None  # not a node of the solve, not in the graph
