"""The output stage: what goes on /tf, odometry, pose, path, loop markers and diagnostics
(sinks faked at the boundary: they keep the encoded bytes, decoded here by rosbags, an
independent CDR reader)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from robotd.app.outputs import RosOutputStage, topic_specs
from robotd.app.pipeline import Pipeline
from robotd.base.clock import ManualClock
from robotd.base.config import Config, replace
from robotd.base.geometry import compose
from robotd.base.messages import Frame, KeyframeStored, Link, OdometryUpdate, PoseStamped, StoredKeyframe
from robotd.io.rosview import map_to_odom

TS = get_typestore(Stores.ROS2_JAZZY)


class RecordingSink:
    name = "fake"

    def __init__(self, keys: set[str]) -> None:
        self.keys = keys
        self.advertised: dict[str, object] = {}
        self.sent: list[tuple[str, bytes, int]] = []
        self.closed = 0

    def advertise(self, key, spec):
        self.advertised[key] = spec

    def publish(self, key, data, stamp_ns):
        self.sent.append((key, data, stamp_ns))

    def close(self):
        self.closed += 1

    def decoded(self, key: str) -> list:
        spec = self.advertised[key]
        return [TS.deserialize_cdr(d, spec.type_name) for k, d, _ in self.sent if k == key]


class FakeGraph:
    """What the output stage reads of the pose graph stage: ``graph.graph`` (ids),
    ``graph.pose(id)``, ``graph.marginal_covariance(id)`` and ``graph.estimate()``."""

    name = "graph"

    def __init__(self) -> None:
        self.poses: dict[int, np.ndarray] = {}
        self.marginals: dict[int, np.ndarray] = {}
        self.graph = self  # PoseGraphStage.graph is the IncrementalGraph

    def subscriptions(self):
        return {}

    def __contains__(self, k):
        return k in self.poses

    def pose(self, k):
        return self.poses[k]

    def marginal_covariance(self, k):
        return self.marginals.get(k, np.diag([1e-4, 1e-4, 1e-5]))

    def estimate(self):
        ids = np.array(sorted(self.poses))
        return ids, np.array([self.poses[i] for i in ids]).reshape(-1, 3)


def odo(stamp_ns: int, x: float, y: float, yaw: float) -> OdometryUpdate:
    p = PoseStamped(stamp_ns, x, y, yaw, np.diag([0.01, 0.02, 0.003]))
    return OdometryUpdate(p, p)


def make(cfg: Config | None = None, keys: set[str] | None = None):
    cfg = cfg or Config()
    sink = RecordingSink(set(topic_specs(cfg)) if keys is None else keys)
    pipeline = Pipeline()
    graph = pipeline.add(FakeGraph())
    clock = ManualClock(0)
    wall = ManualClock(0)
    stage = pipeline.add(RosOutputStage(replace(cfg, "ros2", ros_time=False), [sink], clock, wall_clock=wall))
    return pipeline, stage, sink, graph, wall


def tf_pairs(sink: RecordingSink) -> list[tuple[str, str, float, float, float]]:
    out = []
    for m in sink.decoded("tf"):
        for t in m.transforms:
            q = t.transform.rotation
            yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y ** 2 + q.z ** 2))
            out.append((t.header.frame_id, t.child_frame_id, t.transform.translation.x,
                        t.transform.translation.y, yaw))
    return out


def test_map_to_odom_follows_the_graph_and_a_loop_moves_it_at_once() -> None:
    pipeline, stage, sink, graph, _ = make()
    ms = 1_000_000
    for i in range(0, 101):  # 50 Hz, 2 s of straight driving
        pipeline.publish(odo(i * 20 * ms, 0.01 * i, 0.0, 0.0))
    assert tf_pairs(sink)[0][:2] == ("map", "odom")
    # keyframe 7 at 1.0 s: the odometry says (0.5, 0, 0); the graph puts it elsewhere
    graph.poses[7] = np.array([0.6, 0.2, 0.1])
    kf = StoredKeyframe(Frame(1000 * ms, "floor", np.zeros((8, 8), np.uint8)), PoseStamped(1000 * ms, 0.5, 0, 0),
                        keyframe_id=7, run_id=1)
    n_before = len(sink.sent)
    pipeline.publish(KeyframeStored(kf))
    expected = map_to_odom(np.array([0.6, 0.2, 0.1]), np.array([0.5, 0.0, 0.0]))
    last = tf_pairs(sink)[-1]
    assert last[:2] == ("map", "odom")
    assert np.allclose(last[2:], expected, atol=1e-9)
    assert len(sink.sent) > n_before  # sent at once, not with the next odometry
    # map -> odom composed with odom -> base is the graph's pose of the keyframe
    assert np.allclose(compose(expected, np.array([0.5, 0.0, 0.0])), [0.6, 0.2, 0.1], atol=1e-12)
    # a loop moves the keyframe: a new map -> odom goes out with the link
    graph.poses[7] = np.array([0.4, -0.1, -0.05])
    graph.poses[2] = np.array([0.1, 0.0, 0.0])
    pipeline.publish(Link("loop", 2, 7, np.zeros(3), np.eye(3)))
    assert np.allclose(tf_pairs(sink)[-1][2:], map_to_odom(graph.poses[7], np.array([0.5, 0.0, 0.0])), atol=1e-9)
    assert stage.tf_updates == 2
    # the corrected pose = map -> odom * odometry
    pipeline.publish(odo(2100 * ms, 1.1, 0.0, 0.0))
    pose = sink.decoded("pose")[-1]
    corrected = compose(stage.map_odom, np.array([1.1, 0.0, 0.0]))
    assert pose.header.frame_id == "map"
    assert np.allclose([pose.pose.pose.position.x, pose.pose.pose.position.y], corrected[:2])


def cov3(pose_msg) -> np.ndarray:
    return pose_msg.pose.covariance.reshape(6, 6)[np.ix_((0, 1, 5), (0, 1, 5))]


def test_pose_covariance_is_the_graphs_carried_by_the_odometry() -> None:
    pipeline, stage, sink, graph, _ = make()
    ms = 1_000_000
    sigma_k = np.diag([0.01, 0.01, 0.001])  # the fused odometry's at the keyframe
    q_per_m = np.diag([4e-4, 1e-4, 2e-5])  # what it adds per metre driven straight ahead

    def odometry_cov(x: float) -> np.ndarray:  # dead reckoning from the keyframe at x = 0.5
        d = x - 0.5
        j = np.array([[1, 0, 0], [0, 1, d], [0, 0, 1]])
        return j @ sigma_k @ j.T + d * q_per_m

    def drive(i: int, x: float) -> None:
        p = PoseStamped(i * 20 * ms, x, 0.0, 0.0, odometry_cov(x) if x >= 0.5 else sigma_k)
        pipeline.publish(OdometryUpdate(p, p))

    for i in range(51):
        drive(i, 0.01 * i)
    # before any keyframe: the odometry's own covariance
    assert np.allclose(cov3(sink.decoded("pose")[-1]), sigma_k)
    # keyframe 3 at x = 0.5 m (1.0 s); the graph has it at (2, 1) facing +y (90 deg), with a
    # marginal of 1e-4 m^2 along and 4e-4 m^2 across its own axes and 1e-5 rad^2 in yaw
    graph.poses[3] = np.array([2.0, 1.0, math.pi / 2])
    graph.marginals[3] = np.diag([1e-4, 4e-4, 1e-5])
    kf = StoredKeyframe(Frame(1000 * ms, "floor", np.zeros((8, 8), np.uint8)), PoseStamped(1000 * ms, 0.5, 0, 0),
                        keyframe_id=3, run_id=1)
    pipeline.publish(KeyframeStored(kf))
    assert stage.marginals == 1
    for i in range(51, 101):
        drive(i, 0.01 * i)  # to x = 1.0: 0.5 m past the keyframe
    pose = sink.decoded("pose")[-1]
    assert (pose.pose.pose.position.x, pose.pose.pose.position.y) == pytest.approx((2.0, 1.5))
    # by hand, map axes: the marginal turned by 90 deg is diag(4e-4, 1e-4, 1e-5); the
    # keyframe's yaw swings the 0.5 m lever (+y) along -x: + 0.25 * 1e-5 on x, -0.5e-5 x/yaw;
    # the odometry's own 0.5 m (along odom x = map y): 0.5 * q turned, diag(0.5e-4, 2e-4, 1e-5)
    expected = np.array([[4e-4 + 0.25e-5 + 0.5e-4, 0.0, -0.5e-5],
                         [0.0, 1e-4 + 2e-4, 0.0],
                         [-0.5e-5, 0.0, 1e-5 + 1e-5]])
    assert cov3(pose) == pytest.approx(expected, abs=1e-12)
    # far smaller than the odometry's (which kept the 1e-2 m^2 it had at the keyframe)
    assert np.trace(cov3(pose)) < 0.05 * np.trace(odometry_cov(1.0))
    # a loop shrinks the keyframe's marginal: the published covariance follows at once
    graph.marginals[3] = np.diag([1e-5, 1e-5, 1e-6])
    graph.poses[0] = np.zeros(3)
    pipeline.publish(Link("loop", 0, 3, np.zeros(3), np.eye(3)))
    for i in range(101, 106):  # (the odometry goes out at [ros2] odometry_rate_hz)
        drive(i, 0.01 * i)
    assert np.trace(cov3(sink.decoded("pose")[-1])) < 0.8 * np.trace(expected)
    assert stage.marginals == 2 and stage.counters()["outputs_marginal_failures"] == 0


def test_odom_to_base_only_when_robotd_owns_the_base() -> None:
    for driver, expect in (("kobuki", True), ("ros2", False), ("none", False)):
        pipeline, _, sink, _, _ = make(replace(Config(), "base", driver=driver))
        pipeline.publish(odo(0, 1.0, 2.0, 0.5))
        pairs = [p[:2] for p in tf_pairs(sink)]
        assert (("odom", "base_footprint") in pairs) is expect, driver
        assert ("map", "odom") in pairs


def test_odometry_rate_is_throttled_in_odometry_time() -> None:
    pipeline, _, sink, _, _ = make(replace(Config(), "ros2", odometry_rate_hz=20.0))
    ms = 1_000_000
    for i in range(250):  # 5 s at 50 Hz
        pipeline.publish(odo(i * 20 * ms, 0.0, 0.0, 0.0))
    stamps = [m.header.stamp.sec * 1e9 + m.header.stamp.nanosec for m in sink.decoded("odometry")]
    assert len(stamps) == 100  # 20 Hz over 5 s
    assert min(np.diff(stamps)) >= 40 * ms and max(np.diff(stamps)) <= 60 * ms


def test_static_transforms_path_loops_and_diagnostics() -> None:
    cfg = replace(Config(), "forward_detector", enabled=True)
    pipeline, stage, sink, graph, wall = make(cfg)
    stage.bind(lambda: {"base": 3, "floor": 0}, lambda: {"kobuki": {"connected": 1, "away_s": 0.0, "gaps": 2}})
    pipeline.publish(odo(0, 0.0, 0.0, 0.0))
    static = sink.decoded("tf_static")
    assert len(static) == 1
    children = {t.child_frame_id: t.header.frame_id for t in static[0].transforms}
    assert children == {"base_link": "base_footprint", "floor_camera_optical_frame": "base_link",
                        "forward_camera_optical_frame": "base_link"}
    assert sink.advertised["tf_static"].transient_local
    for i in range(4):
        graph.poses[i] = np.array([float(i), 0.5 * i, 0.0])
    pipeline.publish(Link("loop", 0, 3, np.zeros(3), np.eye(3), source="floor"))
    pipeline.publish(Link("loop", 1, 3, np.zeros(3), np.eye(3), source="forward"))
    pipeline.publish(Link("loop", 1, 99, np.zeros(3), np.eye(3), source="forward"))  # 99: not in the graph
    pipeline.poll()
    path = sink.decoded("path")[-1]
    assert [p.pose.position.x for p in path.poses] == [0.0, 1.0, 2.0, 3.0]
    markers = {m.ns: m for m in sink.decoded("loops")[-1].markers}
    assert [(p.x, p.y) for p in markers["loops/floor"].points] == [(0.0, 0.0), (3.0, 1.5)]
    assert [(p.x, p.y) for p in markers["loops/forward"].points] == [(1.0, 0.5), (3.0, 1.5)]
    n_paths = len(sink.decoded("path"))
    pipeline.publish(Link("loop", 0, 2, np.zeros(3), np.eye(3)))
    pipeline.poll()  # throttled: within path_interval_s of wall time
    assert len(sink.decoded("path")) == n_paths
    wall.advance_ns(1_100_000_000)
    pipeline.poll()
    assert len(sink.decoded("path")) == n_paths + 1
    diag = sink.decoded("diagnostics")[-1]
    by_name = {s.name: s for s in diag.status}
    assert by_name["robotd: queues"].level == 1 and by_name["robotd: queues"].message == "3 dropped"
    assert by_name["robotd: driver kobuki"].level == 0
    assert {kv.key: kv.value for kv in by_name["robotd: driver kobuki"].values}["gaps"] == "2"
    stage.finish()
    stage.finish()
    assert sink.closed == 1


def test_the_localisation_diagnostic_counts_a_relocalising_groups_members_as_grouped() -> None:
    """A relocalisation by a group of forward loops that entered the pose graph as one edge:
    the localisation status carries the group edge and its members under their own name;
    no count of refused loops includes them."""
    from robotd.io.rosview import diagnostics

    counters = {"localised": 1, "relocalisations": 1, "reloc_candidates_refused": 0, "reloc_group_edges": 1,
                "forward_loops_grouped": 3, "forward_loops_failed_gate": 0, "loops_failed_gate": 0,
                "keyframes_stored": 40, "links_loop": 1}
    msg = diagnostics(5, counters, {}, {}, "localised")
    by_name = {s["name"]: {kv["key"]: kv["value"] for kv in s["values"]} for s in msg["status"]}
    assert by_name["robotd: localisation"] == {"localised": "1", "relocalisations": "1",
                                               "reloc_candidates_refused": "0", "reloc_group_edges": "1",
                                               "forward_loops_grouped": "3"}
    assert by_name["robotd: map"]["loops_failed_gate"] == "0"


def test_the_map_diagnostic_counts_each_cameras_refused_loops_apart() -> None:
    """The map status names the floor's and the forward camera's gate refusals under their
    own keys, so a forward loop the gate refused is visible beside the floor's."""
    from robotd.io.rosview import diagnostics

    counters = {"keyframes_stored": 40, "links_loop": 9, "loops_accepted": 7, "loops_failed_gate": 1,
                "forward_loops_accepted": 2, "forward_loops_failed_gate": 4}
    msg = diagnostics(5, counters, {}, {}, "")
    by_name = {s["name"]: {kv["key"]: kv["value"] for kv in s["values"]} for s in msg["status"]}
    assert by_name["robotd: map"] == {"keyframes_stored": "40", "links_loop": "9", "loops_accepted": "7",
                                      "loops_failed_gate": "1", "forward_loops_accepted": "2",
                                      "forward_loops_failed_gate": "4"}


def test_keyframe_images_only_to_the_sinks_that_want_them() -> None:
    pipeline, _, sink, graph, _ = make(keys={"tf", "keyframe_floor"})
    pipeline.publish(odo(0, 0.0, 0.0, 0.0))
    img = (np.arange(64 * 48) % 251).astype(np.uint8).reshape(48, 64)
    graph.poses[1] = np.zeros(3)
    pipeline.publish(KeyframeStored(StoredKeyframe(Frame(0, "floor", img), PoseStamped(0, 0, 0, 0), keyframe_id=1, run_id=1)))
    images = sink.decoded("keyframe_floor")
    assert len(images) == 1 and images[0].format == "jpeg"
    import cv2
    back = cv2.imdecode(images[0].data, cv2.IMREAD_UNCHANGED)
    assert back.shape == img.shape and np.abs(back.astype(int) - img).mean() < 20
    assert {k for k, _, _ in sink.sent} == {"tf", "keyframe_floor"}


def test_ros_time_offset() -> None:
    import time
    cfg = Config()
    sink = RecordingSink({"odometry"})
    clock = ManualClock(5_000_000_000)
    stage = RosOutputStage(cfg, [sink], clock)
    stage.on_odometry(odo(5_000_000_000, 0, 0, 0))
    m = sink.decoded("odometry")[0]
    assert abs(m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 - time.time()) < 5.0


def test_missing_packages_are_one_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    import builtins

    from robotd.app.outputs import build_output_stage
    from robotd.base.errors import ConfigError
    real = builtins.__import__

    def no_dds(name, *a, **k):
        if name.startswith("cyclonedds") or name.startswith("foxglove"):
            raise ImportError(f"No module named {name!r}")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_dds)
    with pytest.raises(ConfigError, match=r"robotd\[ros2\]"):
        build_output_stage(replace(Config(), "ros2", enabled=True), ManualClock())
    with pytest.raises(ConfigError, match=r"robotd\[foxglove\]"):
        build_output_stage(replace(Config(), "foxglove", enabled=True), ManualClock())
    assert build_output_stage(Config(), ManualClock()) is None


def test_static_transforms_repeat_only_to_sinks_that_do_not_latch() -> None:
    cfg = replace(Config(), "ros2", ros_time=False)
    latching, plain = RecordingSink({"tf_static"}), RecordingSink({"tf_static"})
    plain.latches = False  # as Foxglove's server: a client that connects later gets nothing old
    wall = ManualClock(0)
    stage = RosOutputStage(cfg, [latching, plain], ManualClock(), wall_clock=wall)
    stage.on_odometry(odo(0, 0, 0, 0))
    for _ in range(3):
        stage.poll()
        wall.advance_ns(1_000_000_000)
    assert len(latching.decoded("tf_static")) == 1
    assert len(plain.decoded("tf_static")) == 4  # the first, then once a second


def test_repeats_nobody_takes_are_neither_encoded_nor_counted() -> None:
    sink = RecordingSink({"tf_static", "tf"})
    wall = ManualClock(0)
    stage = RosOutputStage(replace(Config(), "ros2", ros_time=False), [sink], ManualClock(), wall_clock=wall)
    stage.on_odometry(odo(0, 0, 0, 0))
    for _ in range(3):
        stage.poll()
        wall.advance_ns(1_000_000_000)
    assert stage.published["tf_static"] == 1 == len(sink.decoded("tf_static"))
