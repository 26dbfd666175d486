"""The kidnapped robot against the same drive without the kidnapping, per seed: how soon and
how well the daemon relocalises, whether the gate keeps every truly overlapping loop, and
the loop-corrected error of both drives (the issue's target: the kidnapped drive's
loop-corrected APE, anchored at the first keyframe, within 2x of the plain drive's).

Each seed runs ``robotd demo --route office --duration D --seed N --no-plot`` twice, with
``--kidnap T --kidnap-to S`` and without, one demo at a time (a subprocess each; its CPU
time is the children's user + system time). From each run's ``summary.json`` and TUM files:

- relocalisation: the time and true distance from the put-down to the relocalising
  keyframe, and that keyframe's pose error (the demo's own figures);
- loops: accepted by the gate and of them truly overlapping, refused by the gate, of those truly
  overlapping (footprint overlap, the demo's judge), in the graph;
- loop-corrected keyframes (``corrected.tum``) against the truth: APE anchored at the first
  keyframe (the judge), ATE after the rigid fit (evo ``--align``), and the rotation of that
  fit (deg): the turn of the whole map about the first keyframe that the anchored measure
  charges over the map's extent and the fit removes;
- the error the graph itself expects of the anchored measure: its keyframes' marginal
  position covariances with the first keyframe held (every stored odometry and loop edge,
  at the stored solution; the full solve left some loops out, so it expects a little
  more), RMS over the keyframes of ``sqrt(trace)``; and the map's heading 1-sigma at its
  keyframes (RMS, deg): how well the map's turn about the first keyframe is known;
- where the anchored error comes from: each map re-solved from its stored edges as it
  is, with the odometry of the route's first S s from the truth (driven once by the
  kidnapped drive), with the loops from the truth, and with all odometry from the truth;
- beside the judge, the plain drive's own keyframe errors sampled at the kidnapped drive's
  route times (route time t before the lift, t - (T + carry - S) after the put-down): the
  kidnapped drive covers the route's first T s and then S.. again, the plain drive all of
  it, so the plain drive's errors over the same ground are the like-for-like baseline.

Run from a snapshot (``git archive``; a demo is minutes): ``bench/bench_kidnap.py
[--seeds 0,1,2,3,4] [--work DIR] [--config FILE] [--out JSON] [--markdown PAGE]``;
``--full``: a 220 s drive (the office route is 232 s) kidnapped at 110 s to 40 s.
``--reuse`` keeps a run whose ``summary.json`` exists in ``--work`` (a bench interrupted
goes on). ``--page-from JSON`` writes the page only. The default takes 10 demos of 2-4
minutes each on a loaded two-core machine.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

try:
    from bench.common import machine_info, print_table, write_json, write_page
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, write_json, write_page

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from robotd.base.geometry import compose, wrap_angle  # noqa: E402
from robotd.evaluation.metrics import align_origin, rigid_fit_2d  # noqa: E402
from robotd.io.trajectory import read_tum  # noqa: E402

DEFAULT_OUT = REPO / "docs" / "benchmarks" / "kidnap.json"
CARRY_S = 5.0  # robotd.app.demo.KIDNAP_CARRY_S (checked in main)


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run_demo(out: Path, seed: int, duration_s: float | None, kidnap: tuple[float, float] | None,
             config: Path | None, reuse: bool, extra: tuple[str, ...] = (), repo: Path = REPO) -> dict[str, Any]:
    """One demo into ``out``; its summary, wall and CPU seconds. ``duration_s`` None: the
    whole route; ``extra``: more demo options (``--forward``); ``repo``: the tree whose
    code runs (another snapshot, for the code before beside this one)."""
    summary_path = out / "summary.json"
    times_path = out.parent / f"{out.name}.times.json"
    if reuse and summary_path.is_file():
        log(f"  reusing {out}")
        times = json.loads(times_path.read_text()) if times_path.is_file() else {"wall_s": None, "cpu_s": None}
        return {"summary": json.loads(summary_path.read_text()), **times}
    cmd = [sys.executable, "-m", "robotd.app.cli", "--log-level", "info", "demo", "--route", "office",
           "--seed", str(seed), "--no-plot", "--out", str(out), *extra]
    if duration_s is not None:
        cmd += ["--duration", f"{duration_s:g}"]
    if kidnap is not None:
        cmd += ["--kidnap", f"{kidnap[0]:g}", "--kidnap-to", f"{kidnap[1]:g}"]
    if config is not None:
        cmd += ["--config", str(config)]
    summary_path.unlink(missing_ok=True)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=repo,
                          env={**os.environ, "PYTHONPATH": str(repo)})
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    (out.parent / f"{out.name}.stdout").write_text(done.stdout)
    (out.parent / f"{out.name}.stderr").write_text(done.stderr)
    if not summary_path.is_file():
        raise RuntimeError(f"{' '.join(cmd)} wrote no summary (exit {done.returncode}): "
                           f"{done.stderr.strip().splitlines()[-1:] or ''}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    times_path.write_text(json.dumps({"wall_s": wall, "cpu_s": cpu}))
    return {"summary": json.loads(summary_path.read_text()), "wall_s": wall, "cpu_s": cpu}


def truth_at(out: Path, stamps_ns: np.ndarray) -> np.ndarray:
    """The true poses ``(N, 3)`` at ``stamps_ns``, interpolated in ``groundtruth.tum``."""
    t_ns, gt = read_tum(out / "groundtruth.tum")
    t = (t_ns - t_ns[0]) / 1e9
    q = (stamps_ns - t_ns[0]) / 1e9
    yaw = np.unwrap(gt[:, 2])
    return np.column_stack([np.interp(q, t, gt[:, 0]), np.interp(q, t, gt[:, 1]), wrap_angle(np.interp(q, t, yaw))])


def corrected_errors(out: Path) -> dict[str, Any]:
    """The loop-corrected keyframes against the truth: per keyframe the anchored error (m)
    and its stamp (s of robot time), the anchored APE and aligned ATE (RMS, m) and the
    rotation of the rigid fit of the anchored estimate onto the truth (deg)."""
    stamps, est = read_tum(out / "corrected.tum")
    truth = truth_at(out, stamps)
    anchored = align_origin(truth[0], est)
    err = np.hypot(*(anchored[:, :2] - truth[:, :2]).T)
    fit = rigid_fit_2d(anchored[:, :2], truth[:, :2])
    aligned = compose(fit, anchored)
    ate = np.hypot(*(aligned[:, :2] - truth[:, :2]).T)
    # the turn about the first keyframe: the heading the fit adds, at the first keyframe
    turn = compose(fit, anchored[0])
    return {"t_s": stamps / 1e9, "err_m": err,
            "ape_anchored_m": float(np.sqrt(np.mean(err ** 2))), "ate_aligned_m": float(np.sqrt(np.mean(ate ** 2))),
            "fit_turn_deg": float(math.degrees(wrap_angle(turn[2] - anchored[0, 2]))),
            "fit_shift_at_first_m": float(np.hypot(*(turn[:2] - anchored[0, :2])))}


def expected_errors(out: Path) -> dict[str, float]:
    """The graph's own expectation of the anchored error (see the module notes): RMS over the
    keyframes of the marginal position 1-sigma (``sqrt`` of the covariance's trace, m) and of
    the heading 1-sigma (deg), the first keyframe held, every stored edge, at the stored
    solution (keyframes without one at their odometry poses)."""
    import gtsam

    from robotd.graph.factors import factor_graph, to_values
    from robotd.graph.model import PoseGraph
    from robotd.io.store import MapStore

    with MapStore.open(out / "map.sqlite", create=False) as store:
        kfs = list(store.keyframes())
        links = store.links()
        opt = store.optimized_poses()
    g = PoseGraph()
    for k in kfs:
        g.add_pose(k.id, opt.get(k.id, np.array([k.x_m, k.y_m, k.yaw_rad])))
    g.fix(kfs[0].id)
    for lk in links:
        g.add_edge(lk.from_id, lk.to_id, np.array([lk.dx_m, lk.dy_m, lk.dyaw_rad]), lk.information, lk.kind)
    marginals = gtsam.Marginals(factor_graph(g), to_values(g.ids, g.poses()))
    pos, yaw = [0.0], [0.0]  # the first keyframe is held
    for k in kfs[1:]:
        c = np.asarray(marginals.marginalCovariance(int(k.id)))
        pos.append(c[0, 0] + c[1, 1])
        yaw.append(c[2, 2])
    return {"expected_ape_anchored_m": float(np.sqrt(np.mean(pos))),
            "expected_heading_sigma_deg": float(np.degrees(np.sqrt(np.mean(yaw)))),
            "sigma_t_s": np.array([k.stamp_ns for k in kfs]) / 1e9, "sigma_m": np.sqrt(pos)}


def replays(out: Path, first_s: float) -> dict[str, float]:
    """Where the anchored error comes from: the map re-solved (plain least squares from the
    true poses, the first keyframe held, every stored odometry and loop edge) as it is, with
    the odometry edges of the first ``first_s`` s replaced by the true relative poses, with
    the loops' replaced, and with every odometry edge's: the anchored APE of each (m)."""
    from robotd.base.geometry import between
    from robotd.graph.batch import BatchParams, optimize_batch
    from robotd.graph.model import PoseGraph
    from robotd.io.store import MapStore

    with MapStore.open(out / "map.sqlite", create=False) as store:
        kfs = list(store.keyframes())
        links = store.links()
    stamps = np.array([k.stamp_ns for k in kfs])
    truth = truth_at(out, stamps)
    row = {k.id: n for n, k in enumerate(kfs)}

    def solve(true_edge: Any) -> float:
        g = PoseGraph()
        for k, p in zip(kfs, truth):
            g.add_pose(k.id, p)
        g.fix(kfs[0].id)
        for lk in links:
            a, b = row[lk.from_id], row[lk.to_id]
            d = (between(truth[a], truth[b]) if true_edge(lk, stamps[b] / 1e9)
                 else np.array([lk.dx_m, lk.dy_m, lk.dyaw_rad]))
            g.add_edge(lk.from_id, lk.to_id, d, lk.information, lk.kind)
        est = optimize_batch(g, BatchParams(robust=False, initialisation="odometry")).poses
        err = np.hypot(*(align_origin(truth[0], est)[:, :2] - truth[:, :2]).T)
        return float(np.sqrt(np.mean(err ** 2)))

    return {"resolved_m": solve(lambda lk, t: False),
            "true_first_odometry_m": solve(lambda lk, t: lk.kind == "odometry" and t < first_s),
            "true_loops_m": solve(lambda lk, t: lk.kind == "loop"),
            "true_odometry_m": solve(lambda lk, t: lk.kind == "odometry")}


def route_time(t_s: np.ndarray, kidnap: tuple[float, float]) -> np.ndarray:
    """The route time of the kidnapped drive's robot times ``t_s`` (s)."""
    at, to = kidnap
    put_down = at + CARRY_S
    return np.where(t_s < at, t_s, t_s - put_down + to)


def row_of(seed: int, kid: dict[str, Any], plain: dict[str, Any], kid_err: dict[str, Any],
           plain_err: dict[str, Any], kidnap: tuple[float, float]) -> dict[str, Any]:
    """The seed's figures (see the module notes)."""
    def loops(s: dict[str, Any]) -> dict[str, Any]:
        fd = s.get("floor_detector", {})
        g = s.get("pose_graph", {})
        return {"accepted_floor": fd.get("loops_accepted"), "truly_overlapping": fd.get("loops_truly_overlapping"),
                "refused_by_gate": fd.get("refused_by_gate", 0),
                "refused_truly_overlapping": fd.get("refused_truly_overlapping", 0),
                "accepted": g.get("loops_accepted"), "in_graph": g.get("loops_in_graph"),
                "down_weighted": g.get("loops_down_weighted", 0)}

    def drive(run: dict[str, Any], err: dict[str, Any]) -> dict[str, Any]:
        s = run["summary"]
        return {"loops": loops(s), **{k: err[k] for k in ("ape_anchored_m", "ate_aligned_m", "fit_turn_deg",
                                                          "fit_shift_at_first_m", "expected_ape_anchored_m",
                                                          "expected_heading_sigma_deg", "replays")},
                "ape_anchored_m_demo": s.get("pose_graph", {}).get("loop_corrected", {}).get("ape_origin_rmse_m"),
                "keyframes": s.get("keyframes"), "wall_s": run["wall_s"], "cpu_s": run["cpu_s"]}

    ks = kid["summary"]
    r = ks.get("relocalisation", {})
    # the plain drive's own errors at the kidnapped drive's route times
    # (the demo's stamps are robot time from 0, which is route time until the lift)
    sampled = np.interp(route_time(kid_err["t_s"], kidnap), plain_err["t_s"], plain_err["err_m"])
    same_ground = float(np.sqrt(np.mean(sampled ** 2)))
    sigma = np.interp(route_time(kid_err["sigma_t_s"], kidnap), plain_err["sigma_t_s"], plain_err["sigma_m"])
    sigma_same_ground = float(np.sqrt(np.mean(sigma ** 2)))
    ka, pa = kid_err["ape_anchored_m"], plain_err["ape_anchored_m"]
    return {
        "seed": seed,
        "relocalised": bool(r.get("relocalised", False)),
        "reloc_after_s": r.get("after_s"), "reloc_after_m_true": r.get("after_m_true"),
        "reloc_position_error_m": r.get("position_error_m"), "reloc_heading_error_deg": r.get("heading_error_deg"),
        "lifts_detected": r.get("lifts_detected"), "relocalisations": r.get("relocalisations"),
        "kidnapped": drive(kid, kid_err),
        "plain": drive(plain, plain_err),
        "ratio_anchored": ka / pa if pa > 0 else math.inf,
        "ratio_aligned": kid_err["ate_aligned_m"] / plain_err["ate_aligned_m"] if plain_err["ate_aligned_m"] > 0 else math.inf,
        "plain_at_kidnapped_route_times_m": same_ground,
        "ratio_same_ground": ka / same_ground if same_ground > 0 else math.inf,
        "expected_plain_at_kidnapped_route_times_m": sigma_same_ground,
        "expected_ratio": kid_err["expected_ape_anchored_m"] / plain_err["expected_ape_anchored_m"],
        "expected_ratio_same_ground": kid_err["expected_ape_anchored_m"] / sigma_same_ground,
        "met": bool(r.get("relocalised", False) and loops(ks)["refused_truly_overlapping"] == 0 and ka <= 2 * pa),
    }


def markdown(payload: dict[str, Any]) -> list[str]:
    """The page from the bench's JSON."""
    p = payload["params"]
    rows = payload["seeds"]
    cmd = (f"robotd demo --route office --duration {p['duration_s']:g} --kidnap {p['kidnap_at_s']:g} "
           f"--kidnap-to {p['kidnap_to_s']:g} --seed N --no-plot")
    lines = ["# The kidnapped robot against the same drive without the kidnapping (generated by "
             "bench/bench_kidnap.py --markdown)", "",
             f"Per seed of the virtual robot: `{cmd}`, and the same without `--kidnap`, one demo at a "
             f"time{' with `--config ' + p['config'] + '`' if p.get('config') else ''}. The judge is the "
             "loop-corrected APE anchored at the first keyframe: the kidnapped drive's within 2x of the "
             "plain drive's, with no truly overlapping loop refused by the gate.", "",
             "| seed | relocalised after (time, true distance) | pose error then | loops accepted, truly overlapping (kidnapped / plain) | "
             "refused by the gate (truly overlapping) | APE anchored, kidnapped / plain (mm) | ratio | met | "
             "ATE aligned, kidnapped / plain (mm) | ratio | map turned by (kidnapped / plain, deg) | "
             "plain at the kidnapped drive's route times (mm) | ratio | the graph's own 1-sigma: anchored APE "
             "(kidnapped / plain, mm) | ratio | plain at the kidnapped drive's route times (mm) | ratio | "
             "heading (kidnapped / plain, deg) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        k, pl = r["kidnapped"], r["plain"]
        rel = (f"{r['reloc_after_s']:.1f} s, {r['reloc_after_m_true']:.2f} m" if r["relocalised"] else "never")
        perr = (f"{100 * r['reloc_position_error_m']:.1f} cm, {r['reloc_heading_error_deg']:.2f} deg"
                if r["relocalised"] else "-")
        lines.append(
            f"| {r['seed']} | {rel} | {perr} | {k['loops']['accepted_floor']}, {k['loops']['truly_overlapping']} / "
            f"{pl['loops']['accepted_floor']}, {pl['loops']['truly_overlapping']} | "
            f"{k['loops']['refused_by_gate']} ({k['loops']['refused_truly_overlapping']}) / "
            f"{pl['loops']['refused_by_gate']} ({pl['loops']['refused_truly_overlapping']}) | "
            f"{1e3 * k['ape_anchored_m']:.1f} / {1e3 * pl['ape_anchored_m']:.1f} | {r['ratio_anchored']:.2f}x | "
            f"{'yes' if r['met'] else 'no'} | "
            f"{1e3 * k['ate_aligned_m']:.1f} / {1e3 * pl['ate_aligned_m']:.1f} | {r['ratio_aligned']:.2f}x | "
            f"{k['fit_turn_deg']:+.4f} / {pl['fit_turn_deg']:+.4f} | "
            f"{1e3 * r['plain_at_kidnapped_route_times_m']:.1f} | {r['ratio_same_ground']:.2f}x | "
            f"{1e3 * k['expected_ape_anchored_m']:.1f} / {1e3 * pl['expected_ape_anchored_m']:.1f} | "
            f"{r['expected_ratio']:.2f}x | {1e3 * r['expected_plain_at_kidnapped_route_times_m']:.1f} | "
            f"{r['expected_ratio_same_ground']:.2f}x | "
            f"{k['expected_heading_sigma_deg']:.3f} / {pl['expected_heading_sigma_deg']:.3f} |")
    met = sum(r["met"] for r in rows)
    lines += ["", f"Met on {met} of {len(rows)} seeds. Loops: the floor loops the gate accepted, and of "
              "them those that truly overlap (footprint overlap); refused: by the chi-square gate (in brackets those that truly overlap, by footprint "
              "overlap). The map's turn is the rotation of the rigid fit of the anchored loop-corrected "
              "keyframes onto the truth: the part of the anchored APE that the aligned ATE removes. The "
              "last two columns sample the plain drive's own anchored keyframe errors at the route times "
              "the kidnapped drive drove (the route's first "
              f"{p['kidnap_at_s']:g} s, then from {p['kidnap_to_s']:g} s again), the like-for-like "
              "baseline beside the judge. The graph's own 1-sigma: the RMS over the keyframes of "
              "their marginal position and heading standard deviations with the first keyframe "
              "held (every stored odometry and loop edge at the stored solution): what the map "
              "itself knows of the anchored error, over all its keyframes and, for the plain drive, "
              "at the kidnapped drive's route times.", ""]
    lines += ["## Where the anchored error comes from", "",
              "Each drive's map re-solved (plain least squares, the first keyframe held, every stored "
              "odometry and loop edge; the daemon's full solve holds one loop per place, about 20, so its "
              f"figures differ) as it is, with the odometry edges of the first {p['kidnap_to_s']:g} s (the "
              "stretch the kidnapped drive drives once, before the ground it is put down on) from the "
              "truth, with the loops from the truth, and with all odometry from the truth: the "
              "anchored APE (mm), kidnapped / plain.", "",
              f"| seed | re-solved | odometry of the first {p['kidnap_to_s']:g} s true | loops true | "
              "all odometry true |", "|---|---|---|---|---|"]
    for r in rows:
        k, pl = r["kidnapped"]["replays"], r["plain"]["replays"]
        lines.append(f"| {r['seed']} | " + " | ".join(
            f"{1e3 * k[key]:.1f} / {1e3 * pl[key]:.1f}"
            for key in ("resolved_m", "true_first_odometry_m", "true_loops_m", "true_odometry_m")) + " |")
    lines.append("")
    cpu = [x for r in rows for x in (r["kidnapped"]["cpu_s"], r["plain"]["cpu_s"]) if x is not None]
    if cpu:
        lines += [f"CPU per demo {min(cpu):.0f}-{max(cpu):.0f} s (user + system).", ""]
    return lines


def main(argv: list[str] | None = None) -> int:
    from robotd.app.demo import KIDNAP_CARRY_S

    if KIDNAP_CARRY_S != CARRY_S:
        raise SystemExit(f"the demo carries for {KIDNAP_CARRY_S} s, this bench assumes {CARRY_S}")
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--full", action="store_true", help="a 220 s drive kidnapped at 110 s to 40 s")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench-kidnap"), help="the demos' output folders")
    ap.add_argument("--reuse", action="store_true", help="keep a run whose summary.json is in --work")
    ap.add_argument("--config", type=Path, default=None, help="the demos' --config")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--markdown", type=Path, default=None)
    ap.add_argument("--page-from", type=Path, default=None, help="measure nothing: write --markdown from this JSON")
    args = ap.parse_args(argv)
    if args.page_from is not None:
        if args.markdown is None:
            ap.error("--page-from needs --markdown")
        write_page(args.markdown, markdown(json.loads(args.page_from.read_text())))
        return 0
    duration, at, to = (220.0, 110.0, 40.0) if args.full else (120.0, 60.0, 20.0)
    seeds = [int(s) for s in args.seeds.split(",")]
    config = args.config.resolve() if args.config is not None else None
    rows = []
    for seed in seeds:
        runs = {}
        for name, kidnap in (("kidnapped", (at, to)), ("plain", None)):
            out = (args.work / f"seed{seed}-{name}").resolve()
            log(f"seed {seed} {name}: {out}")
            runs[name] = run_demo(out, seed, duration, kidnap, config, args.reuse)
        errs = {name: {**corrected_errors((args.work / f"seed{seed}-{name}").resolve()),
                       **expected_errors((args.work / f"seed{seed}-{name}").resolve()),
                       "replays": replays((args.work / f"seed{seed}-{name}").resolve(), to)} for name in runs}
        rows.append(row_of(seed, runs["kidnapped"], runs["plain"], errs["kidnapped"], errs["plain"], (at, to)))
        r = rows[-1]
        log(f"seed {seed}: APE anchored {1e3 * r['kidnapped']['ape_anchored_m']:.2f} / "
            f"{1e3 * r['plain']['ape_anchored_m']:.2f} mm ({r['ratio_anchored']:.2f}x)")
    head = ["seed", "reloc s", "reloc err cm", "refused (true)", "APE k/p mm", "ratio", "ATE k/p mm", "ratio",
            "turn k deg", "same ground ratio", "1-sigma APE k/p mm", "1-sigma ratio", "same ground"]
    print_table(head, [[r["seed"], round(r["reloc_after_s"] or math.nan, 2),
                        round(100 * (r["reloc_position_error_m"] or math.nan), 2),
                        f"{r['kidnapped']['loops']['refused_by_gate']} ({r['kidnapped']['loops']['refused_truly_overlapping']})",
                        f"{1e3 * r['kidnapped']['ape_anchored_m']:.2f}/{1e3 * r['plain']['ape_anchored_m']:.2f}",
                        round(r["ratio_anchored"], 2),
                        f"{1e3 * r['kidnapped']['ate_aligned_m']:.2f}/{1e3 * r['plain']['ate_aligned_m']:.2f}",
                        round(r["ratio_aligned"], 2), round(r["kidnapped"]["fit_turn_deg"], 4),
                        round(r["ratio_same_ground"], 2),
                        f"{1e3 * r['kidnapped']['expected_ape_anchored_m']:.2f}/"
                        f"{1e3 * r['plain']['expected_ape_anchored_m']:.2f}", round(r["expected_ratio"], 2),
                        round(r["expected_ratio_same_ground"], 2)] for r in rows])
    payload = {"machine": machine_info(), "params": {"duration_s": duration, "kidnap_at_s": at, "kidnap_to_s": to,
                                                     "carry_s": CARRY_S, "config": str(args.config) if args.config else None},
               "seeds": rows}
    path = write_json(args.out, payload)
    print(f"\nwrote {path}")
    if args.markdown is not None:
        write_page(args.markdown, markdown(payload))
    return 0


if __name__ == "__main__":
    sys.exit(main())
