"""The CAN base path against the Kobuki path on the same route and sensors.

The virtual robot's sensor streams for a seed (the same draws, so the same wheel and gyro
errors) are sent two ways: as Kobuki feedback packets read by the Kobuki driver over a
pty, and as CAN frames on a python-can virtual bus read by the CAN driver
(:mod:`sim.emulators.can`): the generic ``diff_drive`` DBC (wheel angles and a gyro), the
same with faults injected (:meth:`sim.emulators.can.CanFaults.standard`: a flood of
unknown ids, a bus-off with 0.2 s of silence, the wheels frame gone for 0.3 s, 20 frames
cut short), and ``odrive_cansimple`` (one ODrive per wheel, no gyro: wheel-only). Each
message stream goes through the wheel + gyro EKF (:class:`robotd.odometry.fusion.
OdometryFilter`, default noise model) and is compared with the true pose at each wheel
message's stamp, the start anchored to the truth: end position error and RMS APE
(:func:`robotd.evaluation.metrics.odometry_errors`) of the fused and of the wheel-only odometry. Also reported: frames counted by the CAN driver,
faults injected against the driver's counters, and decode throughput (frames/s of the
driver on the virtual bus, against the Kobuki driver's packets/s in the same run).

With ``--e2e`` it also runs ``robotd demo`` (the whole daemon: camera, keyframes, map)
with ``--base kobuki``, ``--base can`` and ``--base can --can-faults`` on ``--e2e-route``
for ``--e2e-duration`` s, and reports the demo's own summary figures.

Run: ``.venv/bin/python bench/bench_can.py [--route office] [--seeds 3] [--e2e]
[--e2e-route square] [--e2e-duration 60] [--out bench/results/can.json]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

try:
    from bench.common import machine_info, print_table, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, write_json

from robotd.base.messages import BaseStatus, WheelTicks, YawRate
from robotd.evaluation.metrics import odometry_errors
from robotd.odometry.ekf import EkfParams
from robotd.odometry.fusion import OdometryFilter
from robotd.odometry.kinematics import WheelOdometry
from sim.emulators.can import CanFaults, driver_messages, encode_can
from sim.emulators.kobuki import simulate_kobuki
from sim.route import ROUTES, MotionLimits, build_route, plan_motion
from sim.sensors import BaseSensorParams

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "can.json"
PATHS = ("kobuki", "can diff_drive", "can diff_drive + faults", "can odrive (no gyro)")


def odometry_figures(msgs: list[Any], motion: Any) -> dict[str, Any]:
    """Fused (EKF) and wheel-only errors of one message stream against the truth."""
    f = OdometryFilter(params=EkfParams())
    w = WheelOdometry()
    stamps, fused, wheel = [], [], []
    for m in msgs:
        if isinstance(m, WheelTicks):
            f.on_wheels(m)
            p, q = f.pose(), w.update(m)
            stamps.append(m.stamp_ns)
            fused.append((p.x_m, p.y_m, p.yaw_rad))
            wheel.append((q.x_m, q.y_m, q.yaw_rad))
        elif isinstance(m, YawRate):
            f.on_yaw_rate(m)
    truth = motion.pose_at(np.asarray(stamps) / 1e9)
    ef = odometry_errors(truth, np.asarray(fused))
    ew = odometry_errors(truth, np.asarray(wheel))
    return {"wheel_msgs": len(stamps), "yaw_msgs": sum(isinstance(m, YawRate) for m in msgs),
            "fused_end_m": ef.end_position_error_m, "fused_ape_origin_m": ef.ape_origin_rmse_m,
            "fused_end_heading_deg": ef.end_heading_error_deg,
            "wheel_end_m": ew.end_position_error_m, "wheel_ape_origin_m": ew.ape_origin_rmse_m,
            "degraded_changes": [(m.degraded, m.detail) for m in msgs if isinstance(m, BaseStatus)]}


def run_seed(motion: Any, seed: int) -> dict[str, Any]:
    stream = simulate_kobuki(motion, BaseSensorParams(), np.random.default_rng(seed))
    out: dict[str, Any] = {"seed": seed}
    t0 = time.perf_counter()
    msgs = stream.messages("raw_gyro")
    kob_s = time.perf_counter() - t0
    out["kobuki"] = {**odometry_figures(msgs, motion), "packets": len(stream.t_s),
                     "packets_per_s": len(stream.t_s) / kob_s}
    variants = (("can diff_drive", "diff_drive", None),
                ("can diff_drive + faults", "diff_drive", CanFaults.standard(motion.duration_s)),
                ("can odrive (no gyro)", "odrive_cansimple", None))
    for name, convention, faults in variants:
        frames = encode_can(stream.sensors, convention, np.random.default_rng(seed + 3), faults)
        t0 = time.perf_counter()
        msgs, st = driver_messages(frames, stream.sensors)
        dt = time.perf_counter() - t0
        out[name] = {**odometry_figures(msgs, motion), "frames_sent": len(frames.t_s),
                     "frames_per_s": len(frames.t_s) / dt, "injected": frames.injected,
                     "driver": {k: v for k, v in st.items() if k != "name"}}
    return out


def run_e2e(route: str, duration_s: float, seed: int) -> dict[str, Any]:
    """The whole daemon on the virtual robot, three ways; the odometry judged here from the
    demo's trajectory files against the route's truth (:mod:`robotd.evaluation.metrics`)."""
    from robotd.app.demo import run_demo, shipped_calibration
    from robotd.base.config import Config, replace
    from robotd.io.trajectory import read_tum

    cfg = Config()
    cal = shipped_calibration()
    if cal is not None:
        cfg = replace(cfg, "calibration", path=str(cal))
    motion = plan_motion(build_route(route), MotionLimits())
    out = {}
    for name, kw in (("kobuki", {}), ("can", {"base": "can"}),
                     ("can + faults", {"base": "can", "can_faults": True})):
        with tempfile.TemporaryDirectory() as tmp:
            s = run_demo(cfg, out=Path(tmp), route=route, duration_s=duration_s, seed=seed,
                         plot=False, **kw)
            stamps, fused = read_tum(Path(tmp) / "fused.tum")
            _, wheel = read_tum(Path(tmp) / "wheel.tum")
        truth = motion.pose_at(stamps / 1e9)
        ef, ew = odometry_errors(truth, fused), odometry_errors(truth, wheel)
        out[name] = {"ok": s["ok"], "wall_time_s": s["wall_time_s"], "distance_m": ef.distance_m,
                     "odometry_samples": len(stamps), "keyframes": s["keyframes"],
                     "fused_end_m": ef.end_position_error_m, "fused_ape_origin_m": ef.ape_origin_rmse_m,
                     "wheel_end_m": ew.end_position_error_m, "wheel_ape_origin_m": ew.ape_origin_rmse_m,
                     "can": s.get("can")}
    return out


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--route", default="office", choices=sorted(ROUTES))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--e2e", action="store_true", help="also run robotd demo three ways")
    ap.add_argument("--e2e-route", default="square", choices=sorted(ROUTES))
    ap.add_argument("--e2e-duration", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    if args.seeds < 1:
        ap.error("--seeds must be >= 1")
    motion = plan_motion(build_route(args.route), MotionLimits())
    print(f"route {args.route}: {motion.length_m:.1f} m in {motion.duration_s:.0f} s, {args.seeds} seeds")
    per_seed = [run_seed(motion, seed) for seed in range(args.seeds)]
    rows = []
    for r in per_seed:
        for p in PATHS:
            m = r[p]
            rows.append([r["seed"], p, m["wheel_msgs"], m["yaw_msgs"], f"{m['fused_end_m']:.4f}",
                         f"{m['fused_ape_origin_m']:.4f}", f"{m['wheel_end_m']:.4f}", f"{m['wheel_ape_origin_m']:.4f}"])
    print()
    print_table(["seed", "path", "wheel msgs", "yaw msgs", "fused end m", "fused APE anchored m",
                 "wheel-only end m", "wheel-only APE anchored m"], rows)
    print()
    for r in per_seed:
        f = r["can diff_drive + faults"]
        d = f["driver"]
        print(f"seed {r['seed']}: faults injected {f['injected']}; driver counted: frames {d['frames']} "
              f"of {f['frames_sent']} sent, unknown {d['unknown_frames']}, decode errors "
              f"{d['decode_errors']}, error frames {d['error_frames']}, bus-off {d['bus_off']}, "
              f"restarts {d['bus_restarts']}, bus silent {d['bus_silent']}, stale L/R "
              f"{d['stale_left']}/{d['stale_right']}, floods {d['flood_reads']}; degraded changes "
              f"{f['degraded_changes']}")
        print(f"         throughput: CAN driver {r['can diff_drive']['frames_per_s']:.0f} frames/s, "
              f"Kobuki driver {r['kobuki']['packets_per_s']:.0f} packets/s (same run)")
    result: dict[str, Any] = {"machine": machine_info(), "route": args.route, "per_seed": per_seed}
    if args.e2e:
        print(f"\nrobotd demo, route {args.e2e_route}, {args.e2e_duration:g} s, seed 0:")
        e2e = run_e2e(args.e2e_route, args.e2e_duration, 0)
        result["e2e"] = e2e
        print_table(["base", "ok", "wheel msgs", "keyframes", "fused end m", "fused APE anchored m",
                     "wheel-only end m", "wheel-only APE anchored m", "wall s"],
                    [[k, v["ok"], v["odometry_samples"], v["keyframes"], f"{v['fused_end_m']:.4f}",
                      f"{v['fused_ape_origin_m']:.4f}", f"{v['wheel_end_m']:.4f}", f"{v['wheel_ape_origin_m']:.4f}",
                      f"{v['wall_time_s']:.0f}"] for k, v in e2e.items()])
        for k in ("can", "can + faults"):
            c = e2e[k]["can"]
            print(f"{k}: frames {c['frames']} read of {c['frames_sent']} sent; injected "
                  f"{c['faults_injected']}; counted unknown {c['unknown_frames']}, decode errors "
                  f"{c['decode_errors']}, bus-off {c['bus_off']}, bus silent {c['bus_silent']}, "
                  f"stale L/R {c['stale_left']}/{c['stale_right']}, floods {c['flood_reads']}, "
                  f"odometry degraded {c['odometry_degraded_episodes']}x")
    print(f"\nwrote {write_json(args.out, result)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
