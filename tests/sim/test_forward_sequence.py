"""Writing a route's forward keyframes and ground truth for ``robotd eval forward``."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from robotd.io.sequence import list_images, load_ground_truth, read_image
from sim.forward_sequence import (
    SequenceSettings,
    keyframe_times,
    write_forward_sequence,
)
from sim.route import Motion, build_route, plan_motion


def test_keyframes_every_step_or_turn():
    # 1 m straight at 0.5 m/s, then a quarter turn in place at 0.5 rad/s.
    v = np.concatenate([np.full(1000, 0.5), np.zeros(1000)])
    w = np.concatenate([np.zeros(1000), np.full(1000, 0.5 * math.pi / 2)])
    m = Motion.from_velocities(v, w, 0.002)
    t = keyframe_times(m, step_m=0.25, turn_rad=math.radians(30.0), rate_hz=50.0)
    p = m.poses_at(t)
    moving = t < 2.0
    assert np.diff(p[moving, 0]) == pytest.approx(0.25, abs=0.011)  # every 0.25 m (+ one 50 Hz sample)
    turning = t >= 2.0
    assert len(t[turning]) == 3  # 90 deg in 30 deg steps


def test_written_sequence_reads_back_through_robotd_io(tmp_path):
    settings = SequenceSettings(route="corridor", step_m=1.0, turn_rad=math.radians(45.0))
    summary = write_forward_sequence(tmp_path, settings)
    files = list_images(tmp_path, exclude=(tmp_path / "gt.npy",))
    assert len(files) == summary["images"] >= 16  # 16 m out and back, plus the U-turn
    assert files[0].name == "000000.png" and files[-1].name == f"{len(files) - 1:06d}.png"
    assert read_image(files[3]).shape == (480, 640, 3)
    truth = load_ground_truth(tmp_path / "gt.npy", len(files))
    assert np.array_equal(truth, truth.T) and not truth.diagonal().any()
    raw = np.load(tmp_path / "gt.npy")
    assert raw.dtype == np.uint8 and np.array_equal(raw, raw.T)
    overlap = np.load(tmp_path / "overlap.npy").astype(np.float32)
    assert np.all(overlap[raw > 0] >= settings.threshold - 1e-3)
    poses = np.loadtxt(tmp_path / "poses.csv", delimiter=",", skiprows=1)
    assert poses.shape == (len(files), 5)
    motion = plan_motion(build_route("corridor"))
    np.testing.assert_allclose(poses[:, 2:4], motion.poses_at(poses[:, 1])[:, :2], atol=1e-4)
    assert (tmp_path / "world" / "top_view.png").is_file()
    assert json.loads((tmp_path / "sequence.json").read_text())["images"] == len(files)


def test_repeated_laps_start_from_the_same_pose_and_stay_in_the_world():
    from sim.forward_sequence import _repeated_route
    from sim.world.rooms import world_for_route

    one, three = plan_motion(build_route("square")), plan_motion(_repeated_route("square", 3))
    assert three.length_m == pytest.approx(3 * one.length_m, rel=1e-6)
    world = world_for_route("square")
    assert all(world.contains(x, y) for x, y, _ in three.poses[::50])
