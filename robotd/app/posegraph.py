"""The pose graph as a pipeline stage: keyframes and odometry links in, loop candidates
gated, the optimised trajectory out (paper 003 Sec. V; DESIGN.md "Pose graph").

Each stored keyframe enters an iSAM2 graph (:class:`robotd.graph.incremental.IncrementalGraph`)
with its odometry edge: one incremental update per keyframe. A loop candidate (a local
score at or above the mode's trained threshold, with a relative pose from its inlier floor
points) is checked against the graph's own prediction of that relative pose before it may
enter: the innovation ``e = log(predicted^-1 * measured)`` and its covariance
``S = Ad P_a Ad^T + P_b + Sigma_loop`` (the two poses' marginal covariances from iSAM2,
their correlation left out, which makes ``S`` larger and the gate more lenient) give the
Mahalanobis distance ``e^T S^-1 e``; above ``gate_chi2`` (default: the 99.9 % point of
chi-square with 3 degrees of freedom) the candidate is refused as ``failed_gate``. What
passes (:meth:`robotd.graph.incremental.IncrementalGraph.loop_chi2`) becomes a loop :class:`~robotd.base.messages.Link` under the graph's robust
kernel. At the end of a run (and every ``save_every`` keyframes) the whole graph is
re-solved robustly (LAGO, then DCS-weighted Levenberg-Marquardt), the optimised poses go
into the map beside the odometry poses, and loops the optimiser down-weighted are
recorded as ``down_weighted``.

A forward-camera loop (:class:`~robotd.base.messages.ForwardLoop`: heading change and
bearing, no distance) becomes an SE(2) edge whose range is the graph's own prediction with a
large uncertainty (:func:`robotd.forward.planar.loop_edge`), then meets the same gate.

Keyframes of earlier runs are not in the live graph (each run's graph starts at its first
keyframe), so a candidate that reaches one is recorded as ``failed_gate`` with that reason;
relocalisation against the stored map is issue 14's.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from robotd.app.mappedground import MappedGround, MappedGroundParams
from robotd.app.pipeline import Publisher
from robotd.base.geometry import between
from robotd.base.messages import (
    CandidateFate,
    ForwardLoop,
    KeyframeStored,
    Link,
    LoopCandidate,
    MapMatch,
)
from robotd.forward.planar import PlanarLoopParams, loop_edge
from robotd.graph.incremental import IncrementalGraph
from robotd.io.store import MapStore

log = logging.getLogger(__name__)

GATE_CHI2_3DOF_999 = 16.27  # chi-square, 3 degrees of freedom, 99.9 %
DOWN_WEIGHTED = 0.5  # a loop whose final weight is under this counts as down-weighted


class PoseGraphStage(Publisher):
    """The live pose graph (see the module notes). Register it before ``floor`` (it must
    hold a keyframe before that keyframe's loop candidates arrive) and before ``map``."""

    name = "graph"

    def __init__(self, graph: IncrementalGraph, store: MapStore, *, gate_chi2: float = GATE_CHI2_3DOF_999,
                 save_every: int = 0, forward_mount: np.ndarray | None = None,
                 forward_params: PlanarLoopParams | None = None,
                 mapped_ground: MappedGroundParams | None = None) -> None:
        self.graph = graph
        # Localisation over mapped ground (robotd.app.mappedground), when configured.
        self.mapped_ground = None if mapped_ground is None else MappedGround(
            mapped_ground, graph.pose, lambda: graph.estimate()[1][:, :2], graph.loop_chi2)
        self.forward_mount = np.zeros(3) if forward_mount is None else np.asarray(forward_mount, float)
        self.forward_params = PlanarLoopParams() if forward_params is None else forward_params
        self.forward_accepted = 0
        self.forward_failed_gate = 0
        self.store = store
        self.gate_chi2 = gate_chi2
        self.save_every = save_every
        self.accepted = 0
        self.failed_gate = 0
        self.earlier_run = 0
        self.down_weighted = 0
        self.solves = 0
        self.solve_failures = 0
        self.update_ms: list[float] = []
        self.last_solve_ms = 0.0
        self._loops: dict[tuple[int, int], tuple[int, float]] = {}  # edge -> (query, score)
        self._since_save = 0

    def subscriptions(self) -> Mapping[type, Any]:
        return {Link: self.on_link, KeyframeStored: self.on_keyframe, LoopCandidate: self.on_candidate,
                ForwardLoop: self.on_forward_loop, MapMatch: self.on_map_match}

    def on_map_match(self, m: MapMatch) -> None:
        """A transient keyframe matched the map: gated, it re-localises the robot (the graph
        is not changed)."""
        if self.mapped_ground is not None:
            self.mapped_ground.match(m.from_id, m.delta_xyyaw, m.information, self.gate_chi2)

    def on_link(self, link: Link) -> None:
        if link.kind != "odometry" or link.from_id not in self.graph.graph:
            return
        t0 = time.perf_counter()
        self.graph.add_keyframe(link.to_id, link.from_id, link.delta_xyyaw, link.information)
        self.update_ms.append((time.perf_counter() - t0) * 1e3)

    def on_keyframe(self, msg: KeyframeStored) -> None:
        kf = msg.keyframe
        if kf.keyframe_id not in self.graph.graph and not len(self.graph.graph):
            self.graph.add_first(kf.keyframe_id, kf.pose_xyyaw)
        self._since_save += 1
        if self.save_every and self._since_save >= self.save_every:
            self.solve_and_save()

    def on_candidate(self, c: LoopCandidate) -> None:
        self._gate_and_add(c.from_id, c.to_id, c.score, lambda: (c.delta_xyyaw, c.information), "floor")

    def on_forward_loop(self, c: ForwardLoop) -> None:
        def edge() -> tuple[np.ndarray, np.ndarray]:
            predicted = between(self.graph.pose(c.from_id), self.graph.pose(c.to_id))
            return loop_edge(predicted, c.dyaw_rad, c.bearing_rad, self.forward_mount, self.forward_params)

        self._gate_and_add(c.from_id, c.to_id, c.probability, edge, "forward")

    def _gate_and_add(self, from_id: int, to_id: int, score: float,
                      edge: Callable[[], tuple[np.ndarray, np.ndarray]], source: str) -> None:
        """The gate, then the loop edge for a candidate of ``source`` (``"floor"``: fates'
        details as they were; ``"forward"``: prefixed ``forward: ``). ``edge()`` gives its
        ``(delta, information)`` once both keyframes are known to be in this run's graph."""
        prefix = "forward: " if source == "forward" else ""

        def fate(f: str, detail: str) -> None:
            self._publish(CandidateFate(to_id, from_id, score, f, prefix + detail))

        if from_id not in self.graph.graph or to_id not in self.graph.graph:
            self.earlier_run += 1
            fate("failed_gate", "keyframe of an earlier run: not in this run's graph")
            return
        delta, info = edge()
        d2 = self.graph.loop_chi2(from_id, to_id, delta, info)
        if not d2 <= self.gate_chi2:
            if source == "forward":
                self.forward_failed_gate += 1
            else:
                self.failed_gate += 1
            fate("failed_gate", f"chi2 {d2:.1f} > {self.gate_chi2:.2f}")
            return
        t0 = time.perf_counter()
        self.graph.add_loop(from_id, to_id, delta, info)
        self.update_ms.append((time.perf_counter() - t0) * 1e3)
        if source == "forward":
            self.forward_accepted += 1
        else:
            self.accepted += 1
        self._loops[(from_id, to_id)] = (to_id, score)
        if self.mapped_ground is not None:
            self.mapped_ground.loop_accepted(to_id)
        fate("accepted", f"chi2 {d2:.2f}")
        self._publish(Link("loop", from_id, to_id, delta, info, source=source))

    def solve_and_save(self) -> None:
        """Re-solve the whole graph robustly and store the optimised poses."""
        if len(self.graph.graph) < 2:
            return
        t0 = time.perf_counter()
        try:
            result = self.graph.resolve()
        except RuntimeError as exc:  # a solver failure must not stop the daemon
            self.solve_failures += 1
            log.warning("pose graph: the full solve failed (%s); the map keeps the last solution",
                        str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__)
            return
        self.last_solve_ms = (time.perf_counter() - t0) * 1e3
        self.solves += 1
        self._since_save = 0
        self.store.put_optimized_poses([int(i) for i in result.ids], result.poses)
        loop_edges = [(e.from_id, e.to_id) for e in self.graph.graph.edges if e.kind == "loop"]
        for (a, b), w in zip(loop_edges, result.loop_weights):
            if w < DOWN_WEIGHTED and (a, b) in self._loops:
                query, score = self._loops.pop((a, b))
                self.down_weighted += 1
                self._publish(CandidateFate(query, a, score, "down_weighted", f"weight {w:.3f}"))
        log.info("pose graph: %d keyframes, %d loops, solved in %.0f ms", len(self.graph.graph),
                 self.accepted, self.last_solve_ms)

    def finish(self) -> int:
        self.solve_and_save()
        return 0

    def optimized(self) -> tuple[np.ndarray, np.ndarray]:
        """The current estimate: ``(ids (N,), poses (N, 3))``."""
        return self.graph.estimate()

    def counters(self) -> dict[str, int]:
        u = np.asarray(self.update_ms) if self.update_ms else np.zeros(1)
        return {"loops_accepted": self.accepted, "loops_failed_gate": self.failed_gate,
                "loops_earlier_run": self.earlier_run, "loops_down_weighted": self.down_weighted,
                "forward_loops_accepted": self.forward_accepted,
                "forward_loops_failed_gate": self.forward_failed_gate,
                "graph_solves": self.solves, "graph_solve_failures": self.solve_failures,
                "graph_update_median_us": int(np.median(u) * 1e3),
                "graph_update_p99_us": int(np.percentile(u, 99) * 1e3),
                "graph_solve_ms": int(self.last_solve_ms),
                **(self.mapped_ground.counters() if self.mapped_ground is not None else {})}
