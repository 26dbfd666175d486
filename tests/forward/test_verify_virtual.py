"""Epipolar verification on the virtual forward camera's images (no false forward
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


# --- the relative pose a verified forward loop hands the pose graph ------
# Two views of one corridor (the images of the same name in the office sequence above), and
# two pairs of *different* places 2.4-2.6 m apart (images 671/839 and 269/956: no wall cell
# in common) that see the same repeating floor tiles and ceiling panels.
CORRIDOR = np.array([3.49755, 0.0, math.pi])
ALIASED = {"a": (np.array([0.17110, 3.33687, -2.367459]), np.array([0.12268, 5.78204, -2.221038])),
           "b": (np.array([0.22284, 5.88098, -2.503552]), np.array([0.16828, 3.33408, -2.359535]))}


def _truth(renderer, old_pose, new_pose):
    """The true ``(dyaw, bearing, distance)`` of the new camera in the old camera's planar frame."""
    from robotd.base.geometry import between, compose

    cam = renderer.camera
    mount = np.array([cam.x_m, cam.y_m, cam.yaw_rad])
    rel = between(compose(old_pose, mount), compose(new_pose, mount))
    return rel[2], math.atan2(rel[1], rel[0]), math.hypot(rel[0], rel[1])


@pytest.mark.parametrize("rel", [(0.6, 0.0, 0.0), (-0.6, 0.0, 0.0), (1.2, 0.3, 0.15), (-1.0, -0.3, -0.2)])
def test_the_loop_edge_is_the_true_relative_pose_whichever_camera_is_ahead(office, rel):
    """The from/to convention end to end: images rendered at two true poses (the new camera
    ahead of or behind the old one) -> verification -> planar motion -> the pose graph's
    robot-frame edge, which must be the true relative pose of the two robot poses."""
    from robotd.base.geometry import between, compose
    from robotd.forward.planar import loop_edge

    renderer, _, k = office
    cam = renderer.camera
    mount = np.array([cam.x_m, cam.y_m, cam.yaw_rad])
    extract = FeatureExtractor()
    old_pose = CORRIDOR
    new_pose = compose(CORRIDOR, np.array(rel))
    v = verify_pair(extract(renderer.render(old_pose)), extract(renderer.render(new_pose)),
                    VerifyParams(camera_height_m=cam.height_m), k)
    assert v.accepted
    dyaw, bearing, _ = planar_motion(v.rotation, v.translation_dir)
    t_yaw, t_bearing, t_dist = _truth(renderer, old_pose, new_pose)
    assert abs(math.degrees(dyaw - t_yaw)) < 1.5
    assert abs(math.degrees(math.remainder(bearing - t_bearing, math.tau))) < 6
    assert v.range_m is not None and 1 / 1.7 < v.range_m / t_dist < 1.7
    truth = between(old_pose, new_pose)
    delta, _ = loop_edge(truth, dyaw, bearing, mount, range_m=v.range_m)
    # Right in direction and heading; the length is the floor's measurement.
    assert abs(math.degrees(math.remainder(float(delta[2] - truth[2]), math.tau))) < 1.5
    assert math.hypot(*(delta[:2] - truth[:2])) < 0.7 * math.hypot(*truth[:2])


@pytest.mark.parametrize("pair", sorted(ALIASED))
def test_an_aliased_floor_and_ceiling_pass_the_epipolar_check_but_measure_the_wrong_range(office, pair):
    """The daemon's wrong forward loops: different places, the same floor and
    ceiling; the five-point check accepts them with the heading right and the bearing far
    off, which looked like a reversed sign. The floor measures a range a fraction of the
    true one, and the edge built with it is refused by the pose graph's gate."""
    from robotd.base.geometry import between
    from robotd.forward.planar import loop_edge

    renderer, _, k = office
    cam = renderer.camera
    old_pose, new_pose = ALIASED[pair]
    assert _overlap_poses(renderer, old_pose, new_pose) < 0.1  # the truth: not the same place (gt: < 0.1)
    extract = FeatureExtractor()
    v = verify_pair(extract(renderer.render(old_pose)), extract(renderer.render(new_pose)),
                    VerifyParams(camera_height_m=cam.height_m), k)
    assert v.accepted  # the epipolar check alone cannot tell (module notes of verify)
    dyaw, bearing, _ = planar_motion(v.rotation, v.translation_dir)
    t_yaw, t_bearing, t_dist = _truth(renderer, old_pose, new_pose)
    assert abs(math.degrees(dyaw - t_yaw)) < 10
    assert abs(math.degrees(math.remainder(bearing - t_bearing, math.tau))) > 90
    assert v.range_m is not None and v.range_m < 0.35 * t_dist
    # The gate's test with a perfect prediction (the strictest case: no marginals added):
    # the measured range alone puts the edge far outside the 99.9 % gate (16.27).
    mount = np.array([cam.x_m, cam.y_m, cam.yaw_rad])
    truth = between(old_pose, new_pose)
    t_cam_dyaw, t_cam_bearing = t_yaw, t_bearing
    delta, info = loop_edge(truth, t_cam_dyaw, t_cam_bearing, mount, range_m=v.range_m)
    c, s_ = math.cos(delta[2]), math.sin(delta[2])
    d = truth[:2] - delta[:2]
    e = np.array([c * d[0] + s_ * d[1], -s_ * d[0] + c * d[1], math.remainder(float(truth[2] - delta[2]), math.tau)])
    assert float(e @ info @ e) > 16.27


def _overlap_poses(renderer, a: np.ndarray, b: np.ndarray) -> float:
    return float(view_overlap(view_histograms(renderer, np.array([a, b])))[0, 1])


# --- the bearing's uncertainty handed to the pose graph (short-baseline loops) ---
# The daemon's two wrong accepted loops were true revisits 0.23-0.25 m apart with the bearing
# 13-17 deg off under a fixed 2 deg sigma. New cameras around one corridor pose, at short
# (0.12-0.25 m) and long (0.6-1.0 m) baselines, in all directions, turned by a few degrees.
_RELS_SHORT = [(0.2, 0.0, 0.05), (0.0, 0.18, -0.1), (-0.15, 0.12, 0.0), (0.1, -0.1, 0.15),
               (-0.2, -0.1, -0.05), (0.17, 0.17, 0.1)]
_RELS_LONG = [(0.8, 0.0, 0.05), (0.0, 0.6, -0.1), (-0.6, 0.5, 0.0), (0.5, -0.5, 0.15),
              (-0.9, -0.3, -0.05), (0.7, 0.6, 0.1)]


def _bearing_errors(renderer, k, rels):
    """``(error, claimed edge sigma, the inliers' own sigma)`` in radians of each accepted pair."""
    from robotd.base.geometry import compose
    from robotd.forward.planar import PlanarLoopParams

    cam = renderer.camera
    extract = FeatureExtractor()
    old = extract(renderer.render(CORRIDOR))
    floor = PlanarLoopParams().sigma_bearing_rad  # what loop_edge adds in quadrature
    out = []
    for rel in rels:
        new_pose = compose(CORRIDOR, np.array(rel))
        v = verify_pair(old, extract(renderer.render(new_pose)), VerifyParams(camera_height_m=cam.height_m), k)
        if not v.accepted:
            continue
        _, bearing, _ = planar_motion(v.rotation, v.translation_dir)
        _, t_bearing, _ = _truth(renderer, CORRIDOR, new_pose)
        out.append((abs(math.remainder(bearing - t_bearing, math.tau)), math.hypot(floor, v.sigma_bearing_rad),
                    v.sigma_bearing_rad))
    return np.array(out)


def test_the_claimed_bearing_sigma_covers_the_true_error_at_short_and_long_baselines(office):
    """The sigma the edge claims (the inliers' own, :func:`robotd.forward.planar.refine_motion`,
    with the configured 2 deg in quadrature) against the truth. Short baselines: every
    pair's error within 3 sigma. Long baselines: the typical error within 1 sigma (median
    |error| / sigma); a few pairs with few inliers (28-36) are measured there with a biased
    solution 3-25 sigma off (heading off too): no Gaussian sigma describes those, the
    graph's gate and robust solver are what stands against them. The inliers' own sigma
    here is 0.1-1.2 deg at either baseline (the long ones keep fewer inliers): its growth
    as the baseline shrinks, for one scene, is in ``test_planar.py``."""
    renderer, _, k = office
    short = _bearing_errors(renderer, k, _RELS_SHORT)
    long_ = _bearing_errors(renderer, k, _RELS_LONG)
    assert len(short) >= 5 and len(long_) >= 5
    for err, claimed, _ in short:
        assert err <= 3.0 * claimed, (math.degrees(err), math.degrees(claimed))
    assert np.median(long_[:, 0] / long_[:, 1]) <= 1.0
