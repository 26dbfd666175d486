"""Wheel-only dead reckoning against the wheel + gyro EKF on the virtual Kobuki.

For each seed the route (default ``office``, about 110 m as in paper 003, Sec. V) is
planned, the base's encoders and gyro are simulated with the error model of
:mod:`sim.sensors` (its defaults: per-seed wheel radius and wheel-base errors,
slip, gyro turn-on bias, bias walk, white noise and scale error, all quantised as the
Kobuki reports them), and the same messages are run through

- (a) :class:`robotd.odometry.kinematics.WheelOdometry`: dead reckoning from the ticks only;
- (b) :class:`robotd.odometry.fusion.OdometryFilter`: the EKF with its default noise model
  (which equals the default ``[odometry]`` configuration).

Both are compared with the true pose at every feedback packet, after anchoring the
estimate's start to the true start (no other alignment). Reported per seed and as the
median over seeds: end position error, end heading error, drift per 100 m (maximum and
end position error over the distance driven) and the RMS absolute trajectory error.
Throughput: messages per second of the EKF against the wheel-only integrator (the
baseline, timed in the same run), median and interquartile range over repeats after a
warm-up.

Run: ``.venv/bin/python bench/bench_odometry.py [--route office] [--seeds 5]
[--yaw-source raw_gyro] [--repeats 3] [--out bench/results/odometry.json]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
from pathlib import Path
from typing import Any

import numpy as np

try:
    from bench.common import machine_info, print_table, time_repeats, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, time_repeats, write_json

from robotd.base.messages import WheelTicks, YawRate
from robotd.io.trajectory import trajectory_errors
from robotd.odometry.ekf import EkfParams
from robotd.odometry.fusion import OdometryFilter
from robotd.odometry.kinematics import WheelOdometry
from sim.emulators.kobuki import KobukiFeedback, simulate_kobuki
from sim.route import ROUTES, MotionLimits, build_route, plan_motion
from sim.sensors import BaseSensorParams

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "odometry.json"
METRICS = ("end_position_error_m", "end_heading_error_deg", "max_drift_per_100m_m",
           "end_drift_per_100m_m", "rmse_position_m")


def run_wheel_only(wheels: list[WheelTicks]) -> np.ndarray:
    """Poses ``(N, 3)`` of the wheel-only integrator after each wheel message."""
    odo = WheelOdometry()
    out = np.empty((len(wheels), 3))
    for k, msg in enumerate(wheels):
        p = odo.update(msg)
        out[k] = (p.x_m, p.y_m, p.yaw_rad)
    return out


def run_fused(msgs: list[WheelTicks | YawRate]) -> tuple[np.ndarray, OdometryFilter]:
    """Poses ``(N, 3)`` of the EKF after each wheel message, and the filter."""
    f = OdometryFilter(params=EkfParams())
    out = []
    for msg in msgs:
        if isinstance(msg, WheelTicks):
            f.on_wheels(msg)
            p = f.pose()
            out.append((p.x_m, p.y_m, p.yaw_rad))
        else:
            f.on_yaw_rate(msg)
    return np.asarray(out), f


def evaluate_seed(stream: KobukiFeedback, yaw_source: str) -> dict[str, Any]:
    """Errors of both estimators on one simulated run."""
    msgs = stream.messages(yaw_source)
    wheels = [m for m in msgs if isinstance(m, WheelTicks)]
    wheel = run_wheel_only(wheels)
    fused, f = run_fused(msgs)
    e = stream.sensors.errors
    return {
        "drawn_errors": dataclasses.asdict(e),
        "wheel_only": trajectory_errors(stream.true_pose, wheel).as_dict(),
        "fused": trajectory_errors(stream.true_pose, fused).as_dict(),
        "fused_bias_estimate_degps": float(np.degrees(f.state.gyro_bias_radps)),
        "fused_yaw_sigma_deg": float(np.degrees(np.sqrt(f.pose().covariance[2, 2]))),
        "filter_counters": dataclasses.asdict(f.counters),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--route", default="office", choices=sorted(ROUTES))
    ap.add_argument("--seeds", type=int, default=5, help="number of seeds (0, 1, ...)")
    ap.add_argument("--yaw-source", default="raw_gyro",
                    choices=("raw_gyro", "raw_gyro_samples", "inertial"),
                    help="which gyro reading feeds the EKF (raw_gyro is the config default)")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats for the throughput")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    if args.seeds < 1:
        ap.error("--seeds must be >= 1")

    limits = MotionLimits()
    sensor_params = BaseSensorParams()
    motion = plan_motion(build_route(args.route), limits)
    print(f"route {args.route}: {motion.length_m:.1f} m in {motion.duration_s:.0f} s, "
          f"{args.seeds} seeds, yaw source {args.yaw_source}")

    per_seed = []
    streams = []
    for seed in range(args.seeds):
        stream = simulate_kobuki(motion, sensor_params, np.random.default_rng(seed))
        streams.append(stream)
        per_seed.append({"seed": seed, **evaluate_seed(stream, args.yaw_source)})

    rows = []
    for r in per_seed:
        e = r["drawn_errors"]
        for method in ("wheel_only", "fused"):
            m = r[method]
            rows.append([r["seed"], method.replace("_", "-"),
                         *(round(m[k], 3) for k in METRICS)])
        rows[-2].append(f"eB {100 * e['wheel_base_error']:+.1f}%  dR-dL "
                        f"{100 * (e['right_radius_error'] - e['left_radius_error']):+.2f}%  "
                        f"bias {np.degrees(e['gyro_bias0_radps']):+.2f} deg/s")
        rows[-1].append("")
    median = {method: {k: statistics.median(r[method][k] for r in per_seed) for k in METRICS}
              for method in ("wheel_only", "fused")}
    for method in ("wheel_only", "fused"):
        rows.append(["median", method.replace("_", "-"),
                     *(round(median[method][k], 3) for k in METRICS), ""])
    print()
    print_table(["seed", "method", "end pos err m", "end hdg err deg", "max drift m/100m",
                 "end drift m/100m", "RMS ATE m", "errors drawn"], rows)

    # Throughput on the first seed's messages: the EKF against the wheel-only baseline.
    msgs = streams[0].messages(args.yaw_source)
    wheels = [m for m in msgs if isinstance(m, WheelTicks)]
    t_wheel = time_repeats(lambda: run_wheel_only(wheels), repeats=args.repeats, warmup=1)
    t_ekf = time_repeats(lambda: run_fused(msgs), repeats=args.repeats, warmup=1)
    rate_wheel = len(wheels) / t_wheel["median_s"]
    rate_ekf = len(msgs) / t_ekf["median_s"]
    timing = {
        "messages_wheel_only": len(wheels), "messages_fused": len(msgs),
        "wheel_only": {**t_wheel, "messages_per_s": rate_wheel},
        "fused": {**t_ekf, "messages_per_s": rate_ekf},
        "fused_to_wheel_only_rate_ratio": rate_ekf / rate_wheel,
        "fused_real_time_factor": motion.duration_s / t_ekf["median_s"],
    }
    print()
    print_table(["method", "messages", "median s", "IQR s", "messages/s", "x real time"], [
        ["wheel-only (baseline)", len(wheels), round(t_wheel["median_s"], 3),
         round(t_wheel["iqr_s"], 3), round(rate_wheel),
         round(motion.duration_s / t_wheel["median_s"])],
        ["fused EKF", len(msgs), round(t_ekf["median_s"], 3), round(t_ekf["iqr_s"], 3),
         round(rate_ekf), round(motion.duration_s / t_ekf["median_s"])],
    ])
    print(f"EKF rate / wheel-only rate: {rate_ekf / rate_wheel:.2f} "
          f"(the base sends {len(msgs) / motion.duration_s:.0f} messages/s)")

    payload = {
        "benchmark": "odometry",
        "machine": machine_info(),
        "args": {"route": args.route, "seeds": args.seeds, "yaw_source": args.yaw_source,
                 "repeats": args.repeats},
        "route": {"name": args.route, "length_m": motion.length_m, "duration_s": motion.duration_s},
        "limits": dataclasses.asdict(limits),
        "sensor_params": dataclasses.asdict(sensor_params),
        "ekf_params": dataclasses.asdict(EkfParams()),
        "per_seed": per_seed,
        "median": median,
        "timing": timing,
    }
    path = write_json(args.out, payload)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
