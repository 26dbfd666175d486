"""robotd's live outputs: ROS 2 topics over DDS and a Foxglove view, one pipeline stage.

:class:`RosOutputStage` watches the pipeline (fused odometry, stored keyframes, accepted
loops), builds the ROS 2 messages of :mod:`robotd.io.rosview`, encodes each once with the
one message model (:mod:`robotd.base.ros2msg`) and hands the bytes to its sinks:
:class:`DdsSink` (``[ros2]``, the ``robotd[ros2]`` extra, ``cyclonedds``) and
:class:`FoxgloveSink` (``[foxglove]``, the ``robotd[foxglove]`` extra, ``foxglove-sdk``).
:func:`build_output_stage` makes it from the config; :func:`robotd.app.assemble.assemble_daemon`
registers it last, so it sees every message after the stages that make them.

Topics (names relative to ``[ros2] namespace`` unless absolute; QoS in ROS 2's terms):

=====================================  ===================================  ====================================
``/tf``                                 ``tf2_msgs/TFMessage``               reliable, volatile, keep last 100
``/tf_static``                          ``tf2_msgs/TFMessage``               reliable, transient local, keep last 1
``robotd/odometry``                     ``nav_msgs/Odometry``                reliable (or best effort), keep last 10
``robotd/pose``                         ``geometry_msgs/PoseWithCovarianceStamped``  reliable, keep last 10
``robotd/path``                         ``nav_msgs/Path``                    reliable, transient local, keep last 1
``robotd/loop_closures``                ``visualization_msgs/MarkerArray``   reliable, transient local, keep last 1
``/diagnostics``                        ``diagnostic_msgs/DiagnosticArray``  reliable, volatile, keep last 10
``robotd/keyframes/<camera>/compressed`` ``sensor_msgs/CompressedImage``     best effort, keep last 5
=====================================  ===================================  ====================================

``/tf`` carries ``map -> odom`` (loop-corrected, :func:`robotd.io.rosview.map_to_odom`) with
every odometry message and at once when a keyframe enters the graph or a loop is accepted,
and ``odom -> base_footprint`` only when robotd reads the base itself (``[ros2] odom_tf``):
on a ROS robot the base driver publishes that one.

``robotd/pose`` is the fused pose moved into the map frame (``map -> odom`` composed with
it), with the pose graph's covariance: the newest keyframe's marginal from iSAM2, carried
forward by what the odometry added since (:mod:`robotd.graph.covariance`). The marginal is
computed once per keyframe entering the graph and per accepted loop (its time is counted
in ``outputs_marginal_us``), the composition with every odometry message. Before the first
keyframe, or if the graph cannot give the marginal, it carries the odometry's covariance.

Stamps: robotd's clock (host monotonic time, or the virtual robot's from 0) plus the offset
to the Unix clock measured once at start-up (``[ros2] ros_time``), so other ROS nodes can
look the transforms up at their own time.

Cost: every handler's CPU time (``time.thread_time_ns``: building, encoding, sending) is
summed in the ``outputs_cpu_us`` counter, so a run can compare it with the daemon's own.
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import cv2
import numpy as np

from robotd.base import ros2msg
from robotd.base.clock import Clock, MonotonicClock
from robotd.base.config import Config
from robotd.base.errors import ConfigError
from robotd.base.geometry import compose, interpolate_poses
from robotd.base.messages import Frame, KeyframeStored, Link, OdometryUpdate
from robotd.graph.covariance import corrected_pose, tangent_to_world
from robotd.io import rosview
from robotd.io.rosview import TopicSpec

log = logging.getLogger(__name__)


class Sink(Protocol):
    """Where encoded messages go. ``keys``: the topics (by key) this sink wants."""

    name: str
    keys: set[str]

    def advertise(self, key: str, spec: TopicSpec) -> None: ...

    def publish(self, key: str, data: bytes, stamp_ns: int) -> None: ...

    def close(self) -> None: ...


def topic_specs(cfg: Config) -> dict[str, TopicSpec]:
    """Every topic robotd can publish, by key (see the module table)."""
    r = cfg.ros2
    specs = {
        "tf": TopicSpec("/tf", "tf2_msgs/msg/TFMessage", depth=100),
        "tf_static": TopicSpec("/tf_static", "tf2_msgs/msg/TFMessage", transient_local=True, depth=1),
        "odometry": TopicSpec(r.odometry_topic or "robotd/odometry", "nav_msgs/msg/Odometry",
                              reliable=r.odometry_reliable, depth=10 if r.odometry_reliable else 5),
        "pose": TopicSpec(r.pose_topic or "robotd/pose", "geometry_msgs/msg/PoseWithCovarianceStamped"),
        "path": TopicSpec(r.path_topic or "robotd/path", "nav_msgs/msg/Path", transient_local=True, depth=1),
        "loops": TopicSpec(r.loop_closures_topic or "robotd/loop_closures", "visualization_msgs/msg/MarkerArray",
                           transient_local=True, depth=1),
        "diagnostics": TopicSpec("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
    }
    for camera in ("floor", "forward"):
        specs[f"keyframe_{camera}"] = TopicSpec(f"robotd/keyframes/{camera}/compressed",
                                                "sensor_msgs/msg/CompressedImage", reliable=False, depth=5)
    return specs


def ros2_keys(cfg: Config) -> set[str]:
    """The keys ``[ros2]`` switches on."""
    r = cfg.ros2
    keys = {k for k, on in (("tf", r.tf), ("tf_static", r.static_tf), ("odometry", bool(r.odometry_topic)),
                            ("pose", bool(r.pose_topic)), ("path", bool(r.path_topic)),
                            ("loops", bool(r.loop_closures_topic)), ("diagnostics", r.diagnostics),
                            ("keyframe_floor", r.keyframe_images), ("keyframe_forward", r.keyframe_images))
            if on}
    return keys


class DdsSink:
    """ROS 2 topics over DDS (:mod:`drivers.ros2.dds`)."""

    name = "ros2"
    latches = True  # transient-local topics reach late joiners

    def __init__(self, cfg: Config, *, dds_config: str | None = None) -> None:
        from drivers.ros2 import dds

        self._dds = dds
        self.domain_id = dds.domain_id_from(cfg.ros2.domain_id)
        self.namespace = cfg.ros2.namespace
        self.keys = ros2_keys(cfg)
        self.participant = dds.Participant(self.domain_id, config=dds_config)
        self.writers: dict[str, Any] = {}
        self.node_name = "robotd"
        self.distro = dds.ros_distro()
        log.info("ROS 2 output on DDS domain %d (namespace %r, node %s, %s graph information)", self.domain_id,
                 self.namespace or "/", self.node_name, self.distro)

    def advertise(self, key: str, spec: TopicSpec) -> None:
        qos = self._dds.QosSpec(spec.reliable, spec.transient_local, spec.depth)
        self.writers[key] = self.participant.writer(spec.topic, spec.type_name, qos, namespace=self.namespace)
        # ros_discovery_info names the writers robotd's node (``ros2 node list``): again
        # with each new one (only at start-up), the last one latched for late joiners
        try:
            self.participant.announce(self.node_name, self.namespace, self.distro)
        except Exception as exc:  # noqa: BLE001 - the graph information must never stop the outputs
            log.warning("ros_discovery_info not published: %s", exc)

    def publish(self, key: str, data: bytes, stamp_ns: int) -> None:
        self.writers[key].write(data)

    def close(self) -> None:
        self.writers.clear()
        self.participant.close()


def require_foxglove() -> Any:
    """The ``foxglove`` module, or :class:`ConfigError` saying how to install it."""
    try:
        import foxglove
    except ImportError as exc:
        raise ConfigError(f"[foxglove] enabled needs the foxglove-sdk package ({exc}); install "
                          "the extra: pip install 'robotd[foxglove]'") from None
    return foxglove


class FoxgloveSink:
    """A Foxglove WebSocket server (``foxglove-sdk``): every topic as a ``cdr`` channel with
    its ``ros2msg`` schema, so Foxglove's 3D, image, plot and diagnostics panels read them
    as they read ROS 2 data."""

    name = "foxglove"
    latches = False
    """Foxglove's server keeps no message for a client that connects later: the output
    stage repeats ``/tf_static`` to it every second."""

    def __init__(self, host: str, port: int, *, keys: set[str]) -> None:
        foxglove = require_foxglove()
        self._fg = foxglove
        self.keys = keys
        self.context = foxglove.Context()
        try:
            self.server = foxglove.start_server(name="robotd", host=host, port=port, context=self.context)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error for a busy port
            raise ConfigError(f"[foxglove] cannot listen on {host}:{port}: {exc}") from None
        self.port = self.server.port
        self.channels: dict[str, Any] = {}
        log.info("Foxglove live view on ws://%s:%d", host, self.port)
        if host not in ("127.0.0.1", "::1", "localhost"):
            log.warning("the Foxglove view listens on %s: anyone who can reach port %d sees the robot's "
                        "data (the server has no authentication)", host, self.port)

    def advertise(self, key: str, spec: TopicSpec) -> None:
        from foxglove.channel import Channel

        topic = spec.topic if spec.topic.startswith("/") else "/" + spec.topic
        schema = self._fg.Schema(name=spec.type_name, encoding="ros2msg",
                                 data=ros2msg.schema_text(spec.type_name).encode())
        self.channels[key] = Channel(topic, schema=schema, message_encoding="cdr", context=self.context)

    def publish(self, key: str, data: bytes, stamp_ns: int) -> None:
        self.channels[key].log(data, log_time=stamp_ns)

    def close(self) -> None:
        for ch in self.channels.values():
            ch.close()
        self.server.stop()


class RosOutputStage:
    """The output stage (see the module notes). ``clock``: the daemon's clock (for the
    ROS time offset); ``wall_clock``: what throttles the path and the diagnostics."""

    name = "outputs"

    def __init__(self, cfg: Config, sinks: list[Any], clock: Clock, *, wall_clock: Clock | None = None) -> None:
        r = cfg.ros2
        self.cfg = cfg
        self.sinks = sinks
        self.map_frame, self.odom_frame, self.base_frame = r.map_frame, r.odom_frame, r.base_frame
        self.owns_base = r.odom_tf == "always" or (r.odom_tf == "auto" and cfg.base.driver in ("kobuki", "can"))
        self.offset_ns = (time.time_ns() - clock.now_ns()) if r.ros_time else 0
        self.wall = MonotonicClock() if wall_clock is None else wall_clock
        self._min_odom_ns = int(1e9 / r.odometry_rate_hz) if r.odometry_rate_hz > 0 else 0
        self._path_ns = int(r.path_interval_s * 1e9)
        self._jpeg = [cv2.IMWRITE_JPEG_QUALITY, cfg.foxglove.jpeg_quality]
        self.specs = topic_specs(cfg)
        self.active = {k for k in self.specs if any(k in s.keys for s in sinks)}
        for s in sinks:
            for k in sorted(self.specs):
                if k in s.keys:
                    s.advertise(k, self.specs[k])
        self.pipeline: Any = None
        self.queue_drops: Callable[[], Mapping[str, int]] = dict
        self.driver_stats: Callable[[], Mapping[str, Mapping[str, Any]]] = dict
        self.map_odom = np.zeros(3)
        self._hist: collections.deque[tuple[int, float, float, float]] = collections.deque(maxlen=4096)
        self._hist_cov: collections.deque[np.ndarray] = collections.deque(maxlen=4096)
        self._kf_map: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        """The newest keyframe in the graph: map pose, its marginal (map axes), odometry pose
        and covariance at its stamp; what robotd/pose composes with the odometry."""
        self.marginal_ns = 0
        self.marginals = 0
        self.marginal_failures = 0
        self._last_odom: Any = None
        self._next_odom_ns: int | None = None
        self._last_kf: tuple[int, np.ndarray, np.ndarray] | None = None
        self._loops: dict[str, list[tuple[int, int]]] = collections.defaultdict(list)
        self._path_dirty = False
        self._next_path_ns = 0
        self._next_diag_ns = 0
        self._forward_frame: Frame | None = None
        self.published: collections.Counter[str] = collections.Counter()
        self.cpu_ns = 0
        self.tf_updates = 0
        self.on_tf_update: Callable[[int], None] | None = None
        """Called (with the /tf stamp) right after a changed map -> odom was sent (benchmarks)."""
        self._static_sent = False
        self._closed = False

    # -- wiring ----------------------------------------------------------------------------

    def attach(self, pipeline: Any) -> None:
        self.pipeline = pipeline

    def bind(self, queue_drops: Callable[[], Mapping[str, int]],
             driver_stats: Callable[[], Mapping[str, Mapping[str, Any]]]) -> None:
        """What the diagnostics report besides the pipeline's counters (the daemon's)."""
        self.queue_drops, self.driver_stats = queue_drops, driver_stats

    def subscriptions(self) -> Mapping[type, Any]:
        return {OdometryUpdate: self.on_odometry, KeyframeStored: self.on_keyframe, Link: self.on_link,
                Frame: self.on_frame}

    def _graph(self) -> Any:
        if self.pipeline is None:
            return None
        try:
            return self.pipeline.stage("graph").graph
        except KeyError:
            return None

    def _send(self, key: str, type_name: str, msg: dict[str, Any], stamp_ns: int, *,
              unlatched_only: bool = False) -> None:
        if key not in self.active:
            return
        sinks = [s for s in self.sinks if key in s.keys and not (unlatched_only and getattr(s, "latches", True))]
        if not sinks:
            return
        data = ros2msg.encode(type_name, msg)
        for s in sinks:
            try:
                s.publish(key, data, stamp_ns)
            except Exception as exc:  # noqa: BLE001 - an output must never stop the daemon
                self.published[f"failed_{key}"] += 1
                log.debug("%s: publishing %s failed: %s", s.name, key, exc)
        self.published[key] += 1

    def _ros_ns(self, stamp_ns: int) -> int:
        return max(0, int(stamp_ns) + self.offset_ns)

    # -- handlers ----------------------------------------------------------------------------

    def on_odometry(self, u: OdometryUpdate) -> None:
        t0 = time.thread_time_ns()
        p = u.fused
        self._hist.append((p.stamp_ns, p.x_m, p.y_m, p.yaw_rad))
        self._hist_cov.append(p.covariance)
        self._last_odom = p
        if not self._static_sent:
            self._send_static(p.stamp_ns)
        due = self._next_odom_ns
        if due is None or p.stamp_ns >= due:
            # On a fixed schedule of odometry time (every 1/rate s), restarted after a pause.
            due = p.stamp_ns if due is None else due
            self._next_odom_ns = due + self._min_odom_ns
            if self._next_odom_ns <= p.stamp_ns:
                self._next_odom_ns = p.stamp_ns + self._min_odom_ns
            stamp = self._ros_ns(p.stamp_ns)
            self._send_tf(stamp, with_odom=True)
            self._send("odometry", "nav_msgs/msg/Odometry", ros2msg.odometry_msg(
                stamp, p.x_m, p.y_m, p.yaw_rad, p.covariance, self.odom_frame, self.base_frame), stamp)
            if "pose" in self.active:
                (x, y, yaw), cov = self._corrected(p)
                self._send("pose", "geometry_msgs/msg/PoseWithCovarianceStamped", ros2msg.pose_with_covariance_msg(
                    stamp, self.map_frame, x, y, yaw, cov), stamp)
        self.cpu_ns += time.thread_time_ns() - t0

    def on_frame(self, frame: Frame) -> None:
        if frame.camera == "forward" and "keyframe_forward" in self.active:
            self._forward_frame = frame  # sent with the next floor keyframe

    def on_keyframe(self, msg: KeyframeStored) -> None:
        t0 = time.thread_time_ns()
        kf = msg.keyframe
        if self._hist:
            h = np.asarray(self._hist, dtype=np.float64)
            stamps = h[:, 0].astype(np.int64)
            odom_pose = interpolate_poses(stamps, h[:, 1:], np.array([kf.stamp_ns]))[0]
            odom_cov = self._hist_cov[min(int(np.searchsorted(stamps, kf.stamp_ns)), len(stamps) - 1)]
        else:
            odom_pose = np.asarray(kf.pose_xyyaw, float)
            odom_cov = np.zeros((3, 3))
        if kf.keyframe_id is not None:
            self._last_kf = (kf.keyframe_id, odom_pose, odom_cov)
        self._update_map_odom()
        self._path_dirty = True
        stamp = self._ros_ns(kf.stamp_ns)
        if "keyframe_floor" in self.active:
            self._send_image("keyframe_floor", kf.frame, stamp)
        if self._forward_frame is not None:
            self._send_image("keyframe_forward", self._forward_frame, self._ros_ns(self._forward_frame.stamp_ns))
            self._forward_frame = None
        self.cpu_ns += time.thread_time_ns() - t0

    def on_link(self, link: Link) -> None:
        if link.kind != "loop":
            return
        t0 = time.thread_time_ns()
        self._loops[link.source].append((link.from_id, link.to_id))
        self._update_map_odom()
        self._path_dirty = True
        self.cpu_ns += time.thread_time_ns() - t0

    def poll(self) -> int:
        t0 = time.thread_time_ns()
        now = self.wall.now_ns()
        if self._path_dirty and now >= self._next_path_ns:
            self._send_path()
            self._next_path_ns = now + self._path_ns
        if now >= self._next_diag_ns and self._last_odom is not None:
            self._send_diagnostics()
            if self._static_sent:  # for the sinks that do not latch (Foxglove)
                self._send_static(self._last_odom.stamp_ns, unlatched_only=True)
            self._next_diag_ns = now + 1_000_000_000
        self.cpu_ns += time.thread_time_ns() - t0
        return 0

    def finish(self) -> int:
        """End of the run: the final path and loops, then the sinks close."""
        if self._closed:
            return 0
        if self._path_dirty:
            self._send_path()
        self.close()
        return 0

    def close(self) -> None:
        """Close every sink; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        for s in self.sinks:
            try:
                s.close()
            except Exception:  # noqa: BLE001
                log.debug("closing %s failed", s.name, exc_info=True)

    # -- messages ------------------------------------------------------------------------

    def _update_map_odom(self) -> None:
        """map -> odom from the newest keyframe in the graph; sent at once when it changed."""
        graph = self._graph()
        if graph is None or self._last_kf is None or self._last_kf[0] not in graph.graph:
            return
        kf_id, odom_pose, odom_cov = self._last_kf
        map_pose = graph.pose(kf_id)
        if "pose" in self.active:
            self._marginal(graph, kf_id, map_pose, odom_pose, odom_cov)
        new = rosview.map_to_odom(map_pose, odom_pose)
        if np.array_equal(new, self.map_odom):
            return
        self.map_odom = new
        if self._last_odom is not None:
            stamp = self._ros_ns(self._last_odom.stamp_ns)
            self._send_tf(stamp, with_odom=False)
            self.tf_updates += 1
            if self.on_tf_update is not None:
                self.on_tf_update(stamp)

    def _marginal(self, graph: Any, kf_id: int, map_pose: np.ndarray, odom_pose: np.ndarray,
                  odom_cov: np.ndarray) -> None:
        """The keyframe's marginal covariance from the graph (iSAM2), once per keyframe or
        accepted loop (timed: ``outputs_marginal_us``); on failure robotd/pose keeps the
        odometry's covariance (counted, logged once)."""
        t0 = time.perf_counter_ns()
        try:
            cov = tangent_to_world(map_pose, graph.marginal_covariance(kf_id))
        except Exception as exc:  # noqa: BLE001 - GTSAM raises RuntimeError for an indeterminate system
            self.marginal_failures += 1
            if self.marginal_failures == 1:
                log.warning("no marginal covariance of keyframe %d from the pose graph (%s): robotd/pose "
                            "carries the odometry's covariance until the next one", kf_id, exc)
            self._kf_map = None
            return
        finally:
            self.marginal_ns += time.perf_counter_ns() - t0
        self.marginals += 1
        self._kf_map = (map_pose, cov, odom_pose, odom_cov)

    def _corrected(self, p: Any) -> tuple[np.ndarray, np.ndarray]:
        """robotd/pose: the fused pose in the map frame and its covariance, the graph's
        (:func:`robotd.graph.covariance.corrected_pose`) once a keyframe is in it, else the
        odometry's."""
        now = np.array([p.x_m, p.y_m, p.yaw_rad])
        if self._kf_map is None:
            return compose(self.map_odom, now), p.covariance
        map_pose, cov, odom_pose, odom_cov = self._kf_map
        return corrected_pose(map_pose, cov, odom_pose, odom_cov, now, p.covariance)

    def _send_tf(self, stamp: int, *, with_odom: bool) -> None:
        tfs = [ros2msg.planar_transform_msg(stamp, self.map_frame, self.odom_frame, self.map_odom)]
        if with_odom and self.owns_base and self._last_odom is not None:
            p = self._last_odom
            tfs.append(ros2msg.planar_transform_msg(stamp, self.odom_frame, self.base_frame, (p.x_m, p.y_m, p.yaw_rad)))
        self._send("tf", "tf2_msgs/msg/TFMessage", ros2msg.tf_message(tfs), stamp)

    def _send_static(self, stamp_ns: int, *, unlatched_only: bool = False) -> None:
        self._static_sent = True
        stamp = self._ros_ns(stamp_ns)
        self._send("tf_static", "tf2_msgs/msg/TFMessage",
                   rosview.static_transforms(stamp, self.base_frame, self.cfg), stamp,
                   unlatched_only=unlatched_only)

    def _send_image(self, key: str, frame: Frame, stamp: int) -> None:
        ok, buf = cv2.imencode(".jpg", frame.image, self._jpeg)
        if ok:
            self._send(key, "sensor_msgs/msg/CompressedImage", ros2msg.compressed_image_msg(
                stamp, f"{frame.camera}_camera_optical_frame", "jpeg", buf.tobytes()), stamp)

    def _send_path(self) -> None:
        self._path_dirty = False
        graph = self._graph()
        if graph is None or self._last_odom is None or not ({"path", "loops"} & self.active):
            return
        ids, poses = graph.estimate()
        if not len(ids):
            return
        stamp = self._ros_ns(self._last_odom.stamp_ns)
        order = np.argsort(ids)
        self._send("path", "nav_msgs/msg/Path", ros2msg.path_msg(
            stamp, self.map_frame, [stamp] * len(ids), poses[order]), stamp)
        positions = {int(i): (float(p[0]), float(p[1])) for i, p in zip(ids, poses)}
        self._send("loops", "visualization_msgs/msg/MarkerArray",
                   rosview.loop_markers(stamp, self.map_frame, self._loops, positions), stamp)

    def _send_diagnostics(self) -> None:
        if "diagnostics" not in self.active:
            return
        counters = self.pipeline.counters() if self.pipeline is not None else {}
        localisation = ""
        if "localised" in counters:
            graph_stage = self.pipeline.stage("graph")
            fragment = graph_stage.status_fragment() if hasattr(graph_stage, "status_fragment") else ""
            localisation = "localised" if counters["localised"] else (fragment or "not localised")
        try:
            drivers = dict(self.driver_stats())
        except Exception:  # noqa: BLE001 - diagnostics must never stop the daemon
            drivers = {}
        stamp = self._ros_ns(self._last_odom.stamp_ns)
        self._send("diagnostics", "diagnostic_msgs/msg/DiagnosticArray", rosview.diagnostics(
            stamp, counters, drivers, dict(self.queue_drops()), localisation), stamp)

    def counters(self) -> dict[str, int]:
        out = {"outputs_cpu_us": self.cpu_ns // 1000, "outputs_tf_updates": self.tf_updates,
               "outputs_marginals": self.marginals, "outputs_marginal_us": self.marginal_ns // 1000,
               "outputs_marginal_failures": self.marginal_failures}
        out.update({f"published_{k}": n for k, n in sorted(self.published.items())})
        return out


def build_output_stage(cfg: Config, clock: Clock, *, dds_config: str | None = None) -> RosOutputStage | None:
    """The output stage with a sink for each of ``[ros2]`` and ``[foxglove]`` that is
    enabled, or None when neither is. Raises :class:`ConfigError` when an enabled output's
    package is missing (with how to install it) or its port is taken."""
    sinks: list[Any] = []
    try:
        if cfg.ros2.enabled:
            sinks.append(DdsSink(cfg, dds_config=dds_config))
        if cfg.foxglove.enabled:
            f = cfg.foxglove
            sinks.append(FoxgloveSink(f.host, f.port, keys=set(topic_specs(cfg))))
    except BaseException:
        for s in sinks:
            s.close()
        raise
    if not sinks:
        return None
    return RosOutputStage(cfg, sinks, clock)
