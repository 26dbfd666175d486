"""How well the local score tells overlapping frames from the rest, against OpenCV SIFT.

Three parts, our descriptor (modes 1-6) and SIFT on the same images in the same run:

(a) **Overlap separation.** Per floor, ``--pairs`` random frame pairs from the virtual
    robot (``sim.pairs.random_pairs``: 70 % with B within 0.4 m of A at any
    heading, the rest anywhere in a 5 x 5 m area), labelled by the ground-truth footprint
    overlap J (paper 003 eq. 3-4): a loop when J >= 0.33. The ROC AUC of the local score
    (rank statistic, ties half) for loop vs not (target: >= 0.99 for modes 3-6 on every
    floor; mode 6 at least SIFT's), and, to tell distinctiveness from overlap estimation,
    the AUC of loops vs pairs that share no floor at all (J = 0). Score distributions per
    floor and mode: ``floor_quality_scores.png``.
(b) **Graffiti.** ``graf1.png`` vs ``graf3.png`` (``../shared/data/features``) with the
    ground-truth homography ``H1to3p.xml``: a correspondence (p1, p3) is correct when
    ``H p1`` lands within 5 px of p3. Ours: the inlier correspondences of ``local_score``;
    SIFT: its RANSAC inliers (and, for reference, its ratio-test matches). Graffiti is a
    strong viewpoint change (perspective, ~40 degrees out of plane); our descriptor is
    built for a downward floor camera (rotation and translation in the image plane, nearly
    constant scale), so this tests it outside its design.
(c) **Similarity matrices** (paper 003 Fig. 2/3): a 10 m straight run per floor (a frame
    every ``--run-spacing`` m), the local score of each frame against every earlier one,
    each matrix normalised by its maximum; one PNG per floor with the ground-truth J,
    modes 1-6 and SIFT (SIFT on the first ``--sift-run-m`` metres only: BFMatcher 2-NN on
    ~8000 keypoints costs ~0.7 s per pair on gravel). Also the AUC over the run's pairs.

Run from the repo root: ``.venv/bin/python bench/bench_floor_quality.py [--out DIR]``.
Writes ``DIR/floor_quality.json`` and PNGs ``DIR/floor_quality_*.png``. Takes ~15 min
(SIFT dominates); ``--pairs`` and ``--sift-run-m`` trade time for precision.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import cv2
import numpy as np

try:
    from bench.common import print_table, write_json
    from bench.floor_common import (FEATURES_DIR, LOOP_OVERLAP, MODES, SiftBaseline, add_common_args,
                                    bench_floors, header, load_average, log, one_thread, pyplot, r, roc_auc)
except ImportError:  # run as a script: bench/ is on sys.path
    from common import print_table, write_json
    from floor_common import (FEATURES_DIR, LOOP_OVERLAP, MODES, SiftBaseline, add_common_args,
                              bench_floors, header, load_average, log, one_thread, pyplot, r, roc_auc)

from robotd.floor.descriptor import decode, extract
from robotd.floor.match import local_score
from robotd.base.camera import FloorCameraModel, overlap_ratios
from sim.pairs import random_pairs, straight_run

GRAFFITI_TOLERANCE_PX = 5.0
NEAR_FRACTION = 0.7
MAX_OFFSET_M = 0.4


# ----------------------------------------------------------------- (a) overlap separation


def separation(name: str, floor: object, args: argparse.Namespace, sift: SiftBaseline) -> dict:
    """Local scores of random pairs on one floor, per mode and SIFT, and their ROC AUC."""
    cam = FloorCameraModel.default()
    rng = np.random.default_rng(args.seed)
    log(f"  {name}: rendering {args.pairs} pairs")
    pairs = random_pairs(floor, cam, args.pairs, rng, near_fraction=NEAR_FRACTION, max_offset_m=MAX_OFFSET_M)
    j = pairs.overlap
    loop = j >= LOOP_OVERLAP
    disjoint = j == 0.0
    out: dict = {"floor": name, "pairs": len(j), "loops": int(loop.sum()),
                 "partial_non_loops": int((~loop & ~disjoint).sum()), "disjoint": int(disjoint.sum()),
                 "overlap": j.tolist(), "modes": {}}

    def summary(scores: np.ndarray) -> dict:
        return {"auc": roc_auc(scores, loop),
                "auc_vs_disjoint": roc_auc(scores[loop | disjoint], loop[loop | disjoint]),
                "scores": scores.tolist()}

    for mode in MODES:
        log(f"  {name}: mode {mode}")
        da = [decode(extract(im, mode)) for im in pairs.images_a]
        db = [decode(extract(im, mode)) for im in pairs.images_b]
        scores = np.array([local_score(a, b).score for a, b in zip(da, db)], float)
        out["modes"][str(mode)] = summary(scores)
    log(f"  {name}: SIFT ({len(j)} pairs)")
    scores = np.array([sift.match(sift.extract(a), sift.extract(b)).score
                       for a, b in zip(pairs.images_a, pairs.images_b)], float)
    out["sift"] = summary(scores)
    return out


def plot_distributions(results: list[dict], path: Path) -> None:
    """Histograms of the local score of loops (J >= 0.33), partial overlaps and disjoint
    pairs: one row per floor, one column per mode and SIFT."""
    plt = pyplot()
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    cols = [str(m) for m in MODES] + ["sift"]
    fig, axes = plt.subplots(len(results), len(cols), figsize=(2.3 * len(cols), 1.9 * len(results)),
                             dpi=100, squeeze=False)
    for row, res in enumerate(results):
        j = np.asarray(res["overlap"])
        groups = [("J>=0.33", j >= LOOP_OVERLAP, "tab:green"),
                  ("0<J<0.33", (j > 0) & (j < LOOP_OVERLAP), "tab:orange"),
                  ("J=0", j == 0, "tab:blue")]
        for col, key in enumerate(cols):
            ax = axes[row, col]
            d = res["sift"] if key == "sift" else res["modes"][key]
            s = np.asarray(d["scores"])
            bins = np.linspace(0, max(float(s.max()), 1.0), 31)
            for label, sel, colour in groups:
                ax.hist(s[sel], bins=bins, alpha=0.55, color=colour, label=label)
            ax.set_yscale("log")
            ax.yaxis.set_minor_formatter(NullFormatter())
            ax.yaxis.set_major_formatter(ScalarFormatter())
            ax.set_title(f"{res['floor']} {'SIFT' if key == 'sift' else 'mode ' + key}\nAUC {d['auc']:.3f}",
                         fontsize=8)
            ax.tick_params(labelsize=6)
    axes[0, 0].legend(fontsize=6)
    fig.supxlabel("local score (SIFT: RANSAC inliers)", fontsize=9)
    fig.supylabel("pairs (log)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# ----------------------------------------------------------------- (b) graffiti


def read_homography(path: Path) -> np.ndarray:
    """The 3x3 matrix in an OpenCV XML ``<data>`` element (as in ``H1to3p.xml``)."""
    text = path.read_text(encoding="utf-8")
    m = re.search(r"<data>(.*?)</data>", text, re.S)
    if m is None:
        raise ValueError(f"{path}: no <data> element")
    values = np.array([float(v) for v in m.group(1).split()])
    if values.size != 9:
        raise ValueError(f"{path}: expected 9 numbers, got {values.size}")
    return values.reshape(3, 3)


def correct_fraction(h: np.ndarray, xy1: np.ndarray, xy3: np.ndarray, tol_px: float) -> tuple[int, int]:
    """(correct, total) correspondences: ``H xy1`` within ``tol_px`` of ``xy3``."""
    xy1 = np.asarray(xy1, float).reshape(-1, 2)
    xy3 = np.asarray(xy3, float).reshape(-1, 2)
    if len(xy1) == 0:
        return 0, 0
    p = np.column_stack([xy1, np.ones(len(xy1))]) @ h.T
    proj = p[:, :2] / p[:, 2:3]
    err = np.hypot(*(proj - xy3).T)
    return int((err <= tol_px).sum()), len(xy1)


def graffiti(sift: SiftBaseline) -> dict | None:
    paths = [FEATURES_DIR / "graf1.png", FEATURES_DIR / "graf3.png", FEATURES_DIR / "H1to3p.xml"]
    if not all(p.is_file() for p in paths):
        log(f"skipping graffiti: {FEATURES_DIR} is absent (../shared/data not available)")
        return None
    im1 = cv2.imread(str(paths[0]), cv2.IMREAD_GRAYSCALE)
    im3 = cv2.imread(str(paths[1]), cv2.IMREAD_GRAYSCALE)
    h = read_homography(paths[2])
    out: dict = {"image_size": [im1.shape[1], im1.shape[0]], "tolerance_px": GRAFFITI_TOLERANCE_PX, "modes": {}}
    for mode in MODES:
        d1, d3 = decode(extract(im1, mode)), decode(extract(im3, mode))
        res = local_score(d1, d3)
        ok, n = correct_fraction(h, res.xy_a, res.xy_b, GRAFFITI_TOLERANCE_PX)
        out["modes"][str(mode)] = {"features": [len(d1.xy_px), len(d3.xy_px)], "score": float(res.score),
                                   "inliers": n, "correct": ok, "fraction": ok / n if n else float("nan"),
                                   "reason": str(res.reason)}
    f1, f3 = sift.extract(im1), sift.extract(im3)
    m = sift.match(f1, f3)
    ok, n = correct_fraction(h, m.xy_a, m.xy_b, GRAFFITI_TOLERANCE_PX)
    ia, ib = sift.ratio_matches(f1, f3)
    ok_r, n_r = correct_fraction(h, f1.xy[ia], f3.xy[ib], GRAFFITI_TOLERANCE_PX)
    out["sift"] = {"features": [len(f1), len(f3)], "inliers": n, "correct": ok,
                   "fraction": ok / n if n else float("nan"), "ratio_matches": n_r, "ratio_correct": ok_r,
                   "ratio_fraction": ok_r / n_r if n_r else float("nan")}
    return out


# ----------------------------------------------------------------- (c) similarity matrices


def similarity(score_fn, items: list) -> np.ndarray:
    """``(N, N)`` lower-triangular scores ``S[i, j] = score(items[i], items[j])`` for
    ``j < i`` (each frame against every earlier one); NaN elsewhere."""
    n = len(items)
    s = np.full((n, n), np.nan)
    for i in range(1, n):
        for j in range(i):
            s[i, j] = score_fn(items[i], items[j])
    return s


def run_matrices(name: str, floor: object, args: argparse.Namespace, sift: SiftBaseline,
                 png: Path) -> dict:
    cam = FloorCameraModel.default()
    rng = np.random.default_rng(args.seed + 1)
    poses, images = straight_run(floor, cam, rng, (0.0, 0.0, 0.0), 10.0, args.run_spacing)
    n = len(images)
    ii, jj = np.tril_indices(n, -1)
    j_true = np.full((n, n), np.nan)
    j_true[ii, jj] = overlap_ratios(cam, poses[ii], poses[jj])
    loop = j_true[ii, jj] >= LOOP_OVERLAP
    mats: dict[str, np.ndarray] = {}
    out: dict = {"floor": name, "frames": n, "spacing_m": args.run_spacing, "loops": int(loop.sum()),
                 "pairs": len(ii), "modes": {}}
    for mode in MODES:
        log(f"  {name}: run matrix, mode {mode}")
        decs = [decode(extract(im, mode)) for im in images]
        s = similarity(lambda a, b: local_score(a, b).score, decs)
        mats[f"mode {mode}"] = s
        out["modes"][str(mode)] = {"auc": roc_auc(s[ii, jj], loop)}
    n_sift = min(n, int(round(args.sift_run_m / args.run_spacing)) + 1)
    log(f"  {name}: run matrix, SIFT ({n_sift} frames)")
    feats = [sift.extract(im) for im in images[:n_sift]]
    s = similarity(lambda a, b: sift.match(a, b).score, feats)
    mats["SIFT"] = s
    si, sj = np.tril_indices(n_sift, -1)
    out["sift"] = {"frames": n_sift, "auc": roc_auc(s[si, sj], j_true[si, sj] >= LOOP_OVERLAP)}
    # The same first frames for our modes, so the AUCs compare like with like.
    for mode in MODES:
        sm = mats[f"mode {mode}"]
        out["modes"][str(mode)]["auc_sift_frames"] = roc_auc(sm[si, sj], j_true[si, sj] >= LOOP_OVERLAP)

    plt = pyplot()
    panels = [("ground truth J", j_true, 1.0)] + [(k, v, None) for k, v in mats.items()]
    fig, axes = plt.subplots(2, 4, figsize=(15, 8), dpi=100, layout="constrained")
    for ax, (title, m, vmax) in zip(axes.ravel(), panels):
        top = np.nanmax(m) if vmax is None else vmax
        norm = m / top if top and np.isfinite(top) and top > 0 else m
        ext = (0, len(m) * args.run_spacing, len(m) * args.run_spacing, 0)
        im = ax.imshow(norm, cmap="viridis", vmin=0, vmax=1, extent=ext, interpolation="nearest")
        if title == "SIFT":
            title = f"SIFT, first {args.sift_run_m:g} m"
        ax.set_title(f"{title} (max {top:.3g})" if vmax is None else title, fontsize=9)
        ax.set_xlabel("earlier frame, m along the run", fontsize=7)
        ax.set_ylabel("current frame, m", fontsize=7)
        ax.tick_params(labelsize=6)
    fig.colorbar(im, ax=axes, shrink=0.6, label="normalised local score (J for ground truth)")
    fig.suptitle(f"{name}: local score of each frame against the earlier ones, 10 m straight run "
                 f"(paper 003 Fig. 2/3; SIFT on the first {args.sift_run_m:g} m)", fontsize=10)
    fig.savefig(png)
    plt.close(fig)
    out["png"] = str(png)
    return out


# ----------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_common_args(ap)
    ap.add_argument("--pairs", type=int, default=200, help="random frame pairs per floor (default 200)")
    ap.add_argument("--run-spacing", type=float, default=0.1,
                    help="frame spacing of the 10 m runs for the matrices, m (default 0.1)")
    ap.add_argument("--sift-run-m", type=float, default=2.0,
                    help="metres of each run that SIFT's similarity matrix covers (default 2)")
    ap.add_argument("--skip", action="append", default=[], choices=["separation", "graffiti", "matrices"],
                    help="leave a part out (repeatable)")
    args = ap.parse_args(argv)
    load_start = load_average()
    blas = one_thread()
    log(f"load average {load_start}; BLAS pools {blas}")
    sift = SiftBaseline(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    floors = bench_floors(args.floor, args.seed)
    payload = header("floor_quality", load_start=load_start, settings={
        "threads": 1, "seed": args.seed, "pairs_per_floor": args.pairs, "near_fraction": NEAR_FRACTION,
        "max_offset_m": MAX_OFFSET_M, "loop_overlap": LOOP_OVERLAP, "run_spacing_m": args.run_spacing,
        "sift_run_m": args.sift_run_m, "graffiti_tolerance_px": GRAFFITI_TOLERANCE_PX,
        "sift": {"ratio": SiftBaseline.ratio, "ransac_px": SiftBaseline.ransac_px},
    })
    mode_cols = [f"m{m}" for m in MODES]

    if "separation" not in args.skip:
        sep = []
        for bf in floors:
            log(f"(a) separation on {bf.name}")
            sep.append(separation(bf.name, bf.floor, args, sift))
        png = args.out / "floor_quality_scores.png"
        plot_distributions(sep, png)
        payload["separation"] = sep
        print(f"\n(a) ROC AUC of the local score, loops (J >= {LOOP_OVERLAP}) vs the rest; "
              f"{args.pairs} random pairs per floor (target >= 0.99 for m3-m6; m6 >= SIFT)")
        print_table(["floor", "loops", "0<J<.33", "J=0", *mode_cols, "SIFT"],
                    [[s["floor"], s["loops"], s["partial_non_loops"], s["disjoint"],
                      *[r(s["modes"][str(m)]["auc"], 4) for m in MODES], r(s["sift"]["auc"], 4)] for s in sep])
        print("\n    loops vs disjoint pairs only (J = 0): distinctiveness without the J threshold's grey zone")
        print_table(["floor", *mode_cols, "SIFT"],
                    [[s["floor"], *[r(s["modes"][str(m)]["auc_vs_disjoint"], 4) for m in MODES],
                      r(s["sift"]["auc_vs_disjoint"], 4)] for s in sep])
        print(f"    wrote {png}")

    if "graffiti" not in args.skip:
        log("(b) graffiti")
        g = graffiti(sift)
        payload["graffiti"] = g
        if g is not None:
            print(f"\n(b) graffiti graf1 -> graf3, correct = within {GRAFFITI_TOLERANCE_PX:g} px of H1to3p")
            rows = [[f"mode {m}", f"{g['modes'][str(m)]['features'][0]}/{g['modes'][str(m)]['features'][1]}",
                     g["modes"][str(m)]["inliers"], g["modes"][str(m)]["correct"],
                     r(g["modes"][str(m)]["fraction"], 3), g["modes"][str(m)]["reason"]] for m in MODES]
            s = g["sift"]
            rows.append(["SIFT RANSAC inliers", f"{s['features'][0]}/{s['features'][1]}", s["inliers"],
                         s["correct"], r(s["fraction"], 3), ""])
            rows.append(["SIFT ratio-test matches", "", s["ratio_matches"], s["ratio_correct"],
                         r(s["ratio_fraction"], 3), ""])
            print_table(["descriptor", "features", "inliers", "correct", "fraction", "reason"], rows)

    if "matrices" not in args.skip:
        runs = []
        for bf in floors:
            log(f"(c) similarity matrices on {bf.name}")
            runs.append(run_matrices(bf.name, bf.floor, args, sift, args.out / f"floor_quality_matrix_{bf.name}.png"))
        payload["matrices"] = runs
        print(f"\n(c) 10 m straight runs, a frame every {args.run_spacing:g} m: AUC over all earlier-frame pairs")
        print_table(["floor", "frames", "loops", *mode_cols],
                    [[x["floor"], x["frames"], x["loops"], *[r(x["modes"][str(m)]["auc"], 4) for m in MODES]]
                     for x in runs])
        print(f"\n    the first {args.sift_run_m:g} m only, ours vs SIFT")
        print_table(["floor", "frames", *mode_cols, "SIFT"],
                    [[x["floor"], x["sift"]["frames"],
                      *[r(x["modes"][str(m)]["auc_sift_frames"], 4) for m in MODES], r(x["sift"]["auc"], 4)]
                     for x in runs])
        for x in runs:
            print(f"    wrote {x['png']}")

    out = write_json(args.out / "floor_quality.json", payload)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
