"""Localisation over mapped ground: the map stops growing where the robot has already been.

A robot that drives the same rooms for weeks would otherwise add a keyframe every few
centimetres on every pass. The map file, the floor index and, worst, the pose graph grow
with the distance driven, not with the area covered: every pass is tied to the earlier
ones by loops, so iSAM2's cliques and each update's time grow with the number of passes
(measured with `bench/bench_soak.py`: the per-frame time and the resident memory of the
daemon rise lap after lap over the same figure eight). With ``[pose_graph]
localise_mapped`` on, the daemon switches between two modes, as lifelong mapping systems do
(Cartographer's pure localisation, RTAB-Map's graph reduction), in the simplest form that
keeps every stored edge a measured one:

- **Mapping** (the default state): every keyframe is stored, becomes a graph node with its
  odometry edge, and its loops are gated and added as before.
- The robot is **localised** once a loop has been accepted for the newest stored keyframe.
  The *anchor* is then a graph node together with the pose, relative to that node, of a
  reference keyframe whose odometry pose is known.
- While localised, a keyframe whose predicted map position (anchor, then the odometry since
  the reference keyframe) lies within ``mapped_radius_m`` of a keyframe already in the graph
  is **transient**: it is described and queried against the map, but not stored, not
  indexed and not a graph node.
- A transient keyframe's match (a floor candidate at the trained threshold, with its metric
  relative pose) meets the graph's chi-square gate against the prediction, and if it
  passes, re-anchors the robot on the matched keyframe: pure localisation, the map is not
  changed.
- The robot is back to mapping when the prediction is farther than ``mapped_radius_m`` from
  every keyframe (new ground), or when it has travelled ``max_unlocalised_m`` without an
  accepted match (odometry alone is not trusted to say "this is mapped ground" for long).
  The next keyframe is stored with an odometry edge from the anchor's node: the anchor's
  relative pose composed with the odometry chain since, and their covariances propagated
  to first order in the graph's own error convention (:func:`compose_edges`).

Nothing here does I/O; the stages that own the map and the graph call it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from robotd.base.geometry import between, compose, inverse


def adjoint(pose: np.ndarray) -> np.ndarray:
    """``(3, 3)`` adjoint of an SE(2) pose ``(x, y, yaw)`` on tangent vectors ``(vx, vy, w)``
    (GTSAM's ``Pose2.AdjointMap``): ``T exp(xi) = exp(Ad_T xi) T``."""
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    return np.array([[c, -s, float(pose[1])], [s, c, -float(pose[0])], [0.0, 0.0, 1.0]])


# Edge covariances follow the pose graph's convention (GTSAM's BetweenFactor, g2o's
# EDGE_SE2): the error of a relative pose ``delta`` is a tangent vector at its end,
# ``delta_true = delta exp(xi)``, ``xi ~ N(0, covariance)``
# (robotd.base.geometry.between_error_covariance).
def compose_edges(a: tuple[np.ndarray, np.ndarray],
                  b: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``(delta, covariance)`` of two relative poses in a row, ``a (+) b``, independent
    errors, to first order: ``a exp(xa) b exp(xb) = a b exp(Ad(b^-1) xa) exp(xb)``."""
    ad = adjoint(inverse(b[0]))
    cov = ad @ a[1] @ ad.T + b[1]
    return compose(a[0], b[0]), 0.5 * (cov + cov.T)


def invert_edge(e: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``(delta, covariance)`` of the inverse relative pose, to first order:
    ``(d exp(x))^-1 = d^-1 exp(-Ad(d) x)``."""
    ad = adjoint(e[0])
    cov = ad @ e[1] @ ad.T
    return inverse(e[0]), 0.5 * (cov + cov.T)


log = logging.getLogger(__name__)

_ZERO = np.zeros(3)
_NO_COV = np.zeros((3, 3))


@dataclass(frozen=True, slots=True)
class MappedGroundParams:
    """See the module notes. ``mapped_radius_m``: a keyframe this close (by position) to a
    graph node counts as mapped ground; ``max_unlocalised_m``: travel allowed on mapped
    ground without an accepted match before the robot maps again."""

    mapped_radius_m: float = 0.15
    max_unlocalised_m: float = 1.0


class MappedGround:
    """The localisation state over mapped ground, owned by the pose graph stage (which
    reports accepted loops and gates transient matches); the map writer reaches it through
    :class:`robotd.app.stages.map_writer.KeyframeChain` (it asks whether a keyframe is
    transient, chains odometry edges and asks for the edge of the next stored keyframe). ``pose_of(id)`` gives a graph node's current estimate ``(3,)``,
    ``positions()`` every node's ``(N, 2)`` position, ``chi2(from_id, to_id, delta,
    information)`` the graph's gate statistic of a relative pose between two nodes."""

    def __init__(self, params: MappedGroundParams, pose_of: Callable[[int], np.ndarray],
                 positions: Callable[[], np.ndarray],
                 chi2: Callable[[int, int, np.ndarray, np.ndarray], float]) -> None:
        self.params = params
        self._pose_of = pose_of
        self._positions = positions
        self._chi2 = chi2
        self.node: int | None = None  # the graph node the chain starts at
        self.node_to_ref: tuple[np.ndarray, np.ndarray] = (_ZERO, _NO_COV)
        self.chain: tuple[np.ndarray, np.ndarray] = (_ZERO, _NO_COV)  # reference -> newest keyframe
        # A transient keyframe or a re-anchoring since the newest stored keyframe: the next
        # stored keyframe's edge starts at self.node through node_to_ref and the chain.
        self._moved = False
        self.ref_odom_pose: np.ndarray | None = None  # odometry pose of the reference keyframe
        self.chain_odom_pose: np.ndarray | None = None  # odometry pose of the newest keyframe
        self.localised = False
        self.travelled_m = 0.0  # since the last accepted loop or match
        self.transient = 0
        self.matches_accepted = 0
        self.matches_failed_gate = 0
        self.entered = 0  # times the robot went from mapping to localising
        self.left_new_ground = 0
        self.left_unlocalised = 0

    # --- the map writer -----------------------------------------------------------------
    def is_transient(self, odom_pose: np.ndarray) -> bool:
        """Whether a keyframe taken at ``odom_pose`` (the fused odometry pose) lies on mapped
        ground while the robot is localised: it is then not stored."""
        if not self.localised or self.node is None or self.ref_odom_pose is None:
            return False
        step = 0.0 if self.chain_odom_pose is None else float(np.hypot(*(odom_pose[:2] - self.chain_odom_pose[:2])))
        if self.travelled_m + step > self.params.max_unlocalised_m:
            self.localised = False
            self.left_unlocalised += 1
            log.info("mapped ground: %.2f m without an accepted match; storing keyframes again",
                     self.travelled_m + step)
            return False
        predicted = compose(compose(self._pose_of(self.node), self.node_to_ref[0]),
                            between(self.ref_odom_pose, np.asarray(odom_pose, float)))
        xy = self._positions()
        if not len(xy) or float(np.min(np.hypot(*(xy - predicted[:2]).T))) > self.params.mapped_radius_m:
            self.localised = False
            self.left_new_ground += 1
            log.info("mapped ground left: new ground, storing keyframes again")
            return False
        return True

    def extend(self, edge: tuple[np.ndarray, np.ndarray], odom_pose: np.ndarray) -> None:
        """A transient keyframe: its odometry edge from the previous keyframe ``(delta,
        covariance)`` extends the chain."""
        self.chain = compose_edges(self.chain, edge)
        self.travelled_m += float(np.hypot(edge[0][0], edge[0][1]))
        self.chain_odom_pose = np.asarray(odom_pose, float)
        self.transient += 1
        self._moved = True

    def edge_for_stored(self, previous_id: int | None,
                        edge: tuple[np.ndarray, np.ndarray]) -> tuple[int | None, np.ndarray, np.ndarray]:
        """The odometry edge ``(from_id, delta, covariance)`` of a keyframe about to be
        stored, given its edge from the previous keyframe (``previous_id``: that keyframe's
        id if it was stored). Without transient keyframes in between it is that edge."""
        if self.node is None or not self._moved:
            return previous_id, edge[0], edge[1]
        delta, cov = compose_edges(compose_edges(self.node_to_ref, self.chain), edge)
        return self.node, delta, cov

    def stored(self, keyframe_id: int, odom_pose: np.ndarray) -> None:
        """A keyframe was stored (and is, or is about to be, a graph node): the chain
        restarts at it."""
        self.node = keyframe_id
        self.node_to_ref = (_ZERO, _NO_COV)
        self.chain = (_ZERO, _NO_COV)
        self.ref_odom_pose = self.chain_odom_pose = np.asarray(odom_pose, float)
        self.travelled_m = 0.0
        self._moved = False

    def chain_broken(self) -> None:
        """The robot was carried (no odometry across): no longer localised; the next keyframe
        is stored and starts a new chain."""
        if self.localised:
            log.info("mapped ground: the robot was carried; storing keyframes until it is localised again")
        self.localised = False

    # --- the pose graph stage -----------------------------------------------------------
    def loop_accepted(self, query_id: int) -> None:
        """A loop was accepted for stored keyframe ``query_id``: if it is the newest, the
        robot is localised."""
        if query_id == self.node and not self._moved:
            if not self.localised:
                self.entered += 1
                log.info("mapped ground: localised at keyframe %d; keyframes over mapped ground "
                         "are not stored", query_id)
            self.localised = True
            self.travelled_m = 0.0

    def match(self, old_id: int, delta: np.ndarray, information: np.ndarray,
              gate_chi2: float) -> tuple[bool, float]:
        """A transient keyframe (the newest: the chain ends at it) matched stored keyframe
        ``old_id`` with relative pose ``delta`` (the transient in ``old_id``'s frame).
        Gated against the prediction; accepted, it re-anchors the robot on ``old_id``.
        Returns ``(accepted, chi2)``."""
        if self.node is None or not self.localised:
            return False, math.inf
        loop = (np.asarray(delta, float), np.linalg.inv(np.asarray(information, float)))
        # The measured relative pose node -> old: (node -> transient) (+) (transient -> old).
        node_to_old, cov = compose_edges(compose_edges(self.node_to_ref, self.chain), invert_edge(loop))
        if old_id == self.node:
            d2 = float(node_to_old @ np.linalg.solve(cov + 1e-12 * np.eye(3), node_to_old))
        else:
            d2 = self._chi2(self.node, old_id, node_to_old, np.linalg.inv(cov))
        if not d2 <= gate_chi2:
            self.matches_failed_gate += 1
            return False, d2
        self.matches_accepted += 1
        self.node = old_id
        self.node_to_ref = loop
        self.ref_odom_pose = self.chain_odom_pose
        self.chain = (_ZERO, _NO_COV)
        self.travelled_m = 0.0
        self._moved = True
        return True, d2

    def counters(self) -> dict[str, int]:
        return {"keyframes_transient": self.transient, "localise_matches_accepted": self.matches_accepted,
                "localise_matches_failed_gate": self.matches_failed_gate,
                "localise_entered": self.entered, "localise_left_new_ground": self.left_new_ground,
                "localise_left_unlocalised": self.left_unlocalised}
