"""The calibrated odometry model against the simulator's truth and on the office route.

For each seed given a calibration file (``robotd calibrate odometry`` on a calibration
drive of that seed's base: ``robotd record --virtual --route figure8 --seed S --base-seed
N``), two parts:

1. The fitted wheel radii, wheel base and gyro scale against the errors the simulator drew
   for that base (:func:`sim.sensors.draw_errors`, seed N), as relative errors, with the
   fit's own 1-sigma (the targets: radii 0.05 %, wheel base 0.1 %, gyro scale
   0.05 %).
2. The office route (about 110 m) of that seed's base, run through the wheel-only
   integrator and the wheel + gyro filter twice: with the nominal ``[robot]`` geometry
   (the baseline), with the calibrated model and with the simulator's true values (what a
   perfect calibration would give). End position error and RMS position
   error (APE, anchored at the start) against ground truth, and their ratio (wheel-only end error with
   the calibrated model at most a fifth of the nominal one; fused better).

Run: ``.venv/bin/python bench/bench_odometry_calibration.py --calibration '/tmp/cal{seed}.yml'
[--seeds 0,1,2,3,4] [--markdown docs/benchmarks/odometry_calibration.md]``, or
``--synthetic-reference figure8 [--laps 3]`` for the fit alone against the true trajectory
(the route driven that many times), ``--drive-seeds 0,12,13,14,15`` to fit each seed's
recorded drive (``robotd record --virtual --seed S --base-seed N``) as the driver reads it:
the fit alone on the very drive ``robotd calibrate odometry`` was run on. About a minute per seed; ``--full`` is the same (the cost is in making the calibration drives, minutes
each, not here).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

try:
    from bench.common import machine_info, print_table, write_json, write_page
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, write_json, write_page

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from robotd.base.messages import WheelTicks  # noqa: E402
from robotd.io.calibfile import read_calibration  # noqa: E402
from robotd.evaluation.metrics import odometry_errors  # noqa: E402
from robotd.odometry.ekf import EkfParams  # noqa: E402
from robotd.odometry.fusion import OdometryFilter  # noqa: E402
from robotd.odometry.kinematics import DiffDriveParams, WheelOdometry  # noqa: E402
from sim.emulators.kobuki import simulate_kobuki  # noqa: E402
from sim.route import MotionLimits, build_route, plan_motion  # noqa: E402
from sim.sensors import BaseSensorParams, draw_errors  # noqa: E402


def run(msgs: list[Any], drive: DiffDriveParams, gyro_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Wheel-only and fused poses ``(N, 3)`` after each wheel message."""
    wheel = WheelOdometry(drive)
    f = OdometryFilter(drive, EkfParams(), gyro_scale=gyro_scale)
    w_out, f_out = [], []
    for m in msgs:
        if isinstance(m, WheelTicks):
            p = wheel.update(m)
            w_out.append((p.x_m, p.y_m, p.yaw_rad))
            f.on_wheels(m)
            q = f.pose()
            f_out.append((q.x_m, q.y_m, q.yaw_rad))
        else:
            f.on_yaw_rate(m)
    return np.asarray(w_out), np.asarray(f_out)


def repeated_route(route: str, laps: int) -> Any:
    """``route`` driven ``laps`` times over (a closed route: it ends where it starts)."""
    import dataclasses

    r = build_route(route)
    pts = list(r.waypoints_m)
    if laps > 1 and math.dist(pts[0], pts[-1]) > 1e-9:
        raise SystemExit(f"route {route!r} does not end where it starts: no laps")
    return dataclasses.replace(r, waypoints_m=tuple(pts + pts[1:] * (laps - 1)))


def synthetic_model(seed: int, route: str, sigma_m: float, sigma_rad: float, laps: int = 1,
                    drive_seed: int | None = None) -> tuple[Any, dict[str, Any]]:
    """The model fitted to a drive of seed ``seed``'s base along ``route`` (``laps`` times;
    its own seed 100 + seed for the drive's other draws) against the true keyframe poses
    plus white noise (``sigma_m``, ``sigma_rad``): the fit alone, without the pipeline's
    reference. ``drive_seed``: instead the very drive ``robotd record --virtual --seed
    drive_seed --base-seed seed`` makes (its slip, gyro noise and bias walk), read as the
    daemon reads it (the Kobuki driver's wheel ticks and per-packet yaw rates), so the fit
    alone and ``robotd calibrate odometry`` on that recording differ only by the reference.
    Returns the model and the slip events' fit against the simulator's (:func:`slip_truth`)."""
    from calibration.odometry import model_from_fit
    from robotd.odometry.calibration import CalibrationDrive, fit_odometry
    from sim.sensors import simulate_sensors

    p = BaseSensorParams()
    errors = draw_errors(p, np.random.default_rng(seed))
    motion = plan_motion(repeated_route(route, laps), MotionLimits())
    if drive_seed is not None:
        drive, streams = recorded_drive(motion, p, errors, drive_seed, sigma_m, sigma_rad, noise_seed=200 + seed)
        fit = fit_odometry(drive, p.drive.wheel_radius_m, p.drive.wheel_base_m)
        return model_from_fit(fit), slip_truth(fit, streams)
    rng = np.random.default_rng(100 + seed)
    draw_errors(p, rng)  # the drive's own draws follow, as with --base-seed
    s = simulate_sensors(motion, p, errors, rng)
    tp = s.true_pose
    idx = reference_keyframes(tp)
    noise = np.random.default_rng(200 + seed).normal(0, [sigma_m, sigma_m, sigma_rad], (len(idx), 3))
    drive = CalibrationDrive(s.stamp_ns, s.wheel_angle_rad, np.round(s.gyro_t_s * 1e9).astype(np.int64),
                             s.gyro_radps[:, 2], s.stamp_ns[idx], tp[idx] + noise)
    fit = fit_odometry(drive, p.drive.wheel_radius_m, p.drive.wheel_base_m)
    return model_from_fit(fit), slip_truth(fit, s)


def slip_truth(fit: Any, streams: Any | None) -> dict[str, Any]:
    """The slip events' fit (:attr:`~robotd.odometry.calibration.OdometryFit.slip_events`)
    beside the simulator's events of that drive (``streams``: its
    :class:`~sim.sensors.BaseSensorStreams`, None when not known): their count, their RMS
    duration and their count over the fit's time of accelerating or turning (the rate as
    the filter's model uses it), and the fit's errors in its own sigmas."""
    ev = fit.slip_events
    out: dict[str, Any] = {"refused": ev.refused, "events_seen": ev.events_seen,
                           "events_estimated": ev.events_estimated, "demand_s": ev.demand_s,
                           "rate_hz": ev.rate_hz, "rate_sigma_hz": ev.rate_sigma_hz,
                           "duration_s": ev.duration_s, "duration_sigma_s": ev.duration_sigma_s,
                           "ratio_lo": ev.ratio_lo, "ratio_hi": ev.ratio_hi,
                           "wheel_noise_m_sqrt_m": fit.wheel_noise_m_sqrt_m}
    if streams is not None and streams.slip_events > 0:
        d = np.asarray(streams.slip_event_durations_s, float)
        out.update(true_events=int(streams.slip_events), true_duration_s=float(np.sqrt(np.mean(d ** 2))),
                   true_rate_hz=streams.slip_events / ev.demand_s if ev.demand_s > 0 else None,
                   true_slip_noise_m_sqrt_m=float(streams.params.slip_noise_m_per_sqrt_m))
        if not ev.refused:
            out.update(rate_err_sigmas=(ev.rate_hz - out["true_rate_hz"]) / ev.rate_sigma_hz,
                       duration_err_sigmas=(ev.duration_s - out["true_duration_s"]) / ev.duration_sigma_s)
    return out


def reference_keyframes(true_pose: np.ndarray) -> list[int]:
    """Indices of the synthetic reference's keyframes among ``true_pose`` ``(N, 3)``: a new
    one after 0.1 m or 0.1 rad of true motion."""
    idx = [0]
    for k in range(1, len(true_pose)):
        a, b = true_pose[idx[-1]], true_pose[k]
        if math.hypot(b[0] - a[0], b[1] - a[1]) >= 0.1 or abs(math.remainder(b[2] - a[2], 2 * math.pi)) >= 0.1:
            idx.append(k)
    return idx


def recorded_drive(motion: Any, p: BaseSensorParams, errors: Any, drive_seed: int, sigma_m: float,
                   sigma_rad: float, noise_seed: int) -> tuple[Any, Any]:
    """The :class:`~robotd.odometry.calibration.CalibrationDrive` of the virtual robot's
    drive along ``motion`` with seed ``drive_seed`` and the base's ``errors`` (what
    ``robotd record --virtual --seed drive_seed --base-seed N`` draws): the Kobuki driver's
    wheel ticks and yaw rates, the true poses plus white noise (``sigma_m``, ``sigma_rad``;
    generator ``noise_seed``) at :func:`reference_keyframes`, stamped at their wheel packets;
    and the simulator's sensor streams of that drive (its slip events)."""
    from calibration.odometry import unwrapped_angles
    from robotd.base.messages import YawRate
    from robotd.odometry.calibration import CalibrationDrive

    feedback = simulate_kobuki(motion, p, np.random.default_rng(drive_seed), errors=errors)
    msgs = feedback.messages("raw_gyro")
    wheels = np.array([(m.stamp_ns, m.left_ticks, m.right_ticks) for m in msgs if isinstance(m, WheelTicks)],
                      np.int64)
    gyro = [(m.stamp_ns, m.yaw_rate_radps) for m in msgs if isinstance(m, YawRate)]
    tp = feedback.true_pose
    idx = reference_keyframes(tp)
    noise = np.random.default_rng(noise_seed).normal(0, [sigma_m, sigma_m, sigma_rad], (len(idx), 3))
    return CalibrationDrive(wheels[:, 0], unwrapped_angles(wheels[:, 1:], p.drive.ticks_per_rev),
                            np.array([t for t, _ in gyro], np.int64), np.array([w for _, w in gyro], float),
                            feedback.stamp_ns[idx], tp[idx] + noise), feedback.sensors


#: The fields of a fit :func:`write_geometry` puts into the shipped file.
GEOMETRY_FIELDS = ("wheel_radius_left_m", "wheel_radius_right_m", "wheel_base_m", "gyro_scale",
                   "wheel_radius_left_sigma_m", "wheel_radius_right_sigma_m", "wheel_base_sigma_m", "gyro_scale_sigma")


#: The fields of a fit :func:`write_slip` puts into a calibration file.
SLIP_FIELDS = ("wheel_noise_m_sqrt_m", "slip_event_rate_hz", "slip_event_duration_s", "slip_event_rate_sigma_hz",
               "slip_event_duration_sigma_s")


def write_slip(path: Path, model: Any) -> None:
    """The calibration file at ``path`` with ``model``'s slip events (:data:`SLIP_FIELDS`) and
    its wheel slip density where the file holds none (0: a density fitted on the file's own
    drive is kept), everything else of it kept."""
    import dataclasses

    from robotd.io.calibfile import write_calibration

    cal = read_calibration(path)
    if cal.odometry is None:
        raise SystemExit(f"{path}: no odometry model to add the slip to")
    if not model.has_slip_events:
        raise SystemExit(f"{path}: the fit has no slip events to write")
    fields = [k for k in SLIP_FIELDS if k != "wheel_noise_m_sqrt_m" or cal.odometry.wheel_noise_m_sqrt_m == 0.0]
    write_calibration(path, dataclasses.replace(cal, odometry=dataclasses.replace(
        cal.odometry, **{k: getattr(model, k) for k in fields})))


def write_geometry(path: Path, model: Any) -> None:
    """The demo's shipped calibration with ``model``'s wheel radii, wheel base and gyro
    scale and their 1-sigmas (:data:`GEOMETRY_FIELDS`), its noise model kept, at ``path``."""
    import dataclasses

    from robotd.app.demo import shipped_calibration
    from robotd.io.calibfile import write_calibration

    ship_path = shipped_calibration()
    ship = read_calibration(ship_path) if ship_path is not None else None
    if ship is None or ship.odometry is None:
        raise SystemExit("the demo's shipped calibration (with its odometry model) is missing")
    odo = dataclasses.replace(ship.odometry, **{k: getattr(model, k) for k in GEOMETRY_FIELDS})
    write_calibration(path, dataclasses.replace(ship, odometry=odo))


def evaluate(seed: int, calib_path: Path | None, motion: Any, model: Any = None) -> dict[str, Any]:
    p = BaseSensorParams()
    truth = draw_errors(p, np.random.default_rng(seed))
    if model is None:
        model = read_calibration(calib_path).odometry
    if model is None:
        raise SystemExit(f"{calib_path}: no odometry model")
    r0, b0 = p.drive.wheel_radius_m, p.drive.wheel_base_m
    true_l, true_r = r0 * (1 + truth.left_radius_error), r0 * (1 + truth.right_radius_error)
    true_b, true_s = b0 * (1 + truth.wheel_base_error), 1 + truth.gyro_scale_error
    fit = {
        "left_radius_err_pct": 100 * (model.wheel_radius_left_m / true_l - 1),
        "left_radius_sigma_pct": 100 * model.wheel_radius_left_sigma_m / true_l,
        "right_radius_err_pct": 100 * (model.wheel_radius_right_m / true_r - 1),
        "right_radius_sigma_pct": 100 * model.wheel_radius_right_sigma_m / true_r,
        "wheel_base_err_pct": 100 * (model.wheel_base_m / true_b - 1),
        "wheel_base_sigma_pct": 100 * model.wheel_base_sigma_m / true_b,
        "gyro_scale_err_pct": 100 * (model.gyro_scale / true_s - 1),
        "gyro_scale_sigma_pct": 100 * model.gyro_scale_sigma,
        "nominal_left_radius_err_pct": 100 * (r0 / true_l - 1),
        "nominal_wheel_base_err_pct": 100 * (b0 / true_b - 1),
        "nominal_gyro_scale_err_pct": 100 * (1 / true_s - 1),
    }
    stream = simulate_kobuki(motion, p, np.random.default_rng(seed))
    msgs = stream.messages("raw_gyro")
    nominal = DiffDriveParams(wheel_radius_m=r0, wheel_base_m=b0)
    calibrated = DiffDriveParams(wheel_radius_m=r0, wheel_base_m=model.wheel_base_m,
                                 wheel_radius_left_m=model.wheel_radius_left_m,
                                 wheel_radius_right_m=model.wheel_radius_right_m)
    # The simulator's own values: what a perfect calibration would give (the filter's floor).
    true = DiffDriveParams(wheel_radius_m=r0, wheel_base_m=true_b, wheel_radius_left_m=true_l,
                           wheel_radius_right_m=true_r)
    out: dict[str, Any] = {"seed": seed, "calibration": str(calib_path), "fit": fit}
    for name, drive, scale in (("nominal", nominal, 1.0), ("calibrated", calibrated, model.gyro_scale),
                               ("true", true, true_s)):
        wheel, fused = run(msgs, drive, scale)
        out[name] = {"wheel_only": odometry_errors(stream.true_pose, wheel).as_dict(),
                     "fused": odometry_errors(stream.true_pose, fused).as_dict()}
    return out


def write_markdown(path: Path, rows: list[dict[str, Any]], route: str) -> None:
    lines = [
        "# Odometry calibration (generated by bench/bench_odometry_calibration.py --markdown)", "",
        "Calibrations: " + "; ".join(sorted({str(r['calibration']) for r in rows})) + ".", "",
        "Part 1: the fitted model against the simulator's drawn base errors (relative error, the "
        "fit's 1-sigma in brackets; targets: radii 0.05 %, wheel base 0.1 %, gyro scale 0.05 %).", "",
        "| seed | left radius | right radius | wheel base | gyro scale | nominal wheel base off by |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        f = r["fit"]
        lines.append(
            f"| {r['seed']} | {f['left_radius_err_pct']:+.3f} % ({f['left_radius_sigma_pct']:.3f}) | "
            f"{f['right_radius_err_pct']:+.3f} % ({f['right_radius_sigma_pct']:.3f}) | "
            f"{f['wheel_base_err_pct']:+.3f} % ({f['wheel_base_sigma_pct']:.3f}) | "
            f"{f['gyro_scale_err_pct']:+.3f} % ({f['gyro_scale_sigma_pct']:.3f}) | "
            f"{f['nominal_wheel_base_err_pct']:+.2f} % |")
    lines += ["", f"Part 2: the {route} route, nominal model (baseline) against calibrated, same run.", "",
              "| seed | wheel-only end error nominal (m) | calibrated (m) | ratio | true values (m) | "
              "fused end nominal (m) | calibrated (m) | true values (m) | fused APE RMS anchored, nominal (m) | "
              "calibrated (m) | true values (m) |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        n, c, t = r["nominal"], r["calibrated"], r["true"]
        lines.append(
            f"| {r['seed']} | {n['wheel_only']['end_position_error_m']:.3f} | "
            f"{c['wheel_only']['end_position_error_m']:.3f} | "
            f"{c['wheel_only']['end_position_error_m'] / n['wheel_only']['end_position_error_m']:.2f} | "
            f"{t['wheel_only']['end_position_error_m']:.3f} | "
            f"{n['fused']['end_position_error_m']:.3f} | {c['fused']['end_position_error_m']:.3f} | "
            f"{t['fused']['end_position_error_m']:.3f} | "
            f"{n['fused']['ape_origin_rmse_m']:.3f} | {c['fused']['ape_origin_rmse_m']:.3f} | "
            f"{t['fused']['ape_origin_rmse_m']:.3f} |")
    slips = [r for r in rows if r.get("slip_events")]
    if slips:
        lines += ["", "Part 3: the wheel slip events' rate (a second of accelerating or turning, as the filter's "
                  "3-sigma slip test calls it) and RMS duration fitted from the heading windows the fit leaves "
                  "out (`robotd.odometry.slip_events`), against the simulator's events of that drive (their "
                  "count over the same time; in brackets the fit's 1-sigma, in square brackets its error in "
                  "those sigmas), and the wheels' continuous slip density.", "",
                  "| seed | events seen | all, fitted | all, true | rate (/s) | true rate (/s) | RMS duration (s) | "
                  "true RMS (s) | slip density (mm/sqrt(m)) |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in slips:
            e = r["slip_events"]
            if e["refused"]:
                lines.append(f"| {r['seed']} | {e['events_seen']} | refused: {e['refused']} | "
                             f"{e.get('true_events', '')} | | | | | {1e3 * e['wheel_noise_m_sqrt_m']:.3f} |")
                continue
            tr = e.get("true_rate_hz")
            td = e.get("true_duration_s")
            rate = f"{e['rate_hz']:.3f} ({e['rate_sigma_hz']:.3f})" + (f" [{e['rate_err_sigmas']:+.1f}]" if tr else "")
            dur = (f"{e['duration_s']:.3f} ({e['duration_sigma_s']:.3f})"
                   + (f" [{e['duration_err_sigmas']:+.1f}]" if td else ""))
            lines.append(f"| {r['seed']} | {e['events_seen']} | {e['events_estimated']:.1f} | "
                         f"{e.get('true_events', '')} | {rate} | {f'{tr:.3f}' if tr else ''} | {dur} | "
                         f"{f'{td:.3f}' if td else ''} | {1e3 * e['wheel_noise_m_sqrt_m']:.3f} |")
    lines.append("")
    write_page(path, lines)


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calibration", default=None, metavar="PATTERN",
                    help="calibration file of each seed's base, with {seed} in it")
    ap.add_argument("--synthetic-reference", default=None, metavar="ROUTE",
                    help="instead: fit each seed's base on a simulated drive along ROUTE against the "
                         "true poses plus --reference-noise (the fit alone, no pipeline)")
    ap.add_argument("--reference-noise", default="0.0005,0.0005", metavar="M,RAD")
    ap.add_argument("--laps", type=int, default=1, help="with --synthetic-reference: drive the route this many times")
    ap.add_argument("--write-calibration", default=None, metavar="PATTERN",
                    help="with --synthetic-reference: write each seed's fit ({seed} in PATTERN) as a calibration "
                         "file: the demo's shipped file with the fitted wheel radii, wheel base and gyro scale and "
                         "their 1-sigmas (its noise model kept), for bench_nees.py --own-calibration")
    ap.add_argument("--write-slip", default=None, metavar="PATTERN",
                    help="with --synthetic-reference: put each seed's fitted wheel slip density and slip events "
                         "into the existing calibration file ({seed} in PATTERN; the density only where the file "
                         "holds none), the rest of it kept")
    ap.add_argument("--drive-seeds", default=None, metavar="S,S,...",
                    help="with --synthetic-reference: per seed of --seeds, the drive seed of its recorded "
                         "calibration drive (robotd record --virtual --seed S --base-seed N): the fit alone on "
                         "that very drive's wheel and gyro readings, as the driver gives them")
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--route", default="office")
    ap.add_argument("--full", action="store_true", help="the same as the default (see the module text)")
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "odometry_calibration.json")
    ap.add_argument("--markdown", type=Path, default=None)
    args = ap.parse_args(argv)
    motion = plan_motion(build_route(args.route), MotionLimits())
    rows = []
    if (args.calibration is None) == (args.synthetic_reference is None):
        ap.error("give --calibration or --synthetic-reference")
    if args.write_calibration is not None and (args.synthetic_reference is None
                                               or "{seed}" not in args.write_calibration):
        ap.error("--write-calibration needs --synthetic-reference and {seed} in its PATTERN")
    if args.write_slip is not None and (args.synthetic_reference is None or "{seed}" not in args.write_slip):
        ap.error("--write-slip needs --synthetic-reference and {seed} in its PATTERN")
    seeds = [int(s) for s in args.seeds.split(",")]
    drive_seeds: list[int | None] = [None] * len(seeds)
    if args.drive_seeds is not None:
        if args.synthetic_reference is None:
            ap.error("--drive-seeds needs --synthetic-reference")
        drive_seeds = [int(s) for s in args.drive_seeds.split(",")]
        if len(drive_seeds) != len(seeds):
            ap.error(f"--drive-seeds gives {len(drive_seeds)} drive seeds for {len(seeds)} seeds")
    for seed, drive_seed in zip(seeds, drive_seeds):
        if args.synthetic_reference is not None:
            sm, sr = (float(v) for v in args.reference_noise.split(","))
            model, slip = synthetic_model(seed, args.synthetic_reference, sm, sr, args.laps, drive_seed)
            if args.write_calibration is not None:
                write_geometry(Path(args.write_calibration.format(seed=seed)), model)
            if args.write_slip is not None:
                write_slip(Path(args.write_slip.format(seed=seed)), model)
            rows.append(evaluate(seed, None, motion, model))
            rows[-1]["slip_events"] = slip
            laps = f" x {args.laps} laps" if args.laps > 1 else ""
            drive = f", drive seed {drive_seed} (the driver's readings)" if drive_seed is not None else ""
            rows[-1]["calibration"] = (f"synthetic: {args.synthetic_reference}{laps}{drive}, reference noise {sm} m, "
                                       f"{sr} rad")
            rows[-1]["drive_seed"] = drive_seed
            continue
        path = Path(args.calibration.format(seed=seed))
        if not path.is_file():
            print(f"seed {seed}: no calibration file {path}, skipped", file=sys.stderr)
            continue
        rows.append(evaluate(seed, path, motion))
    if not rows:
        print("no calibration file found", file=sys.stderr)
        return 2
    print_table(["seed", "left r %", "right r %", "base %", "gyro scale %", "sigma base %"],
                [[r["seed"], round(r["fit"]["left_radius_err_pct"], 3), round(r["fit"]["right_radius_err_pct"], 3),
                  round(r["fit"]["wheel_base_err_pct"], 3), round(r["fit"]["gyro_scale_err_pct"], 3),
                  round(r["fit"]["wheel_base_sigma_pct"], 3)] for r in rows])
    print()
    print_table(["seed", "wheel end nominal m", "wheel end calib. m", "ratio", "fused end nominal m",
                 "fused end calib. m", "fused APE anchored nominal m", "fused APE anchored calib. m"],
                [[r["seed"], round(r["nominal"]["wheel_only"]["end_position_error_m"], 3),
                  round(r["calibrated"]["wheel_only"]["end_position_error_m"], 3),
                  round(r["calibrated"]["wheel_only"]["end_position_error_m"]
                        / r["nominal"]["wheel_only"]["end_position_error_m"], 2),
                  round(r["nominal"]["fused"]["end_position_error_m"], 3),
                  round(r["calibrated"]["fused"]["end_position_error_m"], 3),
                  round(r["nominal"]["fused"]["ape_origin_rmse_m"], 3),
                  round(r["calibrated"]["fused"]["ape_origin_rmse_m"], 3)] for r in rows])
    slips = [r for r in rows if r.get("slip_events")]
    if slips:
        print()
        print_table(["seed", "seen", "all (fit)", "all (true)", "rate /s", "sigma", "true /s", "RMS s", "sigma",
                     "true RMS s"],
                    [[r["seed"], r["slip_events"]["events_seen"], round(r["slip_events"]["events_estimated"], 1),
                      r["slip_events"].get("true_events"), round(r["slip_events"]["rate_hz"], 3),
                      round(r["slip_events"]["rate_sigma_hz"], 3),
                      round(r["slip_events"]["true_rate_hz"], 3) if r["slip_events"].get("true_rate_hz") else None,
                      round(r["slip_events"]["duration_s"], 3), round(r["slip_events"]["duration_sigma_s"], 3),
                      round(r["slip_events"]["true_duration_s"], 3) if r["slip_events"].get("true_duration_s")
                      else None] for r in slips])
    if args.markdown is not None:
        write_markdown(args.markdown, rows, args.route)
    path = write_json(args.out, {"machine": machine_info(), "route": args.route, "seeds": rows})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
