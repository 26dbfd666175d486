"""The evidence behind a forward eval's false loops: each image pair with its inliers.

Reads the ``forward_eval.json`` that ``robotd eval forward --out DIR`` wrote, takes every
loop a method declared that the ground truth calls false (the detector's by default; ``--method
"best score + epipolar"`` for the baseline's), verifies the pair again with the same
parameters, and writes for each one ``fp_NEW_OLD.png`` (old image left, new right; the
essential matrix's inliers joined by lines, green when they are on the best homography of
the inliers, red when not, with the support's convex hull) and ``false_loops.json`` (the
verification's figures and the inlier coordinates). Each pair is verified twice: with the
paper's check alone (``min_support_area = 0``) and with the support check (the eval's
``min_support_area``, or the default when the eval ran without it).

Run: ``.venv/bin/python bench/forward_false_loops.py --images DIR --eval DIR/eval/forward_eval.json
--out DIR/false_loops [--limit N]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

try:
    from bench.common import machine_info, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, write_json

from robotd.forward import FeatureExtractor, FeatureParams
from robotd.forward.verify import VerifyParams, match_features, verify_pair
from robotd.io.sequence import list_images, load_ground_truth, read_image


def _inliers(old, new, params: VerifyParams, k: np.ndarray):
    """The essential matrix's inliers ``(old (M, 2), new (M, 2))`` and which of them lie on
    the best homography, as :func:`verify_pair` finds them (same seed, same order)."""
    p_old, p_new = match_features(old, new, params.ratio)
    if len(p_old) < 5:
        return p_old, p_new, np.zeros(len(p_old), bool)
    cv2.setRNGSeed(params.seed)
    e, mask = cv2.findEssentialMat(p_old, p_new, k, method=cv2.RANSAC, prob=params.ransac_confidence,
                                   threshold=params.ransac_threshold_px)
    if e is None or mask is None or e.shape[0] < 3:
        return p_old[:0], p_new[:0], np.zeros(0, bool)
    _, _, _, mask2 = cv2.recoverPose(e[:3], p_old, p_new, k, mask=mask.copy())
    inl = np.asarray(mask2).ravel() > 0
    s_old, s_new = p_old[inl], p_new[inl]
    on_plane = np.zeros(len(s_old), bool)
    if len(s_old) >= 4:
        _, hmask = cv2.findHomography(s_old, s_new, cv2.RANSAC, params.homography_threshold_px)
        if hmask is not None:
            on_plane = np.asarray(hmask).ravel() > 0
    return s_old, s_new, on_plane


def _draw(img_old: np.ndarray, img_new: np.ndarray, s_old, s_new, on_plane, planar: bool) -> np.ndarray:
    w = img_old.shape[1]
    vis = np.hstack([img_old, img_new])
    vis = cv2.cvtColor(vis, cv2.COLOR_GRAY2BGR) if vis.ndim == 2 else vis.copy()
    for a, b, p in zip(s_old, s_new, on_plane):
        col = (0, 200, 0) if p else (0, 0, 255)
        pa = tuple(int(v) for v in np.round(a))
        pb = (int(np.round(b[0])) + w, int(np.round(b[1])))
        cv2.line(vis, pa, pb, (255, 200, 0), 1)
        cv2.circle(vis, pa, 4, col, 2)
        cv2.circle(vis, pb, 4, col, 2)
    sel = on_plane if planar else np.ones(len(s_old), bool)
    for pts, dx in ((s_old[sel], 0), (s_new[sel], w)):
        if len(pts) >= 3:
            hull = cv2.convexHull((pts + [dx, 0]).astype(np.int32).reshape(-1, 1, 2))
            cv2.polylines(vis, [hull], True, (255, 0, 255), 2)
    return vis


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--images", type=Path, required=True)
    ap.add_argument("--eval", type=Path, required=True, help="forward_eval.json of robotd eval forward")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--method", default="detector", choices=("detector", "best score + epipolar"))
    ap.add_argument("--limit", type=int, default=50, help="at most this many pairs (default 50)")
    args = ap.parse_args(argv)

    report = json.loads(args.eval.read_text())
    gt_path = Path(report["ground_truth"])
    files = list_images(args.images, exclude=(gt_path,))
    truth = load_ground_truth(gt_path, len(files))
    vp = VerifyParams(**report["params"]["verify"])
    if vp.min_support_area <= 0.0:
        vp = replace(vp, min_support_area=VerifyParams().min_support_area)
    paper_vp = replace(vp, min_support_area=0.0)
    k = np.asarray(report["camera_matrix"], np.float64)
    extract = FeatureExtractor(FeatureParams(**report["params"]["features"]))
    pairs = []
    for t, row in enumerate(report["per_image"]):
        if args.method == "detector":
            j = row["loop"]
        else:
            bs = row["best_score"]
            j = bs["candidate"] if bs["verified"] else None
        if j is not None and not truth[t, j]:
            pairs.append((t, int(j)))
    args.out.mkdir(parents=True, exist_ok=True)
    out = []
    for t, j in pairs[:args.limit]:
        img_old, img_new = read_image(files[j]), read_image(files[t])
        f_old, f_new = extract(img_old), extract(img_new)
        paper = verify_pair(f_old, f_new, paper_vp, k)
        v = verify_pair(f_old, f_new, vp, k)
        s_old, s_new, on_plane = _inliers(f_old, f_new, vp, k)
        name = f"fp_{t}_{j}.png"
        cv2.imwrite(str(args.out / name), _draw(img_old, img_new, s_old, s_new, on_plane, v.planar))
        out.append({"new": t, "old": j, "new_image": files[t].name, "old_image": files[j].name,
                    "paper_reason": paper.reason, "reason": v.reason, "matches": v.n_matches, "inliers": v.n_inliers,
                    "plane_inliers": v.n_plane_inliers, "planar": v.planar,
                    "support_area": v.support_area, "drawing": name,
                    "inliers_old_px": s_old.round(1).tolist(), "inliers_new_px": s_new.round(1).tolist(),
                    "on_plane": on_plane.tolist()})
        print(f"{t} -> {j}: paper {paper.reason}, with the support check {v.reason}; {v.n_inliers} inliers ({v.n_plane_inliers} on one plane), "
              f"support {100 * v.support_area:.1f} % of the image")
    write_json(args.out / "false_loops.json",
               {"benchmark": "forward_false_loops", "machine": machine_info(), "eval": str(args.eval),
                "method": args.method, "min_support_area": vp.min_support_area,
                "false_loops": len(pairs), "pairs": out})
    print(f"{len(pairs)} false loops ({args.method}); wrote {min(len(pairs), args.limit)} pairs to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
