"""Where the default forward detector's CPU time per image goes: each stage, and the
verification's parts, on the development sequences.

The detector's stage timer is the process's CPU clock (``ForwardDetector(timer=
time.process_time)``: a loaded machine stretches wall times far more than these), and the
verification's parts are timed around their functions (``match_features``, the level
motion's ``ransac_planar``, the five-point search near it with its refinement, the fallback
over all the matches or the band, the band's screen when on, the support check). Sequences: rtabmap_samples (no pose),
the virtual office route without a pose and with the daemon's fused pose
(``bench/bench_forward_ablation.py``'s ``odometry_fused.csv``, computed when missing);
variants by the names of ``bench/bench_forward_scale.py``'s ``VARIANTS``, each over the same
features. Printed per sequence and variant: recall at 100 % precision, false positives,
CPU per image features included (median, p99) beside OpenCV's ORB CPU of the same images,
and each part's median / p90 / p99 / mean over the slowest 1 % of images (ms; ``#``: calls
per image). Written: JSON (``--out``).

Run: ``PYTHONPATH=. .venv/bin/python bench/bench_forward_stages.py --dir /tmp/office``
(about 5 minutes per variant on the shared 2-core machine).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

try:
    from bench.bench_forward_ablation import office_fused_odometry, office_sequence
    from bench.bench_forward_scale import VARIANTS, opencv_orb_ms
    from bench.common import machine_info, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from bench_forward_ablation import office_fused_odometry, office_sequence  # type: ignore[no-redef]
    from bench_forward_scale import VARIANTS, opencv_orb_ms  # type: ignore[no-redef]
    from common import machine_info, write_json  # type: ignore[no-redef]

import robotd.forward.detector as detector_mod
import robotd.forward.verify as verify_mod
from robotd.forward import LOOP, FeatureExtractor, ForwardDetector, method_params
from robotd.forward.evaluation import score_decisions
from robotd.forward.verify import camera_matrix_guess
from robotd.io.sequence import list_images, load_ground_truth, read_image

REPO = Path(__file__).resolve().parent.parent
DATA = REPO.parent / "shared" / "data"
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "forward_stages.json"
CLOCK = time.process_time


class PartTimer:
    """CPU seconds and calls of the verification's parts in the current image."""

    def __init__(self) -> None:
        self.acc: dict[str, float] = {}

    def add(self, key: str, seconds: float) -> None:
        self.acc[key] = self.acc.get(key, 0.0) + seconds
        self.acc[key + "#"] = self.acc.get(key + "#", 0.0) + 1.0

    def wrap(self, module: Any, name: str, key: str | Callable[..., str]) -> None:
        inner = getattr(module, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = CLOCK()
            out = inner(*args, **kwargs)
            self.add(key(*args, **kwargs) if callable(key) else key, CLOCK() - t0)
            return out

        setattr(module, name, timed)


def _search_name(*args: Any, **kwargs: Any) -> str:
    """The part a ``_general_motion`` call is: near the level motion, in the band, or over
    all the matches."""
    near = args[5] if len(args) > 5 else kwargs.get("near")
    if near is None:
        return "fallback (all matches)"
    half = args[6] if len(args) > 6 else kwargs.get("half_inliers", True)
    return "search near the level motion" if half else "fallback (band)"


def run_sequence(name: str, folder: Path, truth_path: Path, variants: list[str], parts: PartTimer,
                 odometry: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, object]:
    files = list_images(folder, exclude=(truth_path,))
    truth = load_ground_truth(truth_path, len(files))
    images = [read_image(p) for p in files]
    h, w = images[0].shape[:2]
    k = camera_matrix_guess(w, h, 525.0 if name.startswith("office") else None)
    orb_cpu = opencv_orb_ms(images, CLOCK)
    base = method_params("default")
    ex = FeatureExtractor(base.features)
    feats = []
    for im in images:
        t0 = CLOCK()
        fe = ex(im)
        feats.append((fe, CLOCK() - t0))
    out: dict[str, object] = {"images": len(files), "pose": odometry is not None,
                              "opencv_orb_cpu_ms_median": float(np.median(orb_cpu)), "variants": {}}
    print(f"\n{name}: {len(files)} images ({w}x{h}); OpenCV ORB CPU median {np.median(orb_cpu):.2f} ms", flush=True)
    for variant in variants:
        voc_change, verify_change, det_change = VARIANTS[variant]
        params = replace(base, vocabulary=replace(base.vocabulary, **voc_change),
                         verify=replace(base.verify, **verify_change), **det_change)  # type: ignore[arg-type]
        det = ForwardDetector(params, camera_matrix=k, timer=CLOCK)
        n = len(files)
        cand, conf, decl = np.full(n, -1), np.zeros(n), np.zeros(n, bool)
        rows = []
        for t, (fe, fs) in enumerate(feats):
            parts.acc.clear()
            d = (det.process_features(fe, fs) if odometry is None
                 else det.process_features(fe, fs, odometry[0][t], odometry[1][t]))
            rows.append({**d.times_s, **parts.acc})
            if d.candidate_id is not None:
                cand[t], conf[t], decl[t] = d.candidate_id, d.candidate_probability, d.status == LOOP
        s = score_decisions(cand, conf, decl, truth, 10)
        keys = list(dict.fromkeys(k_ for r in rows for k_ in r))
        tab = {k_: np.array([r.get(k_, 0.0) for r in rows]) * (1.0 if k_.endswith("#") else 1e3) for k_ in keys}
        total = tab["total"]
        slow = total >= np.percentile(total, 99)
        stats = {k_: {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)),
                      "p99": float(np.percentile(v, 99)), "slowest_1pct_mean": float(v[slow].mean())}
                 for k_, v in tab.items()}
        out["variants"][variant] = {**s.as_dict(), "cpu_ms": stats["total"], "parts_ms": stats}  # type: ignore[index]
        print(f"  {variant}: R@100%P {s.recall_at_full_precision:.3f} FP {s.false_positives} loops {s.declared}; "
              f"CPU ms {stats['total']['median']:.1f} / p99 {stats['total']['p99']:.1f} "
              f"(x ORB CPU {stats['total']['median'] / np.median(orb_cpu):.1f})", flush=True)
        print(f"    {'part':<32}{'median':>8}{'p90':>8}{'p99':>8}{'slow 1%':>9}")
        for k_, st in stats.items():
            print(f"    {k_:<32}{st['median']:>8.2f}{st['p90']:>8.2f}{st['p99']:>8.2f}{st['slowest_1pct_mean']:>9.2f}")
    return out


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", type=Path, required=True, help="folder of the virtual office sequence")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--sequences", default="rtabmap_samples;office;office, fused pose",
                    help="semicolon-separated, of rtabmap_samples, office, 'office, fused pose'")
    ap.add_argument("--variants", default="tree;tree, previous planar verification",
                    help=f"semicolon-separated, of {', '.join(VARIANTS)}")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    variants = [v.strip() for v in args.variants.split(";") if v.strip()]
    seqs = [v.strip() for v in args.sequences.split(";") if v.strip()]
    bad = [v for v in variants if v not in VARIANTS] + [q for q in seqs if q not in
                                                          ("rtabmap_samples", "office", "office, fused pose")]
    if bad:
        ap.error(f"unknown variants or sequences: {bad}")
    parts = PartTimer()
    parts.wrap(verify_mod, "match_features", "matching")
    parts.wrap(verify_mod, "ransac_planar", "level motion (two-point)")
    parts.wrap(verify_mod, "_general_motion", _search_name)
    parts.wrap(verify_mod, "_checked", "support check")
    parts.wrap(verify_mod, "_screen_passes", "band screen")
    parts.wrap(detector_mod, "verify_pair", "verify_pair")
    res: dict[str, Any] = {"benchmark": "forward_stages", "machine": machine_info(),
                           "command": " ".join(["bench/bench_forward_stages.py", *(argv if argv is not None
                                                                                    else sys.argv[1:])]),
                           "sequences": {}}
    rt = args.data / "forward" / "rtabmap_samples"
    for q in seqs:
        if q == "rtabmap_samples":
            res["sequences"][q] = run_sequence(q, rt, rt / "ground_truth.bmp", variants, parts)
        else:
            office = office_sequence(args.dir)
            odo = office_fused_odometry(office) if q == "office, fused pose" else None
            res["sequences"][q] = run_sequence(q, office, office / "gt.npy", variants, parts, odo)
        write_json(args.out, res)
    print(f"wrote {write_json(args.out, res)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
