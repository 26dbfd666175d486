"""The live graph's decisions (robotd.graph.gate) as functions of its state: no store, no
pipeline; what it decides comes out through ``emit`` and ``joined_map``."""

from __future__ import annotations

import math

import numpy as np

from robotd.base.geometry import between, compose
from robotd.base.messages import CandidateFate, Link, LoopFate
from robotd.graph.gate import GatedGraph
from robotd.graph.incremental import IncrementalGraph

ODO_INFO = np.diag([1e6, 1e6, 5e4])
LOOP_INFO = np.diag([1 / 0.003 ** 2] * 3)


def _square(n: int) -> list[np.ndarray]:
    """True poses of a 1 m square (0.25 m steps, a quarter turn at each corner)."""
    steps = [np.array([0.25, 0.0, 0.0])] * 4 + [np.array([0.0, 0.0, math.pi / 2])]
    out = [np.zeros(3)]
    for k in range(n - 1):
        out.append(compose(out[-1], steps[k % 5]))
    return out


def _drive(g: GatedGraph, truth: list[np.ndarray], first_id: int = 1) -> list[int]:
    drift = np.array([0.0, 0.0, 0.004])
    odo = truth[0]
    ids = []
    for k, t in enumerate(truth):
        kid = first_id + k
        if k:
            step = between(truth[k - 1], t) + drift
            odo = compose(odo, step)
            g.odometry_link(kid - 1, kid, step, ODO_INFO)
        g.keyframe(kid, 7, odo, k * 10**9, lambda run: {})
        ids.append(kid)
    return ids


def test_the_gate_accepts_a_true_loop_refuses_a_lookalike_and_a_keyframe_outside_the_graph():
    emitted: list = []
    joined: list[int] = []
    g = GatedGraph(IncrementalGraph(), emitted.append, joined.append)
    truth = _square(21)
    ids = _drive(g, truth)
    assert joined == [7]  # an empty map: the run starts the map frame
    assert g.status_fragment() == "" and g.localised()
    g.floor_candidate(ids[0], ids[20], 200.0, between(truth[0], truth[20]), LOOP_INFO)
    g.floor_candidate(ids[2], ids[18], 190.0, between(truth[2], truth[18]) + [0.35, 0.0, 0.0], LOOP_INFO)
    g.floor_candidate(999, ids[18], 150.0, np.zeros(3), LOOP_INFO)
    fates = [(m.query_id, m.candidate_id, m.fate) for m in emitted if isinstance(m, CandidateFate)]
    assert fates == [(ids[20], ids[0], "accepted"), (ids[18], ids[2], "failed_gate"),
                     (ids[18], 999, "failed_gate")]
    [link] = [m for m in emitted if isinstance(m, Link)]
    assert (link.kind, link.from_id, link.to_id) == ("loop", ids[0], ids[20])
    refused = [m for m in emitted if isinstance(m, CandidateFate) and m.fate == "failed_gate"]
    chi2 = float(refused[0].detail.split()[1])
    assert chi2 > g.gate_chi2 and refused[1].detail.startswith("keyframe of an earlier run")
    c = g.counters()
    assert (c["loops_accepted"], c["loops_failed_gate"], c["loops_earlier_run"]) == (1, 1, 1)
    # A stricter gate (a live reload) refuses what the default let through.
    g.gate_chi2 = 1e-9
    g.floor_candidate(ids[1], ids[20], 200.0, between(truth[1], truth[20]), LOOP_INFO)
    assert emitted[-1].fate == "failed_gate"


def test_a_run_on_a_stored_map_is_not_localised_and_a_lift_makes_it_lost():
    emitted: list = []
    joined: list[int] = []
    g = GatedGraph(IncrementalGraph(), emitted.append, joined.append)
    g.keyframe(50, 3, np.zeros(3), 0, lambda run: {1: (np.array([1.0, 0.0, 0.0]), 1)})
    assert joined == [] and not g.localised()
    assert g.status_fragment() == "not localised in the stored map"
    g.wheel_drop(True, 10)
    assert g.status_fragment() == "LOST (lifted)" and g.counters()["lifts"] == 1
    g.wheel_drop(False, 20)
    assert g.status_fragment() == "LOST (relocalising)"
    assert g.end_warning().startswith("the run ended lost: its last 1 keyframes")


def _office_like(n: int) -> list[np.ndarray]:
    """True poses of a 6 x 3.75 m rectangle of 0.15 m steps (a quarter turn every 40 and
    25 steps), driven on past its start."""
    out = [np.zeros(3)]
    sides = [40, 25, 40, 25]
    turns = set(np.cumsum(sides * 3) - 1)
    for k in range(n - 1):
        out.append(compose(out[-1], np.array([0.15, 0.0, math.pi / 2 if k in turns else 0.0])))
    return out


def test_after_a_kidnapping_every_true_loop_passes_the_gate_and_a_look_alike_does_not():
    """A drive whose heading drifts, lifted and put down on ground it drove 110 steps
    before: the new segment relocalises against the run's own keyframes, then every true
    loop from it passes the gate, and a look-alike 8 cm off (a repeated floor print) is
    refused. Judged with the two poses' marginals alone, the relocalised segment's
    ``S`` carries the drift of the whole first segment twice and the look-alikes pass."""
    rng = np.random.default_rng(11)
    odo_sigma = np.array([0.002, 0.002, 0.004])
    odo_info = np.diag(1.0 / odo_sigma**2)
    loop_sigma = np.array([0.003, 0.003, 0.003])
    emitted: list = []
    g = GatedGraph(IncrementalGraph(), emitted.append, lambda run: None)
    truth = _office_like(150)
    odo = truth[0]
    for k, t in enumerate(truth):
        if k:
            step = between(truth[k - 1], t) + rng.normal(0.0, odo_sigma) + [0.0, 0.0, 0.002]
            odo = compose(odo, step)
            g.odometry_link(k - 1, k, step, odo_info)
        g.keyframe(k, 7, odo, k * 10**9, lambda run: {})
    g.wheel_drop(True, 150 * 10**9)
    g.wheel_drop(False, 155 * 10**9)
    first = 150
    put_down = truth[40:100]
    odo = np.array([4.0, -2.0, 1.0])  # the new segment's own frame: anywhere
    look_alikes = []
    for k, t in enumerate(put_down):
        kid = first + k
        if k:
            step = between(put_down[k - 1], t) + rng.normal(0.0, odo_sigma) + [0.0, 0.0, 0.002]
            odo = compose(odo, step)
            g.odometry_link(kid - 1, kid, step, odo_info)
        g.keyframe(kid, 7, odo, (156 + k) * 10**9, lambda run: {})
        old = 40 + k
        g.floor_candidate(old, kid, 200.0, between(truth[old], t) + rng.normal(0.0, loop_sigma),
                          np.diag(1.0 / loop_sigma**2))
        if k >= 10 and k % 5 == 0:
            off = 0.08 * np.array([math.cos(k), math.sin(k), 0.0])
            g.floor_candidate(old - 1, kid, 150.0, between(truth[old - 1], t) + off, np.diag(1.0 / loop_sigma**2))
            look_alikes.append((kid, old - 1))
    c = g.counters()
    assert (c["lifts"], c["relocalisations"], c["localised"]) == (1, 1, 1)
    fates = {(m.query_id, m.candidate_id): m.fate for m in emitted if isinstance(m, CandidateFate)}
    true_loops = [(first + k, 40 + k) for k in range(len(put_down))]
    assert [fates[q] for q in true_loops] == ["accepted"] * len(true_loops)
    assert [fates[q] for q in look_alikes] == ["failed_gate"] * len(look_alikes)
    assert c["loops_failed_gate"] == len(look_alikes) == 10


def test_a_forward_loop_without_a_range_is_gated_at_two_degrees_of_freedom():
    """A forward loop's edge takes its range from the graph's prediction: the innovation
    along the line of sight is zero, the statistic has 2 degrees of freedom, and the bound
    is the 2-dof point of the gate's probability (13.8 for 99.9 %). A bearing error whose
    statistic lies between 13.8 and 16.27 is refused; the same loop with a range measured
    on the floor is gated at 3 degrees of freedom."""
    from robotd.forward.planar import loop_edge
    from robotd.graph.gate import gate_threshold

    assert math.isclose(gate_threshold(16.27, 3), 16.27, rel_tol=1e-9)
    assert math.isclose(gate_threshold(16.27, 2), 13.82, abs_tol=0.01)
    g = GatedGraph(IncrementalGraph(), [].append, [].append)
    truth = _square(21)
    ids = _drive(g, truth)
    a, b = ids[1], ids[19]  # 0.25 m apart along x, the same heading
    rel = between(truth[1], truth[19])
    bearing = math.atan2(rel[1], rel[0])

    def d2(err: float, range_m: float | None) -> float:
        def edge(pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return loop_edge(pred, rel[2], bearing + err, range_m=range_m)
        delta, info = edge(between(g.graph.pose(a), g.graph.pose(b)))
        return g.graph.loop_chi2(a, b, delta, info)

    # the bearing error whose statistic is 15 (between the two bounds), by bisection
    lo, hi = 0.0, math.radians(60.0)
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if d2(mid, None) < 15.0 else (lo, mid)
    err = 0.5 * (lo + hi)
    assert 14.9 < d2(err, None) < 15.1
    emitted: list = []
    g._emit = emitted.append
    g.forward_candidate(a, b, 0.9, lambda pred: loop_edge(pred, rel[2], bearing + err))
    assert emitted[-1].fate == "failed_gate" and emitted[-1].detail.endswith("> 13.82")
    # Measured on the floor (the true range), 3 components: its statistic against 16.27.
    r = float(np.hypot(rel[0], rel[1]))
    g.forward_candidate(a, b, 0.9, lambda pred: loop_edge(pred, rel[2], bearing + err, range_m=r),
                        range_measured=True)
    expected = "accepted" if d2(err, r) <= 16.27 else "failed_gate"
    assert [m.fate for m in emitted if isinstance(m, CandidateFate)][-1] == expected


def test_a_forward_loop_on_a_ridge_no_heading_settled_is_refused_by_the_gate_but_a_right_one_is_taken():
    """Its motion is a point the inliers' noise picked on a heading-bearing ridge: the gate
    takes no such loop into the graph, however well it agrees (the same loop settled is
    accepted)."""
    from robotd.forward.planar import loop_edge

    emitted: list = []
    g = GatedGraph(IncrementalGraph(), emitted.append, [].append)
    truth = _square(21)
    ids = _drive(g, truth)
    a, b = ids[1], ids[19]
    rel = between(truth[1], truth[19])
    bearing = math.atan2(rel[1], rel[0])
    g.forward_candidate(a, b, 0.9, lambda pred: loop_edge(pred, rel[2], bearing, sigma_yaw_rad=math.radians(3.0)),
                        unsettled=True)
    fates = [m for m in emitted if isinstance(m, CandidateFate)]
    assert fates[-1].fate == "failed_gate" and "ridge" in fates[-1].detail
    assert g.counters()["forward_loops_failed_gate"] == 1 and g.counters()["forward_loops_accepted"] == 0
    g.forward_candidate(a, b, 0.9, lambda pred: loop_edge(pred, rel[2], bearing))
    assert [m for m in emitted if isinstance(m, CandidateFate)][-1].fate == "accepted"


def test_a_relocalisation_by_forward_loops_enters_the_graph_as_one_edge_with_the_fits_covariance():
    """Forward loops only relocalise a kidnapped segment: the group enters the graph as one
    edge (the fitted transform's pose of its earliest query, with the fit's covariance),
    none of its members as a loop edge or an accepted loop; a later loop to the same place
    is gated against the pose that edge gave."""
    from robotd.forward.planar import loop_edge
    from robotd.graph.gate import GROUP_MEMBER
    from robotd.graph.reloc import fit_transform

    rng = np.random.default_rng(5)
    emitted: list = []
    g = GatedGraph(IncrementalGraph(), emitted.append, [].append)
    truth = _square(21)
    ids = _drive(g, truth)
    g.wheel_drop(True, 21 * 10**9)
    g.wheel_drop(False, 25 * 10**9)
    after = _square(40)[27:]  # put down further round the square, its odometry in a frame of its own
    odo = np.array([3.0, -1.0, 0.7])
    new = []
    for k, t in enumerate(after):
        kid = 100 + k
        if k:
            step = between(after[k - 1], t)
            odo = compose(odo, step)
            g.odometry_link(kid - 1, kid, step, ODO_INFO)
        g.keyframe(kid, 7, odo, (26 + k) * 10**9, lambda run: {})
        new.append(kid)
    decisions = []
    offer = g._relocaliser.offer
    g._relocaliser.offer = lambda c: decisions.append(offer(c)) or decisions[-1]

    def forward(old: int, k: int, yaw_off: float = 0.0, bearing_off: float = 0.0, **kw) -> None:
        rel = between(truth[old], after[k])
        dyaw = rel[2] + rng.normal(0.0, math.radians(0.5)) + yaw_off
        bearing = math.atan2(rel[1], rel[0]) + rng.normal(0.0, math.radians(1.0)) + bearing_off
        g.forward_candidate(ids[old], new[k], 0.9, lambda pred: loop_edge(pred, dyaw, bearing, **kw),
                            unsettled="sigma_yaw_rad" in kw)

    ridge = math.radians(4.0)
    for old, k in ((5, 1), (10, 5), (14, 9)):  # places apart, on ridges no heading settled
        forward(old, k, sigma_yaw_rad=ridge)
    c = g.counters()
    assert (c["relocalisations"], c["reloc_group_edges"], c["forward_loops_accepted"]) == (1, 1, 0)
    # Counted under their own name, none as refused by the gate.
    assert (c["forward_loops_grouped"], c["forward_loops_failed_gate"]) == (3, 0)
    d = decisions[-1]
    assert d.relocalised and d.covariance is not None and len(d.members) == 3
    # The covariance is the group's fit's.
    fit = fit_transform(d.members, g._odometry_between, g.reloc_params)
    assert fit is not None and np.allclose(d.covariance, fit.covariance, rtol=1e-6, atol=1e-12)
    # One loop edge, from the old keyframe of the earliest query's member to that query: the
    # query's pose as the fitted transform puts it, with the fit's covariance carried there.
    loops = [e for e in g.graph.graph.edges if e.kind == "loop"]
    ref = min(d.members, key=lambda m: m.query_id)
    assert [(e.from_id, e.to_id) for e in loops] == [(ref.old_id, ref.query_id)]

    def delta_at(t: np.ndarray) -> np.ndarray:
        return between(ref.old_pose, compose(t, ref.query_pose))

    assert np.allclose(loops[0].delta, delta_at(d.transform), atol=1e-9)
    # (in the edge's own error coordinates: the graph's between factor's, at its delta)
    jac = np.stack([(between(loops[0].delta, delta_at(d.transform + h))
                     - between(loops[0].delta, delta_at(d.transform - h))) / 2e-6 for h in np.eye(3) * 1e-6], 1)
    assert np.allclose(np.linalg.inv(loops[0].information), jac @ d.covariance @ jac.T, rtol=1e-4, atol=1e-12)
    # The members' fates: ``grouped`` (none accepted, none refused by the gate, which never
    # judged them); the one link published is the group's edge.
    fates = [m for m in emitted if isinstance(m, CandidateFate)]
    members = {(m.query_id, m.old_id) for m in d.members}
    assert {(f.query_id, f.candidate_id) for f in fates} == members
    assert all(f.fate == LoopFate.GROUPED == "grouped" and f.detail.startswith("forward: " + GROUP_MEMBER)
               for f in fates)
    links = [m for m in emitted if isinstance(m, Link)]
    assert [(lk.from_id, lk.to_id, lk.source) for lk in links] == [(ref.old_id, ref.query_id, "forward")]
    # Placed where the truth is (the odometry frame started 3 m away).
    assert np.hypot(*(g.graph.pose(new[9])[:2] - (truth[0][:2] + after[9][:2]))) < 0.1
    # A later settled loop to the same place is gated against that pose: a right one passes,
    # the same one 6 deg off in heading does not.
    forward(15, 11)
    forward(16, 12, yaw_off=math.radians(6.0))
    fates = [m for m in emitted if isinstance(m, CandidateFate)][-2:]
    assert [f.fate for f in fates] == ["accepted", "failed_gate"]
    assert all("chi2" in f.detail for f in fates)
    c = g.counters()
    assert (c["forward_loops_accepted"], c["forward_loops_failed_gate"], c["forward_loops_grouped"]) == (1, 1, 3)
