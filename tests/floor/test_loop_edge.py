"""The loop edge's covariance (:func:`robotd.floor.detector.loop_transform`): the fit's
covariance from independent inlier errors plus the error all the inliers of a frame pair
share, which more inliers do not average away: an offset the two views share in the
camera's frame, which the turn between them makes a translation error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.base.camera import FloorCameraModel
from robotd.base.geometry import between, transform_points, wrap_angle
from robotd.floor.detector import MIN_POINT_SIGMA_M, TURN_SIGMA_M, loop_transform


def _true(turn: float) -> np.ndarray:
    """The query keyframe in the old one's frame."""
    return np.array([0.06, -0.03, turn])


def _pixels(cam: FloorCameraModel, n: int, rng: np.random.Generator, point_sigma_m: float,
            offset_m: np.ndarray, turn: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` floor points both frames see, as pixels of the query and the old frame: each
    point's position in the query frame off by ``point_sigma_m`` (independent), and every
    point in both frames off by ``offset_m (2,)`` in the robot's (the camera's) frame."""
    centre = cam.pixel_to_floor_robot(np.array([[cam.width_px / 2, cam.height_px / 2]]))[0]
    old = centre + rng.uniform(-0.02, 0.02, (n, 2))
    query = transform_points(between(_true(turn), np.zeros(3)), old)  # the same floor points, query frame
    query = query + rng.normal(0.0, point_sigma_m, (n, 2)) + offset_m
    return cam.floor_robot_to_pixel(query), cam.floor_robot_to_pixel(old + offset_m)


def _error(turn: float, delta: np.ndarray) -> np.ndarray:
    e = between(_true(turn), delta)
    e[2] = wrap_angle(e[2])
    return e


def _nees(cam: FloorCameraModel, n: int, offset_sigma_m: float, model_sigma_m: float, trials: int) -> float:
    rng = np.random.default_rng(3)
    out = []
    for _ in range(trials):
        turn = float(rng.uniform(-math.pi, math.pi))
        xy_q, xy_o = _pixels(cam, n, rng, 0.001, rng.normal(0.0, offset_sigma_m, 2), turn)
        fit = loop_transform(cam, xy_q, xy_o, turn_sigma_m=model_sigma_m)
        assert fit is not None
        delta, info = fit
        e = _error(turn, delta)
        out.append(float(e @ info @ e))
    return float(np.mean(out))


def test_an_offset_both_views_share_cancels_when_they_look_the_same_way_and_doubles_when_opposite():
    """Noise-free points with a 1 mm offset in the camera's frame: no error at no turn, twice
    the offset (turned) half a turn apart: the geometry the shared term models."""
    cam = FloorCameraModel.default()
    offset = np.array([0.001, 0.0])
    same, _ = loop_transform(cam, *_pixels(cam, 50, np.random.default_rng(0), 0.0, offset, 0.0))
    assert _error(0.0, same) == pytest.approx(np.zeros(3), abs=2e-6)
    opposite, _ = loop_transform(cam, *_pixels(cam, 50, np.random.default_rng(0), 0.0, offset, math.pi))
    assert np.hypot(*_error(math.pi, opposite)[:2]) == pytest.approx(0.002, rel=0.01)


def test_the_shared_term_grows_with_the_turn_and_bounds_the_translation_covariance():
    """The fit's covariance shrinks as one over the inliers (tenfold from 100 to 1000); the
    edge's keeps ``4 sin^2(turn / 2)`` times the offset's variance on each translation axis
    (none when the views look the same way), the yaw's is the fit's."""
    cam = FloorCameraModel.default()
    for turn in (0.0, 1.0, math.pi):
        cov, alone = {}, {}
        for n in (100, 1000):
            xy_q, xy_o = _pixels(cam, n, np.random.default_rng(1), 0.001, np.zeros(2), turn)
            delta, info = loop_transform(cam, xy_q, xy_o)
            assert delta[:2] == pytest.approx(_true(turn)[:2], abs=1e-3)
            assert wrap_angle(delta[2] - turn) == pytest.approx(0.0, abs=2e-2)
            cov[n] = np.linalg.inv(info)
            alone[n] = np.linalg.inv(loop_transform(cam, xy_q, xy_o, turn_sigma_m=0.0)[1])
            shared = 4.0 * math.sin(0.5 * delta[2]) ** 2 * TURN_SIGMA_M ** 2
            assert np.diag(cov[n] - alone[n]) == pytest.approx([shared] * 2 + [0.0], rel=1e-6, abs=1e-15)
        assert np.diag(alone[100] / alone[1000]) == pytest.approx([10.0] * 3, rel=0.3)
    assert np.diag(cov[1000])[:2].min() > 4.0 * TURN_SIGMA_M ** 2  # half a turn: the offset twice


def test_loop_edges_with_a_shared_offset_are_consistent():
    """Frame pairs at any turn whose views share an offset of TURN_SIGMA_M per axis: with it in
    the model the edges' mean NEES is near 3 with 30 inliers and with 600; without it the
    NEES grows with the inliers (the fit's covariance shrinks as one over their number)."""
    cam = FloorCameraModel.default()
    few = _nees(cam, 30, TURN_SIGMA_M, TURN_SIGMA_M, 200)
    many = _nees(cam, 600, TURN_SIGMA_M, TURN_SIGMA_M, 200)
    many_alone = _nees(cam, 600, TURN_SIGMA_M, 0.0, 200)
    assert 2.4 < few < 3.6
    assert 2.4 < many < 3.6
    assert many_alone > 5.0


@pytest.mark.slow
def test_loop_edges_on_rendered_plank_pairs_are_consistent():
    """Rendered pairs of the printed plank floor (the second frame within 0.25 m of the
    first), declared loops in mode 6 (the most inliers, a few hundred) at the demo
    calibration's threshold: the loop edges' mean NEES is near 3 (within 1.5-4.5 over a few
    dozen edges), below that of the rigid fit's covariance alone (6.0 in the benchmark)."""
    import skimage.data

    from robotd.app.demo import shipped_calibration
    from robotd.base.geometry import rigid_fit_2d, rigid_fit_2d_covariance, between_error_covariance
    from robotd.floor.descriptor import decode, extract
    from robotd.floor.match import local_score
    from robotd.floor.vo import floor_point_pairs
    from robotd.io.calibfile import read_calibration
    from sim.pairs import random_pairs
    from sim.world.pattern import PatternFloor, PatternParams

    path = shipped_calibration()
    if path is None:
        pytest.skip("the demo's shipped calibration is absent")
    threshold = read_calibration(path).loop.for_mode(6)
    cam = FloorCameraModel.default()
    floor = PatternFloor(skimage.data.gravel(), PatternParams(kind="planks"), seed=0)
    pairs = random_pairs(floor, cam, 60, np.random.default_rng(0), near_fraction=1.0, max_offset_m=0.25)
    model, alone = [], []
    for k, (ia, ib) in enumerate(zip(pairs.images_a, pairs.images_b)):
        if pairs.overlap[k] < 0.33:
            continue
        m = local_score(decode(extract(ia, 6)), decode(extract(ib, 6)))
        if m.score < threshold:
            continue
        delta, info = loop_transform(cam, m.xy_a, m.xy_b)
        e = between(between(pairs.poses_b[k], pairs.poses_a[k]), delta)
        e[2] = wrap_angle(e[2])
        assert np.hypot(e[0], e[1]) < 0.05  # a true transform
        po, pq = floor_point_pairs(cam, m.xy_b, m.xy_a)
        cov = between_error_covariance(delta, rigid_fit_2d_covariance(pq, po, rigid_fit_2d(pq, po), MIN_POINT_SIGMA_M)[0])
        model.append(float(e @ info @ e))
        alone.append(float(e @ np.linalg.solve(cov, e)))
    assert len(model) >= 15
    assert 1.5 < np.mean(model) < 4.5
    assert np.mean(alone) > np.mean(model)
