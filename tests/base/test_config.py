"""The TOML config: defaults, the shipped commented file, and errors that name the key."""

import dataclasses
from pathlib import Path

import pytest

from robotd.base.config import Config, replace
from robotd.base.configfile import config_from_dict, load_config, to_toml
from robotd.base.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]


def test_shipped_default_file_equals_code_defaults_but_for_the_services_own_choices():
    # The service on the robot localises over mapped ground (weeks over the same rooms);
    # the code's default keeps every keyframe (the demo, the paper's experiment).
    shipped = load_config(REPO / "systemd" / "robotd.toml")
    assert shipped.pose_graph.localise_mapped and not Config().pose_graph.localise_mapped
    assert shipped == replace(Config(), "pose_graph", localise_mapped=True)


def test_values_are_read_and_converted(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('[floor_camera]\nfps = 15\ndistortion = [0.1, 0, 0, 0, 0]\n[base]\nport = "loop://"\n')
    cfg = load_config(f)
    assert cfg.floor_camera.fps == 15.0 and isinstance(cfg.floor_camera.fps, float)
    assert cfg.floor_camera.distortion == (0.1, 0.0, 0.0, 0.0, 0.0)
    assert cfg.base.port == "loop://"
    assert cfg.robot == Config().robot


@pytest.mark.parametrize("toml, message", [
    ("[floor_camera]\nfsp = 30\n", "unknown key [floor_camera] fsp"),
    ("[camera]\nfps = 30\n", "unknown section [camera]"),
    ("[floor_camera]\nfps = -1\n", "[floor_camera] fps: -1.0 is below the minimum"),
    ("[floor_camera]\nfps = \"fast\"\n", "[floor_camera] fps: expected a number"),
    ("[base]\nbaudrate = 115200.5\n", "[base] baudrate: expected an integer"),
    ("[base]\ndriver = \"roomba\"\n", "[base] driver: 'roomba' is not one of"),
    ("[floor_camera]\ndistortion = [0.1, 0.2]\n", "[floor_camera] distortion: expected 5 numbers"),
    ("[floor_camera]\ncx_px = 700.0\n", "principal point must lie inside the image"),
    ("[odometry]\nwheel_rounding = true\n", "[odometry] wheel_rounding: works only with wheel_increments"),
    ("[odometry]\nslip_event_rate_hz = 0.3\n", "[odometry] slip_event_rate_hz: works only with slip_gate_sigma > 0"),
    ("[odometry]\nedge_floor_m = 0\n", "[odometry] edge_floor_m: 0.0 is below the minimum"),
    ("[forward_detector]\nmax_deferred_tests = -1\n", "[forward_detector] max_deferred_tests: -1 is below the minimum"),
    ("[forward_detector]\nchecks_per_keyframe = -1\n", "[forward_detector] checks_per_keyframe: -1 is below the minimum"),
    ("[forward_detector]\nchecks_per_keyframe = 1.5\n", "[forward_detector] checks_per_keyframe"),
    ("[odometry]\nslip_event_duration_s = -0.1\n", "[odometry] slip_event_duration_s: -0.1 is below the minimum"),
    ("[pose_graph]\nscale_wear = 0.005\n", "[pose_graph] scale_wear: works only with odometry_model"),
    ("[pose_graph]\nscale_wear_gyro = 0.001\n", "[pose_graph] scale_wear_gyro: works only with odometry_model"),
    ("[keyframes]\ndistance_m = nan\n", "[keyframes] distance_m: must be finite"),
    ("robot = 3\n", "[robot] must be a table"),
    ("[recording]\nimage_format = \"webp\"\n", "[recording] image_format: 'webp' is not one of"),
    ("[visual_odometry]\nlive_pose = \"graph\"\n", "[visual_odometry] live_pose: 'graph' is not one of"),
    ("[recording]\njpeg_quality = 0\n", "[recording] jpeg_quality: 0 is below the minimum"),
    ("[recording]\npng_compression = 10\n", "[recording] png_compression: 10 is above the maximum"),
])
def test_bad_values_name_the_key(tmp_path, toml, message):
    f = tmp_path / "c.toml"
    f.write_text(toml)
    with pytest.raises(ConfigError) as err:
        load_config(f)
    assert message in str(err.value)


def test_broken_toml_and_missing_file(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("[base\nport = 1\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(f)
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "missing.toml")


def test_round_trip_through_toml_and_replace():
    cfg = replace(Config(), "keyframes", distance_m=0.2)
    assert cfg.keyframes.distance_m == 0.2
    import tomllib
    assert config_from_dict(tomllib.loads(to_toml(cfg))) == cfg
    with pytest.raises(ConfigError, match=r"\[keyframes\] distance_m"):
        replace(cfg, "keyframes", distance_m=-3.0)


def test_visual_odometry_section(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('[visual_odometry]\nenabled = true\nrole = "vision_only"\nmin_inliers = 12\n')
    vo = load_config(f).visual_odometry
    assert (vo.enabled, vo.role, vo.min_inliers, vo.ransac_threshold_m) == (True, "vision_only", 12, 0.003)
    f.write_text('[visual_odometry]\nrole = "wheels"\n')
    with pytest.raises(ConfigError, match=r"\[visual_odometry\] role"):
        load_config(f)
    f.write_text('[visual_odometry]\nmin_inliers = 2\n')
    with pytest.raises(ConfigError, match=r"\[visual_odometry\] min_inliers"):
        load_config(f)


def test_the_shipped_service_config_is_generated_from_the_definitions(tmp_path):
    """systemd/robotd.toml is `robotd config default --service`: every key with its
    description, unit, range and liveness from the metadata, the defaults but for the
    service's stated choices, so the file cannot drift from the code."""
    from robotd.base.configfile import SERVICE_CHOICES, commented_toml, service_config

    path = REPO / "systemd" / "robotd.toml"
    assert path.read_text() == commented_toml(service=True), (
        "systemd/robotd.toml is out of date: robotd config default --service > systemd/robotd.toml")
    assert load_config(path) == service_config()
    default = commented_toml()
    (tmp_path / "d.toml").write_text(default)
    assert load_config(tmp_path / "d.toml") == Config()
    # The two texts differ in their header and the service's choices only.
    differing = {line for line in set(path.read_text().splitlines()) ^ set(default.splitlines())
                 if not line.startswith("#")}
    assert differing == {f"{key} = {str(value).lower()}" for (_, key), value in SERVICE_CHOICES.items()} | {
        f"{key} = {str(getattr(getattr(Config(), sec), key)).lower()}" for (sec, key) in SERVICE_CHOICES}


def test_config_default_is_a_commented_file_that_loads_as_the_defaults(tmp_path):
    from robotd.base.config import Config
    from robotd.base.configfile import commented_toml, load_config

    text = commented_toml()
    (tmp_path / "d.toml").write_text(text)
    assert load_config(tmp_path / "d.toml") == Config()
    assert "# wheel radius (0.005..1 m)\nwheel_radius_m = 0.035\n" in text
    assert "# how often STATUS is sent to systemd and logged (0.1..3600 s); reload applies it live\n" in text
    driver = {f.name: f for f in dataclasses.fields(Config().base)}["driver"]
    choices = ", ".join(map(repr, driver.metadata["choices"]))
    assert f"(one of {choices})\ndriver = \"kobuki\"" in text
