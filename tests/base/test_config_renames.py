"""Old config files keep loading: each renamed key is taken as its new name with one
warning naming both, and a file with both names is an error (CHANGELOG.md)."""

from __future__ import annotations

import logging
import tomllib
from pathlib import Path

import pytest

from robotd.base.config import Config, VIRTUAL_SOURCE, live_keys, with_virtual_floor_camera
from robotd.base.configfile import RENAMED, config_from_dict, load_config
from robotd.base.errors import ConfigError

OLD = Path(__file__).resolve().parents[1] / "io" / "data" / "config_before_renames.toml"
"""A config as robotd wrote it into recordings and maps before the renames (``to_toml`` of
the earlier schema, the demo's: virtual floor camera), with non-default values in renamed
keys."""


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == "robotd.base.configfile" and r.levelno == logging.WARNING]


def test_an_old_file_loads_with_its_values_and_one_warning_per_renamed_key(tmp_path, caplog):
    path = tmp_path / "old.toml"
    path.write_text('[odometry]\naccel_noise_mps2 = 0.7\nangular_accel_noise_radps2 = 0.4\n'
                    'gyro_bias_walk_radps_sqrt_s = 3e-5\nwheel_v_noise_mps = 0.02\n'
                    '[floor_detector]\nmode = 3\n[visual_odometry]\nmode = "vision_only"\n'
                    '[pose_graph]\nsave_every_keyframes = 50\n'
                    '[forward_detector]\nenabled = true\nfx_px = 500.0\nmount_height_m = 0.5\n'
                    '[forward_camera]\nsource = "v4l2"\n')
    caplog.set_level(logging.WARNING, logger="robotd.base.configfile")
    cfg = load_config(path)
    o = cfg.odometry
    assert (o.accel_noise_density_mps2_per_sqrt_hz, o.angular_accel_noise_density_radps2_per_sqrt_hz,
            o.gyro_bias_walk_radps_per_sqrt_s, o.wheel_v_noise_mps) == (0.7, 0.4, 3e-5, 0.02)
    assert cfg.floor_detector.descriptor_mode == 3 and cfg.visual_odometry.role == "vision_only"
    assert cfg.pose_graph.full_solve_every_keyframes == 50
    assert (cfg.forward_camera.fx_px, cfg.forward_camera.mount_height_m, cfg.forward_camera.source) == (
        500.0, 0.5, "v4l2")
    assert cfg.forward_detector.enabled and cfg.forward_camera.fy_px == Config().forward_camera.fy_px
    got = _warnings(caplog)
    assert len(got) == 8, got  # the eight old keys of the file, once each
    assert f"{path}: [odometry] accel_noise_mps2 is now [odometry] accel_noise_density_mps2_per_sqrt_hz: " \
           "its value is used; rename it in the file (CHANGELOG.md)" in got
    assert sum("[forward_detector] fx_px is now [forward_camera] fx_px" in m for m in got) == 1
    assert sum("[floor_detector] mode is now [floor_detector] descriptor_mode" in m for m in got) == 1


def test_a_file_with_the_new_names_loads_without_a_warning(tmp_path, caplog):
    path = tmp_path / "new.toml"
    path.write_text('[floor_detector]\ndescriptor_mode = 2\n[forward_camera]\nfx_px = 500.0\n')
    caplog.set_level(logging.WARNING, logger="robotd.base.configfile")
    cfg = load_config(path)
    assert cfg.floor_detector.descriptor_mode == 2 and cfg.forward_camera.fx_px == 500.0
    assert _warnings(caplog) == []


@pytest.mark.parametrize("toml, message", [
    ("[floor_detector]\nmode = 3\ndescriptor_mode = 3\n",
     "[floor_detector] mode and [floor_detector] descriptor_mode are the same key ([floor_detector] "
     "mode is its old name): keep only [floor_detector] descriptor_mode"),
    ("[forward_detector]\nwidth_px = 320\n[forward_camera]\nwidth_px = 320\n",
     "[forward_detector] width_px and [forward_camera] width_px are the same key"),
    ("[floor_detector]\nmode = 9\n", "[floor_detector] descriptor_mode: 9 is above the maximum 6"),
    ("[floor_camera]\nsource = \"virtual\"\n",
     "[floor_camera] source: 'virtual' is not a camera of `robotd run`"),
])
def test_old_and_new_name_together_and_bad_old_values_are_errors(tmp_path, toml, message):
    path = tmp_path / "c.toml"
    path.write_text(toml)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_renames_point_to_real_keys_and_old_names_are_gone():
    cfg = Config()
    for (old_sec, old_key), (new_sec, new_key) in RENAMED.items():
        assert hasattr(getattr(cfg, new_sec), new_key), (new_sec, new_key)
        assert not hasattr(getattr(cfg, old_sec), old_key), (old_sec, old_key)
    assert ("pose_graph", "full_solve_every_keyframes") in live_keys()


def test_a_config_robotd_stored_before_the_renames_reads_with_its_values(caplog):
    """Recordings and maps hold the config they were made with (``to_toml``): one written
    by the earlier schema, with the demo's virtual floor camera, still reads."""
    caplog.set_level(logging.WARNING, logger="robotd.base.configfile")
    data = tomllib.loads(OLD.read_text())
    cfg = config_from_dict(data, origin="old.mcap", stored=True)
    assert cfg.floor_camera.source == VIRTUAL_SOURCE
    assert cfg.odometry.accel_noise_density_mps2_per_sqrt_hz == 0.7
    assert (cfg.floor_detector.descriptor_mode, cfg.visual_odometry.role) == (3, "vision_only")
    assert cfg.pose_graph.full_solve_every_keyframes == 50
    assert (cfg.forward_camera.fx_px, cfg.forward_camera.mount_height_m) == (500.0, 0.5)
    assert len(_warnings(caplog)) == len(RENAMED)  # that schema wrote every key
    with pytest.raises(ConfigError, match="'virtual' is not a camera"):
        config_from_dict(data)  # a user's file may not say "virtual"


def test_the_virtual_floor_camera_is_set_by_code_and_survives_a_stored_round_trip():
    from robotd.base.configfile import to_toml

    cfg = with_virtual_floor_camera(Config())
    assert cfg.floor_camera.source == VIRTUAL_SOURCE
    assert config_from_dict(tomllib.loads(to_toml(cfg)), stored=True) == cfg
