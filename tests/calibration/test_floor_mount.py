"""Floor mount from a chessboard on the floor, checked against rendered pictures of known mounts."""

from __future__ import annotations

import argparse
import math

import cv2
import numpy as np
import pytest

from robotd.io.calibfile import CalibrationFile, FloorMount, read_calibration, write_calibration
from calibration.floor_mount import (
    add_floor_mount_arguments,
    board_corners_robot,
    canonical_board_corners,
    measure_floor_mount,
    parse_board_pose,
    run_floor_mount,
)
from calibration.intrinsics import find_board_corners
from robotd.base.errors import CalibrationError
from robotd.base.camera import CameraIntrinsics, FloorCameraModel, overlap_ratio
from tests.calibration import centred_board_pose, render_board

INTR = CameraIntrinsics(640, 480, fx_px=400.0, fy_px=410.0, cx_px=322.0, cy_px=236.5,
                        distortion=(-0.05, 0.01, 0.001, -0.0005, 0.0))
BOARD, SQUARE = (9, 6), 0.025


def _camera(h: float, tilt_deg: float, yaw_deg: float, x: float, y: float) -> FloorCameraModel:
    return FloorCameraModel(INTR, height_m=h, tilt_rad=math.radians(tilt_deg),
                            offset_x_m=x, offset_y_m=y, yaw_rad=math.radians(yaw_deg))


def _angle_diff_deg(a: float, b: float) -> float:
    return (a - b + 180.0) % 360.0 - 180.0


# (height_m, tilt_deg, yaw_deg, x_m, y_m, board yaw in the robot frame, deg)
MOUNTS = [
    (0.40, 0.0, 0.0, 0.0, 0.0, 0.0),        # the default: straight down over the centre
    (0.30, 12.0, 90.0, 0.12, -0.04, 30.0),  # turned a quarter, leaning forward, off-centre
    (0.50, -8.0, -135.0, -0.10, 0.05, 200.0),
    (0.35, 25.0, 180.0, 0.20, 0.0, -100.0),
    (0.45, 5.0, 45.0, 0.0, 0.10, 95.0),
]


@pytest.mark.parametrize("h, tilt, yaw, x, y, board_yaw", MOUNTS)
def test_recovers_rendered_mounts(h, tilt, yaw, x, y, board_yaw):
    cam = _camera(h, tilt, yaw, x, y)
    pose = centred_board_pose(cam, *BOARD, SQUARE, board_yaw)
    img = render_board(cam, *BOARD, SQUARE, pose)
    r = measure_floor_mount(img, INTR, BOARD, SQUARE, pose)
    # Measured: at most 0.08 mm height, 0.054 deg tilt, 0.008 deg yaw, 0.4 mm position
    # (the straight-down view is the weakest: tilt trades against the forward offset).
    assert abs(r.height_m - h) < 0.002
    assert abs(r.tilt_deg - tilt) < 0.2
    assert abs(_angle_diff_deg(r.yaw_deg, yaw)) < 0.2
    assert abs(r.x_m - x) < 0.002 and abs(r.y_m - y) < 0.002
    assert -180.0 < r.yaw_deg <= 180.0
    assert r.reprojection_error_px < 0.15
    assert abs(r.roll_deg) < 0.1  # the rendered camera has no sideways lean
    # Corners come in board order: the first is the board origin, the 9th ends its x side.
    expected = cam.floor_robot_to_pixel(board_corners_robot(BOARD, SQUARE, pose))
    assert np.max(np.linalg.norm(r.corners_px - expected, axis=1)) < 0.3
    # The recovered camera sees the same piece of floor.
    fp_true, fp_meas = cam.footprint_robot(), r.camera_model(INTR).footprint_robot()
    assert overlap_ratio(fp_true, fp_meas) > 0.99
    assert r.mount == FloorMount(r.height_m, r.tilt_deg, r.x_m, r.y_m, r.yaw_deg)


def test_board_order_does_not_depend_on_opencvs_order():
    cam = _camera(0.35, 10.0, 30.0, 0.0, 0.0)
    pose = centred_board_pose(cam, *BOARD, SQUARE, 75.0)
    img = render_board(cam, *BOARD, SQUARE, pose)
    found = find_board_corners(img, BOARD)
    assert found is not None
    grid = found.reshape(BOARD[1], BOARD[0], 2)
    orders = [grid, grid[::-1, ::-1], grid[:, ::-1], grid[::-1, :]]  # every order a 9x6 grid allows
    expected = cam.floor_robot_to_pixel(board_corners_robot(BOARD, SQUARE, pose))
    for g in orders:
        out = canonical_board_corners(img, g.reshape(-1, 2), BOARD)
        assert np.max(np.linalg.norm(out - expected, axis=1)) < 0.3
    # With the colours swapped the black corner squares are at the other end of the board,
    # and so is the origin.
    swapped = canonical_board_corners(255 - img, found, BOARD)
    np.testing.assert_allclose(swapped, expected[::-1], atol=0.3)


def test_position_and_yaw_are_relative_to_where_the_user_says_the_board_is():
    cam = _camera(0.30, 12.0, 90.0, 0.12, -0.04)
    pose = centred_board_pose(cam, *BOARD, SQUARE, 30.0)
    img = render_board(cam, *BOARD, SQUARE, pose)
    base = measure_floor_mount(img, INTR, BOARD, SQUARE, pose)
    shifted = measure_floor_mount(img, INTR, BOARD, SQUARE, (pose[0] + 0.05, pose[1] - 0.02, pose[2]))
    assert shifted.x_m - base.x_m == pytest.approx(0.05, abs=1e-6)
    assert shifted.y_m - base.y_m == pytest.approx(-0.02, abs=1e-6)
    assert shifted.height_m == pytest.approx(base.height_m, abs=1e-6)
    # Saying the board is turned 10 deg more turns the camera's lean 10 deg off forward:
    # a sideways lean the model cannot hold, reported as roll (asin(sin 12 sin 10) = 2.07 deg).
    leaning = measure_floor_mount(img, INTR, BOARD, SQUARE, (pose[0], pose[1], pose[2] + 10.0))
    assert leaning.roll_deg == pytest.approx(math.degrees(math.asin(math.sin(math.radians(12.0))
                                                                    * math.sin(math.radians(10.0)))), abs=0.1)
    assert leaning.reprojection_error_px > 0.3 > base.reprojection_error_px


def test_turning_the_board_turns_a_straight_down_camera():
    cam = _camera(0.40, 0.0, 20.0, 0.03, 0.01)
    pose = centred_board_pose(cam, *BOARD, SQUARE, -40.0)
    img = render_board(cam, *BOARD, SQUARE, pose)
    base = measure_floor_mount(img, INTR, BOARD, SQUARE, pose)
    turned = measure_floor_mount(img, INTR, BOARD, SQUARE, (pose[0], pose[1], pose[2] + 10.0))
    assert _angle_diff_deg(turned.yaw_deg, base.yaw_deg) == pytest.approx(10.0, abs=1e-3)
    assert turned.tilt_deg == pytest.approx(base.tilt_deg, abs=0.01)
    assert turned.height_m == pytest.approx(base.height_m, abs=1e-6)
    # The lens turns about the board origin with it (within the straight-down view's
    # tilt-against-offset uncertainty).
    c, s = math.cos(math.radians(10.0)), math.sin(math.radians(10.0))
    dx, dy = base.x_m - pose[0], base.y_m - pose[1]
    assert (turned.x_m, turned.y_m) == pytest.approx((pose[0] + c * dx - s * dy, pose[1] + s * dx + c * dy), abs=2e-3)
    assert math.hypot(dx, dy) > 0.1  # so the check above is not trivially met


def test_camera_matrix_and_distortion_tuple_work_like_intrinsics():
    cam = _camera(0.35, 10.0, -30.0, 0.05, 0.02)
    pose = centred_board_pose(cam, *BOARD, SQUARE, 60.0)
    img = render_board(cam, *BOARD, SQUARE, pose)
    a = measure_floor_mount(img, INTR, BOARD, SQUARE, pose)
    b = measure_floor_mount(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), (INTR.camera_matrix(), INTR.distortion),
                            BOARD, SQUARE, pose)
    assert (a.height_m, a.tilt_deg, a.yaw_deg, a.x_m, a.y_m) == pytest.approx(
        (b.height_m, b.tilt_deg, b.yaw_deg, b.x_m, b.y_m), abs=1e-9)


def test_wrong_intrinsics_show_in_the_fit():
    cam = _camera(0.35, 10.0, -30.0, 0.05, 0.02)
    pose = centred_board_pose(cam, *BOARD, SQUARE, 60.0)
    img = render_board(cam, *BOARD, SQUARE, pose)
    right = measure_floor_mount(img, INTR, BOARD, SQUARE, pose)
    wrong = CameraIntrinsics(640, 480, 400.0, 410.0, 322.0, 236.5, (0.2, 0.0, 0.0, 0.0, 0.0))  # pincushion, not barrel
    r = measure_floor_mount(img, wrong, BOARD, SQUARE, pose)
    assert right.reprojection_error_px < 0.1
    assert r.reprojection_error_px > 0.3


def test_no_board_in_the_picture():
    img = np.full((480, 640), 120, np.uint8)
    with pytest.raises(CalibrationError, match="no 9x6 chessboard found"):
        measure_floor_mount(img, INTR, BOARD, SQUARE, (0.0, 0.0, 0.0))


def test_a_board_that_looks_the_same_turned_around_is_refused():
    cam = _camera(0.40, 0.0, 0.0, 0.0, 0.0)
    pose = centred_board_pose(cam, 8, 6, SQUARE, 20.0)
    img = render_board(cam, 8, 6, SQUARE, pose)
    with pytest.raises(CalibrationError, match="looks the same turned around"):
        measure_floor_mount(img, INTR, (8, 6), SQUARE, pose)


def test_picture_size_must_match_the_intrinsics():
    with pytest.raises(CalibrationError, match="for 640x480 images, the picture is 320x240"):
        measure_floor_mount(np.zeros((240, 320), np.uint8), INTR, BOARD, SQUARE, (0.0, 0.0, 0.0))


def test_parse_board_pose():
    assert parse_board_pose("0.3,-0.1,90") == (0.3, -0.1, 90.0)
    assert parse_board_pose(" 0.3 , 0 , -45.5 ") == (0.3, 0.0, -45.5)
    for bad in ("0.3,0.1", "a,b,c", "1,2,3,4", "0,0,nan"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_board_pose(bad)


# -------------------------------------------------------------------------- CLI


def _args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_floor_mount_arguments(p)
    return p.parse_args(argv)


def test_cli_measures_and_merges_the_mount(tmp_path, capsys):
    cam = _camera(0.30, 12.0, 90.0, 0.12, -0.04)
    pose = centred_board_pose(cam, *BOARD, SQUARE, 30.0)
    picture = tmp_path / "board.png"
    cv2.imwrite(str(picture), render_board(cam, *BOARD, SQUARE, pose))
    calib = tmp_path / "calibration.yml"
    write_calibration(calib, CalibrationFile(intrinsics=INTR))
    argv = [str(picture), "--calibration", str(calib), "--board", "9x6", "--square", "0.025",
            "--board-pose", f"{pose[0]!r},{pose[1]!r},{pose[2]!r}"]
    assert run_floor_mount(_args(argv)) == 0
    out = capsys.readouterr().out
    back = read_calibration(calib)
    assert back.intrinsics == INTR  # kept
    m = back.mount
    assert m is not None
    assert abs(m.height_m - 0.30) < 0.002 and abs(m.tilt_deg - 12.0) < 0.2
    assert abs(_angle_diff_deg(m.yaw_deg, 90.0)) < 0.2
    assert abs(m.x_m - 0.12) < 0.002 and abs(m.y_m + 0.04) < 0.002
    assert "height          300." in out and "footprint" in out and "mm/px" in out
    # The printed footprint is the recovered camera's: check its forward extent.
    fp = cam.footprint_robot()
    ext_x_mm = (fp[:, 0].max() - fp[:, 0].min()) * 1000
    assert f"{ext_x_mm:.0f} mm along x" in out


def test_cli_needs_intrinsics_and_a_readable_picture(tmp_path):
    calib = tmp_path / "calibration.yml"
    write_calibration(calib, CalibrationFile(mount=FloorMount(0.4, 0.0)))
    picture = tmp_path / "board.png"
    cv2.imwrite(str(picture), np.zeros((480, 640), np.uint8))
    with pytest.raises(CalibrationError, match="has no camera intrinsics"):
        run_floor_mount(_args([str(picture), "--calibration", str(calib), "--board-pose", "0,0,0"]))
    write_calibration(calib, CalibrationFile(intrinsics=INTR))
    notes = tmp_path / "notes.png"
    notes.write_text("not a picture")
    with pytest.raises(CalibrationError, match="cannot read the picture"):
        run_floor_mount(_args([str(notes), "--calibration", str(calib), "--board-pose", "0,0,0"]))
    assert read_calibration(calib).mount is None  # nothing written on failure
