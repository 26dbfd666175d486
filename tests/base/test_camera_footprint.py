"""Footprint overlap J (paper 003 eq. 3) against hand-derived answers."""

import math

import numpy as np
import pytest

from robotd.base.camera import CameraIntrinsics, FloorCameraModel, footprint_world, overlap_ratio, overlap_ratios


def _pinhole() -> FloorCameraModel:
    # No distortion, no tilt: the footprint is a W/fx*h by H/fy*h rectangle (0.64 x 0.48 m),
    # image up = robot forward, so 0.48 m along x and 0.64 m along y.
    return FloorCameraModel(CameraIntrinsics(640, 480, 400.0, 400.0, 319.5, 239.5), height_m=0.40)


@pytest.mark.parametrize("d", [0.0, 0.05, 0.12, 0.3, 0.47])
def test_forward_shift_of_a_rectangle(d):
    cam = _pinhole()
    a = np.array([1.0, 2.0, 0.0])
    b = np.array([1.0 + d, 2.0, 0.0])
    expected = (0.48 - d) / (0.48 + d)  # same width: intersection (0.48-d)W over union (0.48+d)W
    j = overlap_ratio(footprint_world(cam, a), footprint_world(cam, b))
    assert j == pytest.approx(expected, abs=1e-9)
    assert overlap_ratios(cam, a[None], b[None])[0] == pytest.approx(expected, abs=1e-9)


def test_quarter_turn_about_the_centre():
    cam = _pinhole()
    a = np.zeros(3)
    b = np.array([0.0, 0.0, math.pi / 2])
    inter = 0.48 * 0.48  # the 0.64 x 0.48 rectangle and its quarter turn share a 0.48 square
    union = 2 * 0.64 * 0.48 - inter
    assert overlap_ratio(footprint_world(cam, a), footprint_world(cam, b)) == pytest.approx(inter / union, abs=1e-9)


def test_far_pairs_are_zero_and_vectorised_matches_exact():
    cam = FloorCameraModel.default()
    rng = np.random.default_rng(0)
    pa = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(-1, 1, 50), rng.uniform(-3, 3, 50)])
    pb = pa + np.column_stack([rng.normal(0, 0.3, 50), rng.normal(0, 0.3, 50), rng.normal(0, 1, 50)])
    many = overlap_ratios(cam, pa, pb, samples_per_edge=16)
    one = [overlap_ratio(footprint_world(cam, a), footprint_world(cam, b)) for a, b in zip(pa, pb)]
    assert np.allclose(many, one, atol=1e-9)
    assert overlap_ratios(cam, np.zeros((1, 3)), np.array([[5.0, 0.0, 0.0]]))[0] == 0.0
    assert 0 < np.min(many[many > 0]) and np.max(many) <= 1.0
