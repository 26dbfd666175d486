"""Where a demo map's anchored error sits: the whole map's turn about its first keyframe,
and which edges make it.

For each ``robotd demo --out DIR`` given (its ``map.sqlite``, ``corrected.tum`` and
``groundtruth.tum``): the corrected keyframes against the truth (APE anchored at the first
keyframe, the single turn about it that fits the truth best, the keyframes' mean yaw
error), then the same graph linearised at the truth. The daemon's full solve holds only
the loops its live graph admitted (:meth:`robotd.graph.incremental.IncrementalGraph.add_loop`:
a few dozen of the thousand-odd the map stores), replayed here in the map's link order
(the one loop each full solve adds back is not); the odometry edges are independent, each
with its stored information (a bias-window run's own solve is not reproduced, its edges
are). Each edge's error against the truth enters that least-squares problem, the first
keyframe fixed; the correction is linear in those errors, so parts of them can be set to
zero to see what each part makes: the loops' errors, the odometry edges' errors, their
heading errors alone, those of the first 10 or 40 odometry edges alone (the drive's first
seconds, before the loops), and the odometry edges' mean heading drift (their heading
error per second of the drive). ``every loop`` solves with all the map's loops instead.

Run: ``python bench/bench_map_turn.py DIR [DIR ...] [--labels A,B,...] [--out FILE.json]
[--markdown FILE.md]`` (seconds per map).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's robotd first
import numpy as np  # noqa: E402

try:
    from bench.common import machine_info, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, write_json

MDEG = 1e3 * 180.0 / math.pi

#: The odometry edges from the first keyframes whose heading errors a variant sets to zero.
FIRST_EDGES = (10, 40)


def load_run(out: Path) -> dict[str, Any]:
    """A demo's keyframes (ids, stamps), the truth at them, its links and corrected poses."""
    from robotd.io.store import MapStore
    from robotd.io.trajectory import read_tum

    with MapStore.open(out / "map.sqlite", create=False, read_only=True) as store:
        kfs = list(store.keyframes())
        links = store.links()
    ids = np.array([k.id for k in kfs], np.int64)
    stamps = np.array([k.stamp_ns for k in kfs], np.int64)
    gt_t, gt_p = read_tum(out / "groundtruth.tum")
    truth = np.stack([np.interp(stamps, gt_t, gt_p[:, 0]), np.interp(stamps, gt_t, gt_p[:, 1]),
                      np.interp(stamps, gt_t, np.unwrap(gt_p[:, 2]))], 1)
    ct, cp = read_tum(out / "corrected.tum")
    if len(ct) != len(ids) or np.any(ct != stamps):
        raise SystemExit(f"{out}: corrected.tum does not list the map's keyframes")
    return {"ids": ids, "stamps": stamps, "truth": truth, "links": links, "corrected": cp}


def admitted_loops(links: list[Any]) -> list[Any]:
    """The loop links the daemon's live graph lets in, offered in the map's link order."""
    from robotd.graph.incremental import IncrementalGraph

    g = IncrementalGraph()
    return [lk for lk in links if lk.kind == "loop" and g._admit_loop(lk.from_id, lk.to_id)]


def turn_about_start(truth: np.ndarray, anchored: np.ndarray) -> float:
    """The single angle (rad) about the first keyframe that turns ``anchored``'s positions
    best onto the truth's (the sign: the map turned by minus it)."""
    rel_e = anchored[:, :2] - truth[0, :2]
    rel_t = truth[:, :2] - truth[0, :2]
    return float(math.atan2(np.sum(rel_e[:, 0] * rel_t[:, 1] - rel_e[:, 1] * rel_t[:, 0]), np.sum(rel_e * rel_t)))


def demo_figures(run: dict[str, Any]) -> dict[str, float]:
    """The corrected map against the truth, as the demo wrote it."""
    from robotd.base.geometry import wrap_angle
    from robotd.evaluation.metrics import align_origin

    truth = run["truth"]
    anc = align_origin(truth[0], run["corrected"])
    err = np.hypot(*(anc[:, :2] - truth[:, :2]).T)
    return {"ape_anchored_mm": 1e3 * float(np.sqrt(np.mean(err ** 2))),
            "turn_mdeg": MDEG * turn_about_start(truth, anc),
            "yaw_mean_mdeg": MDEG * float(np.mean(wrap_angle(anc[:, 2] - truth[:, 2])))}


def edge_arrays(run: dict[str, Any], links: list[Any]) -> dict[str, np.ndarray]:
    """Per link: its ends (rows), its error against the truth (``log(delta^-1 truth_ij)``,
    in its end's frame), its information, whether it is odometry, its duration (s)."""
    from robotd.base.geometry import between, se2_log

    row = {int(k): n for n, k in enumerate(run["ids"].tolist())}
    truth, stamps = run["truth"], run["stamps"]
    ends = np.array([(row[lk.from_id], row[lk.to_id]) for lk in links], np.int64)
    err = np.array([se2_log(between(np.array([lk.dx_m, lk.dy_m, lk.dyaw_rad]), between(truth[i], truth[j])))
                    for lk, (i, j) in zip(links, ends)])
    info = np.array([np.asarray(lk.information, float).reshape(3, 3) for lk in links])
    odo = np.array([lk.kind == "odometry" for lk in links])
    dt = np.abs(stamps[ends[:, 1]] - stamps[ends[:, 0]]) * 1e-9
    return {"ends": ends, "err": err, "info": info, "odo": odo, "dt": dt}


def linear_solve(truth: np.ndarray, ends: np.ndarray, err: np.ndarray, info: np.ndarray) -> dict[str, float]:
    """The graph's least-squares correction of the truth given the edges' errors (right
    perturbations of every keyframe, the first one fixed), and what it makes of the map."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    n, m = len(truth), len(ends)
    rows, cols, vals = [], [], []
    rhs = np.zeros(3 * m)
    for k, (i, j) in enumerate(ends.tolist()):
        c, s = math.cos(truth[j, 2] - truth[i, 2]), math.sin(truth[j, 2] - truth[i, 2])
        rt = np.array([[c, s], [-s, c]])  # the edge's rotation, transposed
        t = np.array([[math.cos(truth[i, 2]), math.sin(truth[i, 2])],
                      [-math.sin(truth[i, 2]), math.cos(truth[i, 2])]]) @ (truth[j, :2] - truth[i, :2])
        adj = np.eye(3)  # the adjoint of the edge's inverse: how a perturbation of i reaches j's frame
        adj[:2, :2] = rt
        adj[:2, 2] = -rt @ np.array([t[1], -t[0]])
        w = np.linalg.cholesky(info[k]).T  # w^T w = information
        for blk, col in ((w, 3 * j), (-w @ adj, 3 * i)):
            r, cc = np.nonzero(np.ones((3, 3)))
            rows.extend((3 * k + r).tolist())
            cols.extend((col + cc).tolist())
            vals.extend(blk[r, cc].tolist())
        rhs[3 * k:3 * k + 3] = -w @ err[k]
    a = coo_matrix((vals, (rows, cols)), shape=(3 * m, 3 * n)).tocsc()
    keep = np.arange(3, 3 * n)  # the first keyframe fixed
    a = a[:, keep]
    dx = np.zeros(3 * n)
    dx[3:] = spsolve((a.T @ a).tocsc(), a.T @ rhs)
    d = dx.reshape(n, 3)
    c, s = np.cos(truth[:, 2]), np.sin(truth[:, 2])
    dp = np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]], 1)  # world displacement
    corrected = truth.copy()
    corrected[:, :2] += dp
    corrected[:, 2] += d[:, 2]
    return {"ape_anchored_mm": 1e3 * float(np.sqrt(np.mean(np.sum(dp ** 2, 1)))),
            "turn_mdeg": MDEG * turn_about_start(truth, corrected),
            "yaw_mean_mdeg": MDEG * float(np.mean(d[:, 2]))}


def analyse(out: Path) -> dict[str, Any]:
    """The demo's figures and the linearised graph's, whole and in parts (module notes)."""
    run = load_run(out)
    links = run["links"]
    odometry = [lk for lk in links if lk.kind == "odometry"]
    loops = admitted_loops(links)
    e = edge_arrays(run, odometry + loops)
    o = e["odo"]
    drift = float(np.sum(e["err"][o, 2]) / np.sum(e["dt"][o]))  # rad/s, the truth's minus the edges'
    truth = run["truth"]
    variants: dict[str, np.ndarray] = {"as the daemon's graph": e["err"]}
    v = e["err"].copy()
    v[~o] = 0.0
    variants["loops exact"] = v
    v = e["err"].copy()
    v[o] = 0.0
    variants["odometry exact"] = v
    v = e["err"].copy()
    v[o, 2] = 0.0
    variants["odometry heading exact"] = v
    v = e["err"].copy()
    v[o, 2] -= drift * e["dt"][o]
    variants["odometry drift removed"] = v
    for first in FIRST_EDGES:
        v = e["err"].copy()
        v[o & (e["ends"][:, 0] < first), 2] = 0.0
        variants[f"first {first} odometry edges' heading exact"] = v
    out_v = {name: linear_solve(truth, e["ends"], err, e["info"]) for name, err in variants.items()}
    every = edge_arrays(run, odometry + [lk for lk in links if lk.kind == "loop"])
    out_v["every loop"] = linear_solve(truth, every["ends"], every["err"], every["info"])
    return {"keyframes": len(run["ids"]), "loops_stored": int(sum(lk.kind == "loop" for lk in links)),
            "loops_in_graph": len(loops), "odometry_heading_drift_mdeg_per_s": -MDEG * drift,
            "odometry_yaw_sigma_mdeg": MDEG * float(np.median(np.sqrt(np.linalg.inv(e["info"][o])[:, 2, 2]))),
            "demo": demo_figures(run), "linear": out_v}


def markdown(payload: dict[str, Any]) -> list[str]:
    """The page: one row per run and variant."""
    lines = ["# Where a demo map's anchored error sits", "",
             "Generated by `bench/bench_map_turn.py` (see its docstring for the method). Turn: the single "
             "angle about the first keyframe that brings the anchored map's positions best onto the truth; "
             "yaw mean: the keyframes' mean heading error. `demo`: the run's own corrected map; the other "
             "rows the daemon's graph linearised at the truth with independent odometry edges, the named "
             "errors set to zero.", "",
             f"Machine: {payload['machine'].get('machine', '?')}, Python {payload['machine'].get('python', '?')}.", "",
             "| run | loops in the graph (stored) | odometry heading drift (mdeg/s) | odometry yaw sigma, median (mdeg) "
             "| solve | APE anchored (mm) | turn (mdeg) | yaw mean (mdeg) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in payload["runs"]:
        head = (f"| {r['label']} | {r['loops_in_graph']} ({r['loops_stored']}) | "
                f"{r['odometry_heading_drift_mdeg_per_s']:+.1f} | {r['odometry_yaw_sigma_mdeg']:.1f} ")
        rows = [("demo", r["demo"])] + list(r["linear"].items())
        for n, (name, f) in enumerate(rows):
            lead = head if n == 0 else "| | | | "
            lines.append(f"{lead}| {name} | {f['ape_anchored_mm']:.2f} | {f['turn_mdeg']:+.1f} | {f['yaw_mean_mdeg']:+.1f} |")
    lines.append("")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="robotd demo --out folders")
    ap.add_argument("--labels", default="", help="comma-separated names of the runs (default: the folders)")
    ap.add_argument("--out", type=Path, help="JSON to write")
    ap.add_argument("--markdown", type=Path, help="markdown page to write")
    args = ap.parse_args(argv)
    labels = args.labels.split(",") if args.labels else [str(p) for p in args.runs]
    if len(labels) != len(args.runs):
        ap.error(f"--labels names {len(labels)} runs, {len(args.runs)} given")
    runs = []
    for label, path in zip(labels, args.runs):
        r = analyse(path)
        r["label"] = label
        runs.append(r)
        print(f"{label}: drift {r['odometry_heading_drift_mdeg_per_s']:+.1f} mdeg/s, "
              + "; ".join(f"{k} turn {f['turn_mdeg']:+.1f}" for k, f in [("demo", r["demo"]), *r["linear"].items()]),
              flush=True)
    payload = {"machine": machine_info(), "runs": runs}
    if args.out:
        write_json(args.out, payload)
    if args.markdown:
        args.markdown.write_text("\n".join(markdown(payload)) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
