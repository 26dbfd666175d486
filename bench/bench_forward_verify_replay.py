"""Verification without the stored descriptors: what each way costs in recall (the forward
memory's largest part, 9.6 of about 11.3 kB per image on the office route).

The default detector runs once over each development sequence (the real corridor of
``../shared/data/forward/rtabmap_samples`` and the virtual office route, as
``bench/bench_forward_ablation.py`` reads them); every verification it makes is recorded
(the past image's stored features, the new image's, the candidate, its probability), with
the image at which each word was purged. A verification's outcome does not change what the
detector does next (a refused candidate is only dismissed for that image), so the run's
decisions can be replayed with another matching of the past image: each recorded pair is
verified again, the loop declared when it passes, and recall at 100 % precision and false
positives scored as ``robotd eval forward`` does. Same candidates, same RANSAC, same seed;
only what the past image keeps for matching changes:

- ``stored descriptors``: the whole 32-byte ORB descriptor, Lowe's ratio test (the general
  model's verification as it is);
- ``word ids``: correspondences between features that share a word (as a direct index
  does), at most 2 x 2 per word (more is a repeated texture);
- ``first 16 bytes`` / ``first 8 bytes``: a shorter descriptor (ORB's tests are ordered by
  decreasing variance), the same ratio test on it;
- ``no descriptor for purged words``: a feature whose word was purged (seen in its image
  only, 50 images on) loses its descriptor.

Then the search for the essential matrix, with the stored descriptors (what makes the
verification's 99th percentile; ``docs/forward.md``, "Time and memory per image"):

- ``USAC, no local optimisation``: OpenCV's USAC (its faster five-point solver) with the
  same uniform samples, inlier count, threshold, confidence and bound as RANSAC, and no
  refinement of the best model: the same test with a cheaper sample;
- ``USAC, PROSAC order``: the same drawing its samples from the matches ordered by
  descriptor distance first (PROSAC);
- ``USAC screen, then RANSAC``: the cheap search first, refusing the candidate when its
  best model has fewer than ``min_inliers`` inliers in front of both cameras, RANSAC as the
  default otherwise (it accepts a subset of what the default accepts);
- ``RANSAC, at most 200 samples``: the general model with ``max_iterations = 200``.

Then the motion model (``VerifyParams.model``): ``planar model`` (the default detector's: a
level camera's motion found by two-point RANSAC, the essential matrix searched among the
matches near it, the general search capped at 200 samples after it when that fails and the
level motion's consensus reached ``fallback_inliers``), ``planar model, no fallback``, and
``planar motion decides`` (``model = "planar_motion"``: the level motion itself verified);
every other row uses the general model (the five-point RANSAC of the paper over all the
matches; ``stored descriptors`` is that model as it is, the rows above replace its
matching or its search). The detector whose verifications are recorded is the default
(the candidates do not depend on the verification's model).

Reported per variant and sequence: recall at 100 % precision, false positives, loops,
verification time (median, p99; noisy on a loaded machine), and the bytes per image the
variant would save; on the office route also the verified motion of the true loops
against the truth (the sequence's ``poses.csv`` and camera mount): the heading change's
error, and the bearing's for views at least 0.3 m apart (median and 90th percentile,
degrees). Run: ``PYTHONPATH=. .venv/bin/python bench/bench_forward_verify_replay.py
--dir /tmp/office`` (about 10 minutes on a quiet 2-core machine, longer under load);
``--page FILE.json`` rewrites ``docs/benchmarks/forward_verify_replay.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

try:
    from bench.bench_forward_ablation import extract_timed, office_sequence
    from bench.common import machine_info, write_json, write_page
except ImportError:  # run as a script: bench/ is on sys.path
    from bench_forward_ablation import extract_timed, office_sequence  # type: ignore[no-redef]
    from common import machine_info, write_json, write_page

from robotd.forward import LOOP, ForwardDetector, method_params
from robotd.forward.evaluation import score_decisions
from robotd.forward.verify import VerifyParams, camera_matrix_guess, match_features, ransac_iterations, verify_pair
from robotd.io.sequence import list_images, load_ground_truth, read_image

REPO = Path(__file__).resolve().parent.parent
DATA = REPO.parent / "shared" / "data"
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "forward_verify_replay.json"
PAGE = REPO / "docs" / "benchmarks" / "forward_verify_replay.md"


class _View:
    """A past image's keypoints with only some descriptors (``keep``) or shortened ones
    (``width`` bytes): what a variant keeps, read as verify_pair reads features."""

    def __init__(self, f: Any, keep: np.ndarray | None = None, width: int | None = None) -> None:
        self.f, self.keep, self.width = f, keep, width
        self.image_size_px = f.image_size_px
        self.words = getattr(f, "words", None)

    def __len__(self) -> int:
        return len(self.keypoints_px)

    @property
    def keypoints_px(self) -> np.ndarray:
        kp = self.f.keypoints_px
        return kp if self.keep is None else kp[self.keep]

    @property
    def descriptors(self) -> np.ndarray:
        d = self.f.descriptors if self.keep is None else self.f.descriptors[self.keep]
        return np.ascontiguousarray(d if self.width is None else d[:, :self.width])


class _Words:
    """The new image's extracted features with their words (for the word-id matching)."""

    def __init__(self, f: Any, words: np.ndarray) -> None:
        self.keypoints_px, self.descriptors, self.image_size_px, self.words = f.keypoints_px, f.descriptors, f.image_size_px, words

    def __len__(self) -> int:
        return len(self.keypoints_px)


def _word_matches(a: Any, b: Any, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Correspondences through word ids: every pair of features sharing a word, words held
    at most twice by each image."""
    wa, wb = np.asarray(a.words, np.int64), np.asarray(b.words, np.int64)
    ia: list[int] = []
    ib: list[int] = []
    for w in np.intersect1d(wa, wb).tolist():
        x, y = np.flatnonzero(wa == w), np.flatnonzero(wb == w)
        if len(x) * len(y) <= 4:
            for i in x.tolist():
                for j in y.tolist():
                    ia.append(i)
                    ib.append(j)
    return a.keypoints_px[np.asarray(ia, np.int64)], b.keypoints_px[np.asarray(ib, np.int64)]


def record(name: str, folder: Path, truth_path: Path) -> dict[str, Any]:
    """Run the default detector once and keep every verification it made."""
    files = list_images(folder, exclude=(truth_path,))
    truth = load_ground_truth(truth_path, len(files))
    images = [read_image(p) for p in files]
    h, w = images[0].shape[:2]
    k = camera_matrix_guess(w, h, 525.0 if name == "office" else None)
    params = method_params("default")
    det = ForwardDetector(params, camera_matrix=k)
    pairs: list[tuple[int, Any, Any, np.ndarray]] = []
    purged_at: dict[int, int] = {}
    words_of: list[np.ndarray] = []  # each image's word ids (the detector keeps the latest's only)
    inner = det._verify

    def hook(candidate: int, feats: Any, hyp_ids: np.ndarray, odo: Any) -> Any:
        # the past image as stored, with its words; the new image as the detector verifies
        # it (its extracted features) and its words
        words_of.append(det.features_of(len(det) - 1).words)
        old = replace(det.features_of(candidate), words=words_of[candidate])
        pairs.append((len(det) - 1, old, feats, words_of[-1]))
        return inner(candidate, feats, hyp_ids, odo)

    det._verify = hook  # type: ignore[method-assign]
    n = len(files)
    cand, conf, decl = np.full(n, -1), np.zeros(n), np.zeros(n, bool)
    for t, (fe, fs) in enumerate(extract_timed(params.features, images)):
        d = det.process_features(fe, fs)
        if len(words_of) < len(det):  # no verification this time: the hook did not record them
            words_of.append(det.features_of(len(det) - 1).words)
        purged_at.update({int(x): t for x in det.vocabulary.last_purged})
        if d.candidate_id is not None:
            cand[t], conf[t], decl[t] = d.candidate_id, d.candidate_probability, d.status == LOOP
    poses = mount = None
    if (folder / "poses.csv").exists() and (folder / "sequence.json").exists():
        poses = np.loadtxt(folder / "poses.csv", delimiter=",", skiprows=1)[:, 2:5]
        cam = json.loads((folder / "sequence.json").read_text(encoding="utf-8"))["camera"]
        mount = np.array([cam.get("x_m", 0.0), cam.get("y_m", 0.0), cam.get("yaw_rad", 0.0)])
    return {"pairs": pairs, "purged_at": purged_at, "cand": cand, "conf": conf, "decl": decl, "truth": truth,
            "k": k, "verify": params.verify, "poses": poses, "mount": mount, "features_per_image": float(np.mean([len(det.features_of(t)) for t in range(n)]))}


_NO_DISTORTION = np.zeros(5)


def _usac(p_old: np.ndarray, p_new: np.ndarray, k: np.ndarray, params: VerifyParams,
          sampler: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """OpenCV's USAC set to RANSAC's test (module notes), without local optimisation."""
    u = cv2.UsacParams()
    u.confidence = params.ransac_confidence
    u.threshold = params.ransac_threshold_px
    u.maxIterations = ransac_iterations(len(p_old), params.min_inliers, params.ransac_confidence,
                                        cap=params.max_iterations)
    u.sampler = sampler
    u.score = cv2.SCORE_METHOD_RANSAC
    u.loMethod = cv2.LOCAL_OPTIM_NULL
    u.final_polisher = cv2.NONE_POLISHER
    u.randomGeneratorState = params.seed
    u.isParallel = False
    kk = np.asarray(k, np.float64)
    return cv2.findEssentialMat(p_old, p_new, kk, kk, _NO_DISTORTION, _NO_DISTORTION, u)


def _searches() -> dict[str, Callable[..., tuple[np.ndarray | None, np.ndarray | None]]]:
    """The essential-matrix searches of the estimator variants (replacing
    ``robotd.forward.verify.essential_matrix``)."""
    import robotd.forward.verify as verify_mod

    ransac = verify_mod.essential_matrix

    def prosac(p_old: np.ndarray, p_new: np.ndarray, k: np.ndarray, params: VerifyParams) -> Any:
        return _usac(p_old, p_new, k, params, cv2.SAMPLING_PROSAC)  # matches come sorted by distance

    def screened(p_old: np.ndarray, p_new: np.ndarray, k: np.ndarray, params: VerifyParams) -> Any:
        e, mask = _usac(p_old, p_new, k, params, cv2.SAMPLING_UNIFORM)
        if e is None or mask is None or int(mask.sum()) < params.min_inliers:
            return None, None
        if cv2.recoverPose(e[:3], p_old, p_new, np.asarray(k, np.float64), mask=mask.copy())[0] < params.min_inliers:
            return None, None
        return ransac(p_old, p_new, k, params)

    return {"USAC, no local optimisation": lambda a, b, k, p: _usac(a, b, k, p, cv2.SAMPLING_UNIFORM),
            "USAC, PROSAC order": prosac, "USAC screen, then RANSAC": screened}


def _by_distance(a: Any, b: Any, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """:func:`match_features`' matches ordered by descriptor distance, nearest first
    (PROSAC's order)."""
    return match_features(a, b, ratio, by_distance=True)


def replay(rec: dict[str, Any], variant: str) -> dict[str, float | int]:
    """Verify the recorded pairs again with ``variant``'s matching or search; score the decisions."""
    import robotd.forward.verify as verify_mod

    vp: VerifyParams = replace(rec["verify"], **MODEL_VARIANTS.get(variant, {"model": "general"}))
    if variant == "RANSAC, at most 200 samples":
        vp = replace(vp, max_iterations=200)
    searches = _searches()
    saved_search = verify_mod.essential_matrix
    if variant in searches:
        verify_mod.essential_matrix = searches[variant]
    decl = rec["decl"].copy()
    ms = []
    matcher: Callable[..., tuple[np.ndarray, np.ndarray]] = match_features
    if variant == "word ids":
        matcher = _word_matches
    elif variant == "USAC, PROSAC order":
        matcher = _by_distance
    saved = verify_mod.match_features
    verify_mod.match_features = matcher
    dropped = []
    errors: dict[int, tuple[float, float, float]] = {}  # true loops: (heading error, bearing error, distance)
    try:
        for t, old, new, new_words in rec["pairs"]:
            if variant == "word ids":
                new = _Words(new, new_words)
            elif variant.startswith("first "):  # both images compared on the first bytes
                width = int(variant.split()[1])
                old, new = _View(old, width=width), _View(new, width=width)
            elif variant == "no descriptor for purged words":
                keep = np.array([rec["purged_at"].get(int(w), 1 << 30) > t for w in old.words.tolist()], bool)
                dropped.append(1.0 - keep.mean() if len(keep) else 0.0)
                old = _View(old, keep=keep)
            t0 = time.perf_counter()
            v = verify_pair(old, new, vp, rec["k"])
            ms.append((time.perf_counter() - t0) * 1e3)
            decl[t] = v.accepted
            c = int(rec["cand"][t])
            if v.accepted and rec.get("poses") is not None and c >= 0 and rec["truth"][t, c]:
                errors[t] = _pose_error(v, rec["poses"][c], rec["poses"][t], rec["mount"])
    finally:
        verify_mod.match_features = saved
        verify_mod.essential_matrix = saved_search
    s = score_decisions(rec["cand"], rec["conf"], decl, rec["truth"], 10)
    nf = rec["features_per_image"]
    if variant.startswith("first "):
        saved_b = (32 - int(variant.split()[1])) * nf
    elif variant in searches or variant.startswith("RANSAC") or variant in MODEL_VARIANTS:
        saved_b = 0.0
    else:
        saved_b = {"stored descriptors": 0.0, "word ids": 32 * nf,
                   "no descriptor for purged words": 32 * nf * (float(np.mean(dropped)) if dropped else 0.0)}[variant]
    out: dict[str, float | int] = {
        "recall_at_full_precision": s.recall_at_full_precision, "false_positives": s.false_positives,
        "loops": int(decl.sum()), "verify_ms_median": float(np.median(ms)) if ms else 0.0,
        "verify_ms_p99": float(np.percentile(ms, 99)) if ms else 0.0, "bytes_saved_per_image": saved_b}
    if errors:
        out.update(_error_stats(list(errors.values())))
        if variant in MODEL_VARIANTS or variant == "stored descriptors":  # kept to compare on common loops
            out["pose_errors"] = {str(t): list(e) for t, e in errors.items()}  # type: ignore[assignment]
    return out


def _error_stats(errors: list[tuple[float, float, float]]) -> dict[str, float | int]:
    """Median and 90th percentile of the heading errors, and of the bearing errors of the
    views at least 0.3 m apart (degrees)."""
    e = np.abs(np.asarray(errors, np.float64).reshape(-1, 3))
    far = e[:, 2] >= 0.3
    return {"pose_loops": len(e), "yaw_err_deg_median": float(np.median(e[:, 0])),
            "yaw_err_deg_p90": float(np.percentile(e[:, 0], 90)), "bearing_loops": int(far.sum()),
            "bearing_err_deg_median": float(np.median(e[far, 1])) if far.any() else float("nan"),
            "bearing_err_deg_p90": float(np.percentile(e[far, 1], 90)) if far.any() else float("nan")}


def common_loops(variants: dict[str, Any]) -> dict[str, Any]:
    """Each model variant's pose errors beside the general model's (``stored descriptors``)
    on the true loops both verified: ``{variant: {"loops": n, "model": stats, "general": stats}}``."""
    general = variants.get("stored descriptors", {}).get("pose_errors")
    out: dict[str, Any] = {}
    for name in MODEL_VARIANTS:
        mine = variants.get(name, {}).get("pose_errors")
        if general is None or mine is None:
            continue
        both = sorted(set(general) & set(mine), key=int)
        if both:
            out[name] = {"loops": len(both), "model": _error_stats([tuple(mine[t]) for t in both]),
                         "general": _error_stats([tuple(general[t]) for t in both])}
    return out


def _pose_error(v: Any, old_pose: np.ndarray, new_pose: np.ndarray, mount: np.ndarray) -> tuple[float, float, float]:
    """``(heading error, bearing error, distance)`` of a verified motion against the truth:
    degrees, degrees, metres (the new camera in the old camera's planar frame)."""
    from robotd.base.geometry import between, compose
    from robotd.forward.planar import planar_motion

    rel = between(compose(old_pose, mount), compose(new_pose, mount))
    dyaw, bearing, _ = planar_motion(v.rotation, v.translation_dir)
    return (math.degrees(math.remainder(dyaw - float(rel[2]), math.tau)),
            math.degrees(math.remainder(bearing - math.atan2(float(rel[1]), float(rel[0])), math.tau)),
            float(math.hypot(float(rel[0]), float(rel[1]))))


#: The motion-model variants: fields of VerifyParams replaced in the recorded detector's.
MODEL_VARIANTS: dict[str, dict[str, Any]] = {
    "planar model": {"model": "planar"},
    "planar model, no fallback": {"model": "planar", "fallback_inliers": None},
    "planar motion decides": {"model": "planar_motion"},
}

VARIANTS = ("planar model", "planar model, no fallback", "planar motion decides", "stored descriptors", "word ids", "first 16 bytes", "first 8 bytes",
            "no descriptor for purged words",
            "USAC, no local optimisation", "USAC, PROSAC order", "USAC screen, then RANSAC", "RANSAC, at most 200 samples")


def page(res: dict[str, Any]) -> list[str]:
    m = res["machine"]
    lines = ["# Forward verification without the stored descriptors, and other searches for the essential matrix",
             "",
             "Generated by `bench/bench_forward_verify_replay.py` from its JSON (do not edit by hand). The "
             "default detector's verifications on each sequence, replayed with what each variant keeps of the "
             "past image (same candidates, same RANSAC, same seed), or with another search for the essential matrix (the "
             "stored descriptors; the `USAC` and `RANSAC` rows), or with the planar motion model (the `planar model` "
             "rows; every other row is the general five-point model); what is measured: the bench's docstring and "
             "[docs/forward.md](../forward.md), \"Time and memory per image\". The last four columns: the true loops' "
             "verified motion against the truth (office only), heading change error and bearing error (views 0.3 m or "
             "more apart), degrees, median / 90th percentile.",
             "",
             f"Machine and versions: {m.get('machine')}, cpu_count {m.get('cpu_count')}, python {m.get('python')}, "
             f"numpy {m.get('numpy')}, opencv {m.get('opencv')}. Command: `{res['command']}`.",
             "",
             "| sequence | variant | bytes saved per image | R@100%P | FP | loops | verify ms median | verify ms p99 "
             "| true loops | heading err deg | far loops | bearing err deg |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for sname, s in res["sequences"].items():
        for v, r in s["variants"].items():
            pose = (f"{r['pose_loops']} | {r['yaw_err_deg_median']:.2f} / {r['yaw_err_deg_p90']:.2f} | "
                    f"{r['bearing_loops']} | {r['bearing_err_deg_median']:.1f} / {r['bearing_err_deg_p90']:.1f}"
                    if "pose_loops" in r else "- | - | - | -")
            lines.append(f"| {sname} ({s['verifications']} verifications) | {v} | {r['bytes_saved_per_image']:.0f} | "
                         f"{r['recall_at_full_precision']:.3f} | {r['false_positives']} | {r['loops']} | "
                         f"{r['verify_ms_median']:.1f} | {r['verify_ms_p99']:.1f} | {pose} |")
    common = [(sname, v, c) for sname, s in res["sequences"].items() for v, c in s.get("common_loops", {}).items()]
    if common:
        lines += ["", "On the true loops both verified, each planar row against the general model (`stored descriptors`): "
                  "heading change error, and bearing error of the views 0.3 m or more apart, degrees, median / 90th "
                  "percentile.", "",
                  "| sequence | variant | loops | heading err, planar | heading err, general | far loops | "
                  "bearing err, planar | bearing err, general |",
                  "|---|---|---:|---:|---:|---:|---:|---:|"]
        for sname, v, c in common:
            a, b = c["model"], c["general"]
            lines.append(f"| {sname} | {v} | {c['loops']} | {a['yaw_err_deg_median']:.2f} / {a['yaw_err_deg_p90']:.2f} | "
                         f"{b['yaw_err_deg_median']:.2f} / {b['yaw_err_deg_p90']:.2f} | {a['bearing_loops']} | "
                         f"{a['bearing_err_deg_median']:.1f} / {a['bearing_err_deg_p90']:.1f} | "
                         f"{b['bearing_err_deg_median']:.1f} / {b['bearing_err_deg_p90']:.1f} |")
    return lines + [""]


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", type=Path, default=Path(tempfile.gettempdir()) / "robotd-office",
                    help="folder of the virtual office sequence (written when missing)")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--only", choices=("rtabmap_samples", "office"), default=None)
    ap.add_argument("--variants", default=";".join(VARIANTS),
                    help=f"semicolon-separated variants (default: all of {'; '.join(VARIANTS)})")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--page", type=Path, default=None, metavar="JSON",
                    help="only rewrite docs/benchmarks/forward_verify_replay.md from this result")
    args = ap.parse_args(argv)
    if args.page is not None:
        write_page(PAGE, page(json.loads(args.page.read_text(encoding="utf-8"))))
        print(f"wrote {PAGE}")
        return 0
    res: dict[str, Any] = {"benchmark": "forward_verify_replay", "machine": {**machine_info(), "opencv": cv2.__version__},
                           "command": " ".join(["bench/bench_forward_verify_replay.py",
                                                *(argv if argv is not None else sys.argv[1:])]),
                           "sequences": {}}
    variants = [v.strip() for v in args.variants.split(";") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variants {unknown}; choose from {list(VARIANTS)}")
    rt = args.data / "forward" / "rtabmap_samples"
    office = office_sequence(args.dir) if args.only != "rtabmap_samples" else args.dir
    seqs = {"rtabmap_samples": (rt, rt / "ground_truth.bmp"), "office": (office, office / "gt.npy")}
    for name, (folder, truth) in seqs.items():
        if args.only not in (None, name):
            continue
        rec = record(name, folder, truth)
        out: dict[str, Any] = {"verifications": len(rec["pairs"]), "variants": {}}
        print(f"\n{name}: {len(rec['pairs'])} verifications recorded", flush=True)
        for v in variants:
            r = replay(rec, v)
            out["variants"][v] = r
            print(f"  {v:32s} R@100%P {r['recall_at_full_precision']:.3f} FP {r['false_positives']} loops {r['loops']} "
                  f"saves {r['bytes_saved_per_image']:.0f} B/img  verify ms {r['verify_ms_median']:.1f} / p99 "
                  f"{r['verify_ms_p99']:.1f}", flush=True)
        common = common_loops(out["variants"])
        if common:
            out["common_loops"] = common
        res["sequences"][name] = out
        write_json(args.out, res)
    print(f"wrote {write_json(args.out, res)}")
    write_page(PAGE, page(res))
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
