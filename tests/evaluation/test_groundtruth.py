"""A run judged by its ground truth, on a synthetic straight drive."""

import math
from dataclasses import dataclass

import numpy as np
import pytest

from robotd.base.messages import CandidateFate, ForwardLoop, LoopFate
from robotd.evaluation.groundtruth import (
    FORWARD_YAW_OK_DEG,
    forward_evaluation,
    keyframe_errors,
    relocalisation_evaluation,
)
from robotd.evaluation.observations import RunObservations


@dataclass
class Straight:
    """Along x at ``speed`` m/s, turning at ``turn`` rad/s (a GroundTruth)."""

    speed: float = 0.5
    turn: float = 0.0
    dt_s: float = 0.01

    @property
    def t_s(self) -> np.ndarray:
        return np.arange(0.0, 100.0, self.dt_s)

    @property
    def v_mps(self) -> np.ndarray:
        return np.full(len(self.t_s), self.speed)

    def pose_at(self, t_s: float | np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        return np.stack([self.speed * t, np.zeros_like(t), self.turn * t], axis=-1)


def _observed(stamps_s: list[float]) -> RunObservations:
    obs = RunObservations()
    for i, t in enumerate(stamps_s):
        obs.keyframe_ids.append(i + 1)
        obs.keyframe_stamps.append(int(t * 1e9))
        obs.keyframe_poses.append((0.5 * t, 0.0, 0.0))
    return obs


def test_keyframe_errors_of_a_scaled_estimate():
    truth = Straight().pose_at(np.arange(11.0))
    est = truth * [1.02, 1.0, 1.0]  # 2 % too long
    e = keyframe_errors(truth, [("odometry", est)])["odometry"]
    assert e["end_position_error_m"] == pytest.approx(0.1)
    assert e["rpe_rmse_mm"] == pytest.approx(10.0)  # 0.5 m steps, 1 cm each too long
    assert e["ape_origin_rmse_m"] == pytest.approx(0.01 * math.sqrt(np.mean(np.arange(11.0) ** 2)))


def test_the_aligned_ate_forgives_the_first_keyframes_heading_and_the_anchored_ape_does_not():
    truth = Straight().pose_at(np.arange(11.0))  # 5 m along x
    turn = math.radians(1.0)
    est = truth.copy()
    est[0, 2] += turn  # only the first keyframe's heading wrong: anchoring on it turns the rest
    e = keyframe_errors(truth, [("odometry", est)])["odometry"]
    assert e["ate_aligned_rmse_m"] == pytest.approx(0.0, abs=1e-9)
    chord = 2 * math.sin(turn / 2) * 0.5 * np.arange(11.0)
    assert e["ape_origin_rmse_m"] == pytest.approx(math.sqrt(np.mean(chord ** 2)), rel=1e-6)
    bent = est.copy()
    bent[-1, 1] += 0.01  # the shape itself wrong at one keyframe
    assert keyframe_errors(truth, [("o", bent)])["o"]["ate_aligned_rmse_m"] > 0.002


def test_forward_loops_judged_right_and_wrong():
    obs = _observed([10.0, 20.0, 30.0])
    # Keyframe 3 sees keyframe 1's place 10 m behind it... as the truth says: 10 m ahead of 1.
    obs.forward_loops.append(ForwardLoop(1, 3, 0.9, 0.0, 0.0, 40))
    obs.forward_loops.append(ForwardLoop(1, 2, 0.8, math.radians(2 * FORWARD_YAW_OK_DEG), 0.0, 30))
    obs.on_fate(CandidateFate(3, 1, 0.9, LoopFate.ACCEPTED, "forward: chi2 0.1"))
    out = forward_evaluation(Straight(), np.zeros(3), obs, {"forward_images": 3})
    assert out["verified_loops"] == 2 and out["verified_right"] == 1
    assert out["accepted"] == 1 and out["accepted_right"] == 1
    assert [r["fate"] for r in out["loops"]] == ["accepted", "none"]
    assert out["loops"][0]["true_distance_m"] == pytest.approx(10.0)


def test_relocalisation_timing_and_pose_error():
    obs = _observed([1.0, 2.0])
    kidnap = (10.0, 5.0, 2.0)  # lifted at 10 s, carried 2 s
    # Relocalised at 15 s with the pose the truth has then, shifted 5 cm sideways.
    truth = Straight()
    pose = truth.pose_at(15.0) - truth.pose_at(1.0) + np.array([0.5, 0.05, 0.0])
    reloc = [{"stamp_ns": int(15e9), "run": 1, "after_s": 3.0, "after_m": 1.4, "candidates": 4,
              "pose": pose.tolist()}]
    out = relocalisation_evaluation(truth, kidnap, obs, reloc, {"lifts": 1})
    assert out["relocalised"] and out["put_down_at_s"] == 12.0
    assert out["after_s"] == pytest.approx(3.0)
    assert out["after_m_true"] == pytest.approx(1.5, abs=0.01)
    assert out["position_error_m"] == pytest.approx(0.05, abs=1e-9)
    assert relocalisation_evaluation(truth, kidnap, obs, [], {})["relocalised"] is False


def test_forward_loops_beside_the_judge_the_truth_against_the_edges_own_noise():
    obs = _observed([10.0, 10.42, 30.0])  # keyframes 1 and 2 are 0.21 m apart along x
    # 12 deg of bearing at 0.21 m (2.2 cm sideways): wrong by the judge, inside the edge's own
    # noise (3 cm in the camera frame, 2 deg of bearing); 90 deg at 10 m is outside it.
    obs.forward_loops.append(ForwardLoop(1, 2, 0.9, 0.0, math.radians(12.0), 40))
    obs.forward_loops.append(ForwardLoop(1, 3, 0.9, 0.0, math.radians(90.0), 40))
    obs.on_fate(CandidateFate(2, 1, 0.9, LoopFate.ACCEPTED, "forward: chi2 1.0"))
    obs.on_fate(CandidateFate(3, 1, 0.9, LoopFate.ACCEPTED, "forward: chi2 99"))
    out = forward_evaluation(Straight(), np.zeros(3), obs, {"forward_images": 3})
    near, far = out["loops"]
    assert not near["right"] and not near["outside_own_noise"] and near["truth_chi2"] < 2.0
    assert not far["right"] and far["outside_own_noise"] and far["truth_chi2"] > 100.0
    assert out["accepted"] == 2 and out["accepted_right"] == 0 and out["accepted_outside_own_noise"] == 1
