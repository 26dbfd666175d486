"""Training and validating the loop thresholds from a calibration recording (paper 003 Sec. IV-C).

The robot is driven once and recorded. Here the recording's wheel ticks and gyro go
through the same odometry filter as on the robot; floor frames become keyframes by the
daemon's own rule (``spacing_m`` of travel or ``rotation_deg`` of turn, by default the
config's ``[keyframes]`` values), so the pairs are those the daemon will compare. Each
keyframe is described in every mode; pairs of keyframes are scored with the local score
and labelled by the overlap J of their footprints at the *odometry* poses (ground truth
is never used for training). Every pair whose footprints could overlap is scored;
distant pairs (J = 0 whatever the odometry drift at that range) are sampled and weighted
by the inverse of the sampling rate. Pairs far apart in travel whose label the drift of
the odometry could change (most revisits on a long run) are left out rather than
mislabelled (:func:`trusted_pairs`). Validation scores pairs of a second recording and
labels them with its *ground-truth* poses.

Worker processes come from a fork server, not from a fork of the caller: a fork of a
process whose OpenCV or OpenBLAS thread pool is already running (any caller that rendered
or matched before, e.g. a test that recorded the virtual robot) can inherit a held lock
and hang. The fork server is a fresh process that has imported the descriptor code once,
so workers still start in milliseconds. Workers run numpy and OpenCV single-threaded: the
matrices of one match are small, and BLAS threads on top of two busy worker processes only
fight over the cores (measured: a mode-4 match took 6x longer with OpenBLAS's default
threads on the 2-core machine).
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from calibration.loop_curve import LoopCurve, PrecisionRecall, fit_loop_curve, pick_threshold, precision_recall
from robotd.base.errors import CalibrationError, RobotdError
from robotd.base.camera import FloorCameraModel, overlap_ratios
from robotd.base.geometry import interpolate_poses

log = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]
MODES = (1, 2, 3, 4, 5, 6)


@dataclass(frozen=True)
class TrainParams:
    """``spacing_m``, ``rotation_deg``: travel or turn that makes the next keyframe (the
    daemon's ``[keyframes]`` defaults); ``odometry``: 'fused' or 'wheel' poses label the
    pairs; ``far_pairs_per_keyframe``: distant pairs sampled per keyframe; ``r``: the
    overlap that makes a loop; ``confidence``: P(loop | score) the threshold must reach;
    ``workers``: processes that describe and score; ``seed``: of the pair sampling;
    ``drift``: a bound on the odometry's position error per metre of travel between two
    keyframes; ``label_tolerance``: the largest such error, as a fraction of the footprint's
    shorter side, at which an overlap from odometry still labels a pair (see
    :func:`trusted_pairs`)."""

    modes: tuple[int, ...] = MODES
    spacing_m: float = 0.05
    rotation_deg: float = 10.0
    odometry: str = "fused"
    far_pairs_per_keyframe: float = 4.0
    r: float = 0.33
    confidence: float = 0.99
    workers: int = 2
    seed: int = 0
    drift: float = 0.02
    label_tolerance: float = 0.1


@dataclass(eq=False)
class CalibrationRun:
    """Keyframes of a recording: ``stamps_ns (N,)``, poses ``(N, 3)`` by fused and by
    wheel-only odometry and (virtual robot only) by ground truth, and descriptor bytes per mode."""

    stamps_ns: np.ndarray
    fused: np.ndarray
    wheel: np.ndarray
    truth: np.ndarray | None
    descriptors: dict[int, list[bytes]] = field(default_factory=dict)
    worker_peak_rss_mb: float = 0.0  # largest peak resident memory of a describing worker


# -- worker processes ------------------------------------------------------------------------

_WORKER: dict[str, Any] = {}  # per worker process: set by the pool initialiser, never in the parent


def _init_worker(descriptors: list[bytes] | None = None) -> None:
    """Pool initialiser: one thread per worker for BLAS and OpenCV; the descriptors to
    score, decoded once per worker."""
    import cv2
    from threadpoolctl import threadpool_limits

    from robotd.floor.descriptor import decode

    cv2.setNumThreads(1)
    _WORKER["limits"] = threadpool_limits(limits=1)
    _WORKER["descriptors"] = None if descriptors is None else [decode(d) for d in descriptors]


def _pool(workers: int, descriptors: list[bytes] | None = None) -> Any:
    """A pool of ``workers`` processes from the fork server (see the module notes). As with
    any non-fork start method, a script that calls in here needs the
    ``if __name__ == "__main__":`` guard (the ``robotd`` command has it)."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["cv2", "robotd.floor.descriptor", "robotd.floor.match", "calibration.train"])
    return ctx.Pool(max(1, workers), initializer=_init_worker, initargs=(descriptors,))


def _peak_rss_mb() -> float:
    """This process's peak resident memory, MB (Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _describe_all(image: np.ndarray, modes: tuple[int, ...]) -> tuple[list[bytes], float]:
    from robotd.floor.descriptor import extract

    return [extract(image, m) for m in modes], _peak_rss_mb()


def recording_config(path: Path) -> Any:
    """The robotd config a recording was made with (its ``robotd`` metadata), or None."""
    import tomllib

    from drivers.recording.reader import RecordingReader
    from robotd.base.config import config_from_dict

    with RecordingReader(path) as reader:
        text = reader.metadata.get("robotd", {}).get("config_toml", "")
    if not text:
        return None
    try:
        return config_from_dict(tomllib.loads(text))
    except (tomllib.TOMLDecodeError, RobotdError) as exc:
        log.warning("%s: cannot use the config the recording was made with (%s); using the "
                    "defaults (pass --config to choose)", path, exc)
        return None


def load_run(path: Path, cfg: Any, params: TrainParams, progress: Progress | None = None) -> CalibrationRun:
    """Read a recording, run the odometry, pick keyframes, and describe them in every mode.

    Keyframes are chosen by the daemon's :class:`~robotd.app.daemon.KeyframeSelector` on the
    fused pose at each floor frame (``spacing_m`` of travel or ``rotation_deg`` of turn
    since the last keyframe). Each keyframe's fused pose is the filter's pose at the frame's
    stamp; its wheel-only and ground-truth poses are those tracks interpolated at that stamp.
    """
    from drivers.recording.reader import RecordingReader
    from robotd.app.daemon import KeyframeSelector
    from robotd.base.messages import Frame, PoseStamped, WheelTicks, YawRate
    from robotd.app.service import build_odometry

    reader = RecordingReader(path)
    span = reader.time_range_ns
    if span is None:
        raise CalibrationError(f"{path}: the recording holds no messages")
    odo = build_odometry(cfg)
    truth_t: list[int] = []
    truth_p: list[tuple[float, float, float]] = []
    wheel_t: list[int] = []
    wheel_p: list[tuple[float, float, float]] = []
    stamps: list[int] = []
    fused: list[np.ndarray] = []
    pending: list[Frame] = []
    selector = KeyframeSelector(params.spacing_m, math.radians(params.rotation_deg))
    jobs: list[Any] = []
    results: list[list[bytes]] = []
    worker_mb = 0.0
    total = max(1, span[1] - span[0])
    pool = _pool(params.workers)

    def collect(upto: int, show: bool = False) -> None:
        """Wait for the descriptions of keyframes before ``upto``."""
        nonlocal worker_mb
        while len(results) < upto:
            described, mb = jobs[len(results)].get()
            results.append(described)
            worker_mb = max(worker_mb, mb)
            if show and progress is not None and (len(results) % 50 == 0 or len(results) == len(jobs)):
                progress("describing the last keyframes", len(results), len(jobs))

    def take(frame: Frame) -> None:
        p = odo.pose_at(frame.stamp_ns)
        if p is None:
            return
        xyyaw = np.array([p.x_m, p.y_m, p.yaw_rad])
        if not selector.offer(xyyaw):
            return
        stamps.append(frame.stamp_ns)
        fused.append(xyyaw)
        # A few images queued per worker, not the whole recording: reading outruns describing.
        collect(len(jobs) - 4 * params.workers)
        jobs.append(pool.apply_async(_describe_all, (frame.image, params.modes)))

    try:
        for n, (topic, msg) in enumerate(reader.messages()):
            if isinstance(msg, WheelTicks):
                if odo.on_wheels(msg):
                    w = odo.wheel_pose()
                    wheel_t.append(w.stamp_ns)
                    wheel_p.append((w.x_m, w.y_m, w.yaw_rad))
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
                progress("reading the recording (s)", int(getattr(msg, "stamp_ns", span[0]) - span[0]) // 10**9,
                         total // 10**9)
        if progress is not None:
            progress("reading the recording (s)", total // 10**9, total // 10**9)
        collect(len(jobs), show=True)
    finally:
        pool.close()
        pool.join()
        reader.close()
    if len(stamps) < 10 or len(wheel_t) < 2:
        raise CalibrationError(f"{path}: only {len(stamps)} keyframes with odometry; a calibration run "
                               "needs a drive with floor frames and wheel/gyro data")
    st = np.asarray(stamps, np.int64)
    run = CalibrationRun(st, np.asarray(fused), interpolate_poses(np.asarray(wheel_t), np.asarray(wheel_p), st),
                         None, {m: [r[i] for r in results] for i, m in enumerate(params.modes)}, worker_mb)
    if len(truth_t) >= 2:
        run.truth = interpolate_poses(np.asarray(truth_t), np.asarray(truth_p), st)
    return run


# -- pairs and scores ---------------------------------------------------------------------

def candidate_pairs(poses: np.ndarray, camera: FloorCameraModel, far_per_keyframe: float,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(i, j, weight)`` with i > j: every pair whose centres are close enough for the
    footprints to overlap (weight 1), and a uniform sample of the others, weighted by
    (all distant pairs) / (sampled distant pairs)."""
    reach = camera.footprint_reach_m()
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


def _travel_m(poses: np.ndarray) -> np.ndarray:
    """``(N,)`` distance travelled along the keyframe poses ``(N, 3)`` up to each one, metres."""
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])


def trusted_pairs(poses: np.ndarray, camera: FloorCameraModel, i: np.ndarray, j: np.ndarray,
                  drift: float, tolerance: float) -> np.ndarray:
    """Which pairs (i[k], j[k]) odometry can label: ``(P,)`` bool.

    Odometry drifts: the relative pose of two keyframes is off by up to ``drift`` times the
    travel between them (the fused odometry of the virtual robot stays within 1.5 %), so a
    revisit after a long drive can look like no overlap, or a neighbour's footprint like a
    loop. A pair is labelled only where that bound cannot change the answer much: the bound
    is at most ``tolerance`` times the footprint's shorter side, or the footprints are
    further apart than their reach plus the bound (disjoint whatever the drift). The other
    pairs stay out of training: on a long run they are most revisits, which costs evidence
    but not correctness.
    """
    travel = _travel_m(poses)
    bound = drift * np.abs(travel[i] - travel[j])
    fp = camera.footprint_robot(8)
    side = float(np.min(fp.max(axis=0) - fp.min(axis=0)))
    reach = camera.footprint_reach_m()
    apart = np.hypot(poses[i, 0] - poses[j, 0], poses[i, 1] - poses[j, 1])
    return (bound <= tolerance * side) | (apart > reach + bound)


def _score_chunk(pairs: np.ndarray) -> tuple[np.ndarray, float]:
    from robotd.floor.match import local_score

    descs = _WORKER["descriptors"]
    return np.array([local_score(descs[a], descs[b]).score for a, b in pairs], dtype=float), _peak_rss_mb()


def score_pairs(descriptors: list[bytes], i: np.ndarray, j: np.ndarray, workers: int = 2,
                progress: Progress | None = None, label: str = "scoring") -> tuple[np.ndarray, float]:
    """Local score ``(P,)`` of every pair (i[k], j[k]) of keyframes, on ``workers``
    processes, and the largest peak resident memory of a worker, MB."""
    pairs = np.column_stack([i, j])
    chunks = [pairs[k:k + 1000] for k in range(0, len(pairs), 1000)]
    out: list[np.ndarray] = []
    worker_mb = 0.0
    with _pool(workers, list(descriptors)) as pool:
        for k, (res, mb) in enumerate(pool.imap(_score_chunk, chunks)):
            out.append(res)
            worker_mb = max(worker_mb, mb)
            if progress is not None:
                progress(label, k + 1, len(chunks))
    return (np.concatenate(out) if out else np.zeros(0)), worker_mb


@dataclass(frozen=True, eq=False)
class ModeResult:
    """One mode's trained curve and threshold, with the pairs behind it: ``scores``,
    ``overlap`` (J at the training poses) and ``weights``, all ``(P,)``."""

    mode: int
    curve: LoopCurve
    threshold: float | None
    scores: np.ndarray
    overlap: np.ndarray
    weights: np.ndarray
    seconds: float
    worker_peak_rss_mb: float = 0.0
    untrusted: int = 0  # candidate pairs left unlabelled: odometry drift could change their label
    mislabelled: int | None = None  # labels that ground truth (virtual robot only) contradicts


def train(run: CalibrationRun, camera: FloorCameraModel, params: TrainParams,
          progress: Progress | None = None) -> dict[int, ModeResult]:
    """Score and label the pairs of a loaded run, fit each mode's curve, pick thresholds."""
    if params.odometry not in ("fused", "wheel"):
        raise CalibrationError(f"odometry must be 'fused' or 'wheel', not {params.odometry!r}")
    poses = run.fused if params.odometry == "fused" else run.wheel
    rng = np.random.default_rng(params.seed)
    i, j, w = candidate_pairs(poses, camera, params.far_pairs_per_keyframe, rng)
    keep = trusted_pairs(poses, camera, i, j, params.drift, params.label_tolerance)
    i, j, w = i[keep], j[keep], w[keep]
    overlap = overlap_ratios(camera, poses[i], poses[j])
    mislabelled = None
    if run.truth is not None:  # a virtual-robot recording: how often the odometry's label is wrong
        truth = overlap_ratios(camera, run.truth[i], run.truth[j])
        mislabelled = int(np.sum((truth >= params.r) != (overlap >= params.r)))
    results: dict[int, ModeResult] = {}
    for m in params.modes:
        t0 = time.monotonic()
        s, worker_mb = score_pairs(run.descriptors[m], i, j, params.workers, progress, f"scoring mode {m}")
        curve = fit_loop_curve(s, overlap >= params.r, weights=w)
        results[m] = ModeResult(m, curve, pick_threshold(curve, params.confidence), s, overlap, w,
                                time.monotonic() - t0, worker_mb, int(np.sum(~keep)), mislabelled)
    return results


@dataclass(frozen=True)
class ModeValidation:
    """One mode's thresholds applied to a validation run: over all scored pairs, and over
    *revisits* only (pairs more than ``revisit_m`` of travel apart: the loops a loop
    detector exists for, not the neighbours along the path)."""

    mode: int
    all_pairs: PrecisionRecall
    revisits: PrecisionRecall


def validate(run: CalibrationRun, camera: FloorCameraModel, thresholds: dict[int, float | None],
             params: TrainParams, revisit_m: float = 2.0,
             progress: Progress | None = None) -> dict[int, ModeValidation]:
    """Precision and recall of the thresholds on a run labelled by its ground truth.

    The pairs are chosen as in training (every pair whose true footprints could overlap,
    plus weighted distant pairs), from the ground-truth poses; a pair is a loop when its
    true overlap is at least ``params.r``. A mode without a threshold declares no loop
    (the daemon's behaviour): threshold +inf, recall 0, precision undefined (NaN).
    """
    if run.truth is None:
        raise CalibrationError("validation needs a recording with /ground_truth (the virtual robot's)")
    rng = np.random.default_rng(params.seed + 1)
    i, j, w = candidate_pairs(run.truth, camera, params.far_pairs_per_keyframe, rng)
    loop = overlap_ratios(camera, run.truth[i], run.truth[j]) >= params.r
    travel = _travel_m(run.truth)
    revisit = travel[i] - travel[j] > revisit_m
    out: dict[int, ModeValidation] = {}
    for m, t in thresholds.items():
        if t is None:
            none = np.zeros(len(i))  # nothing scored: with an infinite threshold no pair is declared
            out[m] = ModeValidation(m, precision_recall(none, loop, math.inf, w),
                                    precision_recall(none[revisit], loop[revisit], math.inf, w[revisit]))
            continue
        s, _ = score_pairs(run.descriptors[m], i, j, params.workers, progress, f"validating mode {m}")
        out[m] = ModeValidation(m, precision_recall(s, loop, t, w),
                                precision_recall(s[revisit], loop[revisit], t, w[revisit]))
    return out


# -- command line ---------------------------------------------------------------------------

def _progress_printer() -> Progress:
    from calibration.intrinsics import ProgressBar  # one progress bar for every calibration step

    bars: dict[str, Any] = {}

    def show(label: str, done: int, total: int) -> None:
        bars.setdefault(label, ProgressBar(label))(done, total)

    return show


def _common_arguments(p: Any) -> None:
    p.add_argument("--config", type=Path, default=None,
                   help="robotd config (odometry, floor camera); default: the one the recording "
                        "was made with, else the defaults")
    p.add_argument("--modes", default="1,2,3,4,5,6", help="descriptor modes (default: all)")
    p.add_argument("--spacing", type=float, default=None, metavar="M",
                   help="keyframe spacing, metres (default: the config's [keyframes] distance_m)")
    p.add_argument("--rotation", type=float, default=None, metavar="DEG",
                   help="keyframe rotation, degrees (default: the config's [keyframes] rotation_deg)")
    p.add_argument("--r", type=float, default=TrainParams.r,
                   help=f"footprint overlap J that makes a loop (default {TrainParams.r})")
    p.add_argument("--far-pairs", type=float, default=TrainParams.far_pairs_per_keyframe, metavar="K",
                   help="distant pairs sampled per keyframe (default "
                        f"{TrainParams.far_pairs_per_keyframe:g})")
    p.add_argument("--workers", type=int, default=TrainParams.workers, help="worker processes")
    p.add_argument("--json", type=Path, default=None, metavar="FILE", help="also write the results as JSON")


def add_loop_curve_arguments(p: Any) -> None:
    p.add_argument("recording", type=Path, help="MCAP recording of a calibration drive")
    p.add_argument("--calibration", type=Path, required=True,
                   help="calibration file to write the thresholds into (created or updated)")
    p.add_argument("--odometry", choices=("fused", "wheel"), default="fused",
                   help="which odometry labels the pairs (default: fused wheel+gyro, as in the paper)")
    p.add_argument("--confidence", type=float, default=TrainParams.confidence,
                   help=f"P(loop | score) at the threshold (default {TrainParams.confidence})")
    p.add_argument("--drift", type=float, default=TrainParams.drift, metavar="F",
                   help="bound on the odometry's position error per metre of travel (default "
                        f"{TrainParams.drift:g}); pairs whose label that error could change are not used")
    p.add_argument("--label-tolerance", type=float, default=TrainParams.label_tolerance, metavar="F",
                   help="largest such error that still labels a pair, as a fraction of the footprint's "
                        f"shorter side (default {TrainParams.label_tolerance:g})")
    p.add_argument("--plot", type=Path, default=None, help="write the curves (paper Fig. 5) to this PNG")
    _common_arguments(p)


def _setup(args: Any) -> tuple[Any, FloorCameraModel, TrainParams]:
    from robotd.io.calibfile import camera_model, read_calibration
    from robotd.base.config import Config, load_config

    if args.config is not None:
        cfg = load_config(args.config)
    else:
        cfg = recording_config(args.recording)
        if cfg is None:
            log.info("%s holds no config: using the default config", args.recording)
            cfg = Config()
    calib = read_calibration(args.calibration) if args.calibration.exists() else None
    try:
        modes = tuple(sorted({int(m) for m in args.modes.split(",")}))
    except ValueError:
        raise CalibrationError(f"--modes must be a comma-separated list of 1..6, got {args.modes!r}") from None
    if not modes or not set(modes) <= set(MODES):
        raise CalibrationError(f"--modes must be a comma-separated list of 1..6, got {args.modes!r}")
    confidence = getattr(args, "confidence", TrainParams.confidence)
    spacing = cfg.keyframes.distance_m if args.spacing is None else args.spacing
    rotation = cfg.keyframes.rotation_deg if args.rotation is None else args.rotation
    drift = getattr(args, "drift", TrainParams.drift)
    tolerance = getattr(args, "label_tolerance", TrainParams.label_tolerance)
    if not (spacing > 0 and rotation > 0 and 0 < args.r <= 1 and 0 < confidence < 1
            and args.far_pairs >= 0 and args.workers >= 1 and drift >= 0 and tolerance > 0):
        raise CalibrationError("need --spacing > 0, --rotation > 0, 0 < --r <= 1, 0 < --confidence < 1, "
                               "--far-pairs >= 0, --workers >= 1, --drift >= 0, --label-tolerance > 0")
    params = TrainParams(modes=modes, spacing_m=spacing, rotation_deg=rotation,
                         odometry=getattr(args, "odometry", "fused"), far_pairs_per_keyframe=args.far_pairs,
                         r=args.r, confidence=confidence, workers=args.workers, drift=drift,
                         label_tolerance=tolerance)
    return cfg, camera_model(calib, cfg.floor_camera), params


def _row(name: str, values: list[str]) -> str:
    return f"{name:<22}" + "".join(f"{v:>9}" for v in values)


def format_table_iii(res: dict[int, ModeResult], params: TrainParams) -> str:
    """The trained thresholds in the layout of paper 003's Table III (one column per mode),
    with what stands behind each: P(loop) at the threshold and the training loops above it."""
    modes = list(res)
    lines = [_row("local score", [f"mode {m}" for m in modes])]
    lines.append(_row("threshold", [_fmt(r.threshold) for r in res.values()]))
    p_at, above, loops = [], [], []
    for r in res.values():
        is_loop = r.overlap >= params.r
        loops.append(str(int(is_loop.sum())))
        if r.threshold is None:
            p_at.append("-")
            above.append("-")
            continue
        p_at.append(f"{float(r.curve.at(r.threshold)):.4f}")
        above.append(str(int(np.sum((r.scores >= r.threshold) & is_loop))))
    lines.append(_row("P(loop) at threshold", p_at))
    lines.append(_row("loops (J >= r)", loops))
    lines.append(_row("loops above threshold", above))
    return "\n".join(lines)


def run_loop_curve(args: Any) -> int:
    import json
    import sys

    from robotd.io.calibfile import CalibrationFile, LoopThresholds, update_calibration

    t0 = time.monotonic()
    cfg, camera, params = _setup(args)
    progress = _progress_printer()
    run = load_run(args.recording, cfg, params, progress)
    t_load = time.monotonic() - t0
    res = train(run, camera, params, progress)
    seconds = time.monotonic() - t0
    own_mb = _peak_rss_mb()
    worker_mb = max([run.worker_peak_rss_mb] + [r.worker_peak_rss_mb for r in res.values()])
    thresholds = {m: r.threshold for m, r in res.items()}
    update_calibration(args.calibration, CalibrationFile(loop=LoopThresholds.from_mapping(
        thresholds, overlap_r=params.r, confidence=params.confidence)))
    first = next(iter(res.values()))
    n_near = int(np.sum(first.weights == 1.0))
    out = sys.stdout
    print(f"\n{len(run.stamps_ns)} keyframes (every {params.spacing_m:g} m or {params.rotation_deg:g} deg); "
          f"{len(first.scores)} scored pairs per mode ({n_near} that could overlap, "
          f"{len(first.scores) - n_near} sampled distant ones); labels from {params.odometry} odometry, "
          f"loop = J >= {params.r}; {first.untrusted} candidate pairs left unlabelled (a drift of "
          f"{params.drift:g} per metre of travel could change their label)", file=out)
    if first.mislabelled is not None:
        print(f"ground truth (virtual robot) contradicts {first.mislabelled} of the {len(first.scores)} "
              "labels", file=out)
    print(f"Thresholds (paper 003 Table III): smallest local score with P(loop | score) >= "
          f"{params.confidence}", file=out)
    print(format_table_iii(res, params), file=out)
    print(f"training time {seconds:.1f} s (reading and describing {t_load:.1f} s, scoring "
          f"{sum(r.seconds for r in res.values()):.1f} s) on {params.workers} worker process(es); peak resident "
          f"memory {own_mb:.0f} MB (main process), {worker_mb:.0f} MB (largest worker)", file=out)
    untrained = [m for m, t in thresholds.items() if t is None]
    if untrained:
        print(f"modes {', '.join(map(str, untrained))}: no score reaches P(loop) >= {params.confidence} "
              "with enough evidence; no threshold (the daemon declares no loops in these modes)", file=out)
    print(f"thresholds written to {args.calibration}", file=out)
    if args.plot is not None:
        from robotd.io.plots import plot_loop_curves

        plot_loop_curves(args.plot, {m: r.curve for m, r in res.items()}, thresholds, params.confidence,
                         title=f"P(J >= {params.r} | local score), {len(run.stamps_ns)} keyframes, "
                               f"labels from {params.odometry} odometry")
        print(f"curves: {args.plot}", file=out)
    if args.json is not None:
        args.json.write_text(json.dumps({
            "recording": str(args.recording), "odometry": params.odometry, "keyframes": len(run.stamps_ns),
            "spacing_m": params.spacing_m, "r": params.r, "confidence": params.confidence,
            "pairs": len(first.scores), "near_pairs": n_near, "workers": params.workers,
            "unlabelled_pairs": first.untrusted, "mislabelled_pairs": first.mislabelled, "drift": params.drift,
            "label_tolerance": params.label_tolerance,
            "seconds": seconds, "seconds_load": t_load, "peak_rss_mb_main": own_mb,
            "peak_rss_mb_largest_worker": worker_mb,
            "modes": {str(m): {"threshold": r.threshold, "loops": int(np.sum(r.overlap >= params.r)),
                               "seconds": r.seconds,
                               "curve": {"score_lo": r.curve.score_lo.tolist(),
                                         "score_hi": r.curve.score_hi.tolist(),
                                         "probability": r.curve.probability.tolist(),
                                         "lower": r.curve.lower.tolist()}}
                      for m, r in res.items()},
        }, indent=2) + "\n")
    return 0


def _fmt(t: float | None) -> str:
    return "-" if t is None else f"{t:.1f}"


def add_validate_arguments(p: Any) -> None:
    p.add_argument("recording", type=Path, help="MCAP recording of another drive (with ground truth)")
    p.add_argument("--calibration", type=Path, required=True, help="calibration file with thresholds")
    p.add_argument("--revisit", type=float, default=2.0, metavar="M",
                   help="pairs more than this much travel apart count as revisits (default 2 m)")
    _common_arguments(p)


def _pr_json(pr: PrecisionRecall) -> dict[str, Any]:
    """Counts, precision and recall as JSON values (null where undefined)."""
    def num(x: float) -> float | None:
        return x if math.isfinite(x) else None

    return {"true_positives": pr.true_positives, "false_positives": pr.false_positives,
            "false_negatives": pr.false_negatives, "precision": num(pr.precision), "recall": num(pr.recall)}


def _pct(x: float) -> str:
    return "-" if x != x else f"{100.0 * x:.2f}%"


def run_validate(args: Any) -> int:
    import json
    import sys

    from robotd.io.calibfile import read_calibration

    cfg, camera, params = _setup(args)
    calib = read_calibration(args.calibration)
    if calib.loop is None:
        raise CalibrationError(f"{args.calibration}: no loop thresholds (run `robotd calibrate loop-curve`)")
    if args.r != calib.loop.overlap_r:
        log.warning("validating with r = %s but the thresholds were trained for r = %s",
                    args.r, calib.loop.overlap_r)
    progress = _progress_printer()
    run = load_run(args.recording, cfg, params, progress)
    res = validate(run, camera, {m: calib.loop.for_mode(m) for m in params.modes}, params,
                   revisit_m=args.revisit, progress=progress)
    out = sys.stdout
    print(f"\n{len(run.stamps_ns)} keyframes (every {params.spacing_m:g} m or {params.rotation_deg:g} deg); "
          f"a loop is a ground-truth overlap J >= {params.r}; distant pairs sampled and weighted", file=out)
    modes = list(res)
    rows: list[tuple[str, Callable[[ModeValidation], str]]] = [
        ("threshold", lambda v: _fmt(v.all_pairs.threshold if math.isfinite(v.all_pairs.threshold) else None)),
        ("declared loops", lambda v: str(v.all_pairs.true_positives + v.all_pairs.false_positives)),
        ("false loops", lambda v: str(v.all_pairs.false_positives)),
        ("missed loops", lambda v: str(v.all_pairs.false_negatives)),
        ("precision", lambda v: _pct(v.all_pairs.precision)),
        ("recall", lambda v: _pct(v.all_pairs.recall)),
        (f"revisits (> {args.revisit:g} m): loops", lambda v: str(v.revisits.true_positives
                                                                  + v.revisits.false_negatives)),
        ("  precision", lambda v: _pct(v.revisits.precision)),
        ("  recall", lambda v: _pct(v.revisits.recall)),
    ]
    print(f"{'local score':<26}" + "".join(f"{'mode ' + str(m):>9}" for m in modes), file=out)
    for name, cell in rows:
        print(f"{name:<26}" + "".join(f"{cell(v):>9}" for v in res.values()), file=out)
    if args.json is not None:
        args.json.write_text(json.dumps({
            "recording": str(args.recording), "keyframes": len(run.stamps_ns), "r": params.r,
            "revisit_m": args.revisit,
            "modes": {str(m): {
                "threshold": v.all_pairs.threshold if math.isfinite(v.all_pairs.threshold) else None,
                "all": _pr_json(v.all_pairs), "revisits": _pr_json(v.revisits)} for m, v in res.items()},
        }, indent=2) + "\n")
    return 0
