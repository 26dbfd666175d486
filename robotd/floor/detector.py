"""The floor loop detector as the daemon uses it: describe each keyframe, query the map.

Each new keyframe's floor image is described (compact descriptor, mode from the config),
the map index is queried for earlier keyframes that look alike, excluding those taken in
the last ``exclude_recent_s`` seconds (they overlap trivially), and the keyframe is added
to the index. Which candidates are loops is decided later from the trained
P(loop | score) thresholds (paper 003 Sec. III-B, IV-C).
"""

from __future__ import annotations

import bisect
import math
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from robotd.base.config import FloorDetectorConfig
from robotd.floor.descriptor import decode, extract_with_positions
from robotd.floor.index import Candidate, FloorIndex
from robotd.floor.match import MatchParams
from robotd.base.geometry import (between_error_covariance, information_from_covariance, rigid_fit_2d,
                                  rigid_fit_2d_covariance)
from robotd.floor.vo import floor_point_pairs

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FloorDetectorParams:
    """``descriptor_mode``: descriptor mode 1-6 (paper 003) (512 B .. 16 kB per image); ``candidates``: how many
    candidates a query returns; ``shortlist``: keyframes scored locally per query after the
    global shortlist; ``exclude_recent_s``: keyframes younger than this are not queried;
    ``ransac_confidence``: :attr:`robotd.floor.match.MatchParams.confidence` of the query's
    local scores (0: every RANSAC hypothesis scored)."""

    descriptor_mode: int = FloorDetectorConfig.descriptor_mode
    candidates: int = FloorDetectorConfig.candidates
    shortlist: int = FloorDetectorConfig.shortlist
    exclude_recent_s: float = FloorDetectorConfig.exclude_recent_s
    ransac_confidence: float = FloorDetectorConfig.ransac_confidence

    @classmethod
    def from_config(cls, section: FloorDetectorConfig) -> FloorDetectorParams:
        """The params of a ``[floor_detector]`` table (whose defaults these are)."""
        return cls(descriptor_mode=section.descriptor_mode, candidates=section.candidates,
                   shortlist=section.shortlist, exclude_recent_s=section.exclude_recent_s,
                   ransac_confidence=section.ransac_confidence)


@dataclass(frozen=True, eq=False)
class Loop:
    """A declared loop: keyframe ``to_id`` sees the floor ``from_id`` saw.

    ``delta (3,)``: the pose of ``to_id`` in the frame of ``from_id`` (x_m, y_m, yaw_rad),
    from the inlier floor points; ``information (3, 3)``: its inverse covariance.
    """

    from_id: int
    to_id: int
    score: float
    n_inliers: int
    delta: np.ndarray
    information: np.ndarray


@dataclass(frozen=True, eq=False)
class KeyframeQuery:
    """What one keyframe's query found: its descriptor bytes, the candidates, and the
    candidates declared loops (local score at or above the mode's trained threshold)."""

    keyframe_id: int
    stamp_ns: int
    descriptor: bytes
    candidates: list[Candidate]
    loops: list[Loop]


#: The loop edge's noise model (see :func:`loop_transform`): maximum-likelihood values over the
#: loop edges of descriptor modes 1-6 on 150 rendered pairs of the printed-plank floor
#: (``bench/bench_nees.py --skip-odometry --floors planks --pairs 150 --seed 7`` prints them).
#: The floor on the inliers' residual sigma per coordinate, metres.
MIN_POINT_SIGMA_M = 8.7e-4
#: 1-sigma per axis, metres, of an offset the two views of a loop share in the camera's frame;
#: the turn between the views makes it a translation error ``(I - R(dyaw)) b``.
TURN_SIGMA_M = 4.5e-5


def loop_transform(camera: Any, xy_query_px: np.ndarray, xy_old_px: np.ndarray,
                   min_sigma_m: float = MIN_POINT_SIGMA_M, turn_sigma_m: float = TURN_SIGMA_M
                   ) -> tuple[np.ndarray, np.ndarray] | None:
    """Relative pose of the query keyframe in the old keyframe's frame, and its information.

    Matched pixels become floor points in each robot frame (camera model,
    :func:`robotd.floor.vo.floor_point_pairs`); the rigid fit maps the query's points onto
    the old ones (paper 003 Sec. IV-D, as visual odometry does). The covariance is the
    fit's Gauss-Newton one from its residuals (at least ``min_sigma_m`` per coordinate),
    :func:`robotd.base.geometry.rigid_fit_2d_covariance`, plus the error all the inliers share,
    turned into the frame the pose graph measures the edge's error in
    (:func:`robotd.base.geometry.between_error_covariance`). None if under 3 points.

    The fit's covariance takes the inliers' errors as independent, so it shrinks as one
    over their number; the error they share does not (each image's registration to the floor
    as a whole: in the simulator the resampling of the floor's texture and the camera's pixel
    grid, on a robot also the camera model and its mounting). An offset ``b`` the two views
    share in the camera's frame cancels when they look the same way and grows with the turn
    ``dyaw`` between them: the fit's translation is off by ``(I - R(dyaw)) b``, of covariance
    ``4 sin^2(dyaw / 2) turn_sigma_m^2`` on each axis. On rendered pairs the error shared by
    the inliers grows so with the turn, and a constant term beside it fits to zero
    (``docs/odometry.md``, "The loop edges' covariance").
    """
    po, pq = floor_point_pairs(camera, xy_old_px, xy_query_px)
    if len(pq) < 3:
        return None
    delta = rigid_fit_2d(pq, po)
    cov, _ = rigid_fit_2d_covariance(pq, po, delta, min_sigma_m)
    shared = 4.0 * math.sin(0.5 * float(delta[2])) ** 2 * turn_sigma_m ** 2
    cov[0, 0] += shared
    cov[1, 1] += shared
    return delta, information_from_covariance(between_error_covariance(delta, cov))


class FloorLoopDetector:
    """Describes keyframes and finds earlier look-alikes through a :class:`FloorIndex`."""

    def __init__(self, params: FloorDetectorParams, index: FloorIndex | None = None,
                 threshold: float | None = None, camera: Any = None) -> None:
        """``index``: the map's earlier keyframes (earlier runs, or this run before a
        restart of the detector), all of which count as old; ``threshold``: the mode's
        trained local-score threshold (None: declare no loops); ``camera``: the floor camera
        model, to turn matched pixels into a loop transform."""
        if threshold is not None and camera is None:
            raise ValueError("declaring loops needs the floor camera model")
        self.params = params
        self.threshold = threshold
        self.camera = camera
        self.index = index if index is not None else FloorIndex()
        # Every keyframe already in the index is old: its stamps belong to earlier runs,
        # whose clocks (CLOCK_MONOTONIC restarts at boot) cannot be compared with ours.
        ids = self.index.ids
        self._prior_max_id: int | None = int(ids.max()) if len(ids) else None
        # (stamp_ns, keyframe_id) of this run's keyframes, in time order, for the
        # recent-keyframe exclusion. Keyframe ids grow with time across runs.
        self._run_stamps: list[tuple[int, int]] = []

    @classmethod
    def from_store(cls, store: Any, params: FloorDetectorParams, threshold: float | None = None,
                   camera: Any = None) -> "FloorLoopDetector":
        """Rebuild the index from a map's stored descriptors of the same mode (a restart
        continues the same map: every stored keyframe is old to the new run). Descriptors
        that do not decode are skipped and counted."""
        index = FloorIndex.from_store(store, params.descriptor_mode)
        if len(index):
            log.info("floor index: %d keyframes loaded from the map", len(index))
        return cls(params, index, threshold, camera)

    def describe(self, image: np.ndarray) -> tuple[bytes, np.ndarray]:
        """The keyframe's compact descriptor (at most the mode's byte budget), and its
        keypoints where the detector found them, which the map does not store
        (:func:`robotd.floor.descriptor.extract_with_positions`)."""
        return extract_with_positions(image, self.params.descriptor_mode)

    def query_and_add(self, keyframe_id: int, stamp_ns: int, descriptor: bytes) -> KeyframeQuery:
        """Query the map with a stored keyframe's descriptor, then add it to the index."""
        return self._query(keyframe_id, stamp_ns, descriptor, add=True)

    def query(self, stamp_ns: int, descriptor: bytes) -> KeyframeQuery:
        """Query the map with a keyframe that is not stored (a transient keyframe over
        mapped ground): nothing is added; its loops carry ``to_id`` -1."""
        return self._query(-1, stamp_ns, descriptor, add=False)

    def _query(self, keyframe_id: int, stamp_ns: int, descriptor: bytes, *, add: bool) -> KeyframeQuery:
        desc = decode(descriptor)
        # Recent means: this run, and within exclude_recent_s. Everything before the last
        # of this run's keyframes older than the cutoff is old, and so is every keyframe of
        # an earlier run (their ids are all smaller than this run's).
        cutoff = stamp_ns - int(self.params.exclude_recent_s * 1e9)
        i = bisect.bisect_left(self._run_stamps, (cutoff, -1))
        last_old_id = self._run_stamps[i - 1][1] if i > 0 else self._prior_max_id
        candidates: list[Candidate] = []
        if last_old_id is not None:
            # Candidates that cannot reach the loop threshold are not checked
            # geometrically (they come back with score 0: nothing declares them a loop).
            candidates = self.index.query(desc, k=self.params.candidates,
                                          exclude_after_id=last_old_id,
                                          shortlist=self.params.shortlist,
                                          min_score=self.threshold or 0.0,
                                          match_params=(MatchParams(confidence=self.params.ransac_confidence)
                                                        if self.params.ransac_confidence > 0 else None))
        if add:
            self.index.add(keyframe_id, desc)
            if self._run_stamps and stamp_ns < self._run_stamps[-1][0]:
                log.warning("keyframe %d: stamp %d before the previous keyframe's within one run",
                            keyframe_id, stamp_ns)
                stamp_ns = self._run_stamps[-1][0]
            self._run_stamps.append((stamp_ns, keyframe_id))
        loops = []
        if self.threshold is not None:
            for c in candidates:
                if c.local.score < self.threshold:
                    continue
                fit = loop_transform(self.camera, c.local.xy_a, c.local.xy_b)
                if fit is not None:
                    loops.append(Loop(c.keyframe_id, keyframe_id, float(c.local.score),
                                      int(c.local.n_inliers), fit[0], fit[1]))
        return KeyframeQuery(keyframe_id, stamp_ns, descriptor, candidates, loops)
