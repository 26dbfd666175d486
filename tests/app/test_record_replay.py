"""Record the virtual robot to MCAP, replay it through the daemon: the same map comes out."""

from pathlib import Path

import numpy as np

from drivers.recording.reader import read_recording
from robotd.base.config import Config, replace
from robotd.app.demo import run_demo
from robotd.app.service import run_replay
from robotd.io.store import MapStore


def test_replay_reproduces_the_live_keyframes(tmp_path: Path):
    rec = tmp_path / "run.mcap"
    s = run_demo(Config(), out=tmp_path / "live", route="square", duration_s=8.0, seed=5,
                 plot=False, record=rec)
    topics: dict[str, int] = {}
    for topic, _ in read_recording(rec):
        topics[topic] = topics.get(topic, 0) + 1
    assert topics["/floor_camera/image/compressed"] == s["frames_rendered"]
    assert topics["/wheel_ticks"] == s["odometry_samples"]
    assert topics["/ground_truth"] > 0 and topics["/odom"] == s["odometry_samples"]

    cfg = replace(replace(Config(), "map", path=str(tmp_path / "replay.sqlite")),
                  "floor_camera", source="virtual")
    r = run_replay(cfg, rec, speed=None)
    assert r["frames"] == s["frames_rendered"] and r["keyframes"] == s["keyframes"]
    with MapStore.open(tmp_path / "live" / "map.sqlite", create=False) as a, \
            MapStore.open(tmp_path / "replay.sqlite", create=False) as b:
        ka, kb = list(a.keyframes()), list(b.keyframes())
        assert [k.stamp_ns for k in ka] == [k.stamp_ns for k in kb]
        pa = np.array([[k.x_m, k.y_m, k.yaw_rad] for k in ka])
        pb = np.array([[k.x_m, k.y_m, k.yaw_rad] for k in kb])
        assert np.max(np.abs(pa - pb)) < 1e-5
        assert np.array_equal(a.keyframe_image(ka[-1].id), b.keyframe_image(kb[-1].id))
