"""bench_nees: the split of the single edges at a start or a stop, on edges whose lag is known; one
interval decomposed by kind and component; the scale prior's wear."""

from __future__ import annotations

import numpy as np
import pytest

from bench.bench_nees import speed_change_edges


def _straight_edges(speeds: np.ndarray, tau_s: float) -> dict:
    """Keyframes 5 cm apart on the x axis at ``speeds``; each edge measures its length
    short by ``tau_s`` times the speed gained over it (a pose trailing the truth by tau)."""
    n = len(speeds)
    truth = np.zeros((n, 3))
    truth[:, 0] = 0.05 * np.arange(n)
    dv = np.diff(speeds)
    delta = np.zeros((n - 1, 3))
    delta[:, 0] = 0.05 - tau_s * dv
    cov = np.tile(np.diag([1e-6, 1e-6, 1e-6]), (n - 1, 1, 1))
    return {"delta": delta, "cov": cov, "truth": truth, "speed_mps": speeds}


def test_the_lag_of_the_edges_across_a_speed_change_is_recovered():
    speeds = np.array([0.0, 0.2, 0.4, 0.4, 0.4, 0.4, 0.1, 0.0, 0.0])
    out = speed_change_edges(_straight_edges(speeds, tau_s=0.007))
    assert out["edges"] == 4 and out["others"] == 4  # |dv| 0.2, 0.2, 0.3, 0.1 against 0
    assert out["tau_ms"] == pytest.approx(7.0, rel=1e-9)
    assert out["others_nees"] == pytest.approx(0.0, abs=1e-12)
    # the errors are tau * dv = 1.4, 1.4, 2.1, 0.7 mm under a 1 mm sigma: NEES e^2 / 1e-6
    assert out["nees"] == pytest.approx(np.mean(np.square([1.4, 1.4, 2.1, 0.7])), rel=1e-6)
    assert out["nees_position"] == pytest.approx(out["nees"], rel=1e-9)


def test_a_leading_pose_gives_a_negative_lag():
    speeds = np.array([0.0, 0.3, 0.3, 0.0])
    assert speed_change_edges(_straight_edges(speeds, tau_s=-0.004))["tau_ms"] == pytest.approx(-4.0, rel=1e-9)


def _calibration_file(path, left_m: float, right_m: float, base_m: float, gyro_scale: float) -> None:
    from robotd.io.calibfile import CalibrationFile, OdometryModel, write_calibration

    write_calibration(path, CalibrationFile(odometry=OdometryModel(
        wheel_radius_left_m=left_m, wheel_radius_right_m=right_m, wheel_base_m=base_m, gyro_scale=gyro_scale,
        gyro_bias_radps=0.0, gyro_noise_radps_sqrt_hz=5e-4, wheel_noise_m_sqrt_m=0.0,
        wheel_radius_left_sigma_m=3.5e-6, wheel_radius_right_sigma_m=3.5e-6, wheel_base_sigma_m=2.3e-4,
        gyro_scale_sigma=1e-4, gyro_bias_sigma_radps=1e-4)))


def test_a_calibration_is_measured_against_the_base_it_was_made_for(tmp_path):
    from types import SimpleNamespace

    from bench.bench_nees import geometry_errors
    from sim.sensors import BaseSensorParams

    d = BaseSensorParams().drive
    r0, b0 = d.wheel_radius_m, d.wheel_base_m
    drawn = SimpleNamespace(left_radius_error=0.002, right_radius_error=-0.001, wheel_base_error=0.015,
                            gyro_scale_error=-0.002)
    # the calibration: left radius right, right 0.1 % long, wheel base 1.5 % short of the truth
    path = tmp_path / "cal.yml"
    _calibration_file(path, r0 * 1.002, r0 * 0.999 * 1.001, b0 * 1.015 * 0.985, 0.998 * 1.0005)
    g = geometry_errors(path, drawn)
    assert g["left_radius"] == pytest.approx(0.0, abs=1e-12)
    assert g["right_radius"] == pytest.approx(0.001, rel=1e-9)
    assert g["distance"] == pytest.approx(0.999 * 0.001 / (1.002 + 0.999), rel=1e-9)
    assert g["wheel_base"] == pytest.approx(-0.015, rel=1e-9)
    assert g["gyro_scale"] == pytest.approx(0.0005, rel=1e-9)
    assert g["wheel_base_sigma"] == pytest.approx(2.3e-4 / (b0 * 1.015 * 0.985), rel=1e-9)


@pytest.mark.parametrize("args, says", [
    (["--own-calibration", "cal.yml"], "needs {seed}"),
    (["--own-calibration", "cal{seed}.yml", "--shipped-geometry"], "takes the place of"),
    (["--own-calibration", "cal{seed}.yml", "--seeds", "2"], "no calibration file"),
    (["--scale-wear", "0.003"], "--scale-wear takes"),
    (["--scale-wear", "0,0.002"], "--scale-wear takes"),
    (["--scale-wear", "a,b"], "--scale-wear takes"),
])
def test_own_calibration_refuses_what_it_cannot_run(args, says, tmp_path, monkeypatch, capsys):
    from bench.bench_nees import main
    from sim.sensors import BaseSensorParams

    monkeypatch.chdir(tmp_path)
    d = BaseSensorParams().drive
    _calibration_file(tmp_path / "cal0.yml", d.wheel_radius_m, d.wheel_radius_m, d.wheel_base_m, 1.0)
    with pytest.raises(SystemExit) as exc:
        main(args + ["--skip-loops", "--out", str(tmp_path / "out.json")])
    assert exc.value.code == 2
    assert says in capsys.readouterr().err
    assert not (tmp_path / "out.json").exists()


def test_an_honest_seeds_spread_is_the_chi_square_of_its_disjoint_chains():
    from bench.bench_nees import honest_spread

    two = honest_spread(2100, 1000)  # two disjoint chains: chi2 with 6 degrees of freedom, halved
    assert two["k"] == 2
    assert two["p5"] == pytest.approx(1.635 / 2, abs=1e-3) and two["p95"] == pytest.approx(12.592 / 2, abs=1e-3)
    assert 0.4 < two["within_2_4"] < 0.5
    assert honest_spread(2100, 1)["within_2_4"] > 0.999
    rng = np.random.default_rng(1)  # the same chance by drawing two chains' chi2(3) and averaging
    means = rng.chisquare(3, (200_000, 2)).mean(axis=1)
    assert np.mean((means >= 2) & (means <= 4)) == pytest.approx(two["within_2_4"], abs=0.005)


def test_the_scale_wear_widens_the_calibrations_own_uncertainty(tmp_path):
    from bench.bench_nees import daemon_scale_sigmas
    from sim.sensors import BaseSensorParams

    d = BaseSensorParams().drive
    path = tmp_path / "cal.yml"
    _calibration_file(path, d.wheel_radius_m, d.wheel_radius_m, d.wheel_base_m, 1.0)
    own_wheel = 0.5 * np.hypot(3.5e-6 / d.wheel_radius_m, 3.5e-6 / d.wheel_radius_m)
    wheel, gyro = daemon_scale_sigmas(path, (0.01, 0.004))
    assert wheel == pytest.approx(np.hypot(own_wheel, 0.01), rel=1e-9)
    assert gyro == pytest.approx(np.hypot(1e-4, 0.004), rel=1e-9)
    wheel, gyro = daemon_scale_sigmas(path)  # the config's defaults, 0.003 and 0.002
    assert (wheel, gyro) == (pytest.approx(np.hypot(own_wheel, 0.003)), pytest.approx(np.hypot(1e-4, 0.002)))


def test_one_interval_is_decomposed_by_kind_and_component(monkeypatch):
    """Four straight edges of 5 cm (errors of 100 um along the track, 4 um across, 100 urad
    in yaw), one turn on the spot, one arc: each kind's RMS errors, the claimed sigmas and
    the NEES of the filter's own covariance and of the edge's (here the same but floored)."""
    import math

    import bench.bench_nees as bn
    from robotd.base.geometry import compose

    steps = [np.array([0.05, 0.0, 0.0])] * 4 + [np.array([0.0, 0.0, 0.17]), np.array([0.05, 0.002, 0.08])]
    truth = [np.zeros(3)]
    for s in steps:
        truth.append(compose(truth[-1], s))
    errs = [np.array([1e-4, 4e-6, 1e-4]), np.array([-1e-4, -4e-6, -1e-4])] * 3
    own = np.diag([1e-8, 1.6e-11, 1e-8])  # the filter's claim: each component's error exactly 1 sigma
    delta = np.array([compose(s, e) for s, e in zip(steps, errs)])  # between(delta, truth step) = -e
    floored = np.diag([1e-8, 1e-8, 1e-8])
    d = {"delta": delta, "cov": np.array([floored] * 6), "truth": np.array(truth), "speed_mps": np.full(7, 0.3)}
    monkeypatch.setattr(bn, "_joint_error", lambda d, i, j: (errs[i], own))
    out = bn.interval_parts(d, (1e-9, 1e-9))
    assert out["straight"]["intervals"] == 4 and out["turn on the spot"]["intervals"] == 1
    assert out["arc"]["intervals"] == 1 and out["all"]["intervals"] == 6
    s = out["straight"]
    assert (s["along_rms"], s["across_rms"], s["yaw_rms"]) == (pytest.approx(100.0), pytest.approx(4.0),
                                                               pytest.approx(100.0))
    assert (s["along_sigma"], s["across_sigma"], s["yaw_sigma"]) == (pytest.approx(100.0), pytest.approx(4.0),
                                                                     pytest.approx(100.0))
    assert s["along_nees"] == pytest.approx(1.0) and s["across_nees"] == pytest.approx(1.0)
    assert s["filter"] == pytest.approx(3.0) and s["filter_position"] == pytest.approx(2.0)
    # the floor: 100 um on the across-track 4 um leaves that component ~0 of its 1
    assert s["edge_position"] == pytest.approx(1.0 + 0.0016, rel=1e-3)
    assert s["across_sigma_edge"] == pytest.approx(100.0)
    assert not math.isnan(out["arc"]["edge_scale"])
