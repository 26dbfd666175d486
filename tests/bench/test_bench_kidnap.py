"""``bench/bench_kidnap.py``: the route times it compares the two drives at, and its measures
of the loop-corrected keyframes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from bench.bench_kidnap import corrected_errors, route_time
from robotd.base.geometry import compose
from robotd.io.trajectory import write_tum


def test_route_time_is_the_robot_time_before_the_lift_and_shifted_after_the_put_down():
    t = np.array([0.0, 59.0, 65.0, 70.0, 120.0])
    # lifted at 60 s, carried 5 s, put down where the route was at 20 s
    np.testing.assert_allclose(route_time(t, (60.0, 20.0)), [0.0, 59.0, 20.0, 25.0, 75.0])


def test_a_map_turned_about_its_first_keyframe_shows_in_the_anchored_measure_not_the_aligned(tmp_path: Path):
    t_ns = np.arange(0, 50) * 200_000_000
    truth = np.column_stack([np.linspace(0.0, 10.0, 50), np.zeros(50), np.zeros(50)])
    write_tum(tmp_path / "groundtruth.tum", t_ns, truth)
    turn = math.radians(0.05)
    # the first keyframe held where it is, the rest turned about it (a kink after it)
    turned = compose(np.array([0.0, 0.0, turn]), truth)
    turned[0] = truth[0]
    write_tum(tmp_path / "corrected.tum", t_ns, turned)
    e = corrected_errors(tmp_path)
    # the keyframe 10 m out is 10 m * 0.05 deg = 8.7 mm off
    assert abs(e["err_m"][-1] - 10.0 * turn) < 1e-5
    assert e["ape_anchored_m"] > 4e-3
    assert e["ate_aligned_m"] < 1e-5
    assert abs(e["fit_turn_deg"] + 0.05) < 1e-4  # the fit turns it back
