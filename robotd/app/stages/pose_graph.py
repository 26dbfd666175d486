"""The pose graph as a pipeline stage: keyframes and odometry links in, loop candidates
gated, the optimised trajectory out (paper 003 Sec. V; DESIGN.md "Pose graph").

The decisions (the chi-square gate, relocalisation, localisation over mapped ground) are
:class:`robotd.graph.gate.GatedGraph`'s, in the algorithm layer; this stage feeds it the
messages, publishes the fates and loop links it decides, and does the I/O: it reads the
map frame's poses at the run's first keyframe, records the runs that join the map frame,
and every ``save_every`` keyframes and at the end re-solves the whole graph robustly
(LAGO, DCS-weighted Levenberg-Marquardt, then GNC) and stores the optimised poses of the
keyframes in the map frame beside their odometry poses.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from robotd.app.pipeline import Publisher
from robotd.base.messages import (
    CandidateFate,
    ForwardLoop,
    KeyframeStored,
    Link,
    LoopCandidate,
    MapMatch,
    WheelDrop,
)
from robotd.forward.planar import PlanarLoopParams, loop_edge
from robotd.graph.gate import GATE_CHI2_3DOF_999, GatedGraph
from robotd.graph.incremental import IncrementalGraph
from robotd.graph.mappedground import MappedGround, MappedGroundParams
from robotd.graph.reloc import RelocParams
from robotd.io.store import MapStore

log = logging.getLogger(__name__)


def _load_malloc_trim() -> Callable[[int], int] | None:
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc: nothing to trim
        return None


_MALLOC_TRIM = _load_malloc_trim()


def release_freed_memory() -> None:
    """glibc's ``malloc_trim(0)``: hand the pages freed by a full solve (the old iSAM2, the
    batch's factorisations) back to the system; glibc keeps them otherwise. Measured on a
    synthetic 10,000-keyframe graph of repeated laps: 123 MB resident, 89 MB after the
    trim. Nothing where the C library is not glibc."""
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)


class PoseGraphStage(Publisher):
    """The live pose graph (see the module notes). Registered before ``floor`` and
    ``forward`` (``precedes``, checked by :meth:`robotd.app.pipeline.Pipeline.check`): it
    must hold a keyframe before that keyframe's loop candidates arrive, all three being
    subscribers of :class:`KeyframeStored`."""

    name = "graph"
    produces = (CandidateFate, Link)
    optional_inputs = (LoopCandidate, ForwardLoop, MapMatch, WheelDrop)
    precedes = ("floor", "forward")  # they publish a stored keyframe's loops: it must be in the graph

    def __init__(self, graph: IncrementalGraph, store: MapStore, *, gate_chi2: float = GATE_CHI2_3DOF_999,
                 save_every: int = 0, forward_mount: np.ndarray | None = None,
                 forward_params: PlanarLoopParams | None = None,
                 mapped_ground: MappedGroundParams | None = None,
                 reloc_params: RelocParams | None = None) -> None:
        self.graph = graph
        self.gated = GatedGraph(graph, self._publish, self._joined_map, gate_chi2=gate_chi2,
                                mapped_ground=mapped_ground, reloc_params=reloc_params)
        self.forward_mount = np.zeros(3) if forward_mount is None else np.asarray(forward_mount, float)
        self.forward_params = PlanarLoopParams() if forward_params is None else forward_params
        self.store = store
        self.save_every = save_every
        self.solves = 0
        self.solve_failures = 0
        self.last_solve_ms = 0.0
        self._since_save = 0

    @property
    def mapped_ground(self) -> MappedGround | None:
        """The localisation over mapped ground (None when off): this stage owns it, the map
        writer reaches it through :class:`robotd.app.stages.map_writer.KeyframeChain`."""
        return self.gated.mapped_ground

    @property
    def gate_chi2(self) -> float:
        return self.gated.gate_chi2

    @property
    def relocalised_at(self) -> list[dict[str, Any]]:
        """Per relocalisation, the figures logged."""
        return self.gated.relocalised_at

    def subscriptions(self) -> Mapping[type, Any]:
        return {Link: self.on_link, KeyframeStored: self.on_keyframe, LoopCandidate: self.on_candidate,
                ForwardLoop: self.on_forward_loop, MapMatch: self.on_map_match,
                WheelDrop: self.on_wheel_drop}

    def set_gate(self, gate_chi2: float) -> None:
        """Live reload: the chi-square gate on loop candidates."""
        self.gated.gate_chi2 = gate_chi2

    def set_save_every(self, keyframes: int) -> None:
        """Live reload: re-solve and save the graph every this many keyframes (0: at the end)."""
        self.save_every = keyframes

    def _joined_map(self, run_id: int) -> None:
        self.store.add_map_frame_run(run_id)

    def on_map_match(self, m: MapMatch) -> None:
        self.gated.map_match(m.from_id, m.delta_xyyaw, m.information)

    def on_link(self, link: Link) -> None:
        if link.kind == "odometry":
            self.gated.odometry_link(link.from_id, link.to_id, link.delta_xyyaw, link.information, link.bias)

    def on_wheel_drop(self, msg: WheelDrop) -> None:
        self.gated.wheel_drop(msg.lifted, msg.stamp_ns)

    def on_keyframe(self, msg: KeyframeStored) -> None:
        kf = msg.keyframe
        self.gated.keyframe(kf.keyframe_id, kf.run_id, kf.pose_xyyaw, kf.stamp_ns,
                            lambda run: self.store.map_frame_poses(exclude_run=run))
        self._since_save += 1
        if self.save_every and self._since_save >= self.save_every:
            self.solve_and_save()

    def on_candidate(self, c: LoopCandidate) -> None:
        self.gated.floor_candidate(c.from_id, c.to_id, c.score, c.delta_xyyaw, c.information)

    def on_forward_loop(self, c: ForwardLoop) -> None:
        def edge(predicted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return loop_edge(predicted, c.dyaw_rad, c.bearing_rad, self.forward_mount, self.forward_params,
                             range_m=c.range_m, sigma_bearing_rad=c.sigma_bearing_rad,
                             sigma_yaw_rad=c.sigma_yaw_rad)

        self.gated.forward_candidate(c.from_id, c.to_id, c.probability, edge, range_measured=c.range_m is not None,
                                     unsettled=c.sigma_yaw_rad is not None)

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
        release_freed_memory()
        self.last_solve_ms = (time.perf_counter() - t0) * 1e3
        self.solves += 1
        self._since_save = 0
        keep = self.gated.after_solve(result.ids, result.loop_weights)
        self.store.put_optimized_poses([int(result.ids[n]) for n in keep], result.poses[keep])
        log.info("pose graph: %d keyframes, %d loops, solved in %.0f ms", len(self.graph.graph),
                 self.gated.accepted, self.last_solve_ms)

    def finish(self) -> int:
        self.gated.finish()
        self.solve_and_save()
        warning = self.gated.end_warning()
        if warning:
            log.warning("%s", warning)
        return 0

    def optimized(self) -> tuple[np.ndarray, np.ndarray]:
        """The current estimate: ``(ids (N,), poses (N, 3))``."""
        return self.graph.estimate()

    def status_fragment(self) -> str:
        """Where the robot stands with the map, for the STATUS line."""
        return self.gated.status_fragment()

    def counters(self) -> dict[str, int]:
        u = np.asarray(self.gated.update_ms) if self.gated.update_ms else np.zeros(1)
        return {**self.gated.counters(),
                "graph_solves": self.solves, "graph_solve_failures": self.solve_failures,
                "graph_isam_failures": self.graph.isam_failures,  # each recovered: iSAM2 rebuilt whole
                "graph_loops_left_out": self.graph.held_loops,  # accepted and stored, not in the graph
                "graph_bias_windows": self.graph.bias_windows,  # [pose_graph] odometry_model "bias_window"
                "graph_update_median_us": int(np.median(u) * 1e3),
                "graph_update_p99_us": int(np.percentile(u, 99) * 1e3),
                "graph_solve_ms": int(self.last_solve_ms),
                **self._scale_counters()}

    def _scale_counters(self) -> dict[str, int]:
        """The scale variable's estimate in parts per million ([pose_graph] odometry_model
        "bias_scale_window"): how much too large the calibration's wheel distance and gyro
        rate are by the graph's loops."""
        s = self.graph.scale_estimate()
        if s is None:
            return {}
        return {"graph_scale_wheel_ppm": int(round(float(s[0]) * 1e6)),
                "graph_scale_gyro_ppm": int(round(float(s[1]) * 1e6))}
