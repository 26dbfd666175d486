"""The live pose graph's decisions, as functions of its state (paper 003 Sec. V; DESIGN.md
"Pose graph"): the chi-square gate on loop candidates, relocalisation of the run's
trajectory segments against the map frame, and localisation over mapped ground
(:mod:`robotd.graph.mappedground`). No I/O: the pipeline stage
(:mod:`robotd.app.stages.pose_graph`) feeds it the keyframes, links and candidates, reads
the map frame's stored poses for it, publishes what it emits (the candidates' fates
and the loop links) and writes what it reports (``joined_map``: a run joined the map
frame; :meth:`GatedGraph.after_solve`: which solved poses are in the map frame).

Each stored keyframe enters an iSAM2 graph (:class:`robotd.graph.incremental.IncrementalGraph`)
with its odometry edge: one incremental update per keyframe. A loop candidate (a local
score at or above the mode's trained threshold, with a relative pose from its inlier floor
points) is checked against the graph's own prediction of that relative pose before it may
enter: the innovation ``e = log(predicted^-1 * measured)`` and its covariance
``S = Ad P_a Ad^T + P_b + Sigma_loop`` (the two poses' marginal covariances from iSAM2,
their correlation left out, which makes ``S`` larger and the gate more lenient) give the
Mahalanobis distance ``e^T S^-1 e``; above ``gate_chi2`` (default: the 99.9 % point of
chi-square with 3 degrees of freedom) the candidate is refused as ``failed_gate``. A loop
between two trajectory segments (a relocalised one and the ground it was placed on, or an
earlier run's keyframe) is judged with the two poses' correlation (iSAM2's joint marginal,
``S = A J A^T + Sigma_loop``, ``A = [-Ad, I]``): the relocalised segment's marginals carry
the map's whole drift since its first keyframe, the relative pose very little of it, so
without the correlation ``S`` was many times too large there (true loops' chi-square had a
median of 0.1-1.4 on the kidnapped office drives) and a look-alike a few centimetres off
passed. What
passes (:meth:`robotd.graph.incremental.IncrementalGraph.loop_chi2`) becomes a loop :class:`~robotd.base.messages.Link` under the graph's robust
kernel. When the stage re-solves the whole graph
robustly (LAGO, DCS-weighted Levenberg-Marquardt, then GNC), loops the optimiser
down-weighted are recorded as ``down_weighted`` (:meth:`GatedGraph.after_solve`).

A forward-camera loop (:class:`~robotd.base.messages.ForwardLoop`: heading change and
bearing, no distance) becomes an SE(2) edge whose range is the graph's own prediction with a
large uncertainty (:func:`robotd.forward.planar.loop_edge`), then meets the same gate at
the same probability for the components it measures: 2 degrees of freedom without a
range measured on the floor (13.8 by default), 3 with one (:func:`gate_threshold`). A
forward loop whose motion lies on a heading-bearing ridge that no prior heading settled
(``ForwardLoop.sigma_yaw_rad``: a point the inliers' noise picked on the ridge, its heading
and bearing each as uncertain as the ridge is wide) is refused by the gate, however well it
agrees; it is held for relocalisation like any other (there its honest noise lets it weigh
no more than it measures), and the forward stage settles the next view of the place at the
heading the graph then gives.

Relocalisation. The map frame is the frame of the run that started the
map; a run that relocalises against it joins it (``MapStore.map_frame_runs``). A run that
starts on a map with keyframes in the map frame does not know where it is: it says so
("not localised in the stored map", in the log and STATUS), keeps running on odometry in
its own frame, and holds the loop candidates that reach a map keyframe in a
:class:`robotd.graph.reloc.Relocaliser` until two or more independent ones agree on the
transform to the map frame (the rule and why: :mod:`robotd.graph.reloc`). Then the old
keyframes of the agreeing loops enter the graph fixed at their optimised map poses, the
run's trajectory is moved into the map frame and tied to them by those loops
(:meth:`robotd.graph.incremental.IncrementalGraph.attach`); a group of forward loops only
ties it by one edge instead, the group's fitted transform with the fit's covariance
(:func:`robotd.graph.reloc.group_constraint`), and none of its members becomes a loop edge
or an accepted loop (their fate is ``grouped``, its detail :data:`GROUP_MEMBER`): a
ridge loop that agrees with the group only within its wide noise places the segment no
more than the fit lets it, and never enters as a loop of its own. The log and STATUS say
"relocalised against run N after X s and Y m", and every later candidate meets the gate
as usual (an old keyframe it reaches enters the graph fixed first). Held candidates that
never agree are recorded as ``failed_gate`` with the reason (``relocalisation: ...``).

A kidnapping: the base reports a wheel drop (:class:`~robotd.base.messages.WheelDrop`)
while the robot is carried; the keyframe stage takes no keyframes then and the map writer
links no odometry edge across it, so the next keyframe starts a new segment of the
trajectory in a frame of its own (:meth:`~robotd.graph.incremental.IncrementalGraph.add_segment`).
It says "LOST" and relocalises that segment as above, against the map's keyframes
of earlier runs and of this run's localised segments.

Forward loops relocalise too (with the floor detector off as well): a verified forward loop
from the lost trajectory to a keyframe with a map pose is held like a floor candidate, and
the trajectory relocalises when a second, independent one agrees with it, a floor loop or
a forward loop after odometry has moved the robot at least ``min_separation_m``; the two
bearings then fix the range (:func:`robotd.graph.reloc.fit_transform`). The log and STATUS
say which camera did it: "relocalised against run N after X s and Y m (forward camera)"
(or "floor camera", "floor and forward cameras").
Only keyframes in the map frame get optimised poses in the map file: a segment that never
relocalised keeps its odometry poses only (its frame is its own).
"""

from __future__ import annotations

import array
import bisect
import collections
import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from robotd.base.geometry import between
from robotd.base.messages import CandidateFate, Link, LoopFate
from robotd.graph.incremental import IncrementalGraph
from robotd.graph.mappedground import MappedGround, MappedGroundParams
from robotd.graph.reloc import (
    Relocaliser,
    RelocCandidate,
    RelocDecision,
    RelocParams,
    chain_relative,
    group_constraint,
)

log = logging.getLogger(__name__)

GATE_CHI2_3DOF_999 = 16.27  # chi-square, 3 degrees of freedom, 99.9 %
DOWN_WEIGHTED = 0.5  # a loop whose final weight is under this counts as down-weighted
GROUP_MEMBER = "relocalisation: a member of the relocalising group, which entered the graph as one edge"
"""How the detail of a relocalising group's member's fate begins (after ``forward: ``) when
the group entered the graph as one edge (:func:`robotd.graph.reloc.group_constraint`): the
member is no loop edge of its own (fate ``grouped``; the gate never judged it)."""

Emit = Callable[[CandidateFate | Link], None]


def gate_threshold(gate_chi2: float, dof: int) -> float:
    """The gate's bound for a loop that measures ``dof`` components: the chi-square point
    at the probability ``gate_chi2`` has at 3 degrees of freedom (99.9 % by default).

    A forward loop without a range of its own is an edge at the graph's predicted range
    (:func:`robotd.forward.planar.loop_edge`): its innovation along the line of sight is
    zero by construction, so its Mahalanobis distance has 2 degrees of freedom (bearing
    and heading change), and the 3-dof bound would let a bearing error through that the
    2-dof bound of the same probability refuses."""
    from scipy.stats import chi2

    return float(chi2.ppf(chi2.cdf(gate_chi2, 3), dof))


def _prefixed(source: str, detail: str) -> str:
    """A fate's detail, prefixed ``forward: `` for a forward loop (as the gate's own)."""
    return f"forward: {detail}" if source == "forward" else detail


def _given(edge: tuple[np.ndarray, np.ndarray]) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
    """``edge`` as the gate takes a candidate's edge (a function giving it)."""
    return lambda: edge


class GatedGraph:
    """The gate, relocalisation and mapped ground over one :class:`IncrementalGraph` (see
    the module notes). ``emit`` receives every :class:`CandidateFate` and loop
    :class:`Link` decided; ``joined_map(run_id)`` is told when the run joins the map frame
    (it starts the map, or relocalises into it). ``mapped_ground``: localisation over
    mapped ground on, with these parameters (:attr:`mapped_ground` is then its state)."""

    def __init__(self, graph: IncrementalGraph, emit: Emit, joined_map: Callable[[int], None], *,
                 gate_chi2: float = GATE_CHI2_3DOF_999, mapped_ground: MappedGroundParams | None = None,
                 reloc_params: RelocParams | None = None) -> None:
        self.graph = graph
        self._emit = emit
        self._joined_map = joined_map
        self.gate_chi2 = gate_chi2
        self.mapped_ground = None if mapped_ground is None else MappedGround(
            mapped_ground, graph.pose, lambda: graph.estimate()[1][:, :2], graph.loop_chi2)
        self.accepted = 0
        self.failed_gate = 0
        self.earlier_run = 0
        self.down_weighted = 0
        self.forward_accepted = 0
        self.forward_failed_gate = 0
        self.forward_grouped = 0  # members of relocalising groups that entered as one edge
        self.update_ms = array.array("d")  # each incremental update's time (8 bytes each, no float objects)
        self._loops: dict[tuple[int, int], tuple[int, float]] = {}  # edge -> (query, score)
        self._init_relocalisation(reloc_params)

    # -- input -----------------------------------------------------------------------------

    def odometry_link(self, from_id: int, to_id: int, delta: np.ndarray, information: np.ndarray,
                      bias: tuple[Any, ...] | None = None) -> None:
        """An odometry edge: ``to_id`` joins the graph (ignored when ``from_id`` is not in it);
        ``bias``: its bias terms (:meth:`robotd.graph.incremental.IncrementalGraph.add_keyframe`)."""
        if from_id not in self.graph.graph:
            return
        t0 = time.perf_counter()
        self.graph.add_keyframe(to_id, from_id, delta, information, bias)
        self.update_ms.append((time.perf_counter() - t0) * 1e3)

    def keyframe(self, keyframe_id: int, run_id: int, pose: np.ndarray, stamp_ns: int,
                 map_poses: Callable[[int], dict[int, tuple[np.ndarray, int]]]) -> None:
        """A stored keyframe (after its odometry link, if any). ``map_poses(run_id)``: the map
        frame's keyframes of earlier runs, ``id -> (pose (3,), run)``, asked once, at the
        run's first keyframe."""
        self._track_keyframe(int(keyframe_id), run_id, pose, stamp_ns, map_poses)
        if keyframe_id not in self.graph.graph and not len(self.graph.graph):
            self.graph.add_first(keyframe_id, pose)

    def floor_candidate(self, from_id: int, to_id: int, score: float, delta: np.ndarray,
                        information: np.ndarray) -> None:
        """A floor loop candidate: held for relocalisation, or gated."""
        if self._relocalisation_takes(from_id, to_id, score, delta, information, "floor"):
            return
        self._gate_and_add(from_id, to_id, score, lambda: (delta, information), "floor")

    def forward_candidate(self, from_id: int, to_id: int, probability: float,
                          edge: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], *,
                          range_measured: bool = False, unsettled: bool = False) -> None:
        """A forward loop: ``edge(predicted)`` gives its ``(delta, information)`` from the
        graph's predicted relative pose (the forward camera measures no range, unless the
        floor gave it: ``range_measured``). ``unsettled``: its motion lies on a
        heading-bearing ridge no prior heading settled (the forward stage's module notes):
        held for relocalisation like any other, but never gated into the graph (module
        notes)."""
        if self._relocalisation_takes(from_id, to_id, probability, None, None, "forward", edge=edge,
                                      measured_dims=3 if range_measured else 2, unsettled=unsettled):
            return
        if unsettled:
            self._refuse_unsettled(from_id, to_id, probability)
            return
        self._gate_and_add(from_id, to_id, probability, self._forward_edge(from_id, to_id, edge), "forward",
                           dof=3 if range_measured else 2)

    def _refuse_unsettled(self, from_id: int, to_id: int, probability: float) -> None:
        self.forward_failed_gate += 1
        self._emit(CandidateFate(to_id, from_id, probability, LoopFate.FAILED_GATE,
                                 "forward: on a heading-bearing ridge no heading settled"))

    def _forward_edge(self, from_id: int, to_id: int, edge: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
                      ) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
        """A forward loop's edge at the graph's predicted relative pose (asked when gated)."""
        return lambda: edge(between(self.graph.pose(from_id), self.graph.pose(to_id)))

    def map_match(self, from_id: int, delta: np.ndarray, information: np.ndarray) -> None:
        """A transient keyframe matched the map: gated, it re-localises the robot over mapped
        ground (the graph is not changed)."""
        if self.mapped_ground is not None and from_id in self.graph.graph:
            # (A keyframe of an earlier run that is not in the graph cannot be gated against.)
            self.mapped_ground.match(from_id, delta, information, self.gate_chi2)

    def after_solve(self, ids: np.ndarray, loop_weights: np.ndarray) -> list[int]:
        """After a full re-solve: the indices into ``ids`` whose poses belong in the map
        (this run's keyframes in the map frame; earlier runs' keep theirs); loops the
        optimiser down-weighted (weight under :data:`DOWN_WEIGHTED`) are emitted as such."""
        keep = [n for n, i in enumerate(ids) if self._in_map_frame(int(i)) and int(i) not in self._map_poses]
        loop_edges = [(e.from_id, e.to_id) for e in self.graph.graph.edges if e.kind == "loop"]
        for (a, b), w in zip(loop_edges, loop_weights):
            if w < DOWN_WEIGHTED and (a, b) in self._loops:
                query, score = self._loops.pop((a, b))
                self.down_weighted += 1
                self._emit(CandidateFate(query, a, score, LoopFate.DOWN_WEIGHTED, f"weight {w:.3f}"))
        return keep

    def finish(self) -> None:
        """End of the run: held candidates are refused; says if the run ends unlocalised."""
        self._drop_pending("relocalisation: no agreeing candidate before the run ended")

    def end_warning(self) -> str:
        """"" or why the run's last keyframes keep their odometry poses only."""
        if self._run_id is None or self._in_map_frame(self._segments[-1]):
            return ""
        last = len([k for k in self.graph.graph.ids if self._segment_of(int(k)) == len(self._segments) - 1])
        return (f"the run ended {'not localised in the stored map' if self._state == 'not_localised' else 'lost'}: "
                f"its last {last} keyframes keep their odometry poses only")

    def localised(self) -> bool:
        """Whether the newest segment is in the map frame."""
        return self._run_id is not None and self._in_map_frame(self._segments[-1])

    def counters(self) -> dict[str, int]:
        return {"loops_accepted": self.accepted, "loops_failed_gate": self.failed_gate,
                "loops_earlier_run": self.earlier_run, "loops_down_weighted": self.down_weighted,
                "forward_loops_accepted": self.forward_accepted,
                "forward_loops_failed_gate": self.forward_failed_gate,
                "forward_loops_grouped": self.forward_grouped,
                "localised": int(self.localised()),
                "relocalisations": self.relocalisations, "reloc_candidates_refused": self.reloc_refused,
                "reloc_group_edges": self.group_constraints,
                "lifts": self.lifts,
                **(self.mapped_ground.counters() if self.mapped_ground is not None else {})}

    # -- the gate --------------------------------------------------------------------------

    def _gate_and_add(self, from_id: int, to_id: int, score: float,
                      edge: Callable[[], tuple[np.ndarray, np.ndarray]], source: str, dof: int = 3) -> None:
        """The gate, then the loop edge for a candidate of ``source`` (``"floor"``: fates'
        details as they were; ``"forward"``: prefixed ``forward: ``). ``edge()`` gives its
        ``(delta, information)`` once both keyframes are known to be in this run's graph.
        ``dof``: the components the loop measures (:func:`gate_threshold`)."""
        prefix = "forward: " if source == "forward" else ""

        def fate(f: LoopFate, detail: str) -> None:
            self._emit(CandidateFate(to_id, from_id, score, f, prefix + detail))

        if from_id not in self.graph.graph or to_id not in self.graph.graph:
            self.earlier_run += 1
            fate(LoopFate.FAILED_GATE, "keyframe of an earlier run: not in this run's graph")
            return
        delta, info = edge()
        # Across trajectory segments (a relocalised segment and the ground it was placed on)
        # the two poses' correlation is most of their uncertainty: the gate takes it in.
        d2 = self.graph.loop_chi2(from_id, to_id, delta, info,
                                  joint=self._segment_of(from_id) != self._segment_of(to_id))
        bound = self.gate_chi2 if dof == 3 else gate_threshold(self.gate_chi2, dof)
        if not d2 <= bound:
            if source == "forward":
                self.forward_failed_gate += 1
            else:
                self.failed_gate += 1
            fate(LoopFate.FAILED_GATE, f"chi2 {d2:.1f} > {bound:.2f}")
            return
        t0 = time.perf_counter()
        in_graph = self.graph.add_loop(from_id, to_id, delta, info)
        self.update_ms.append((time.perf_counter() - t0) * 1e3)
        if source == "forward":
            self.forward_accepted += 1
        else:
            self.accepted += 1
        if in_graph:  # a loop left out of the graph (add_loop) is never down-weighted
            self._loops[(from_id, to_id)] = (to_id, score)
        if self.mapped_ground is not None:
            self.mapped_ground.loop_accepted(to_id)
        fate(LoopFate.ACCEPTED, f"chi2 {d2:.2f}")
        self._emit(Link("loop", from_id, to_id, delta, info, source=source))

    # -- relocalisation (module notes) -----------------------------------------------------

    def _init_relocalisation(self, params: RelocParams | None) -> None:
        self.reloc_params = RelocParams() if params is None else params
        self._relocaliser = Relocaliser(self._odometry_between, self.reloc_params)
        self._run_id: int | None = None
        self._map_poses: dict[int, tuple[np.ndarray, int]] = {}  # earlier runs: id -> (map pose, run)
        self._segments: list[int] = []  # first keyframe id of each segment of this run
        self._in_map: set[int] = set()  # segments (indices) in the map frame
        self._travelled: dict[int, float] = {}  # keyframe -> odometry distance along its segment, m
        self._stamps: dict[int, int] = {}  # keyframe -> stamp, ns (this segment's)
        self._last_kf: tuple[int, np.ndarray] | None = None
        self._segment_start_ns = 0
        self._put_down_ns: int | None = None
        self._lifted = False
        self._state = "map"  # map | not_localised | lifted | lost | relocalised
        self._reloc_text = ""
        self.relocalisations = 0
        self.reloc_refused = 0
        self.lifts = 0
        self.relocalised_at: list[dict[str, Any]] = []  # per relocalisation: the figures logged
        self.group_constraints = 0  # relocalising groups that entered the graph as one edge
        self._edges_into: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}
        self._edges_seen = 0

    def _segment_of(self, keyframe_id: int) -> int:
        """The segment (index) of one of this run's keyframes; -1 for earlier runs'."""
        return bisect.bisect_right(self._segments, keyframe_id) - 1

    def _in_map_frame(self, keyframe_id: int) -> bool:
        """Whether a keyframe's pose in the graph is in the map frame."""
        if keyframe_id in self._map_poses:
            return True
        seg = self._segment_of(keyframe_id)
        return seg >= 0 and seg in self._in_map

    def _track_keyframe(self, kid: int, run_id: int, pose: np.ndarray, stamp_ns: int,
                        map_poses: Callable[[int], dict[int, tuple[np.ndarray, int]]]) -> None:
        """Segments, distance driven and stamps; the run's first keyframe decides whether
        the run starts the map or must relocalise against it."""
        pose = np.asarray(pose, dtype=float)
        if self._run_id is None:
            self._run_id = int(run_id)
            self._start_segment(kid, stamp_ns)
            self._map_poses = map_poses(self._run_id)
            if self._map_poses:
                runs = sorted({r for _p, r in self._map_poses.values()})
                self._state = "not_localised"
                log.warning("not localised in the stored map (%d keyframes of run%s %s in the map "
                            "frame): running on odometry in this run's own frame until %d loops "
                            "(floor or forward camera) agree on where it is", len(self._map_poses), "s" if len(runs) > 1 else "",
                            ", ".join(map(str, runs)), self.reloc_params.min_agreeing)
            else:
                self._in_map.add(0)
                self._joined_map(self._run_id)
                log.info("no keyframes in the map frame yet: run %d starts the map", self._run_id)
        elif kid not in self.graph.graph and len(self.graph.graph):
            # No odometry edge reached it: the chain was broken (the robot was carried).
            self._start_segment(kid, self._put_down_ns if self._put_down_ns is not None else stamp_ns)
            self.graph.add_segment(kid, pose)
            if not self._lifted:
                self._state = "lost"
            log.warning("keyframe %d starts a new trajectory segment in a frame of its own: lost until "
                        "%d loops agree on where it is (%d if all from the forward camera)", kid,
                        self.reloc_params.min_agreeing, self.reloc_params.min_forward_only)
        if self._last_kf is not None and self._segment_of(self._last_kf[0]) == self._segment_of(kid):
            step = float(np.hypot(*(pose[:2] - self._last_kf[1][:2])))
            self._travelled[kid] = self._travelled.get(self._last_kf[0], 0.0) + step
        else:
            self._travelled[kid] = 0.0
        self._stamps[kid] = int(stamp_ns)
        self._last_kf = (kid, pose)

    def _start_segment(self, keyframe_id: int, start_ns: int) -> None:
        if self._segments:
            self._drop_pending("relocalisation: the trajectory was broken again (the robot was carried)")
        self._segments.append(keyframe_id)
        self._segment_start_ns = int(start_ns)
        self._put_down_ns = None
        self._travelled = {}
        self._stamps = {}

    def wheel_drop(self, lifted: bool, stamp_ns: int) -> None:
        """The base's wheel-drop switches: ``lifted`` (carried) or put down at ``stamp_ns``."""
        if lifted and not self._lifted:
            self._lifted = True
            self.lifts += 1
            self._state = "lifted"
            log.warning("lifted (wheel drop): lost; no odometry edge will cross the carry, and the "
                        "trajectory relocalises after the robot is put down")
        elif not lifted and self._lifted:
            self._lifted = False
            self._put_down_ns = stamp_ns
            self._state = "lost"
            log.warning("put down: lost until %d loops agree on where (%d if all from the forward camera)",
                        self.reloc_params.min_agreeing, self.reloc_params.min_forward_only)

    def _odometry_between(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray] | None:
        edges = self.graph.graph.edges
        if len(edges) != self._edges_seen:
            for e in edges[self._edges_seen:]:
                if e.kind == "odometry":
                    self._edges_into[e.to_id] = (e.from_id, e.delta, e.information)
            self._edges_seen = len(edges)
        return chain_relative(self._edges_into, a, b)

    def _refuse(self, query: int, old: int, score: float, detail: str) -> None:
        self.reloc_refused += 1
        self._emit(CandidateFate(query, old, score, LoopFate.FAILED_GATE, detail))

    def _relocalisation_takes(self, old: int, query: int, score: float, delta: np.ndarray | None,
                              info: np.ndarray | None, source: str, *,
                              edge: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
                              measured_dims: int = 3, unsettled: bool = False) -> bool:
        """Handle a candidate whose two keyframes are not in one frame: hold it for
        relocalisation, or refuse it with the reason. False: the gate judges it (an old map
        keyframe it reaches is first added to the graph, fixed)."""
        if query not in self.graph.graph or self._run_id is None:
            return False
        q_map = self._in_map_frame(query)
        earlier = old not in self.graph.graph
        if earlier and old not in self._map_poses:
            return False  # the gate's own refusal: a keyframe of an earlier run outside the map frame
        o_map = self._in_map_frame(old)
        if not earlier and (self._segment_of(old) == self._segment_of(query) or (q_map and o_map)):
            return False
        if q_map and o_map:  # an earlier run's map keyframe, reached from the map frame
            self.graph.add_fixed(old, self._map_poses[old][0])
            return False
        prefix = "forward: " if source == "forward" else ""
        if not o_map:
            self._refuse(query, old, score, f"{prefix}keyframe of a trajectory not localised in the map")
            return True
        old_pose, old_run = (self._map_poses[old] if earlier
                             else (self.graph.pose(old), int(self._run_id)))
        if edge is not None:  # a forward loop: its edge at a first guess of the range, until the group's fit
            delta, info = edge(np.array([1.0, 0.0, 0.0]))
        if delta is None or info is None:
            raise ValueError("a floor candidate needs its delta and information")
        cand = RelocCandidate(old, query, float(score), np.asarray(old_pose, float), np.asarray(delta, float),
                              np.asarray(info, float), self.graph.pose(query), self._travelled.get(query, 0.0),
                              old_run, source, edge, measured_dims, unsettled)
        decision = self._relocaliser.offer(cand)
        if decision.relocalised:
            self._relocalise(decision)
            # The other held candidates are in one frame with their old keyframes now: the gate
            # judges them as any later candidate (a look-alike among them fails it).
            for p, _why in decision.dropped:
                if p.unsettled:
                    self._refuse_unsettled(p.old_id, p.query_id, p.score)
                    continue
                if p.old_id not in self.graph.graph:
                    self.graph.add_fixed(p.old_id, p.old_pose)
                if p.edge is not None:
                    self._gate_and_add(p.old_id, p.query_id, p.score, self._forward_edge(p.old_id, p.query_id, p.edge),
                                       "forward", dof=p.measured_dims)
                else:
                    self._gate_and_add(p.old_id, p.query_id, p.score, _given((p.delta, p.information)), "floor")
        else:
            for p, why in decision.dropped:
                self._refuse(p.query_id, p.old_id, p.score, _prefixed(p.source, why))
            log.debug("relocalisation: keyframe %d sees keyframe %d of run %d: %s", query, old, old_run,
                      decision.detail)
        return True

    def _drop_pending(self, why: str) -> None:
        for p in self._relocaliser.reset():
            self._refuse(p.query_id, p.old_id, p.score, _prefixed(p.source, why))

    def _relocalise(self, d: RelocDecision) -> None:
        """Anchor the current segment in the map frame with the agreeing loops."""
        seg = len(self._segments) - 1
        ids = [int(k) for k in self.graph.graph.ids if self._segment_of(int(k)) == seg]
        assert d.transform is not None  # relocalised
        transform = d.transform
        group = (group_constraint(d.members, transform, d.covariance)
                 if (d.covariance is not None and self.reloc_params.forward_group_as_one
                     and all(m.source == "forward" for m in d.members)) else None)
        loops = [group] if group is not None else [(m.old_id, m.query_id, m.delta, m.information)
                                                   for m in d.members]
        olds = {old for old, _q, _d, _i in loops}
        for m in d.members:
            if m.old_id in olds and m.old_id not in self.graph.graph:
                self.graph.add_fixed(m.old_id, m.old_pose)
        t0 = time.perf_counter()
        self.graph.attach(ids, transform, loops)
        self.update_ms.append((time.perf_counter() - t0) * 1e3)
        self._in_map.add(seg)
        if group is not None:  # the group is one edge: its members are evidence, none of them a loop edge
            old, query, delta, info = group
            self.group_constraints += 1
            for m in d.members:
                self.forward_grouped += 1
                self._emit(CandidateFate(m.query_id, m.old_id, m.score, LoopFate.GROUPED,
                                         _prefixed(m.source, f"{GROUP_MEMBER} ({old}->{query}): {d.detail}")))
            self._emit(Link("loop", old, query, delta, info, source="forward"))
        else:
            for m in d.members:
                if m.source == "forward":
                    self.forward_accepted += 1
                else:
                    self.accepted += 1
                self._loops[(m.old_id, m.query_id)] = (m.query_id, m.score)
                self._emit(CandidateFate(m.query_id, m.old_id, m.score, LoopFate.ACCEPTED,
                                         _prefixed(m.source, f"relocalisation: {d.detail}")))
                self._emit(Link("loop", m.old_id, m.query_id, m.delta, m.information, source=m.source))
        self.relocalisations += 1
        newest = max(d.members, key=lambda m: m.query_id)
        runs = collections.Counter(m.old_run for m in d.members)
        run = runs.most_common(1)[0][0]
        after_s = max(0.0, (self._stamps.get(newest.query_id, self._segment_start_ns) - self._segment_start_ns) / 1e9)
        after_m = self._travelled.get(newest.query_id, 0.0)
        cameras = " and ".join(sorted({m.source for m in d.members}))
        self._state = "relocalised"
        self._reloc_text = (f"relocalised against run {run} after {after_s:.1f} s and {after_m:.1f} m "
                            f"({cameras} camera{'s' if ' and ' in cameras else ''})")
        self.relocalised_at.append({"run": run, "after_s": after_s, "after_m": after_m, "cameras": cameras,
                                    "keyframe": newest.query_id, "stamp_ns": self._stamps.get(newest.query_id, 0),
                                    "candidates": len(d.members),
                                    "pose": [float(v) for v in self.graph.pose(newest.query_id)]})
        if self._run_id is not None:
            self._joined_map(self._run_id)
        log.info("%s (%s; keyframes %s; the lost frame is at x %.2f m, y %.2f m, yaw %.1f deg in the map)",
                 self._reloc_text, d.detail, ", ".join(f"{m.query_id}->{m.old_id}" for m in d.members),
                 transform[0], transform[1], math.degrees(transform[2]))

    def status_fragment(self) -> str:
        """Where the robot stands with the map, for the STATUS line ("" when it simply
        continues the map it started)."""
        if self._state == "not_localised":
            return "not localised in the stored map"
        if self._state == "lifted":
            return "LOST (lifted)"
        if self._state == "lost":
            return "LOST (relocalising)"
        if self._state == "relocalised":
            return self._reloc_text
        return ""
