"""The demo's report: the table it prints (:func:`print_summary`) and its plots."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import numpy as np

from robotd.evaluation.groundtruth import FORWARD_BEARING_OK_DEG, FORWARD_YAW_OK_DEG, LOOP_R, FloorEvaluation, Summary
from robotd.evaluation.observations import RunObservations

if TYPE_CHECKING:
    from sim.robot import VirtualRobot


@dataclass(frozen=True, eq=False)
class GraphPlot:
    """What the trajectory plot draws of the pose graph: keyframe ``ids (K,)``, their
    ``optimized (K, 3)`` and ``vo_only (K, 3)`` poses (None without visual odometry), the
    loop edges ``(older id, newer id)``."""

    ids: list[int]
    optimized: np.ndarray
    vo_only: np.ndarray | None
    loops: list[tuple[int, int]]


def plot_demo_trajectories(out: Path, robot: VirtualRobot, obs: RunObservations, truth: np.ndarray,
                           fused: np.ndarray, wheel: np.ndarray, distance_m: float,
                           graph: GraphPlot | None = None, wheel_nominal: np.ndarray | None = None) -> None:
    """``out/trajectories.png``: the truth, the odometry (anchored at the truth's start, as
    the errors are; ``wheel_nominal``: wheel-only odometry with the nominal model, when
    ``wheel`` is the calibrated model's), the loop-corrected keyframes and their loop edges
    over the floor."""
    from robotd.base.geometry import compose, inverse, transform_points
    from robotd.evaluation.metrics import align_origin
    from robotd.io.plots import plot_trajectories

    # Odometry starts at its own origin; draw it from the route's start, as the errors do.
    to_world = compose(truth[0], inverse(fused[0]))
    kf = transform_points(to_world, np.asarray(obs.keyframe_poses).reshape(-1, 3)[:, :2])
    if wheel_nominal is None:
        estimates = {"wheel only": align_origin(truth[0], wheel)}
    else:
        estimates = {"wheel only (calibrated model)": align_origin(truth[0], wheel)}
    estimates["fused (EKF)"] = align_origin(truth[0], fused)
    loop_xy = None
    if graph is not None:
        opt = compose(to_world, graph.optimized)
        if graph.vo_only is not None:
            estimates["floor VO alone (keyframes)"] = compose(to_world, graph.vo_only)
        estimates["loop-corrected (pose graph)"] = opt
        row = {k: i for i, k in enumerate(graph.ids)}
        pairs = [(row[a], row[b]) for a, b in graph.loops if a in row and b in row]
        loop_xy = np.array([[opt[a, :2], opt[b, :2]] for a, b in pairs]).reshape(-1, 2, 2)
    if wheel_nominal is not None:
        estimates["wheel only (nominal model)"] = align_origin(truth[0], wheel_nominal)
    plot_trajectories(out / "trajectories.png", robot.floor, truth, estimates,
                      keyframes_xy=kf, loop_edges_xy=loop_xy,
                      title=f"robotd demo: route {robot.settings.route}, {distance_m:.0f} m")


def plot_floor_similarity(out: Path, floor: FloorEvaluation, stamps_ns: np.ndarray, exclude_recent_s: float,
                          mode: int) -> None:
    """``out/similarity.png``: the candidates' local scores beside the true overlap."""
    from robotd.io.plots import plot_similarity

    score_m = np.full(floor.overlap.shape, np.nan, np.float32)
    for c in floor.report.candidates:
        score_m[c.query, c.candidate] = c.local_score
    plot_similarity(out / "similarity.png", floor.overlap, score_m, stamps_ns, exclude_recent_s, mode=mode)


def _print_comparison(f: TextIO, title: str, columns: list[tuple[str, dict[str, float]]],
                      rows: tuple[tuple[str, str, str], ...]) -> None:
    """A table: ``rows`` of (label, key, format) looked up in each column's dict."""
    print(f"{title:<26}" + "".join(f"{name:>12}" for name, _ in columns), file=f)
    for label, key, fmt in rows:
        print(f"{label:<26}" + "".join(f"{fmt.format(col.get(key, math.nan)):>12}" for _, col in columns), file=f)


def print_summary(s: Summary, f: TextIO) -> None:
    """The short table the demo prints."""
    w, fu = s["wheel_only"], s["fused"]
    if s.get("interrupted"):
        print(f"interrupted ({s['interrupted']}) after {s['robot_time_s']:.1f} s of robot time of the "
              f"planned {s['planned_robot_time_s']:.1f} s; the figures below are of that part", file=f)
    rows = [
        ("route", f"{s['route']} (seed {s['seed']})"),
        ("distance", f"{s['distance_m']:.1f} m in {s['robot_time_s']:.0f} s robot time"),
        ("wall time", f"{s['wall_time_s']:.1f} s (x{s['real_time_factor']:.1f} real time)"),
        ("frames", f"{s['frames_processed']} processed of {s['frames_rendered']} rendered"),
        ("calibration", s.get("calibration") or "none (no loops declared)"),
        ("keyframes", f"{s['keyframes']}"),
        ("map links", f"odometry {s['links']['odometry']}, loop {s['links']['loop']}"),
        ("drops", ", ".join(f"{k} {v}" for k, v in s["drops"].items())),
        ("packet errors", ", ".join(f"{k} {v}" for k, v in s["packet_errors"].items())),
    ]
    if "can" in s:
        cs = s["can"]
        rows[-1] = ("CAN frames", f"{cs['frames']} read of {cs['frames_sent']} sent ({cs['convention']}): "
                    f"used {cs['frames_used']}, unknown {cs['unknown_frames']}, decode errors "
                    f"{cs['decode_errors']}, error frames {cs['error_frames']}, bus-off {cs['bus_off']}, "
                    f"floods {cs['flood_reads']}, stale left/right {cs['stale_left']}/{cs['stale_right']}, "
                    f"odometry degraded {cs['odometry_degraded_episodes']}x")
    width = max(len(r[0]) for r in rows)
    for k, v in rows:
        print(f"{k:<{width}}  {v}", file=f)
    print(file=f)
    columns = [("wheel only", w), ("fused", fu)]
    if s.get("wheel_only_nominal"):  # the odometry model is calibrated: before and after
        columns = [("wheel nom.", s["wheel_only_nominal"]), ("wheel cal.", w), ("fused", fu)]
    _print_comparison(f, "odometry vs ground truth", columns, (
        ("end position error (m)", "end_position_error_m", "{:.4f}"),
        ("end heading error (deg)", "end_heading_error_deg", "{:.3f}"),
        ("max position error (m)", "ape_origin_max_m", "{:.4f}"),
        ("end drift per 100 m (m)", "end_drift_per_100m_m", "{:.4f}"),
    ))
    g = s.get("pose_graph")
    if g:
        print(file=f)
        columns = [("wheel+gyro", g["odometry"]), ("loop-corr.", g["loop_corrected"])]
        if "vo_only" in g:
            columns.insert(1, ("VO only", g["vo_only"]))
        _print_comparison(f, f"at the {g['keyframes']} keyframes", columns, (
            ("end position error (m)", "end_position_error_m", "{:.4f}"),
            ("end heading error (deg)", "end_heading_error_deg", "{:.3f}"),
            ("APE RMS, anchored (m)", "ape_origin_rmse_m", "{:.4f}"),
            ("ATE RMS, aligned (m)", "ate_aligned_rmse_m", "{:.4f}"),
            ("RPE per step, RMS (mm)", "rpe_rmse_mm", "{:.3f}"),
        ))
        print(f"pose graph: {g['loops_in_graph']} loop edges accepted, {g.get('loops_failed_gate', 0)} "
              f"refused by the chi-square gate, {g.get('loops_down_weighted', 0)} down-weighted by the "
              f"optimiser; iSAM2 update median {g.get('graph_update_median_us', 0) / 1e3:.2f} ms, p99 "
              f"{g.get('graph_update_p99_us', 0) / 1e3:.2f} ms; last full solve {g.get('graph_solve_ms', 0)} ms",
              file=f)
    v = s.get("visual_odometry")
    if v:
        how = (f"{v.get('vo_combined', 0)} graph edges combined with the wheel + gyro edge, "
               f"{v.get('vo_disagreed', 0)} steps left out (disagreeing with it); the live filter "
               f"fused {v.get('vo_fused', 0)}, its gate refused {v.get('vo_rejected_by_filter', 0)}"
               if v["role"] == "fused" else f"{v.get('vo_fallback', 0)} fell back to the wheel + gyro edge")
        print(f"floor visual odometry ({v['role']}): {v.get('vo_ok', 0)} of {v.get('vo_steps', 0)} steps "
              f"measured; {how}", file=f)
    fw = s.get("forward_detector")
    if fw:
        print(file=f)
        print(f"forward loops: {fw['images']} forward keyframes ({fw['unsynced']} without a frame in time), "
              f"{fw['verified_loops']} loops verified, {fw['verified_right']} of them right by the truth "
              f"(heading within {FORWARD_YAW_OK_DEG:g} deg, bearing within {FORWARD_BEARING_OK_DEG:g} deg)", file=f)
        print(f"  into the pose graph: {fw['accepted']} accepted ({fw['accepted_right']} right, "
              f"{fw['accepted'] - fw['accepted_right']} wrong), "
              f"{fw['refused_by_gate']} refused by the gate, "
              + (f"{fw['grouped']} in through their relocalising group's one edge, " if fw.get("grouped") else "")
              + f"{fw['not_planar']} not planar; "
              f"{fw['failed_verification']} candidates failed the epipolar check", file=f)
        if fw.get("accepted_outside_own_noise") is not None:
            print(f"  accepted edges whose truth lies outside their own noise (chi2, 99.9 %): "
                  f"{fw['accepted_outside_own_noise']}", file=f)
        print(f"  per forward keyframe: median {fw['ms_per_image_median']} ms, p99 {fw['ms_per_image_p99']} ms; "
              f"vocabulary {fw['vocabulary_words']} words", file=f)
        od = fw.get("order_dependent")
        if od is not None:
            print(f"  decided by arrival order, not by the data (0 when the run does not depend on the "
                  f"machine's load): {od['late']} forward keyframes published late, "
                  f"{od['frames_evicted']} frames pushed out of the buffer", file=f)
        dq = fw.get("deferred")
        if dq is not None and (dq["deferred"] or dq["inline"] or dq.get("across")):
            print(f"  verifications left to later forward keyframes: {dq['deferred']} "
                  f"(waited up to {dq['wait_max']} keyframes; {dq['at_end']} at the end of the input), "
                  f"{dq['inline']} run in their own keyframe (the queue full), {dq.get('forced', 0)} finished "
                  f"over the budget (the queue over its bound), {dq.get('across', 0)} at once "
                  f"(a view of another odometry chain); at most {dq.get('checks_max', 0)} checks in one keyframe",
                  file=f)
        for r in fw.get("loops", []):
            if r["fate"] == "accepted" and not r["right"]:
                bearing = "-" if r["bearing_error_deg"] is None else f"{r['bearing_error_deg']:.1f}"
                rng = "none" if r.get("measured_range_m") is None else f"{r['measured_range_m']:.2f} m"
                print(f"  wrong, accepted: keyframe {r['to']} -> {r['from']}, {r['true_distance_m']:.2f} m apart, "
                      f"{r['inliers']} inliers, heading {r['yaw_error_deg']:.1f} deg and bearing {bearing} deg off, "
                      f"range on the floor {rng}; gate {r.get('fate_detail', '')}"
                      + (f"; truth chi2 {r['truth_chi2']:.1f}" if "truth_chi2" in r else ""), file=f)
        if fw.get("cpu_ms_per_image_median") is not None:
            share = fw.get("verify_share")
            print(f"  per forward keyframe in the pipeline thread's CPU time: median {fw['cpu_ms_per_image_median']} ms, "
                  f"p99 {fw['cpu_ms_per_image_p99']} ms; verification in wall time median {fw['verify_ms_median']} ms, "
                  f"p99 {fw['verify_ms_p99']} ms"
                  + (f", {100 * share:.0f} % of the detector's time" if share is not None else ""), file=f)
            if fw.get("features_ms_median"):
                print(f"  OpenCV's feature extraction of the same images: median {fw['features_ms_median']} ms "
                      f"(the whole keyframe {fw['ms_per_image_median'] / fw['features_ms_median']:.1f} x that)", file=f)
    rl = s.get("relocalisation")
    if rl:
        print(file=f)
        print(f"kidnapped at {rl['kidnapped_at_s']:.1f} s, carried {rl['carried_s']:.0f} s over "
              f"{rl['carried_m']:.1f} m; lifts detected {rl['lifts_detected']}, odometry chain broken "
              f"{rl['odometry_breaks']}x", file=f)
        if rl.get("relocalised"):
            print(f"  relocalised against run {rl['against_run']} by the {rl.get('cameras', 'floor')} camera "
                  f"{rl['after_s']:.1f} s and "
                  f"{rl['after_m_true']:.2f} m (odometry: {rl['after_m_daemon']:.2f} m) after being put down, "
                  f"{rl['agreeing_candidates']} agreeing candidates; pose error then "
                  f"{rl['position_error_m']:.3f} m, {rl['heading_error_deg']:.2f} deg", file=f)
        else:
            print("  NOT relocalised before the end of the run", file=f)
    fd = s.get("floor_detector")
    if fd:
        print(file=f)
        print(f"floor loop candidates (mode {fd['mode']}): {fd['queries']} map queries, "
              f"{fd['candidates_returned']} candidates", file=f)
        print(f"  revisits (true overlap J >= 0.33 with an older keyframe): {fd['queries_with_true_revisit']}, "
              f"found among the candidates: {fd['revisits_found_among_candidates']}", file=f)
        print(f"  top candidate truly overlapping: {fd['top1_true_overlap']} of {fd['top1_total']}", file=f)
        if fd.get("threshold") is not None:
            print(f"  candidates at or above the threshold ({fd['threshold']:.2f}): "
                  f"{fd.get('above_threshold', 0)}; loop edges accepted: {fd['loops_accepted']}, "
                  f"truly overlapping (J >= {LOOP_R}): {fd['loops_truly_overlapping']}, "
                  f"sharing some floor: {fd['loops_sharing_floor']}", file=f)
            print(f"  refused by the graph's gate: {fd.get('refused_by_gate', 0)}, truly overlapping: "
                  f"{fd.get('refused_truly_overlapping', 0)}", file=f)
        else:
            print("  declared loops: none (no trained threshold for this mode)", file=f)
        for lv, (t, n) in fd["top1_precision_above_score"].items():
            print(f"  top candidates with local score >= {lv}: {t} of {n} truly overlapping", file=f)
        print(f"  {'query':>7} {'candidate':>9} {'local score':>11} {'true J':>7}", file=f)
        for b in fd["best_candidates"]:
            print(f"  {b['query_keyframe']:>7} {b['candidate_keyframe']:>9} {b['local_score']:>11.2f} "
                  f"{b['true_overlap_J']:>7.2f}", file=f)
