"""The odometry stage: the one owner of the odometry filter (:mod:`robotd.odometry.fusion`)."""

from __future__ import annotations

import logging
from collections.abc import Mapping

from robotd.app.pipeline import Handler, Publisher
from robotd.app.stages.keyframes import KeyframeOdometry
from robotd.base.messages import BaseStatus, OdometryUpdate, VisualOdometryStep, WheelTicks, YawRate
from robotd.odometry.fusion import OdometryFilter

log = logging.getLogger(__name__)


class OdometryStage(Publisher):
    """Wheel ticks and gyro into the odometry filter (:mod:`robotd.odometry.ekf`); publishes
    an :class:`~robotd.base.messages.OdometryUpdate` after each accepted wheel reading.

    The stage owns the filter. Floor visual odometry reaches it as a message
    (:class:`~robotd.base.messages.VisualOdometryStep`, fused at its keyframe's time); the
    keyframe stage reads the wheel + gyro pose history through one narrow interface,
    :meth:`keyframe_odometry`.

    A base driver that knows its wheel readings have stopped (a stale wheel on a CAN
    bus) says so with :class:`~robotd.base.messages.BaseStatus`: the odometry is then
    ``degraded`` (``odometry_degraded`` 1, with ``degraded_detail``; the STATUS line
    says so) until the driver reports it healthy again; ``odometry_degraded_episodes``
    counts the times it became degraded.
    """

    name = "odometry"
    produces = (OdometryUpdate,)
    optional_inputs = (VisualOdometryStep, BaseStatus)

    def __init__(self, odometry: OdometryFilter) -> None:
        self.odometry = odometry
        self.wheel_msgs = 0
        self.yaw_msgs = 0
        self.rejected = 0
        self.degraded = False
        self.degraded_detail = ""
        self.degraded_episodes = 0

    def subscriptions(self) -> Mapping[type, Handler]:
        return {WheelTicks: self.on_wheels, YawRate: self.on_yaw_rate,
                BaseStatus: self.on_base_status, VisualOdometryStep: self.on_visual_step}

    def keyframe_odometry(self) -> KeyframeOdometry:
        """The wheel + gyro filter's pose history and keyframe edges (the twin when visual
        odometry is fused: :attr:`robotd.odometry.fusion.OdometryFilter.wheel_gyro`), for the
        keyframe stage, its only reader."""
        return self.odometry.wheel_gyro

    @property
    def vo_gate_nis(self) -> float:
        """The filter's chi-square gate on a visual step (3 degrees of freedom)."""
        return self.odometry.vo_gate_nis

    def on_base_status(self, msg: BaseStatus) -> None:
        if msg.degraded and not self.degraded:
            self.degraded_episodes += 1
            log.warning("odometry degraded: %s", msg.detail)
        elif self.degraded and not msg.degraded:
            log.info("odometry no longer degraded")
        self.degraded = msg.degraded
        self.degraded_detail = msg.detail if msg.degraded else ""

    def on_wheels(self, msg: WheelTicks) -> None:
        self.wheel_msgs += 1
        if self.odometry.on_wheels(msg) is False:
            self.rejected += 1
            return
        if self.pipeline is not None and self.pipeline.subscribed(OdometryUpdate):
            self._publish(OdometryUpdate(self.odometry.pose(), self.odometry.wheel_pose()))

    def on_yaw_rate(self, msg: YawRate) -> None:
        self.yaw_msgs += 1
        if self.odometry.on_yaw_rate(msg) is False:
            self.rejected += 1

    def on_visual_step(self, msg: VisualOdometryStep) -> None:
        """Fuse a floor visual odometry step at its keyframe's time
        (:meth:`robotd.odometry.fusion.OdometryFilter.on_visual_odometry`)."""
        self.odometry.on_visual_odometry(msg.stamp_ns, msg.prev_stamp_ns, msg.delta_xyyaw, msg.covariance)

    def counters(self) -> dict[str, int]:
        f = self.odometry.counters
        return {"wheel_msgs": self.wheel_msgs, "yaw_msgs": self.yaw_msgs,
                "odometry_rejected": self.rejected, "odometry_degraded": int(self.degraded),
                "odometry_degraded_episodes": self.degraded_episodes, "vo_fused": f.vo_fused,
                "vo_rejected_by_filter": f.vo_rejected}
