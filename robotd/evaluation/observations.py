"""What a run's pipeline published, kept for the evaluation against ground truth.

:class:`RunObservations` is a pipeline observer (``subscriptions()``, as the stages): it
keeps the stored keyframes, the floor queries' candidates, the declared loops and the
forward loops with their fates. No I/O; :mod:`robotd.evaluation.groundtruth` judges them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from robotd.base.messages import CandidateFate, ForwardLoop, KeyframeStored, Link, LoopFate
from robotd.floor.detector import KeyframeQuery

FloorQuery = tuple[int, list[tuple[int, float, float, int]]]
"""One floor query: the query keyframe's id and its candidates ``(keyframe id, local score,
global score, inliers)``."""


class RunObservations:
    """Pipeline observer that keeps what the evaluation needs, in publication order."""

    name = "run_observations"

    def __init__(self) -> None:
        self.keyframe_ids: list[int] = []
        self.keyframe_stamps: list[int] = []
        self.keyframe_poses: list[tuple[float, float, float]] = []  # the filter's (x_m, y_m, yaw_rad)
        self.visual_poses: dict[int, np.ndarray] = {}  # keyframe id -> VO-only pose (3,), when VO is on
        self.queries: list[FloorQuery] = []
        self.loops: list[tuple[int, int]] = []  # declared floor loops: (older keyframe, newer)
        self.refused: list[tuple[int, int]] = []  # refused by the graph's chi-square gate: (older, newer)
        self.forward_loops: list[ForwardLoop] = []  # verified by the forward camera
        self.forward_fates: dict[tuple[int, int], LoopFate] = {}  # (older, newer) -> fate
        self.forward_fate_details: dict[tuple[int, int], str] = {}  # (older, newer) -> why (the gate's chi2)

    def subscriptions(self) -> dict[type, Callable[..., None]]:
        return {KeyframeStored: self.on_keyframe, KeyframeQuery: self.on_floor_query, Link: self.on_link,
                CandidateFate: self.on_fate, ForwardLoop: self.forward_loops.append}

    def on_fate(self, fate: CandidateFate) -> None:
        if fate.detail.startswith("forward: "):
            self.forward_fates[(fate.candidate_id, fate.query_id)] = fate.fate
            self.forward_fate_details[(fate.candidate_id, fate.query_id)] = fate.detail[len("forward: "):]
        elif fate.fate == LoopFate.FAILED_GATE and fate.detail.startswith("chi2"):  # not an earlier run's
            self.refused.append((fate.candidate_id, fate.query_id))

    def on_link(self, link: Link) -> None:
        if link.kind == "loop" and link.source == "floor":
            self.loops.append((link.from_id, link.to_id))

    def on_keyframe(self, msg: KeyframeStored) -> None:
        kf = msg.keyframe
        assert kf.keyframe_id is not None  # set once stored
        self.keyframe_poses.append((kf.pose.x_m, kf.pose.y_m, kf.pose.yaw_rad))
        self.keyframe_ids.append(kf.keyframe_id)
        self.keyframe_stamps.append(kf.stamp_ns)
        if kf.visual_pose is not None:
            self.visual_poses[kf.keyframe_id] = np.asarray(kf.visual_pose, dtype=float)

    def on_floor_query(self, query: KeyframeQuery) -> None:
        self.queries.append((query.keyframe_id, [
            (c.keyframe_id, float(c.local.score), float(c.global_score), int(c.local.n_inliers))
            for c in query.candidates]))

    @property
    def stamps_ns(self) -> np.ndarray:
        """``(K,) int64`` stamps of the stored keyframes."""
        return np.asarray(self.keyframe_stamps, dtype=np.int64)
