"""Intrinsic calibration: OpenCV's published result on real photos, a rendered camera, rejects, CLI."""

from __future__ import annotations

import argparse
import io
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from robotd.io.calibfile import CalibrationFile, FloorMount, read_calibration, write_calibration
from calibration.intrinsics import (
    ProgressBar,
    RejectReason,
    add_intrinsics_arguments,
    board_object_points,
    calibrate_intrinsics,
    parse_board,
    run_intrinsics,
)
from robotd.base.errors import CalibrationError
from robotd.base.camera import CameraIntrinsics, FloorCameraModel
from tests.calibration import SHARED_DATA, centred_board_pose, render_board
from tests.shared_data import require

PHOTOS = SHARED_DATA / "calibration" / "opencv_left"


@pytest.fixture
def opencv_photos() -> Path:
    """The OpenCV sample photos (skipped where ../shared/data is absent, failed in CI)."""
    return require(PHOTOS / "left_intrinsics.yml", "OpenCV sample photos").parent


needs_photos = pytest.mark.usefixtures("opencv_photos")

# OpenCV's result for these photos (left_intrinsics.yml; DATA README).
PUBLISHED = {"fx": 535.9157, "fy": 535.9157, "cx": 342.2832, "cy": 235.5708, "error": 0.3926}


def _photos() -> list[Path]:
    return sorted(PHOTOS.glob("left*.jpg"))


@pytest.fixture(scope="module")
def published() -> dict:
    path = require(PHOTOS / "left_intrinsics.yml", "OpenCV sample photos")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    out = {"K": fs.getNode("camera_matrix").mat(), "dist": fs.getNode("distortion_coefficients").mat().ravel(),
           "error": fs.getNode("avg_reprojection_error").real(), "flags": int(fs.getNode("flags").real()),
           "aspect": fs.getNode("aspectRatio").real(),
           "per_view": fs.getNode("per_view_reprojection_errors").mat().ravel()}
    fs.release()
    return out


@pytest.fixture(scope="module")
def opencv_left():
    require(PHOTOS / "left_intrinsics.yml", "OpenCV sample photos")
    return calibrate_intrinsics(_photos(), board_inner_corners=(9, 6), square_size_m=0.025, fix_aspect_ratio=True)


@needs_photos
def test_published_file_is_what_the_readme_says(published):
    k = published["K"]
    assert published["flags"] == cv2.CALIB_FIX_ASPECT_RATIO and published["aspect"] == 1.0
    assert k[0, 0] == pytest.approx(PUBLISHED["fx"], abs=1e-4) and k[1, 1] == pytest.approx(PUBLISHED["fy"], abs=1e-4)
    assert k[0, 2] == pytest.approx(PUBLISHED["cx"], abs=1e-4) and k[1, 2] == pytest.approx(PUBLISHED["cy"], abs=1e-4)
    assert published["error"] == pytest.approx(PUBLISHED["error"], abs=1e-4)


@needs_photos
def test_reproduces_opencv_published_intrinsics(opencv_left, published):
    r = opencv_left
    k = published["K"]
    assert len(_photos()) == 13 and len(r.used_images) == 13 and r.rejected == ()
    assert (r.intrinsics.width_px, r.intrinsics.height_px) == (640, 480)
    # Measured on OpenCV 5.0.0: fx = fy +0.193 px, cx +0.090 px, cy +0.025 px, RMS +0.0162 px
    # (the published run used OpenCV 4.6; its corner detector differs slightly on left02/left13).
    assert abs(r.intrinsics.fx_px - k[0, 0]) < 0.5
    assert abs(r.intrinsics.fy_px - k[1, 1]) < 0.5
    assert abs(r.intrinsics.cx_px - k[0, 2]) < 0.5
    assert abs(r.intrinsics.cy_px - k[1, 2]) < 0.5
    assert r.intrinsics.fx_px == r.intrinsics.fy_px  # the aspect ratio is held at 1
    assert abs(r.rms_error_px - published["error"]) < 0.05
    assert r.mean_error_px < r.rms_error_px
    # The differences are far inside OpenCV's own uncertainty of the estimate (~1 px).
    assert all(0.3 < s < 2.0 for s in r.std_dev_px)


@needs_photos
def test_distortion_and_per_image_errors_match_published(opencv_left, published):
    r = opencv_left
    # Same lens model: the two calibrations move points by the same amount (within 0.5 px)
    # over the part of the image the boards covered.
    grid = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, 11), np.linspace(-0.35, 0.35, 8)), -1).reshape(-1, 2)
    pts = np.column_stack([grid, np.ones(len(grid))])
    ours, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), r.intrinsics.camera_matrix(), r.intrinsics.distortion_array())
    theirs, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), published["K"], published["dist"])
    assert np.max(np.abs(ours - theirs)) < 0.5
    assert r.intrinsics.distortion[0] == pytest.approx(published["dist"][0], abs=0.005)
    # Per image, as OpenCV's sample reports them: left02 is by far the worst in both.
    names = [Path(p).name for p in r.used_images]
    assert names[int(np.argmax(r.per_image_error_px))] == "left02.jpg"
    assert np.max(np.abs(np.array(r.per_image_error_px) - published["per_view"])) < 0.1


@needs_photos
def test_free_aspect_ratio_estimates_fx_and_fy_separately():
    r = calibrate_intrinsics(_photos(), fix_aspect_ratio=False)
    assert r.intrinsics.fx_px != r.intrinsics.fy_px
    assert abs(r.intrinsics.fx_px - PUBLISHED["fx"]) < 1.0 and abs(r.intrinsics.fy_px - PUBLISHED["fy"]) < 1.0
    assert r.flags & cv2.CALIB_FIX_ASPECT_RATIO == 0


@needs_photos
def test_bad_images_are_rejected_with_reasons_and_do_not_change_the_result(tmp_path, opencv_left):
    not_image = tmp_path / "notes.jpg"
    not_image.write_text("this is not a picture\n")
    missing = tmp_path / "missing.jpg"
    no_board = tmp_path / "floor.png"
    rng = np.random.default_rng(1)
    cv2.imwrite(str(no_board), cv2.GaussianBlur(rng.integers(0, 256, (480, 640), dtype=np.uint8), (0, 0), 3))
    small = tmp_path / "small.png"  # a real board photo, but half the size
    cv2.imwrite(str(small), cv2.resize(cv2.imread(str(PHOTOS / "left01.jpg")), (320, 240)))
    images = [not_image, *_photos()[:6], missing, no_board, small, *_photos()[6:]]
    calls = []
    r = calibrate_intrinsics(images, fix_aspect_ratio=True, progress=lambda d, t, p: calls.append((d, t, p)))
    reasons = {Path(x.path).name: x.reason for x in r.rejected}
    assert reasons == {"notes.jpg": RejectReason.UNREADABLE, "missing.jpg": RejectReason.UNREADABLE,
                       "floor.png": RejectReason.CORNERS_NOT_FOUND, "small.png": RejectReason.WRONG_SIZE}
    details = {Path(x.path).name: x.detail for x in r.rejected}
    assert details["missing.jpg"] == "no such file"
    assert "320x240" in details["small.png"] and "640x480" in details["small.png"]
    assert [Path(x.path).name for x in r.rejected] == ["notes.jpg", "missing.jpg", "floor.png", "small.png"]
    assert len(r.used_images) == 13
    # Identical up to the last bits OpenCV's parallel solver varies in.
    assert r.intrinsics.fx_px == pytest.approx(opencv_left.intrinsics.fx_px, abs=1e-6) and r.intrinsics.cx_px == pytest.approx(opencv_left.intrinsics.cx_px, abs=1e-6)
    assert [c[0] for c in calls] == list(range(1, 18)) and all(c[1] == 17 for c in calls)


@needs_photos
def test_fewer_than_three_usable_images_is_an_error(tmp_path):
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    with pytest.raises(CalibrationError, match=r"only 2 of 3 images are usable.*junk\.png: unreadable"):
        calibrate_intrinsics([*_photos()[:2], junk])


def test_no_images_is_an_error():
    with pytest.raises(CalibrationError, match="only 0 of 0"):
        calibrate_intrinsics([])


def test_board_points_and_parsing():
    pts = board_object_points((9, 6), 0.025)
    assert pts.shape == (54, 3)
    assert pts[1].tolist() == pytest.approx([0.025, 0.0, 0.0])  # along the 9-corner side first
    assert pts[9].tolist() == pytest.approx([0.0, 0.025, 0.0])
    assert pts[-1].tolist() == pytest.approx([0.2, 0.125, 0.0])
    assert parse_board("9x6") == (9, 6) and parse_board("7X4") == (7, 4)
    for bad in ("9", "9x", "ax6", "1x6", "9x6x2"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_board(bad)


def test_recovers_a_rendered_camera(tmp_path):
    """Views of a board on the virtual floor through a known lens (no shared data needed)."""
    truth = dict(fx=420.0, fy=415.0, cx=330.0, cy=245.0, dist=(-0.08, 0.02, 0.001, -0.0007, 0.0))
    board, square = (6, 5), 0.03
    rng = np.random.default_rng(3)
    paths = []
    for k in range(16):
        tilt = rng.choice([-1.0, 1.0]) * rng.uniform(25.0, 38.0)
        cam = FloorCameraModel(CameraIntrinsics(640, 480, truth["fx"], truth["fy"], truth["cx"], truth["cy"],
                                                truth["dist"]), height_m=0.2, tilt_rad=math.radians(tilt),
                               yaw_rad=math.radians(rng.uniform(-180, 180)))
        pose = centred_board_pose(cam, *board, square, rng.uniform(-180, 180),
                                  at_px=(rng.uniform(200, 440), rng.uniform(150, 330)))
        path = tmp_path / f"view{k:02d}.png"
        cv2.imwrite(str(path), render_board(cam, *board, square, pose))
        paths.append(path)
    r = calibrate_intrinsics(paths, board_inner_corners=board, square_size_m=square)
    assert len(r.used_images) >= 10  # views whose board runs off the image are rejected
    assert all(x.reason is RejectReason.CORNERS_NOT_FOUND for x in r.rejected)
    assert abs(r.intrinsics.fx_px - truth["fx"]) < 0.5 and abs(r.intrinsics.fy_px - truth["fy"]) < 0.5
    # The principal point of a dozen small-board views is known to about half a pixel.
    assert abs(r.intrinsics.cx_px - truth["cx"]) < 1.0 and abs(r.intrinsics.cy_px - truth["cy"]) < 1.0
    assert r.rms_error_px < 0.1
    grid = np.stack(np.meshgrid(np.linspace(-0.6, 0.6, 13), np.linspace(-0.45, 0.45, 9)), -1).reshape(-1, 2)
    pts = np.column_stack([grid, np.ones(len(grid))])
    k_true = np.array([[truth["fx"], 0, truth["cx"]], [0, truth["fy"], truth["cy"]], [0, 0, 1.0]])
    ours, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), r.intrinsics.camera_matrix(), r.intrinsics.distortion_array())
    true, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), k_true, np.array(truth["dist"]))
    assert np.max(np.abs(ours - true)) < 1.0


# -------------------------------------------------------------------------- CLI


def _args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_intrinsics_arguments(p)
    return p.parse_args(argv)


@needs_photos
def test_cli_writes_a_file_opencv_reads_and_keeps_the_mount(tmp_path, capsys, opencv_left):
    out = tmp_path / "calibration.yml"
    mount = FloorMount(height_m=0.31, tilt_deg=4.0, x_m=0.12, y_m=-0.02, yaw_deg=90.0)
    write_calibration(out, CalibrationFile(mount=mount))
    notes = tmp_path / "notes.jpg"
    notes.write_text("no picture")
    argv = [str(p) for p in _photos()] + [str(notes), "--board", "9x6", "--square", "0.025",
                                          "--fix-aspect-ratio", "--out", str(out)]
    assert run_intrinsics(_args(argv)) == 0
    printed = capsys.readouterr()
    assert "left02.jpg" in printed.out and "<- worst" in printed.out
    assert "notes.jpg  unreadable" in printed.out
    assert f"{opencv_left.intrinsics.fx_px:.4f}" in printed.out
    assert printed.err.count("\n") >= 1 and "14/14" in printed.err  # plain progress lines (not a TTY)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    k = fs.getNode("camera_matrix").mat()
    d = fs.getNode("distortion_coefficients").mat()
    w, h = int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real())
    err = fs.getNode("avg_reprojection_error").real()
    fs.release()
    # A second run of OpenCV's solver can differ in the last bits (parallel sums).
    np.testing.assert_allclose(k, opencv_left.intrinsics.camera_matrix(), rtol=0, atol=1e-6)
    assert d.shape == (1, 5)
    np.testing.assert_allclose(d.ravel(), opencv_left.intrinsics.distortion, rtol=0, atol=1e-8)
    assert (w, h) == (640, 480) and err == pytest.approx(opencv_left.rms_error_px, abs=1e-8)
    back = read_calibration(out)
    assert back.mount == mount
    assert back.intrinsics is not None and back.intrinsics.fx_px == k[0, 0]


@needs_photos
def test_written_file_gives_opencv_the_same_matrix(tmp_path, opencv_left):
    out = tmp_path / "calibration.yml"
    write_calibration(out, opencv_left.calibration_file())
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    k = fs.getNode("camera_matrix").mat()
    d = fs.getNode("distortion_coefficients").mat()
    fs.release()
    np.testing.assert_array_equal(k, opencv_left.intrinsics.camera_matrix())  # bit for bit
    assert d.ravel().tolist() == list(opencv_left.intrinsics.distortion)
    back = read_calibration(out)
    assert back.intrinsics == opencv_left.intrinsics
    assert back.reprojection_error_px == opencv_left.rms_error_px


def test_progress_bar_tty_and_plain():
    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    tty = Tty()
    bar = ProgressBar("corners", tty, width=10)
    for i in range(1, 5):
        bar(i, 4, f"/x/img{i}.png")
    text = tty.getvalue()
    assert text.count("\r") == 4 and text.endswith("corners [##########] 4/4 img4.png\n")
    assert "[#####.....] 2/4 img2.png" in text
    plain = io.StringIO()
    bar = ProgressBar("corners", plain, width=10)
    for i in range(1, 101):
        bar(i, 100, "")
    lines = plain.getvalue().splitlines()
    assert "\r" not in plain.getvalue()
    assert 15 <= len(lines) <= 21 and lines[-1] == "corners [##########] 100/100"

