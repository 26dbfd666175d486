"""The daemon on a ROS 2 robot: [base] driver = "ros2" and [floor_camera] source = "ros2"
opened through the registry as `robotd run` opens them, fed by a publisher process (a ROS 2
base driver and camera node, as far as DDS can tell) on the loopback interface."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from drivers.ros2 import dds  # noqa: E402
from robotd.app.assemble import assemble_daemon, open_map  # noqa: E402
from robotd.app.notify import Notifier  # noqa: E402
from robotd.app.service import open_sources  # noqa: E402
from robotd.base.clock import MonotonicClock  # noqa: E402
from robotd.base.config import Config, replace  # noqa: E402
from tests.drivers.test_ros2_dds import PEER, domain_for, peer_env  # noqa: E402


@pytest.mark.slow
def test_daemon_runs_on_ros2_topics(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    domain = domain_for(5)
    monkeypatch.setenv("CYCLONEDDS_URI", dds.loopback_config())  # this process: lo only
    cfg = replace(Config(), "base", driver="ros2")
    cfg = replace(cfg, "floor_camera", source="ros2", width_px=64, height_px=48, cx_px=31.5, cy_px=23.5)
    cfg = replace(cfg, "ros2", domain_id=domain, input_timeout_s=0.2)
    cfg = replace(cfg, "map", path=str(tmp_path / "map.sqlite"))
    cfg = replace(cfg, "visual_odometry", enabled=False)
    clock = MonotonicClock()
    sources = open_sources(cfg, clock)
    assert {n: type(s).__name__ for n, s in sources.items()} == {"base": "Ros2Base", "floor": "Ros2Camera"}
    peer = subprocess.Popen([sys.executable, str(PEER), "pub", str(domain), "3"], env=peer_env(domain),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        with open_map(cfg) as store:
            daemon = assemble_daemon(cfg, clock, sources, store, Notifier(), lossless=False,
                                     load_calibration_file=False, floor_detector=False,
                                     driver_stats=lambda: {n: s.stats() for n, s in sources.items()})
            report = daemon.run(stop_when=lambda: peer.poll() is not None)
            pose = daemon.pipeline.stage("odometry").odometry.pose()
            keyframes = store.count_keyframes()
    finally:
        for s in sources.values():
            s.close()
        out, err = peer.communicate(timeout=10)
    assert peer.returncode == 0, err.decode()[-2000:]
    sent = [json.loads(line) for line in out.decode().splitlines()]
    c = report.counters
    n_odom = sum(1 for s in sent if s["topic"] == "/odom")
    assert c["wheel_msgs"] >= n_odom - 5 and c["odometry_rejected"] == 0
    assert c["yaw_msgs"] > 0.8 * c["wheel_msgs"]
    # 0.2 m/s on an arc at 0.1 rad/s for the publisher's 3 s: the fused pose is where the
    # base said it was (the filter integrates the ticks and the gyro)
    t_end = (sent[-1]["stamp_ns"] - sent[0]["stamp_ns"]) / 1e9
    yaw = 0.1 * t_end
    assert math.hypot(pose.x_m - 2.0 * math.sin(yaw), pose.y_m - 2.0 * (1.0 - math.cos(yaw))) < 0.01
    assert abs(pose.yaw_rad - yaw) < 0.02
    # floor frames (10 Hz: one every 2 cm) became keyframes (one per [keyframes] distance_m
    # of travel): the map holds most of the steps they span (the first frames wait for
    # odometry, a few are lost at the end)
    assert c["frames"] >= 20
    spacing_m = cfg.keyframes.distance_m
    assert 0.6 * c["frames"] * 0.02 / spacing_m <= keyframes <= c["frames"] * 0.02 / spacing_m + 1
    # the base's 0.5 s pause: one gap in the driver's stats (STATUS shows it)
    assert report.driver_stats["base"]["gaps"] >= 1
    assert np.isfinite(pose.covariance).all()
