"""ROS 2 over DDS between two processes on the loopback interface (cyclonedds).

Every participant here, ours and the peer process's, is pinned to ``lo`` with multicast
off (:func:`drivers.ros2.dds.loopback_config`, or ``CYCLONEDDS_URI`` for the peer), on a
domain id of its own, so nothing leaves the machine.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from drivers.ros2 import dds  # noqa: E402
from robotd.base import ros2msg  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
PEER = ROOT / "tests" / "drivers" / "ros2_peer.py"


def domain_for(n: int) -> int:
    """A domain id for this test process (100..219), away from the default 0. Under
    pytest-xdist (``./dev test``) each worker of a run gets its own ten (from their common
    parent's pid and the worker's number), so two workers never share a domain."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")  # "gw0", "gw1", ...
    if worker.startswith("gw"):
        return 100 + (os.getppid() * 7 + 10 * int(worker[2:]) + n) % 120
    return 100 + (os.getpid() * 7 + n) % 120


def peer_env(domain: int) -> dict[str, str]:
    env = dict(os.environ)
    env["CYCLONEDDS_URI"] = dds.loopback_config()
    env["ROS_DOMAIN_ID"] = str(domain)
    env["PYTHONPATH"] = str(ROOT)
    return env


@pytest.mark.parametrize("typename", ["tf2_msgs/msg/TFMessage", "nav_msgs/msg/Odometry", "sensor_msgs/msg/Imu",
                                      "sensor_msgs/msg/Image", "visualization_msgs/msg/MarkerArray",
                                      "diagnostic_msgs/msg/DiagnosticArray", "nav_msgs/msg/Path",
                                      "rmw_dds_common/msg/ParticipantEntitiesInfo"])
def test_cyclone_types_serialise_as_the_model(typename: str) -> None:
    """The IdlStruct types (which name the DDS topics) read the model's bytes and write
    them back identically: ROS 2's DDS type and the model agree byte for byte."""
    from tests.base.test_ros2msg import SAMPLES

    ours = ros2msg.encode(typename, SAMPLES[typename])
    cls = dds.idl_type(typename)
    assert cls.__idl_typename__ == ros2msg.dds_type_name(typename)
    theirs = cls.deserialize(ours).serialize()
    pad = lambda b: b + b"\0" * (-len(b) % 4)  # noqa: E731
    assert pad(theirs) == pad(ours)


def test_domain_id_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    from robotd.base.errors import ConfigError

    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert dds.domain_id_from(-1) == 42
    assert dds.domain_id_from(7) == 7
    monkeypatch.delenv("ROS_DOMAIN_ID")
    assert dds.domain_id_from(-1) == 0
    monkeypatch.setenv("ROS_DOMAIN_ID", "x")
    with pytest.raises(ConfigError, match="ROS_DOMAIN_ID"):
        dds.domain_id_from(-1)


def test_outputs_reach_a_subscriber_in_another_process(tmp_path: Path) -> None:
    """map -> odom, odometry at its rate, and /tf_static to a late joiner."""
    from robotd.app.outputs import DdsSink, RosOutputStage
    from robotd.app.pipeline import Pipeline
    from robotd.base.clock import ManualClock
    from robotd.base.config import Config, replace
    from robotd.base.messages import Frame, KeyframeStored, OdometryUpdate, PoseStamped, StoredKeyframe
    from robotd.io.rosview import map_to_odom
    from tests.app.test_outputs import FakeGraph

    domain = domain_for(1)
    cfg = replace(replace(Config(), "ros2", enabled=True, domain_id=domain, odometry_rate_hz=20.0),
                  "ros2", ros_time=True)
    out = tmp_path / "sub.json"
    peer = subprocess.Popen([sys.executable, str(PEER), "sub", str(domain), str(out), "30", "5", "2", "10"],
                            env=peer_env(domain), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    pipeline = Pipeline()
    graph = pipeline.add(FakeGraph())
    clock = ManualClock(0)
    sink = DdsSink(cfg, dds_config=dds.loopback_config())
    stage = pipeline.add(RosOutputStage(cfg, [sink], clock))
    writer_gids = {k: w.guid.hex() for k, w in sink.writers.items()}
    try:
        t_end = time.monotonic() + 40
        i = 0
        while peer.poll() is None and time.monotonic() < t_end:
            stamp = i * 20_000_000  # 50 Hz odometry
            p = PoseStamped(stamp, 0.01 * i, 0.0, 0.0, np.diag([0.01, 0.01, 0.001]))
            pipeline.publish(OdometryUpdate(p, p))
            if i % 25 == 10:  # a keyframe every 0.5 s; the graph puts each one further left
                k = i // 25 + 1
                graph.poses[k] = np.array([p.x_m, 0.01 * k, 0.001 * k])
                pipeline.publish(KeyframeStored(StoredKeyframe(Frame(stamp, "floor", np.zeros((4, 4), np.uint8)),
                                                               p, keyframe_id=k, run_id=1)))
            i += 1
            time.sleep(0.02)  # odometry time at the pace of the wall clock (ROS-time stamps)
    finally:
        stage.finish()
        if peer.poll() is None:
            peer.kill()
        _, err = peer.communicate(timeout=10)
    assert peer.returncode == 0, err.decode()[-2000:]
    got = json.loads(out.read_text())
    map_odom = [t for t in got["tf"] if (t[1], t[2]) == ("map", "odom")]
    assert len(map_odom) >= 5
    # the correction the graph asked for arrived (after keyframe 1), with ROS-time stamps
    moved = [t for t in map_odom if abs(t[4]) > 1e-6]
    assert moved, "no loop-corrected map -> odom received"
    # each value sent is the one the graph implied at a keyframe: map pose * odom pose^-1
    expected = [tuple(map_to_odom(graph.poses[k], np.array([graph.poses[k][0], 0.0, 0.0])))
                for k in sorted(graph.poses)]
    for t in moved:
        assert any(np.allclose(t[3:6], e, atol=1e-9) for e in expected)
    assert all(abs(t[0] - t[6]) < 60e9 for t in map_odom)  # stamped in Unix time, not from 0
    assert ("odom", "base_footprint") in {(t[1], t[2]) for t in got["tf"]}  # robotd owns the (kobuki) base
    # the late joiner got /tf_static (sent once, before any /tf)
    assert got["tf_static_joined_after_s"] is not None and len(got["static"]) == 1
    frames = {child: parent for parent, child, _z in got["static"][0]}
    assert frames == {"base_link": "base_footprint", "floor_camera_optical_frame": "base_link"}
    # odometry at its rate: 20 Hz of odometry time, in order, nothing lost (reliable)
    stamps = np.array([o[0] for o in got["odometry"]])
    assert len(stamps) >= 5
    # every 50 ms of odometry time on average; 50 Hz input puts each one 40 or 60 ms apart
    assert set(np.diff(stamps).tolist()) <= {40_000_000, 60_000_000}
    assert abs(int(stamps[-1] - stamps[0]) - 50_000_000 * (len(stamps) - 1)) <= 10_000_000
    assert {(o[1], o[2]) for o in got["odometry"]} == {("odom", "base_footprint")}
    assert got["odometry"][0][3] == pytest.approx(0.01)
    # ros_discovery_info: robotd's participant holds one node, "robotd" in "/", whose
    # writers are the topics' (what `ros2 node list` and `ros2 node info` read)
    assert got["discovery"], "no ros_discovery_info received"
    last = got["discovery"][-1]
    assert last["gid"] == sink.participant.guid.hex()
    (ns, name, readers, writers), = last["nodes"]
    assert (ns, name, readers) == ("/", "robotd", [])
    assert sorted(writers) == sorted(writer_gids.values())
    assert writer_gids["tf"] in writers and len(writers) == len(sink.keys) == 7


@pytest.mark.slow
def test_demo_on_ros2_reaches_a_subscriber(tmp_path: Path) -> None:
    """``robotd demo --ros2`` in one process, a subscriber in another, each on ``lo``."""
    domain = domain_for(2)
    out = tmp_path / "sub.json"
    env = peer_env(domain)
    demo = subprocess.Popen([sys.executable, "-m", "robotd.app.cli", "demo", "--ros2", "--duration", "30",
                             "--no-plot", "--out", str(tmp_path / "demo")],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    peer = subprocess.run([sys.executable, str(PEER), "sub", str(domain), str(out), "240", "20", "1", "40"],
                          env=env, capture_output=True, timeout=300)
    demo.kill()
    demo.communicate(timeout=30)
    assert peer.returncode == 0, peer.stderr.decode()[-2000:]
    got = json.loads(out.read_text())
    map_odom = [t for t in got["tf"] if (t[1], t[2]) == ("map", "odom")]
    assert len(map_odom) >= 20
    assert ("odom", "base_footprint") in {(t[1], t[2]) for t in got["tf"]}
    assert got["tf_static_joined_after_s"] is not None and len(got["static"]) == 1
    frames = {child: parent for parent, child, _z in got["static"][0]}
    assert frames["floor_camera_optical_frame"] == "base_link"
    z = {child: z for _p, child, z in got["static"][0]}
    assert z["floor_camera_optical_frame"] == pytest.approx(0.40)  # the virtual robot's lens height
    stamps = np.array([o[0] for o in got["odometry"]])
    assert len(stamps) >= 40
    # 20 Hz of odometry time from the Kobuki's 50 Hz: 40 or 60 ms apart, 50 ms on average
    assert set(np.diff(stamps).tolist()) <= {40_000_000, 60_000_000}
    assert abs(int(stamps[-1] - stamps[0]) - 50_000_000 * (len(stamps) - 1)) <= 10_000_000
