"""``bench/bench_map_turn.py``: the linearised graph's correction of the truth and the turn
it measures."""

from __future__ import annotations

import math

import numpy as np

from bench.bench_map_turn import linear_solve, turn_about_start
from robotd.base.geometry import between, compose, se2_log, wrap_angle


def _square(n: int = 41) -> np.ndarray:
    """Keyframes along three sides of a 2 m square, turning left at the corners."""
    poses = [np.zeros(3)]
    for k in range(1, n):
        step = np.array([0.15, 0.0, math.pi / 2 if k % 13 == 0 else 0.0])
        poses.append(compose(poses[-1], step))
    return np.array(poses)


def _chain(truth: np.ndarray, yaw_errors: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Odometry edges along ``truth`` whose headings are off by ``yaw_errors`` (rad)."""
    ends = np.array([(k, k + 1) for k in range(len(truth) - 1)])
    deltas = np.array([between(truth[i], truth[j]) for i, j in ends])
    deltas[:, 2] += yaw_errors
    err = np.array([se2_log(between(d, between(truth[i], truth[j]))) for d, (i, j) in zip(deltas, ends)])
    info = np.repeat(np.diag([1e6, 1e6, 1e4])[None], len(ends), 0)
    return ends, err, info


def test_a_chain_alone_is_the_odometry_composed():
    truth = _square()
    rng = np.random.default_rng(3)
    yaw_err = rng.normal(0.0, 1e-4, len(truth) - 1)
    ends, err, info = _chain(truth, yaw_err)
    got = linear_solve(truth, ends, err, info)
    composed = [truth[0]]
    for (i, j), e in zip(ends, yaw_err):
        d = between(truth[i], truth[j])
        composed.append(compose(composed[-1], d + np.array([0.0, 0.0, e])))
    composed = np.array(composed)
    ape = 1e3 * math.sqrt(np.mean(np.sum((composed[:, :2] - truth[:, :2]) ** 2, 1)))
    assert abs(got["ape_anchored_mm"] - ape) < 1e-3 * ape
    assert abs(got["yaw_mean_mdeg"] - 1e3 * math.degrees(np.mean(wrap_angle(composed[:, 2] - truth[:, 2])))) < 1e-3


def test_the_first_edge_heading_error_turns_the_whole_map_about_the_start():
    truth = _square()
    yaw_err = np.zeros(len(truth) - 1)
    yaw_err[0] = 2e-4  # the first edge turned by 0.2 mrad, all others exact
    ends, err, info = _chain(truth, yaw_err)
    got = linear_solve(truth, ends, err, info)
    n = len(truth)
    assert abs(got["yaw_mean_mdeg"] - 1e3 * math.degrees(2e-4) * (n - 1) / n) < 1e-3
    # every keyframe after the first sits on the truth turned by 0.2 mrad about the second,
    # 15 cm from the start: about that turn about the start, fitted back with the other sign
    assert abs(got["turn_mdeg"] + 1e3 * math.degrees(2e-4)) < 0.1 * 1e3 * math.degrees(2e-4)


def test_a_stiff_loop_back_to_the_start_spreads_the_first_edge_error_along_the_chain():
    truth = _square()
    yaw_err = np.zeros(len(truth) - 1)
    yaw_err[0] = 2e-4
    ends, err, info = _chain(truth, yaw_err)
    alone = linear_solve(truth, ends, err, info)
    # an exact loop from the last keyframe back to the start that knows the heading far
    # better than the chain and the position not at all: the last keyframe's heading is
    # the truth's, each of the n - 1 edges takes its share of the first edge's error e
    # alike, so keyframe k is off by e (1 - k / (n - 1))
    n = len(truth)
    ends = np.vstack([ends, [0, n - 1]])
    err = np.vstack([err, np.zeros(3)])
    info = np.concatenate([info, np.diag([1e-6, 1e-6, 1e9])[None]])
    got = linear_solve(truth, ends, err, info)
    k = np.arange(n)
    want = 1e3 * math.degrees(np.mean(2e-4 * (1.0 - k / (n - 1)) * (k > 0)))
    assert abs(got["yaw_mean_mdeg"] - want) < 1e-3 * want
    assert alone["yaw_mean_mdeg"] > 1.9 * want


def test_turn_about_start_finds_a_turn_it_is_given():
    truth = _square()
    turned = compose(np.array([0.0, 0.0, 1e-3]), truth)
    assert abs(turn_about_start(truth, turned) + 1e-3) < 1e-9
