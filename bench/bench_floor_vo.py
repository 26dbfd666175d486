"""Floor visual odometry per descriptor mode on a virtual drive (paper 003, Sec. IV-D, V,
Table IV, Fig. 7), against wheel-only odometry from the same run.

The route (default ``square``, 16 m; ``--full``: ``office``, about 110 m as in the paper)
is planned, the Kobuki's encoders and gyro are simulated (:mod:`sim.sensors` defaults),
and a keyframe is taken whenever the true pose moved ``--spacing`` metres or 10 degrees
(the ``[keyframes]`` defaults). Each keyframe's floor image is rendered on the default
mixed floor and on the printed-plank floor (:mod:`sim.world.pattern`, the paper's worst
case). Per floor and mode 1-6: the success rate of the steps, the median and 95th
percentile translation and rotation error per step against the true increment, the time
per step (decode + match + metric fit; extraction timed apart), and the end-to-end error
of vision-only odometry (:func:`robotd.floor.vo.integrate`, failed steps taking the wheel
+ gyro EKF's increment, counted) next to wheel-only dead reckoning (the baseline) and
the EKF of the same run.

Run: ``.venv/bin/python bench/bench_floor_vo.py [--full] [--route NAME] [--seed 0]
[--out bench/results]``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

try:
    from bench.common import machine_info, print_table, write_json
    from bench.floor_common import RESULTS_DIR, log, one_thread, printed_floor, versions
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, write_json
    from floor_common import RESULTS_DIR, log, one_thread, printed_floor, versions

from robotd.base.camera import FloorCameraModel
from robotd.base.geometry import between
from robotd.base.messages import WheelTicks
from robotd.floor.descriptor import MODES, decode, extract
from robotd.floor.vo import FloorVisualOdometry, VoParams, integrate
from robotd.odometry.fusion import OdometryFilter
from robotd.odometry.kinematics import WheelOdometry
from sim.cameras.floor import FloorRenderer, RenderParams
from sim.emulators.kobuki import simulate_kobuki
from sim.route import build_route, plan_motion
from sim.sensors import BaseSensorParams
from sim.world.floor import Floor


def odometry_run(route: str, seed: int) -> dict[str, np.ndarray]:
    """True, wheel-only and EKF poses ``(N, 3)`` at each wheel packet, stamps, speeds."""
    motion = plan_motion(build_route(route))
    stream = simulate_kobuki(motion, BaseSensorParams(), np.random.default_rng(seed))
    wheel, ekf = WheelOdometry(), OdometryFilter()
    w_out, e_out = [], []
    for msg in stream.messages("raw_gyro"):
        if isinstance(msg, WheelTicks):
            p = wheel.update(msg)
            ekf.on_wheels(msg)
            q = ekf.pose()
            w_out.append((p.x_m, p.y_m, p.yaw_rad))
            e_out.append((q.x_m, q.y_m, q.yaw_rad))
        else:
            ekf.on_yaw_rate(msg)
    vw = np.array([motion.velocity_at(float(t)) for t in stream.t_s])
    return {"truth": stream.true_pose, "wheel": np.array(w_out), "ekf": np.array(e_out),
            "t_s": stream.t_s, "vw": vw}


def keyframe_indices(truth: np.ndarray, spacing_m: float, turn_rad: float = math.radians(10)) -> list[int]:
    """Packet indices where the true pose moved ``spacing_m`` or ``turn_rad`` since the last."""
    keep = [0]
    for i in range(1, len(truth)):
        d = between(truth[keep[-1]], truth[i])
        if math.hypot(d[0], d[1]) >= spacing_m or abs(d[2]) >= turn_rad:
            keep.append(i)
    return keep


def end_error(truth: np.ndarray, est: np.ndarray) -> tuple[float, float]:
    """End position error (m) and heading error (deg) after anchoring the start to the truth."""
    rel_true = between(truth[0], truth[-1])
    rel_est = between(est[0], est[-1])
    d = between(rel_true, rel_est)
    return math.hypot(d[0], d[1]), abs(math.degrees(d[2]))


def run_mode(images: list[np.ndarray], kf_truth: np.ndarray, kf_ekf: np.ndarray, mode: int) -> dict[str, Any]:
    """VO over the keyframes in one mode: step errors, timings, the vision-only end error."""
    cam = FloorCameraModel.default()
    t0 = time.perf_counter()
    descs = [extract(img, mode) for img in images]
    extract_ms = 1e3 * (time.perf_counter() - t0) / len(images)
    vo = FloorVisualOdometry(cam, VoParams(descriptor_mode=mode))
    vo.step(descs[0])
    steps, times = [], []
    for d in descs[1:]:
        t = time.perf_counter()
        steps.append(vo.step(decode(d)))
        times.append(time.perf_counter() - t)
    true_inc = between(kf_truth[:-1], kf_truth[1:])
    ok = np.array([s.ok for s in steps])
    err = np.array([s.delta - d for s, d in zip(steps, true_inc)])[ok]
    et = np.hypot(err[:, 0], err[:, 1]) * 1e3 if len(err) else np.array([math.nan])
    er = np.degrees(np.abs(np.array([math.remainder(a, 2 * math.pi) for a in err[:, 2]]))) if len(err) else et
    track = integrate(steps, between(kf_ekf[:-1], kf_ekf[1:]), start_xyyaw=kf_truth[0])
    pos, head = end_error(kf_truth, track.poses)
    return {"mode": mode, "steps": len(steps), "success_rate": float(ok.mean()),
            "trans_err_mm_median": float(np.median(et)), "trans_err_mm_p95": float(np.percentile(et, 95)),
            "rot_err_deg_median": float(np.median(er)), "rot_err_deg_p95": float(np.percentile(er, 95)),
            "step_ms_median": 1e3 * statistics.median(times), "extract_ms_mean": extract_ms,
            "fallback_steps": track.n_fallback, "lost_steps": track.n_lost,
            "vo_end_pos_err_m": pos, "vo_end_heading_err_deg": head}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--full", action="store_true", help="the 110 m office route (slow)")
    ap.add_argument("--route", default=None, help="route name (default square, office with --full)")
    ap.add_argument("--spacing", type=float, default=0.05, help="keyframe spacing, m")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=RESULTS_DIR)
    args = ap.parse_args(argv)
    route = args.route or ("office" if args.full else "square")
    threads = one_thread()
    run = odometry_run(route, args.seed)
    kf = keyframe_indices(run["truth"], args.spacing)
    kf_truth, kf_ekf = run["truth"][kf], run["ekf"][kf]
    wheel_end = end_error(run["truth"], run["wheel"])
    ekf_end = end_error(run["truth"], run["ekf"])
    log(f"route {route}: {len(kf)} keyframes; wheel-only end error {wheel_end[0]:.3f} m "
        f"{wheel_end[1]:.2f} deg, EKF {ekf_end[0]:.3f} m {ekf_end[1]:.2f} deg")
    cam = FloorCameraModel.default()
    floors = [("mixed", Floor.default(seed=args.seed)), ("printed", printed_floor(args.seed).floor)]
    results = []
    for name, floor in floors:
        rend = FloorRenderer(floor, cam, RenderParams(), np.random.default_rng(args.seed))
        images = [rend.render(run["truth"][i], float(run["vw"][i, 0]), float(run["vw"][i, 1]),
                              float(run["t_s"][i])) for i in kf]
        for mode in MODES:
            r = run_mode(images, kf_truth, kf_ekf, mode)
            r["floor"] = name
            results.append(r)
            log(f"{name} mode {mode}: success {r['success_rate']:.3f}, end {r['vo_end_pos_err_m']:.3f} m")
    rows = [[r["floor"], r["mode"], round(r["success_rate"], 3), round(r["trans_err_mm_median"], 2),
             round(r["trans_err_mm_p95"], 2), round(r["rot_err_deg_median"], 3), round(r["rot_err_deg_p95"], 3),
             round(r["step_ms_median"], 1), r["fallback_steps"], round(r["vo_end_pos_err_m"], 3),
             round(r["vo_end_heading_err_deg"], 2)] for r in results]
    print_table(["floor", "mode", "success", "dt med mm", "dt p95 mm", "dyaw med deg", "dyaw p95 deg",
                 "step ms", "fallback", "VO end m", "VO end deg"], rows)
    print(f"baseline, same run: wheel-only end {wheel_end[0]:.3f} m {wheel_end[1]:.2f} deg; "
          f"wheel+gyro EKF end {ekf_end[0]:.3f} m {ekf_end[1]:.2f} deg; {len(kf)} keyframes")
    path = write_json(args.out / f"floor_vo_{route}.json", {
        "machine": machine_info(), "versions": versions(), "threads": threads, "route": route, "seed": args.seed,
        "spacing_m": args.spacing, "keyframes": len(kf),
        "wheel_only_end": {"pos_m": wheel_end[0], "heading_deg": wheel_end[1]},
        "ekf_end": {"pos_m": ekf_end[0], "heading_deg": ekf_end[1]}, "results": results})
    log(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
