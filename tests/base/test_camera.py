"""The downward floor camera's pinhole model: projections, footprint, orientation."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from robotd.base.camera import CameraIntrinsics, FloorCameraModel, polygon_area_signed


def _plain(fx_px: float = 400.0, fy_px: float = 400.0, distortion: tuple = (0.0,) * 5,
           **mount: float) -> FloorCameraModel:
    """640x480, fx = fy = 400, no distortion, 0.4 m high, straight down."""
    intr = CameraIntrinsics(640, 480, fx_px=fx_px, fy_px=fy_px, cx_px=319.5, cy_px=239.5, distortion=distortion)
    return FloorCameraModel(intr, **mount)


def _pixels_inside(model: FloorCameraModel, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.5, -0.5], [model.width_px - 0.5, model.height_px - 0.5], size=(n, 2))


def test_round_trip_with_distortion_default_model() -> None:
    cam = FloorCameraModel.default()
    uv = _pixels_inside(cam, 2000, seed=1)
    back = cam.floor_robot_to_pixel(cam.pixel_to_floor_robot(uv))
    assert np.max(np.abs(back - uv)) < 1e-6


@settings(derandomize=True, database=None, max_examples=40, deadline=None)
@given(
    k1=st.floats(-0.3, 0.1),
    k2=st.floats(-0.05, 0.05),
    p1=st.floats(-0.003, 0.003),
    p2=st.floats(-0.003, 0.003),
    tilt=st.floats(-0.5, 0.5),
    yaw=st.floats(-math.pi, math.pi),
    height=st.floats(0.1, 1.0),
    fx=st.floats(300.0, 800.0),
)
def test_round_trip_any_mount(k1: float, k2: float, p1: float, p2: float, tilt: float, yaw: float,
                              height: float, fx: float) -> None:
    # Only lenses whose radial map is one-to-one over the whole image are real lenses.
    r = np.linspace(0.0, 3.0, 3001)
    rd = r * (1.0 + k1 * r**2 + k2 * r**4)
    fold = np.nonzero(np.diff(rd) <= 0)[0]
    corner = math.hypot(320.0 / fx, 240.0 / (1.02 * fx))
    assume(fold.size == 0 or rd[fold[0]] > 1.05 * corner)
    cam = _plain(fx_px=fx, fy_px=fx * 1.02, distortion=(k1, k2, p1, p2, 0.0), tilt_rad=tilt, yaw_rad=yaw,
                 height_m=height, offset_x_m=0.07, offset_y_m=-0.03)
    uv = _pixels_inside(cam, 300, seed=2)
    xy = cam.pixel_to_floor_robot(uv)
    assert np.all(np.isfinite(xy))
    assert np.max(np.abs(cam.floor_robot_to_pixel(xy) - uv)) < 1e-6


def test_footprint_area_untilted_undistorted_is_the_hand_computed_rectangle() -> None:
    h = 0.5
    cam = _plain(height_m=h, fx_px=400.0, fy_px=500.0, offset_x_m=0.1, offset_y_m=0.02)
    poly = cam.footprint_robot(samples_per_edge=4)
    # (W / fx * h) x (H / fy * h): 0.8 m across the robot, 0.48 m along it.
    assert polygon_area_signed(poly) == pytest.approx((640 / 400 * h) * (480 / 500 * h), rel=1e-9)
    # Image height runs along the robot's x axis, image width along y, centred on the lens.
    assert poly[:, 0].min() == pytest.approx(0.1 - 0.24, abs=1e-9)
    assert poly[:, 0].max() == pytest.approx(0.1 + 0.24, abs=1e-9)
    assert poly[:, 1].min() == pytest.approx(0.02 - 0.40, abs=1e-9)
    assert poly[:, 1].max() == pytest.approx(0.02 + 0.40, abs=1e-9)


def test_footprint_is_counter_clockwise_for_any_yaw() -> None:
    for yaw in (0.0, 1.0, -2.5, math.pi):
        poly = _plain(yaw_rad=yaw, distortion=(-0.05, 0, 0, 0, 0)).footprint_robot()
        assert polygon_area_signed(poly) > 0.3  # positive = counter-clockwise, ~0.33 m^2


def test_barrel_distortion_widens_the_footprint() -> None:
    plain = polygon_area_signed(_plain().footprint_robot(32))
    barrel = polygon_area_signed(_plain(distortion=(-0.05, 0, 0, 0, 0)).footprint_robot(32))
    assert barrel > plain * 1.03


def test_image_orientation_up_is_forward_right_is_robot_right() -> None:
    cam = _plain()
    top, bottom, right = cam.pixel_to_floor_robot([[319.5, 0.0], [319.5, 479.0], [639.0, 239.5]])
    assert top[0] > 0.2 and abs(top[1]) < 1e-12  # image up = robot forward (+x)
    assert bottom[0] < -0.2
    assert right[1] < -0.3 and abs(right[0]) < 1e-12  # image right = robot right (-y)


def test_yaw_turns_image_up_counter_clockwise() -> None:
    cam = _plain(yaw_rad=math.pi / 2)
    top = cam.pixel_to_floor_robot([[319.5, 0.0]])[0]
    assert top[1] > 0.2 and abs(top[0]) < 1e-12  # image up now points left (+y)


def test_tilt_moves_the_footprint_forward() -> None:
    flat = _plain().footprint_robot()
    tilted = _plain(tilt_rad=0.3).footprint_robot()
    assert tilted[:, 0].mean() > flat[:, 0].mean() + 0.1
    # Forward edge recedes more than the rear edge: a trapezoid wider at the far end.
    far = tilted[tilted[:, 0] > np.median(tilted[:, 0])]
    near = tilted[tilted[:, 0] <= np.median(tilted[:, 0])]
    assert np.ptp(far[:, 1]) > np.ptp(near[:, 1])


def test_metres_per_px_at_centre() -> None:
    assert FloorCameraModel.default().metres_per_px_at_centre() == pytest.approx(0.40 / 400.0, rel=1e-6)
    assert _plain(height_m=0.8, fx_px=500.0, fy_px=500.0).metres_per_px_at_centre() == pytest.approx(0.8 / 500.0, rel=1e-9)
    # Tilt: the principal ray is longer (h / cos t) and meets the floor obliquely.
    t = 0.4
    tilted = _plain(tilt_rad=t).metres_per_px_at_centre()
    along = 0.4 / 400.0 / math.cos(t) ** 2
    across = 0.4 / 400.0 / math.cos(t)
    assert tilted == pytest.approx(0.5 * (along + across), rel=1e-4)


def test_default_sees_about_064_by_048_m_at_1mm_per_px() -> None:
    cam = FloorCameraModel.default()
    poly = cam.footprint_robot(32)
    assert np.ptp(poly[:, 1]) == pytest.approx(0.64, rel=0.08)
    assert np.ptp(poly[:, 0]) == pytest.approx(0.48, rel=0.08)
    assert (cam.width_px, cam.height_px) == (640, 480)


def test_points_behind_or_beyond_the_lens_fold_are_nan() -> None:
    steep = _plain(tilt_rad=1.2)
    uv = steep.floor_robot_to_pixel([[-5.0, 0.0], [0.5, 0.0]])
    assert np.all(np.isnan(uv[0]))  # behind the image plane
    assert np.all(np.isfinite(uv[1]))
    barrel = _plain(distortion=(-0.05, 0, 0, 0, 0))  # radial map folds back at r = 2.58
    uv = barrel.floor_robot_to_pixel([[0.0, 0.4 * 3.0], [0.0, 0.4 * 2.0]])
    assert np.all(np.isnan(uv[0]))
    assert np.all(np.isfinite(uv[1]))


def test_pixels_above_the_horizon_are_nan() -> None:
    cam = _plain(tilt_rad=1.2)  # 69 deg tilt, 31 deg half field of view: top rows see sky
    xy = cam.pixel_to_floor_robot([[319.5, 0.0], [319.5, 479.0]])
    assert np.all(np.isnan(xy[0]))
    assert np.all(np.isfinite(xy[1]))
    with pytest.raises(ValueError, match="horizon"):
        cam.footprint_robot()


def test_precomputed_grids_are_cached_and_agree_with_point_calls() -> None:
    cam = dataclasses.replace(FloorCameraModel.default(), tilt_rad=0.2, yaw_rad=0.3)
    grid = cam.pixel_floor_grid_robot()
    assert grid is cam.pixel_floor_grid_robot()
    assert cam.undistorted_rays() is cam.undistorted_rays()
    assert grid.shape == (480, 640, 2) and not grid.flags.writeable
    rows = np.array([0, 100, 479])
    cols = np.array([0, 320, 639])
    uv = np.column_stack([cols, rows]).astype(float)
    assert np.allclose(grid[rows, cols], cam.pixel_to_floor_robot(uv), atol=1e-12)
    rays = cam.undistorted_rays()[rows, cols]
    # Each ray from the lens reaches its floor point.
    s = -cam.height_m / rays[:, 2]
    hit = cam.position_robot_m[:2] + rays[:, :2] * s[:, None]
    assert np.allclose(hit, grid[rows, cols], atol=1e-12)


def test_from_config_converts_degrees() -> None:
    cfg = SimpleNamespace(width_px=320, height_px=240, fx_px=300.0, fy_px=310.0, cx_px=160.0, cy_px=120.0,
                          distortion=(-0.1, 0.01, 0.0, 0.0, 0.0), mount_height_m=0.3, mount_tilt_deg=10.0,
                          mount_x_m=0.05, mount_y_m=-0.01, mount_yaw_deg=90.0)
    cam = FloorCameraModel.from_config(cfg)
    assert cam.tilt_rad == pytest.approx(math.radians(10.0))
    assert cam.yaw_rad == pytest.approx(math.pi / 2)
    assert cam.intrinsics.distortion == (-0.1, 0.01, 0.0, 0.0, 0.0)
    assert (cam.width_px, cam.intrinsics.fy_px, cam.offset_y_m) == (320, 310.0, -0.01)


def test_invalid_models_are_rejected() -> None:
    with pytest.raises(ValueError, match="dist"):
        _plain(distortion=(0.1, 0.0))
    with pytest.raises(ValueError, match="height_m"):
        _plain(height_m=0.0)


# ----------------------------------------------------------------------- intrinsics


def test_intrinsics_camera_matrix_and_distortion_by_hand() -> None:
    k = CameraIntrinsics(640, 480, fx_px=401.25, fy_px=399.5, cx_px=321.1, cy_px=238.7,
                         distortion=[-0.05, 0.01, 0.001, -0.002, 0.003])
    np.testing.assert_array_equal(k.camera_matrix(), [[401.25, 0, 321.1], [0, 399.5, 238.7], [0, 0, 1]])
    assert k.distortion == (-0.05, 0.01, 0.001, -0.002, 0.003)  # a list becomes a tuple: hashable
    assert k.distortion_array().shape == (5,) and k.distortion_array()[3] == -0.002
    assert hash(k) == hash(CameraIntrinsics(640, 480, 401.25, 399.5, 321.1, 238.7,
                                            (-0.05, 0.01, 0.001, -0.002, 0.003)))


def test_intrinsics_from_opencv_layouts() -> None:
    k = np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]])
    four = CameraIntrinsics.from_camera_matrix(k, [0.1, 0.01, 0.001, 0.002], 640, 480)
    assert (four.fx_px, four.fy_px, four.cx_px, four.cy_px) == (500.0, 510.0, 320.0, 240.0)
    assert four.distortion == (0.1, 0.01, 0.001, 0.002, 0.0)
    np.testing.assert_array_equal(four.camera_matrix(), k)
    eight = CameraIntrinsics.from_camera_matrix(k, np.array([[0.1, 0.01, 0.001, 0.002, 0.3, 0, 0, 0]]), 640, 480)
    assert eight.distortion == (0.1, 0.01, 0.001, 0.002, 0.3)
    with pytest.raises(ValueError, match="k4"):
        CameraIntrinsics.from_camera_matrix(k, [0.1, 0.01, 0.001, 0.002, 0.3, 0.5, 0, 0], 640, 480)
    with pytest.raises(ValueError, match="3x3"):
        CameraIntrinsics.from_camera_matrix(np.eye(2), [0.0] * 5, 640, 480)
    with pytest.raises(ValueError, match="no skew"):
        CameraIntrinsics.from_camera_matrix(k + [[0, 2.0, 0], [0, 0, 0], [0, 0, 0]], [0.0] * 5, 640, 480)


def test_intrinsics_from_the_config_section() -> None:
    from robotd.base.config import FloorCameraConfig

    cfg = FloorCameraConfig()
    k = CameraIntrinsics.from_config(cfg)
    assert k == CameraIntrinsics(cfg.width_px, cfg.height_px, cfg.fx_px, cfg.fy_px, cfg.cx_px, cfg.cy_px,
                                 tuple(cfg.distortion))
    # The shipped default config describes the virtual robot's camera.
    assert k == FloorCameraModel.default().intrinsics
    assert FloorCameraModel.from_config(cfg).intrinsics == k


def test_invalid_intrinsics_are_rejected() -> None:
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        CameraIntrinsics(640, 480, -400.0, 400.0, 320.0, 240.0)
    with pytest.raises(ValueError, match="image size"):
        CameraIntrinsics(640.5, 480, 400.0, 400.0, 320.0, 240.0)
    with pytest.raises(ValueError, match="finite"):
        CameraIntrinsics(640, 480, 400.0, 400.0, math.nan, 240.0)
    with pytest.raises(TypeError, match="CameraIntrinsics"):
        FloorCameraModel(intrinsics=(640, 480, 400.0, 400.0, 320.0, 240.0))  # type: ignore[arg-type]


def _undistort_written_out(model: FloorCameraModel, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Newton inversion of the distortion with :meth:`FloorCameraModel._distort` and its
    Jacobian written out term by term (the model's own computes their common terms once)."""
    k1, k2, p1, p2, k3 = model.intrinsics.distortion
    x, y = xd.copy(), yd.copy()
    for _ in range(50):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        fx_, fy_ = model._distort(x, y)
        ex, ey = fx_ - xd, fy_ - yd
        j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        j21 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        det = j11 * j22 - j12 * j21
        dx = (j22 * ex - j12 * ey) / det
        dy = (-j21 * ex + j11 * ey) / det
        x -= dx
        y -= dy
        if np.nanmax(np.abs(dx), initial=0.0) < 1e-15 and np.nanmax(np.abs(dy), initial=0.0) < 1e-15:
            break
    return x, y


@pytest.mark.parametrize("distortion", [(-0.28, 0.07, 0.001, -0.0015, 0.0), (0.05, -0.01, -0.002, 0.002, 0.004),
                                        (-0.1, 0.0, 0.0, 0.0, 0.0)])
def test_undistort_is_the_written_out_newton_to_the_bit(distortion: tuple) -> None:
    """The same x, y to the bit as the written-out iteration, for any set of pixels (its
    stop is over the whole set), the default model's lens included, a NaN and an empty set."""
    for cam in (FloorCameraModel.default(), _plain(distortion=distortion)):
        k = cam.intrinsics
        for n, seed in ((1, 0), (117, 1), (2000, 2), (0, 3)):
            uv = _pixels_inside(cam, n, seed)
            xd, yd = (uv[:, 0] - k.cx_px) / k.fx_px, (uv[:, 1] - k.cy_px) / k.fy_px
            if n > 1:
                xd[0] = np.nan
            got, want = cam._undistort(xd, yd), _undistort_written_out(cam, xd, yd)
            for a, b in zip(got, want):
                assert a.tobytes() == b.tobytes()
