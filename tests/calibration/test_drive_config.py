"""The config of a calibration command from a recording made by an earlier robotd (whose
config used the old key names and the demo's virtual floor camera)."""

from __future__ import annotations

import logging
from pathlib import Path

from calibration.train import drive_config
from drivers.recording.writer import RecordingWriter
from robotd.base.config import VIRTUAL_SOURCE
from robotd.base.configfile import RENAMED

OLD = Path(__file__).resolve().parents[1] / "io" / "data" / "config_before_renames.toml"


def test_a_recording_made_with_the_old_schema_gives_its_config_with_the_values_applied(tmp_path, caplog):
    path = tmp_path / "old.mcap"
    writer = RecordingWriter(path, config_toml=OLD.read_text())
    writer.close()
    caplog.set_level(logging.WARNING)
    cfg = drive_config(None, path)
    assert cfg.floor_camera.source == VIRTUAL_SOURCE
    assert cfg.odometry.accel_noise_density_mps2_per_sqrt_hz == 0.7
    assert (cfg.floor_detector.descriptor_mode, cfg.visual_odometry.role) == (3, "vision_only")
    assert cfg.pose_graph.full_solve_every_keyframes == 50
    assert (cfg.forward_camera.fx_px, cfg.forward_camera.mount_height_m) == (500.0, 0.5)
    renamed = [r.getMessage() for r in caplog.records if " is now [" in r.getMessage()]
    assert len(renamed) == len(RENAMED) and all(f"{path} (its config)" in m for m in renamed)
    assert "cannot use the config" not in caplog.text  # not fallen back to the defaults
