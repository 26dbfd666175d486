"""The keyframe stage: floor frames take the odometry pose at their stamp; some become
keyframes (:class:`~robotd.base.messages.Keyframe`)."""

from __future__ import annotations

import collections
from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

from robotd.app.pipeline import Handler, Publisher
from robotd.base.clock import Clock
from robotd.base.messages import Frame, Keyframe, PoseStamped, WheelDrop
from robotd.keyframes import KeyframeSelector


class KeyframeOdometry(Protocol):
    """What the keyframe stage reads of the wheel + gyro filter (owned by the odometry
    stage, :meth:`robotd.app.stages.odometry.OdometryStage.keyframe_odometry`; implemented
    by :class:`robotd.odometry.fusion.OdometryFilter`)."""

    def settled_stamp_ns(self) -> int | None: ...

    def pose_at(self, stamp_ns: int) -> PoseStamped | None: ...

    def keyframe_edge(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray] | None: ...

    def keyframe_edge_terms(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray, Any] | None: ...


class LiftIntervals:
    """When the robot was off the floor, from the base's :class:`WheelDrop` messages
    (stamps, ns): a frame taken then shows nothing of the floor it will be put down on, and
    no odometry edge may cross such an interval (the robot was carried)."""

    def __init__(self) -> None:
        self.intervals: list[list[int | None]] = []  # [lifted_ns, put_down_ns or None]

    def on_wheel_drop(self, msg: WheelDrop) -> None:
        lifted = bool(self.intervals) and self.intervals[-1][1] is None
        if msg.lifted and not lifted:
            self.intervals.append([msg.stamp_ns, None])
        elif not msg.lifted and lifted:
            self.intervals[-1][1] = msg.stamp_ns

    def covers(self, stamp_ns: int) -> bool:
        """Whether the robot was off the floor at ``stamp_ns``."""
        return any(a is not None and a <= stamp_ns and (b is None or stamp_ns <= b)
                   for a, b in reversed(self.intervals))

    def lifted_between(self, a_ns: int, b_ns: int) -> bool:
        """Whether the robot was lifted at some time in ``(a_ns, b_ns]``."""
        return any(a is not None and a_ns < a <= b_ns for a, _b in reversed(self.intervals))


class KeyframeStage(Publisher):
    """Floor frames take the odometry pose at their stamp; some become keyframes.

    The pose is the wheel + gyro filter's (:attr:`OdometryFilter.wheel_gyro`): with floor
    visual odometry fused, the fused pose depends on when each visual step reached the
    filter, which live is whenever the pipeline got to its keyframe; the keyframes and
    their edges must not (a replay reproduces the live map).

    A frame is held until the odometry has settled past its stamp, so every keyframe pose is
    interpolated, never extrapolated, and final (a replay gives the same poses). Live
    (``lossless=False``), a frame that waits longer than ``max_sync_wait_s`` of clock time
    is dropped and counted in ``frames_unsynced`` (the base stopped talking; fresh frames
    matter more). Lossless (replay, the virtual robot), a frame waits as long as it takes:
    its odometry is on its way, and dropping it would make the result depend on the CPU.

    The stage owns the lift intervals (:class:`LiftIntervals`): while the base reports a
    wheel drop (the robot is carried), frames are not keyframes (counted in
    ``frames_lifted``): the camera sees nothing of the floor the robot will be put down on;
    a keyframe after a lift says so (``Keyframe.carried``), and the map writer links no
    odometry edge to it.

    Each keyframe carries the filter's motion since the previous keyframe, with its
    covariance from the pose clone (``Keyframe.odometry_edge``; None at the first one).
    """

    name = "keyframes"
    produces = (Keyframe,)
    optional_inputs = (WheelDrop,)

    def __init__(self, odometry: KeyframeOdometry | None, clock: Clock, *, distance_m: float, rotation_rad: float,
                 max_sync_wait_s: float, lossless: bool, camera: str = "floor",
                 max_pending: int = 64, bias_terms: bool = False) -> None:
        self.odometry = odometry  # None: no base, frames cannot get a pose
        self.bias_terms = bias_terms  # the edges' bias terms too ([pose_graph] odometry_model)
        self.clock = clock
        self.selector = KeyframeSelector(distance_m, rotation_rad)
        self.camera = camera
        self.lossless = lossless
        self.max_pending = max_pending
        self._max_wait_ns = int(max_sync_wait_s * 1e9)
        self.pending: collections.deque[Frame] = collections.deque()
        self.frames = 0
        self.frames_unsynced = 0
        self.frames_without_odometry = 0
        self.frames_other_camera = 0
        self.frames_lifted = 0
        self.keyframes = 0
        self.lifts = LiftIntervals()
        self._previous_ns: int | None = None  # the previous keyframe's stamp

    def subscriptions(self) -> Mapping[type, Handler]:
        return {Frame: self.on_frame, WheelDrop: self.lifts.on_wheel_drop}

    def set_spacing(self, *, distance_m: float | None = None, rotation_rad: float | None = None) -> None:
        """Live reload: how far the robot moves (m) or turns (rad) between keyframes."""
        if distance_m is not None:
            self.selector.distance_m = distance_m
        if rotation_rad is not None:
            self.selector.rotation_rad = rotation_rad

    def on_frame(self, frame: Frame) -> None:
        if frame.camera != self.camera:
            self.frames_other_camera += 1
            return
        self.frames += 1
        self.pending.append(frame)
        if not self.lossless and len(self.pending) > self.max_pending:
            self.pending.popleft()
            self.frames_unsynced += 1
        self.poll()

    def poll(self) -> int:
        """Handle every held frame whose pose is now known; returns how many."""
        done = 0
        while self.pending:
            frame = self.pending[0]
            if self.odometry is None:
                self.pending.popleft()
                self.frames_without_odometry += 1
                done += 1
                continue
            settled = self.odometry.settled_stamp_ns()
            if settled is None or settled < frame.stamp_ns:
                if not self.lossless and self.clock.now_ns() - frame.stamp_ns > self._max_wait_ns:
                    self.pending.popleft()
                    self.frames_unsynced += 1
                    done += 1
                    continue
                break
            self.pending.popleft()
            self._take(frame, self.odometry.pose_at(frame.stamp_ns))
            done += 1
        return done

    def finish(self) -> int:
        """End of input: nothing more will arrive, so the newest pose is final as well.

        Held frames stamped up to the newest odometry sample take their pose now; frames
        after it can never have one and are counted in ``frames_unsynced``. Without this a
        run whose clock stops with the input (the virtual robot, a replay) would wait for a
        settled pose forever.
        """
        done = 0
        while self.pending:
            frame = self.pending.popleft()
            done += 1
            if self.odometry is None:
                self.frames_without_odometry += 1
                continue
            self._take(frame, self.odometry.pose_at(frame.stamp_ns))
        return done

    def _take(self, frame: Frame, pose: PoseStamped | None) -> None:
        if pose is None:
            self.frames_unsynced += 1
            return
        if self.lifts.intervals and self.lifts.covers(frame.stamp_ns):
            self.frames_lifted += 1
            return
        xyyaw = np.array([pose.x_m, pose.y_m, pose.yaw_rad])
        if self.selector.offer(xyyaw):
            self.keyframes += 1
            previous, self._previous_ns = self._previous_ns, frame.stamp_ns
            carried = previous is not None and self.lifts.lifted_between(previous, frame.stamp_ns)
            edge: tuple[np.ndarray, np.ndarray] | None = None
            bias = None
            if self.odometry is not None and self.bias_terms:
                got = self.odometry.keyframe_edge_terms(frame.stamp_ns)
                if got is not None:
                    edge, bias = (got[0], got[1]), tuple(got[2])
            elif self.odometry is not None:
                edge = self.odometry.keyframe_edge(frame.stamp_ns)
            if type(frame) is not Frame:  # a replay's frame, decoded when read: here, once
                frame = Frame(frame.stamp_ns, frame.camera, frame.image, frame.seq)
            self._publish(Keyframe(frame, pose, odometry_edge=edge, odometry_bias=bias, carried=carried))

    def counters(self) -> dict[str, int]:
        return {"frames": self.frames, "frames_unsynced": self.frames_unsynced,
                "frames_without_odometry": self.frames_without_odometry,
                "frames_other_camera": self.frames_other_camera, "frames_lifted": self.frames_lifted,
                "keyframes": self.keyframes}
