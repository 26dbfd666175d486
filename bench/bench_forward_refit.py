"""The forward stage's planar refit (:mod:`robotd.app.stages.forward_loops`) on a demo's
forward images: CPU time of its parts per verified view, against a baseline revision of
the code in the same run, and whether the two give the same fits.

For each stored forward image of the map (``robotd demo --forward`` writes them) the
nearest older image by the keyframes' poses (at least 20 images older, within 0.8 m and
25 deg) is verified as the daemon's detector verifies (its default parameters, the map's
camera); each accepted view is refitted as the stage refits it:

- ``match``: the two images' matches (read from the verification's ``match_index``);
- ``scan``: the heading scan around the verified and the level motion's heading (one scan
  when both round to one lattice heading; ``fit_planar_scans``), the fit with more inliers
  kept;
- ``ridge``: the fixed-heading fits of a loop on a heading-bearing ridge (at the kept fit's
  heading with its sigmas, and 0.5 deg either side for the bearing's slope without them),
  run for every view here (in the daemon only ridge loops run them).

The baseline's ``robotd/forward/planefit.py`` is read from ``--baseline-rev`` (``git
show``); everything else is this checkout's. With ``--baseline-calls current`` (default)
the baseline's side makes the same calls, so the ratio is ``planefit.py``'s alone; with
``earlier`` it makes the stage's calls from before its refit read the verification's
matches (matched again, one ``fit_planar`` per centre, the ridge's side fits with their
sigmas). Before and after alternate per view, each part timed by the thread's CPU clock,
``--repeats`` times. The fits are compared to the bit (heading, bearing, inliers, the
scan's profile and sigmas; the ridge fits' bearings).

Run: ``python bench/bench_forward_refit.py --map DEMO_OUT/map.sqlite --baseline-rev REV [--baseline-calls C]
[--pairs 80] [--repeats 5] [--label TEXT] [--out DIR] [--page FILE.md]`` (a few minutes).
Writes ``forward_refit.json`` and, with ``--page``, its Markdown page; ``--page-from JSON
--page FILE.md`` writes the page of a kept JSON only. Besides the fits identical to the
bit, it counts those the same up to rounding (the same inliers and profile, heading,
bearings and sigmas within 1e-6).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sqlite3
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's robotd first
import numpy as np  # noqa: E402

try:
    from bench.common import REPO_ROOT, git_commit, machine_info, module_at_revision, write_json, write_page
except ImportError:  # run as a script: bench/ is on sys.path
    from common import REPO_ROOT, git_commit, machine_info, module_at_revision, write_json, write_page

PARTS = ("match", "scan", "ridge")


def baseline_planefit(rev: str) -> Any:
    """``robotd/forward/planefit.py`` as it is at git revision ``rev``, as a module."""
    return module_at_revision(rev, "robotd/forward/planefit.py", "baseline_planefit")


def load_views(map_path: Path, max_pairs: int) -> tuple[np.ndarray, list[tuple[Any, Any, Any]]]:
    """The map's camera matrix and up to ``max_pairs`` accepted verifications ``(old, new,
    verification)`` (module notes)."""
    from robotd.forward import method_params
    from robotd.forward.detector import daemon_params
    from robotd.forward.features import CompactFeatures
    from robotd.forward.verify import verify_pair

    con = sqlite3.connect(f"file:{map_path}?mode=ro", uri=True)
    cam = tomllib.loads(con.execute("SELECT config FROM runs ORDER BY id LIMIT 1").fetchone()[0])["forward_camera"]
    k = np.array([[cam["fx_px"], 0.0, cam["cx_px"]], [0.0, cam["fy_px"], cam["cy_px"]], [0.0, 0.0, 1.0]])
    rows = con.execute("SELECT f.image_id, k.x_m, k.y_m, k.yaw_rad, f.image_width, f.image_height, f.keypoints, "
                       "f.descriptors FROM forward_images f JOIN keyframes k ON k.id = f.keyframe_id "
                       "ORDER BY f.image_id").fetchall()
    pose = np.array([[r[1], r[2], r[3]] for r in rows])
    feats = [CompactFeatures(np.zeros(0, np.uint32), np.frombuffer(r[6], "<u2").astype(np.uint16).reshape(-1, 2),
                             np.frombuffer(r[7], np.uint8).reshape(-1, 32), (r[4], r[5])) for r in rows]
    vp = daemon_params(method_params("default")).verify
    views = []
    for i in range(len(rows)):
        j_max = i - 20
        if j_max <= 0:
            continue
        d = np.hypot(*(pose[:j_max, :2] - pose[i, :2]).T)
        turn = np.abs(np.remainder(pose[:j_max, 2] - pose[i, 2] + math.pi, math.tau) - math.pi)
        ok = np.flatnonzero((d < 0.8) & (turn < math.radians(25.0)))
        if not len(ok):
            continue
        j = int(ok[np.argmin(d[ok])])
        v = verify_pair(feats[j], feats[i], vp, k)
        if v.accepted and v.rotation is not None:
            views.append((feats[j], feats[i], v))
        if len(views) >= max_pairs:
            break
    return k, views


def refit(pf: Any, now: bool, old: Any, new: Any, v: Any, k: np.ndarray, thr: float, ratio: float,
          times: dict[str, float]) -> tuple[Any, list[float]]:
    """The stage's refit of one view (module notes) with planefit module ``pf``, ``now``
    the current code's way; adds each part's CPU ms to ``times``; the kept fit and the
    ridge fits' bearings."""
    from robotd.forward.planar import planar_motion
    from robotd.forward.verify import match_features

    t0 = time.thread_time()
    if now:
        ia, ib = v.match_index
        p_old, p_new = old.keypoints_px[ia], new.keypoints_px[ib]
    else:
        p_old, p_new = match_features(old, new, ratio)
    t1 = time.thread_time()
    verified, _, _ = planar_motion(v.rotation, v.translation_dir)
    level = float(v.level_yaw_rad)
    step = pf.SCAN_STEP_RAD
    centres = [verified] if not math.isfinite(level) or round(level / step) == round(verified / step) \
        else [verified, level]
    fits = pf.fit_planar_scans(p_old, p_new, k, centres, threshold_px=thr) if now else \
        [pf.fit_planar(p_old, p_new, k, c, threshold_px=thr) for c in centres]
    fit = None
    for f in fits:
        if f is not None and (fit is None or f.n_inliers > fit.n_inliers):
            fit = f
    t2 = time.thread_time()
    bearings: list[float] = []
    if fit is not None:
        yaw, side = fit.dyaw_rad, math.radians(0.5)
        if now and hasattr(pf, "fit_planar_fixed"):  # the three in one call, as the stage makes them
            best, *sides = pf.fit_planar_fixed(p_old, p_new, k, [yaw, yaw - side, yaw + side], [True, False, False],
                                               threshold_px=thr)
        else:
            best = pf.fit_planar(p_old, p_new, k, yaw, threshold_px=thr, fix_yaw=True)
            extra = {"sigmas": False} if now else {}
            sides = [pf.fit_planar(p_old, p_new, k, y, threshold_px=thr, fix_yaw=True, **extra)
                     for y in (yaw - side, yaw + side)]
        bearings = [f.bearing_rad if f is not None else math.nan for f in [best, *sides]]
        if best is not None:
            bearings.append(best.sigma_bearing_rad)
    t3 = time.thread_time()
    for part, a, b in (("match", t0, t1), ("scan", t1, t2), ("ridge", t2, t3)):
        times[part] += (b - a) * 1e3
    return fit, bearings


def same(a: Any, b: Any) -> bool:
    if a is None or b is None:
        return a is b
    return bool(a.dyaw_rad == b.dyaw_rad and a.bearing_rad == b.bearing_rad and np.array_equal(a.inliers, b.inliers)
                and a.sigma_bearing_rad == b.sigma_bearing_rad and a.sigma_yaw_rad == b.sigma_yaw_rad
                and np.array_equal(a.scan_yaw_rad, b.scan_yaw_rad) and np.array_equal(a.scan_inliers, b.scan_inliers))


def close(a: Any, b: Any, tol: float = 1e-6) -> bool:
    """The same fit up to rounding: the same inliers and scan profile, heading, bearing and
    sigmas within ``tol`` (radians; the sigmas relative)."""
    if a is None or b is None:
        return a is b

    def near(x: float, y: float, rel: bool = False) -> bool:
        if not (math.isfinite(x) and math.isfinite(y)):
            return x == y or (math.isnan(x) and math.isnan(y))
        return abs(x - y) <= tol * (max(abs(x), abs(y)) if rel else 1.0)

    return bool(np.array_equal(a.inliers, b.inliers) and np.array_equal(a.scan_yaw_rad, b.scan_yaw_rad)
                and np.array_equal(a.scan_inliers, b.scan_inliers) and near(a.dyaw_rad, b.dyaw_rad)
                and abs(math.remainder(a.bearing_rad - b.bearing_rad, math.tau)) <= tol
                and near(a.sigma_bearing_rad, b.sigma_bearing_rad, True) and near(a.sigma_yaw_rad, b.sigma_yaw_rad, True))


def page_lines(out: dict[str, Any], json_name: str = "forward_refit.json") -> list[str]:
    """The benchmark's Markdown page from its JSON ``out`` (kept as ``json_name``)."""
    m, pv, off = out["machine"], out["per_view_ms"], out["level_minus_verified_deg"]
    lines = ["# The forward stage's planar refit, per verified view", "",
             f"Generated by `bench/bench_forward_refit.py` from `{json_name}` (read in "
             "[forward.md](../forward.md), \"Time per forward keyframe\"). The stage's refit of each view verified on "
             f"{out['label']} ({out['views']} views, {out['two_scans']} of them scanned around two headings; the level "
             f"motion's heading {off['median']} deg from the verified one at the median, {off['p90']} at the 90th "
             f"percentile), the current code against the baseline revision's `planefit.py` in the same run "
             + ("(the same calls on both sides; the ridge's three fits one `fit_planar_fixed` call where the current "
                "code has it), " if out.get("baseline_calls", "earlier") == "current" else
                "(the baseline making the stage's earlier calls: matched again, one scan per centre, the ridge's "
                "side fits with sigmas), ")
             + f"alternating per view, {out['repeats']} times each; CPU ms per view (the thread's clock). "
             f"Machine: {m.get('machine')}, {m.get('cpu_count')} cores, numpy {m.get('numpy')}; load average "
             f"{out['load'][0]} at the start, {out['load'][1]} at the end.", "",
             "| part | baseline | now | now / baseline |", "|---|---:|---:|---:|"]
    for r in out["parts"]:
        lines.append(f"| {r['part']} | {r['baseline_cpu_ms_per_view']:.2f} | {r['now_cpu_ms_per_view']:.2f} | "
                     f"{r['ratio']:.2f} |")
    lines += [f"| **all three** | {pv['baseline_median']} (median) | {pv['now_median']} (median) | "
              f"**{out['ratio_total']:.2f}** (totals) |", "",
              f"Fits identical to the bit (heading, bearing, inliers, sigmas, the scan's profile; the ridge fits' "
              f"bearings): {out['identical_fits']} of {out['views']} views"
              + (f"; the same up to rounding (the same inliers and profile, heading, bearings and sigmas within "
                 f"1e-6): {out['same_fits_to_rounding']}" if "same_fits_to_rounding" in out else "")
              + ". The ridge's fits run here for every view; in the daemon only for loops on a heading-bearing "
              "ridge.", ""]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", type=Path, help="a forward demo's map.sqlite (required unless --page-from)")
    ap.add_argument("--baseline-rev",
                    help="git revision of the baseline's planefit.py (the code before the change measured; "
                         "the current branch against itself measures nothing)")
    ap.add_argument("--baseline-calls", choices=("current", "earlier"), default="current",
                    help="the stage's calls on the baseline's side: 'current' (the same calls as now, so the "
                         "ratio is planefit.py's alone) or 'earlier' (matched again, one fit_planar per centre, "
                         "the ridge's side fits with sigmas: the stage before its refit read the verification's "
                         "matches)")
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--label", default=None, help="what the map is, for the page (default: its path)")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results")
    ap.add_argument("--page", type=Path, default=None, help="also write the Markdown page here")
    ap.add_argument("--page-from", type=Path, default=None,
                    help="measure nothing: write --page from this JSON (a run's, kept under another name)")
    args = ap.parse_args(argv)
    if args.page_from is not None:
        if args.page is None:
            ap.error("--page-from needs --page")
        out = json.loads(args.page_from.read_text(encoding="utf-8"))
        write_page(args.page, page_lines(out, args.page_from.name))
        print(f"wrote {args.page}")
        return 0
    if args.map is None or args.baseline_rev is None:
        ap.error("--map and --baseline-rev are required (unless --page-from)")
    from robotd.forward import method_params
    from robotd.forward import planefit as now_pf
    from robotd.forward.detector import daemon_params

    load0 = round(os.getloadavg()[0], 1)
    base_pf = baseline_planefit(args.baseline_rev)
    vp = daemon_params(method_params("default")).verify
    k, views = load_views(args.map, args.pairs)
    before = {p: 0.0 for p in PARTS}
    after = {p: 0.0 for p in PARTS}
    per_view: list[tuple[float, float]] = []
    identical = rounding = two_scans = 0
    offsets = []
    for n, (old, new, v) in enumerate(views):
        vb, va = 0.0, 0.0
        for r in range(args.repeats):
            for now in ((False, True) if (n + r) % 2 == 0 else (True, False)):
                t = after if now else before
                s0 = sum(t.values())
                calls_now = now or args.baseline_calls == "current"
                got = refit(now_pf if now else base_pf, calls_now, old, new, v, k, vp.ransac_threshold_px, vp.ratio,
                            t)
                if now:
                    va += sum(t.values()) - s0
                    got_now = got
                else:
                    vb += sum(t.values()) - s0
                    got_base = got
        per_view.append((vb / args.repeats, va / args.repeats))
        bear_b, bear_n = got_base[1], got_now[1]
        sides_equal = bear_b[:3] == bear_n[:3] and (len(bear_b) < 4 or bear_b[3] == bear_n[3])
        identical += same(got_base[0], got_now[0]) and sides_equal
        sides_close = len(bear_b) == len(bear_n) and all(
            (math.isnan(x) and math.isnan(y)) or abs(math.remainder(x - y, math.tau)) <= 1e-6 * max(1.0, abs(x))
            for x, y in zip(bear_b, bear_n))
        rounding += close(got_base[0], got_now[0]) and sides_close
        from robotd.forward.planar import planar_motion

        verified = planar_motion(v.rotation, v.translation_dir)[0]
        if math.isfinite(v.level_yaw_rad):
            off = abs(math.degrees(math.remainder(v.level_yaw_rad - verified, math.tau)))
            offsets.append(off)
            two_scans += round(v.level_yaw_rad / now_pf.SCAN_STEP_RAD) != round(verified / now_pf.SCAN_STEP_RAD)
    reps = args.repeats
    rows = [{"part": p, "baseline_cpu_ms_per_view": round(before[p] / reps / max(len(views), 1), 3),
             "now_cpu_ms_per_view": round(after[p] / reps / max(len(views), 1), 3),
             "ratio": round(after[p] / max(before[p], 1e-9), 3)} for p in PARTS]
    tot_b, tot_a = sum(before.values()), sum(after.values())
    pv = np.array(per_view) if per_view else np.zeros((0, 2))
    out = {"machine": machine_info(), "commit": git_commit(), "baseline_rev": args.baseline_rev,
           "baseline_calls": args.baseline_calls,
           "baseline_commit": subprocess.run(["git", "rev-parse", args.baseline_rev], cwd=REPO_ROOT,
                                             capture_output=True, text=True).stdout.strip(),
           "load": [load0, round(os.getloadavg()[0], 1)], "map": str(args.map), "label": args.label or str(args.map), "views": len(views), "repeats": reps, "identical_fits": identical,
           "same_fits_to_rounding": rounding,
           "two_scans": two_scans,
           "level_minus_verified_deg": {"median": round(float(np.median(offsets)), 2) if offsets else None,
                                        "p90": round(float(np.percentile(offsets, 90)), 2) if offsets else None,
                                        "max": round(float(np.max(offsets)), 2) if offsets else None},
           "parts": rows, "ratio_total": round(tot_a / max(tot_b, 1e-9), 3),
           "per_view_ms": {"baseline_median": round(float(np.median(pv[:, 0])), 2) if len(pv) else None,
                           "now_median": round(float(np.median(pv[:, 1])), 2) if len(pv) else None,
                           "baseline_max": round(float(pv[:, 0].max()), 2) if len(pv) else None,
                           "now_max": round(float(pv[:, 1].max()), 2) if len(pv) else None}}
    print(f"{len(views)} verified views, {two_scans} with two scans; fits identical in {identical}, "
          f"the same to rounding in {rounding}")
    print(f"{'part':>6} | {'baseline ms/view':>16} | {'now ms/view':>11} | ratio")
    for r in rows:
        print(f"{r['part']:>6} | {r['baseline_cpu_ms_per_view']:>16.3f} | {r['now_cpu_ms_per_view']:>11.3f} | "
              f"{r['ratio']:.3f}")
    print(f"total ratio {out['ratio_total']}; per view median {out['per_view_ms']}")
    print(f"level - verified heading (deg): {out['level_minus_verified_deg']}")
    path = write_json(args.out / "forward_refit.json", out)
    print(f"wrote {path}")
    if args.page is not None:
        write_page(args.page, page_lines(out))
        print(f"wrote {args.page}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
