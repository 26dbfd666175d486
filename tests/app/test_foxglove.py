"""The Foxglove live view: a plain ``websockets`` client (not Foxglove's own) speaks the
WebSocket protocol to the server, subscribes, and decodes what it receives with rosbags."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

pytest.importorskip("foxglove")
websockets_sync = pytest.importorskip("websockets.sync.client")

from rosbags.typesys import Stores, get_typestore  # noqa: E402

from robotd.app.outputs import FoxgloveSink, RosOutputStage, topic_specs  # noqa: E402
from robotd.app.pipeline import Pipeline  # noqa: E402
from robotd.base.clock import ManualClock  # noqa: E402
from robotd.base.config import Config, replace  # noqa: E402
from robotd.base.messages import Frame, KeyframeStored, Link, OdometryUpdate, PoseStamped, StoredKeyframe  # noqa: E402
from tests.app.test_outputs import FakeGraph  # noqa: E402

TS = get_typestore(Stores.ROS2_HUMBLE)


def recv_json(ws, op: str) -> dict:
    while True:
        m = ws.recv(timeout=10)
        if isinstance(m, str):
            d = json.loads(m)
            if d.get("op") == op:
                return d


def test_a_websockets_client_subscribes_and_decodes() -> None:
    cfg = replace(replace(Config(), "foxglove", enabled=True), "ros2", ros_time=False)
    sink = FoxgloveSink("127.0.0.1", 0, keys=set(topic_specs(cfg)))  # port 0: any free port
    pipeline = Pipeline()
    graph = pipeline.add(FakeGraph())
    stage = pipeline.add(RosOutputStage(cfg, [sink], ManualClock(), wall_clock=ManualClock()))
    try:
        uri = f"ws://127.0.0.1:{sink.port}"
        with websockets_sync.connect(uri, subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws:
            assert ws.subprotocol == "foxglove.sdk.v1"
            info = recv_json(ws, "serverInfo")
            assert info["name"] == "robotd"
            channels: dict[str, dict] = {}
            while len(channels) < len(sink.channels):
                for ch in recv_json(ws, "advertise")["channels"]:
                    channels[ch["topic"]] = ch
            assert channels["/tf"]["encoding"] == "cdr" and channels["/tf"]["schemaEncoding"] == "ros2msg"
            assert channels["/robotd/path"]["schemaName"] == "nav_msgs/msg/Path"
            wanted = ["/tf", "/robotd/odometry", "/robotd/path", "/robotd/loop_closures",
                      "/robotd/keyframes/floor/compressed", "/diagnostics"]
            subs = {n + 1: channels[t] for n, t in enumerate(wanted)}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": sid, "channelId": ch["id"]} for sid, ch in subs.items()]}))
            # Publish until every subscribed topic has been seen (the subscription is
            # asynchronous on the server's side: early messages may go to nobody).
            seen: dict[str, list] = {t: [] for t in wanted}
            img = (np.arange(48 * 64) % 200).astype(np.uint8).reshape(48, 64)
            for i in range(400):
                stamp = i * 20_000_000
                p = PoseStamped(stamp, 0.01 * i, 0.0, 0.0, np.eye(3) * 0.01)
                pipeline.publish(OdometryUpdate(p, p))
                if i % 20 == 0:
                    k = i // 20
                    graph.poses[k] = np.array([0.01 * i, 0.002 * k, 0.0])
                    pipeline.publish(KeyframeStored(StoredKeyframe(Frame(stamp, "floor", img), p, keyframe_id=k, run_id=1)))
                    if k >= 2:
                        pipeline.publish(Link("loop", 0, k, np.zeros(3), np.eye(3)))
                    stage.wall.advance_ns(1_100_000_000)
                    pipeline.poll()
                while True:
                    try:
                        m = ws.recv(timeout=0.01 if i < 399 else 2)
                    except TimeoutError:
                        break
                    if isinstance(m, bytes):
                        assert m[0] == 0x01  # message data
                        sid, log_time = struct.unpack_from("<IQ", m, 1)
                        ch = subs[sid]
                        msg = TS.deserialize_cdr(m[13:], ch["schemaName"])
                        seen[ch["topic"]].append((log_time, msg))
                if all(seen.values()) and len(seen["/robotd/path"][-1][1].poses) >= 3:
                    break
    finally:
        stage.finish()
    assert all(seen.values()), {t: len(v) for t, v in seen.items()}
    log_time, tf = seen["/tf"][-1]
    assert tf.transforms[0].header.frame_id == "map" and tf.transforms[0].child_frame_id == "odom"
    assert log_time == tf.transforms[0].header.stamp.sec * 10**9 + tf.transforms[0].header.stamp.nanosec
    _, odom = seen["/robotd/odometry"][-1]
    assert odom.header.frame_id == "odom" and odom.pose.covariance[0] == pytest.approx(0.01)
    _, path = seen["/robotd/path"][-1]
    assert path.header.frame_id == "map"
    assert [p.pose.position.y for p in path.poses] == [graph.poses[k][1] for k in sorted(graph.poses)][:len(path.poses)]
    _, loops = seen["/robotd/loop_closures"][-1]
    assert loops.markers[0].ns == "loops/floor" and len(loops.markers[0].points) >= 2
    _, image = seen["/robotd/keyframes/floor/compressed"][-1]
    import cv2
    assert cv2.imdecode(image.data, cv2.IMREAD_UNCHANGED).shape == (48, 64)
    _, diag = seen["/diagnostics"][-1]
    assert "robotd: odometry" in {s.name for s in diag.status}


def test_the_schemas_it_advertises_parse_in_rosbags() -> None:
    from rosbags.typesys import get_types_from_msg

    from robotd.base import ros2msg

    for spec in topic_specs(Config()).values():
        types = get_types_from_msg(ros2msg.schema_text(spec.type_name), spec.type_name)
        assert spec.type_name in types
