"""The forward camera's column raycaster against hand-computed geometry, and its labels."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from robotd.base.errors import ConfigError
from sim.cameras.forward import (
    ForwardCameraModel,
    ForwardRenderer,
    ForwardRenderParams,
    same_place_matrix,
    view_histograms,
    view_overlap,
)
from sim.world.rooms import WorldParams, corridor_world

CLEAN = ForwardRenderParams(noise_sigma=0.0, mipmap=False)


@pytest.fixture(scope="module")
def box():
    """Free space x in -1 .. 5, y in -1 .. 1 (a corridor along 0..4 m, 2 m wide, square ends)."""
    return corridor_world(np.array([[0.0, 0.0], [4.0, 0.0]]), seed=0,
                          params=WorldParams(corridor_width_m=2.0))


def _wall_index(world, predicate) -> int:
    ks = [k for k in range(world.n_walls) if predicate(world.a_m[k], world.b_m[k])]
    assert len(ks) == 1
    return ks[0]


def test_columns_hit_the_expected_walls(box):
    r = ForwardRenderer(box, ForwardCameraModel(), CLEAN)
    hits = r.cast(np.array([0.0, 0.0, 0.0]))  # camera at (0.1, 0), looking east
    east = _wall_index(box, lambda a, b: a[0] == b[0] == 5.0)
    north = _wall_index(box, lambda a, b: a[1] == b[1] == 1.0)
    south = _wall_index(box, lambda a, b: a[1] == b[1] == -1.0)
    assert hits.wall[319] == east and hits.wall[320] == east
    assert hits.depth_m[319] == pytest.approx(4.9)
    # Column 0 looks 31.3 deg left: x_n = -319.5 / 525, it meets y = 1 at depth 1 / 0.6086.
    xn = -319.5 / 525.0
    assert hits.wall[0] == north
    assert hits.depth_m[0] == pytest.approx(1.0 / -xn)
    # North wall runs east to west (free space on its left), texture column 0 at its west end.
    assert hits.tex_m[0] == pytest.approx(0.1 + 1.0 / -xn + 1.0)
    assert hits.wall[639] == south


def test_a_wall_at_known_distance_occupies_the_right_rows(box):
    r = ForwardRenderer(box, ForwardCameraModel(height_m=0.6), CLEAN)
    _, _, mask = r.maps(np.array([0.0, 0.0, 0.0]))
    col = mask[:, 319]
    # End wall at depth 4.9 m: bottom edge at v = cy + 0.6 * 525 / 4.9 = 303.79,
    # top edge at v = cy - 1.9 * 525 / 4.9 = 35.93.
    rows = np.flatnonzero(col)
    assert rows[0] == 36 and rows[-1] == 303
    assert len(rows) == 303 - 36 + 1


def test_wall_pixels_show_the_wall_texture_unmirrored(box):
    r = ForwardRenderer(box, ForwardCameraModel(height_m=0.6), CLEAN)
    img = r.render_clean(np.array([0.0, 0.0, 0.0]))
    east = _wall_index(box, lambda a, b: a[0] == b[0] == 5.0)
    tex = box.wall_texture(east).astype(np.float32)
    ppm = box.params.px_per_m
    for v, u in [(100, 319), (200, 250), (280, 400)]:
        xn = (u - 319.5) / 525.0
        y_hit = -xn * 4.9  # image left is north (+y)
        tex_col = (1.0 - y_hit) * ppm - 0.5  # texture column 0 at the wall's north end
        h = 0.6 - (v - 239.5) * 4.9 / 525.0
        tex_row = (2.5 - h) * ppm - 0.5
        expect = cv2.remap(tex, np.float32([[tex_col]]), np.float32([[tex_row]]), cv2.INTER_LINEAR)[0, 0]
        assert abs(float(img[v, u]) - float(expect)) <= 1.5, (v, u)


def test_rendering_is_deterministic(box):
    pose = np.array([1.0, 0.2, 0.3])
    a = ForwardRenderer(box, rng=np.random.default_rng(5)).render(pose)
    b = ForwardRenderer(box, rng=np.random.default_rng(5)).render(pose)
    c = ForwardRenderer(box, rng=np.random.default_rng(6)).render(pose)
    assert a.shape == (480, 640) and a.dtype == np.uint8
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.abs(a.astype(int) - c.astype(int)).mean() < 4.0  # only the noise differs


def test_floor_and_ceiling_fill_the_rest(box):
    r = ForwardRenderer(box, ForwardCameraModel(), CLEAN)
    _, _, mask = r.maps(np.array([0.0, 0.0, 0.0]))
    # Down the corridor the top and bottom rows see the ceiling and the floor; at the image
    # edges the near side walls reach the top: column 0 meets the north wall 1.643 m away,
    # whose foot is at v = 239.5 + 0.6 * 525 / 1.643 = 431.2.
    assert not mask[0, 250:390].any() and not mask[-1, 250:390].any()
    assert mask[:432, 0].all() and not mask[432:, 0].any()
    assert mask[240].all()  # the horizon row is all wall inside a closed room


def test_labels_same_pose_and_opposite_walls(box):
    r = ForwardRenderer(box, ForwardCameraModel(), CLEAN)
    poses = np.array([[1.0, 0.0, 0.0],       # east
                      [1.0, 0.0, math.pi],   # west: the opposite walls
                      [1.0, 0.0, 0.0]])      # east again, same pose
    ov = view_overlap(view_histograms(r, poses))
    assert np.allclose(ov, ov.T)
    assert ov[0, 2] == pytest.approx(1.0)
    assert ov[0, 1] < 0.05  # only the side walls near the camera could be shared
    same = same_place_matrix(ov, threshold=0.3, leave_below=0.1)
    assert np.array_equal(same, same.T)
    assert same[0, 2] and same[2, 0]
    assert not same[0, 1] and not same[1, 2] and not same.diagonal().any()


def test_same_place_needs_the_robot_to_have_left():
    # Three nearly identical views in a row are not a revisit; after leaving, they are.
    ov = np.array([[1.0, 0.9, 0.8, 0.0, 0.7],
                   [0.9, 1.0, 0.9, 0.0, 0.7],
                   [0.8, 0.9, 1.0, 0.0, 0.8],
                   [0.0, 0.0, 0.0, 1.0, 0.0],
                   [0.7, 0.7, 0.8, 0.0, 1.0]], np.float32)
    same = same_place_matrix(ov, threshold=0.5, leave_below=0.1)
    assert not same[0, 1] and not same[0, 2] and not same[1, 2]
    assert same[4, 0] and same[4, 1] and same[4, 2] and same[0, 4]
    assert not same[3].any()


def test_camera_model_rejects_distortion_and_bad_height():
    from robotd.base.camera import CameraIntrinsics

    k = CameraIntrinsics(640, 480, 525.0, 525.0, 319.5, 239.5, (0.1, 0.0, 0.0, 0.0, 0.0))
    with pytest.raises(ConfigError, match="distortion"):
        ForwardCameraModel(intrinsics=k)
    with pytest.raises(ConfigError, match="height_m"):
        ForwardCameraModel(height_m=0.0)
