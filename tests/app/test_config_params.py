"""One source of truth: the algorithm parameter classes are built from their config
sections, and their defaults are the config's defaults (written once, in
robotd/base/config.py)."""

from __future__ import annotations

import dataclasses
import inspect
import math

import numpy as np
import pytest

from robotd.base.config import Config, replace
from robotd.floor.detector import FloorDetectorParams
from robotd.floor.vo import VoParams
from robotd.forward.planar import PlanarLoopParams
from robotd.odometry.ekf import EkfParams
from robotd.odometry.kinematics import DiffDriveParams


def test_the_params_of_the_default_config_are_the_params_defaults():
    cfg = Config()
    assert EkfParams.from_config(cfg.odometry) == EkfParams()
    assert DiffDriveParams.from_config(cfg.robot) == DiffDriveParams()
    assert FloorDetectorParams.from_config(cfg.floor_detector) == FloorDetectorParams()
    vo = VoParams.from_config(cfg.visual_odometry, cfg.floor_detector.descriptor_mode)
    default = VoParams()
    assert (vo.descriptor_mode, vo.min_inliers, vo.ransac_threshold_m) == (
        default.descriptor_mode, default.min_inliers, default.ransac_threshold_m)
    assert PlanarLoopParams.from_config(cfg.forward_detector) == PlanarLoopParams()


def test_every_odometry_key_reaches_the_filter():
    """Each [odometry] key is an EkfParams field of the same name: a changed value arrives."""
    cfg = Config()
    for f in dataclasses.fields(cfg.odometry):
        if f.name in ("noise_model", "slip_gate_sigma"):  # build_odometry reads them (test_assemble_noise.py)
            continue
        value = getattr(cfg.odometry, f.name)
        changed = replace(cfg, "odometry", **{f.name: (not value) if isinstance(value, bool) else value * 1.5 + 1e-6})
        params = EkfParams.from_config(changed.odometry)
        assert getattr(params, f.name) == getattr(changed.odometry, f.name), f.name
        assert getattr(params, f.name) != getattr(EkfParams(), f.name), f.name


def test_changed_sections_reach_the_other_params():
    cfg = replace(Config(), "robot", wheel_radius_m=0.05, wheel_base_m=0.3, ticks_per_rev=1000.0)
    assert DiffDriveParams.from_config(cfg.robot) == DiffDriveParams(0.05, 0.3, 1000.0)
    assert DiffDriveParams.from_config(cfg.robot, wheel_base_m=0.31).wheel_base_m == 0.31
    cfg = replace(cfg, "floor_detector", descriptor_mode=2, candidates=7, shortlist=20, exclude_recent_s=3.0,
                  ransac_confidence=0.95)
    assert FloorDetectorParams.from_config(cfg.floor_detector) == FloorDetectorParams(2, 7, 20, 3.0, 0.95)
    cfg = replace(cfg, "visual_odometry", min_inliers=11, ransac_threshold_m=0.004)
    vo = VoParams.from_config(cfg.visual_odometry, 2)
    assert (vo.descriptor_mode, vo.min_inliers, vo.ransac_threshold_m) == (2, 11, 0.004)
    cfg = replace(cfg, "forward_detector", sigma_bearing_deg=3.0, sigma_yaw_deg=0.5)
    loop = PlanarLoopParams.from_config(cfg.forward_detector)
    assert (loop.sigma_bearing_rad, loop.sigma_yaw_rad) == pytest.approx((math.radians(3.0), math.radians(0.5)))


def test_the_stage_defaults_of_the_app_are_the_config_defaults():
    """Stages built in robotd/app with keyword defaults of their own: the same values."""
    from robotd.app.stages.forward_loops import ForwardLoopStage
    from robotd.app.stages.pose_graph import PoseGraphStage
    from robotd.graph.mappedground import MappedGroundParams

    cfg = Config()
    assert MappedGroundParams() == MappedGroundParams(cfg.pose_graph.mapped_radius_m,
                                                      cfg.pose_graph.max_unlocalised_m)
    assert inspect.signature(PoseGraphStage).parameters["gate_chi2"].default == cfg.pose_graph.gate_chi2
    fw = inspect.signature(ForwardLoopStage).parameters
    assert (fw["distance_m"].default, fw["rotation_rad"].default, fw["sync_tolerance_s"].default) == (
        cfg.forward_detector.distance_m, math.radians(cfg.forward_detector.rotation_deg),
        cfg.forward_detector.sync_tolerance_s)


def test_driver_keyword_defaults_that_are_config_keys_are_the_config_defaults():
    """The CAN driver's keywords named like [can] and [robot] keys default to those keys'
    defaults (``yaw`` excepted: the driver's default is no gyro, the config names the
    shipped DBC's signal); the Kobuki's baud rate is [base]'s."""
    from drivers.can.driver import CanBaseDriver
    from drivers.kobuki.protocol import BAUDRATE

    cfg = Config()
    defaults = {**dataclasses.asdict(cfg.can), **dataclasses.asdict(cfg.robot)}
    params = inspect.signature(CanBaseDriver).parameters
    shared = [n for n, p in params.items() if n in defaults and n != "yaw"
              and p.default is not inspect.Parameter.empty]
    assert len(shared) >= 9, shared
    for name in shared:
        assert params[name].default == defaults[name], name
    assert BAUDRATE == cfg.base.baudrate


def test_ransac_confidence_reaches_the_floor_query():
    """``[floor_detector] ransac_confidence`` is the confidence of every query's matcher;
    0 leaves the index's own match parameters."""
    from robotd.floor.descriptor import extract
    from robotd.floor.detector import FloorLoopDetector
    from robotd.floor.index import FloorIndex

    seen = []

    class Spy(FloorIndex):
        @property
        def ids(self) -> np.ndarray:
            return np.array([0])  # one keyframe of an earlier run: every query asks the index

        def query(self, *args, **kwargs):
            seen.append(kwargs.get("match_params"))
            return []

    image = (np.random.default_rng(0).random((240, 320)) * 255).astype(np.uint8)
    blob = extract(image, 1)
    for confidence in (0.95, 0.0):
        spy = Spy()
        FloorLoopDetector(FloorDetectorParams(descriptor_mode=1, ransac_confidence=confidence), spy).query(0, blob)
        got = seen[-1]
        assert (got.confidence if got is not None else 0.0) == confidence
