"""Epipolar verification on the virtual forward camera's images (issue 14: no false forward
loops on the virtual route).

The poses are keyframes of the office route (seed 0, the bench's 1139-image sequence:
``bench/bench_forward_sequence.py --step-m 0.4 --turn-deg 30 --repeats 4``, images 2, 71,
172 and 457). Image 71 looks at a copy of the poster that image 2 sees, on a wall 90 deg
away: the detector declared that loop before the support check existed.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.forward.features import FeatureExtractor
from robotd.forward.planar import planar_motion
from robotd.forward.verify import (
    ACCEPTED,
    SMALL_SUPPORT,
    VerifyParams,
    camera_matrix_guess,
    verify_pair,
)
from sim.cameras.forward import (
    ForwardCameraModel,
    ForwardRenderer,
    ForwardRenderParams,
    view_histograms,
    view_overlap,
)
from sim.world.rooms import WorldParams, world_for_route

POSES = {
    "poster": np.array([0.83333, 0.0, 0.0]),            # image 2: the poster on the left wall
    "poster_copy": np.array([0.0, 2.81139, -math.pi / 2]),  # image 71: its copy, 90 deg away
    "corridor": np.array([3.33226, 6.0, 0.0]),           # image 172
    "corridor_again": np.array([3.75289, 6.0, 0.0]),     # image 457, next lap, 0.42 m on
}


@pytest.fixture(scope="module")
def office():
    world = world_for_route("office", 0, WorldParams())
    camera = ForwardCameraModel()
    renderer = ForwardRenderer(world, camera, ForwardRenderParams(noise_sigma=2.0), np.random.default_rng(2))
    extract = FeatureExtractor()
    feats = {k: extract(renderer.render(p, 0.0)) for k, p in POSES.items()}
    k_matrix = camera_matrix_guess(640, 480, camera.intrinsics.fx_px)
    return renderer, feats, k_matrix


def _overlap(renderer, a: str, b: str) -> float:
    return float(view_overlap(view_histograms(renderer, np.array([POSES[a], POSES[b]])))[0, 1])


def test_a_repeated_poster_passes_the_papers_check_but_not_the_support_check(office):
    renderer, feats, k = office
    assert _overlap(renderer, "poster", "poster_copy") < 0.01  # the truth: not the same place
    paper = verify_pair(feats["poster"], feats["poster_copy"], VerifyParams(min_support_area=0.0), k)
    assert paper.accepted and paper.n_inliers >= 40  # measured 65
    dyaw, _, _ = planar_motion(paper.rotation, paper.translation_dir)
    assert abs(math.degrees(dyaw)) < 45  # a heading change far from the true 90 deg
    v = verify_pair(feats["poster"], feats["poster_copy"], VerifyParams(), k)
    assert not v.accepted and v.reason == SMALL_SUPPORT
    assert v.planar and v.support_area < 0.02  # measured 0.010: the checker strip under the poster


def test_a_true_loop_on_the_next_lap_is_still_accepted(office):
    renderer, feats, k = office
    assert _overlap(renderer, "corridor", "corridor_again") > 0.5  # measured 0.63
    v = verify_pair(feats["corridor"], feats["corridor_again"], VerifyParams(), k)
    assert v.accepted and v.reason == ACCEPTED
    assert v.n_inliers >= 100 and v.support_area > 0.2  # measured 220 and 0.46
    dyaw, bearing, tilt = planar_motion(v.rotation, v.translation_dir)
    # The truth: same heading, the new camera 0.42 m straight ahead.
    assert abs(math.degrees(dyaw)) < 2 and abs(math.degrees(bearing)) < 5 and math.degrees(tilt) < 3
