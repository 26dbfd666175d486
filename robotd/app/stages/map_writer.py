"""The map writer stage: keyframes and links into the map store."""

from __future__ import annotations

import collections
import logging
from collections.abc import Mapping
from typing import Protocol

import numpy as np

from robotd.app.pipeline import Handler, Publisher
from robotd.base.geometry import information_from_covariance
from robotd.base.messages import (
    CandidateFate,
    DescribedKeyframe,
    Keyframe,
    KeyframeStored,
    Link,
    MeasuredKeyframe,
    StoredKeyframe,
    TransientKeyframe,
    keyframe_as,
)
from robotd.io.store import MapStore
from robotd.keyframes import downsample
from robotd.odometry.increments import odometry_edge

log = logging.getLogger(__name__)


class KeyframeChain(Protocol):
    """What the map writer asks of the localisation over mapped ground
    (:class:`robotd.graph.mappedground.MappedGround`, owned by the pose graph stage)."""

    def is_transient(self, odom_pose: np.ndarray) -> bool: ...

    def chain_broken(self) -> None: ...

    def extend(self, edge: tuple[np.ndarray, np.ndarray], odom_pose: np.ndarray) -> None: ...

    def edge_for_stored(self, previous_id: int | None, edge: tuple[np.ndarray, np.ndarray],
                        ) -> tuple[int | None, np.ndarray, np.ndarray]: ...

    def stored(self, keyframe_id: int, odom_pose: np.ndarray) -> None: ...


class MapWriterStage(Publisher):
    """Writes keyframes and links to the map store.

    It takes ``takes``, the last keyframe message of the pipeline (a
    :class:`~robotd.base.messages.MeasuredKeyframe` with visual odometry, a
    :class:`~robotd.base.messages.DescribedKeyframe` with the floor detector alone, else the
    bare :class:`~robotd.base.messages.Keyframe`), and publishes
    :class:`~robotd.base.messages.KeyframeStored` with the map's id.

    Each keyframe after the run's first also gets an odometry link from the previous one:
    ``Keyframe.odometry_edge``, the filter's increment with its covariance from the pose
    clone (:meth:`robotd.odometry.fusion.OdometryFilter.keyframe_edge`) or what visual
    odometry made of it. A keyframe without one (the filter had no clone) falls back to the
    relative transform of the fused poses with the difference of their covariances
    (:func:`robotd.odometry.increments.odometry_edge`). No odometry link crosses a time the
    robot was lifted (``Keyframe.carried``): the keyframe after it starts a new chain
    (``odometry_breaks``), which the pose graph relocalises. With localisation over mapped
    ground (``chain``, :class:`robotd.graph.mappedground.MappedGround`), a keyframe over
    mapped ground is not stored: it extends the chain and goes out as a
    :class:`~robotd.base.messages.TransientKeyframe`.
    """

    name = "map"
    produces = (KeyframeStored, TransientKeyframe, Link)
    optional_inputs = (CandidateFate,)

    def __init__(self, store: MapStore, run_id: int, *, image_width_px: int,
                 takes: type[Keyframe] = MeasuredKeyframe, chain: KeyframeChain | None = None) -> None:
        self.store = store
        self.run_id = run_id
        self.image_width_px = image_width_px
        self.takes = takes
        self.chain = chain
        self._previous: Keyframe | None = None
        self._previous_id: int | None = None  # None: the previous keyframe was not stored
        self.stored = 0
        self.transient = 0
        self.links = collections.Counter[str]()
        self.fates = collections.Counter[str]()
        self._fates: list[tuple[int, int, float, str, str]] = []
        self.odometry_breaks = 0

    def subscriptions(self) -> Mapping[type, Handler]:
        return {self.takes: self.on_keyframe, Link: self.on_link, CandidateFate: self.on_fate}

    def on_fate(self, fate: CandidateFate) -> None:
        self._fates.append((fate.query_id, fate.candidate_id, fate.score, fate.fate, fate.detail))
        self.fates[fate.fate] += 1

    def flush_fates(self) -> None:
        """Write the candidates' fates gathered since the last flush (one transaction)."""
        if self._fates:
            self.store.add_loop_candidates(self._fates)
            self._fates = []

    def finish(self) -> int:
        self.flush_fates()
        return 0

    def on_keyframe(self, kf: Keyframe) -> None:
        mapped = self.chain
        transient = mapped is not None and mapped.is_transient(kf.pose_xyyaw)
        prev = self._previous
        carried = prev is not None and kf.carried
        if carried:  # no odometry link across a lift: the wheels did not see the motion
            prev = None
            if mapped is not None:
                mapped.chain_broken()
        edge = None if prev is None else self._odometry_edge(prev, kf)
        if mapped is not None and transient and edge is not None:
            # Over mapped ground: not stored, the odometry chain grows (robotd.graph.mappedground).
            mapped.extend((edge[0], np.linalg.inv(edge[1])), kf.pose_xyyaw)
            self._previous, self._previous_id = kf, None
            self.transient += 1
            self._publish(TransientKeyframe(kf))
            return
        stored = self._store(kf)  # a failed write raises here and leaves the chain as it was
        previous_id = self._previous_id
        self._previous, self._previous_id = kf, stored.keyframe_id
        if carried:
            self.odometry_breaks += 1
            log.info("keyframe %d: the robot was carried since the previous keyframe; no odometry "
                     "link between them", stored.keyframe_id)
        if edge is not None:
            from_id: int | None = previous_id
            delta, info = edge
            if mapped is not None:  # from the chain's start when transient keyframes came between
                from_id, delta, cov = mapped.edge_for_stored(previous_id, (delta, np.linalg.inv(info)))
                info = information_from_covariance(cov)
            if from_id is not None:  # the bias terms only for the filter's own edge, not a chain's
                bias = kf.odometry_bias if from_id == previous_id and kf.odometry_edge is not None else None
                self._publish(Link("odometry", from_id, stored.keyframe_id, delta, info, bias=bias))
        if mapped is not None:
            mapped.stored(stored.keyframe_id, kf.pose_xyyaw)
        self._publish(KeyframeStored(stored))
        self.flush_fates()

    @staticmethod
    def _odometry_edge(prev: Keyframe, kf: Keyframe) -> tuple[np.ndarray, np.ndarray]:
        """``(delta, information)`` from the previous keyframe (stored or not) to ``kf``."""
        if kf.odometry_edge is not None:  # measured by the filter or by visual odometry
            delta, cov = kf.odometry_edge
            return np.asarray(delta, float), information_from_covariance(cov)
        return odometry_edge(prev.pose_xyyaw, prev.pose.covariance, kf.pose_xyyaw, kf.pose.covariance)

    def _store(self, kf: Keyframe) -> StoredKeyframe:
        descriptor = mode = None
        if isinstance(kf, DescribedKeyframe) and kf.descriptor is not None:
            mode, descriptor = kf.descriptor
        keyframe_id = self.store.add_keyframe(
            self.run_id, kf.stamp_ns, kf.pose_xyyaw, kf.pose.covariance,
            downsample(kf.frame.image, self.image_width_px),
            descriptor=descriptor, descriptor_mode=mode,
        )
        self.stored += 1
        # The acknowledgement (debug level: several a second): add_keyframe has committed.
        log.debug("keyframe %d committed (run %d, %d stored)", keyframe_id, self.run_id, self.stored)
        return keyframe_as(StoredKeyframe, kf, keyframe_id=keyframe_id, run_id=self.run_id)

    def on_link(self, link: Link) -> None:
        self.store.add_link(link.kind, link.from_id, link.to_id, link.delta_xyyaw, link.information)
        self.links[link.kind] += 1

    def counters(self) -> dict[str, int]:
        return {"keyframes_stored": self.stored, "keyframes_not_stored": self.transient,
                "odometry_breaks": self.odometry_breaks,
                **{f"links_{k}": n for k, n in sorted(self.links.items())},
                **{f"candidates_{k}": n for k, n in sorted(self.fates.items())}}
