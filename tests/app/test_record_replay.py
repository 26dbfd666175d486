"""Record the virtual robot to MCAP, replay it through the daemon: the same map comes out,
every time, with every frame processed."""

from __future__ import annotations

import hashlib
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from drivers.recording.reader import read_recording
from robotd.app.demo import run_demo
from robotd.app.service import run_replay
from robotd.base.config import Config, replace, with_virtual_floor_camera
from robotd.io.store import MapStore


def _replay(rec: Path, map_path: Path) -> dict:
    cfg = with_virtual_floor_camera(replace(Config(), "map", path=str(map_path)))
    return run_replay(cfg, rec, speed=None)


def _map_content(path: Path) -> str:
    """A digest of everything a replay decides: keyframes (stamp, pose, covariance,
    descriptor, image) and links, in id order. Run rows differ (wall-clock epoch)."""
    h = hashlib.sha256()
    with sqlite3.connect(path) as raw:
        for row in raw.execute("SELECT id, run_id, stamp_ns, x_m, y_m, yaw_rad, covariance, image,"
                               " descriptor, descriptor_mode FROM keyframes ORDER BY id"):
            h.update(repr(row).encode())
        for row in raw.execute("SELECT * FROM links ORDER BY id"):
            h.update(repr(row).encode())
    raw.close()
    return h.hexdigest()


def _assert_same_keyframes(live: Path, replayed: Path) -> None:
    with MapStore.open(live, create=False) as a, MapStore.open(replayed, create=False) as b:
        ka, kb = list(a.keyframes()), list(b.keyframes())
        assert [k.stamp_ns for k in ka] == [k.stamp_ns for k in kb]
        pa = np.array([[k.x_m, k.y_m, k.yaw_rad] for k in ka])
        pb = np.array([[k.x_m, k.y_m, k.yaw_rad] for k in kb])
        assert np.max(np.abs(pa - pb)) < 1e-5
        assert [k.descriptor for k in ka] == [k.descriptor for k in kb]
        assert np.array_equal(a.keyframe_image(ka[-1].id), b.keyframe_image(kb[-1].id))
        assert len(a.links("odometry")) == len(b.links("odometry")) == len(ka) - 1


def test_replay_reproduces_the_live_keyframes(tmp_path: Path):
    """Recorded lossless (PNG): the replay sees the very pixels the live run saw."""
    rec = tmp_path / "run.mcap"
    s = run_demo(replace(Config(), "recording", image_format="png"), out=tmp_path / "live",
                 route="square", duration_s=8.0, seed=5, plot=False, record=rec)
    topics: dict[str, int] = {}
    for topic, _ in read_recording(rec):
        topics[topic] = topics.get(topic, 0) + 1
    assert topics["/floor_camera/image/compressed"] == s["frames_rendered"]
    assert topics["/wheel_ticks"] == s["odometry_samples"]
    assert topics["/ground_truth"] > 0 and topics["/odom"] == s["odometry_samples"]

    r = _replay(rec, tmp_path / "replay.sqlite")
    assert r["frames"] == s["frames_rendered"] and r["frames_unsynced"] == 0
    assert r["keyframes"] == s["keyframes"]
    _assert_same_keyframes(tmp_path / "live" / "map.sqlite", tmp_path / "replay.sqlite")


def test_ten_replays_give_identical_maps(tmp_path: Path):
    rec = tmp_path / "short.mcap"
    s = run_demo(Config(), out=tmp_path / "live", route="figure8", duration_s=3.0, seed=2,
                 plot=False, record=rec)
    digests = set()
    for i in range(10):
        r = _replay(rec, tmp_path / f"replay{i}.sqlite")
        assert (r["frames"], r["frames_unsynced"], r["keyframes"]) == (s["frames_rendered"], 0, s["keyframes"])
        digests.add(_map_content(tmp_path / f"replay{i}.sqlite"))
    assert len(digests) == 1


@pytest.mark.slow
def test_a_long_full_speed_replay_loses_no_frame(tmp_path: Path):
    """Two and a half minutes of robot time replayed as fast as the CPU allows: every frame
    reaches the pipeline, none waits out its odometry, the keyframes are the live run's
    (recorded lossless, PNG, so the descriptors must be identical too)."""
    rec = tmp_path / "long.mcap"
    s = run_demo(replace(Config(), "recording", image_format="png"), out=tmp_path / "live",
                 route="office", duration_s=150.0, seed=0, plot=False, record=rec)
    assert s["robot_time_s"] >= 120.0
    r = _replay(rec, tmp_path / "replay.sqlite")
    assert r["frames"] == s["frames_rendered"] and r["frames_unsynced"] == 0
    assert r["keyframes"] == s["keyframes"]
    _assert_same_keyframes(tmp_path / "live" / "map.sqlite", tmp_path / "replay.sqlite")


def test_an_interrupted_replay_says_so_and_reports_what_it_did(tmp_path: Path):
    """Ctrl-C used to report the whole recording as replayed and exit 0."""
    import signal
    import subprocess
    import sys

    rec = tmp_path / "run.mcap"
    run_demo(Config(), out=tmp_path / "live", route="square", duration_s=4.0, seed=5,
             plot=False, record=rec)
    map_path = tmp_path / "replay.sqlite"
    proc = subprocess.Popen([sys.executable, "-m", "robotd.app.cli", "replay", str(rec), "--map",
                             str(map_path), "--speed", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in proc.stderr:  # at real speed, the replay has about 4 s to go
        if "robotd running" in line:
            proc.send_signal(signal.SIGINT)
            break
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr[-3000:]
    assert "Traceback" not in stderr and stdout == ""
    said = stderr.strip().splitlines()[-1]  # the outcome, after the log lines
    assert said.startswith(f"robotd: replay of {rec} interrupted (SIGINT) after ")
    done_s = float(said.split(" after ")[1].split(" ")[0])
    assert 0.0 <= done_s < 3.5 and "of its 4.0 s" in said
    with MapStore.open(map_path, create=False) as store:
        (run,) = store.runs()
        assert run.ended_ns is not None  # the map is consistent, its run closed
        assert f"{store.count_keyframes()} keyframes -> {map_path}" in said
