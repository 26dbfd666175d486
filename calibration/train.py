"""Training and validating the loop thresholds from a calibration recording (paper 003 Sec. IV-C).

The robot is driven once and recorded. Here the recording's wheel ticks and gyro go
through the same odometry filter as on the robot; floor frames become keyframes every
``spacing_m`` of travel; each keyframe is described in every mode; pairs of keyframes
are scored with the local score and labelled by the overlap J of their footprints at the
*odometry* poses (ground truth is never used for training). Only pairs whose footprints
could overlap are all scored; distant pairs (J = 0 whatever the odometry drift at that
range) are sampled and weighted by the inverse of the sampling rate. Validation scores
pairs of a second recording and labels them with its *ground-truth* poses.
"""

from __future__ import annotations

import logging
import multiprocessing
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from calibration.loop_curve import LoopCurve, PrecisionRecall, fit_loop_curve, pick_threshold
from robotd.errors import CalibrationError
from robotd.floorcam import FloorCameraModel, overlap_ratios
from robotd.geometry import between

log = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]
MODES = (1, 2, 3, 4, 5, 6)


@dataclass(frozen=True)
class TrainParams:
    """``spacing_m``: travel between keyframes; ``odometry``: 'fused' or 'wheel' poses label
    the pairs; ``far_pairs_per_keyframe``: distant pairs sampled per keyframe; ``r``: the
    overlap that makes a loop; ``confidence``: P(loop | score) the threshold must reach."""

    modes: tuple[int, ...] = MODES
    spacing_m: float = 0.03
    odometry: str = "fused"
    far_pairs_per_keyframe: float = 4.0
    r: float = 0.33
    confidence: float = 0.99
    workers: int = 2
    seed: int = 0


@dataclass(eq=False)
class CalibrationRun:
    """Keyframes of a recording: ``stamps_ns (N,)``, poses ``(N, 3)`` by fused and by
    wheel-only odometry and (virtual robot only) by ground truth, and descriptor bytes per mode."""

    stamps_ns: np.ndarray
    fused: np.ndarray
    wheel: np.ndarray
    truth: np.ndarray | None
    descriptors: dict[int, list[bytes]] = field(default_factory=dict)


# -- describing keyframes in worker processes -------------------------------------------

def _describe_all(image: np.ndarray, modes: tuple[int, ...]) -> list[bytes]:
    from robotd.floor.descriptor import extract

    return [extract(image, m) for m in modes]


def load_run(path: Path, cfg: Any, params: TrainParams, progress: Progress | None = None) -> CalibrationRun:
    """Read a recording, run the odometry, pick keyframes, and describe them in every mode."""
    from drivers.recording import RecordingReader
    from robotd.messages import Frame, PoseStamped, WheelTicks, YawRate
    from robotd.service import build_odometry

    reader = RecordingReader(path)
    span = reader.time_range_ns
    if span is None:
        raise CalibrationError(f"{path}: the recording holds no messages")
    odo = build_odometry(cfg)
    truth_t: list[int] = []
    truth_p: list[tuple[float, float, float]] = []
    stamps: list[int] = []
    fused: list[np.ndarray] = []
    wheel: list[np.ndarray] = []
    pending: list[Frame] = []
    last: np.ndarray | None = None
    ctx = multiprocessing.get_context("fork")
    pool = ctx.Pool(max(1, params.workers))
    jobs: list[Any] = []
    total = max(1, span[1] - span[0])

    def take(frame: Frame) -> None:
        nonlocal last
        p = odo.pose_at(frame.stamp_ns)
        if p is None:
            return
        xyyaw = np.array([p.x_m, p.y_m, p.yaw_rad])
        if last is not None and np.hypot(*between(last, xyyaw)[:2]) < params.spacing_m:
            return
        last = xyyaw
        w = odo.wheel_pose()  # wheel-only pose at the latest sample: within 20 ms of the frame
        stamps.append(frame.stamp_ns)
        fused.append(xyyaw)
        wheel.append(np.array([w.x_m, w.y_m, w.yaw_rad]))
        jobs.append(pool.apply_async(_describe_all, (frame.image, params.modes)))

    try:
        for n, (topic, msg) in enumerate(reader.messages()):
            if isinstance(msg, WheelTicks):
                odo.on_wheels(msg)
            elif isinstance(msg, YawRate):
                odo.on_yaw_rate(msg)
            elif isinstance(msg, Frame) and msg.camera == "floor":
                pending.append(msg)
            elif isinstance(msg, PoseStamped) and topic == "/ground_truth":
                truth_t.append(msg.stamp_ns)
                truth_p.append((msg.x_m, msg.y_m, msg.yaw_rad))
            settled = odo.settled_stamp_ns()
            while pending and settled is not None and settled >= pending[0].stamp_ns:
                take(pending.pop(0))
            if progress is not None and n % 500 == 0:
                progress("reading and describing", int(getattr(msg, "stamp_ns", span[0]) - span[0]), total)
        results = []
        for k, job in enumerate(jobs):
            results.append(job.get())
            if progress is not None and k % 50 == 0:
                progress("describing keyframes", k, len(jobs))
    finally:
        pool.close()
        pool.join()
    if len(stamps) < 10:
        raise CalibrationError(f"{path}: only {len(stamps)} keyframes with odometry; a calibration run "
                               "needs a drive with floor frames and wheel/gyro data")
    run = CalibrationRun(np.asarray(stamps, np.int64), np.asarray(fused), np.asarray(wheel), None,
                         {m: [r[i] for r in results] for i, m in enumerate(params.modes)})
    if truth_t:
        tt = np.asarray(truth_t)
        tp = np.asarray(truth_p)
        idx = np.clip(np.searchsorted(tt, run.stamps_ns), 0, len(tt) - 1)
        run.truth = tp[idx]
    return run


# -- pairs and scores ---------------------------------------------------------------------

def candidate_pairs(poses: np.ndarray, camera: FloorCameraModel, far_per_keyframe: float,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(i, j, weight)`` with i > j: every pair whose centres are close enough for the
    footprints to overlap (weight 1), and a uniform sample of the others, weighted by
    (all distant pairs) / (sampled distant pairs)."""
    fp = camera.footprint_robot(8)
    reach = 2.0 * float(np.max(np.hypot(fp[:, 0], fp[:, 1])))
    n = len(poses)
    near_i, near_j = [], []
    for i in range(1, n):
        d = np.hypot(poses[:i, 0] - poses[i, 0], poses[:i, 1] - poses[i, 1])
        j = np.flatnonzero(d < reach)
        near_i.append(np.full(len(j), i))
        near_j.append(j)
    ni = np.concatenate(near_i) if near_i else np.zeros(0, int)
    nj = np.concatenate(near_j) if near_j else np.zeros(0, int)
    total_far = n * (n - 1) // 2 - len(ni)
    want = int(min(total_far, far_per_keyframe * n))
    fi, fj = [], []
    taken = set(zip(ni.tolist(), nj.tolist()))  # near pairs, then each sampled one: no repeats
    while len(fi) < want:
        i = rng.integers(1, n, want)
        j = (rng.random(want) * i).astype(int)
        for a, b in zip(i.tolist(), j.tolist()):
            if (a, b) not in taken and len(fi) < want:
                taken.add((a, b))
                fi.append(a)
                fj.append(b)
    w_far = total_far / want if want else 0.0
    i = np.concatenate([ni, np.asarray(fi, int)])
    j = np.concatenate([nj, np.asarray(fj, int)])
    w = np.concatenate([np.ones(len(ni)), np.full(len(fi), w_far)])
    return i, j, w


_SHARED: list[Any] = []


def _score_chunk(pairs: np.ndarray) -> np.ndarray:
    from robotd.floor.match import local_score

    descs = _SHARED[0]
    return np.array([local_score(descs[a], descs[b]).score for a, b in pairs], dtype=float)


def score_pairs(descriptors: list[bytes], i: np.ndarray, j: np.ndarray, workers: int = 2,
                progress: Progress | None = None, label: str = "scoring") -> np.ndarray:
    """Local score of every pair (i[k], j[k]) of keyframes, on ``workers`` processes."""
    from robotd.floor.descriptor import decode

    _SHARED[:] = [[decode(d) for d in descriptors]]  # inherited by the forked workers
    pairs = np.column_stack([i, j])
    chunks = [pairs[k:k + 2000] for k in range(0, len(pairs), 2000)]
    out: list[np.ndarray] = []
    with multiprocessing.get_context("fork").Pool(max(1, workers)) as pool:
        for k, res in enumerate(pool.imap(_score_chunk, chunks)):
            out.append(res)
            if progress is not None:
                progress(label, k + 1, len(chunks))
    _SHARED.clear()
    return np.concatenate(out) if out else np.zeros(0)


@dataclass(frozen=True, eq=False)
class ModeResult:
    """One mode's trained curve and threshold, with the pairs behind it."""

    mode: int
    curve: LoopCurve
    threshold: float | None
    scores: np.ndarray
    overlap: np.ndarray
    weights: np.ndarray
    seconds: float


def train(run: CalibrationRun, camera: FloorCameraModel, params: TrainParams,
          progress: Progress | None = None) -> dict[int, ModeResult]:
    """Score and label the pairs of a loaded run, fit each mode's curve, pick thresholds."""
    if params.odometry not in ("fused", "wheel"):
        raise CalibrationError(f"odometry must be 'fused' or 'wheel', not {params.odometry!r}")
    poses = run.fused if params.odometry == "fused" else run.wheel
    rng = np.random.default_rng(params.seed)
    i, j, w = candidate_pairs(poses, camera, params.far_pairs_per_keyframe, rng)
    overlap = overlap_ratios(camera, poses[i], poses[j])
    results: dict[int, ModeResult] = {}
    for m in params.modes:
        t0 = time.monotonic()
        s = score_pairs(run.descriptors[m], i, j, params.workers, progress, f"scoring mode {m}")
        curve = fit_loop_curve(s, overlap >= params.r, weights=w)
        results[m] = ModeResult(m, curve, pick_threshold(curve, params.confidence), s, overlap, w,
                                time.monotonic() - t0)
    return results


def validate(run: CalibrationRun, camera: FloorCameraModel, thresholds: dict[int, float | None],
             params: TrainParams, progress: Progress | None = None) -> dict[int, PrecisionRecall | None]:
    """Precision and recall of the thresholds on a run labelled by its ground truth."""
    if run.truth is None:
        raise CalibrationError("validation needs a recording with /ground_truth (the virtual robot's)")
    rng = np.random.default_rng(params.seed + 1)
    i, j, w = candidate_pairs(run.truth, camera, params.far_pairs_per_keyframe, rng)
    loop = overlap_ratios(camera, run.truth[i], run.truth[j]) >= params.r
    out: dict[int, PrecisionRecall | None] = {}
    for m, t in thresholds.items():
        if t is None:
            out[m] = None
            continue
        s = score_pairs(run.descriptors[m], i, j, params.workers, progress, f"validating mode {m}")
        # Distant pairs stand for many: count a declared distant pair with its weight.
        declared = s >= t
        tp = int(np.sum(declared & loop))
        fp = float(np.sum(w[declared & ~loop]))
        fn = int(np.sum(~declared & loop))
        out[m] = PrecisionRecall(float(t), tp, int(round(fp)), fn)
    return out


# -- command line ---------------------------------------------------------------------------

def _progress_printer() -> Progress:
    from calibration.intrinsics import ProgressBar  # one progress bar for every calibration step

    bars: dict[str, Any] = {}

    def show(label: str, done: int, total: int) -> None:
        bars.setdefault(label, ProgressBar(label))(done, total)

    return show


def add_loop_curve_arguments(p: Any) -> None:
    p.add_argument("recording", type=Path, help="MCAP recording of a calibration drive")
    p.add_argument("--calibration", type=Path, required=True,
                   help="calibration file to write the thresholds into (created or updated)")
    p.add_argument("--config", type=Path, default=None, help="robotd config (robot geometry, camera)")
    p.add_argument("--modes", default="1,2,3,4,5,6", help="descriptor modes to train (default: all)")
    p.add_argument("--odometry", choices=("fused", "wheel"), default="fused",
                   help="which odometry labels the pairs (default: fused wheel+gyro, as in the paper)")
    p.add_argument("--spacing", type=float, default=0.03, metavar="M", help="keyframe spacing, metres")
    p.add_argument("--r", type=float, default=0.33, help="footprint overlap that makes a loop")
    p.add_argument("--confidence", type=float, default=0.99, help="P(loop | score) at the threshold")
    p.add_argument("--plot", type=Path, default=None, help="write the curves (paper Fig. 5) to this PNG")
    p.add_argument("--workers", type=int, default=2)


def _setup(args: Any) -> tuple[Any, FloorCameraModel, TrainParams]:
    from calibration.calibfile import camera_model, read_calibration
    from robotd.config import Config, load_config

    cfg = load_config(args.config) if args.config else Config()
    calib = read_calibration(args.calibration) if args.calibration.exists() else None
    try:
        modes = tuple(sorted({int(m) for m in args.modes.split(",")}))
    except ValueError:
        raise CalibrationError(f"--modes must be a comma-separated list of 1..6, got {args.modes!r}") from None
    if not modes or not set(modes) <= set(MODES):
        raise CalibrationError(f"--modes must be a comma-separated list of 1..6, got {args.modes!r}")
    params = TrainParams(modes=modes, spacing_m=args.spacing, odometry=getattr(args, "odometry", "fused"),
                         r=args.r, confidence=getattr(args, "confidence", 0.99), workers=args.workers)
    return cfg, camera_model(calib, cfg.floor_camera), params


def run_loop_curve(args: Any) -> int:
    import resource
    import sys

    from calibration.calibfile import CalibrationFile, LoopThresholds, update_calibration

    t0 = time.monotonic()
    cfg, camera, params = _setup(args)
    progress = _progress_printer()
    run = load_run(args.recording, cfg, params, progress)
    res = train(run, camera, params, progress)
    seconds = time.monotonic() - t0
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    thresholds = {m: r.threshold for m, r in res.items()}
    update_calibration(args.calibration, CalibrationFile(loop=LoopThresholds.from_mapping(
        thresholds, overlap_r=params.r, confidence=params.confidence)))
    n_pairs = len(next(iter(res.values())).scores)
    print(f"\n{len(run.stamps_ns)} keyframes every {params.spacing_m:.3f} m, {n_pairs} scored pairs per mode, "
          f"labels from {params.odometry} odometry (J >= {params.r})", file=sys.stdout)
    print("local score   " + "".join(f"  mode {m}" for m in res), file=sys.stdout)
    print("threshold     " + "".join(f"{_fmt(r.threshold):>8}" for r in res.values()), file=sys.stdout)
    print("loops >= thr  " + "".join(f"{int(np.sum((r.scores >= r.threshold) & (r.overlap >= params.r))) if r.threshold is not None else '-':>8}"
                                     for r in res.values()), file=sys.stdout)
    print(f"training time {seconds:.1f} s, peak memory {peak_mb:.0f} MB (this process; the two "
          f"workers are forks of it)", file=sys.stdout)
    print(f"thresholds written to {args.calibration}", file=sys.stdout)
    if args.plot is not None:
        from robotd.plots import plot_loop_curves

        plot_loop_curves(args.plot, {m: r.curve for m, r in res.items()}, thresholds, params.confidence,
                         title=f"P(J >= {params.r} | local score), labels from {params.odometry} odometry")
        print(f"curves: {args.plot}", file=sys.stdout)
    return 0


def _fmt(t: float | None) -> str:
    return "-" if t is None else f"{t:.1f}"


def add_validate_arguments(p: Any) -> None:
    p.add_argument("recording", type=Path, help="MCAP recording of another drive (with ground truth)")
    p.add_argument("--calibration", type=Path, required=True, help="calibration file with thresholds")
    p.add_argument("--config", type=Path, default=None)
    p.add_argument("--modes", default="1,2,3,4,5,6")
    p.add_argument("--spacing", type=float, default=0.03, metavar="M")
    p.add_argument("--r", type=float, default=0.33)
    p.add_argument("--workers", type=int, default=2)


def run_validate(args: Any) -> int:
    import sys

    from calibration.calibfile import read_calibration

    cfg, camera, params = _setup(args)
    calib = read_calibration(args.calibration)
    if calib.loop is None:
        raise CalibrationError(f"{args.calibration}: no loop thresholds (run `robotd calibrate loop-curve`)")
    progress = _progress_printer()
    run = load_run(args.recording, cfg, params, progress)
    res = validate(run, camera, {m: calib.loop.for_mode(m) for m in params.modes}, params, progress)
    print(f"\n{len(run.stamps_ns)} keyframes; loops by ground-truth overlap J >= {params.r}", file=sys.stdout)
    print(f"{'mode':>4} {'threshold':>9} {'declared':>8} {'true':>6} {'false':>6} {'missed':>6} "
          f"{'precision':>9} {'recall':>7}", file=sys.stdout)
    for m, pr in res.items():
        if pr is None:
            print(f"{m:>4} {'-':>9}  (no threshold trained)", file=sys.stdout)
            continue
        print(f"{m:>4} {pr.threshold:>9.1f} {pr.true_positives + pr.false_positives:>8} {pr.true_positives:>6} "
              f"{pr.false_positives:>6} {pr.false_negatives:>6} {pr.precision:>9.4f} {pr.recall:>7.3f}",
              file=sys.stdout)
    return 0
