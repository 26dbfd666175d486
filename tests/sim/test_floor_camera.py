"""Floor camera rendering: geometry against the camera model, blur, gain, noise."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import skimage.data

from robotd.base.errors import ConfigError
from robotd.base.camera import FloorCameraModel
from robotd.base.geometry import inverse, transform_points
from sim.world.floor import Floor, ImageFloor
from sim.cameras.floor import FloorRenderer, RenderParams

CLEAN = RenderParams(noise_sigma=0.0, shot_noise=False, drift_amplitude=0.0, motion_blur=False)


def _dot_floor(dot_xy_m: tuple[float, float], mpp: float = 0.001) -> ImageFloor:
    """A black 2 x 2 m floor centred on the origin with one bright Gaussian dot."""
    n = 2001
    origin = (-1.0, 1.0)
    col = (dot_xy_m[0] - origin[0]) / mpp
    row = (origin[1] - dot_xy_m[1]) / mpp
    c, r = np.meshgrid(np.arange(n), np.arange(n))
    img = 250.0 * np.exp(-((c - col) ** 2 + (r - row) ** 2) / (2.0 * 3.0**2))
    return ImageFloor(np.rint(img).astype(np.uint8), metres_per_px=mpp, origin_xy_m=origin)


def _centroid(img: np.ndarray) -> np.ndarray:
    w = np.where(img > 20, img.astype(np.float64), 0.0)
    rows, cols = np.indices(img.shape)
    return np.array([(w * cols).sum() / w.sum(), (w * rows).sum() / w.sum()])


@pytest.mark.parametrize(
    "camera",
    [
        FloorCameraModel.default(),
        dataclasses.replace(FloorCameraModel.default(), tilt_rad=0.25, yaw_rad=0.4, offset_x_m=0.08,
                            offset_y_m=-0.02,
                            intrinsics=dataclasses.replace(FloorCameraModel.default().intrinsics,
                                                           distortion=(-0.12, 0.02, 0.001, -0.001, 0.0))),
    ],
    ids=["default", "tilted-yawed-distorted"],
)
def test_marked_dot_appears_where_the_camera_model_projects_it(camera: FloorCameraModel) -> None:
    dot = (0.23, -0.11)
    floor = _dot_floor(dot)
    renderer = FloorRenderer(floor, camera, CLEAN, np.random.default_rng(0))
    checked = 0
    for pose in (np.array([0.0, 0.0, 0.0]), np.array([0.1, -0.2, 0.9]), np.array([0.35, 0.05, -2.4]),
                 np.array([0.05, 0.0, 0.2]), np.array([0.3, -0.3, 2.0])):
        dot_robot = transform_points(inverse(pose), np.array([dot]))
        expected = camera.floor_robot_to_pixel(dot_robot)[0]
        assert np.all(np.isfinite(expected))
        if not (20 < expected[0] < camera.width_px - 20 and 20 < expected[1] < camera.height_px - 20):
            continue
        img = renderer.render(pose, 0.0, 0.0, 0.0)
        assert img.shape == (camera.height_px, camera.width_px) and img.dtype == np.uint8
        # Sub-pixel agreement; a sign or axis error would be off by tens of pixels.
        assert np.linalg.norm(_centroid(img) - expected) < 0.1, pose
        checked += 1
    assert checked >= 3


def test_render_equals_a_direct_lookup_of_the_floor() -> None:
    rng = np.random.default_rng(3)
    texture = rng.integers(0, 256, (1500, 1500), dtype=np.uint8)
    floor = ImageFloor(texture, metres_per_px=0.001, origin_xy_m=(-0.75, 0.75))
    cam = dataclasses.replace(FloorCameraModel.default(), tilt_rad=0.1, yaw_rad=-0.3)
    pose = np.array([0.02, -0.03, 0.7])
    img = FloorRenderer(floor, cam, CLEAN, np.random.default_rng(0)).render_clean(pose)
    # Pixels whose floor point falls exactly on a texture pixel centre do not depend on
    # the interpolation: pick pixels, compute the floor point independently, compare.
    uv = rng.uniform([0, 0], [639, 479], (400, 2)).round()
    world = transform_points(pose, cam.pixel_to_floor_robot(uv))
    col = (world[:, 0] + 0.75) / 0.001
    row = (0.75 - world[:, 1]) / 0.001
    c0, r0 = np.floor(col).astype(int), np.floor(row).astype(int)
    fc, fr = col - c0, row - r0
    t = texture.astype(np.float64)
    bilinear = (t[r0, c0] * (1 - fc) * (1 - fr) + t[r0, c0 + 1] * fc * (1 - fr)
                + t[r0 + 1, c0] * (1 - fc) * fr + t[r0 + 1, c0 + 1] * fc * fr)
    got = img[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    # cv2.remap interpolates with 5-bit fractional weights: up to 1/32 px of position error.
    assert np.median(np.abs(got - bilinear)) < 3.0
    assert np.mean(np.abs(got - bilinear)) < 5.0
    shuffled = np.roll(bilinear, 1)
    assert np.mean(np.abs(got - shuffled)) > 40.0  # the comparison can fail


def _directional_energy(img: np.ndarray) -> tuple[float, float]:
    f = img.astype(np.float64)
    return float(np.mean(np.diff(f, axis=0) ** 2)), float(np.mean(np.diff(f, axis=1) ** 2))


def _spectral_energy(img: np.ndarray) -> tuple[float, float]:
    """Power at high vertical-only and high horizontal-only spatial frequencies.

    Vertical: |f_v| > 0.15 cycles/px with |f_u| < 0.01; horizontal: the transpose. A blur
    along v removes the first and leaves the second (its gain at f_v = 0 is 1).
    """
    f = img.astype(np.float64)
    f = (f - f.mean()) * np.outer(np.hanning(f.shape[0]), np.hanning(f.shape[1]))
    power = np.abs(np.fft.fft2(f)) ** 2
    fv = np.abs(np.fft.fftfreq(f.shape[0]))[:, None]
    fu = np.abs(np.fft.fftfreq(f.shape[1]))[None, :]
    vertical = power[(fv > 0.15) & (fu < 0.01)].sum()
    horizontal = power[(fu > 0.15) & (fv < 0.01)].sum()
    return float(vertical), float(horizontal)


@pytest.fixture(scope="module")
def gravel() -> Floor:
    return Floor.from_photos([skimage.data.gravel()], seed=7)


def test_forward_motion_blurs_along_the_image_vertical_only(gravel: Floor) -> None:
    cam = FloorCameraModel.default()
    pose = np.array([0.3, 0.2, 0.0])
    still = FloorRenderer(gravel, cam, dataclasses.replace(CLEAN, exposure_s=0.01, reference_exposure_s=0.01),
                          np.random.default_rng(0))
    moving = FloorRenderer(gravel, cam, dataclasses.replace(CLEAN, exposure_s=0.01, reference_exposure_s=0.01,
                                                            motion_blur=True), np.random.default_rng(0))
    assert moving.blur_samples(1.0, 0.0) >= 9  # 1 m/s * 10 ms = 10 mm = 10 px of blur
    a = still.render_clean(pose, 1.0, 0.0)
    b = moving.render_clean(pose, 1.0, 0.0)
    vert_a, horiz_a = _spectral_energy(a)
    vert_b, horiz_b = _spectral_energy(b)
    # Robot forward is image up: high frequencies along v are wiped out, along u kept.
    assert vert_b < 0.1 * vert_a
    assert horiz_b == pytest.approx(horiz_a, rel=0.1)
    # Blur is an average over the exposure: the mean brightness does not change.
    assert float(b.mean()) == pytest.approx(float(a.mean()), rel=0.01)


def test_turning_blurs_the_image_edges_more_than_the_centre(gravel: Floor) -> None:
    cam = FloorCameraModel.default()  # lens above the robot centre: the centre barely moves
    params = dataclasses.replace(CLEAN, exposure_s=0.01, reference_exposure_s=0.01, motion_blur=True)
    r = FloorRenderer(gravel, cam, params, np.random.default_rng(0))
    pose = np.array([-0.4, 0.3, 1.0])
    a = r.render_clean(pose, 0.0, 0.0)
    b = r.render_clean(pose, 0.0, 2.0)  # 0.02 rad in the exposure: ~8 px at the corners

    def hf(img: np.ndarray) -> float:
        v, h = _directional_energy(img)
        return v + h

    centre = (slice(200, 280), slice(280, 360))
    corner = (slice(0, 80), slice(0, 80))
    assert hf(b[centre]) > 0.85 * hf(a[centre])
    assert hf(b[corner]) < 0.5 * hf(a[corner])


def test_exposure_scales_brightness_by_the_exposure_ratio(gravel: Floor) -> None:
    cam = FloorCameraModel.default()
    pose = np.array([1.0, -2.0, 0.3])
    base = FloorRenderer(gravel, cam, CLEAN, np.random.default_rng(0)).render(pose, 0.0, 0.0, 0.0)
    longer = dataclasses.replace(CLEAN, exposure_s=0.005)  # 1.25 x the reference exposure
    bright = FloorRenderer(gravel, cam, longer, np.random.default_rng(0)).render(pose, 0.0, 0.0, 0.0)
    keep = bright < 250  # leave out saturated pixels
    ratio = bright[keep].astype(np.float64).mean() / base[keep].astype(np.float64).mean()
    assert ratio == pytest.approx(1.25, abs=0.01)


def test_gain_drift_follows_the_documented_sinusoid(gravel: Floor) -> None:
    params = dataclasses.replace(CLEAN, drift_amplitude=0.15, drift_period_s=40.0)
    r = FloorRenderer(gravel, FloorCameraModel.default(), params, np.random.default_rng(0))
    pose = np.array([0.5, 0.5, 0.0])
    assert r.gain_at(10.0) == pytest.approx(1.15)
    assert r.gain_at(30.0) == pytest.approx(0.85)
    mean_0 = r.render(pose, 0.0, 0.0, 0.0).astype(np.float64).mean()
    mean_30 = r.render(pose, 0.0, 0.0, 30.0).astype(np.float64).mean()
    assert mean_30 / mean_0 == pytest.approx(0.85, abs=0.01)


def test_sensor_noise_has_the_modelled_variance_and_is_seeded(gravel: Floor) -> None:
    params = RenderParams(noise_sigma=2.0, shot_noise=True, electrons_per_level=40.0, drift_amplitude=0.0,
                          motion_blur=False)
    cam = FloorCameraModel.default()
    pose = np.array([0.2, 0.1, 0.5])
    r = FloorRenderer(gravel, cam, params, np.random.default_rng(42))
    clean = r.render_clean(pose)
    noisy = r.render(pose, 0.0, 0.0, 0.0).astype(np.float64)
    ok = (clean > 10) & (clean < 240)
    resid = noisy[ok] - clean[ok]
    expected_var = 2.0**2 + clean[ok].mean() / 40.0 + 1.0 / 12.0  # read + shot + rounding
    assert resid.var() == pytest.approx(expected_var, rel=0.05)
    assert abs(resid.mean()) < 0.05
    again = FloorRenderer(gravel, cam, params, np.random.default_rng(42)).render(pose, 0.0, 0.0, 0.0)
    assert np.array_equal(again, noisy.astype(np.uint8))
    other = FloorRenderer(gravel, cam, params, np.random.default_rng(43)).render(pose, 0.0, 0.0, 0.0)
    assert not np.array_equal(other, again)


def test_vignetting_darkens_the_corners_by_the_set_fraction() -> None:
    flat = ImageFloor(np.full((10, 10), 100, dtype=np.uint8), fill=100)
    params = dataclasses.replace(CLEAN, vignetting=0.3)
    img = FloorRenderer(flat, FloorCameraModel.default(), params, np.random.default_rng(0)).render(
        np.zeros(3), 0.0, 0.0, 0.0)
    assert img[240, 320] == 100
    assert img[0, 0] == 70 and img[479, 639] == 70


def test_patches_are_reused_while_the_view_stays_inside(gravel: Floor) -> None:
    r = FloorRenderer(gravel, FloorCameraModel.default(), CLEAN, np.random.default_rng(0), patch_margin_m=0.3)
    for k in range(30):  # 0.29 m of travel: inside the margin
        r.render(np.array([0.01 * k, 0.0, 0.0]), 0.3, 0.0, k / 30.0)
    assert r.patches_fetched == 1
    r.render(np.array([1.0, 0.0, 0.0]), 0.3, 0.0, 1.0)
    assert r.patches_fetched == 2


def test_pixels_above_the_horizon_are_black() -> None:
    cam = dataclasses.replace(FloorCameraModel.default(), tilt_rad=1.2)
    flat = ImageFloor(np.full((10, 10), 100, dtype=np.uint8), fill=100)
    img = FloorRenderer(flat, cam, CLEAN, np.random.default_rng(0)).render(np.zeros(3), 0.0, 0.0, 0.0)
    assert img[0, 320] == 0 and img[479, 320] == 100


def test_bad_render_params_name_the_field() -> None:
    with pytest.raises(ConfigError, match="drift_amplitude"):
        RenderParams(drift_amplitude=1.5)
    with pytest.raises(ConfigError, match="exposure_s"):
        RenderParams(exposure_s=math.nan)
