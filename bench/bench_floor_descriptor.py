"""Compact floor descriptor against OpenCV SIFT: extraction time, size, matching time.

Paper 003 Sec. IV-B on our descriptor (modes 1-6) and on OpenCV SIFT, same frames, same
run, one thread (OpenCV and numpy's BLAS, :func:`floor_common.one_thread`):

* Table I: extraction time per 640x480 frame, per mode and SIFT, per floor, and the ratio
  SIFT / ours (target: >= 10x in every mode);
* Fig. 4: local features per frame and bytes per frame per mode, with the share of the
  mode's byte budget used (target: never above it, >= 85 % used on textured floors);
  SIFT's size as ``features x 128`` float32 (OpenCV's output) and as uint8;
* OpenCV ORB (500 keypoints, ``cv2.ORB_create()``'s default) extraction on the same
  frames, the cheap binary baseline a user might pick instead;
* Table II: matching time per frame pair (``local_score`` on decoded descriptors; SIFT:
  2-NN ratio test and RANSAC) and the ratio SIFT / ours (target: >= 50x). Pairs are the
  consecutive frames of the run and as many random pairs of frames of it.

Frames: a straight run of ``--frames`` frames 5 cm apart (12 by default, 30 with ``--full``) on each floor (gravel, grass,
brick, the herringbone photo, the default mixed floor, and every ``--floor FILE``).
Times are the median over frames (or pairs) of each item's median over ``--repeats``
timed calls after a warm-up; the spread is the interquartile range over items.

Times are CPU seconds of the calling thread (:func:`floor_common.time_each`).

**The office drive** (the daemon's case): the floor frames of the recorded 60 s office drive
(``robotd record --virtual --route office --duration 60``, cached as ``./dev bench daemon``
caches it; ``--recording`` names another), mode 4 as the daemon describes keyframes:

* describe time per frame, interleaved frame by frame (each method sees the same load):
  the default extraction, the selectable ``FULL_RESOLUTION`` one (the maps at every
  pixel with the exact channel split and the full repeat pool: the bytes before the
  faster defaults), the selectable cheaper ``COARSE`` one (the maps and the orientation
  from the detection image halved), the selectable ``QUARTER`` one (the candidates found on
  the detection image halved too: a quarter of its pixels), that one with ``detect_prefilter``
  (its quarter image the low-passed detection image halved), the default with
  ``orientation_from_maps`` (the orientation read from the pooled maps), OpenCV ORB (500) and SIFT, on ``--office-frames``
  frames spread over the drive;
* query time of the floor index (:class:`robotd.floor.index.FloorIndex`, the daemon's
  shortlist of 10 and the demo's loop threshold as ``min_score``) at 1,000 and 10,000
  keyframes, built as ``./dev bench daemon --scale`` builds it (the drive's first
  ``--office-distinct`` = 1,000 frames, repeated under new ids beyond that; ``--office-queries`` of those frames
  queried with the 20 s around them excluded), for the default descriptors; and, as a
  user might write it, ORB (500) + brute-force Hamming 2-NN
  (ratio 0.8) + RANSAC similarity against the ORB features of the same 10 shortlisted
  frames (matching time only, the query frame's ORB extraction is in its describe time).

Run from the repo root: ``.venv/bin/python bench/bench_floor_descriptor.py [--out DIR]
[--doc docs/benchmarks/floor_descriptor.md]``. Writes ``DIR/floor_descriptor.json`` and
``DIR/floor_descriptor_features.png``, and with ``--doc`` the Markdown page of the run.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import cv2
import numpy as np

try:
    from bench.common import print_table, write_json, write_page
    from bench.floor_common import (MODES, SiftBaseline, add_common_args, bench_floors, header,
                                    load_average, log, one_thread, pyplot, r, spread, time_each)
except ImportError:  # run as a script: bench/ is on sys.path
    from common import print_table, write_json, write_page
    from floor_common import (MODES, SiftBaseline, add_common_args, bench_floors, header,
                              load_average, log, one_thread, pyplot, r, spread, time_each)

from robotd.floor.descriptor import FULL_RESOLUTION, MODE_BYTES, QUARTER, ExtractParams, decode, extract
from robotd.floor.match import local_score
from robotd.base.camera import FloorCameraModel
from sim.pairs import straight_run

SPACING_M = 0.05
#: Selectable, not the default: the pooled maps and the orientation from the detection image
#: halved (cheaper; the demo's visual odometry lost accuracy with it).
COARSE = ExtractParams(orientation_step=2, exact_maps=True)
QUARTER_PREFILTERED = dataclasses.replace(QUARTER, detect_prefilter=True)
ORIENTATION_FROM_MAPS = ExtractParams(orientation_from_maps=True)
OFFICE_MODE = 4  # the daemon's mode
OFFICE_SHORTLIST = 10  # [floor_detector] shortlist
OFFICE_SIZES = (1000, 10000)


def bench_floor(name: str, floor: object, args: argparse.Namespace, sift: SiftBaseline) -> dict:
    """Every measurement for one floor."""
    cam = FloorCameraModel.default()
    rng = np.random.default_rng(args.seed)
    _, images = straight_run(floor, cam, rng, (0.0, 0.0, 0.0), (args.frames - 1) * SPACING_M, SPACING_M)
    n = len(images)
    consecutive = [(i, i + 1) for i in range(n - 1)]
    random_pairs = []
    while len(random_pairs) < n - 1:
        i, j = (int(v) for v in rng.choice(n, 2, replace=False))
        random_pairs.append((i, j))
    pairs = consecutive + random_pairs
    out: dict = {"floor": name, "frames": n, "pairs": {"consecutive": len(consecutive), "random": len(random_pairs)},
                 "modes": {}}

    for mode in MODES:
        log(f"  {name}: mode {mode}")
        t_ext = time_each(lambda im: extract(im, mode), images, args.repeats, warmup=2)
        blobs = [extract(im, mode) for im in images]
        t_dec = time_each(decode, blobs, args.repeats, warmup=2)
        decs = [decode(b) for b in blobs]
        sizes = np.array([len(b) for b in blobs])
        feats = np.array([len(d.xy_px) for d in decs])
        t_match = time_each(lambda p: local_score(decs[p[0]], decs[p[1]]), pairs, args.repeats, warmup=2)
        scores = np.array([local_score(decs[i], decs[j]).score for i, j in pairs], float)
        budget = MODE_BYTES[mode]
        out["modes"][str(mode)] = {
            "extract": t_ext, "decode": t_dec, "match": t_match,
            "features_mean": float(feats.mean()), "features_min": int(feats.min()), "features_max": int(feats.max()),
            "bytes_mean": float(sizes.mean()), "bytes_min": int(sizes.min()), "bytes_max": int(sizes.max()),
            "budget_bytes": int(budget), "budget_used_mean": float(sizes.mean() / budget),
            "budget_used_min": float(sizes.min() / budget), "over_budget_frames": int((sizes > budget).sum()),
            "score_consecutive_mean": float(scores[: len(consecutive)].mean()),
            "score_random_mean": float(scores[len(consecutive):].mean()),
        }

    log(f"  {name}: SIFT")
    t_ext = time_each(sift.extract, images, args.sift_repeats, warmup=1)
    feats = [sift.extract(im) for im in images]
    t_match = time_each(lambda p: sift.match(feats[p[0]], feats[p[1]]), pairs, args.sift_repeats, warmup=1)
    nf = np.array([len(f) for f in feats])
    scores = np.array([sift.match(feats[i], feats[j]).score for i, j in pairs], float)
    out["sift"] = {
        "extract": t_ext, "match": t_match,
        "features_mean": float(nf.mean()), "features_min": int(nf.min()), "features_max": int(nf.max()),
        "bytes_float32_mean": float(nf.mean() * 128 * 4), "bytes_uint8_mean": float(nf.mean() * 128),
        "score_consecutive_mean": float(scores[: len(consecutive)].mean()),
        "score_random_mean": float(scores[len(consecutive):].mean()),
    }
    log(f"  {name}: ORB")
    orb = cv2.ORB_create()
    t_orb = time_each(lambda im: orb.detectAndCompute(im, None), images, args.repeats, warmup=2)
    out["orb"] = {"extract": t_orb,
                  "features_mean": float(np.mean([len(orb.detect(im, None)) for im in images]))}
    for mode in MODES:
        m = out["modes"][str(mode)]
        m["extract_ratio_orb"] = t_orb["median_ms"] / m["extract"]["median_ms"]
        m["extract_ratio_sift"] = t_ext["median_ms"] / m["extract"]["median_ms"]
        m["match_ratio_sift"] = t_match["median_ms"] / m["match"]["median_ms"]
        m["bytes_ratio_sift_uint8"] = out["sift"]["bytes_uint8_mean"] / m["bytes_mean"]
    return out


def office_recording(args: argparse.Namespace) -> Path:
    """The recorded 60 s office drive (``--recording``, or the cache ``./dev bench daemon`` keeps)."""
    try:
        from bench.bench_daemon import ensure_recording
    except ImportError:
        from bench_daemon import ensure_recording
    ns = argparse.Namespace(recording=args.recording, cache=Path.home() / ".cache" / "robotd-bench",
                            route="office", duration=60.0, seed=0, forward=False)
    return ensure_recording(ns)


def bench_office(args: argparse.Namespace, sift: SiftBaseline) -> dict:
    """Describe and query times on the office drive's floor frames (module docstring)."""
    from drivers.recording.reader import RecordingReader
    from robotd.app.demo import shipped_calibration
    from robotd.base.messages import Frame
    from robotd.floor.index import FloorIndex, IndexParams
    from robotd.io.calibfile import read_calibration

    recording = office_recording(args)
    log(f"office drive: {recording}")
    with RecordingReader(recording) as rd:
        n_all = sum(1 for _t, msg in rd.messages() if isinstance(msg, Frame) and msg.camera == "floor")
    timed_at = set(np.linspace(0, n_all - 1, args.office_frames).astype(int).tolist())
    orb = cv2.ORB_create(nfeatures=500)
    methods = {"ours": lambda im: extract(im, OFFICE_MODE),
               "full_resolution": lambda im: extract(im, OFFICE_MODE, FULL_RESOLUTION),
               "coarse": lambda im: extract(im, OFFICE_MODE, COARSE),
               "quarter": lambda im: extract(im, OFFICE_MODE, QUARTER),
               "quarter_prefiltered": lambda im: extract(im, OFFICE_MODE, QUARTER_PREFILTERED),
               "orientation_from_maps": lambda im: extract(im, OFFICE_MODE, ORIENTATION_FROM_MAPS),
               "orb": lambda im: orb.detectAndCompute(im, None), "sift": sift.extract}
    times: dict[str, list[float]] = {k: [] for k in methods}
    blobs: dict[str, list[bytes]] = {"ours": []}
    orb_feats: list[tuple[np.ndarray, np.ndarray | None]] = []
    timed_frames: dict[int, np.ndarray] = {}
    warm = False
    with RecordingReader(recording) as rd:
        i = 0
        for _t, msg in rd.messages():
            if not (isinstance(msg, Frame) and msg.camera == "floor"):
                continue
            if i >= args.office_distinct and i > max(timed_at):
                break
            img = msg.image
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
            if not warm:
                for fn in methods.values():
                    fn(img)
                warm = True
            if i in timed_at:
                timed_frames[i] = img
                for name, fn in methods.items():
                    t0 = time.thread_time()
                    fn(img)
                    times[name].append(time.thread_time() - t0)
            if i < args.office_distinct:
                blobs["ours"].append(extract(img, OFFICE_MODE))
                kp, des = orb.detectAndCompute(img, None)
                orb_feats.append((np.float32([k.pt for k in kp]).reshape(-1, 2), des))
            i += 1
    distinct = len(blobs["ours"])
    out: dict = {"recording": recording.name, "frames": n_all, "timed_frames": len(timed_at), "mode": OFFICE_MODE,
                 "describe": {k: spread(v) for k, v in times.items()},
                 "bytes_mean": {k: float(np.mean([len(b) for b in v])) for k, v in blobs.items()},
                 "distinct": distinct, "shortlist": OFFICE_SHORTLIST, "query": {}}
    calib = read_calibration(shipped_calibration())
    min_score = (calib.loop.for_mode(OFFICE_MODE) if calib.loop is not None else None) or 0.0
    out["min_score"] = min_score
    fps = n_all / 60.0
    recent = int(20.0 * fps)
    rng = np.random.default_rng(args.seed)
    qs = rng.choice(distinct, size=min(args.office_queries, distinct), replace=False)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    for name in blobs:
        log(f"  office: index of the {name} descriptors")
        index = FloorIndex(IndexParams(shortlist=OFFICE_SHORTLIST))
        decoded = [decode(b) for b in blobs[name]]
        res = []
        for size in OFFICE_SIZES:
            for k in range(len(index), size):
                index.add(k, decoded[k % distinct])
            ids = np.arange(size)
            q_ms, orb_ms, loops = [], [], 0
            for q in qs:
                excluded = ids[np.abs(ids % distinct - q) < recent]
                t0 = time.thread_time()
                cands = index.query(decoded[q], k=5, min_score=min_score, exclude_ids=excluded)
                q_ms.append(time.thread_time() - t0)
                loops += len(cands)
                if name != "ours":
                    continue
                short = index.shortlist(decoded[q], exclude_ids=excluded)
                pts, des = orb_feats[q]
                t0 = time.thread_time()
                for kf_id, _g in short:
                    pts_b, des_b = orb_feats[kf_id % distinct]
                    if des is None or des_b is None or len(des) < 2 or len(des_b) < 2:
                        continue
                    good = [m[0] for m in bf.knnMatch(des, des_b, k=2)
                            if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
                    if len(good) >= 4:
                        cv2.estimateAffinePartial2D(pts[[m.queryIdx for m in good]], pts_b[[m.trainIdx for m in good]],
                                                    method=cv2.RANSAC, ransacReprojThreshold=8.0)
                orb_ms.append(time.thread_time() - t0)
            row = {"keyframes": size, "query": spread(q_ms), "candidates_mean": loops / len(qs),
                   "index_mb": index.nbytes / 1e6}
            if orb_ms:
                row["orb_match_shortlist"] = spread(orb_ms)
            res.append(row)
        out["query"][name] = res
    out["queries"] = len(qs)
    out["describe_ratio_orb"] = out["describe"]["orb"]["median_ms"] / out["describe"]["ours"]["median_ms"]
    out["describe_ratio_full_resolution"] = (out["describe"]["full_resolution"]["median_ms"]
                                             / out["describe"]["ours"]["median_ms"])
    return out


def plot_features(results: list[dict], path: Path) -> None:
    """Paper Fig. 4: local features per frame per mode and SIFT (bars, log scale) and floor
    (groups); beside it the share of each mode's byte bound used."""
    plt = pyplot()
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 4.5), dpi=110)
    width = 0.8 / (len(MODES) + 1)
    x = np.arange(len(results))
    for k, mode in enumerate(MODES):
        ax.bar(x + (k - 3) * width, [res["modes"][str(mode)]["features_mean"] for res in results],
               width, label=f"mode {mode}")
        ax2.bar(x + (k - 3) * width, [100 * res["modes"][str(mode)]["budget_used_mean"] for res in results],
                width, label=f"mode {mode}")
    ax.bar(x + 3 * width, [res["sift"]["features_mean"] for res in results], width, color="k", label="SIFT")
    ax.set_yscale("log")
    ax.set_xticks(x, [res["floor"] for res in results])
    ax.set_ylabel("local features per frame (mean, log)")
    ax.set_title("Local features per 640x480 frame (paper 003 Fig. 4)")
    ax.legend(fontsize=7, ncol=4, loc="upper left")
    ax.set_ylim(top=ax.get_ylim()[1] * 8)
    ax2.set_xticks(x, [res["floor"] for res in results])
    ax2.axhline(85, color="k", ls="--", lw=1)
    ax2.axhline(100, color="r", lw=1)
    ax2.set_ylim(0, 110)
    ax2.set_ylabel("bytes used, % of the mode's bound (mean over frames)")
    ax2.set_title("Descriptor size against its bound (dashed: 85 %, red: 100 %)")
    ax2.legend(fontsize=7, ncol=6, loc="lower center")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def print_floors(results: list[dict]) -> None:
    """The per-floor tables (paper 003 Tables I, II and Fig. 4)."""

    def per_mode(res: dict, key: str, sub: str | None = None, nd: int = 2) -> list[float]:
        vals = [res["modes"][str(m)][key] for m in MODES]
        return [r(v[sub] if sub else v, nd) for v in vals]

    mode_cols = [f"m{m}" for m in MODES]
    print("\nTable I: extraction time per 640x480 frame, ms (median over frames; one thread)")
    print_table(["floor", *mode_cols, "SIFT", "ORB"],
                [[res["floor"], *per_mode(res, "extract", "median_ms"), r(res["sift"]["extract"]["median_ms"], 1),
                  r(res["orb"]["extract"]["median_ms"], 2)] for res in results])
    print("\n  spread (IQR over frames), ms")
    print_table(["floor", *mode_cols, "SIFT"],
                [[res["floor"], *per_mode(res, "extract", "iqr_ms"), r(res["sift"]["extract"]["iqr_ms"], 1)]
                 for res in results])
    print("\n  SIFT / ours (target >= 10)")
    print_table(["floor", *mode_cols], [[res["floor"], *per_mode(res, "extract_ratio_sift", nd=1)] for res in results])
    print("\n  ORB / ours")
    print_table(["floor", *mode_cols], [[res["floor"], *per_mode(res, "extract_ratio_orb", nd=2)] for res in results])

    print("\nFig. 4: local features per frame (mean; SIFT: keypoints)")
    print_table(["floor", *mode_cols, "SIFT"],
                [[res["floor"], *per_mode(res, "features_mean", nd=1), r(res["sift"]["features_mean"], 0)]
                 for res in results])
    print("\n  bytes per frame, mean (max) / bound; SIFT: features x 128 x float32 and x uint8")
    rows = []
    for res in results:
        cells = [f"{res['modes'][str(m)]['bytes_mean']:.0f} ({res['modes'][str(m)]['bytes_max']})" for m in MODES]
        rows.append([res["floor"], *cells, f"{res['sift']['bytes_float32_mean']:.0f}",
                     f"{res['sift']['bytes_uint8_mean']:.0f}"])
    print_table(["floor", *[f"m{m} /{MODE_BYTES[m]}" for m in MODES], "SIFT f32", "SIFT u8"], rows)
    print("\n  share of the bound used, % : mean / minimum over frames (target >= 85, never > 100)")
    rows = [[res["floor"], *[f"{100 * res['modes'][str(m)]['budget_used_mean']:.1f} / "
                             f"{100 * res['modes'][str(m)]['budget_used_min']:.1f}" for m in MODES]]
            for res in results]
    print_table(["floor", *mode_cols], rows)

    print("\nTable II: matching time per frame pair, ms (median over consecutive and random pairs)")
    print_table(["floor", *mode_cols, "SIFT"],
                [[res["floor"], *per_mode(res, "match", "median_ms", 3), r(res["sift"]["match"]["median_ms"], 1)]
                 for res in results])
    print("\n  spread (IQR over pairs), ms")
    print_table(["floor", *mode_cols, "SIFT"],
                [[res["floor"], *per_mode(res, "match", "iqr_ms", 3), r(res["sift"]["match"]["iqr_ms"], 1)]
                 for res in results])
    print("\n  SIFT / ours (target >= 50)")
    print_table(["floor", *mode_cols], [[res["floor"], *per_mode(res, "match_ratio_sift", nd=1)] for res in results])
    print("\n  decode time per descriptor, ms (not in the match times: the index decodes once per keyframe)")
    print_table(["floor", *mode_cols], [[res["floor"], *per_mode(res, "decode", "median_ms", 3)] for res in results])
    print("\n  mean local score, consecutive pairs / random pairs (sanity: consecutive >> random)")
    rows = [[res["floor"], *[f"{res['modes'][str(m)]['score_consecutive_mean']:.1f}/"
                             f"{res['modes'][str(m)]['score_random_mean']:.1f}" for m in MODES],
             f"{res['sift']['score_consecutive_mean']:.0f}/{res['sift']['score_random_mean']:.0f}"]
            for res in results]
    print_table(["floor", *mode_cols, "SIFT"], rows)



def print_office(o: dict) -> None:
    """The office drive's tables."""
    d = o["describe"]
    print(f"\nOffice drive ({o['timed_frames']} of {o['frames']} frames, mode {o['mode']}): describe, ms per frame "
          "(median, IQR; interleaved)")
    print_table(["method", "median", "IQR"],
                [[k, r(v["median_ms"], 2), r(v["iqr_ms"], 2)] for k, v in d.items()])
    print(f"  ORB / ours {o['describe_ratio_orb']:.2f}; FULL_RESOLUTION / ours {o['describe_ratio_full_resolution']:.2f}")
    print(f"\n  query, ms (median, IQR over {o['queries']} queries; shortlist {o['shortlist']}, "
          f"min_score {o['min_score']:.1f})")
    rows = []
    for name, res in o["query"].items():
        for row in res:
            orb_cell = (f"{row['orb_match_shortlist']['median_ms']:.2f}" if "orb_match_shortlist" in row else "")
            rows.append([name, row["keyframes"], r(row["query"]["median_ms"], 2), r(row["query"]["iqr_ms"], 2),
                         r(row["candidates_mean"], 2), r(row["index_mb"], 1), orb_cell])
    print_table(["descriptors", "keyframes", "median", "IQR", "loops/query", "index MB", "ORB match shortlist"], rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_common_args(ap)
    ap.add_argument("--frames", type=int, default=None,
                    help="frames per floor, 5 cm apart (default 12, with --full 30: SIFT's matching on the rich "
                         "floors takes minutes per floor)")
    ap.add_argument("--full", action="store_true", help="the paper-sized run: 30 frames per floor")
    ap.add_argument("--repeats", type=int, default=3, help="timed calls per frame or pair, ours (default 3)")
    ap.add_argument("--doc", type=Path, default=None, help="also write the Markdown page of the run here")
    ap.add_argument("--sift-repeats", type=int, default=1,
                    help="timed calls per frame or pair, SIFT (default 1: it is 10-1000x slower)")
    ap.add_argument("--recording", type=Path, default=None,
                    help="office drive MCAP (default: the one ./dev bench daemon caches, recorded if missing)")
    ap.add_argument("--office-frames", type=int, default=100, help="office frames timed (default 100)")
    ap.add_argument("--office-queries", type=int, default=100, help="index queries per size (default 100)")
    ap.add_argument("--office-distinct", type=int, default=1000,
                    help="distinct frames in the index, repeated beyond (default 1000)")
    ap.add_argument("--skip", action="append", default=[], choices=["floors", "office"], help="leave a part out")
    args = ap.parse_args(argv)
    if args.frames is None:
        args.frames = 30 if args.full else 12
    load_start = load_average()
    blas = one_thread()
    log(f"load average {load_start}; BLAS pools {blas}")
    sift = SiftBaseline(args.seed)

    office = None
    if "office" not in args.skip:
        office = bench_office(args, sift)
        print_office(office)
    results = []
    for bf in ([] if "floors" in args.skip else bench_floors(args.floor, args.seed)):
        log(f"floor {bf.name} ({bf.source})")
        res = bench_floor(bf.name, bf.floor, args, sift)
        res["source"] = bf.source
        results.append(res)

    if results:
        print_floors(results)

    args.out.mkdir(parents=True, exist_ok=True)
    png = args.out / "floor_descriptor_features.png"
    if results:
        plot_features(results, png)
    payload = header("floor_descriptor", load_start=load_start, settings={
        "threads": 1, "image": [640, 480], "frames_per_floor": args.frames, "spacing_m": SPACING_M,
        "repeats": args.repeats, "sift_repeats": args.sift_repeats, "seed": args.seed,
        "mode_bytes": {str(m): int(MODE_BYTES[m]) for m in MODES},
        "sift": {"ratio": SiftBaseline.ratio, "ransac_px": SiftBaseline.ransac_px,
                 "matcher": "BFMatcher L2 knnMatch k=2", "model": "estimateAffinePartial2D RANSAC"},
        "timing": "median over items of the median of repeats, after warm-up; spread = IQR over items",
    })
    payload["floors"] = results
    payload["office"] = office
    out = write_json(args.out / "floor_descriptor.json", payload)
    print(f"\nwrote {out} and {png}")
    if args.doc is not None:
        write_page(args.doc, markdown(payload))
        print(f"wrote {args.doc}")
    return 0


def markdown(p: dict) -> list[str]:
    """The page of a run: extraction against SIFT and ORB, bytes, matching."""
    floors = p["floors"]
    m = p["machine"]
    cols = [f"m{k}" for k in MODES]

    def row(cells: list[object]) -> str:
        return "| " + " | ".join(str(c) for c in cells) + " |"

    def head(names: list[str]) -> list[str]:
        return [row(names), "|" + "---|" + "---:|" * (len(names) - 1)]

    lines = ["# The floor descriptor against OpenCV SIFT and ORB (`./dev bench floor_descriptor`)", "",
             "Generated from `floor_descriptor.json` by `bench/bench_floor_descriptor.py --doc`; the script's",
             "docstring says what is measured. CPU ms of one thread per 640 x 480 frame,",
             "measured on a machine shared with other jobs: read the ratios, which come from one run.", "",
             f"Machine: {m.get('platform', '')}, {m.get('cpu_count', '?')} CPUs, load average "
             f"{m.get('load_average_start')} at the start, {m.get('load_average_end')} at the end.", ""]
    o = p.get("office")
    if o:
        d = o["describe"]
        names = {"ours": "ours (default)",
                 "full_resolution": "ours, `FULL_RESOLUTION` (the maps at every pixel, the exact split: the previous bytes)",
                 "coarse": "ours, `COARSE` (maps and orientation from the image halved: `orientation_step=2`, "
                           "`exact_maps`)",
                 "quarter": "ours, `QUARTER` (candidates too from the image halved: `detect_step=2`, `exact_maps`)",
                 "quarter_prefiltered": "ours, `QUARTER` with `detect_prefilter` (the halved image low-passed first)",
                 "orientation_from_maps": "ours, `orientation_from_maps` (the orientation read from the pooled maps)",
                 "orb": "OpenCV ORB (500)",
                 "sift": "OpenCV SIFT"}
        lines += ["## The office drive (the daemon's keyframes)", "",
                  f"{o['timed_frames']} floor frames spread over the recorded 60 s office drive ({o['frames']} "
                  f"frames), mode {o['mode']}, the methods interleaved frame by frame. `FULL_RESOLUTION` gives the "
                  "bytes before the faster defaults; `COARSE` is cheaper and not the default: the demo's visual "
                  "odometry lost accuracy with it"
                  + ("; `QUARTER` is cheaper still and not the default: the printed plank floor aliases with it"
                     if "quarter" in d else "")
                  + (" (less with `detect_prefilter`, but still above the alias test's bound)"
                     if "quarter_prefiltered" in d else "") + " (docs/performance.md).", "",
                  "Describe, ms per frame:", "", *head(["method", "median", "IQR", "bytes (mean)"])]
        for k, v in d.items():
            b = o["bytes_mean"].get(k)
            lines.append(row([names.get(k, k), f"{v['median_ms']:.2f}", f"{v['iqr_ms']:.2f}",
                              f"{b:.0f}" if b is not None else ""]))
        lines += ["", f"ORB / ours {o['describe_ratio_orb']:.2f}, `FULL_RESOLUTION` / ours "
                      f"{o['describe_ratio_full_resolution']:.2f}, SIFT / ours "
                      f"{d['sift']['median_ms'] / d['ours']['median_ms']:.1f}.", "",
                  f"Query of the floor index, ms ({o['queries']} queries per size; shortlist {o['shortlist']}, "
                  f"the demo's loop threshold {o['min_score']:.1f} as `min_score`; {o['distinct']} distinct frames, "
                  "repeated under new ids beyond), and ORB's brute-force matching against the same "
                  "shortlisted frames:", "",
                  *head(["descriptors", "keyframes", "query median", "IQR", "loops per query", "index MB",
                         "ORB match of the shortlist"])]
        for name, res in o["query"].items():
            for q in res:
                orb_cell = f"{q['orb_match_shortlist']['median_ms']:.2f}" if "orb_match_shortlist" in q else ""
                lines.append(row([names.get(name, name), q["keyframes"], f"{q['query']['median_ms']:.2f}",
                                  f"{q['query']['iqr_ms']:.2f}", f"{q['candidates_mean']:.2f}",
                                  f"{q['index_mb']:.1f}", orb_cell]))
        lines.append("")
    if not floors:
        return lines + ["The benchmark floors were not part of this run (`--skip floors`).", ""]
    lines += ["## The benchmark floors", "",
              f"The virtual floor camera, {p['settings']['frames_per_floor']} frames 5 cm apart per floor, "
              "median over frames.", "",
              "Extraction, ms:", "", *head(["floor", *cols, "SIFT", "ORB (500)"])]
    for res in floors:
        lines.append(row([res["floor"], *[f"{res['modes'][str(k)]['extract']['median_ms']:.2f}" for k in MODES],
                          f"{res['sift']['extract']['median_ms']:.1f}", f"{res['orb']['extract']['median_ms']:.2f}"]))
    lines += ["", "SIFT / ours and ORB / ours (above 1: ours is faster):", "", *head(["floor", *cols])]
    for res in floors:
        lines.append(row([res["floor"], *[f"{res['modes'][str(k)]['extract_ratio_sift']:.1f} / "
                                          f"{res['modes'][str(k)]['extract_ratio_orb']:.2f}" for k in MODES]]))
    lines += ["", "Bytes per frame, mean (largest) against the bound, and local features:", "",
              *head(["floor", *[f"m{k} / {MODE_BYTES[k]}" for k in MODES], "SIFT keypoints"])]
    for res in floors:
        lines.append(row([res["floor"], *[f"{res['modes'][str(k)]['bytes_mean']:.0f} ({res['modes'][str(k)]['bytes_max']}),"
                                          f" {res['modes'][str(k)]['features_mean']:.0f} kp" for k in MODES],
                          f"{res['sift']['features_mean']:.0f}"]))
    lines += ["", "Matching a pair of decoded descriptors (`local_score`), ms, and SIFT's 2-NN + RANSAC:", "",
              *head(["floor", *cols, "SIFT"])]
    for res in floors:
        lines.append(row([res["floor"], *[f"{res['modes'][str(k)]['match']['median_ms']:.3f}" for k in MODES],
                          f"{res['sift']['match']['median_ms']:.1f}"]))
    return lines + [""]


if __name__ == "__main__":
    sys.exit(main())
