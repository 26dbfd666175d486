"""``[recording]`` and ``[floor_camera]`` decide how `robotd record` writes its file."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from drivers.recording.reader import RecordingReader, read_recording
from robotd.app.service import open_recording
from robotd.base.camera import FloorCameraModel
from robotd.base.config import Config, replace
from robotd.base.messages import Frame
from tests.drivers.test_recording_ros import quat_matrix, read_with_rosbags


def _frame() -> Frame:
    rng = np.random.default_rng(0)
    return Frame(1_000, "floor", (rng.random((480, 640)) * 255).astype(np.uint8), 4)


def test_config_chooses_the_frame_format_and_quality(tmp_path: Path) -> None:
    frame = _frame()
    sizes = {}
    for fmt, quality in (("png", 90), ("jpeg", 90), ("jpeg", 15)):
        cfg = replace(Config(), "recording", image_format=fmt, jpeg_quality=quality)
        path = tmp_path / f"{fmt}{quality}.mcap"
        w = open_recording(cfg, path)
        w.write_frame(frame)
        w.close()
        sizes[fmt, quality] = path.stat().st_size
        with RecordingReader(path) as r:
            want = "png_compression 1" if fmt == "png" else f"jpeg_quality {quality}"
            assert (r.metadata["robotd"]["image_format"], r.metadata["robotd"]["image_quality"]) == (fmt, want)
        (got,) = [m for _, m in read_recording(path)]
        assert np.array_equal(got.image, frame.image) == (fmt == "png")
    assert sizes["jpeg", 15] < sizes["jpeg", 90] < sizes["png", 90]


def test_the_default_config_records_compact_jpeg(tmp_path: Path) -> None:
    w = open_recording(Config(), tmp_path / "d.mcap")
    w.write_frame(_frame())
    w.close()
    (img,) = read_with_rosbags(tmp_path / "d.mcap")["/floor_camera/image/compressed"]
    assert img.format == "jpeg" and bytes(img.data[:2]) == b"\xff\xd8"


def test_camera_info_and_mount_come_from_the_floor_camera_section(tmp_path: Path) -> None:
    cfg = replace(Config(), "floor_camera", fx_px=512.0, cy_px=250.0, mount_tilt_deg=8.0, mount_x_m=0.12,
                  mount_yaw_deg=-20.0, distortion=[0.1, -0.01, 0.0, 0.001, 0.002])
    w = open_recording(cfg, tmp_path / "c.mcap")
    w.write_frame(_frame())
    w.close()
    got = read_with_rosbags(tmp_path / "c.mcap")
    (info,) = got["/floor_camera/camera_info"]
    assert (info.k[0], info.k[4], info.k[5]) == (512.0, 400.0, 250.0)
    assert list(info.d) == [0.1, -0.01, 0.0, 0.001, 0.002]
    (static,) = got["/tf_static"]
    cam = {t.child_frame_id: t for t in static.transforms}["floor_camera_optical_frame"].transform
    model = FloorCameraModel.from_config(cfg.floor_camera)
    np.testing.assert_allclose(quat_matrix(cam.rotation), model.rotation_robot_from_camera, atol=1e-12)
    assert (cam.translation.x, cam.translation.z) == (0.12, 0.40)
    assert math.isclose(model.rotation_robot_from_camera[0, 2], math.sin(math.radians(8.0)))
