"""A run judged by its ground truth: odometry and pose graph at the keyframes, the floor
detector's candidates and loops, the forward camera's loops, a kidnapping's relocalisation.

The inputs are what the run published (:class:`~robotd.evaluation.observations.RunObservations`,
the pipeline's counters) and the true motion (:class:`GroundTruth`: the simulator's
:class:`sim.route.Motion` is one); the outputs are JSON-ready dicts, the demo's summary
sections, which the benchmarks read as well. No I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from robotd.base.camera import FloorCameraModel
from robotd.base.geometry import between, compose, inverse, wrap_angle
from robotd.base.messages import LoopFate
from robotd.evaluation.metrics import Alignment, ape_translation_rmse, odometry_errors, rpe_per_step
from robotd.evaluation.observations import RunObservations
from robotd.floor.evaluation import CandidateReport, candidate_report, overlap_matrix
from robotd.forward.planar import PlanarLoopParams, loop_edge

LOOP_R = 0.33
"""The loop definition's overlap ratio r (paper 003 Sec. III-A): two keyframes show the same
place when their floor footprints' intersection over union J is at least this."""

FORWARD_YAW_OK_DEG = 5.0
FORWARD_BEARING_OK_DEG = 10.0
"""A forward loop's measured heading change and bearing are "right" when within these of the
truth (the bearing is judged only when the true cameras are more than 0.2 m apart)."""

FORWARD_OWN_NOISE_CHI2 = {2: 13.82, 3: 16.27}
"""The second measure beside that judge: a forward loop edge is outside its own noise when
the true relative pose of its keyframes is further from the edge than these chi-square
bounds (99.9 %) under the edge's own information matrix, by the degrees of freedom it
measures (2 without a range on the floor, 3 with one), as the graph's gate counts them."""

Summary = dict[str, Any]
"""A JSON-ready section of the demo's summary (values: numbers, strings, lists, dicts)."""


class GroundTruth(Protocol):
    """The true motion at a fixed step: ``t_s (N,)`` seconds, the speed ``v_mps (N,)`` over
    each step of ``dt_s``, and the pose ``(x_m, y_m, yaw_rad)`` at any time."""

    @property
    def t_s(self) -> np.ndarray: ...

    @property
    def v_mps(self) -> np.ndarray: ...

    @property
    def dt_s(self) -> float: ...

    def pose_at(self, t_s: float | np.ndarray) -> np.ndarray: ...


def keyframe_errors(truth: np.ndarray, columns: Sequence[tuple[str, np.ndarray]]) -> dict[str, dict[str, float]]:
    """Each estimate of the keyframe poses (``columns``: name, ``(K, 3)``) against the
    ``truth (K, 3)`` at the same keyframes: end errors, APE (translation, RMS, anchored at
    the first keyframe: :attr:`~robotd.evaluation.metrics.Alignment.ORIGIN`) and RPE per
    keyframe-to-keyframe step (RMS), and the ATE (translation RMS after the rigid
    least-squares fit of all positions, :attr:`~robotd.evaluation.metrics.Alignment.ALIGNED`:
    the shape of the trajectory, whatever error the first keyframe's pose carries into the
    rest; NaN for fewer than two keyframes)."""
    out = {}
    for name, est in columns:
        e = odometry_errors(truth, est)
        rpe_t, rpe_r = rpe_per_step(truth, est)
        ate = ape_translation_rmse(truth, est, Alignment.ALIGNED) if len(truth) >= 2 else math.nan
        out[name] = {"end_position_error_m": e.end_position_error_m,
                     "end_heading_error_deg": e.end_heading_error_deg,
                     "ape_origin_rmse_m": e.ape_origin_rmse_m, "ate_aligned_rmse_m": ate,
                     "rpe_rmse_mm": rpe_t * 1e3, "rpe_rmse_deg": float(np.degrees(rpe_r))}
    return out


@dataclass(frozen=True, eq=False)
class FloorEvaluation:
    """The floor queries judged by footprint overlap: the summary section, and what a plot
    of it needs (``overlap (K, K)`` J of the keyframes, in ``obs.keyframe_ids``' order; the
    candidate ``report``)."""

    summary: Summary
    overlap: np.ndarray
    report: CandidateReport


def floor_evaluation(camera: FloorCameraModel, truth: GroundTruth, obs: RunObservations, *,
                     exclude_recent_s: float, mode: int) -> FloorEvaluation:
    """The map queries' candidates, the declared loops and the gate's refusals judged by
    ground-truth footprint overlap (J >= :data:`LOOP_R` is a true revisit)."""
    ids = np.asarray(obs.keyframe_ids)
    stamps = obs.stamps_ns
    row = {int(k): i for i, k in enumerate(ids)}
    overlap = overlap_matrix(camera, truth.pose_at(stamps / 1e9))
    queries = [(row[q], [(row[c], s) for c, s, _g, _n in cs]) for q, cs in obs.queries]
    rep = candidate_report(overlap, stamps, queries, exclude_recent_s)
    best = sorted(rep.candidates, key=lambda c: -c.local_score)[:10]
    scores = np.array([c.local_score for c in rep.candidates]) if rep.candidates else np.zeros(0)
    levels = sorted({float(np.quantile(scores, q)) for q in (0.5, 0.9, 0.99)}) if len(scores) else []
    d: Summary = {
        "mode": mode, "queries": rep.queries,
        "candidates_returned": len(rep.candidates),
        "queries_with_true_revisit": rep.queries_with_true_loop,
        "revisits_found_among_candidates": rep.found,
        "recall_of_candidates": rep.recall,
        "top1_true_overlap": rep.top1_true, "top1_total": rep.top1_total,
        "top1_precision_above_score": {f"{lv:.2f}": rep.precision_above(lv) for lv in levels},
        "best_candidates": [{"query_keyframe": int(ids[c.query]), "candidate_keyframe": int(ids[c.candidate]),
                             "local_score": c.local_score, "true_overlap_J": c.overlap} for c in best],
    }
    # Loop edges that entered the map (above the threshold, through the graph's gate),
    # judged by the truth.
    j = np.array([overlap[row[a], row[b]] for a, b in obs.loops], dtype=float)
    d["loops_accepted"] = int(len(j))
    d["loops_truly_overlapping"] = int(np.sum(j >= LOOP_R))
    d["loops_sharing_floor"] = int(np.sum(j > 0))
    # The gate's refusals judged the same way: a truly overlapping one is a true loop the
    # graph's prediction disagreed with (odometry covariance too tight, or a bad transform).
    jr = np.array([overlap[row[a], row[b]] for a, b in obs.refused if a in row and b in row], dtype=float)
    d["refused_by_gate"] = int(len(jr))
    d["refused_truly_overlapping"] = int(np.sum(jr >= LOOP_R))
    return FloorEvaluation(d, overlap, rep)


def forward_evaluation(truth: GroundTruth, mount: np.ndarray, obs: RunObservations,
                       counters: Mapping[str, float], loop_params: PlanarLoopParams | None = None) -> Summary:
    """The forward loops judged by the truth: each verified loop's heading change and bearing
    against the true camera poses (``mount (3,)``: the forward camera on the robot) of its
    two keyframes, and what the pose graph did with it. Beside that judge, each loop's edge
    (:func:`robotd.forward.planar.loop_edge` with ``loop_params``, the range the truth's where
    none was measured) against the true relative pose of its keyframes: ``truth_chi2`` under
    the edge's own information, outside its noise past :data:`FORWARD_OWN_NOISE_CHI2`."""
    stamp_of = dict(zip(obs.keyframe_ids, obs.keyframe_stamps))
    c = counters
    rows = []
    for m in obs.forward_loops:
        if m.from_id not in stamp_of or m.to_id not in stamp_of:
            continue
        a, b = (compose(truth.pose_at(stamp_of[k] / 1e9), mount) for k in (m.from_id, m.to_id))
        rel = between(a, b)
        dist = float(np.hypot(rel[0], rel[1]))
        yaw_err = abs(math.degrees(wrap_angle(m.dyaw_rad - rel[2])))
        bearing_err = abs(math.degrees(wrap_angle(m.bearing_rad - math.atan2(rel[1], rel[0]))))
        right = yaw_err <= FORWARD_YAW_OK_DEG and (dist <= 0.2 or bearing_err <= FORWARD_BEARING_OK_DEG)
        robot_rel = between(truth.pose_at(stamp_of[m.from_id] / 1e9), truth.pose_at(stamp_of[m.to_id] / 1e9))
        delta, info = loop_edge(robot_rel, m.dyaw_rad, m.bearing_rad, mount, loop_params, range_m=m.range_m,
                                sigma_bearing_rad=m.sigma_bearing_rad, sigma_yaw_rad=m.sigma_yaw_rad)
        cos, sin = math.cos(delta[2]), math.sin(delta[2])  # the edge's error coordinates (the gate's)
        d = robot_rel[:2] - delta[:2]
        e = np.array([cos * d[0] + sin * d[1], -sin * d[0] + cos * d[1], wrap_angle(robot_rel[2] - delta[2])])
        chi2 = float(e @ info @ e)
        rows.append({"from": m.from_id, "to": m.to_id, "probability": m.probability,
                     "inliers": m.inliers, "true_distance_m": dist, "yaw_error_deg": yaw_err,
                     "bearing_error_deg": bearing_err if dist > 0.2 else None, "right": right,
                     "measured_range_m": m.range_m, "truth_chi2": chi2,
                     "outside_own_noise": chi2 > FORWARD_OWN_NOISE_CHI2[3 if m.range_m is not None else 2],
                     "dyaw_deg": math.degrees(m.dyaw_rad), "true_dyaw_deg": math.degrees(rel[2]),
                     "bearing_deg": math.degrees(m.bearing_rad),
                     "true_bearing_deg": math.degrees(math.atan2(rel[1], rel[0])),
                     "sigma_bearing_deg": (None if m.sigma_bearing_rad is None
                                           else math.degrees(m.sigma_bearing_rad)),
                     "sigma_yaw_deg": (None if m.sigma_yaw_rad is None else math.degrees(m.sigma_yaw_rad)),
                     "fate": str(obs.forward_fates.get((m.from_id, m.to_id), "none")),
                     "fate_detail": obs.forward_fate_details.get((m.from_id, m.to_id), "")})
    accepted = [r for r in rows if r["fate"] == LoopFate.ACCEPTED]
    return {"images": c.get("forward_images", 0), "frames": c.get("forward_frames", 0),
            "unsynced": c.get("forward_unsynced", 0), "verified_loops": len(rows),
            "verified_right": sum(r["right"] for r in rows),
            "accepted": len(accepted), "accepted_right": sum(r["right"] for r in accepted),
            "accepted_outside_own_noise": sum(r["outside_own_noise"] for r in accepted),
            "refused_by_gate": c.get("forward_loops_failed_gate", 0),
            "grouped": c.get("forward_loops_grouped", 0),
            "failed_verification": c.get("forward_failed_verification", 0),
            "not_planar": c.get("forward_not_planar", 0),
            "vocabulary_words": c.get("forward_vocabulary", 0),
            "ms_per_image_median": c.get("forward_ms_median"), "ms_per_image_p99": c.get("forward_ms_p99"),
            "cpu_ms_per_image_median": c.get("forward_cpu_ms_median"),
            "cpu_ms_per_image_p99": c.get("forward_cpu_ms_p99"),
            "features_ms_median": c.get("forward_features_ms_median"),
            "verify_ms_median": c.get("forward_verify_ms_median"), "verify_ms_p99": c.get("forward_verify_ms_p99"),
            "verify_share": (round(c["forward_verify_ms_total"] / c["forward_ms_total"], 3)
                             if c.get("forward_ms_total") else None),
            "loops": rows}


def relocalisation_evaluation(truth: GroundTruth, kidnap: tuple[float, float, float], obs: RunObservations,
                              relocalisations: Sequence[Mapping[str, Any]],
                              counters: Mapping[str, float]) -> Summary:
    """The kidnapping ``(at_s, to_s, carry_s)`` judged by the truth: when the robot was put
    down, how long and how far it drove until the daemon relocalised (the daemon's own
    figures, from its odometry, in ``relocalisations``, and the truth's distance), and the
    pose error of the relocalising keyframe right after relocalisation (the graph's
    estimate then, in the map frame, against the true pose)."""
    at_s, to_s, carry_s = kidnap
    c = counters
    put_down_s = at_s + carry_s
    stamps = obs.stamps_ns
    first_s = stamps[0] / 1e9 if len(stamps) else 0.0
    # The map frame is the first run's odometry frame: its origin is the truth's first keyframe pose
    # as the odometry saw it (the odometry starts at zero there, as the demo's plots assume).
    fused0 = np.array(obs.keyframe_poses[0]) if obs.keyframe_poses else np.zeros(3)
    to_world = compose(truth.pose_at(first_s), inverse(fused0))
    out: Summary = {"kidnapped_at_s": at_s, "put_down_at_s": put_down_s, "carried_s": carry_s,
                    "put_down_where_route_was_at_s": to_s,
                    "carried_m": float(np.hypot(*(truth.pose_at(at_s)[:2] - truth.pose_at(put_down_s + 1e-3)[:2]))),
                    "lifts_detected": c.get("lifts", 0), "odometry_breaks": c.get("odometry_breaks", 0),
                    "relocalisations": c.get("relocalisations", 0),
                    "candidates_refused_before": c.get("reloc_candidates_refused", 0)}
    after = [r for r in relocalisations if r["stamp_ns"] / 1e9 >= put_down_s]
    if not after:
        out["relocalised"] = False
        return out
    r = after[0]
    t_s = r["stamp_ns"] / 1e9
    k0 = int(np.searchsorted(truth.t_s, put_down_s))
    k1 = int(np.searchsorted(truth.t_s, t_s))
    true_m = float(np.sum(np.abs(truth.v_mps[k0:k1])) * truth.dt_s)
    err = between(truth.pose_at(t_s), compose(to_world, np.asarray(r["pose"])))
    out.update({"relocalised": True, "against_run": r["run"], "after_s": t_s - put_down_s,
                "after_s_daemon": r["after_s"], "after_m_daemon": r["after_m"], "after_m_true": true_m,
                "agreeing_candidates": r["candidates"], "cameras": r.get("cameras", "floor"),
                "position_error_m": float(np.hypot(err[0], err[1])),
                "heading_error_deg": float(abs(np.degrees(wrap_angle(err[2]))))})
    return out
