"""The calibration file: round trips, OpenCV compatibility, damaged files, atomic writes, merging."""

from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import pytest

import robotd.io.calibfile as calibfile
from robotd.io.calibfile import (
    CalibrationFile,
    FloorMount,
    LoopThresholds,
    camera_model,
    merge,
    read_calibration,
    update_calibration,
    write_calibration,
)
from robotd.base.camera import CameraIntrinsics
from robotd.base.config import FloorCameraConfig
from robotd.base.errors import CalibrationError
from tests.calibration import SHARED_DATA
from tests.shared_data import require

INTR = CameraIntrinsics(width_px=640, height_px=480, fx_px=401.25, fy_px=399.5, cx_px=321.1, cy_px=238.7,
                        distortion=(-0.051, 0.012, 0.0011, -0.0004, 0.003))
MOUNT = FloorMount(height_m=0.352, tilt_deg=7.5, x_m=0.105, y_m=-0.021, yaw_deg=-90.0)
LOOP = LoopThresholds(thresholds=(None, 0.41, 0.38, 0.35, 0.33, 0.3), overlap_r=0.33, confidence=0.99)
FULL = CalibrationFile(intrinsics=INTR, reprojection_error_px=0.183, mount=MOUNT, loop=LOOP)

GOOD_TEXT = """%YAML:1.0
---
image_width: 640
image_height: 480
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 400., 0., 320., 0., 400., 240., 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -0.05, 0., 0., 0., 0. ]
"""


def test_round_trip_of_every_part(tmp_path):
    path = tmp_path / "calibration.yml"
    write_calibration(path, FULL)
    back = read_calibration(path)
    assert back == FULL  # floats survive exactly (17 significant digits)
    assert back.loop.for_mode(1) is None and back.loop.for_mode(3) == 0.38


def test_the_file_is_plain_opencv_yaml(tmp_path):
    path = tmp_path / "calibration.yml"
    write_calibration(path, FULL)
    text = path.read_text()
    assert text.startswith("%YAML") and "!!opencv-matrix" in text
    assert "loop_threshold_mode_1" not in text and "loop_threshold_mode_2:" in text  # untrained: absent
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.getNode("camera_matrix").mat().tolist() == [[401.25, 0, 321.1], [0, 399.5, 238.7], [0, 0, 1]]
    d = fs.getNode("distortion_coefficients").mat()
    assert d.shape == (1, 5) and d.ravel().tolist() == list(INTR.distortion)
    assert fs.getNode("image_width").isInt() and fs.getNode("image_width").real() == 640
    assert fs.getNode("image_height").real() == 480
    assert fs.getNode("avg_reprojection_error").real() == 0.183
    assert fs.getNode("mount_height_m").real() == 0.352 and fs.getNode("mount_yaw_deg").real() == -90.0
    assert fs.getNode("loop_confidence").real() == 0.99
    fs.release()


def test_reads_the_file_opencvs_own_sample_wrote():
    calib = read_calibration(require(SHARED_DATA / "calibration" / "opencv_left" / "left_intrinsics.yml",
                                     "OpenCV's published calibration"))
    ci = calib.intrinsics
    assert ci is not None and calib.mount is None and calib.loop is None
    assert (ci.width_px, ci.height_px) == (640, 480)
    assert ci.fx_px == pytest.approx(535.9157, abs=1e-4) and ci.fy_px == ci.fx_px
    assert ci.cx_px == pytest.approx(342.2832, abs=1e-4) and ci.cy_px == pytest.approx(235.5708, abs=1e-4)
    assert ci.distortion == pytest.approx((-0.26637, -0.03859, 0.00178, -0.00028, 0.23839), abs=1e-5)
    assert calib.reprojection_error_px == pytest.approx(0.3926, abs=1e-4)


def test_minimal_file_without_error_or_extras(tmp_path):
    path = tmp_path / "c.yml"
    path.write_text(GOOD_TEXT + "nframes: 13\nflags: 2\n")  # keys of other tools are ignored
    calib = read_calibration(path)
    assert calib.intrinsics == CameraIntrinsics(640, 480, 400.0, 400.0, 320.0, 240.0, (-0.05, 0.0, 0.0, 0.0, 0.0))
    assert calib.reprojection_error_px is None


def test_missing_file(tmp_path):
    path = tmp_path / "nope.yml"
    with pytest.raises(CalibrationError, match=r"nope\.yml: no such calibration file"):
        read_calibration(path)


def test_directory_instead_of_file(tmp_path):
    with pytest.raises(CalibrationError, match="is a directory"):
        read_calibration(tmp_path)


@pytest.mark.parametrize(
    "content, message",
    [
        (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "binary data"),
        (b"\xff\xd8\xff\xe0garbage\xff", "not UTF-8"),
        (b"", "empty"),
        (b"just some words\n", "not valid OpenCV YAML"),
        (b'<?xml version="1.0"?>\n<opencv_storage><image_width>640</image_width></opencv_storage>\n',
         "looks like XML"),
        (b"%YAML:1.0\n---\n", "not a mapping"),
        (b"%YAML:1.0\n---\nnframes: 13\n", "holds no calibration"),
        # Truncated in the middle of the matrix data (a write cut short).
        (GOOD_TEXT.encode()[:180], "not valid OpenCV YAML"),
        (GOOD_TEXT.replace("data: [ 400., 0., 320., 0., 400., 240., 0., 0., 1. ]", "data: [ 400., 0. ]").encode(),
         "camera_matrix is a damaged matrix"),
        (GOOD_TEXT.replace("rows: 3\n   cols: 3", "rows: 1\n   cols: 9").encode(), "camera_matrix must be 3x3"),
        (GOOD_TEXT.replace("camera_matrix: !!opencv-matrix", "camera_matrix: 5\nold_matrix: !!opencv-matrix").encode(),
         "camera_matrix must be an !!opencv-matrix (rows, cols, dt, data), got the number 5"),
        (GOOD_TEXT.replace("image_width: 640", "image_width: wide").encode(), "image_width must be a number"),
        (GOOD_TEXT.replace("image_width: 640", "image_width: 640.5").encode(), "image_width must be an integer"),
        (GOOD_TEXT.replace("image_width: 640\n", "").encode(), "incomplete: image_width missing"),
        (GOOD_TEXT.replace("400., 0., 320., 0., 400.", "-400., 0., 320., 0., 400.").encode(),
         "focal lengths must be positive"),
        (GOOD_TEXT.replace("400., 0., 320., 0.,", "400., 3., 320., 0.,").encode(), "no skew"),
        (GOOD_TEXT.replace("rows: 5", "rows: 8").replace("-0.05, 0., 0., 0., 0.", "-0.05, 0., 0., 0., 0., 0.1, 0., 0.")
         .encode(), "rational or thin-prism"),
        (GOOD_TEXT.replace("image_height: 480", "image_height: 480\nimage_height: 240").encode(),
         "image_height appears more than once"),
        (GOOD_TEXT.encode() + b"mount_heigth_m: 0.4\n", "unknown key mount_heigth_m"),
        (GOOD_TEXT.encode() + b"mount_height_m: 0.4\nmount_tilt_deg: 0.\n", "the floor-mount section is incomplete"),
        (GOOD_TEXT.encode() + b"mount_height_m: -0.4\nmount_tilt_deg: 0.\nmount_x_m: 0.\nmount_y_m: 0.\n"
         b"mount_yaw_deg: 0.\n", "mount_height_m must be positive"),
        (GOOD_TEXT.encode() + b"mount_height_m: .Nan\nmount_tilt_deg: 0.\nmount_x_m: 0.\nmount_y_m: 0.\n"
         b"mount_yaw_deg: 0.\n", "mount_height_m must be a finite number"),
        (GOOD_TEXT.encode() + b"loop_threshold_mode_2: 0.4\n", "the loop-threshold section is incomplete"),
        (GOOD_TEXT.encode() + b"loop_threshold_mode_2: 0.4\nloop_overlap_r: 0.33\nloop_confidence: 1.5\n",
         "loop_confidence must lie in"),
    ],
)
def test_damaged_files_name_the_path_and_the_fault(tmp_path, content, message):
    path = tmp_path / "calibration.yml"
    path.write_bytes(content)
    with pytest.raises(CalibrationError) as err:
        read_calibration(path)
    text = str(err.value)
    assert text.startswith(f"{path}: ")
    assert message in text


def test_write_is_atomic_when_the_rename_fails(tmp_path, monkeypatch):
    path = tmp_path / "calibration.yml"
    write_calibration(path, FULL)
    before = path.read_bytes()

    def no_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(calibfile.os, "replace", no_replace)
    with pytest.raises(CalibrationError, match="No space left on device"):
        write_calibration(path, CalibrationFile(intrinsics=INTR))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.yml"]  # no temporary file left


def test_write_is_atomic_when_writing_fails_midway(tmp_path, monkeypatch):
    path = tmp_path / "calibration.yml"
    write_calibration(path, FULL)
    before = path.read_bytes()
    real_write = os.write

    def half_then_fail(fd, data):
        if len(data) > 100:
            real_write(fd, bytes(data[:100]))
            raise OSError(5, "Input/output error")
        return real_write(fd, data)

    monkeypatch.setattr(calibfile.os, "write", half_then_fail)
    with pytest.raises(CalibrationError, match="Input/output error"):
        write_calibration(path, CalibrationFile(mount=MOUNT))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["calibration.yml"]


def test_write_into_a_missing_directory(tmp_path):
    with pytest.raises(CalibrationError, match="cannot write"):
        write_calibration(tmp_path / "no" / "such" / "c.yml", FULL)


def test_empty_calibration_is_not_written(tmp_path):
    with pytest.raises(CalibrationError, match="empty"):
        write_calibration(tmp_path / "c.yml", CalibrationFile())
    assert not (tmp_path / "c.yml").exists()


def test_merge_replaces_one_part_and_keeps_the_others():
    new_mount = FloorMount(height_m=0.5, tilt_deg=0.0)
    merged = merge(FULL, CalibrationFile(mount=new_mount))
    assert merged == CalibrationFile(intrinsics=INTR, reprojection_error_px=0.183, mount=new_mount, loop=LOOP)
    # New intrinsics replace the old ones' reprojection error too (unknown here).
    assert merge(FULL, CalibrationFile(intrinsics=INTR)).reprojection_error_px is None
    with pytest.raises(CalibrationError, match="without intrinsics"):
        CalibrationFile(reprojection_error_px=0.2)
    with pytest.raises(CalibrationError, match="must be >= 0"):
        CalibrationFile(intrinsics=INTR, reprojection_error_px=-0.1)
    assert merge(None, CalibrationFile(loop=LOOP)) == CalibrationFile(loop=LOOP)
    assert merge(FULL, CalibrationFile()) == FULL


def test_update_calibration_creates_then_merges(tmp_path):
    path = tmp_path / "c.yml"
    update_calibration(path, CalibrationFile(intrinsics=INTR, reprojection_error_px=0.183))
    update_calibration(path, CalibrationFile(loop=LOOP))
    update_calibration(path, CalibrationFile(mount=MOUNT))
    assert read_calibration(path) == FULL


def test_update_never_overwrites_a_damaged_file(tmp_path):
    path = tmp_path / "c.yml"
    path.write_bytes(GOOD_TEXT.encode()[:180])
    with pytest.raises(CalibrationError, match="not valid OpenCV YAML"):
        update_calibration(path, CalibrationFile(mount=MOUNT))
    assert path.read_bytes() == GOOD_TEXT.encode()[:180]


def test_loop_thresholds_checks():
    lt = LoopThresholds.from_mapping({2: 0.5, 6: 0.25})
    assert lt.thresholds == (None, 0.5, None, None, None, 0.25)
    assert lt.for_mode(6) == 0.25 and lt.for_mode(1) is None
    with pytest.raises(CalibrationError, match="modes must be 1..6"):
        LoopThresholds.from_mapping({7: 0.5})
    with pytest.raises(CalibrationError, match="need 6 entries"):
        LoopThresholds(thresholds=(0.5,))
    with pytest.raises(CalibrationError, match="loop_overlap_r"):
        LoopThresholds(overlap_r=0.0)
    with pytest.raises(ValueError):
        lt.for_mode(0)


def test_camera_model_takes_calibrated_parts_and_falls_back_to_the_config():
    cfg = FloorCameraConfig()
    base = camera_model(None, cfg)
    assert base.intrinsics == CameraIntrinsics.from_config(cfg)
    assert (base.intrinsics.fx_px, base.height_m, base.intrinsics.distortion) == (
        cfg.fx_px, cfg.mount_height_m, tuple(cfg.distortion))

    only_mount = camera_model(CalibrationFile(mount=MOUNT), cfg)
    assert only_mount.intrinsics.fx_px == cfg.fx_px and only_mount.intrinsics.cx_px == cfg.cx_px
    assert only_mount.height_m == 0.352 and only_mount.offset_x_m == 0.105 and only_mount.offset_y_m == -0.021
    assert only_mount.tilt_rad == pytest.approx(math.radians(7.5)) and only_mount.yaw_rad == pytest.approx(-math.pi / 2)

    full = camera_model(FULL, cfg)
    assert full.intrinsics == INTR
    assert full.height_m == MOUNT.height_m

    only_intr = camera_model(CalibrationFile(intrinsics=INTR), cfg)
    assert only_intr.intrinsics.fx_px == INTR.fx_px and only_intr.height_m == cfg.mount_height_m


def test_camera_model_refuses_intrinsics_of_another_image_size():
    small = CameraIntrinsics(320, 240, 200.0, 200.0, 160.0, 120.0)
    with pytest.raises(CalibrationError, match="320x240 images but the floor camera delivers 640x480"):
        camera_model(CalibrationFile(intrinsics=small), FloorCameraConfig())


def test_paths_may_be_strings(tmp_path):
    path = str(tmp_path / "c.yml")
    write_calibration(path, CalibrationFile(mount=MOUNT))
    assert read_calibration(Path(path)).mount == MOUNT


def test_the_odometry_models_white_accelerations_are_optional(tmp_path):
    """A file written before the accelerations were fitted loads without them; one with
    them round-trips; half of them is refused naming the keys."""
    import dataclasses

    from robotd.io.calibfile import OdometryModel

    old = OdometryModel(wheel_radius_left_m=0.035, wheel_radius_right_m=0.0351, wheel_base_m=0.232,
                        gyro_scale=1.0004, gyro_bias_radps=0.005, gyro_noise_radps_sqrt_hz=5.6e-4,
                        wheel_noise_m_sqrt_m=0.0, wheel_radius_left_sigma_m=1e-6,
                        wheel_radius_right_sigma_m=1e-6, wheel_base_sigma_m=1e-4, gyro_scale_sigma=1e-4,
                        gyro_bias_sigma_radps=7e-5)
    path = tmp_path / "old.yml"
    write_calibration(path, CalibrationFile(odometry=old))
    assert "accel" not in path.read_text()
    back = read_calibration(path).odometry
    assert back == old and not back.has_process_noise and back.accel_noise_mps2_sqrt_hz is None
    new = dataclasses.replace(old, accel_noise_mps2_sqrt_hz=0.0154, angular_accel_noise_radps2_sqrt_hz=0.0766,
                              accel_noise_sigma=1.8e-4, angular_accel_noise_sigma=5.3e-4)
    write_calibration(path, CalibrationFile(odometry=new))
    assert read_calibration(path).odometry == new and new.has_process_noise
    half = path.read_text().replace("odometry_angular_accel_noise_sigma", "odometry_unknown_x")
    path.write_text("\n".join(ln for ln in half.splitlines() if "odometry_unknown_x" not in ln) + "\n")
    with pytest.raises(CalibrationError, match="odometry_angular_accel_noise_sigma"):
        read_calibration(path)
    with pytest.raises(CalibrationError, match="positive"):
        dataclasses.replace(new, angular_accel_noise_radps2_sqrt_hz=0.0)


def test_the_odometry_models_slip_events_are_optional_and_all_four_or_none(tmp_path):
    """A file without the slip events loads without them; one with them round-trips; a
    half group, a rate of 0 or a negative sigma is refused naming the key."""
    import dataclasses

    from robotd.io.calibfile import OdometryModel

    old = OdometryModel(wheel_radius_left_m=0.035, wheel_radius_right_m=0.0351, wheel_base_m=0.232,
                        gyro_scale=1.0004, gyro_bias_radps=0.005, gyro_noise_radps_sqrt_hz=5.6e-4,
                        wheel_noise_m_sqrt_m=5e-4, wheel_radius_left_sigma_m=1e-6,
                        wheel_radius_right_sigma_m=1e-6, wheel_base_sigma_m=1e-4, gyro_scale_sigma=1e-4,
                        gyro_bias_sigma_radps=7e-5)
    assert not old.has_slip_events
    new = dataclasses.replace(old, slip_event_rate_hz=0.23, slip_event_duration_s=0.19,
                              slip_event_rate_sigma_hz=0.05, slip_event_duration_sigma_s=0.02)
    path = tmp_path / "c.yml"
    write_calibration(path, CalibrationFile(odometry=new))
    assert "odometry_slip_event_rate_hz: 0.23" in path.read_text()
    back = read_calibration(path).odometry
    assert back == new and back.has_slip_events
    text = path.read_text()
    path.write_text("\n".join(ln for ln in text.splitlines() if "slip_event_duration_sigma_s" not in ln) + "\n")
    with pytest.raises(CalibrationError, match="odometry_slip_event_duration_sigma_s"):
        read_calibration(path)
    with pytest.raises(CalibrationError, match="odometry_slip_event_rate_hz must be in"):
        dataclasses.replace(new, slip_event_rate_hz=0.0)
    with pytest.raises(CalibrationError, match="odometry_slip_event_rate_sigma_hz must be >= 0"):
        dataclasses.replace(new, slip_event_rate_sigma_hz=-1.0)
