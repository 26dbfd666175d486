"""The default forward detector's word search: time per image as the run grows, bytes per
image in RAM and in the map file, and what its approximate search costs in recall.

Two parts, each against a baseline of the same run:

1. **Sequences** (the development data, as ``bench/bench_forward_ablation.py`` reads them):
   the real corridor of ``../shared/data/forward/rtabmap_samples`` (84 images) and the
   virtual office route (1139 images at 640x480, written into ``--dir`` when missing). The
   default detector runs over the same extracted features with its own word search
   (``binary_search = "tree"``, :class:`robotd.forward.vocabulary.BinaryWordTree`), the
   same with a wider beam (8 leaves instead of 4: a more exact search for more time), and
   with usearch's HNSW graph (the search it replaces). Reported: recall at 100 % precision,
   false positives, time per image *features included* (median, p99) beside OpenCV's own
   ORB extraction (300 keypoints) of the same images in the same run, the word stage's
   time, bytes per image held in RAM by part, and bytes per image in the map file (the
   detector's images and words written with :meth:`robotd.io.store.MapStore.add_forward_image`,
   as the daemon does; the file's growth over the same keyframes without forward rows).
2. **Scale**: ``--images`` images (default 2000; ``--full``: 10,000) made from the office
   route's images, lap after lap, each lap changed so that words do not simply repeat:
   every image shifted by a few pixels (the same random shift for a lap), mirrored on odd
   laps, its brightness scaled and offset (per lap). The default detector (tree) runs over
   them; reported: the median and p99 of the per-image time (features included) over the
   200 images up to 1000 and up to the end, their ratio, OpenCV's ORB over the same
   windows, the same on the process's CPU clock (a loaded machine stretches wall times
   more), each stage's median and mean per window, and bytes per image in RAM (the
   detector's parts) and the process RSS after 1, 5, 10, 20, 50, 62, 100, 200, 300 and every 500
   images.

Run: ``PYTHONPATH=. .venv/bin/python bench/bench_forward_scale.py --dir /tmp/office``
(about 10 minutes on the shared 2-core machine); ``--full`` for 10,000 images;
``--page FILE.json`` rewrites ``docs/benchmarks/forward_scale.md`` from a result; a run with
``--out`` elsewhere leaves the page as it is.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

try:
    from bench.bench_forward_ablation import extract_timed, office_sequence
    from bench.common import machine_info, write_json, write_page
except ImportError:  # run as a script: bench/ is on sys.path
    from bench_forward_ablation import extract_timed, office_sequence  # type: ignore[no-redef]
    from common import machine_info, write_json, write_page

from robotd.forward import LOOP, FeatureExtractor, ForwardDetector, method_params
from robotd.forward.detector import STAGES
from robotd.forward.evaluation import score_decisions
from robotd.forward.verify import camera_matrix_guess
from robotd.io.sequence import list_images, load_ground_truth, read_image

REPO = Path(__file__).resolve().parent.parent
DATA = REPO.parent / "shared" / "data"
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "forward_scale.json"
PAGE = REPO / "docs" / "benchmarks" / "forward_scale.md"
WINDOW = 200
#: The scale part's memory samples: these image counts, and every 500 images.
EARLY_SAMPLES = (1, 5, 10, 20, 50, 62, 100, 200, 300)
#: The variants compared: name -> fields of VocabularyParams, of VerifyParams and of
#: DetectorParams replaced in the default (``--variants`` picks some).
_BOUNDED: tuple[dict[str, object], dict[str, object]] = (
    {"guided_estimator": "usac", "fallback_band_px": 10.0}, {"verify_fallbacks": 1})
VARIANTS: dict[str, tuple[dict[str, object], dict[str, object], dict[str, object]]] = {
    "tree": ({}, {}, {}),
    "tree, beam 8": ({"tree_beam": 8}, {}, {}),
    "usearch": ({"binary_search": "usearch"}, {}, {}),
    "tree, general verification": ({}, {"model": "general"}, {}),
    "tree, USAC verification": ({}, {"model": "general", "estimator": "usac"}, {}),
    "tree, USAC without local optimisation": ({}, {"model": "general", "estimator": "usac", "local_optimisation": False},
                                              {}),
    "tree, RANSAC at most 200 samples": ({}, {"model": "general", "max_iterations": 200}, {}),
    # the bounded verification (robotd.forward.detector.bounded_verification, the default), and
    # its levers one at a time left out; "previous planar verification" is the verification
    # without the bound (robotd.forward.detector.unbounded_verification)
    "tree, bounded verification": ({}, _BOUNDED[0], _BOUNDED[1]),
    "tree, previous planar verification": ({}, {"guided_estimator": None, "fallback_band_px": None},
                                           {"verify_fallbacks": None}),
    "tree, RANSAC near the level motion": ({}, {**_BOUNDED[0], "guided_estimator": None}, _BOUNDED[1]),
    "tree, fallback over all matches": ({}, {**_BOUNDED[0], "fallback_band_px": None}, _BOUNDED[1]),
    "tree, fallbacks unbounded": ({}, _BOUNDED[0], {}),
    "tree, USAC in the fallback": ({}, {**_BOUNDED[0], "fallback_estimator": "usac"}, _BOUNDED[1]),
    # the band fallback's screen (VerifyParams.fallback_screen: USAC first, which can only refuse)
    "tree, band fallback screened": ({}, {**_BOUNDED[0], "fallback_screen": "usac"}, _BOUNDED[1]),
}


def rss_bytes() -> int:
    """Resident set size of this process (Linux /proc)."""
    with open("/proc/self/statm", encoding="ascii") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def gray(im: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im


def opencv_orb_ms(images: list[np.ndarray], clock: Callable[[], float] = time.perf_counter) -> np.ndarray:
    """OpenCV's own ORB (300 keypoints) per image, ms by ``clock``: the time column's
    baseline (wall by default; ``time.process_time``: CPU of the process, all its threads,
    beside the wall times, which a loaded machine stretches)."""
    orb = cv2.ORB_create(nfeatures=300)
    out = np.zeros(len(images))
    for i, im in enumerate(images):
        g = gray(im)
        t0 = clock()
        orb.detectAndCompute(g, None)
        out[i] = (clock() - t0) * 1e3
    return out


def map_file_bytes(det: ForwardDetector, kept_new: list, kept_purged: list, kept_words: list) -> dict[str, float]:
    """Bytes per image the detector's memory takes in a map file: the file's growth when
    the forward rows are written over keyframes already there (``kept_words``: each
    image's word ids as the run gave them; the detector keeps them for its latest image
    only)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "map.sqlite"
        from robotd.io.store import MapStore

        n = len(det)
        with MapStore.open(path, synchronous="NORMAL") as store:
            run = store.begin_run("bench = 1\n", started_ns=1)
            cov = np.eye(3) * 1e-4
            kfs = [store.add_keyframe(run, 10 + i, (0.1 * i, 0.0, 0.0), cov, None) for i in range(n)]
        before = path.stat().st_size
        with MapStore.open(path, synchronous="NORMAL") as store:
            kind = det.params.features.kind
            for t in range(n):
                f = det.features_of(t)
                ids, descs = kept_new[t]
                store.add_forward_image(t, kfs[t], kind, f.image_size_px, kept_words[t], f.keypoints_q, f.descriptors,
                                        new_words=[(int(i), d.tobytes()) for i, d in zip(ids, descs)],
                                        purged=[int(i) for i in kept_purged[t]])
        after = path.stat().st_size
        # the restart: the memory read back and taken up by a fresh detector
        t0 = time.perf_counter()
        with MapStore.open(path, read_only=True) as store:
            images, words = store.forward_memory()
        restored = ForwardDetector(det.params, camera_matrix=det.camera_matrix)
        from robotd.forward.features import CompactFeatures

        dim = det.params.features.descriptor_size
        feats = [CompactFeatures(w, kq, np.frombuffer(d, np.uint8).reshape(-1, dim), size)
                 for (_, _, _, size, w, kq, d) in images]
        wd = np.zeros((len(words), dim), np.uint8)
        for k, w in enumerate(words):
            if not w[4]:
                wd[k] = np.frombuffer(w[2], np.uint8)
        restored.restore(feats, wd, np.array([w[3] for w in words], np.int64), np.array([w[4] for w in words], bool))
        restore_s = time.perf_counter() - t0
    return {"bytes_per_image": (after - before) / max(n, 1), "file_bytes": after, "restore_s": restore_s,
            "restored_searchable_words": restored.vocabulary.n_searchable}


def run_sequence(name: str, folder: Path, truth_path: Path, variants: list[str], recent: int = 10,
                 odometry: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, object]:
    """Each variant over one sequence (``odometry``: ``(N, 3)`` poses and ``(N, 3, 3)``
    covariances given with the images, the office route's fused pose; None: no pose)."""
    files = list_images(folder, exclude=(truth_path,))
    truth = load_ground_truth(truth_path, len(files))
    images = [read_image(p) for p in files]
    h, w = images[0].shape[:2]
    k = camera_matrix_guess(w, h, 525.0 if name.startswith("office") else None)
    cv_ms = opencv_orb_ms(images)
    cv_cpu = opencv_orb_ms(images, time.process_time)
    base = method_params("default")
    feats = extract_timed(base.features, images)
    # the features' CPU (the process's, all its threads), for the CPU time per image
    ex = FeatureExtractor(base.features)
    feat_cpu = np.zeros(len(images))
    for i, im in enumerate(images):
        c0 = time.process_time()
        ex(im)
        feat_cpu[i] = (time.process_time() - c0) * 1e3
    out: dict[str, object] = {"images": len(files), "image_size": [w, h], "pose": odometry is not None,
                              "opencv_orb_cpu_ms_p99": float(np.percentile(cv_cpu, 99)),
                              "opencv_orb_ms": {"median": float(np.median(cv_ms)),
                                                "p99": float(np.percentile(cv_ms, 99))},
                              "opencv_orb_cpu_ms_median": float(np.median(cv_cpu)),
                              "variants": {}}
    print(f"\n{name}: {len(files)} images ({w}x{h}); OpenCV ORB (300): median {np.median(cv_ms):.1f} ms", flush=True)
    for variant in variants:
        voc_change, verify_change, det_change = VARIANTS[variant]
        params = replace(base, vocabulary=replace(base.vocabulary, **voc_change),
                         verify=replace(base.verify, **verify_change), **det_change)  # type: ignore[arg-type]
        det = ForwardDetector(params, camera_matrix=k)
        n = len(files)
        cand, conf, decl = np.full(n, -1), np.zeros(n), np.zeros(n, bool)
        total, words_ms, verify_ms = np.zeros(n), np.zeros(n), np.zeros(n)
        stage_ms = {st: np.zeros(n) for st in STAGES}
        verified = np.zeros(n, bool)
        kept_new, kept_purged, kept_words = [], [], []
        cpu_ms = np.zeros(n)  # the detector's CPU per image, features excluded
        for t, (fe, fs) in enumerate(feats):
            c0 = time.process_time()
            d = (det.process_features(fe, fs) if odometry is None
                 else det.process_features(fe, fs, odometry[0][t], odometry[1][t]))
            cpu_ms[t] = (time.process_time() - c0) * 1e3
            total[t] = d.times_s["total"] * 1e3
            words_ms[t] = d.times_s["words"] * 1e3
            verify_ms[t] = d.times_s["verify"] * 1e3
            for st in STAGES:
                stage_ms[st][t] = d.times_s[st] * 1e3
            verified[t] = d.verification is not None
            kept_new.append(det.vocabulary.last_new)
            kept_purged.append(det.vocabulary.last_purged)
            kept_words.append(det.features_of(t).words)
            if d.candidate_id is not None:
                cand[t], conf[t], decl[t] = d.candidate_id, d.candidate_probability, d.status == LOOP
        s = score_decisions(cand, conf, decl, truth, recent)
        mem = det.memory_bytes()
        row = {**s.as_dict(), "ms_median": float(np.median(total)), "ms_p99": float(np.percentile(total, 99)),
               "words_ms_median": float(np.median(words_ms)), "words_ms_p99": float(np.percentile(words_ms, 99)),
               "verify_ms_median": float(np.median(verify_ms)), "verify_ms_p99": float(np.percentile(verify_ms, 99)),
               "images_verified": int(verified.sum()),
               "cpu_ms_without_features": {"median": float(np.median(cpu_ms)), "p99": float(np.percentile(cpu_ms, 99))},
               # the CPU per image with the features (the same images' extraction CPU added)
               "cpu_ms": {"median": float(np.median(cpu_ms + feat_cpu)),
                          "p99": float(np.percentile(cpu_ms + feat_cpu, 99))},
               # each stage's own median, p99 and mean (ms), and its share of the slowest 1 %
               "stages_ms": {st: {"median": float(np.median(v)), "p99": float(np.percentile(v, 99)),
                                  "mean": float(v.mean()),
                                  "slowest_1pct_mean": float(v[total >= np.percentile(total, 99)].mean())}
                             for st, v in stage_ms.items()},
               # the images above the 99th percentile of the total: how much of them is verification
               "verify_share_of_slowest": float(verify_ms[total >= np.percentile(total, 99)].sum()
                                                / max(total[total >= np.percentile(total, 99)].sum(), 1e-9)),
               "ratio_to_opencv_orb": float(np.median(total) / np.median(cv_ms)),
               "words": len(det.vocabulary), "searchable_words": det.vocabulary.n_searchable,
               "ram_bytes_per_image": sum(mem.values()) / n,
               "ram_bytes_per_image_by_part": {p: v / n for p, v in mem.items()}}
        if variant == "tree" and odometry is None:
            row["map_file"] = map_file_bytes(det, kept_new, kept_purged, kept_words)
        out["variants"][variant] = row
        mf = row.get("map_file", {}).get("bytes_per_image", float("nan"))
        print(f"  {variant:13s} R@100%P {s.recall_at_full_precision:.3f} FP {s.false_positives} "
              f"ms {row['ms_median']:.1f} / p99 {row['ms_p99']:.1f} (words {row['words_ms_median']:.1f}, verify p99 "
              f"{row['verify_ms_p99']:.1f}) "
              f"x ORB {row['ratio_to_opencv_orb']:.1f}  RAM {row['ram_bytes_per_image']:.0f} B/img "
              f"{ {p: round(v) for p, v in row['ram_bytes_per_image_by_part'].items()} }  map {mf:.0f} B/img",
              flush=True)
    return out


def changed(im: np.ndarray, lap: int, rng_seed: int) -> np.ndarray:
    """Image ``im`` as lap ``lap`` shows it: lap 0 as is; later laps shifted (up to 12 px),
    mirrored on odd laps, brightness scaled 0.75-1.25 and offset by up to 20 grey levels."""
    g = gray(im)
    if lap == 0:
        return g
    r = np.random.default_rng(rng_seed * 1000 + lap)
    dx, dy = r.integers(-12, 13, 2)
    a, b = r.uniform(0.75, 1.25), r.uniform(-20, 20)
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    out = cv2.warpAffine(g, m, (g.shape[1], g.shape[0]), borderMode=cv2.BORDER_REPLICATE)
    if lap % 2:
        out = out[:, ::-1]
    return np.clip(out.astype(np.float32) * a + b, 0, 255).astype(np.uint8)


def run_scale(folder: Path, n: int, seed: int, partial: Callable[[dict[str, object]], None] | None = None,
              memory_only: bool = False) -> dict[str, object]:
    """The scale part (module notes); ``partial`` gets the result so far every 1000 images.
    ``memory_only``: no candidate is ever verified (k = 10^9 consistent candidates asked):
    the detector's memory is the same (nothing in it depends on a verification without a
    working memory bound) in a fraction of the time; its times are not the detector's."""
    files = list_images(folder, exclude=(folder / "gt.npy",))
    base_images = [read_image(p) for p in files]
    params = method_params("default")
    if memory_only:
        params = replace(params, consistency=10**9)
    h, w = base_images[0].shape[:2]
    det = ForwardDetector(params, camera_matrix=camera_matrix_guess(w, h, 525.0))
    ex = FeatureExtractor(params.features)
    orb = cv2.ORB_create(nfeatures=300)
    total, orb_ms, words_ms, verify_ms = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    stage_ms = {s: np.zeros(n) for s in STAGES}
    cpu_ms, orb_cpu_ms = np.zeros(n), np.zeros(n)  # the process's CPU (a loaded machine stretches wall times)
    samples = []
    loops = 0

    def window(at: int) -> dict[str, float] | None:
        if at < WINDOW:
            return None
        sl = slice(at - WINDOW, at)
        return {"median_ms": float(np.median(total[sl])), "p99_ms": float(np.percentile(total[sl], 99)),
                "opencv_orb_median_ms": float(np.median(orb_ms[sl])), "words_median_ms": float(np.median(words_ms[sl])),
                "verify_p99_ms": float(np.percentile(verify_ms[sl], 99)),
                "cpu_median_ms": float(np.median(cpu_ms[sl])), "opencv_orb_cpu_median_ms": float(np.median(orb_cpu_ms[sl])),
                "stages_median_ms": {s: float(np.median(v[sl])) for s, v in stage_ms.items()},
                "stages_mean_ms": {s: float(np.mean(v[sl])) for s, v in stage_ms.items()}}

    def scale_result(done: int) -> dict[str, object]:
        at = {str(z): window(z) for z in sorted({1000, 2000, 5000, 10000, done}) if z <= done}
        first, last = at.get("1000"), at[str(done)]
        return {"images": done, "images_planned": n, "base_images": len(files), "loops": int(loops), "window": WINDOW,
                "at": at, "median_ratio_end_to_1000": (last["median_ms"] / first["median_ms"]) if first and last else None,
                "whole_run": {"median_ms": float(np.median(total[:done])), "p99_ms": float(np.percentile(total[:done], 99)),
                              "opencv_orb_median_ms": float(np.median(orb_ms[:done]))},
                "samples": list(samples)}

    t_start = time.perf_counter()
    print(f"\nscale: {n} images from {len(files)} office images, lap after lap (changed per lap)", flush=True)
    for i in range(n):
        im = changed(base_images[i % len(files)], i // len(files), seed)
        c0, t0 = time.process_time(), time.perf_counter()
        orb.detectAndCompute(im, None)
        c1, t1 = time.process_time(), time.perf_counter()
        fe = ex(im)
        t2 = time.perf_counter()
        d = det.process_features(fe, t2 - t1)
        c2 = time.process_time()
        cpu_ms[i], orb_cpu_ms[i] = (c2 - c1) * 1e3, (c1 - c0) * 1e3
        orb_ms[i] = (t1 - t0) * 1e3
        total[i] = d.times_s["total"] * 1e3
        words_ms[i] = d.times_s["words"] * 1e3
        verify_ms[i] = d.times_s["verify"] * 1e3
        for s, v in stage_ms.items():
            v[i] = d.times_s.get(s, 0.0) * 1e3
        loops += d.status == LOOP
        done = i + 1
        if done % 500 == 0 or done == n or done in EARLY_SAMPLES:
            mem = det.memory_bytes()
            samples.append({"images": done, "rss_bytes": rss_bytes(), "ram_bytes_per_image": sum(mem.values()) / done,
                            "ram_bytes_per_image_by_part": {p: v / done for p, v in mem.items()},
                            "words": len(det.vocabulary), "searchable_words": det.vocabulary.n_searchable,
                            "elapsed_s": time.perf_counter() - t_start})
            last = slice(max(0, done - 500), done)
            print(f"  {done:6d} images {samples[-1]['elapsed_s']:6.0f} s  last 500: median {np.median(total[last]):.1f} ms "
                  f"(ORB {np.median(orb_ms[last]):.1f}, words {np.median(words_ms[last]):.1f})  "
                  f"RAM {samples[-1]['ram_bytes_per_image']:.0f} B/img  searchable words {det.vocabulary.n_searchable}",
                  flush=True)

        if partial is not None and done % 1000 == 0 and done < n:
            partial(scale_result(done))

    return scale_result(n)


def fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def page(res: dict) -> list[str]:
    """The Markdown page of a result."""
    m = res["machine"]
    lines = ["# Forward word search: time and memory per image",
             "",
             "Generated by `bench/bench_forward_scale.py` from its JSON (do not edit by hand; "
             "`--page FILE.json` rewrites it). What is measured: [docs/forward.md](../forward.md), "
             "\"Time and memory\".",
             "",
             "Times come from a shared 2-core machine under a varying load: compare a row with OpenCV's own "
             "ORB extraction (300 keypoints) of the same images in the same run (the `ORB ms` and `x ORB` "
             "columns), not rows of different runs with each other. Times include feature extraction.",
             "",
             f"Machine and versions: {m.get('machine')}, cpu_count {m.get('cpu_count')}, python {m.get('python')}, "
             f"numpy {m.get('numpy')}, opencv {m.get('opencv')}. Command: `{res['command']}`.",
             "",
             "## The default detector on the development sequences, with each word search and verification",
             "",
             "`tree`: the default detector as the run measured it (see the command and commit above): "
             "robotd's own incremental k-medians tree over the binary words (a beam of 4 leaves) and the "
             "planar verification; `tree, bounded verification`: its work per image bounded (the essential "
             "matrix near the level motion searched by OpenCV's USAC, the general search after a failed one "
             "drawing its samples within 10 px of the level motion and run at most once per image: "
             "`robotd.forward.detector.bounded_verification`, the default since the run that measured it as "
             "`tree`); `tree, previous planar verification`: the verification without the bound "
             "(`unbounded_verification`): RANSAC near the level motion, the general search over all the "
             "matches for every view tried; `tree, "
             "RANSAC near the level motion`, `tree, fallback over all matches`, `tree, fallbacks unbounded`, "
             "`tree, USAC in the fallback`: one of the bound's levers changed; `tree, beam 8`: the default scanning 8 leaves; `usearch`: the HNSW "
             "graph the tree replaced; `tree, general verification`: OpenCV's five-point RANSAC over all the "
             "matches (`model = \"general\"`, the paper's); `tree, USAC verification`: the general verification "
             "with the essential matrix searched by OpenCV's USAC (`estimator = \"usac\"`, with its local "
             "optimisation); `tree, USAC without local optimisation`: the same with `local_optimisation = False`; "
             "`tree, RANSAC at most 200 samples`: the general verification with RANSAC's samples capped at 200 "
             "(`max_iterations = 200`). Same features, same run (rows that were not run are missing). The "
             "sequences: rtabmap_samples and the office route without a pose, and (`--fused`) the office route "
             "with the daemon's fused pose, the office target's configuration (up to three views verified per "
             "image). `verify ms p99`: the verification's own time at its 99th percentile; `verified`: images "
             "whose candidate was verified. RAM: what the detector holds per image (its stored images, the "
             "inverted index, the word search); map file: the file's growth per image when the detector's "
             "images and words are written as the daemon writes them.",
             "",
             "| sequence | variant | R@100%P | FP | ms median | ms p99 | ORB ms | x ORB | words ms | verify ms p99 | verified | searchable words | RAM B/image (images + index + search) | map file B/image |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|"]
    for sname, s in res.get("sequences", {}).items():
        orb = s["opencv_orb_ms"]["median"]
        for v, r in s["variants"].items():
            parts = r["ram_bytes_per_image_by_part"]
            mf = r.get("map_file", {}).get("bytes_per_image")
            lines.append(f"| {sname} ({s['images']}) | {v} | {r['recall_at_full_precision']:.3f} | {r['false_positives']} | "
                         f"{r['ms_median']:.1f} | {r['ms_p99']:.1f} | {orb:.1f} | {r['ratio_to_opencv_orb']:.1f} | "
                         f"{r['words_ms_median']:.1f} | {fmt(r.get('verify_ms_p99'))} | {r.get('images_verified', '-')} | "
                         f"{r['searchable_words']} | {r['ram_bytes_per_image']:.0f} "
                         f"({parts['images']:.0f} + {parts['index']:.0f} + {parts['vocabulary']:.0f}) | "
                         + (f"{mf:.0f} |" if mf is not None else "- |"))
    for sname, s in res.get("sequences", {}).items():
        mf = s["variants"].get("tree", {}).get("map_file")
        if mf:
            lines += ["", f"{sname}: the map file read back and a new detector restored from it (its word "
                          f"tree rebuilt from the stored words) in {mf['restore_s']:.1f} s, "
                          f"{mf['restored_searchable_words']} searchable words."]
    staged = [(sname, s, v, r) for sname, s in res.get("sequences", {}).items() for v, r in s["variants"].items()
              if "stages_ms" in r]
    if staged:
        lines += ["", "### Where the time goes: each stage's median / p99 (ms), and its mean over the slowest 1 % of images",
                  "", "Stages as the detector times them (`Detection.times_s`): `features` ORB extraction, `words` "
                  "the word search, new words, purging and adding the image to the inverted index, `likelihood` the "
                  "vote and the likelihood, `filter` the Bayes filter and the candidate, `verify` the epipolar "
                  "check (matching, the essential matrix, the motion refinement, the planar check), `memory` the "
                  "working memory (none without a bound).", "",
                  "| sequence | variant | " + " | ".join(STAGES) + " | total |",
                  "|---|---|" + "---:|" * (len(STAGES) + 1)]
        for sname, s, v, r in staged:
            st = r["stages_ms"]
            cells = [f"{st[k]['median']:.1f} / {st[k]['p99']:.1f} ({st[k]['slowest_1pct_mean']:.1f})" for k in STAGES]
            lines.append(f"| {sname} | {v} | " + " | ".join(cells) + f" | {r['ms_median']:.1f} / {r['ms_p99']:.1f} |")
    cpu = [(sname, s, v, r) for sname, s, v, r in staged if "cpu_ms_without_features" in r]
    if cpu:
        lines += ["", "CPU time beside the wall times above (the process's CPU, `time.process_time`; a loaded "
                  "machine stretches wall times, not these): per image with the features (median / p99 ms, and "
                  "the median over OpenCV's ORB CPU of the same images), the detector without the features, and "
                  "OpenCV's ORB of the same images.", "",
                  "| sequence | variant | CPU ms, features included | x ORB CPU | detector CPU ms, features excluded "
                  "| OpenCV ORB CPU ms median |",
                  "|---|---|---:|---:|---:|---:|"]
        for sname, s, v, r in cpu:
            c = r["cpu_ms_without_features"]
            orb_cpu = s["opencv_orb_cpu_ms_median"]
            w = r.get("cpu_ms")
            with_f = f"{w['median']:.1f} / {w['p99']:.1f}" if w else "-"
            ratio = f"{w['median'] / orb_cpu:.1f}" if w else "-"
            lines.append(f"| {sname} | {v} | {with_f} | {ratio} | {c['median']:.1f} / {c['p99']:.1f} | {orb_cpu:.1f} |")
    sc = res.get("scale")
    if sc:
        lines += ["",
                  f"## Time as the run grows: {sc['images']} images"
                  + (f" (of {sc['images_planned']} planned: the run was stopped there)"
                     if sc.get("images_planned", sc["images"]) > sc["images"] else ""),
                  "",
                  f"The office route's {sc['base_images']} images lap after lap, each lap shifted by up to 12 px, "
                  "mirrored on odd laps and its brightness changed (`changed()` in the bench), so the words of a "
                  f"lap are not those of the last one; the default detector (tree). Windows of the {sc['window']} "
                  "images up to the given count." + (f" {sc['note']}" if sc.get("note") else ""),
                  "",
                  "| images | ms median | ms p99 | ORB ms median | words ms median | likelihood + filter ms median "
                  "| verify ms median / p99 | CPU ms median | ORB CPU ms median |",
                  "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for z, wdw in sc["at"].items():
            if wdw:
                st = wdw.get("stages_median_ms")
                lf = fmt(st["likelihood"] + st["filter"]) if st else "-"
                vm = fmt(st["verify"]) if st else "-"
                lines.append(f"| {z} | {wdw['median_ms']:.1f} | {wdw['p99_ms']:.1f} | {wdw['opencv_orb_median_ms']:.1f} | "
                             f"{wdw['words_median_ms']:.1f} | {lf} | {vm} / {fmt(wdw.get('verify_p99_ms'))} | "
                             f"{fmt(wdw.get('cpu_median_ms'))} | {fmt(wdw.get('opencv_orb_cpu_median_ms'))} |")
        a, z = sc["at"].get("1000"), sc["at"].get(str(sc["images"]))
        if a and z and sc["images"] > 1000:
            rel = (z["median_ms"] / z["opencv_orb_median_ms"]) / (a["median_ms"] / a["opencv_orb_median_ms"])
            rel_w = (z["words_median_ms"] / z["opencv_orb_median_ms"]) / (a["words_median_ms"] / a["opencv_orb_median_ms"])
            lines += ["", f"Median at {sc['images']} over the median at 1000: {sc['median_ratio_end_to_1000']:.2f} as "
                          f"measured; {rel:.2f} with each window's time divided by OpenCV's ORB of the same window "
                          f"(the load changed during the run); the word stage alone: {rel_w:.2f}"
                          + (f"; in the process's CPU {z['cpu_median_ms'] / a['cpu_median_ms']:.2f}, "
                             f"{(z['cpu_median_ms'] / z['opencv_orb_cpu_median_ms']) / (a['cpu_median_ms'] / a['opencv_orb_cpu_median_ms']):.2f} "
                             "divided by OpenCV's ORB CPU" if "cpu_median_ms" in z and "cpu_median_ms" in a else "")
                          + f". The process RSS includes the bench's own {sc['base_images']} decoded images."]
        lines += ["", "| images | RAM B/image (images + index + search) | searchable words | process RSS MB |",
                  "|---:|---|---:|---:|"]
        for smp in sc["samples"]:
            p = smp["ram_bytes_per_image_by_part"]
            lines.append(f"| {smp['images']} | {smp['ram_bytes_per_image']:.0f} ({p['images']:.0f} + {p['index']:.0f} + "
                         f"{p['vocabulary']:.0f}) | {smp['searchable_words']} | {smp['rss_bytes'] / 1e6:.0f} |")
    sm = res.get("scale_memory")
    if sm:
        lines += ["", f"## Memory as the run grows, current arrays: {sm['images']} images", "",
                  "The same images with no candidate ever verified (`--memory-only`: the detector's memory does "
                  "not depend on its verifications); its times are not the detector's and are not shown."
                  + (f" {sm['note']}" if sm.get("note") else ""), "",
                  "| images | RAM B/image (images + index + search) | searchable words |", "|---:|---|---:|"]
        for smp in sm["samples"]:
            p = smp["ram_bytes_per_image_by_part"]
            lines.append(f"| {smp['images']} | {smp['ram_bytes_per_image']:.0f} ({p['images']:.0f} + {p['index']:.0f} + "
                         f"{p['vocabulary']:.0f}) | {smp['searchable_words']} |")
    return lines + [""]


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", type=Path, default=Path(tempfile.gettempdir()) / "robotd-office",
                    help="folder of the virtual office sequence (written when missing)")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--images", type=int, default=2000, help="images of the scale part")
    ap.add_argument("--full", action="store_true", help="10,000 images in the scale part")
    ap.add_argument("--only", choices=("sequences", "scale"), default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--memory-only", action="store_true",
                    help="the scale part without verification, for its memory only (kept as 'scale_memory')")
    ap.add_argument("--fused", action="store_true",
                    help="also the office route with the daemon's fused pose (bench_forward_ablation's "
                         "odometry_fused.csv beside the images; computed when missing, which takes long)")
    ap.add_argument("--variants", default=";".join(VARIANTS),
                    help=f"semicolon-separated variants of the sequences part (default: all of {', '.join(VARIANTS)})")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--update", action="store_true",
                    help="keep the parts of --out's earlier result that this run does not redo (with --only)")
    ap.add_argument("--page", type=Path, default=None, metavar="JSON",
                    help="only rewrite docs/benchmarks/forward_scale.md from this result")
    args = ap.parse_args(argv)
    if args.page is not None:
        write_page(PAGE, page(json.loads(args.page.read_text(encoding="utf-8"))))
        print(f"wrote {PAGE}")
        return 0
    n = 10000 if args.full else args.images
    res: dict[str, object] = {"benchmark": "forward_scale", "machine": {**machine_info(), "opencv": cv2.__version__},
                              "command": " ".join(["bench/bench_forward_scale.py", *(argv if argv is not None else sys.argv[1:])]),
                              "sequences": {}}
    if args.update and args.out.exists():
        earlier = json.loads(args.out.read_text(encoding="utf-8"))
        res["sequences"] = earlier.get("sequences", {}) if args.only == "scale" else {}
        for key in ("scale", "scale_memory"):
            if key in earlier and (args.only == "sequences" or key != ("scale_memory" if args.memory_only else "scale")):
                res[key] = earlier[key]
        res["command"] = f"{earlier.get('command')}; then {res['command']}"
    office = office_sequence(args.dir)
    if args.only in (None, "sequences"):
        rt = args.data / "forward" / "rtabmap_samples"
        variants = [v.strip() for v in args.variants.split(";") if v.strip()]
        unknown = [v for v in variants if v not in VARIANTS]
        if unknown:
            ap.error(f"unknown variants {unknown}; choose from {list(VARIANTS)}")
        res["sequences"]["rtabmap_samples"] = run_sequence("rtabmap_samples", rt, rt / "ground_truth.bmp", variants)
        write_json(args.out, res)
        res["sequences"]["office"] = run_sequence("office", office, office / "gt.npy", variants)
        write_json(args.out, res)
        if args.fused:
            try:
                from bench.bench_forward_ablation import office_fused_odometry
            except ImportError:  # run as a script
                from bench_forward_ablation import office_fused_odometry  # type: ignore[no-redef]
            res["sequences"]["office, fused pose"] = run_sequence("office, fused pose", office, office / "gt.npy",
                                                                  variants, odometry=office_fused_odometry(office))
            write_json(args.out, res)
    if args.only in (None, "scale"):
        def partial(sc: dict[str, object]) -> None:
            write_json(args.out, {**res, "scale": sc})

        key = "scale_memory" if args.memory_only else "scale"
        res[key] = run_scale(office, n, args.seed, None if args.memory_only else partial, args.memory_only)
        sc = res[key]
        print(f"median at {n} / median at 1000: {sc['median_ratio_end_to_1000']}")
    print(f"wrote {write_json(args.out, res)}")
    if args.out.resolve() != DEFAULT_OUT.resolve():
        print(f"{PAGE} left as it is (a result written elsewhere; --page {args.out} renders it)")
        return 0
    write_page(PAGE, page(res))
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
