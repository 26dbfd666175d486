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

With ``--late-vo``, floor visual odometry steps are added: a keyframe every
``--vo-every`` feedback packets, its step the true motion since the previous keyframe plus
noise drawn from the covariance handed over with it (so the steps are exactly as good as
they claim). The fused filter (``vo_twin``, as the daemon builds it) gets them at once, or
late by a random 0 to ``--vo-late-ms`` (the pipeline's latency), or late without the
journal that lets it go back to the frame's time (the filter before 128adcb). Reported:
the errors of each (the late one must equal the immediate one bit for bit), the steps the
filter's gate refused, and the CPU time of each against the filter without visual steps
(the baseline, timed in the same run).

Run: ``.venv/bin/python bench/bench_odometry.py [--route office] [--seeds 5]
[--yaw-source raw_gyro] [--repeats 3] [--late-vo] [--out bench/results/odometry.json]``.
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

from robotd.base.geometry import between
from robotd.base.messages import WheelTicks, YawRate
from robotd.evaluation.metrics import odometry_errors
from robotd.odometry.ekf import EkfParams
from robotd.odometry.fusion import OdometryFilter
from robotd.odometry.kinematics import WheelOdometry
from sim.emulators.kobuki import KobukiFeedback, simulate_kobuki
from sim.route import ROUTES, MotionLimits, build_route, plan_motion
from sim.sensors import BaseSensorParams

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "odometry.json"
METRICS = ("end_position_error_m", "end_heading_error_deg", "max_drift_per_100m_m",
           "end_drift_per_100m_m", "ape_origin_rmse_m")


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


VO_SIGMA = (0.0005, 0.0005, 0.001)  # m, m, rad: one synthetic visual step's noise


def run_with_vo(msgs: list[WheelTicks | YawRate], stream: KobukiFeedback, every: int,
                late_max: int, journal: bool, seed: int) -> tuple[np.ndarray, OdometryFilter]:
    """The fused filter (``vo_twin``) with a synthetic visual step at every ``every``-th
    wheel message, handed over ``0..late_max`` wheel messages after its frame (uniform,
    in keyframe order); ``journal=False`` applies late steps to the current state (no
    going back). Poses ``(N, 3)`` after each wheel message (the live output), the filter."""
    rng = np.random.default_rng(1000 + seed)  # the steps' noise: the same whatever the latency
    rng_late = np.random.default_rng(2000 + seed)
    f = OdometryFilter(params=EkfParams(), vo_twin=True)
    if not journal:
        f._journal = None  # the filter as it was before the journal
    cov = np.diag(np.square(VO_SIGMA))
    due: list[tuple[int, int, int | None, np.ndarray | None]] = []
    prev: tuple[int, int] | None = None  # (wheel index, stamp) of the last keyframe
    out = []
    k = -1
    for msg in msgs:
        if not isinstance(msg, WheelTicks):
            f.on_yaw_rate(msg)
            continue
        k += 1
        f.on_wheels(msg)
        if k % every == every - 1:
            delta = None
            if prev is not None:
                delta = between(stream.true_pose[prev[0]], stream.true_pose[k]) + rng.normal(0.0, VO_SIGMA)
            at = max(k + int(rng_late.integers(0, late_max + 1)), due[-1][0] if due else 0)
            due.append((at, int(msg.stamp_ns), None if prev is None else prev[1], delta))
            prev = (k, int(msg.stamp_ns))
        while due and due[0][0] <= k:
            _, t, t_prev, delta = due.pop(0)
            f.on_visual_odometry(t, t_prev, delta, None if delta is None else cov)
        p = f.pose()
        out.append((p.x_m, p.y_m, p.yaw_rad))
    for _, t, t_prev, delta in due:  # steps still pending at the end: the last pose gets them
        f.on_visual_odometry(t, t_prev, delta, None if delta is None else cov)
    p = f.pose()
    out[-1] = (p.x_m, p.y_m, p.yaw_rad)
    return np.asarray(out), f


def evaluate_late_vo(stream: KobukiFeedback, yaw_source: str, every: int, late_max: int,
                     seed: int) -> dict[str, Any]:
    """Errors of the fused filter given visual steps at once, late, and late without the
    journal; bit-for-bit agreement of the first two."""
    msgs = stream.messages(yaw_source)
    res: dict[str, Any] = {}
    poses = {}
    for name, late, journal in (("vo_at_once", 0, True), ("vo_late", late_max, True),
                                ("vo_late_no_journal", late_max, False)):
        est, f = run_with_vo(msgs, stream, every, late, journal, seed)
        poses[name] = est
        res[name] = {**odometry_errors(stream.true_pose, est).as_dict(),
                     "vo_fused": f.counters.vo_fused, "vo_rejected": f.counters.vo_rejected}
    d = poses["vo_late"][-1] - poses["vo_at_once"][-1]
    d[2] = (d[2] + np.pi) % (2 * np.pi) - np.pi
    res["late_minus_at_once_max_abs"] = float(np.abs(d).max())
    return res


def evaluate_seed(stream: KobukiFeedback, yaw_source: str) -> dict[str, Any]:
    """Errors of both estimators on one simulated run."""
    msgs = stream.messages(yaw_source)
    wheels = [m for m in msgs if isinstance(m, WheelTicks)]
    wheel = run_wheel_only(wheels)
    fused, f = run_fused(msgs)
    e = stream.sensors.errors
    return {
        "drawn_errors": dataclasses.asdict(e),
        "wheel_only": odometry_errors(stream.true_pose, wheel).as_dict(),
        "fused": odometry_errors(stream.true_pose, fused).as_dict(),
        "fused_bias_estimate_degps": float(np.degrees(f.state.gyro_bias_radps)),
        "fused_yaw_sigma_deg": float(np.degrees(np.sqrt(f.pose().covariance[2, 2]))),
        "filter_counters": dataclasses.asdict(f.counters),
    }


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--route", default="office", choices=sorted(ROUTES))
    ap.add_argument("--seeds", type=int, default=5, help="number of seeds (0, 1, ...)")
    ap.add_argument("--yaw-source", default="raw_gyro",
                    choices=("raw_gyro", "raw_gyro_samples", "inertial"),
                    help="which gyro reading feeds the EKF (raw_gyro is the config default)")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats for the throughput")
    ap.add_argument("--late-vo", action="store_true",
                    help="add synthetic visual steps, at once and late (see the module text)")
    ap.add_argument("--vo-every", type=int, default=6,
                    help="a keyframe every this many feedback packets (6 = 8 Hz, as the demo)")
    ap.add_argument("--vo-late-ms", type=float, default=500.0,
                    help="largest latency of a visual step, ms (the demo: 53 median, 527 max)")
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
        if args.late_vo:
            late_max = round(args.vo_late_ms / 20.0)  # feedback packets are 20 ms apart
            per_seed[-1]["late_vo"] = evaluate_late_vo(stream, args.yaw_source, args.vo_every,
                                                       late_max, seed)

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
                 "end drift m/100m", "APE RMS anchored m", "errors drawn"], rows)

    late_vo_timing = None
    if args.late_vo:
        print()
        vrows = []
        names = ("vo_at_once", "vo_late", "vo_late_no_journal")
        for r in per_seed:
            lv = r["late_vo"]
            for name in names:
                m = lv[name]
                vrows.append([r["seed"], name.replace("_", " "), round(m["end_position_error_m"], 3),
                              round(m["end_heading_error_deg"], 2), round(m["ape_origin_rmse_m"], 3),
                              f"{m['vo_fused']} / {m['vo_rejected']}"])
            vrows.append([r["seed"], "late - at once (max abs)", f"{lv['late_minus_at_once_max_abs']:.1e}",
                          "", "", ""])
        print_table(["seed", "fused filter", "end pos err m", "end hdg err deg", "APE RMS anchored m",
                     "steps fused / refused"], vrows)
        msgs0 = streams[0].messages(args.yaw_source)
        late_max = round(args.vo_late_ms / 20.0)
        t_none = time_repeats(lambda: run_fused(msgs0), repeats=args.repeats, warmup=1)
        t_once = time_repeats(lambda: run_with_vo(msgs0, streams[0], args.vo_every, 0, True, 0),
                              repeats=args.repeats, warmup=1)
        t_late = time_repeats(lambda: run_with_vo(msgs0, streams[0], args.vo_every, late_max, True, 0),
                              repeats=args.repeats, warmup=1)
        t_old = time_repeats(lambda: run_with_vo(msgs0, streams[0], args.vo_every, late_max, False, 0),
                             repeats=args.repeats, warmup=1)
        late_vo_timing = {"no_vo": t_none, "vo_at_once": t_once, "vo_late": t_late,
                          "vo_late_no_journal": t_old}
        print()
        print_table(["filter (seed 0)", "median s", "IQR s", "x the filter without VO"], [
            [n, round(t["median_s"], 2), round(t["iqr_s"], 2), round(t["median_s"] / t_none["median_s"], 2)]
            for n, t in (("no visual steps (baseline)", t_none), ("VO at once", t_once),
                         ("VO late, journal", t_late), ("VO late, no journal", t_old))])

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
                 "repeats": args.repeats, "late_vo": args.late_vo, "vo_every": args.vo_every,
                 "vo_late_ms": args.vo_late_ms},
        "route": {"name": args.route, "length_m": motion.length_m, "duration_s": motion.duration_s},
        "limits": dataclasses.asdict(limits),
        "sensor_params": dataclasses.asdict(sensor_params),
        "ekf_params": dataclasses.asdict(EkfParams()),
        "per_seed": per_seed,
        "median": median,
        "timing": timing,
        "late_vo_timing": late_vo_timing,
        "vo_sigma": VO_SIGMA if args.late_vo else None,
    }
    path = write_json(args.out, payload)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
