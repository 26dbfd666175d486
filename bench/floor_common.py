"""What the floor-descriptor benchmarks share: the floors, the SIFT baseline, ROC AUC, plots.

The three floor benchmarks (``bench_floor_descriptor.py``, ``bench_floor_quality.py``,
``bench_floor_map.py``) measure our compact descriptor (paper 003) against OpenCV SIFT on
the same frames in the same run. This module holds the parts they have in common:

* :func:`bench_floors`: the five visibly different floors (three scikit-image photographs,
  each a single-texture floor; the herringbone brick photo from ``../shared/data/floor``;
  the default mixed floor) plus any floor image file named on the command line;
* :class:`SiftBaseline`: ``cv2.SIFT_create()`` / ``detectAndCompute``, a brute-force 2-NN
  match with Lowe's ratio test (0.8) and ``cv2.estimateAffinePartial2D`` RANSAC; SIFT's
  score of a pair is its number of RANSAC inliers;
* :func:`roc_auc` (the Mann-Whitney rank statistic, ties counted half), timing summaries,
  the JSON header (machine, versions, commit) and the matplotlib set-up.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

try:
    from bench.common import REPO_ROOT, machine_info
except ImportError:  # run as a script: bench/ is on sys.path
    from common import REPO_ROOT, machine_info

#: The herringbone brick photograph (``../shared/data``, never copied into the repo).
HERRINGBONE = REPO_ROOT.parent / "shared" / "data" / "floor" / "brick_floor_herringbone_1k.png"
#: The graffiti viewpoint pair and its ground-truth homography.
FEATURES_DIR = REPO_ROOT.parent / "shared" / "data" / "features"
#: Where results go unless ``--out`` says otherwise.
RESULTS_DIR = Path(__file__).resolve().parent / "results"
#: Footprint overlap at or above which two frames show the same place (paper 003, eq. 4).
LOOP_OVERLAP = 0.33
MODES = (1, 2, 3, 4, 5, 6)


def log(msg: str) -> None:
    """Progress line on stderr (the tables go to stdout)."""
    print(msg, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- floors


@dataclass(frozen=True)
class BenchFloor:
    """A named floor for the virtual camera and where its texture comes from."""

    name: str
    floor: Any  # sim.world.floor.Floor
    source: str


def bench_floors(extra_files: Sequence[str | Path] = (), seed: int = 0) -> list[BenchFloor]:
    """The benchmark floors: gravel, grass, brick (scikit-image photos, one texture each),
    the herringbone brick photo (skipped with a message when ``../shared`` is absent), the
    default mixed floor (brick, grass and gravel regions), then one floor per extra file."""
    import skimage.data

    from sim.world.floor import Floor

    out = [
        BenchFloor("gravel", Floor.from_photos([skimage.data.gravel()], seed=seed), "skimage.data.gravel"),
        BenchFloor("grass", Floor.from_photos([skimage.data.grass()], seed=seed), "skimage.data.grass"),
        BenchFloor("brick", Floor.from_photos([skimage.data.brick()], seed=seed), "skimage.data.brick"),
    ]
    if HERRINGBONE.is_file():
        out.append(BenchFloor("herringbone", Floor.from_photos([HERRINGBONE], seed=seed), str(HERRINGBONE)))
    else:
        log(f"skipping the herringbone floor: {HERRINGBONE} is absent (../shared/data not available)")
    out.append(BenchFloor("mixed", Floor.default(seed=seed), "Floor.default (brick, grass, gravel regions)"))
    for f in extra_files:
        path = Path(f)
        out.append(BenchFloor(path.stem, Floor.from_photos([path], seed=seed), str(path)))
    return out


def printed_floor(seed: int = 0) -> BenchFloor:
    """The paper's worst case, printed planks whose few prints repeat (``sim.world.pattern``,
    gravel photo printed on 0.45 x 0.12 m planks, 4 prints): not one of the five floors,
    offered for the map benchmark."""
    import skimage.data

    from sim.world.pattern import PatternFloor, PatternParams

    return BenchFloor("printed", PatternFloor(skimage.data.gravel(), PatternParams(kind="planks"), seed=seed),
                      "PatternFloor planks of skimage.data.gravel, 4 prints")


def add_common_args(ap: argparse.ArgumentParser, default_out: Path = RESULTS_DIR) -> None:
    """``--out DIR``, ``--floor FILE`` (repeatable), ``--seed``."""
    ap.add_argument("--out", type=Path, default=default_out,
                    help=f"directory for the JSON and PNG results (default {default_out})")
    ap.add_argument("--floor", action="append", default=[], metavar="FILE",
                    help="an extra floor photograph (repeatable); each becomes a single-texture floor")
    ap.add_argument("--seed", type=int, default=0, help="seed of the floors, frames and pair choices")


# --------------------------------------------------------------------------- SIFT


@dataclass(frozen=True, eq=False)
class SiftFeatures:
    """SIFT keypoints ``xy (N, 2) float32`` pixels and descriptors ``(N, 128) float32``."""

    xy: np.ndarray
    desc: np.ndarray

    def __len__(self) -> int:
        return len(self.xy)


@dataclass(frozen=True, eq=False)
class SiftMatch:
    """Result of matching two SIFT feature sets: the ratio-test survivors and the RANSAC
    inliers among them (``xy_a``, ``xy_b``: ``(K, 2)`` pixels); ``score`` = inliers."""

    n_matches: int
    n_inliers: int
    xy_a: np.ndarray
    xy_b: np.ndarray

    @property
    def score(self) -> int:
        return self.n_inliers


class SiftBaseline:
    """OpenCV SIFT as the paper's baseline: default ``cv2.SIFT_create()``, brute-force L2
    2-NN with ratio 0.8, then a 4-DoF similarity (``estimateAffinePartial2D``) by RANSAC
    with a 3 px reprojection threshold."""

    ratio = 0.8
    ransac_px = 3.0

    def __init__(self, seed: int = 0) -> None:
        self._sift = cv2.SIFT_create()
        self._matcher = cv2.BFMatcher(cv2.NORM_L2)
        self._seed = seed

    def extract(self, image: np.ndarray) -> SiftFeatures:
        kps, desc = self._sift.detectAndCompute(image, None)
        xy = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        if desc is None:
            desc = np.zeros((0, 128), np.float32)
        return SiftFeatures(xy, desc)

    def ratio_matches(self, a: SiftFeatures, b: SiftFeatures) -> tuple[np.ndarray, np.ndarray]:
        """Index arrays ``(ia, ib)`` of the 2-NN matches a -> b that pass the ratio test."""
        if len(a) == 0 or len(b) < 2:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        knn = self._matcher.knnMatch(a.desc, b.desc, k=2)
        ia = [m[0].queryIdx for m in knn if len(m) == 2 and m[0].distance < self.ratio * m[1].distance]
        ib = [m[0].trainIdx for m in knn if len(m) == 2 and m[0].distance < self.ratio * m[1].distance]
        return np.asarray(ia, np.int64), np.asarray(ib, np.int64)

    def match(self, a: SiftFeatures, b: SiftFeatures) -> SiftMatch:
        ia, ib = self.ratio_matches(a, b)
        empty = np.zeros((0, 2), np.float32)
        if len(ia) < 3:  # a similarity fits any 2 points: not evidence
            return SiftMatch(len(ia), 0, empty, empty)
        cv2.setRNGSeed(self._seed)
        src, dst = a.xy[ia], b.xy[ib]
        _, mask = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC,
                                              ransacReprojThreshold=self.ransac_px)
        if mask is None:
            return SiftMatch(len(ia), 0, empty, empty)
        keep = mask.ravel().astype(bool)
        return SiftMatch(len(ia), int(keep.sum()), src[keep], dst[keep])


# --------------------------------------------------------------------------- statistics


def roc_auc(scores: np.ndarray, positive: np.ndarray) -> float:
    """Area under the ROC curve of ``scores`` for labels ``positive`` (bool), by the rank
    statistic: P(score of a random positive > score of a random negative), ties count
    half. NaN when either class is empty."""
    s = np.asarray(scores, dtype=np.float64)
    y = np.asarray(positive, dtype=bool)
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    order = np.argsort(s, kind="mergesort")
    sorted_s = s[order]
    ranks = np.empty(len(s), np.float64)
    # Midranks: every run of equal scores gets the mean of its 1-based ranks.
    starts = np.flatnonzero(np.r_[True, sorted_s[1:] != sorted_s[:-1]])
    ends = np.r_[starts[1:], len(s)]
    mid = 0.5 * (starts + 1 + ends)
    ranks[order] = np.repeat(mid, ends - starts)
    u = ranks[y].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))


def spread(values_s: Sequence[float]) -> dict[str, float]:
    """Median and interquartile range of times given in seconds, as milliseconds."""
    ms = [1e3 * v for v in values_s]
    if len(ms) >= 2:
        q1, med, q3 = statistics.quantiles(ms, n=4, method="inclusive")
    else:
        q1 = med = q3 = ms[0]
    return {"median_ms": med, "iqr_ms": q3 - q1, "n": len(ms)}


def time_each(fn: Callable[[Any], object], items: Sequence[Any], repeats: int = 3,
              warmup: int = 2) -> dict[str, float]:
    """Time ``fn(item)`` for every item: ``warmup`` untimed calls on the first items, then
    ``repeats`` timed calls per item; the per-item medians summarised by :func:`spread`.

    The time is the calling thread's CPU time (``time.thread_time``): everything here runs
    on that one thread (:func:`one_thread`), and on a machine shared with other jobs the
    wall time also counts the time the thread waited for a core."""
    for k in range(warmup):
        fn(items[k % len(items)])
    per_item = []
    for item in items:
        runs = []
        for _ in range(repeats):
            t0 = time.thread_time()
            fn(item)
            runs.append(time.thread_time() - t0)
        per_item.append(statistics.median(runs))
    return spread(per_item)


def one_thread() -> list[dict[str, Any]]:
    """Run OpenCV and numpy's BLAS on one thread, the condition of the issue's targets.

    ``cv2.setNumThreads(1)`` alone is not enough: ``local_score``'s descriptor-distance
    product goes through numpy's BLAS (OpenBLAS here), which by default uses every core.
    On a 2-core machine whose other core is busy, each product of a 170 x 48 matrix or
    larger then waits for a descheduled BLAS thread: 16 ms instead of 0.4 ms (measured).
    Returns threadpoolctl's description of the BLAS pools after the limit (for the JSON).
    """
    from threadpoolctl import threadpool_info, threadpool_limits

    cv2.setNumThreads(1)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"  # for BLAS libraries loaded later (scipy's, through scikit-image)
    threadpool_limits(limits=1)  # process-wide until exit (no context manager: a benchmark is the process)
    return [{"library": i.get("internal_api"), "version": i.get("version"), "num_threads": i.get("num_threads")}
            for i in threadpool_info()]


def versions() -> dict[str, str]:
    """Versions of the libraries whose speed or results the floor benchmarks depend on."""
    import matplotlib
    import shapely
    import skimage

    return {"opencv": cv2.__version__, "numpy": np.__version__, "scikit-image": skimage.__version__,
            "matplotlib": matplotlib.__version__, "shapely": shapely.__version__}


def load_average() -> list[float] | None:
    """``os.getloadavg()`` (1, 5, 15 min), or None where unavailable: the machine's
    contention during the run (timings are ratios within the run for that reason)."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def header(name: str, settings: dict[str, Any], load_start: list[float] | None = None) -> dict[str, Any]:
    """The common head of a benchmark's JSON: name, machine (with commit, and the load
    average ``load_start`` measured when the run began and the one now), versions, BLAS
    thread pools, settings."""
    from threadpoolctl import threadpool_info

    machine = {**machine_info(), "load_average_start": load_start, "load_average_end": load_average()}
    blas = [{"library": i.get("internal_api"), "num_threads": i.get("num_threads")} for i in threadpool_info()]
    return {"benchmark": name, "machine": machine, "versions": versions(), "blas_threads": blas,
            "settings": settings}


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def r(x: float, nd: int = 2) -> float:
    """Round for a table cell (NaN stays NaN)."""
    return round(float(x), nd)
