"""The pipeline: stages registered by name, messages routed to them by type.

Every source's messages (``WheelTicks``, ``YawRate``, ``Frame``, ...) are published to the
:class:`Pipeline`, which hands each one to the stages that subscribe to its type, in the
order the stages were registered. A stage may publish further messages (an
:class:`~robotd.base.messages.OdometryUpdate`, a :class:`~robotd.base.messages.Keyframe`,
a :class:`~robotd.base.messages.Link`); they are delivered at once, depth first, so one
input is handled completely before the next and a run is deterministic. Adding a source or
a stage is a registration, not an edit of the daemon: a forward-camera detector subscribes
to forward frames and publishes loop links, a pose graph subscribes to links.

The stages of today, in the order :func:`robotd.app.assemble.build_pipeline` registers them:

``odometry``  wheel ticks + gyro -> the EKF; publishes ``OdometryUpdate``.
``keyframes`` floor frames wait until the odometry has settled past their stamp, then take
              the fused pose at that stamp; a frame far enough from the last keyframe is
              published as a ``Keyframe``.
``floor``     describes each ``Keyframe`` (compact descriptor) before it is stored, then
              queries the map with each ``KeyframeStored``; publishes the query (the
              candidates) and a loop ``Link`` per declared loop.
``visual_odometry`` (optional) the motion from the previous keyframe by floor visual
              odometry: fused into the filter, or (vision only) the keyframe's odometry edge.
``map``       stores each ``Keyframe`` (publishing ``KeyframeStored``), the odometry link
              from the run's previous keyframe, and every ``Link``.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import numpy as np

from robotd.app.mappedground import MappedGround
from robotd.base.clock import Clock
from robotd.base.geometry import between_error_covariance, compose, information_from_covariance
from robotd.base.messages import (
    BaseStatus,
    CandidateFate,
    Frame,
    Keyframe,
    KeyframeStored,
    Link,
    LoopCandidate,
    LoopFate,
    MapMatch,
    OdometryUpdate,
    PoseStamped,
    TransientKeyframe,
    WheelDrop,
    WheelTicks,
    YawRate,
)
from robotd.floor.detector import FloorLoopDetector
from robotd.floor.vo import FloorVisualOdometry
from robotd.io.store import MapStore
from robotd.keyframes import KeyframeSelector, downsample
from robotd.odometry.fusion import OdometryFilter
from robotd.odometry.increments import combine_edges, edge_disagreement, odometry_edge

log = logging.getLogger(__name__)

Handler = Callable[[Any], None]


class Stage(Protocol):
    """One step of the pipeline.

    ``name`` identifies it (counters, logs); :meth:`subscriptions` maps each message type
    it consumes to its handler. Optional methods, called when present: ``attach(pipeline)``
    (once, at registration: the stage keeps the pipeline to publish to), ``poll() -> int``
    (work that waits on something other than a new message, e.g. frames waiting for
    odometry; returns how many items it handled), ``finish() -> int`` (end of input) and
    ``counters() -> dict[str, int]``.
    """

    name: str

    def subscriptions(self) -> Mapping[type, Handler]: ...


class Pipeline:
    """Routes messages to the stages registered for their type (see the module notes)."""

    def __init__(self) -> None:
        self._stages: dict[str, Any] = {}
        self._routes: dict[type, list[Handler]] = collections.defaultdict(list)
        self.inputs = 0
        """Messages published from outside (the sources), a measure of progress."""
        self.unrouted: collections.Counter[str] = collections.Counter()
        """Messages of a type no stage consumes, by type name."""

    def add(self, stage: Any) -> Any:
        """Register ``stage`` (after every stage registered before it); returns it."""
        if stage.name in self._stages:
            raise ValueError(f"a stage named {stage.name!r} is already registered")
        self._stages[stage.name] = stage
        for msg_type, handler in stage.subscriptions().items():
            self._routes[msg_type].append(handler)
        if hasattr(stage, "attach"):
            stage.attach(self)
        return stage

    def instrument(self, wrap: Callable[[str, str, Callable[..., Any]], Callable[..., Any]]) -> None:
        """Replace every stage's message handlers and its ``poll``/``finish`` by
        ``wrap(stage_name, handler_name, fn)`` (a function with the same signature), e.g.
        to account CPU time per stage (``bench/bench_daemon.py``). Call it once, after
        the last stage was added and before the first message."""
        for msg_type, handlers in self._routes.items():
            handlers[:] = [wrap(getattr(getattr(h, "__self__", None), "name", "?"),
                                getattr(h, "__name__", msg_type.__name__), h) for h in handlers]
        for stage in self._stages.values():
            for what in ("poll", "finish"):
                if hasattr(stage, what):
                    setattr(stage, what, wrap(stage.name, what, getattr(stage, what)))

    def stage(self, name: str) -> Any:
        """The stage registered as ``name`` (KeyError if none)."""
        return self._stages[name]

    @property
    def stages(self) -> list[Any]:
        return list(self._stages.values())

    def subscribed(self, msg_type: type) -> bool:
        """Whether any stage consumes ``msg_type`` (lets a stage skip building a message)."""
        return bool(self._routes.get(msg_type))

    def feed(self, msg: Any) -> None:
        """A message from a source: counted as input, then published."""
        self.inputs += 1
        self.publish(msg)

    def publish(self, msg: Any) -> None:
        """Hand ``msg`` to every stage subscribed to its type, in registration order."""
        handlers = self._routes.get(type(msg))
        if not handlers:
            self.unrouted[type(msg).__name__] += 1
            return
        for handler in handlers:
            handler(msg)

    def poll(self) -> int:
        """Let every stage do waiting work; returns how many items were handled."""
        return sum(s.poll() for s in self._stages.values() if hasattr(s, "poll"))

    def finish(self) -> int:
        """End of input: every stage finishes what it holds; returns items handled."""
        return sum(s.finish() for s in self._stages.values() if hasattr(s, "finish"))

    def counters(self) -> dict[str, int]:
        """Every stage's counters in one flat mapping (the names are unique by design)."""
        out: dict[str, int] = {"inputs": self.inputs}
        for s in self._stages.values():
            if hasattr(s, "counters"):
                out.update(s.counters())
        for name, n in self.unrouted.items():
            out[f"unrouted_{name}"] = n
        return out


class Publisher:
    """Mixin: keeps the pipeline a stage publishes to."""

    pipeline: Pipeline | None = None

    def attach(self, pipeline: Pipeline) -> None:
        self.pipeline = pipeline

    def _publish(self, msg: Any) -> None:
        if self.pipeline is not None:
            self.pipeline.publish(msg)


class OdometryStage(Publisher):
    """Wheel ticks and gyro into the odometry filter (:mod:`robotd.odometry.ekf`).

    A base driver that knows its wheel readings have stopped (a stale wheel on a CAN
    bus) says so with :class:`~robotd.base.messages.BaseStatus`: the odometry is then
    ``degraded`` (``odometry_degraded`` 1, with ``degraded_detail``; the STATUS line
    says so) until the driver reports it healthy again; ``odometry_degraded_episodes``
    counts the times it became degraded.
    """

    name = "odometry"

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
                BaseStatus: self.on_base_status}

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

    def counters(self) -> dict[str, int]:
        f = self.odometry.counters
        return {"wheel_msgs": self.wheel_msgs, "yaw_msgs": self.yaw_msgs,
                "odometry_rejected": self.rejected, "odometry_degraded": int(self.degraded),
                "odometry_degraded_episodes": self.degraded_episodes, "vo_fused": f.vo_fused,
                "vo_rejected_by_filter": f.vo_rejected}


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
        return any(a <= stamp_ns and (b is None or stamp_ns <= b) for a, b in reversed(self.intervals))

    def lifted_between(self, a_ns: int, b_ns: int) -> bool:
        """Whether the robot was lifted at some time in ``(a_ns, b_ns]``."""
        return any(a_ns < a <= b_ns for a, _b in reversed(self.intervals))


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

    While the base reports a wheel drop (the robot is carried, :class:`LiftIntervals`),
    frames are not keyframes (counted in ``frames_lifted``): the camera sees nothing of the
    floor the robot will be put down on.
    """

    name = "keyframes"

    def __init__(self, odometry: OdometryFilter | None, clock: Clock, *, distance_m: float, rotation_rad: float,
                 max_sync_wait_s: float, lossless: bool, camera: str = "floor",
                 max_pending: int = 64) -> None:
        self.odometry = odometry  # None: no base, frames cannot get a pose
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
        self.mapped_ground: MappedGround | None = None  # set by the assembly: transient keyframes
        self.lifts = LiftIntervals()

    def subscriptions(self) -> Mapping[type, Handler]:
        return {Frame: self.on_frame, WheelDrop: self.lifts.on_wheel_drop}

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
            settled = self.odometry.wheel_gyro.settled_stamp_ns()
            if settled is None or settled < frame.stamp_ns:
                if not self.lossless and self.clock.now_ns() - frame.stamp_ns > self._max_wait_ns:
                    self.pending.popleft()
                    self.frames_unsynced += 1
                    done += 1
                    continue
                break
            self.pending.popleft()
            self._take(frame, self.odometry.wheel_gyro.pose_at(frame.stamp_ns))
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
            self._take(frame, self.odometry.wheel_gyro.pose_at(frame.stamp_ns))
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
            transient = self.mapped_ground is not None and self.mapped_ground.is_transient(xyyaw)
            # The filter's motion since the previous keyframe, with its covariance from
            # the pose clone (None at the first one).
            edge = self.odometry.keyframe_edge(frame.stamp_ns) if self.odometry is not None else None
            self._publish(Keyframe(frame, pose, odometry_edge=edge, transient=transient))

    def counters(self) -> dict[str, int]:
        return {"frames": self.frames, "frames_unsynced": self.frames_unsynced,
                "frames_without_odometry": self.frames_without_odometry,
                "frames_other_camera": self.frames_other_camera, "frames_lifted": self.frames_lifted,
                "keyframes": self.keyframes}


class FloorDetectorStage(Publisher):
    """The floor loop detector (:class:`robotd.floor.detector.FloorLoopDetector`).

    Describes each keyframe before it is stored (the descriptor goes into the same map
    row), then queries the map with it once it has an id. Publishes the query result (a
    :class:`~robotd.floor.detector.KeyframeQuery`), a :class:`LoopCandidate` per candidate
    at or above the trained threshold (the pose graph gates it), and the fate of the
    others (:class:`CandidateFate`).
    """

    name = "floor"

    def __init__(self, detector: FloorLoopDetector) -> None:
        self.detector = detector
        self.queries = 0
        self.transient_queries = 0
        self.candidates = 0
        self.loops = 0

    def subscriptions(self) -> Mapping[type, Handler]:
        return {Keyframe: self.describe, KeyframeStored: self.query, TransientKeyframe: self.query_transient}

    def query_transient(self, msg: TransientKeyframe) -> None:
        """A transient keyframe (over mapped ground) is matched against the map, not added;
        its matches go to the pose graph as :class:`MapMatch`."""
        kf = msg.keyframe
        if "floor" not in kf.descriptors:
            return
        result = self.detector.query(kf.stamp_ns, kf.descriptors["floor"][1])
        self.transient_queries += 1
        for loop in result.loops:
            self._publish(MapMatch(loop.from_id, loop.score, loop.delta, loop.information))

    def describe(self, kf: Keyframe) -> None:
        kf.descriptors["floor"] = (self.detector.params.descriptor_mode, self.detector.describe(kf.frame.image))

    def query(self, msg: KeyframeStored) -> None:
        kf = msg.keyframe
        if "floor" not in kf.descriptors or kf.keyframe_id is None:
            return
        result = self.detector.query_and_add(kf.keyframe_id, kf.stamp_ns, kf.descriptors["floor"][1])
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


class VisualOdometryStage:
    """Floor visual odometry between consecutive keyframes (paper 003 Sec. IV-D).

    Registered after ``floor`` (it reuses the keyframe's descriptor) and before ``map``.
    ``fused``: each step is a relative-pose measurement in the wheel + gyro filter
    (:meth:`robotd.odometry.fusion.OdometryFilter.on_visual_odometry`; a failed step leaves
    the filter alone), and the keyframe's odometry edge becomes the wheel + gyro edge and
    the step combined as two independent measurements
    (:func:`robotd.odometry.increments.combine_edges`; the filter keeps a wheel + gyro twin
    for those edges, ``vo_twin``), counted in ``vo_combined``; a step that disagrees with the
    wheel + gyro edge beyond the filter's chi-square gate (``vo_gate_nis``) is left out of
    the edge (``vo_disagreed``), as the filter leaves it out of its state. In both modes it keeps the
    visual odometry alone dead-reckoned (``Keyframe.visual_pose``). ``vision_only``: each successful step becomes the keyframe's
    odometry edge in the map (the pose graph's odometry), and a failed one falls back to
    the filter's increment (counted in ``vo_fallback``).
    """

    name = "visual_odometry"

    def __init__(self, vo: FloorVisualOdometry, odometry: OdometryFilter | None, mode: str) -> None:
        if mode not in ("fused", "vision_only"):
            raise ValueError(f"visual odometry mode must be 'fused' or 'vision_only', not {mode!r}")
        self.vo = vo
        self.odometry = odometry
        self.mode = mode
        self._prev_stamp_ns: int | None = None
        self._visual_pose: np.ndarray | None = None
        self.steps = 0
        self.ok = 0
        self.fallback = 0
        self.combined = 0
        self.disagreed = 0
        self.failures = collections.Counter[str]()

    def subscriptions(self) -> Mapping[type, Handler]:
        return {Keyframe: self.on_keyframe}

    def on_keyframe(self, kf: Keyframe) -> None:
        desc = kf.descriptors.get("floor")
        result = self.vo.step(desc[1] if desc is not None and desc[0] == self.vo.params.descriptor_mode
                              else kf.frame.image)
        first = self._prev_stamp_ns is None
        if not first:
            self.steps += 1
            if result.ok:
                self.ok += 1
            else:
                self.failures[result.reason] += 1
        step = None
        if result.ok and not first:
            step = (result.delta, between_error_covariance(result.delta, result.covariance))
        if first or self._visual_pose is None:
            self._visual_pose = kf.pose_xyyaw
        elif step is not None or kf.odometry_edge is not None:
            self._visual_pose = compose(self._visual_pose, (step or kf.odometry_edge)[0])
        kf.visual_pose = self._visual_pose
        if self.mode == "fused" and self.odometry is not None:
            self.odometry.on_visual_odometry(kf.stamp_ns, self._prev_stamp_ns,
                                             result.delta if result.ok else None,
                                             result.covariance if result.ok else None)
            if step is not None:
                if kf.odometry_edge is None:
                    kf.odometry_edge = step
                elif edge_disagreement(kf.odometry_edge, step) > self.odometry.vo_gate_nis:
                    self.disagreed += 1  # a wrong step (a look-alike lattice shift): wheels only
                else:
                    kf.odometry_edge = combine_edges(kf.odometry_edge, step)
                    self.combined += 1
        elif self.mode == "vision_only" and not first:
            if step is not None:
                kf.odometry_edge = step
            else:
                self.fallback += 1
        self._prev_stamp_ns = kf.stamp_ns

    def status_fragment(self) -> str:
        """For STATUS: how many steps the floor measured (a dirty lens or a bare floor shows
        here first)."""
        if not self.steps:
            return ""
        return f"floor VO {100.0 * self.ok / self.steps:.0f} % of {self.steps} steps"

    def counters(self) -> dict[str, int]:
        out = {"vo_steps": self.steps, "vo_ok": self.ok, "vo_fallback": self.fallback,
               "vo_combined": self.combined, "vo_disagreed": self.disagreed}
        out.update({f"vo_failed_{k}": n for k, n in sorted(self.failures.items())})
        return out


class LoopsUngated(Publisher):
    """Without a pose graph ([pose_graph] enabled = false), every loop candidate at or
    above the threshold becomes a loop link, recorded as accepted without a gate."""

    name = "loops_ungated"

    def subscriptions(self) -> Mapping[type, Handler]:
        return {LoopCandidate: self.on_candidate}

    def on_candidate(self, c: LoopCandidate) -> None:
        self._publish(CandidateFate(c.to_id, c.from_id, c.score, LoopFate.ACCEPTED, "no pose graph: not gated"))
        self._publish(Link("loop", c.from_id, c.to_id, c.delta_xyyaw, c.information))


class MapWriterStage(Publisher):
    """Writes keyframes and links to the map store.

    Each keyframe after the run's first also gets an odometry link from the previous one:
    ``Keyframe.odometry_edge``, the filter's increment with its covariance from the pose
    clone (:meth:`robotd.odometry.fusion.OdometryFilter.keyframe_edge`) or what vision-only
    visual odometry measured instead. A keyframe without one (the filter had no clone)
    falls back to the relative transform of the fused poses with the difference of their
    covariances (:func:`robotd.odometry.increments.odometry_edge`).
    No odometry link crosses a time the robot was lifted (:class:`LiftIntervals`): the
    keyframe after it starts a new chain (``odometry_breaks``), which the pose graph
    relocalises. Over mapped ground (``Keyframe.transient``), keyframes are not stored and
    extend the chain of :class:`robotd.app.mappedground.MappedGround` instead.
    """

    name = "map"

    def __init__(self, store: MapStore, run_id: int, *, image_width_px: int) -> None:
        self.store = store
        self.run_id = run_id
        self.image_width_px = image_width_px
        self._previous: Keyframe | None = None
        self.stored = 0
        self.transient = 0
        self.mapped_ground: MappedGround | None = None  # set by the assembly: transient keyframes
        self.links = collections.Counter[str]()
        self.fates = collections.Counter[str]()
        self._fates: list[tuple[int, int, float, str, str]] = []
        self.lifts = LiftIntervals()
        self.odometry_breaks = 0

    def subscriptions(self) -> Mapping[type, Handler]:
        return {Keyframe: self.on_keyframe, Link: self.on_link, CandidateFate: self.on_fate,
                WheelDrop: self.lifts.on_wheel_drop}

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
        prev = self._previous
        mapped = self.mapped_ground
        carried = (prev is not None and bool(self.lifts.intervals)
                   and self.lifts.lifted_between(prev.stamp_ns, kf.stamp_ns))
        if carried:  # no odometry link across a lift: the wheels did not see the motion
            prev = None
            if mapped is not None:
                mapped.chain_broken()
        edge = None if prev is None else self._odometry_edge(prev, kf)
        if mapped is not None and kf.transient and edge is not None:
            # Over mapped ground: not stored, the odometry chain grows (robotd.app.mappedground).
            mapped.extend((edge[0], np.linalg.inv(edge[1])), kf.pose_xyyaw)
            self._previous = kf
            self.transient += 1
            self._publish(TransientKeyframe(kf))
            return
        self._store(kf)  # a failed write raises here and leaves the chain as it was
        self._previous = kf
        if carried:
            self.odometry_breaks += 1
            log.info("keyframe %d: the robot was carried since the previous keyframe; no odometry "
                     "link between them", kf.keyframe_id)
        if edge is not None:
            assert prev is not None
            from_id, delta, info = prev.keyframe_id, edge[0], edge[1]
            if mapped is not None:  # from the chain's start when transient keyframes came between
                from_id, delta, cov = mapped.edge_for_stored(prev.keyframe_id, (delta, np.linalg.inv(info)))
                info = information_from_covariance(cov)
            if from_id is not None:
                self._publish(Link("odometry", from_id, kf.keyframe_id, delta, info))
        if mapped is not None:
            mapped.stored(kf.keyframe_id, kf.pose_xyyaw)
        self._publish(KeyframeStored(kf))
        self.flush_fates()

    @staticmethod
    def _odometry_edge(prev: Keyframe, kf: Keyframe) -> tuple[np.ndarray, np.ndarray]:
        """``(delta, information)`` from the previous keyframe (stored or not) to ``kf``."""
        if kf.odometry_edge is not None:  # measured by another stage (visual odometry)
            delta, cov = kf.odometry_edge
            return np.asarray(delta, float), information_from_covariance(cov)
        return odometry_edge(prev.pose_xyyaw, prev.pose.covariance, kf.pose_xyyaw, kf.pose.covariance)

    def _store(self, kf: Keyframe) -> None:
        descriptor = mode = None
        if "floor" in kf.descriptors:
            mode, descriptor = kf.descriptors["floor"]
        kf.keyframe_id = self.store.add_keyframe(
            self.run_id, kf.stamp_ns, kf.pose_xyyaw, kf.pose.covariance,
            downsample(kf.frame.image, self.image_width_px),
            descriptor=descriptor, descriptor_mode=mode,
        )
        kf.run_id = self.run_id
        self.stored += 1
        # The acknowledgement (debug level: several a second): add_keyframe has committed.
        log.debug("keyframe %d committed (run %d, %d stored)", kf.keyframe_id, self.run_id, self.stored)

    def on_link(self, link: Link) -> None:
        self.store.add_link(link.kind, link.from_id, link.to_id, link.delta_xyyaw, link.information)
        self.links[link.kind] += 1

    def counters(self) -> dict[str, int]:
        return {"keyframes_stored": self.stored, "keyframes_not_stored": self.transient,
                "odometry_breaks": self.odometry_breaks,
                **{f"links_{k}": n for k, n in sorted(self.links.items())},
                **{f"candidates_{k}": n for k, n in sorted(self.fates.items())}}
