"""Per-image time and memory of the forward detector as the run grows, with and without the
working memory.

The virtual robot drives the office route lap after lap; each keyframe (every 0.1 m or
10 deg) is rendered at 640x480 by the forward camera (:mod:`sim.cameras.forward`), its SIFT
features are extracted once, and the same features go to two detectors in the same process:

- ``paper``: :class:`robotd.forward.ForwardDetector` as the paper has it (every past image
  votes and is a hypothesis);
- ``wm``: the same with a working memory of ``--max-places`` places
  (:mod:`robotd.forward.memory`): long-term places no longer vote, and come back when a
  neighbour is recognised.

Recorded per image and detector: every stage's time, the working-memory size, the places
retrieved and transferred, the loops; every 250 images the process RSS, the vocabulary size
and the bytes of the inverted index, the usearch index and the stored features. Reported:
the median and 99th percentile of the per-image time (the 200 images up to 1k, 5k, 10k),
the slope of a line fitted to the per-image time (ms per 1000 images), memory per image,
loops found (true when the two true poses are within 1 m and 30 deg), and brute force's
per-image time (:class:`robotd.forward.baselines.BruteForceMatcher`, measured on the first
``--brute-images`` images, extrapolated linearly to 1k/5k/10k: it compares each image with
every past one). Both detectors share one process, so the RSS is of both together; the
parts are given separately.

Run: ``.venv/bin/python bench/bench_forward_memory.py`` (2000 images, about 10 min on a
quiet machine) or ``--full`` (10 000 images). Partial results are written every 500 images.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

try:
    from bench.common import machine_info, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, write_json

from robotd.forward import (
    LOOP,
    DetectorParams,
    FeatureExtractor,
    FeatureParams,
    ForwardDetector,
    MemoryParams,
)
from robotd.forward.baselines import BruteForceMatcher
from robotd.forward.verify import camera_matrix_guess
from sim.cameras.forward import ForwardCameraModel, ForwardRenderer, ForwardRenderParams
from sim.forward_sequence import _repeated_route, keyframe_times
from sim.route import MotionLimits, plan_motion
from sim.world.rooms import world_for_route

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "forward_memory.json"
SIZES = (1000, 2000, 5000, 10000)
WINDOW = 200
COLUMNS = ("features", "words", "likelihood", "filter", "verify", "memory", "total")


def rss_bytes() -> int:
    """Resident set size of this process (Linux /proc)."""
    with open("/proc/self/statm", encoding="ascii") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def route_poses(n: int, route: str, seed: int) -> tuple[np.ndarray, np.ndarray, object]:
    """At least ``n`` keyframe poses of the route driven lap after lap, and their times."""
    world = world_for_route(route, seed)
    laps = 1
    while True:
        motion = plan_motion(_repeated_route(route, laps), MotionLimits())
        times = keyframe_times(motion, 0.1, math.radians(10.0))
        if len(times) >= n:
            return motion.poses_at(times[:n]), times[:n], world
        laps = max(laps + 1, int(math.ceil(laps * n / max(len(times), 1))))


def true_loop(poses: np.ndarray, a: int, b: int) -> bool:
    d = math.hypot(*(poses[a, :2] - poses[b, :2]))
    dyaw = abs(math.remainder(float(poses[a, 2] - poses[b, 2]), math.tau))
    return d <= 1.0 and dyaw <= math.radians(30.0)


def window_stats(x: np.ndarray, at: int) -> dict | None:
    if len(x) < at:
        return None
    w = x[at - WINDOW:at] * 1e3
    return {"median_ms": float(np.median(w)), "p99_ms": float(np.percentile(w, 99)),
            "mean_ms": float(w.mean())}


def slope_ms_per_1000(x: np.ndarray, start: int) -> float | None:
    """Slope of a least-squares line through the per-image time (ms per 1000 images) from
    image ``start`` on (a robust check: also the difference of window medians)."""
    if len(x) - start < 2 * WINDOW:
        return None
    i = np.arange(start, len(x))
    return float(np.polyfit(i, x[start:] * 1e3, 1)[0] * 1000)


def brute_force(feats: list, k: np.ndarray, n: int) -> dict:
    """BruteForceMatcher over the first ``n`` images: per-image time against past images
    compared, a line through it, and that line at 1k/5k/10k (extrapolated)."""
    bf = BruteForceMatcher(camera_matrix=k)
    t, pairs = [], []
    for f in feats[:n]:
        r = bf.process_features(f)
        t.append(r.time_s)
        pairs.append(r.pairs)
    t, pairs = np.asarray(t), np.asarray(pairs)
    use = pairs > 0
    per_pair = float(np.polyfit(pairs[use], t[use], 1)[0]) if use.sum() > 2 else float("nan")
    return {"images_measured": n, "max_pairs": int(pairs.max()),
            "per_pair_ms": per_pair * 1e3, "measured_last_image_ms": float(t[-1] * 1e3),
            "extrapolated_ms": {str(s): per_pair * (s - bf.recent_excluded) * 1e3 for s in SIZES}}


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--images", type=int, default=2000)
    ap.add_argument("--full", action="store_true", help="10 000 images")
    ap.add_argument("--max-places", type=int, default=1200,
                    help="working-memory bound (default 1200, a little more than one lap of 1031)")
    ap.add_argument("--brute-images", type=int, default=40,
                    help="measure brute force on this many first images (0: skip)")
    ap.add_argument("--max-features", type=int, default=0,
                    help="keep the strongest N SIFT keypoints per image (default 0: all, the detector's "
                         "default; a cap makes a long run fit a loaded machine)")
    ap.add_argument("--route", default="office")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    n = 10000 if args.full else args.images

    t0 = time.perf_counter()
    poses, times, world = route_poses(n, args.route, args.seed)
    cam = ForwardCameraModel()
    renderer = ForwardRenderer(world, cam, ForwardRenderParams(noise_sigma=2.0),
                               np.random.default_rng(args.seed + 2))
    intr = cam.intrinsics
    k = camera_matrix_guess(intr.width_px, intr.height_px, intr.fx_px)
    print(f"{n} keyframes of {args.route!r} lap after lap (route planned in {time.perf_counter() - t0:.1f} s)")

    fp = FeatureParams(max_features=args.max_features)
    extract = FeatureExtractor(fp)
    dets = {"paper": ForwardDetector(DetectorParams(features=fp), camera_matrix=k),
            "wm": ForwardDetector(DetectorParams(features=fp, memory=MemoryParams(max_places=args.max_places)),
                                  camera_matrix=k)}
    st = {m: {c: np.zeros(n) for c in COLUMNS} for m in dets}
    wm_size = np.zeros(n, np.int64)
    loops: dict[str, list] = {m: [] for m in dets}
    retrieved = transferred = 0
    render_t = np.zeros(n)
    samples: list[dict] = []
    feats_kept: list = []
    feat_bytes = 0
    brute = None

    def report(done: int) -> dict:
        res = {"benchmark": "forward_memory", "machine": machine_info(), "images": done,
               "images_planned": n, "route": args.route, "max_places": args.max_places,
               "max_features": args.max_features, "command": " ".join(sys.argv),
               "render_ms_median": float(np.median(render_t[:done]) * 1e3), "window": WINDOW,
               "samples": samples, "brute_force": brute, "methods": {}}
        for m, d in dets.items():
            s = {c: v[:done] for c, v in st[m].items()}
            detector_only = s["total"] - s["features"]
            found = loops[m]
            n_true = sum(true_loop(poses, a, b) for a, b in found)
            res["methods"][m] = {
                "at": {str(z): {"total": window_stats(s["total"], z),
                                "without_features": window_stats(detector_only, z),
                                **{c: window_stats(s[c], z) for c in COLUMNS[:-1]}}
                       for z in SIZES if z <= done},
                "vote_filter_memory_at": {str(z): window_stats(bounded_stages(st[m], done), z)
                                          for z in SIZES if z <= done},
                "slope_ms_per_1000_images": {
                    "vote_filter_memory_from_max_places": slope_ms_per_1000(bounded_stages(st[m], done),
                                                                            min(args.max_places, done)),
                    "total_from_1000": slope_ms_per_1000(s["total"], 1000),
                    "without_features_from_1000": slope_ms_per_1000(detector_only, 1000),
                    "without_features_from_max_places": slope_ms_per_1000(detector_only, min(args.max_places, done))},
                "loops": len(found), "loops_true_by_pose": int(n_true),
                "vocabulary_words": len(d.vocabulary),
                "inverted_index_bytes": d.index.memory_bytes(),
                "usearch_bytes": int(d.vocabulary._index.memory_usage),
                "wm_word_store_bytes": d.memory.memory_bytes(),
            }
        res["methods"]["wm"].update({"working_memory_max": int(wm_size[:done].max()) if done else 0,
                                     "retrieved": retrieved, "transferred": transferred})
        both = set(loops["paper"]) & set(loops["wm"])
        res["loops_in_both"] = len(both)
        res["features_bytes"] = feat_bytes
        res["per_image_series_ms"] = {m: {"total": np.round(st[m]["total"][:done] * 1e3, 2).tolist(),
                                          "without_features": np.round((st[m]["total"][:done] - st[m]["features"][:done]) * 1e3, 2).tolist(),
                                          "vote_filter_memory": np.round(bounded_stages(st[m], done) * 1e3, 3).tolist()}
                                      for m in dets}
        res["wm_size"] = wm_size[:done].tolist()
        return res

    t_start = time.perf_counter()
    for i in range(n):
        a = time.perf_counter()
        img = renderer.render(poses[i], float(times[i]))
        b = time.perf_counter()
        f = extract(img)
        c = time.perf_counter()
        render_t[i] = b - a
        feat_bytes += f.descriptors.nbytes + f.keypoints_px.nbytes
        if args.brute_images and i < args.brute_images:
            feats_kept.append(f)
        for m, d in dets.items():
            det = d.process_features(f, c - b)
            for col in COLUMNS:
                st[m][col][i] = det.times_s[col]
            if det.status == LOOP:
                loops[m].append((i, int(det.loop_id)))
            if m == "wm":
                wm_size[i] = det.working_memory
                retrieved += len(det.retrieved)
                transferred += len(det.transferred)
        done = i + 1
        if done % 250 == 0 or done == n:
            samples.append({"images": done, "rss_bytes": rss_bytes(), "features_bytes": feat_bytes,
                            **{f"{m}_words": len(d.vocabulary) for m, d in dets.items()},
                            **{f"{m}_index_bytes": d.index.memory_bytes() for m, d in dets.items()},
                            **{f"{m}_usearch_bytes": int(d.vocabulary._index.memory_usage) for m, d in dets.items()},
                            "elapsed_s": time.perf_counter() - t_start})
            print(f"{done:6d} images  {time.perf_counter() - t_start:7.0f} s  rss {samples[-1]['rss_bytes'] / 1e9:.2f} GB  "
                  + "  ".join(f"{m}: {np.median(st[m]['total'][done - 250:done] - st[m]['features'][done - 250:done]) * 1e3:.1f} ms"
                              f" loops {len(loops[m])}" for m in dets)
                  + f"  wm {wm_size[i]}", flush=True)
        if args.brute_images and done == args.brute_images:
            print(f"brute force on the first {done} images ...", flush=True)
            brute = brute_force(feats_kept, k, done)
            feats_kept = []
            print(f"  {brute['per_pair_ms']:.2f} ms per pair; extrapolated "
                  + ", ".join(f"{s}: {v / 1e3:.1f} s" for s, v in brute["extrapolated_ms"].items()), flush=True)
        if done % 500 == 0 or done == n:
            res = report(done)
            write_json(args.out, res)
            plot(args.out.with_suffix(".png"), st, done, args.max_places)

    res = report(n)
    print_summary(res)
    print(f"\nwrote {write_json(args.out, res)} and {args.out.with_suffix('.png')}")
    return 0


def bounded_stages(st: dict, done: int) -> np.ndarray:
    """Seconds per image of the stages the working memory bounds: the vote (likelihood),
    the filter and the memory's own bookkeeping."""
    return st["likelihood"][:done] + st["filter"][:done] + st["memory"][:done]


def plot(path: Path, st: dict, done: int, max_places: int) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(10, 10), sharex=True)
    i = np.arange(done)
    for ax, col, title in ((axes[0], "total", "per image, features included"),
                           (axes[1], "detector", "per image without feature extraction"),
                           (axes[2], "bounded", "vote + filter + memory (the stages the working memory bounds)")):
        for m, colour, label in (("paper", "tab:red", "paper (no bound)"),
                                 ("wm", "tab:blue", f"working memory, {max_places} places")):
            y = {"total": st[m]["total"][:done],
                 "detector": st[m]["total"][:done] - st[m]["features"][:done],
                 "bounded": bounded_stages(st[m], done)}[col]
            ax.plot(i, y * 1e3, ",", color=colour, alpha=0.3)
            if done >= 51:
                med = np.array([np.median(y[max(0, j - 50):j + 1]) for j in range(done)])
                ax.plot(i, med * 1e3, "-", color=colour, label=label + " (running median of 51)")
        ax.set_ylabel("ms")
        ax.set_title(title)
        ax.set_yscale("log")
        ax.legend(loc="upper left")
        ax.grid(True, which="both", alpha=0.3)
    axes[2].set_xlabel("image index")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def print_summary(res: dict) -> None:
    print(f"\n{res['images']} images; render {res['render_ms_median']:.1f} ms median")
    for m, r in res["methods"].items():
        print(f"\n{m}: loops {r['loops']} ({r['loops_true_by_pose']} true by pose), words {r['vocabulary_words']}")
        for z, a in r["at"].items():
            t, wf = a["total"], a["without_features"]
            print(f"  at {z:>5}: total median {t['median_ms']:.1f} ms p99 {t['p99_ms']:.1f} ms; "
                  f"without features median {wf['median_ms']:.1f} ms p99 {wf['p99_ms']:.1f} ms")
        for z, a in r["vote_filter_memory_at"].items():
            print(f"  at {z:>5}: vote + filter + memory median {a['median_ms']:.2f} ms p99 {a['p99_ms']:.2f} ms")
        print(f"  slope: {r['slope_ms_per_1000_images']}")
    if res.get("brute_force"):
        print(f"\nbrute force (extrapolated from {res['brute_force']['images_measured']} images): "
              + ", ".join(f"{s}: {v / 1e3:.1f} s" for s, v in res["brute_force"]["extrapolated_ms"].items()))


if __name__ == "__main__":
    sys.exit(main())
