"""``robotd eval forward``: the forward loop detector on an image sequence, scored against a
ground-truth matrix, beside two baselines.

The images of ``--images`` run through :class:`robotd.forward.ForwardDetector` in natural
name order. The same features also feed

- "best score": the detector's likelihoods without the Bayes filter (the highest tf-idf
  vote wins when it beats the virtual no-loop image), without and with the same epipolar
  verification;
- "brute force": SIFT matching and five-point RANSAC against every past image
  (``--no-brute-force`` skips it: its time grows with the square of the sequence).

Printed: precision, recall, recall at 100 % precision and the time per image of each
method. With ``--out``: ``forward_eval.json`` (settings, versions, scores, every image's
decisions and stage times), ``stage_times.png`` (paper Fig. 7) and
``likelihood_posterior_K.png`` for one image (paper Fig. 5).
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from robotd.base.errors import SequenceError
from robotd.base.files import check_output_folder, nonempty_path, write_text_replacing

log = logging.getLogger(__name__)


def add_arguments(sub: argparse._SubParsersAction[Any]) -> None:
    """Register ``eval forward`` under ``sub``."""
    ev = sub.add_parser("eval", help="evaluate a detector on recorded data")
    esub = ev.add_subparsers(dest="eval_command", metavar="ACTION", required=True)
    fw = esub.add_parser(
        "forward", help="the forward loop detector on an image sequence with ground truth",
        description="Run the forward-camera loop detector (incremental vocabulary, Bayes filter, "
                    "epipolar verification; Angeli et al. 2008) over the images of a folder in "
                    "natural name order and score it against a ground-truth same-place matrix, "
                    "beside two baselines: the same likelihoods without the filter, and brute-force "
                    "SIFT matching with RANSAC against every past image.")
    fw.add_argument("--images", type=nonempty_path, required=True, metavar="DIR",
                    help="folder of images (jpg, png, bmp, ...), taken in name order")
    fw.add_argument("--ground-truth", type=nonempty_path, required=True, metavar="FILE",
                    help="N x N matrix, non-zero = same place (.npy, .csv, MATLAB .mat as Lip6, NewCollege "
                         "and CityCentre publish it, or an image such as .bmp/.png; either triangle)")
    fw.add_argument("--method", choices=("default", "paper"), default="default",
                    help="detector: 'default' (ORB, binary vocabulary with purging, the levers kept by "
                         "the ablation, docs/forward.md) or 'paper' (paper 000 as written: SIFT, 0.8 on a "
                         "neighbourhood's posterior)")
    fw.add_argument("--tolerance", type=int, default=0, metavar="K",
                    help="a declared loop counts as right within K images of a true match (default 0)")
    fw.add_argument("--every", type=int, default=1, metavar="N",
                    help="take every N-th image (and the ground truth's rows and columns; default 1)")
    fw.add_argument("--odometry", type=nonempty_path, default=None, metavar="FILE",
                    help="the robot's odometry pose of each image (CSV with a header: x_m, y_m, yaw_rad and "
                         "optionally var_x_m2, var_y_m2, var_yaw_rad2; one row per image in name order), "
                         "given to the detector with its image (never a ground truth)")
    fw.add_argument("--out", type=nonempty_path, default=None, metavar="DIR",
                    help="write forward_eval.json and the plots here")
    fw.add_argument("--features", choices=("sift", "orb"), default=None,
                    help="override the method's features (default: ORB for 'default', SIFT for 'paper')")
    fw.add_argument("--likelihood", choices=("paper", "rtabmap"), default=None,
                    help="override the method's likelihood normalisation")
    fw.add_argument("--recent", type=int, default=10, metavar="P",
                    help="the last P images are never loop hypotheses (default 10)")
    fw.add_argument("--min-inliers", type=int, default=None, metavar="N",
                    help="epipolar inliers needed to accept a loop (default: the detector's)")
    fw.add_argument("--min-support-area", type=float, default=None, metavar="F",
                    help="fraction of each image the verified inliers must cover (default: the "
                         "detector's; 0 = the paper's check without it)")
    fw.add_argument("--focal-px", type=float, default=None,
                    help="focal length in pixels for the essential matrix (default: the image width)")
    fw.add_argument("--plot-image", type=int, default=None, metavar="K",
                    help="draw the likelihood and posterior of the image at position K (0 = first; "
                         "default: the first accepted loop)")
    fw.add_argument("--no-brute-force", action="store_true", help="skip the brute-force baseline")
    fw.set_defaults(func=run_forward)


def _versions() -> dict[str, str]:
    import cv2
    import usearch

    from robotd import __version__

    return {"robotd": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "opencv": cv2.__version__, "usearch": usearch.__version__,
            "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
            "system": platform.platform()}


def read_odometry(path: Path, n_images: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``--odometry`` CSV: ``(n, 3)`` poses (x_m, y_m, yaw_rad) and ``(n, 3, 3)``
    diagonal covariances (zero when the file has no variance columns). Raises
    :class:`SequenceError` with one line for a file that is not that."""
    try:
        with open(path, encoding="utf-8") as f:
            header = [c.strip() for c in f.readline().split(",")]
            rows = np.loadtxt(f, delimiter=",", ndmin=2)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise SequenceError(f"cannot read odometry file {path}: {str(exc).splitlines()[0]}") from None
    missing = [c for c in ("x_m", "y_m", "yaw_rad") if c not in header]
    if missing:
        raise SequenceError(f"odometry file {path}: no column {', '.join(missing)} in its header")
    if rows.shape != (n_images, len(header)):
        raise SequenceError(f"odometry file {path}: {rows.shape[0]} rows of {rows.shape[1]} values for "
                            f"{n_images} images and {len(header)} columns")
    pose = rows[:, [header.index(c) for c in ("x_m", "y_m", "yaw_rad")]]
    cov = np.zeros((n_images, 3, 3))
    for k, c in enumerate(("var_x_m2", "var_y_m2", "var_yaw_rad2")):
        if c in header:
            cov[:, k, k] = rows[:, header.index(c)]
    if not (np.isfinite(pose).all() and np.isfinite(cov).all()) or (cov < 0).any():
        raise SequenceError(f"odometry file {path}: values that are not finite, or a negative variance")
    return pose, cov


def _time_stats(t: np.ndarray) -> dict[str, float]:
    t = np.asarray(t, np.float64) * 1e3
    return {"median_ms": float(np.median(t)), "mean_ms": float(t.mean()),
            "p99_ms": float(np.percentile(t, 99)), "max_ms": float(t.max())}


def run_forward(args: argparse.Namespace) -> int:
    """``robotd eval forward``."""
    from dataclasses import asdict, replace

    from robotd.forward import (LOOP, STAGES, FeatureExtractor, FeatureParams, ForwardDetector,
                                method_params, verify_pair)
    from robotd.forward.baselines import BruteForceMatcher, best_score
    from robotd.forward.evaluation import positives, pr_curve, score_decisions
    from robotd.forward.verify import camera_matrix_guess
    from robotd.io.sequence import list_images, load_ground_truth, read_image

    if args.recent < 1:
        raise SequenceError(f"--recent must be at least 1, got {args.recent}")
    if args.tolerance < 0:
        raise SequenceError(f"--tolerance must be >= 0, got {args.tolerance}")
    if args.every < 1:
        raise SequenceError(f"--every must be at least 1, got {args.every}")
    if args.out is not None:
        check_output_folder(args.out, "forward_eval.json, pr_curve.json and the plots")
    files = list_images(args.images, exclude=(args.ground_truth,))
    truth = load_ground_truth(args.ground_truth, len(files))
    odometry = None if args.odometry is None else read_odometry(args.odometry, len(files))
    files = files[::args.every]
    truth = truth[::args.every, ::args.every]
    if odometry is not None:
        odometry = (odometry[0][::args.every], odometry[1][::args.every])
    n = len(files)
    tol = args.tolerance
    if args.plot_image is not None and not 0 <= args.plot_image < n:
        raise SequenceError(f"--plot-image {args.plot_image} is outside the sequence (0..{n - 1})")
    params = method_params(args.method, recent_excluded=args.recent)
    if args.features is not None and args.features != params.features.kind:
        params = replace(params, features=FeatureParams(kind=args.features,
                                                        max_features=params.features.max_features))
    if args.likelihood is not None:
        params = replace(params, likelihood=args.likelihood)
    if args.min_inliers is not None:
        params = replace(params, verify=replace(params.verify, min_inliers=args.min_inliers))
    if args.min_support_area is not None:
        if not 0.0 <= args.min_support_area < 1.0:
            raise SequenceError(f"--min-support-area must be in [0, 1), got {args.min_support_area}")
        params = replace(params, verify=replace(params.verify, min_support_area=args.min_support_area))
    print(f"{args.images}: {n} images, {int(positives(truth, args.recent).sum())} of them revisit a "
          f"place at least {args.recent} images back; method {args.method} (features "
          f"{params.features.kind}, likelihood {params.likelihood}); tolerance {tol} images"
          + (f", one image in {args.every}" if args.every > 1 else "")
          + (f"; odometry from {args.odometry}" if odometry is not None else ""))

    extract = FeatureExtractor(params.features)
    k_matrix = None
    detector: ForwardDetector | None = None
    brute: BruteForceMatcher | None = None
    rows: list[dict[str, Any]] = []
    det_cand, det_conf, det_decl = (np.full(n, -1), np.zeros(n), np.zeros(n, bool))
    bs_cand, bs_conf, bs_decl = (np.full(n, -1), np.zeros(n), np.zeros(n, bool))
    bsv_decl = np.zeros(n, bool)
    bf_cand, bf_conf, bf_decl = (np.full(n, -1), np.zeros(n), np.zeros(n, bool))
    stage_t = {s: np.zeros(n) for s in STAGES}
    det_total, bs_total, bsv_total, bf_total = (np.zeros(n) for _ in range(4))
    plot_k = args.plot_image
    plot_data: dict[str, Any] | None = None
    t_start = time.perf_counter()
    for t, path in enumerate(files):
        image = read_image(path)
        if detector is None:
            h, w = image.shape[:2]
            k_matrix = camera_matrix_guess(w, h, args.focal_px)
            detector = ForwardDetector(params, camera_matrix=k_matrix)
            if not args.no_brute_force:
                brute = BruteForceMatcher(params.verify, args.recent, k_matrix)
        elif image.shape[:2] != (h, w):
            raise SequenceError(f"{path} is {image.shape[1]}x{image.shape[0]}, the sequence's "
                                f"first image {w}x{h}")
        t0 = time.perf_counter()
        feats = extract(image)
        t_feat = time.perf_counter() - t0
        d = (detector.process_features(feats, t_feat) if odometry is None
             else detector.process_features(feats, t_feat, odometry[0][t], odometry[1][t]))
        for s in STAGES:
            stage_t[s][t] = d.times_s[s]
        det_total[t] = d.times_s["total"]
        if d.candidate_id is not None:
            det_cand[t], det_conf[t], det_decl[t] = d.candidate_id, d.candidate_probability, d.status == LOOP
        # Best score: the same features, words and votes, no filter.
        bs_total[t] = t_feat + d.times_s["words"] + d.times_s["likelihood"]
        cand, ratio = best_score(d.scores, d.virtual_score, d.n_hypotheses)
        bs_ok = None
        bsv_total[t] = bs_total[t]
        if cand is not None:
            bs_cand[t], bs_conf[t], bs_decl[t] = cand, ratio, ratio > 1.0
            if ratio > 1.0:
                t1 = time.perf_counter()
                bs_ok = verify_pair(detector.features_of(cand), feats, params.verify, k_matrix).accepted
                bsv_total[t] += time.perf_counter() - t1
                bsv_decl[t] = bs_ok
        row: dict[str, Any] = {
            "image": path.name, "status": d.status, "candidate": d.candidate_id,
            "candidate_probability": round(d.candidate_probability, 6), "loop": d.loop_id,
            "inliers": d.verification.n_inliers if d.verification else None,
            "verification": None if d.verification is None else {
                "reason": d.verification.reason, "plane_inliers": d.verification.n_plane_inliers,
                "planar": d.verification.planar,
                "support_area": round(d.verification.support_area, 4)},
            "features": d.n_features, "new_words": d.new_words, "vocabulary": d.vocabulary_size,
            "times_ms": {k: round(v * 1e3, 3) for k, v in d.times_s.items()},
            "best_score": {"candidate": cand, "ratio": None if cand is None else round(ratio, 6),
                           "verified": bs_ok},
        }
        if brute is not None:
            b = brute.process_features(feats)
            bf_total[t] = t_feat + b.time_s
            if b.candidate_id is not None:
                bf_cand[t], bf_conf[t], bf_decl[t] = b.candidate_id, b.n_inliers, b.loop
            row["brute_force"] = {"candidate": b.candidate_id, "inliers": b.n_inliers, "loop": b.loop,
                                  "time_ms": round(b.time_s * 1e3, 3)}
        rows.append(row)
        if plot_k is None and d.status == LOOP:
            plot_k = t
        if plot_k == t:
            plot_data = {"scores": d.scores[:d.n_hypotheses].copy(), "virtual": d.virtual_score,
                         "posterior": d.posterior.copy()}
        if (t + 1) % 100 == 0:
            log.info("%d / %d images, %.1f s", t + 1, n, time.perf_counter() - t_start)

    results = {
        "detector": (score_decisions(det_cand, det_conf, det_decl, truth, args.recent, tol), det_total),
        "best score": (score_decisions(bs_cand, bs_conf, bs_decl, truth, args.recent, tol), bs_total),
        "best score + epipolar": (score_decisions(bs_cand, bs_conf, bsv_decl, truth, args.recent, tol),
                                  bsv_total),
    }
    if brute is not None:
        results["brute force"] = (score_decisions(bf_cand, bf_conf, bf_decl, truth, args.recent, tol),
                                  bf_total)
    # The detector's precision-recall curve over its decision threshold: every candidate
    # verified or not is swept by its probability (the verified ones alone are the
    # operating point).
    curves = {"detector (verified loops)": pr_curve(det_cand, det_conf, det_decl, truth, args.recent, tol),
              "best score": pr_curve(bs_cand, bs_conf, bs_decl, truth, args.recent, tol)}
    _print_table(results, stage_t)
    if detector is not None:
        print(f"vocabulary: {len(detector.vocabulary)} words after {n} images "
              f"({len(detector.vocabulary) / n:.0f} new words per image); inverted index "
              f"{detector.index.memory_bytes() / 1e3:.0f} kB")

    if args.out is not None:
        out: Path = args.out
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SequenceError(f"cannot create output folder {out}: {exc}") from None
        from robotd.io.plots import plot_likelihood_posterior, plot_stage_times

        report = {
            "images": str(args.images), "ground_truth": str(args.ground_truth), "n_images": n,
            "method": args.method, "tolerance": tol, "every": args.every,
            "odometry": None if args.odometry is None else str(args.odometry),
            "pr_curves": curves,
            "params": asdict(params), "camera_matrix": None if k_matrix is None else k_matrix.tolist(),
            "versions": _versions(),
            "methods": {name: {**s.as_dict(), "time_per_image": _time_stats(tt)}
                        for name, (s, tt) in results.items()},
            "stage_time_per_image": {s: _time_stats(v) for s, v in stage_t.items()},
            "memory": {"words": len(detector.vocabulary) if detector else 0,
                       "inverted_index_bytes": detector.index.memory_bytes() if detector else 0},
            "per_image": rows,
        }
        write_text_replacing(out / "forward_eval.json", json.dumps(report, indent=1))
        extra = {"brute force (features + matching)": bf_total} if brute is not None else None
        plot_stage_times(out / "stage_times.png", {"features": stage_t["features"],
                                                   "word search": stage_t["words"],
                                                   "likelihood": stage_t["likelihood"],
                                                   "filter": stage_t["filter"],
                                                   "verification (total)": stage_t["verify"]},
                         extra_s=extra, title=f"{args.images.name}: time per image by stage")
        written = [out / "forward_eval.json", out / "stage_times.png"]
        from robotd.io.plots import plot_pr_curves

        s_det = results["detector"][0]
        plot_pr_curves(out / "pr_curve.png", curves,
                       {"detector": (s_det.recall, s_det.precision)},
                       title=f"{args.images.name}: precision-recall ({args.method}, tolerance {tol})")
        write_text_replacing(out / "pr_curve.json", json.dumps(
            {"method": args.method, "tolerance": tol, "curves": curves,
             "operating_point": s_det.as_dict()}, indent=1))
        written += [out / "pr_curve.png", out / "pr_curve.json"]
        if plot_data is not None and plot_k is not None:
            nh = len(plot_data["scores"])
            lp = out / f"likelihood_posterior_{plot_k}.png"
            plot_likelihood_posterior(lp, plot_k, plot_data["scores"], plot_data["virtual"],
                                      plot_data["posterior"], params.filter.loop_threshold,
                                      truth[plot_k, :nh],
                                      title=f"image {plot_k} ({files[plot_k].name}): posterior and "
                                            f"likelihood over {nh} past images")
            written.append(lp)
        print("wrote " + ", ".join(str(p) for p in written))
    return 0


def _print_table(results: dict[str, Any], stage_t: dict[str, np.ndarray]) -> None:
    out = sys.stdout
    print(f"{'method':<24}{'precision':>10}{'recall':>8}{'R@100%P':>9}{'loops':>7}{'TP':>5}{'FP':>5}"
          f"{'ms/image median':>17}{'mean':>8}{'max':>8}", file=out)
    for name, (s, tt) in results.items():
        ts = _time_stats(tt)
        print(f"{name:<24}{s.precision:>10.3f}{s.recall:>8.3f}{s.recall_at_full_precision:>9.3f}"
              f"{s.declared:>7}{s.true_positives:>5}{s.false_positives:>5}"
              f"{ts['median_ms']:>17.1f}{ts['mean_ms']:>8.1f}{ts['max_ms']:>8.1f}", file=out)
    parts = ", ".join(f"{k} {np.median(v) * 1e3:.1f}" for k, v in stage_t.items())
    print(f"detector stages, median ms per image: {parts}", file=out)
