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

from calibration.loop_curve import (
    LoopCurve,
    PrecisionRecall,
    fit_loop_curve,
    pick_threshold,
    precision_recall,
)
from robotd.base.camera import FloorCameraModel, overlap_ratios
from robotd.base.errors import CalibrationError, RobotdError
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


def peak_rss_mb() -> float:
    """This process's peak resident memory, MB (Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _describe_all(image: np.ndarray, modes: tuple[int, ...]) -> tuple[list[bytes], float]:
    from robotd.floor.descriptor import extract

    return [extract(image, m) for m in modes], peak_rss_mb()


def drive_config(config_path: Path | None, recording: Path) -> Any:
    """The config of a calibration command: the file ``--config`` names, else the one the
    recording was made with, else the defaults (logged)."""
    from robotd.base.config import Config
    from robotd.base.configfile import load_config

    if config_path is not None:
        return load_config(config_path)
    cfg = recording_config(recording)
    if cfg is None:
        log.info("%s holds no config: using the default config", recording)
        cfg = Config()
    return cfg


def recording_config(path: Path) -> Any:
    """The robotd config a recording was made with (its ``robotd`` metadata), or None."""
    import tomllib

    from drivers.recording.reader import RecordingReader
    from robotd.base.configfile import config_from_dict

    with RecordingReader(path) as reader:
        text = reader.metadata.get("robotd", {}).get("config_toml", "")
    if not text:
        return None
    try:
        # Written by robotd itself, possibly by an earlier version: old key names are
        # taken (with a warning each) and the replayed recording's virtual camera accepted.
        return config_from_dict(tomllib.loads(text), origin=f"{path} (its config)", stored=True)
    except (tomllib.TOMLDecodeError, RobotdError) as exc:
        log.warning("%s: cannot use the config the recording was made with (%s); using the "
                    "defaults (pass --config to choose)", path, exc)
        return None


class _KeyframeCollector:
    """A pipeline observer for training: keeps the wheel-only track, and sends each stored
    keyframe's image to the describing workers (a few images queued per worker, not the
    whole recording: reading outruns describing)."""

    name = "training"

    def __init__(self, pool: Any, params: TrainParams, total_ns: int, start_ns: int,
                 progress: Progress | None) -> None:
        self.pool = pool
        self.params = params
        self.total_ns, self.start_ns = total_ns, start_ns
        self.progress = progress
        self.wheel_t: list[int] = []
        self.wheel_p: list[tuple[float, float, float]] = []
        self.stamps: list[int] = []
        self.fused: list[np.ndarray] = []
        self.jobs: list[Any] = []
        self.results: list[list[bytes]] = []
        self.worker_mb = 0.0
        self._next_report_ns = start_ns

    def subscriptions(self) -> dict[type, Any]:
        from robotd.base.messages import KeyframeStored, OdometryUpdate

        return {OdometryUpdate: self.on_odometry, KeyframeStored: self.on_keyframe}

    def on_odometry(self, u: Any) -> None:
        w = u.wheel
        self.wheel_t.append(w.stamp_ns)
        self.wheel_p.append((w.x_m, w.y_m, w.yaw_rad))
        if self.progress is not None and w.stamp_ns >= self._next_report_ns:
            self.progress("reading the recording (s)", (w.stamp_ns - self.start_ns) // 10**9,
                          self.total_ns // 10**9)
            self._next_report_ns = w.stamp_ns + 10**9

    def on_keyframe(self, msg: Any) -> None:
        kf = msg.keyframe
        self.stamps.append(kf.stamp_ns)
        self.fused.append(kf.pose_xyyaw)
        self.collect(len(self.jobs) - 4 * self.params.workers)
        self.jobs.append(self.pool.apply_async(_describe_all, (kf.frame.image, self.params.modes)))

    def collect(self, upto: int, show: bool = False) -> None:
        """Wait for the descriptions of keyframes before ``upto``."""
        while len(self.results) < upto:
            described, mb = self.jobs[len(self.results)].get()
            self.results.append(described)
            self.worker_mb = max(self.worker_mb, mb)
            if show and self.progress is not None and (
                    len(self.results) % 50 == 0 or len(self.results) == len(self.jobs)):
                self.progress("describing the last keyframes", len(self.results), len(self.jobs))


def load_run(path: Path, cfg: Any, params: TrainParams, progress: Progress | None = None) -> CalibrationRun:
    """Replay a recording through the daemon's own pipeline and describe its keyframes in
    every mode.

    The daemon is assembled as the service assembles it (:func:`robotd.app.assemble.
    assemble_daemon`: the same odometry, the same frame/odometry synchronisation, the same
    keyframe selection, here with ``spacing_m`` of travel or ``rotation_deg`` of turn), fed
    losslessly by the recording, with a temporary map. Each keyframe's fused pose is the
    filter's pose at the frame's stamp; its wheel-only and ground-truth poses are those
    tracks interpolated at that stamp.
    """
    import tempfile

    from drivers.recording.reader import RecordingReader
    from drivers.recording.replay import ReplayDriver
    from robotd.app.assemble import assemble_daemon
    from robotd.app.service import replay_finished
    from robotd.app.notify import Notifier
    from robotd.base.clock import ManualClock
    from robotd.base.config import replace
    from robotd.base.messages import PoseStamped
    from robotd.io.store import MapStore

    with RecordingReader(path) as reader:
        span = reader.time_range_ns
    if span is None:
        raise CalibrationError(f"{path}: the recording holds no messages")
    cfg = replace(cfg, "keyframes", distance_m=params.spacing_m, rotation_deg=params.rotation_deg,
                  image_width_px=0)
    cfg = replace(cfg, "floor_detector", enabled=False)
    clock = ManualClock(span[0])
    pool = _pool(params.workers)
    collector = _KeyframeCollector(pool, params, max(1, span[1] - span[0]), span[0], progress)
    truth: list[tuple[int, tuple[float, float, float]]] = []

    def other(topic: str, m: Any) -> None:  # the replay's thread: list.append is atomic
        if topic == "/ground_truth" and isinstance(m, PoseStamped):
            truth.append((m.stamp_ns, (m.x_m, m.y_m, m.yaw_rad)))

    try:
        with tempfile.TemporaryDirectory(prefix="robotd-train-") as tmp, \
                ReplayDriver(path, clock, on_other=other) as replay, \
                MapStore.open(Path(tmp) / "train.sqlite", synchronous="NORMAL", clock=clock) as store:
            daemon = assemble_daemon(cfg, clock, {"replay": replay}, store, Notifier(), lossless=True,
                                     observers=[collector], load_calibration_file=False,
                                     floor_detector=False, pose_graph=False)
            report = daemon.run(stop_when=lambda: replay_finished(replay, daemon))
            if report.source_errors.get("replay"):
                raise CalibrationError(f"{path}: the replay stopped on an error (see the log)")
        if progress is not None:
            progress("reading the recording (s)", collector.total_ns // 10**9, collector.total_ns // 10**9)
        collector.collect(len(collector.jobs), show=True)
    finally:
        pool.close()
        pool.join()
    stamps, wheel_t = collector.stamps, collector.wheel_t
    if len(stamps) < 10 or len(wheel_t) < 2:
        raise CalibrationError(f"{path}: only {len(stamps)} keyframes with odometry; a calibration run "
                               "needs a drive with floor frames and wheel/gyro data")
    st = np.asarray(stamps, np.int64)
    results = collector.results
    run = CalibrationRun(st, np.asarray(collector.fused),
                         interpolate_poses(np.asarray(wheel_t), np.asarray(collector.wheel_p), st),
                         None, {m: [r[i] for r in results] for i, m in enumerate(params.modes)},
                         collector.worker_mb)
    if len(truth) >= 2:
        run.truth = interpolate_poses(np.asarray([t for t, _ in truth]), np.asarray([p for _, p in truth]), st)
    return run


# -- pairs and scores ---------------------------------------------------------------------

def candidate_pairs(poses: np.ndarray, camera: FloorCameraModel, far_per_keyframe: float,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(i, j, weight)`` with i > j: every pair whose centres are close enough for the
    footprints to overlap (weight 1), and a uniform sample of the others, weighted by
    (all distant pairs) / (sampled distant pairs)."""
    reach = camera.footprint_reach_m()
    n = len(poses)
    near_i: list[np.ndarray] = []
    near_j: list[np.ndarray] = []
    for i in range(1, n):
        d = np.hypot(poses[:i, 0] - poses[i, 0], poses[:i, 1] - poses[i, 1])
        j = np.flatnonzero(d < reach)
        near_i.append(np.full(len(j), i))
        near_j.append(j)
    ni = np.concatenate(near_i) if near_i else np.zeros(0, int)
    nj = np.concatenate(near_j) if near_j else np.zeros(0, int)
    total_far = n * (n - 1) // 2 - len(ni)
    want = int(min(total_far, far_per_keyframe * n))
    fi: list[int] = []
    fj: list[int] = []
    taken = set(zip(ni.tolist(), nj.tolist()))  # near pairs, then each sampled one: no repeats
    while len(fi) < want:
        draw_i = rng.integers(1, n, want)
        draw_j = (rng.random(want) * draw_i).astype(int)
        for a, b in zip(draw_i.tolist(), draw_j.tolist()):
            if (a, b) not in taken and len(fi) < want:
                taken.add((a, b))
                fi.append(a)
                fj.append(b)
    w_far = total_far / want if want else 0.0
    pair_i = np.concatenate([ni, np.asarray(fi, int)])
    pair_j = np.concatenate([nj, np.asarray(fj, int)])
    weight = np.concatenate([np.ones(len(ni)), np.full(len(fi), w_far)])
    return pair_i, pair_j, weight


def _travel_m(poses: np.ndarray) -> np.ndarray:
    """``(N,)`` distance travelled along the keyframe poses ``(N, 3)`` up to each one, metres."""
    return np.concatenate([np.zeros(1), np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])


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
    return np.array([local_score(descs[a], descs[b]).score for a, b in pairs], dtype=float), peak_rss_mb()


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
