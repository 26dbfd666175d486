"""The paper's loop-closure experiment (paper 003 Sec. V, Table IV, Fig. 7-8) on the daemon.

For each floor (the printed plank floor, the paper's worst case, and the default floor of
real photos), each odometry (``vo``: vision-only, the map's odometry edges are floor
visual odometry, its steps on the detected keypoint positions; ``vo-coded``: the same on
the descriptor's coordinate grid, as the paper reuses the descriptor; ``wheel``: the wheel
+ gyro filter's edges) and each
descriptor mode, the virtual robot drives the route through the whole daemon, exactly as
``robotd demo`` does (Kobuki bytes over a pty, rendered floor frames, keyframes, the
floor loop detector with the floor's trained thresholds, the live pose graph with its
chi-square gate and robust re-solves). Then, against ground truth at the keyframes:

* paper Table IV: the start-to-end error (dx, dy, dtheta) of the odometry alone and of
  the loop-corrected trajectory (the start is anchored to the truth, the end's error is
  in the start's frame), plus APE (RMS position error, anchored at the start: evo's
  ``--align_origin``) and RPE (RMS step error);
* the loop edges accepted, and how many of them are false by ground truth: the measured
  relative pose more than ``FALSE_LOOP_M`` from the true one (a look-alike), and how many
  of those kept their weight in the final graph; candidates the gate refused, and how
  many of those were true loops (with their transform errors: a refused true loop is
  either a wrong transform or a covariance too tight for it);
* false loops injected: ``--inject`` fractions (default 5 % and 20 %) of the accepted loop
  edges are replaced by wrong ones (random keyframe pairs at least 1 m apart by the
  truth, each carrying the replaced edge's measurement and information), and the stored
  graph is re-solved with robotd's batch optimiser; APE beside the clean re-solve's, and
  beside the re-solve with the same edges only removed (replacing 20 % of the true loops
  also loses their information: that part of the growth is not the wrong edges' harm),
  and beside the re-solve with the same wrong edges added to all the true ones (the
  outliers' harm alone); the maps are kept beside result.json for such re-solves;
* the trajectories, one panel per mode (paper Fig. 7/8), per floor and odometry.

Thresholds: the default floor uses the calibration shipped with the demo (a figure-eight
calibration drive over that floor, ``tools/demo_calibration.sh``); the plank floor gets
its own calibration drive the same way (``robotd record --virtual --route figure8 --seed
11 --floor-pattern planks``, then ``robotd calibrate loop-curve``), made once into
``--out`` and reused. A mode without a trained threshold declares no loop (the daemon
says so); the table shows it.

Default: the 16 m square route, modes 1-6, the plank floor, vision-only odometry (about 12
min on a quiet 2-core machine, the plank calibration drive included). ``--full``: the
office route (about 110 m, ~7000 frames, the paper's run), both floors, both odometries
(about 2 h). Every run writes ``--out/RUN/result.json``
and is skipped when that exists, so an interrupted bench resumes (delete the folder to
start afresh).

Run from the repo root: ``.venv/bin/python bench/bench_loop_closure.py [--full]
[--floors planks,mixed] [--odometry vo,wheel] [--modes 1,2,3,4,5,6] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

try:
    from bench.common import machine_info, print_table, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, write_json

from robotd.app.cli import main as robotd
from robotd.app.demo import run_demo, shipped_calibration
from robotd.app.graph_cli import graph_from_map
from robotd.base.camera import FloorCameraModel, overlap_ratios
from robotd.base.config import Config, replace
from robotd.base.geometry import between, interpolate_poses, wrap_angle
from robotd.base.messages import CandidateFate, LoopCandidate, LoopFate
from robotd.graph import BatchParams, PoseGraph, optimize_batch
from robotd.graph.model import chain_poses
from robotd.io.store import MapStore
from robotd.evaluation.groundtruth import LOOP_R
from robotd.evaluation.metrics import align_origin, odometry_errors, rpe_per_step
from robotd.io.trajectory import read_tum

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "loop_closure"
#: A loop edge whose measured relative pose is farther than this from the truth is false.
FALSE_LOOP_M = 0.05
#: Wrong loop edges join keyframes at least this far apart by the truth.
WRONG_LOOP_MIN_M = 1.0
ODOMETRY = {"vo": "floor VO alone", "vo-coded": "floor VO alone on the descriptor's grid (paper 003)",
            "wheel": "wheel + gyro"}
MODES = (1, 2, 3, 4, 5, 6)


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


class LoopWatcher:
    """A pipeline observer: every loop candidate above the threshold (with its measured
    relative pose) and every fate the pose graph gave one."""

    name = "bench_loops"

    def __init__(self) -> None:
        self.candidates: list[tuple[int, int, float, list[float]]] = []
        self.fates: list[tuple[int, int, str, str]] = []

    def subscriptions(self) -> dict[type, Any]:
        return {LoopCandidate: self.on_candidate, CandidateFate: self.on_fate}

    def on_candidate(self, c: LoopCandidate) -> None:
        self.candidates.append((c.from_id, c.to_id, float(c.score), [float(v) for v in c.delta_xyyaw]))

    def on_fate(self, f: CandidateFate) -> None:
        if f.fate != LoopFate.BELOW_THRESHOLD:
            self.fates.append((f.query_id, f.candidate_id, f.fate, f.detail))

    def finish(self) -> int:
        return 0

    def counters(self) -> dict[str, int]:
        return {}


# --------------------------------------------------------------------------- calibration


def calibration_for(floor: str, out: Path) -> Path:
    """The floor's calibration file: the demo's shipped one for the default floor; for the
    planks a calibration drive over planks, trained as a user would (made once)."""
    if floor == "mixed":
        path = shipped_calibration()
        if path is None:
            raise SystemExit("the demo's shipped calibration is missing (tools/demo_calibration.sh makes it)")
        return path
    cal = out / f"calibration-{floor}.yml"
    if cal.exists():
        return cal
    drive = out / f"calibration-{floor}-figure8.mcap"
    if not drive.exists():
        log(f"{floor}: recording the calibration drive (figure8, seed 11)")
        tmp = drive.with_suffix(".part.mcap")
        png = out / "record-png.toml"  # train on the camera's own pixels
        png.write_text('[recording]\nimage_format = "png"\n')
        if robotd(["record", str(tmp), "--virtual", "--route", "figure8", "--seed", "11",
                   "--config", str(png), *FLOOR_ARGS[floor]]) != 0:
            raise SystemExit(f"recording the {floor} calibration drive failed")
        tmp.rename(drive)
    log(f"{floor}: training the loop thresholds")
    tmp = cal.with_suffix(".part.yml")
    tmp.unlink(missing_ok=True)
    rc = robotd(["calibrate", "loop-curve", str(drive), "--calibration", str(tmp),
                 "--plot", str(out / f"calibration-{floor}-curves.png"),
                 "--json", str(out / f"calibration-{floor}.json")])
    if rc != 0:
        raise SystemExit(f"training the {floor} thresholds failed (exit {rc})")
    tmp.rename(cal)
    drive.unlink()  # gigabytes of PNG frames; the trained file and its JSON stay
    return cal


FLOOR_ARGS = {"planks": ["--floor-pattern", "planks"], "mixed": []}
FLOOR_PATTERN = {"planks": "planks", "mixed": None}


# --------------------------------------------------------------------------- one run


def run_one(floor: str, odometry: str, mode: int, route: str, seed: int, calibration: Path,
            d: Path) -> dict[str, Any]:
    """One drive through the daemon, then its figures against the truth."""
    cfg = replace(Config(), "calibration", path=str(calibration))
    cfg = replace(cfg, "floor_detector", descriptor_mode=mode)
    if odometry in ("vo", "vo-coded"):
        cfg = replace(cfg, "visual_odometry", enabled=True, role="vision_only",
                      keypoint_positions="coded" if odometry == "vo-coded" else "detected")
    else:  # the wheel + gyro filter's own edges
        cfg = replace(cfg, "visual_odometry", enabled=False)
    watcher = LoopWatcher()
    t0 = time.monotonic()
    summary = run_demo(cfg, out=d, route=route, floor_pattern=FLOOR_PATTERN[floor], seed=seed,
                       plot=False, observers=(watcher,))
    wall = time.monotonic() - t0
    return evaluate(d, watcher, summary, wall)


def _keyframe_truth(d: Path, stamps_ns: np.ndarray) -> np.ndarray:
    gt_stamps, gt_poses = read_tum(d / "groundtruth.tum")
    return interpolate_poses(gt_stamps, gt_poses, stamps_ns)


def start_to_end(truth: np.ndarray, est: np.ndarray) -> dict[str, float]:
    """Paper Table IV: the end pose's error in the start's frame (start anchored)."""
    e = between(between(truth[0], truth[-1]), between(est[0], est[-1]))
    return {"dx_m": float(e[0]), "dy_m": float(e[1]), "dtheta_deg": float(math.degrees(wrap_angle(e[2])))}


def trajectory_figures(truth: np.ndarray, est: np.ndarray) -> dict[str, float]:
    e = odometry_errors(truth, est)
    rpe_t, rpe_r = rpe_per_step(truth, est)
    return {**start_to_end(truth, est), "end_m": e.end_position_error_m, "ape_m": e.ape_origin_rmse_m,
            "rpe_mm": rpe_t * 1e3, "rpe_deg": float(math.degrees(rpe_r))}


def _edge_error(truth: dict[int, np.ndarray], a: int, b: int, delta: np.ndarray) -> np.ndarray:
    """``(3,)`` error of a measured relative pose b-in-a against the truth, yaw wrapped."""
    e = between(between(truth[a], truth[b]), np.asarray(delta, float))
    e[2] = wrap_angle(e[2])
    return e


def _delta_error(truth: dict[int, np.ndarray], a: int, b: int, delta: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) error of a measured relative pose b-in-a."""
    e = _edge_error(truth, a, b, delta)
    return float(math.hypot(e[0], e[1])), float(abs(math.degrees(e[2])))


def _nees(truth: dict[int, np.ndarray], edges: list[Any]) -> float | None:
    """Mean normalised estimation error squared of ``edges`` against the truth."""
    if not edges:
        return None
    errs = [_edge_error(truth, e.from_id, e.to_id, e.delta) for e in edges]
    return float(np.mean([err @ e.information @ err for err, e in zip(errs, edges)]))


def evaluate(d: Path, watcher: LoopWatcher, summary: dict[str, Any], wall_s: float) -> dict[str, Any]:
    with MapStore.open(d / "map.sqlite", create=False) as store:
        graph, stamps = graph_from_map(store)
        optimized = store.optimized_poses()
        fates = store.loop_candidates()
    ids = graph.ids
    truth_arr = _keyframe_truth(d, np.asarray(stamps, np.int64))
    truth = {int(k): p for k, p in zip(ids, truth_arr)}
    odo_edges = [e for e in graph.edges if e.kind == "odometry"]
    chained = chain_poses(ids, odo_edges)
    odo = np.array([chained[int(k)] for k in ids])
    result: dict[str, Any] = {
        "keyframes": int(len(ids)), "distance_m": summary["distance_m"], "wall_s": wall_s,
        "robot_s": summary["robot_time_s"], "real_time_factor": summary["robot_time_s"] / wall_s,
        "threshold": summary.get("floor_detector", {}).get("threshold"),
        "odometry_alone": trajectory_figures(truth_arr, odo),
    }
    if summary.get("visual_odometry"):
        result["visual_odometry"] = summary["visual_odometry"]
    if optimized and all(int(k) in optimized for k in ids):
        opt = np.array([optimized[int(k)] for k in ids])
        result["loop_corrected"] = trajectory_figures(truth_arr, opt)
    # Loop edges in the map, judged by the truth; their fate at the end.
    down = {(q, c) for q, c, _s, f, _d in ((r.query_id, r.candidate_id, r.score, r.fate, r.detail) for r in fates)
            if f == "down_weighted"}
    loops = [e for e in graph.edges if e.kind == "loop"]
    errs = [_delta_error(truth, e.from_id, e.to_id, e.delta) for e in loops]
    false = [(e, t) for e, (t, _r) in zip(loops, errs) if t > FALSE_LOOP_M]
    cam = FloorCameraModel.default()
    j = (overlap_ratios(cam, np.array([truth[e.from_id] for e in loops]), np.array([truth[e.to_id] for e in loops]))
         if loops else np.zeros(0))
    result["loops"] = {
        "above_threshold": len(watcher.candidates),
        "accepted": len(loops),
        "accepted_truly_overlapping": int(np.sum(j >= LOOP_R)),
        "false": len(false),
        "false_with_weight": sum(1 for e, _t in false if (e.to_id, e.from_id) not in down),
        "down_weighted": len(down),
        "accepted_error_mm_median": float(np.median([t for t, _r in errs]) * 1e3) if errs else None,
        "accepted_error_mm_p95": float(np.percentile([t for t, _r in errs], 95) * 1e3) if errs else None,
    }
    # Are the stated covariances right? NEES (e^T I e against the truth; 3 when they are)
    # of the odometry edges and of the accepted loop edges.
    result["nees"] = {"odometry_mean": _nees(truth, odo_edges), "loops_mean": _nees(truth, loops)}
    # The gate's refusals, judged by the truth: true loops (transform within FALSE_LOOP_M)
    # and look-alikes.
    measured = {(a, b): np.asarray(dl) for a, b, _s, dl in watcher.candidates}
    refused = [(q, c, det) for q, c, f, det in watcher.fates if f == LoopFate.FAILED_GATE and (c, q) in measured]
    ref_err = [_delta_error(truth, c, q, measured[(c, q)]) for q, c, _det in refused]
    ref_chi2 = [float(det.split()[1]) for _q, _c, det in refused if det.startswith("chi2 ")]
    true_ref = [t for t, _r in ref_err if t <= FALSE_LOOP_M]
    result["gate"] = {
        "refused": len(refused), "refused_true": len(true_ref),
        "refused_true_error_mm_median": float(np.median(true_ref) * 1e3) if true_ref else None,
        "refused_true_error_mm_p90": float(np.percentile(true_ref, 90) * 1e3) if true_ref else None,
        "refused_chi2_median": float(np.median(ref_chi2)) if ref_chi2 else None,
    }
    result["_truth"] = truth_arr.tolist()
    result["_odometry"] = odo.tolist()
    if "loop_corrected" in result:
        result["_optimized"] = opt.tolist()
    return result


# --------------------------------------------------------------------------- injection


def inject_wrong_loops(graph: PoseGraph, truth: dict[int, np.ndarray], fraction: float,
                       rng: np.random.Generator) -> tuple[PoseGraph, PoseGraph, PoseGraph, int]:
    """Three copies of ``graph``: one with ``fraction`` of its loop edges replaced by wrong
    ones (each joins a random pair of keyframes at least ``WRONG_LOOP_MIN_M`` apart by the
    truth and carries the replaced edge's measurement and information), one with the
    same edges only removed (what the replaced graph would be if the wrong edges did no
    harm: the lost true loops alone), and one with every true edge kept and the wrong ones
    added (the outliers' harm without the lost information)."""
    loops = [i for i, e in enumerate(graph.edges) if e.kind == "loop"]
    k = int(round(fraction * len(loops)))
    replaced = set(rng.choice(loops, size=k, replace=False).tolist()) if k else set()
    ids = graph.ids
    xy = np.array([truth[int(i)][:2] for i in ids])
    out, removed, added = PoseGraph(), PoseGraph(), PoseGraph()
    for i, p in zip(ids, graph.poses()):
        for g in (out, removed, added):
            g.add_pose(int(i), p)
    for i, e in enumerate(graph.edges):
        added.add_edge(e.from_id, e.to_id, e.delta, e.information, e.kind)
        if i not in replaced:
            out.add_edge(e.from_id, e.to_id, e.delta, e.information, e.kind)
            removed.add_edge(e.from_id, e.to_id, e.delta, e.information, e.kind)
            continue
        while True:
            a, b = rng.choice(len(ids), size=2, replace=False)
            if np.hypot(*(xy[a] - xy[b])) >= WRONG_LOOP_MIN_M:
                break
        out.add_edge(int(ids[a]), int(ids[b]), e.delta, e.information, "loop")
        added.add_edge(int(ids[a]), int(ids[b]), e.delta, e.information, "loop")
    for f in graph.fixed:
        for g in (out, removed, added):
            g.fix(f)
    return out, removed, added, k


def injection(d: Path, fractions: list[float], seed: int) -> dict[str, Any]:
    """The stored graph re-solved clean and with wrong loops injected: APE (anchored) against the truth."""
    with MapStore.open(d / "map.sqlite", create=False) as store:
        graph, stamps = graph_from_map(store)
    truth_arr = _keyframe_truth(d, np.asarray(stamps, np.int64))
    truth = {int(k): p for k, p in zip(graph.ids, truth_arr)}
    n_loops = sum(1 for e in graph.edges if e.kind == "loop")
    if n_loops == 0:
        return {"loops": 0}

    def ape(g: PoseGraph) -> tuple[float, float, int]:
        r = optimize_batch(g, BatchParams())
        pos = r.pose_of()
        est = np.array([pos[int(k)] for k in graph.ids])
        return odometry_errors(truth_arr, est).ape_origin_rmse_m, r.time_s, int(np.sum(r.loop_weights < 0.5))

    clean, t_clean, dw_clean = ape(graph)
    out: dict[str, Any] = {"loops": n_loops, "clean_ape_m": clean, "clean_time_s": t_clean,
                           "clean_down_weighted": dw_clean, "injected": []}
    rng = np.random.default_rng(seed)
    for frac in fractions:
        g, without, with_all, k = inject_wrong_loops(graph, truth, frac, rng)
        a, t, dw = ape(g)
        a0, _t0, _dw0 = ape(without)
        a1, _t1, dw1 = ape(with_all)
        out["injected"].append({"fraction": frac, "wrong_edges": k, "ape_m": a, "time_s": t,
                                "down_weighted": dw, "ape_growth_pct": 100.0 * (a - clean) / clean,
                                "ape_removed_only_m": a0,
                                "ape_growth_from_wrong_edges_pct": 100.0 * (a - a0) / a0,
                                "ape_added_m": a1, "added_down_weighted": dw1,
                                "ape_growth_added_pct": 100.0 * (a1 - clean) / clean})
    return out


# --------------------------------------------------------------------------- report


def plot_runs(path: Path, title: str, runs: dict[int, dict[str, Any]]) -> None:
    """Paper Fig. 7/8: per mode, the truth, the odometry alone and the loop-corrected path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = sorted(runs)
    cols = min(3, len(modes))
    rows = math.ceil(len(modes) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.6 * rows), squeeze=False)
    for ax in axes.ravel()[len(modes):]:
        ax.axis("off")
    for ax, m in zip(axes.ravel(), modes):
        r = runs[m]
        truth = np.asarray(r["_truth"])
        ax.plot(truth[:, 0], truth[:, 1], color="black", lw=1.0, label="ground truth")
        odo = align_origin(truth[0], np.asarray(r["_odometry"]))
        ax.plot(odo[:, 0], odo[:, 1], color="tab:orange", lw=0.9, label="odometry alone")
        if "_optimized" in r:
            opt = align_origin(truth[0], np.asarray(r["_optimized"]))
            ax.plot(opt[:, 0], opt[:, 1], color="tab:blue", lw=0.9, label="with loops")
        lp = r["loops"]
        ax.set_title(f"mode {m}: {lp['accepted']} loops, {lp['false']} false", fontsize=10)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    axes.ravel()[0].legend(fontsize=8, loc="best")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table_iv(results: list[dict[str, Any]]) -> None:
    rows = []
    for r in results:
        o = r["odometry_alone"]
        c = r.get("loop_corrected")
        lp = r["loops"]
        rows.append([r["floor"], r["odometry"], r["mode"],
                     "-" if r["threshold"] is None else f"{r['threshold']:.0f}",
                     f"{o['dx_m']:+.3f}", f"{o['dy_m']:+.3f}", f"{o['dtheta_deg']:+.2f}",
                     f"{c['dx_m']:+.3f}" if c else "-", f"{c['dy_m']:+.3f}" if c else "-",
                     f"{c['dtheta_deg']:+.2f}" if c else "-",
                     f"{o['end_m']:.3f}", f"{c['end_m']:.3f}" if c else "-",
                     f"{o['ape_m']:.3f}", f"{c['ape_m']:.3f}" if c else "-",
                     f"{o['rpe_mm']:.2f}", f"{c['rpe_mm']:.2f}" if c else "-",
                     lp["accepted"], lp["false"], lp["false_with_weight"], lp["down_weighted"],
                     f"{r['gate']['refused']}/{r['gate']['refused_true']}",
                     f"{r['real_time_factor']:.2f}"])
    print_table(["floor", "odometry", "mode", "thr", "dx", "dy", "dth", "dx loop", "dy loop", "dth loop",
                 "end", "end loop", "APE", "APE loop", "RPE mm", "RPE loop", "loops", "false",
                 "false kept", "down-wt", "gate refused/true", "x real"], rows)


def injection_table(results: list[dict[str, Any]]) -> None:
    rows = []
    for r in results:
        inj = r.get("injection", {})
        if not inj.get("loops"):
            continue
        for i in inj["injected"]:
            rows.append([r["floor"], r["odometry"], r["mode"], inj["loops"], f"{100 * i['fraction']:.0f} %",
                         i["wrong_edges"], f"{inj['clean_ape_m'] * 1e3:.3f}", f"{i['ape_m'] * 1e3:.3f}",
                         f"{i['ape_growth_pct']:+.1f} %", f"{i.get('ape_removed_only_m', math.nan) * 1e3:.3f}",
                         f"{i.get('ape_growth_from_wrong_edges_pct', math.nan):+.1f} %", i["down_weighted"],
                         f"{i.get('ape_added_m', math.nan) * 1e3:.3f}",
                         f"{i.get('ape_growth_added_pct', math.nan):+.1f} %"])
    if rows:
        print_table(["floor", "odometry", "mode", "loops", "injected", "wrong edges", "APE clean mm",
                     "APE replaced mm", "growth", "APE edges removed mm", "growth from wrong", "down-weighted",
                     "APE added mm", "growth added"], rows)


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--full", action="store_true", help="the office route (~110 m) with both odometries (~2 h)")
    ap.add_argument("--route", default=None, help="route (default square; office with --full)")
    ap.add_argument("--floors", default=None, help="comma-separated: planks, mixed (default planks; both with --full)")
    ap.add_argument("--odometry", default=None, help="comma-separated: vo, vo-coded (the paper's: the steps on the descriptor's "
                    "grid), wheel (default vo; vo and wheel with --full)")
    ap.add_argument("--modes", default="1,2,3,4,5,6", help="comma-separated descriptor modes")
    ap.add_argument("--inject", default="0.05,0.2", help="fractions of accepted loops replaced by wrong ones")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    route = args.route or ("office" if args.full else "square")
    floors = [f for f in (args.floors or ("planks,mixed" if args.full else "planks")).split(",") if f]
    odometries = [o for o in (args.odometry or ("vo,wheel" if args.full else "vo")).split(",") if o]
    modes = [int(m) for m in args.modes.split(",") if m]
    fractions = [float(f) for f in args.inject.split(",") if f]
    for f in floors:
        if f not in FLOOR_ARGS:
            ap.error(f"unknown floor {f!r} (planks, mixed)")
    for o in odometries:
        if o not in ODOMETRY:
            ap.error(f"unknown odometry {o!r} (vo, vo-coded, wheel)")
    if not set(modes) <= set(MODES):
        ap.error("modes are 1..6")
    out = args.out / route
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for floor in floors:
        cal = calibration_for(floor, args.out)
        for odometry in odometries:
            per_mode = {}
            for mode in modes:
                d = out / f"{floor}-{odometry}-m{mode}"
                res_path = d / "result.json"
                if res_path.exists():
                    log(f"{d.name}: have it")
                    r = json.loads(res_path.read_text())
                else:
                    log(f"{d.name}: driving {route} ({ODOMETRY[odometry]}, mode {mode})")
                    r = run_one(floor, odometry, mode, route, args.seed, cal, d)
                    r.update(floor=floor, odometry=odometry, mode=mode, route=route)
                    res_path.write_text(json.dumps(r) + "\n")
                    lc = r.get("loop_corrected", {})
                    log(f"  {r['keyframes']} keyframes, {r['loops']['accepted']} loops "
                        f"({r['loops']['false']} false), end {r['odometry_alone']['end_m']:.3f} m -> "
                        f"{lc.get('end_m', float('nan')):.3f} m, x{r['real_time_factor']:.2f} real time")
                injected = r.get("injection", {}).get("injected") or [{}]
                if "ape_added_m" not in injected[0] and (d / "map.sqlite").exists():
                    r["injection"] = injection(d, fractions, args.seed)
                    res_path.write_text(json.dumps(r) + "\n")
                per_mode[mode] = r
                results.append(r)
            png = out / f"trajectories-{floor}-{odometry}.png"
            plot_runs(png, f"{route}, {floor} floor, {ODOMETRY[odometry]} odometry", per_mode)
            log(f"wrote {png}")
    print(f"\nroute {route}: start-to-end error (m, deg) of the odometry alone and with loops (paper Table IV), "
          f"APE (RMS, anchored at the first keyframe)/RPE at keyframes, loops accepted and false by ground truth (> {FALSE_LOOP_M * 1e3:.0f} mm off)")
    table_iv(results)
    print("\nwrong loop edges injected into the stored graph, re-solved by robotd's batch optimiser")
    injection_table(results)
    slim = [{k: v for k, v in r.items() if not k.startswith("_")} for r in results]
    path = write_json(out / "loop_closure.json", {"machine": machine_info(), "route": route, "seed": args.seed,
                                                   "false_loop_m": FALSE_LOOP_M, "results": slim})
    log(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
