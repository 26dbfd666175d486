"""A restart on a stored map through the daemon's own stages (floor descriptors, the map
index, the trained threshold, floor loop transforms, the pose graph): the virtual robot's
floor camera renders a first run along the square route, then a second run that starts
elsewhere on it with odometry of its own; the second run relocalises against the first."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from robotd.app.assemble import build_pipeline
from robotd.app.demo import shipped_calibration
from robotd.base.camera import FloorCameraModel
from robotd.base.clock import ManualClock
from robotd.base.config import Config, replace
from robotd.base.geometry import between, compose, wrap_angle
from robotd.base.messages import Frame, Keyframe, PoseStamped
from robotd.io.calibfile import read_calibration
from robotd.io.store import MapStore
from sim.cameras.floor import FloorRenderer, RenderParams
from sim.route import MotionLimits, build_route, plan_motion
from sim.world.floor import Floor

DRIFT_PER_STEP = np.array([0.0, 0.0, 0.002])  # odometry heading error per keyframe, rad


def _drive(pipeline, renderer, motion, times_s: np.ndarray, stamp0_s: float,
           drift: np.ndarray = DRIFT_PER_STEP) -> list[tuple[float, np.ndarray]]:
    """Keyframes at ``times_s`` of the route: the rendered floor and an odometry pose that
    starts at zero and drifts by ``drift`` per keyframe; returns ``(stamp_s, true pose)``."""
    odo = np.zeros(3)
    prev = None
    cov = np.zeros((3, 3))
    out = []
    for n, t in enumerate(times_s):
        truth = motion.pose_at(t)
        if prev is not None:
            odo = compose(odo, between(prev, truth) + drift)
            cov = cov + np.diag([1e-6, 1e-6, 1e-5])
        prev = truth
        v, w = motion.velocity_at(t)
        stamp = stamp0_s + t
        image = renderer.render(truth, v, w, t)
        pipeline.publish(Keyframe(Frame(int(stamp * 1e9), "floor", image, n),
                                  PoseStamped(int(stamp * 1e9), *odo, cov.copy())))
        out.append((stamp, truth))
    return out


@pytest.mark.slow
def test_a_restart_relocalises_against_the_first_run_from_real_floor_loops(tmp_path: Path, caplog):
    calib_path = shipped_calibration()
    assert calib_path is not None
    calib = read_calibration(calib_path)
    cfg = replace(Config(), "calibration", path=str(calib_path))
    cfg = replace(cfg, "visual_odometry", enabled=False)
    cam = FloorCameraModel.from_config(cfg.floor_camera)
    motion = plan_motion(build_route("square"), MotionLimits())
    floor = Floor.default(seed=0)
    clock = ManualClock()
    caplog.set_level(logging.INFO, logger="robotd")  # the stage and the gate (robotd.graph.gate)
    with MapStore.open(tmp_path / "map.sqlite") as store:
        run1 = store.begin_run("")
        p1 = build_pipeline(cfg, clock, store, run1, lossless=True, calibration=calib)
        renderer = FloorRenderer(floor, cam, RenderParams(), np.random.default_rng(1))
        # Most of a lap without loops: an exact odometry, so that the map is the truth (run 2's
        # pose in it can then be judged against the truth).
        _drive(p1, renderer, motion, np.arange(0.0, 16.0, 0.2), 0.0, drift=np.zeros(3))
        p1.finish()
        store.end_run(run1)
        assert store.map_frame_runs() == {run1}
        first = {k.id: k for k in store.keyframes(run1)}
        assert "run 1 starts the map" in caplog.text

        # Restarted 9 s into the route (at the first corner, turned 90 deg; the odometry at zero again).
        run2 = store.begin_run("")
        p2 = build_pipeline(cfg, clock, store, run2, lossless=True, calibration=calib)
        graph = p2.stage("graph")
        times = np.arange(9.0, 15.0, 0.2)
        seen = _drive(p2, renderer, motion, times[:1], 1000.0)
        assert graph.status_fragment() == "not localised in the stored map"
        seen += _drive(p2, renderer, motion, times[1:], 1000.0)
        c = p2.counters()
        assert (c["relocalisations"], c["localised"]) == (1, 1), c
        [r] = graph.relocalised_at
        assert r["run"] == run1 and r["after_m"] < 1.5
        assert graph.status_fragment().startswith(f"relocalised against run {run1} after ")
        assert f"relocalised against run {run1} after" in caplog.text
        # The relocalising keyframe's pose in the map frame (run 1's odometry frame, which is
        # the truth's at the route start) is near its true pose; its own odometry is not.
        stamp_of = {k.id: k.stamp_ns / 1e9 for k in store.keyframes(run2)}
        truth_then = motion.pose_at(stamp_of[r["keyframe"]] - 1000.0)
        pose = np.asarray(r["pose"])
        assert np.hypot(*(pose[:2] - truth_then[:2])) < 0.05
        assert abs(wrap_angle(pose[2] - truth_then[2])) < np.radians(1.0)
        odo = store.keyframe(r["keyframe"])
        assert np.hypot(odo.x_m - truth_then[0], odo.y_m - truth_then[1]) > 1.5
        p2.finish()
        assert store.map_frame_runs() == {run1, run2}
        opt = store.optimized_poses()
        assert all(k in opt for k in first)
        run2_ids = sorted(stamp_of)
        err = [np.hypot(*(opt[k][:2] - motion.pose_at(stamp_of[k] - 1000.0)[:2])) for k in run2_ids]
        assert max(err) < 0.05
