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


@pytest.mark.parametrize("args, message", [
    (["--calibration", "cal{seed}.yml", "--write-calibration", "out{seed}.yml"], "--write-calibration needs"),
    (["--synthetic-reference", "calibration", "--write-calibration", "out.yml"], "--write-calibration needs"),
    (["--calibration", "cal{seed}.yml", "--write-slip", "out{seed}.yml"], "--write-slip needs"),
    (["--synthetic-reference", "calibration", "--write-slip", "out.yml"], "--write-slip needs"),
    (["--calibration", "cal{seed}.yml", "--drive-seeds", "11"], "--drive-seeds needs --synthetic-reference"),
    (["--synthetic-reference", "figure8", "--seeds", "0,1", "--drive-seeds", "11"],
     "--drive-seeds gives 1 drive seeds for 2 seeds"),
])
def test_options_refused_without_what_they_need(args, message, tmp_path, monkeypatch, capsys):
    """``--write-calibration`` and ``--write-slip`` need the fit alone and a seed pattern;
    ``--drive-seeds`` needs the fit alone and one drive seed per seed: exit 2, the reason on
    stderr, nothing written."""
    from bench.bench_odometry_calibration import main

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(args + ["--out", str(tmp_path / "o.json")])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_the_fit_alone_on_a_recorded_drive_reads_that_very_drive():
    """``--drive-seeds``: the wheel ticks, yaw rates and truth the virtual robot of ``robotd
    record --virtual --seed 12 --base-seed 1`` plays, as the Kobuki driver reads them."""
    import numpy as np

    from bench.bench_odometry_calibration import recorded_drive
    from calibration.odometry import unwrapped_angles
    from robotd.base.camera import FloorCameraModel
    from robotd.base.clock import ManualClock
    from sim.robot import VirtualRobot, VirtualRobotSettings
    from sim.sensors import BaseSensorParams, draw_errors

    p = BaseSensorParams()
    settings = VirtualRobotSettings(route="figure8", seed=12, base_seed=1, duration_s=4.0)
    with VirtualRobot(settings, FloorCameraModel.default(), ManualClock()) as robot:
        fb = robot.base.feedback
        drive, _streams = recorded_drive(robot.motion, p, draw_errors(p, np.random.default_rng(1)), 12, 0.0, 0.0, 0)
    np.testing.assert_array_equal(drive.wheel_stamp_ns, fb.stamp_ns)
    ticks = np.column_stack([fb.left_ticks, fb.right_ticks])
    np.testing.assert_array_equal(drive.wheel_angle_rad, unwrapped_angles(ticks, p.drive.ticks_per_rev))
    # one yaw rate per packet with raw gyro samples, their mean (in the driver's digits)
    has = fb.gyro_count > 0
    assert len(drive.gyro_radps) == int(has.sum())
    z = np.where(np.arange(fb.gyro_digits.shape[1])[None, :] < fb.gyro_count[:, None], fb.gyro_digits[:, :, 2], 0)
    np.testing.assert_allclose(drive.gyro_radps, np.deg2rad(z.sum(axis=1)[has] / fb.gyro_count[has] * 0.00875),
                               rtol=1e-12, atol=1e-15)
    # the reference: the true poses at wheel packets, without noise here
    rows = np.searchsorted(fb.stamp_ns, drive.ref_stamp_ns)
    np.testing.assert_array_equal(drive.ref_pose, fb.true_pose[rows])
    assert len(drive.ref_stamp_ns) > 5 and drive.ref_stamp_ns[0] == fb.stamp_ns[0]


def test_write_slip_adds_the_slip_events_and_a_missing_density_and_keeps_the_rest(tmp_path):
    """The slip events always; the wheel slip density only into a file that holds none (a
    density from the file's own drive is kept); geometry, noise model and loops kept."""
    from bench.bench_odometry_calibration import write_slip
    from robotd.app.demo import shipped_calibration
    from robotd.io.calibfile import read_calibration, write_calibration

    shipped = read_calibration(shipped_calibration())
    # A file from before the slip fit: the shipped one without its density and slip events.
    ship = dataclasses.replace(shipped, odometry=dataclasses.replace(
        shipped.odometry, wheel_noise_m_sqrt_m=0.0, slip_event_rate_hz=None, slip_event_duration_s=None,
        slip_event_rate_sigma_hz=None, slip_event_duration_sigma_s=None))
    assert not ship.odometry.has_slip_events
    fitted = dataclasses.replace(ship.odometry, wheel_noise_m_sqrt_m=5e-4, wheel_base_m=0.3, slip_event_rate_hz=0.2,
                                 slip_event_duration_s=0.19, slip_event_rate_sigma_hz=0.05,
                                 slip_event_duration_sigma_s=0.02)
    path = tmp_path / "seed1.yml"
    write_calibration(path, ship)
    write_slip(path, fitted)
    got = read_calibration(path)
    assert got.odometry == dataclasses.replace(fitted, wheel_base_m=ship.odometry.wheel_base_m)
    assert got.loop == ship.loop
    own = tmp_path / "seed3.yml"
    write_calibration(own, dataclasses.replace(ship, odometry=dataclasses.replace(ship.odometry,
                                                                                  wheel_noise_m_sqrt_m=4e-4)))
    write_slip(own, fitted)
    assert read_calibration(own).odometry.wheel_noise_m_sqrt_m == 4e-4
    assert read_calibration(own).odometry.slip_event_rate_hz == 0.2
