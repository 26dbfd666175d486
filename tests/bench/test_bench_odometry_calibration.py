"""bench_odometry_calibration's calibration files of the fit alone."""

from __future__ import annotations

import dataclasses

import pytest


def test_the_fit_alones_file_is_the_shipped_one_with_the_fitted_geometry(tmp_path):
    from bench.bench_odometry_calibration import GEOMETRY_FIELDS, write_geometry
    from robotd.app.demo import shipped_calibration
    from robotd.io.calibfile import read_calibration

    ship = read_calibration(shipped_calibration())
    fitted = dataclasses.replace(ship.odometry, wheel_radius_left_m=0.0349, wheel_radius_right_m=0.0351,
                                 wheel_base_m=0.2261, gyro_scale=0.998, wheel_radius_left_sigma_m=9e-6,
                                 wheel_radius_right_sigma_m=8e-6, wheel_base_sigma_m=1.3e-4, gyro_scale_sigma=1.1e-4,
                                 accel_noise_mps2_sqrt_hz=0.5, angular_accel_noise_radps2_sqrt_hz=0.5)
    path = tmp_path / "seed1.yml"
    write_geometry(path, fitted)
    got = read_calibration(path)
    for k in GEOMETRY_FIELDS:
        assert getattr(got.odometry, k) == pytest.approx(getattr(fitted, k), rel=1e-12)
    # the noise model and everything else stay the shipped file's
    assert got.odometry.accel_noise_mps2_sqrt_hz == pytest.approx(ship.odometry.accel_noise_mps2_sqrt_hz, rel=1e-12)
    assert got.loop == ship.loop and got.mount == ship.mount


@pytest.mark.parametrize("args", [
    ["--calibration", "cal{seed}.yml", "--write-calibration", "out{seed}.yml"],
    ["--synthetic-reference", "calibration", "--write-calibration", "out.yml"],
])
def test_write_calibration_refuses_without_the_fit_alone_or_a_seed(args, tmp_path, monkeypatch, capsys):
    from bench.bench_odometry_calibration import main

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(args + ["--out", str(tmp_path / "o.json")])
    assert exc.value.code == 2
    assert "--write-calibration needs" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
