"""The floor loop detector stage (paper 003): describes keyframes, queries the map."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from robotd.app.pipeline import Handler, Publisher
from robotd.base.messages import (
    CandidateFate,
    DescribedKeyframe,
    Keyframe,
    KeyframeStored,
    LoopCandidate,
    LoopFate,
    MapMatch,
    TransientKeyframe,
    keyframe_as,
)
from robotd.floor.detector import FloorLoopDetector, KeyframeQuery


class FloorDetectorStage(Publisher):
    """The floor loop detector (:class:`robotd.floor.detector.FloorLoopDetector`).

    Describes each :class:`Keyframe` (publishing it again as a
    :class:`~robotd.base.messages.DescribedKeyframe`, whose descriptor the map stores in the
    keyframe's row), then queries the map with each stored keyframe. Publishes the query
    result (a :class:`~robotd.floor.detector.KeyframeQuery`), a :class:`LoopCandidate` per
    candidate at or above the trained threshold (the pose graph gates it), and the fate of
    the others (:class:`CandidateFate`). A transient keyframe (over mapped ground) is
    matched against the map, not added; its matches go out as :class:`MapMatch`.
    """

    name = "floor"
    produces = (DescribedKeyframe, KeyframeQuery, LoopCandidate, CandidateFate, MapMatch)
    optional_inputs = (TransientKeyframe,)

    def __init__(self, detector: FloorLoopDetector) -> None:
        self.detector = detector
        self.queries = 0
        self.transient_queries = 0
        self.candidates = 0
        self.loops = 0

    def subscriptions(self) -> Mapping[type, Handler]:
        return {Keyframe: self.describe, KeyframeStored: self.query, TransientKeyframe: self.query_transient}

    @property
    def mode(self) -> int:
        """The descriptor mode (fixed for the daemon's life)."""
        return self.detector.params.descriptor_mode

    @property
    def threshold(self) -> float | None:
        """The trained loop threshold of the mode (None: untrained, no loops declared)."""
        return self.detector.threshold

    def set_threshold(self, threshold: float | None) -> None:
        """Live reload: the calibration file's loop threshold for the running mode."""
        self.detector.threshold = threshold

    def set_query_params(self, **changes: object) -> None:
        """Live reload: the map query's sizes (``candidates``, ``shortlist``,
        ``exclude_recent_s`` of :class:`robotd.floor.detector.FloorDetectorParams`)."""
        self.detector.params = dataclasses.replace(self.detector.params, **changes)  # type: ignore[arg-type]

    def describe(self, kf: Keyframe) -> None:
        coded, positions = self.detector.describe(kf.frame.image)
        self._publish(keyframe_as(DescribedKeyframe, kf, descriptor=(self.detector.params.descriptor_mode, coded),
                                  keypoints_px=positions))

    def query_transient(self, msg: TransientKeyframe) -> None:
        kf = msg.keyframe
        if not isinstance(kf, DescribedKeyframe) or kf.descriptor is None:
            return
        result = self.detector.query(kf.stamp_ns, kf.descriptor[1])
        self.transient_queries += 1
        for loop in result.loops:
            self._publish(MapMatch(loop.from_id, loop.score, loop.delta, loop.information))

    def query(self, msg: KeyframeStored) -> None:
        kf = msg.keyframe
        if kf.descriptor is None:
            return
        result = self.detector.query_and_add(kf.keyframe_id, kf.stamp_ns, kf.descriptor[1])
        self.queries += 1
        self.candidates += len(result.candidates)
        self._publish(result)
        threshold = self.detector.threshold
        declared = {loop.from_id for loop in result.loops}
        for c in result.candidates:
            score = float(c.local.score)
            if threshold is None:
                continue  # untrained: nothing is declared, nothing to record
            if score < threshold:
                self._publish(CandidateFate(kf.keyframe_id, c.keyframe_id, score, LoopFate.BELOW_THRESHOLD,
                                            f"score {score:.2f} < {threshold:.2f}"))
            elif c.keyframe_id not in declared:
                self._publish(CandidateFate(kf.keyframe_id, c.keyframe_id, score, LoopFate.NO_TRANSFORM,
                                            "fewer than 3 inliers map onto the floor"))
        for loop in result.loops:
            self.loops += 1
            self._publish(LoopCandidate(loop.from_id, loop.to_id, loop.score, loop.delta,
                                        loop.information))

    def counters(self) -> dict[str, int]:
        return {"floor_queries": self.queries, "floor_transient_queries": self.transient_queries,
                "floor_candidates": self.candidates,
                "loop_candidates_above_threshold": self.loops}
