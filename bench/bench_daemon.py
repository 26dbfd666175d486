"""The whole daemon's CPU per robot second, stage by stage, on a recorded drive.

A Raspberry Pi 4/5 core is 2-3x slower than one here; the daemon's budget is a fraction of
one core. This benchmark:

* records the virtual robot's ``office`` drive once (``robotd record --virtual --route
  office --duration 60``, JPEG frames as the recorder writes them; cached under
  ``--cache``, keyed by route, duration and seed) and replays it through the whole daemon
  as ``robotd replay`` does (:func:`robotd.app.assemble.assemble_daemon`: odometry,
  keyframes, floor describe and query, floor visual odometry, pose graph, map store;
  the forward detector with ``--forward``, which then needs a recording with a forward
  camera), with the demo's shipped loop thresholds so that loops are declared and the
  pose graph closes them, as in ``robotd demo``;
* charges the CPU time of the pipeline thread (``time.thread_time``) to the stage whose
  handler runs, exclusively (a stage that publishes to another is not charged for it:
  :meth:`robotd.app.pipeline.Pipeline.instrument`), and the rest of the process's CPU
  (``os.times``: user + system of every thread) to "input": the replay's MCAP reading and
  JPEG decoding, the queues and the main loop (on the robot: the drivers and the camera);
* prints CPU seconds per robot second and per metre by stage, the pipeline's CPU per
  keyframe (median, p99; everything a keyframe causes), the floor describe and query times
  per keyframe (each handler alone, without the stages it publishes to), resident memory (peak and after the replay), and what the run found
  (loop edges judged by ground-truth footprint overlap, APE RMS anchored at the start of
  the loop-corrected keyframes against the recorded ground truth);
* runs a baseline in the same process on the same keyframes: OpenCV ORB (500 features)
  on each keyframe's full frame, then brute-force Hamming matching (k = 2, Lowe's ratio
  0.8) and a RANSAC similarity fit (``cv2.estimateAffinePartial2D``) against the ORB
  features of the same keyframes the floor index shortlisted for it; interleaved with
  ORB's extraction, the same keyframe images described by our default extraction and by
  the selectable ``FULL_RESOLUTION`` one (the maps at every pixel, the bytes before the
  faster defaults) and ``QUARTER`` one (the candidates from a quarter of the pixels);
* ``--scale N,...``: the floor index at larger maps: every frame of the recording is
  described (then, when more are needed, the frames turned by 180 degrees, mirrored left
  to right, mirrored top to bottom), N of them indexed, and ``--queries`` frames of the
  drive queried with the loop threshold as ``min_score`` and every copy of the frames of
  the 20 s around it left out, as the detector does (beyond the distinct images, the
  descriptors are repeated under new ids: the cost of the scan and of the shortlist is
  measured, not the shortlist of a real map of that size); describe
  and query medians, the index's memory and the process's at each size, and the same
  queries on the daemon's index (``IndexParams.resident`` descriptors kept decoded, the
  others decoded again from their bytes when shortlisted) and on the index
  ``FloorIndex.from_store`` builds from a map of the same descriptors (read back through
  the map); then, on indexes built afresh, each query's CPU time by part (shortlist, the
  map's read, decode, local score), and whether the three returned the same candidates;
* ``--memory N`` (alone, in a process of its own): the whole daemon's resident memory as
  its map grows to N keyframes (:func:`memory_run`; ``--localise-mapped`` as the service
  runs it), sampled every ``--memory-every`` keyframes into ``NAME-memory.json`` (and a
  partial JSON while it runs); ``--memory-page JSON...`` writes
  ``docs/benchmarks/daemon-memory.md`` from such files;
* ``--residency MAP``: the floor query on a daemon's map (e.g. three laps kept with
  ``--memory 1500 --keep-map FILE``) repeated to the ``--scale`` sizes, its descriptors in
  RAM, read back, and as ``FloorIndex.from_store`` holds them (:func:`query_residency`);
  several maps (``LABEL=MAP ...``): each in turn, ``--rounds`` times, with how each map's
  queries repeat its keyframes and the local scores and geometric checks per query; a map
  of laps of new frames comes from ``--memory N --memory-seeds 0,0,0 --keep-map FILE``
  (each lap every third frame of the drive, lap k the frame counts k mod 3);
* ``--compare-stages LABEL=JSON ...``: a page of replays of two trees alternated (e.g. the
  code before a change and after it, each run a process of its own): CPU by stage per run,
  each label's mean and its ratio to the first label's (:func:`stage_comparison`);
* ``--load MAP [--before DIR]``: ``FloorIndex.from_store``'s load time and the process's
  resident memory around it, each load in a fresh process, alternating with the checkout
  of the code before in ``DIR`` (:func:`map_load`).

Run from the repo root: ``./dev bench daemon [--out DIR]`` (default ``bench/results``).
Writes ``DIR/daemon.json``; ``--doc FILE`` also writes the markdown page generated from
it (``docs/benchmarks/daemon.md``). Takes ~5-10 min (the first run records the drive,
about 1-2 min more); ``--full`` replays the whole office route (about 232 s, 110 m) and
describes 10,000 distinct images for the index at 10,000 keyframes (default: 1,000, then
repeated).
"""

from __future__ import annotations

import argparse
import collections
import gc
import hashlib
import json
import math
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's robotd first
import numpy as np  # noqa: E402

try:
    from bench.common import REPO_ROOT, grow_repeated_map, machine_info, print_table, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import REPO_ROOT, grow_repeated_map, machine_info, print_table, write_json

STAGES = ("odometry", "keyframes", "floor describe", "floor query", "visual odometry", "pose graph",
          "forward detector", "store", "other stages", "input (replay, queues, main loop)")
"""The rows of the table, in the order of the daemon's data flow."""

_STAGE_OF = {"odometry": "odometry", "keyframes": "keyframes", "visual_odometry": "visual odometry",
             "graph": "pose graph", "forward": "forward detector", "map": "store"}


def stage_row(stage: str, handler: str) -> str:
    """The table row a pipeline handler's CPU time is charged to."""
    if stage == "floor":
        return "floor describe" if handler == "describe" else "floor query"
    return _STAGE_OF.get(stage, "other stages")


class StageClock:
    """Charges the CPU time of the calling thread to (stage, handler), exclusive of the
    handlers it publishes to (they are timed themselves), keeps each call's exclusive time
    (``samples``: the per-call medians of the floor describe and query are of those
    handlers alone, not of the visual odometry, pose graph and store they publish to), and
    sums per keyframe the inclusive time of the handlers of each
    :class:`~robotd.base.messages.Keyframe` (which includes the later stages: the
    described, measured and stored keyframe are published from within them)."""

    def __init__(self) -> None:
        self.cpu_s: collections.Counter[tuple[str, str]] = collections.Counter()
        self.calls: collections.Counter[tuple[str, str]] = collections.Counter()
        self.samples: dict[tuple[str, str], list[float]] = collections.defaultdict(list)
        self.per_keyframe_s: dict[int, float] = collections.defaultdict(float)
        self._children: list[float] = []

    def wrap(self, stage: str, handler: str, fn: Any) -> Any:
        from robotd.base.messages import Keyframe

        key = (stage, handler)
        clock = time.thread_time

        def timed(*args: Any) -> Any:
            t0 = clock()
            self._children.append(0.0)
            try:
                return fn(*args)
            finally:
                dt = clock() - t0
                own = dt - self._children.pop()
                self.cpu_s[key] += own
                self.calls[key] += 1
                self.samples[key].append(own)  # the handler alone, as in the table
                if self._children:
                    self._children[-1] += dt
                if args and type(args[0]) is Keyframe:  # its handlers' time includes the later stages
                    self.per_keyframe_s[id(args[0])] += dt

        return timed

    def by_row(self) -> dict[str, float]:
        out = dict.fromkeys(STAGES, 0.0)
        for (stage, handler), s in self.cpu_s.items():
            out[stage_row(stage, handler)] += s
        return out


# ------------------------------------------------------------------------- recording


def ensure_recording(args: argparse.Namespace, seed: int | None = None) -> Path:
    """The cached recording of the drive, made with ``robotd record --virtual`` if missing.

    ``seed``: the drive recorded with that seed (other camera and sensor noise) on the robot
    of ``args.seed`` (``--base-seed``: the same wheel and gyro errors); default ``args.seed``."""
    if args.recording is not None and seed is None:
        return args.recording
    seed = args.seed if seed is None else int(seed)
    dur = "full" if args.duration is None else f"{args.duration:g}s"
    fwd = "-forward" if args.forward else ""
    base = "" if seed == args.seed else f"-base{args.seed}"
    path = args.cache / f"{args.route}-{dur}-seed{seed}{base}{fwd}.mcap"
    if path.exists():
        print(f"recording: {path} (cached)")
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    print(f"recording the virtual robot to {path} ...", flush=True)
    if args.forward:
        # robotd record has no --forward: record through the demo with the forward camera on,
        # in a child process like robotd record (the rendering would stay in this one's RSS).
        code = ("import sys, tempfile; from pathlib import Path; from robotd.app.demo import run_demo; "
                "from robotd.base.config import Config, replace; "
                "cfg = replace(Config(), 'forward_detector', enabled=True); "
                "d = None if sys.argv[2] == 'None' else float(sys.argv[2]); "
                "t = tempfile.TemporaryDirectory(); "
                "run_demo(cfg, out=Path(t.name), route=sys.argv[1], duration_s=d, seed=int(sys.argv[3]), "
                "plot=False, record=Path(sys.argv[4]))")
        subprocess.run([sys.executable, "-c", code, args.route, str(args.duration), str(args.seed), str(path)],
                       check=True, stdout=subprocess.DEVNULL, env={**os.environ, "PYTHONPATH": str(REPO_ROOT)})
        return path
    cmd = [sys.executable, "-m", "robotd.app.cli", "record", "--virtual", "--route", args.route,
           "--seed", str(seed), *(["--base-seed", str(args.seed)] if base else []), str(path)]
    if args.duration is not None:
        cmd[-1:-1] = ["--duration", str(args.duration)]
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run(cmd, check=True, cwd=tmp, stdout=subprocess.DEVNULL,
                       env={**os.environ, "PYTHONPATH": str(REPO_ROOT)})
    return path


def read_truth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps_ns (M,), poses (M, 3))`` of the recording's ``/ground_truth``."""
    from drivers.recording.reader import RecordingReader
    from drivers.recording.schemas import TOPIC_GROUND_TRUTH

    from robotd.base.messages import PoseStamped

    stamps, poses = [], []
    with RecordingReader(path) as r:
        for topic, msg in r.messages(only=(PoseStamped,)):  # the frames not decoded
            if topic == TOPIC_GROUND_TRUTH:
                stamps.append(msg.stamp_ns)
                poses.append((msg.x_m, msg.y_m, msg.yaw_rad))
    return np.asarray(stamps, np.int64), np.asarray(poses, float).reshape(-1, 3)


def truth_at(stamps_ns: np.ndarray, truth: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Ground truth interpolated linearly at ``stamps_ns`` (yaw unwrapped first)."""
    ts, p = truth
    yaw = np.unwrap(p[:, 2])
    t = np.asarray(stamps_ns, float)
    return np.column_stack([np.interp(t, ts, p[:, 0]), np.interp(t, ts, p[:, 1]), np.interp(t, ts, yaw)])


# ---------------------------------------------------------------------------- replay


def make_config(args: argparse.Namespace, map_path: Path) -> Any:
    """``robotd replay``'s config (floor camera: virtual) with the demo's loop thresholds."""
    from robotd.app.demo import shipped_calibration
    from robotd.base.config import Config, replace, with_virtual_floor_camera

    cfg = Config()
    cfg = with_virtual_floor_camera(cfg)
    cfg = replace(cfg, "map", path=str(map_path))
    cfg = replace(cfg, "calibration", path=str(shipped_calibration()))
    if args.keyframe_distance is not None:
        cfg = replace(cfg, "keyframes", distance_m=args.keyframe_distance)
    if args.shortlist is not None:
        cfg = replace(cfg, "floor_detector", shortlist=args.shortlist)
    if getattr(args, "candidates", None) is not None:
        cfg = replace(cfg, "floor_detector", candidates=args.candidates)
    if args.ransac_confidence:
        cfg = replace(cfg, "floor_detector", ransac_confidence=args.ransac_confidence)
    if args.localise_mapped:
        cfg = replace(cfg, "pose_graph", localise_mapped=True)
    if args.forward:
        cfg = replace(cfg, "forward_detector", enabled=True)
    return cfg


def rss_mb() -> float:
    """Resident memory now, MB (``VmRSS``)."""
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return math.nan


def trimmed_rss_mb() -> float:
    """Resident memory after glibc's ``malloc_trim(0)`` (what the process holds, without
    the free lists glibc keeps; as ``bench_soak``); ``rss_mb()`` where there is no glibc."""
    import ctypes
    import ctypes.util

    try:
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    return rss_mb()


def process_memory() -> dict[str, float]:
    """Where the resident memory is, MB: ``RssAnon`` (heap, mmaps: what the code allocates),
    ``RssFile`` (mapped libraries and files) from ``/proc/self/status``, and glibc's
    ``mallinfo2``: bytes in use (``malloc_used_mb``: live allocations), held free in its
    arenas (``malloc_free_mb``: fragmentation), in its own mmaps (``malloc_mmap_mb``), and
    the arena count as the main arena plus its others' size; empty where not Linux glibc."""
    import ctypes
    import ctypes.util

    out: dict[str, float] = {}
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                k = line.split(":")[0]
                if k in ("RssAnon", "RssFile", "RssShmem", "VmData"):
                    out[k] = int(line.split()[1]) / 1024
    except OSError:
        pass

    class MallInfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                   "fsmblks", "uordblks", "fordblks", "keepcost")]

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallinfo2.restype = MallInfo2
        m = libc.mallinfo2()
        out.update({"malloc_used_mb": m.uordblks / 1e6, "malloc_free_mb": m.fordblks / 1e6,
                    "malloc_mmap_mb": m.hblkhd / 1e6, "malloc_arena_mb": m.arena / 1e6})
    except (OSError, AttributeError):
        pass
    return out


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def replay(args: argparse.Namespace, recording: Path, map_path: Path) -> dict[str, Any]:
    """Replay the recording through the instrumented daemon; CPU by stage and the rest."""
    from drivers.recording.replay import ReplayDriver
    from robotd.app.assemble import assemble_daemon, open_map
    from robotd.app.notify import Notifier
    from robotd.app.service import replay_finished
    from robotd.base.clock import ManualClock

    cfg = make_config(args, map_path)
    clock = ManualClock()
    timer = StageClock()
    with ReplayDriver(recording, clock, None) as rd:
        span = rd.time_range_ns
        clock.set_ns(span[0])
        with open_map(cfg, clock=clock) as store:
            daemon = assemble_daemon(cfg, clock, {"replay": rd}, store, Notifier(), lossless=True)
            daemon.pipeline.instrument(timer.wrap)
            rss0 = rss_mb()
            t0, w0 = os.times(), time.perf_counter()
            report = daemon.run(stop_when=lambda: replay_finished(rd, daemon))
            t1, w1 = os.times(), time.perf_counter()
    robot_s = (span[1] - span[0]) / 1e9
    rows = timer.by_row()
    process_s = (t1.user - t0.user) + (t1.system - t0.system)
    rows["input (replay, queues, main loop)"] = max(0.0, process_s - sum(rows.values()))
    per_kf = np.array(list(timer.per_keyframe_s.values())) * 1e3
    describe = np.array(timer.samples[("floor", "describe")]) * 1e3
    query = np.array(timer.samples[("floor", "query")]) * 1e3
    c = report.counters

    def stats(v: np.ndarray) -> dict[str, float | None]:
        if len(v) == 0:
            return {"median": None, "p99": None, "n": 0}
        return {"median": float(np.median(v)), "p99": float(np.quantile(v, 0.99)), "n": int(len(v))}

    return {"robot_s": robot_s, "wall_s": w1 - w0, "process_cpu_s": process_s,
            "user_s": t1.user - t0.user, "system_s": t1.system - t0.system,
            "stage_cpu_s": rows, "keyframes": int(c.get("keyframes", 0)),
            "keyframe_ms": stats(per_kf), "describe_ms": stats(describe), "query_ms": stats(query),
            "rss_before_mb": rss0, "rss_after_mb": rss_mb(), "peak_rss_mb": peak_rss_mb(),
            "counters": {k: v for k, v in c.items() if isinstance(v, (int, float))},
            "config": {"keyframe_distance_m": cfg.keyframes.distance_m, "mode": cfg.floor_detector.descriptor_mode,
                       "shortlist": cfg.floor_detector.shortlist,
                       "ransac_confidence": cfg.floor_detector.ransac_confidence,
                       "localise_mapped": cfg.pose_graph.localise_mapped,
                       "forward": cfg.forward_detector.enabled}}


def judge(map_path: Path, truth: tuple[np.ndarray, np.ndarray], exclude_recent_s: float) -> dict[str, Any]:
    """The run's map against the truth: loop edges (footprint overlap J of the two
    keyframes' true poses, loop when J >= 0.33), revisits (keyframes with a truly
    overlapping keyframe older than ``exclude_recent_s``) and how many of them got a loop
    edge, and the APE (RMS, anchored at the first keyframe: evo's ``--align_origin``) of the
    loop-corrected and the odometry keyframe poses. The JSON keys keep their first name,
    ``ate_*_m``, so that the committed runs still make the pages."""
    from robotd.base.camera import FloorCameraModel, overlap_ratios
    from robotd.base.config import Config
    from robotd.floor.evaluation import overlap_matrix
    from robotd.evaluation.metrics import odometry_errors
    from robotd.io.store import MapStore

    camera = FloorCameraModel.from_config(Config().floor_camera)
    with MapStore.open(map_path, create=False) as store:
        kfs = list(store.keyframes())
        opt = store.optimized_poses()
        loops = [(lk.from_id, lk.to_id) for lk in store.links("loop")]
    ids = np.array([k.id for k in kfs])
    stamps = np.array([k.stamp_ns for k in kfs], np.int64)
    true_poses = truth_at(stamps, truth)
    row = {int(k): i for i, k in enumerate(ids)}
    # The distance driven: the whole recorded truth (stored keyframes skip the ground
    # driven over transient keyframes when the map is localised on).
    tp = truth[1]
    out: dict[str, Any] = {"keyframes": len(kfs), "distance_m": float(np.sum(np.hypot(
        np.diff(tp[:, 0]), np.diff(tp[:, 1]))))}
    pairs = [(row[a], row[b]) for a, b in loops if a in row and b in row]
    j = (overlap_ratios(camera, true_poses[[p[0] for p in pairs]], true_poses[[p[1] for p in pairs]])
         if pairs else np.zeros(0))
    out["loop_edges"] = len(loops)
    out["loop_edges_true"] = int(np.sum(j >= 0.33))
    out["loop_edges_false"] = int(np.sum(j < 0.33))
    out["loop_edges_no_shared_floor"] = int(np.sum(j <= 0))
    overlap = overlap_matrix(camera, true_poses)
    old = stamps[None, :] < stamps[:, None] - int(exclude_recent_s * 1e9)
    revisit = np.any((overlap >= 0.33) & old, axis=1)
    closed = np.zeros(len(ids), bool)
    for a, b in pairs:
        closed[max(a, b)] = True
    out["revisits"] = int(revisit.sum())
    out["revisits_closed"] = int((revisit & closed).sum())
    est = np.array([[k.x_m, k.y_m, k.yaw_rad] for k in kfs])
    out["ate_odometry_m"] = odometry_errors(true_poses, est).ape_origin_rmse_m
    if all(int(k) in opt for k in ids):
        out["ate_loop_corrected_m"] = odometry_errors(true_poses, np.array([opt[int(k)] for k in ids])).ape_origin_rmse_m
    else:
        out["ate_loop_corrected_m"] = None
    return out


# -------------------------------------------------------------------------- baseline


def keyframe_frames(recording: Path, stamps_ns: set[int]) -> dict[int, np.ndarray]:
    """The recording's floor frames at the keyframes' stamps, grey."""
    import cv2

    from drivers.recording.reader import RecordingReader
    from robotd.base.messages import Frame

    out = {}
    with RecordingReader(recording) as r:
        for _topic, msg in r.messages():
            if isinstance(msg, Frame) and msg.camera == "floor" and msg.stamp_ns in stamps_ns:
                img = msg.image
                out[msg.stamp_ns] = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
    return out


def baseline(recording: Path, map_path: Path, exclude_recent_s: float, shortlist: int,
             mode: int = 4) -> dict[str, Any]:
    """ORB + brute-force Hamming + RANSAC of each keyframe against the keyframes the floor
    index shortlists for it (the same shortlist, rebuilt from the stored descriptors with
    the detector's exclusion of the last ``exclude_recent_s``). Beside ORB's extraction,
    interleaved on the same keyframe images: our default extraction (as the daemon runs
    it) and the selectable :data:`~robotd.floor.descriptor.FULL_RESOLUTION` and
    :data:`~robotd.floor.descriptor.QUARTER` ones."""
    import cv2

    from robotd.floor.descriptor import FULL_RESOLUTION, QUARTER, decode, extract
    from robotd.floor.index import FloorIndex, IndexParams
    from robotd.io.store import MapStore

    with MapStore.open(map_path, create=False) as store:
        kfs = [k for k in store.keyframes() if k.descriptor is not None]
    frames = keyframe_frames(recording, {k.stamp_ns for k in kfs})
    orb = cv2.ORB_create(nfeatures=500)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    index = FloorIndex(IndexParams(shortlist=shortlist))
    feats: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    extract_ms, match_ms, inliers = [], [], []
    ours_ms: dict[str, list[float]] = {"default": [], "full_resolution": [], "quarter": []}
    for k in kfs:
        img = frames.get(k.stamp_ns)
        if img is None:
            continue
        t0 = time.thread_time()
        kp, des = orb.detectAndCompute(img, None)
        pts = np.float32([p.pt for p in kp]).reshape(-1, 2)
        extract_ms.append((time.thread_time() - t0) * 1e3)
        for name, params in (("default", None), ("full_resolution", FULL_RESOLUTION), ("quarter", QUARTER)):
            t0 = time.thread_time()
            extract(img, mode, params)
            ours_ms[name].append((time.thread_time() - t0) * 1e3)
        desc = decode(k.descriptor)
        older = [(i, s) for i, s in ((kk.id, kk.stamp_ns) for kk in kfs if kk.id in feats)
                 if s < k.stamp_ns - int(exclude_recent_s * 1e9)]
        short = index.shortlist(desc, exclude_after_id=max(i for i, _ in older)) if older else []
        t0 = time.thread_time()
        best = 0
        for kf_id, _g in short:
            pts_b, des_b = feats[kf_id]
            if des is None or des_b is None or len(des) < 2 or len(des_b) < 2:
                continue
            good = [m[0] for m in bf.knnMatch(des, des_b, k=2) if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
            if len(good) < 4:
                continue
            a = pts[[m.queryIdx for m in good]]
            b = pts_b[[m.trainIdx for m in good]]
            _m, mask = cv2.estimateAffinePartial2D(a, b, method=cv2.RANSAC, ransacReprojThreshold=8.0)
            if mask is not None:
                best = max(best, int(mask.sum()))
        if short:
            match_ms.append((time.thread_time() - t0) * 1e3)
            inliers.append(best)
        feats[k.id] = (pts, des)
        index.add(k.id, desc)

    def stats(v: list[float]) -> dict[str, float | None]:
        return {"median": statistics.median(v) if v else None,
                "p99": float(np.quantile(v, 0.99)) if v else None, "n": len(v)}

    return {"orb_extract_ms": stats(extract_ms), "orb_match_shortlist_ms": stats(match_ms),
            "describe_default_ms": stats(ours_ms["default"]),
            "describe_full_resolution_ms": stats(ours_ms["full_resolution"]),
            "describe_quarter_ms": stats(ours_ms["quarter"]),
            "keyframes": len(extract_ms), "queries": len(match_ms),
            "median_best_inliers": statistics.median(inliers) if inliers else None}


# ----------------------------------------------------------------------------- scale


class _QueryParts:
    """Where a floor query's CPU time goes (thread CPU, summed by part): the shortlist
    (global scan and ranking), the read back (the index's loader: the map's read and the
    decode), the decode alone, and the local score (the query side's preparation included).
    :meth:`timed` wraps an index; :meth:`patched` times the decode and the local matcher of
    :mod:`robotd.floor.index` (by name, so it times the code of any checkout)."""

    def __init__(self) -> None:
        self.s: collections.Counter[str] = collections.Counter()

    def wrap(self, part: str, fn: Any) -> Any:
        def timed(*a: Any, **kw: Any) -> Any:
            t0 = time.thread_time()
            try:
                return fn(*a, **kw)
            finally:
                self.s[part] += time.thread_time() - t0
        return timed

    def timed(self, index: Any) -> Any:
        index.shortlist = self.wrap("shortlist", index.shortlist)
        if getattr(index, "_loader", None) is not None:
            index._loader = self.wrap("read back", index._loader)
        return index

    def patched(self) -> Any:
        import contextlib

        import robotd.floor.index as fi

        parts = self

        class TimedMatcher(fi.Matcher):  # type: ignore[misc, name-defined]
            def __init__(self, *a: Any, **kw: Any) -> None:
                t0 = time.thread_time()
                super().__init__(*a, **kw)
                parts.s["local score"] += time.thread_time() - t0

            def score(self, *a: Any, **kw: Any) -> Any:
                t0, p0 = time.thread_time(), parts.s["positions"]
                try:
                    return super().score(*a, **kw)
                finally:  # a read-back descriptor's positions, decoded within: counted as decode
                    parts.s["local score"] += time.thread_time() - t0 - (parts.s["positions"] - p0)

            def score_many(self, *a: Any, **kw: Any) -> Any:  # the code since the query scores in batches
                t0, p0 = time.thread_time(), parts.s["positions"]
                try:
                    return super().score_many(*a, **kw)
                finally:
                    parts.s["local score"] += time.thread_time() - t0 - (parts.s["positions"] - p0)

        @contextlib.contextmanager
        def cm() -> Any:
            matcher, decode = fi.Matcher, fi.decode
            fi.Matcher, fi.decode = TimedMatcher, self.wrap("decode", decode)
            local = getattr(fi, "decode_local", None)  # the read back in two steps, where the code has it
            partial = getattr(fi, "PartialDescriptor", None)
            positions = partial.positions if partial is not None else None
            if local is not None:
                fi.decode_local = self.wrap("decode", local)
            if partial is not None:
                partial.positions = self.wrap("positions", positions)
            try:
                yield self
            finally:
                fi.Matcher, fi.decode = matcher, decode
                if local is not None:
                    fi.decode_local = local
                if partial is not None:
                    partial.positions = positions
        return cm()

    def per_query_ms(self, total_s: float, queries: int) -> dict[str, float]:
        """Mean CPU ms per query by part; ``read`` is the read back less its decode, ``decode``
        that and (read back in two steps) the positions decoded within the local score,
        ``other`` what the parts do not cover (the candidates' bookkeeping, the resident set)."""
        s = self.s
        out = {"shortlist": s["shortlist"], "read": max(0.0, s["read back"] - s["decode"]),
               "decode": s["decode"] + s["positions"], "local score": s["local score"]}
        out["other"] = total_s - s["shortlist"] - s["read back"] - s["local score"] - s["positions"]
        out["total"] = total_s
        return {k: v * 1e3 / queries for k, v in out.items()}


def scale(recording: Path, sizes: list[int], queries: int, mode: int, shortlist: int,
          duration_s: float, max_distinct: int) -> dict[str, Any]:
    """Describe the recording's frames (and turned or mirrored copies) until the largest
    size is reached; index them and time queries at each size, with the demo's loop
    threshold for ``mode`` as the detector passes it (``min_score``).

    Three indexes answer the same queries in turn: every descriptor in RAM; the daemon's
    index with its descriptors decoded again from their bytes when read back (as before the
    map read was timed); and the daemon's index as it is built from a map
    (``FloorIndex.from_store`` on a map of the same descriptors: the map's read and the
    decode). A first pass times the queries; a second, on indexes built afresh, times
    each part of them (:class:`_QueryParts`), and every query's candidates are compared
    across the three."""
    from robotd.app.demo import shipped_calibration
    from robotd.io.calibfile import read_calibration

    calib = read_calibration(shipped_calibration())
    min_score = (calib.loop.for_mode(mode) if calib.loop is not None else None) or 0.0
    import cv2

    from drivers.recording.reader import RecordingReader
    from robotd.base.messages import Frame
    from robotd.floor.descriptor import decode, extract
    from robotd.floor.index import FloorIndex, IndexParams
    from robotd.io.store import MapStore

    need = min(max(sizes), max_distinct)
    variants = [lambda im: im, lambda im: cv2.rotate(im, cv2.ROTATE_180), lambda im: cv2.flip(im, 1),
                lambda im: cv2.flip(im, 0)]
    blobs: list[bytes] = []
    describe_ms: list[float] = []
    n_frames = 0
    for v in variants:  # the recording read again per variant: no frame is kept in memory
        with RecordingReader(recording) as r:
            for _topic, msg in r.messages():
                if len(blobs) >= need:
                    break
                if isinstance(msg, Frame) and msg.camera == "floor":
                    img = msg.image
                    img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
                    t0 = time.thread_time()
                    blobs.append(extract(v(img), mode))
                    describe_ms.append((time.thread_time() - t0) * 1e3)
                    n_frames += v is variants[0]
        if len(blobs) >= need:
            break
    distinct = len(blobs)
    if distinct < need:
        # Not enough distinct images: the larger sizes repeat descriptors under new ids. The
        # global scan still covers every row and the shortlist scores as many keyframes, so
        # the cost is measured; which keyframes are shortlisted is not that of a real map.
        print(f"scale: {distinct} distinct images; larger maps repeat them", flush=True)
    out: dict[str, Any] = {"min_score": min_score, "describe_ms": {"median": statistics.median(describe_ms),
                                           "p99": float(np.quantile(describe_ms, 0.99)),
                                           "n": len(describe_ms)}, "sizes": []}
    index = FloorIndex(IndexParams(shortlist=shortlist))
    rng = np.random.default_rng(0)
    rss0 = rss_mb()
    decoded = [decode(b) for b in blobs[:n_frames]]  # queries: the drive's own frames
    recent = int(20.0 * n_frames / max(1.0, duration_s))  # frames in 20 s
    import robotd.floor.index as fi

    def copy(on_demand: bool) -> Any:
        # on_demand: the daemon's index (IndexParams.resident descriptors kept decoded), the
        # others decoded again from their bytes when shortlisted (decode looked up at call
        # time, so that _QueryParts times it); otherwise every descriptor in RAM.
        # As FloorIndex.from_store reads them back: in two steps (decode_local) where the code has it.
        loader = (lambda i: getattr(fi, "decode_local", fi.decode)(blobs[i % distinct])) if on_demand else None
        ix = FloorIndex(IndexParams(shortlist=shortlist), loader=loader)
        for i in range(len(index)):
            ix.add(i, index.descriptor(i))
        return ix

    with tempfile.TemporaryDirectory() as tmp:
        map_path = Path(tmp) / "scale-map.sqlite"
        kf_ids: list[int] = []
        for n in sorted(sizes):
            for i in range(len(index), n):
                index.add(i, decode(blobs[i % distinct]))
            with MapStore.open(map_path, synchronous="NORMAL") as store:  # the map of the same descriptors
                run = store.begin_run("", started_ns=0)
                for i in range(len(kf_ids), n):
                    kf_ids.append(store.add_keyframe(run, i, (0.0, 0.0, 0.0), np.eye(3), None,
                                                     blobs[i % distinct], mode))
            qs = rng.choice(len(decoded), size=min(queries, len(decoded)), replace=False)
            ids = np.arange(n)
            kf_of = np.asarray(kf_ids, np.int64)
            row: dict[str, Any] = {"keyframes": n, "distinct": min(n, distinct), "resident": IndexParams().resident}
            with MapStore.open(map_path, create=False, read_only=True) as store:
                for timing_pass in ("times", "parts"):
                    parts = {k: _QueryParts() for k in ("in RAM", "read back", "from the map")}
                    built = {"in RAM": index if timing_pass == "times" else copy(False), "read back": copy(True),
                             "from the map": FloorIndex.from_store(store, mode, IndexParams(shortlist=shortlist))}
                    if timing_pass == "parts":
                        built = {k: parts[k].timed(v) for k, v in built.items()}
                    loads0 = {k: getattr(v, "loads", 0) for k, v in built.items()}
                    ms: dict[str, list[float]] = {k: [] for k in built}
                    same = True
                    for q in qs:
                        # As the detector: nothing from the last (or next) 20 s of the drive, in any copy.
                        excluded = ids[np.abs(ids % distinct % n_frames - q) < recent]
                        got = {}
                        for name, ix in built.items():
                            ex = kf_of[excluded] if name == "from the map" else excluded
                            if timing_pass == "parts":
                                with parts[name].patched():
                                    t0 = time.thread_time()
                                    cands = ix.query(decoded[q], k=5, min_score=min_score, exclude_ids=ex)
                                    parts[name].s["total"] += time.thread_time() - t0
                            else:
                                t0 = time.thread_time()
                                cands = ix.query(decoded[q], k=5, min_score=min_score, exclude_ids=ex)
                                ms[name].append((time.thread_time() - t0) * 1e3)
                            back = (lambda kf: int(np.searchsorted(kf_of, kf))) if name == "from the map" else int
                            got[name] = [(back(c.keyframe_id), c.global_score, c.score) for c in cands]
                        same &= got["in RAM"] == got["read back"] == got["from the map"]
                    reads = {k: (getattr(v, "loads", 0) - loads0[k]) / len(qs) for k, v in built.items()}
                    if timing_pass == "times":
                        def stats(v: list[float]) -> dict[str, float]:
                            return {"median": statistics.median(v), "p99": float(np.quantile(v, 0.99)), "n": len(v)}

                        row["query_ms"] = stats(ms["in RAM"])
                        row["query_read_back_ms"] = {**stats(ms["read back"]), "reads_per_query": reads["read back"],
                                                     "resident": built["read back"].params.resident}
                        row["query_from_map_ms"] = {**stats(ms["from the map"]),
                                                    "reads_per_query": reads["from the map"],
                                                    "index_mb": built["from the map"].nbytes / 1e6}
                        row["same_candidates"] = same
                    else:
                        row["parts_ms"] = {k: p.per_query_ms(p.s["total"], len(qs)) for k, p in parts.items()}
                        row["same_candidates"] = bool(row["same_candidates"] and same)
                    del built
            row.update({"index_mb": index.nbytes / 1e6, "rss_mb": rss_mb(), "rss_growth_mb": rss_mb() - rss0})
            print(f"scale: {n} keyframes: in RAM {row['query_ms']['median']:.2f} ms, read back "
                  f"{row['query_read_back_ms']['median']:.2f} ms, from the map {row['query_from_map_ms']['median']:.2f}"
                  f" ms ({row['query_from_map_ms']['reads_per_query']:.1f} reads per query), same candidates: "
                  f"{row['same_candidates']}; parts (ms per query): "
                  + "; ".join(f"{k}: " + ", ".join(f"{pk} {pv:.2f}" for pk, pv in v.items())
                              for k, v in row["parts_ms"].items()), flush=True)
            out["sizes"].append(row)
    return out


# ---------------------------------------------------------------------------- memory


class TruthOdometry:
    """The keyframe stage's odometry (``KeyframeOdometry``) from the recording's ground
    truth, for :func:`memory_run`: lap ``k`` of the drive is stamped ``k`` laps later and
    has the first lap's poses (``truth``: the lap's own recording's, set by the run), as a
    robot driving its round again; edges and poses carry
    a covariance growing with the motion (1 % of it, 1 mm and 1 mrad at least)."""

    def __init__(self, truth: tuple[np.ndarray, np.ndarray], lap_ns: int) -> None:
        self.truth, self.lap_ns = truth, lap_ns
        self.settled: int | None = None
        self._previous: np.ndarray | None = None

    def settled_stamp_ns(self) -> int | None:
        return self.settled

    def _at(self, stamp_ns: int) -> np.ndarray:
        t0 = int(self.truth[0][0])
        return truth_at(np.array([(stamp_ns - t0) % self.lap_ns + t0]), self.truth)[0]

    def pose_at(self, stamp_ns: int) -> Any:
        from robotd.base.geometry import wrap_angle
        from robotd.base.messages import PoseStamped

        p = self._at(stamp_ns)
        return PoseStamped(stamp_ns, float(p[0]), float(p[1]), wrap_angle(float(p[2])), np.diag([1e-6, 1e-6, 1e-6]))

    def keyframe_edge(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        from robotd.base.geometry import between

        p, prev = self._at(stamp_ns), self._previous
        self._previous = p
        if prev is None:
            return None
        d = between(prev, p)
        sig = 0.01 * np.abs(d) + np.array([1e-3, 1e-3, 1e-3])
        return d, np.diag(sig ** 2)


def graph_memory(graph: Any) -> dict[str, Any]:
    """The pose graph's size: its edges (odometry and loop), the factors in iSAM2, and its
    Bayes tree's cliques (count, largest, sum of frontal x separator sizes: the entries
    of the conditionals it stores; :meth:`robotd.graph.incremental.IncrementalGraph.stats`)."""
    return {f"graph_{k}": v for k, v in graph.stats().items()}


def sqlite_memory_mb() -> float:
    """Memory SQLite's allocator holds in this process (every connection's page cache,
    schema and statements: ``sqlite3_memory_used``), MB; NaN where the library is not found."""
    import ctypes
    import ctypes.util

    try:
        lib = ctypes.CDLL(ctypes.util.find_library("sqlite3") or "libsqlite3.so.0")
        lib.sqlite3_memory_used.restype = ctypes.c_int64
        return float(lib.sqlite3_memory_used()) / 1e6
    except (OSError, AttributeError):
        return math.nan


def memory_breakdown(floor: Any, trace: bool) -> dict[str, Any]:
    """Where the memory is, for :func:`memory_run`'s samples: the floor index's global
    array and its descriptors in RAM (``index_global_mb``, ``index_descriptors_mb``),
    SQLite's allocator (``sqlite_mb``) and, with ``trace`` (``tracemalloc`` running), the
    Python side: every traced allocation (numpy's data included) by file, the largest
    first (``traced_mb``, ``traced_by_file``), and tracemalloc's own overhead."""
    index = floor.detector.index
    packed = getattr(index, "_packed", None)
    desc = getattr(index, "descriptors_nbytes", None)
    desc_b = desc if desc is not None else (packed.nbytes if packed is not None else 0)
    out: dict[str, Any] = {"index_descriptors_mb": desc_b / 1e6, "index_global_mb": (index.nbytes - desc_b) / 1e6,
                           "sqlite_mb": sqlite_memory_mb()}
    if trace:
        import tracemalloc

        snap = tracemalloc.take_snapshot()
        stats = snap.statistics("filename")
        out["traced_mb"] = sum(s.size for s in stats) / 1e6
        out["tracemalloc_overhead_mb"] = tracemalloc.get_tracemalloc_memory() / 1e6
        root = str(REPO_ROOT) + os.sep
        out["traced_by_file"] = [[str(s.traceback[0].filename).replace(root, ""), round(s.size / 1e6, 2), s.count]
                                 for s in stats[:12]]
    return out


def release_breakdown(pipeline: Any, trace: bool) -> list[dict[str, Any]]:
    """Attribution by removal, at the end of :func:`memory_run`: the daemon's large parts
    let go one after the other (iSAM2, then the rest of the pose graph and its gate, then
    the floor index), each followed by a collection and ``malloc_trim(0)``; per step the
    C allocator's bytes in use, the resident memory and (with ``trace``) the Python side's
    traced bytes. What each step frees is what that part held (GTSAM's C++ included,
    which tracemalloc does not see). Destructive: the daemon is not used afterwards."""
    import gc

    from robotd.floor.index import FloorIndex
    from robotd.graph.model import PoseGraph

    def sample(what: str) -> dict[str, Any]:
        gc.collect()
        rss = trimmed_rss_mb()
        pm = process_memory()
        row = {"what": what, "rss_mb": rss, "malloc_used_mb": pm.get("malloc_used_mb", math.nan),
               "malloc_free_mb": pm.get("malloc_free_mb", math.nan), "RssAnon": pm.get("RssAnon", math.nan)}
        if trace:
            import tracemalloc

            row["traced_mb"] = tracemalloc.get_traced_memory()[0] / 1e6
        return row

    stage = pipeline.stage("graph")
    graph = stage.graph
    rows = [sample("at the end")]
    graph._isam = graph._new_isam()
    graph._cached = None
    rows.append(sample("iSAM2 let go"))
    graph.graph = PoseGraph()
    graph._clear_fold()
    gated = getattr(stage, "gated", None)
    if gated is not None:
        for name in ("update_ms", "_loops", "_travelled", "_stamps", "_edges_into"):
            part = getattr(gated, name, None)
            if isinstance(part, dict):
                part.clear()
            elif part is not None:
                del part[:]
    rows.append(sample("the pose graph and its gate let go"))
    floor = pipeline.stage("floor")
    floor.detector.index = FloorIndex()
    rows.append(sample("the floor index let go"))
    return rows


def _tracing() -> bool:
    import tracemalloc

    return tracemalloc.is_tracing()


def memory_run(args: argparse.Namespace, recording: Path | list[Path], keyframes: int,
               on_sample: Any = None) -> dict[str, Any]:
    """The whole daemon's resident memory as its map grows to ``keyframes`` keyframes.

    The daemon is assembled as for the replay (every stage, the map on disk) and the
    recording's floor frames are fed to it lap after lap, each lap stamped after the
    previous one, until that many keyframes are stored. Given several recordings
    (``--memory-seeds``: the same recording again, or the route driven with other seeds),
    lap ``k`` is the ``k``-th of them (in turn), with its own ground truth, and only every
    third floor frame is fed, on lap ``k`` those whose count is ``k mod 3`` (the virtual
    robot takes its frames at the same places on every drive of a route; so three laps in
    a row have no frame, and no keyframe, at the same place, as a robot's laps do not).
    The virtual floor is drawn from the seed: other seeds are other floors (laps that
    revisit nothing), so laps of the same rooms give the same seed again (``0,0,0``):
    every lap
    sees new frames, as a robot driving its round again does; with one recording every
    lap is that recording again, each query's best candidate a byte-identical image of
    an earlier lap. The keyframe spacing, floor
    describe and query, visual odometry, the pose graph (every later lap revisits: loops
    are declared and closed) and the store run as on the robot. The keyframes' poses come
    from the recorded ground truth (:class:`TruthOdometry`), so the wheel + gyro filter is
    idle here; its history is bounded and is in the replay's figures. Resident memory,
    the floor index's bytes and the CPU are sampled every ``--memory-every`` keyframes
    (``on_sample(samples)`` after each, so a run stopped early keeps what it measured)."""
    import gc

    from drivers.recording.reader import EncodedFrame, RecordingReader
    from robotd.app.assemble import assemble_daemon, open_map
    from robotd.app.notify import Notifier
    from robotd.base.clock import ManualClock
    from robotd.base.messages import Frame

    recordings = [recording] if isinstance(recording, Path) else list(recording)
    truths = [read_truth(rec) for rec in recordings]
    spans = []
    for rec in recordings:
        with RecordingReader(rec) as r:
            spans.append(r.time_range_ns)
    assert all(sp is not None for sp in spans)
    span = (min(sp[0] for sp in spans), max(sp[1] for sp in spans))
    lap_ns = span[1] - span[0] + 40_000_000
    truth = truths[0]
    samples: list[dict[str, float]] = []
    with tempfile.TemporaryDirectory() as tmp:
        cfg = make_config(args, Path(tmp) / "map.sqlite")
        clock = ManualClock(span[0])
        with open_map(cfg, clock=clock) as store:
            daemon = assemble_daemon(cfg, clock, {}, store, Notifier(), lossless=True)
            pipeline = daemon.pipeline
            odo = TruthOdometry(truth, lap_ns)
            pipeline.stage("keyframes").odometry = odo
            floor = pipeline.stage("floor")
            config = {"keyframe_distance_m": cfg.keyframes.distance_m, "mode": cfg.floor_detector.descriptor_mode,
                      "shortlist": cfg.floor_detector.shortlist, "localise_mapped": cfg.pose_graph.localise_mapped,
                      "loop_spacing": pipeline.stage("graph").graph.params.loop_spacing,
                      "loops_per_keyframe": pipeline.stage("graph").graph.params.loops_per_keyframe,
                      "fold": getattr(pipeline.stage("graph").graph.params, "fold", 1),
                      "resident": (floor.detector.index.params.resident
                                   if getattr(floor.detector.index, "on_demand", False) else 0)}
            query_ms: list[float] = []  # each floor query's thread CPU since the last sample
            index_query = floor.detector.index.query

            def timed_query(*a: Any, **kw: Any) -> Any:
                t = time.thread_time()
                try:
                    return index_query(*a, **kw)
                finally:
                    query_ms.append((time.thread_time() - t) * 1e3)

            floor.detector.index.query = timed_query
            gc.collect()
            rss0 = rss_mb()
            if args.memory_trace:
                import tracemalloc

                tracemalloc.start(1)
            t0 = os.times()
            lap, frames, n, c = 0, 0, 0, {}
            next_sample = args.memory_every
            while n < keyframes:
                odo.truth = truths[lap % len(recordings)]
                # laps of new frames: every third frame, lap k those whose count is k mod 3 (the
                # recordings' frames are taken at the same places on every seed): three laps in
                # a row have no frame, and so no keyframe, at the same place
                parity = lap % 3 if len(recordings) > 1 else None
                floor_frames = 0
                with RecordingReader(recordings[lap % len(recordings)]) as r:
                    for _topic, msg in r.messages(only=(Frame,), lazy_images=True):
                        if msg.camera != "floor":
                            continue
                        floor_frames += 1
                        if parity is not None and floor_frames % 3 != parity:
                            continue
                        stamp = msg.stamp_ns + lap * lap_ns
                        frame = (msg.restamped(stamp) if isinstance(msg, EncodedFrame)
                                 else Frame(stamp, msg.camera, msg.image, msg.seq))
                        clock.set_ns(stamp)
                        odo.settled = stamp
                        pipeline.feed(frame)
                        pipeline.poll()
                        frames += 1
                        if frames % 10 == 0:  # keyframes taken: stored, or transient (localise_mapped)
                            c = pipeline.counters()
                            n = c.get("keyframes_stored", 0) + c.get("keyframes_not_stored", 0)
                        if n >= next_sample:
                            t = os.times()
                            pm = process_memory()
                            samples.append({"keyframes": n, "stored": c.get("keyframes_stored", 0),
                                            "rss_mb": rss_mb(), "rss_trimmed_mb": trimmed_rss_mb(), "laps": lap + 1,
                                            **pm, **{f"{k}_trimmed": v for k, v in process_memory().items()},
                                            "index_mb": floor.detector.index.nbytes / 1e6,
                                            "cpu_s": (t.user - t0.user) + (t.system - t0.system),
                                            **graph_memory(pipeline.stage("graph").graph),
                                            **memory_breakdown(floor, _tracing()),
                                            "query_ms_median": statistics.median(query_ms) if query_ms else math.nan,
                                            "query_ms_p99": float(np.quantile(query_ms, 0.99)) if query_ms else math.nan,
                                            "index_loads": int(getattr(floor.detector.index, "loads", 0)),
                                            "index_load_failures": int(getattr(floor.detector.index, "load_failures", 0))})
                            query_ms.clear()
                            s = samples[-1]
                            print(f"memory: {n} keyframes, RSS {s['rss_mb']:.0f} MB ({s['rss_trimmed_mb']:.0f} "
                                  f"trimmed), index {s['index_mb']:.1f} MB (descriptors {s['index_descriptors_mb']:.1f})"
                                  f", SQLite {s['sqlite_mb']:.1f} MB, anon {s.get('RssAnon', math.nan):.0f} MB"
                                  f" file {s.get('RssFile', math.nan):.0f} MB, malloc used "
                                  f"{s.get('malloc_used_mb', math.nan):.0f} free {s.get('malloc_free_mb', math.nan):.0f}"
                                  f" (after trim {s.get('malloc_free_mb_trimmed', math.nan):.0f}) mmap "
                                  f"{s.get('malloc_mmap_mb', math.nan):.0f} MB, graph {s.get('graph_factors', 0)} factors "
                                  f"{s.get('graph_tree_nnz', 0)} nnz, query {s['query_ms_median']:.2f} ms median "
                                  f"({s['index_loads']} descriptors read so far), {s['cpu_s']:.0f} s CPU"
                                  + (f", traced {s['traced_mb']:.1f} MB" if "traced_mb" in s else ""), flush=True)
                            next_sample += args.memory_every
                            if args.memory_trace_from and n >= args.memory_trace_from and not _tracing():
                                import tracemalloc

                                tracemalloc.start(1)  # from here on: what is allocated and stays
                            if on_sample is not None:
                                on_sample({"keyframes_target": keyframes, "laps": lap + 1, "frames": frames,
                                           "rss_before_mb": rss0, "samples": samples, "config": config})
                        if n >= keyframes:
                            break
                lap += 1
            pipeline.finish()
            t1 = os.times()
            c = pipeline.counters()
            gc.collect()
            rss_after = rss_mb()
            out = {"rss_trimmed_after_mb": trimmed_rss_mb(), "keyframes_target": keyframes, "keyframes_stored": int(c.get("keyframes_stored", 0)),
                   "keyframes": int(c.get("keyframes_stored", 0) + c.get("keyframes_not_stored", 0)),
                   "frames": frames, "laps": lap, "rss_before_mb": rss0, "rss_after_mb": rss_after,
                   "peak_rss_mb": peak_rss_mb(), "index_mb": floor.detector.index.nbytes / 1e6,
                   "cpu_s": (t1.user - t0.user) + (t1.system - t0.system),
                   "loop_edges": int(c.get("links_loop", 0)), "samples": samples,
                   "map_file_mb": (Path(tmp) / "map.sqlite").stat().st_size / 1e6, "config": config,
                   "recordings": [str(rec) for rec in recordings]}
            out.update(graph_memory(pipeline.stage("graph").graph))
            out.update(memory_breakdown(floor, _tracing()))
            out.update({k: int(c[k]) for k in ("graph_update_median_us", "graph_update_p99_us", "graph_solve_ms")
                        if k in c})
            out["released"] = release_breakdown(pipeline, _tracing())
            print("memory released at the end, MB (malloc in use, RSS after malloc_trim): "
                  + "; ".join(f"{r['what']} {r['malloc_used_mb']:.1f} {r['rss_mb']:.1f}" for r in out["released"]),
                  flush=True)
        if args.keep_map is not None:
            import shutil

            shutil.copyfile(Path(tmp) / "map.sqlite", args.keep_map)
    return out


def forward_memory_run(args: argparse.Namespace, images: int, forward_dir: Path,
                       on_sample: Any = None) -> dict[str, Any]:
    """The whole daemon's resident memory as its forward detector takes ``images`` images.

    The daemon is assembled with the forward detector on (``robotd run``'s stages, its map
    on disk) and the forward detector of its ``forward`` stage is given the images of
    ``forward_dir`` (a rendered office sequence of ``bench_forward_scale.py``: PNGs and
    ``poses.csv``) lap after lap, each lap changed as ``bench_forward_scale.changed`` does
    (shifted, mirrored on odd laps, brightness changed), with the lap's poses, read from
    disk one at a time (no image kept). Each image is written to the map as the stage
    writes it, under a keyframe row of its own (this drive has no floor keyframes), so
    the detector keeps only its newest images' features in memory and reads older ones
    back when it verifies them, as the daemon does: the detector's memory, the process's
    and the allocator's are sampled every ``--memory-every`` images."""
    import cv2

    from robotd.app.assemble import assemble_daemon, open_map
    from robotd.app.notify import Notifier
    from robotd.base.clock import ManualClock

    try:
        from bench.bench_forward_scale import changed
    except ImportError:  # run as a script: bench/ is on sys.path
        from bench_forward_scale import changed

    files = sorted(forward_dir.glob("*.png"))
    poses = np.loadtxt(forward_dir / "poses.csv", delimiter=",", skiprows=1)[:, 2:5]
    if not files or len(poses) != len(files):
        raise SystemExit(f"{forward_dir}: {len(files)} PNGs and {len(poses)} poses")
    args.forward = True
    samples: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        cfg = make_config(args, Path(tmp) / "map.sqlite")
        clock = ManualClock(0)
        with open_map(cfg, clock=clock) as store:
            daemon = assemble_daemon(cfg, clock, {}, store, Notifier(), lossless=True)
            stage = daemon.pipeline.stage("forward")
            det = stage.detector
            gc.collect()
            rss0 = rss_mb()
            t0 = os.times()
            cov = np.diag([1e-4, 1e-4, 1e-5])
            loops = 0
            for i in range(images):
                lap, j = divmod(i, len(files))
                im = changed(cv2.imread(str(files[j]), cv2.IMREAD_GRAYSCALE), lap, 0)
                d = det.process(im, poses[j], cov)
                loops += d.loop_id is not None
                kid = store.add_keyframe(daemon.run_id, (i + 1) * 10**8, poses[j], cov, None)
                stage._store_image(kid)  # as the stage stores each forward keyframe's image
                if (i + 1) % args.memory_every == 0 or i + 1 == images:
                    t = os.times()
                    pm = process_memory()
                    row = {"images": i + 1, "laps": lap + 1, "rss_mb": rss_mb(), "rss_trimmed_mb": trimmed_rss_mb(),
                           **pm, "loops": loops, "cpu_s": (t.user - t0.user) + (t.system - t0.system),
                           "read_back": det.read_back, "store_errors": stage.store_errors}
                    if hasattr(det, "memory_bytes"):
                        row["detector_bytes"] = det.memory_bytes()
                    samples.append(row)
                    print(f"forward memory: {i + 1} images, RSS {row['rss_mb']:.0f} MB ({row['rss_trimmed_mb']:.0f} "
                          f"trimmed), anon {pm.get('RssAnon', math.nan):.0f} MB, malloc used "
                          f"{pm.get('malloc_used_mb', math.nan):.0f} MB, {loops} loops, {row['cpu_s']:.0f} s CPU",
                          flush=True)
                    if on_sample is not None:
                        on_sample({"images_target": images, "rss_before_mb": rss0, "samples": samples})
    return {"images_target": images, "rss_before_mb": rss0, "samples": samples, "forward_dir": str(forward_dir)}


def query_residency(map_path: Path, sizes: list[int], residents: list[int], queries: int,
                    shortlist: int, exclude_recent_s: float = 20.0, confidence: float = 0.0) -> dict[str, Any]:
    """The floor query's time with the local descriptors in RAM against read back from the
    map (``FloorIndex.from_store``'s loader, ``resident`` of them kept decoded), on a
    map's keyframes queried in the order they were driven.

    The index at each size holds the map's keyframes (``map_path``: a map written by the
    daemon, e.g. ``--memory N --keep-map FILE``) repeated under new ids until it has that
    many (each copy a further pass over the same floor); the last ``queries`` keyframes of
    the map are the queries, in order, each leaving out every copy of the keyframes within
    ``exclude_recent_s`` of it, with the demo's loop threshold as ``min_score``. The
    variants are timed query by query in turn (thread CPU), the same queries for each.
    ``confidence`` > 0: also in RAM and from the map with RANSAC's adaptive stop at that
    confidence (``MatchParams.confidence``, the variants named ``..., ransac C``). Each
    variant's digests: every query's candidates and scores, and its loops' inlier pairs."""
    import robotd.floor.descriptor as fi
    from robotd.app.demo import shipped_calibration
    from robotd.floor.descriptor import decode
    from robotd.floor.index import FloorIndex, IndexParams
    from robotd.floor.match import MatchParams
    from robotd.io.calibfile import read_calibration
    from robotd.io.store import MapStore

    out: dict[str, Any] = {"map": str(map_path), "sizes": [], "ransac_confidence": confidence}
    adaptive = MatchParams(confidence=confidence) if confidence > 0 else None
    tag = f", ransac {confidence:g}"
    with MapStore.open(map_path, read_only=True) as store:
        recs = [r for r in store.keyframes() if r.descriptor is not None]
        mode = int(recs[0].descriptor_mode)
        calib = read_calibration(shipped_calibration())
        min_score = (calib.loop.for_mode(mode) if calib.loop is not None else None) or 0.0
        n0 = len(recs)
        src_ids = np.array([r.id for r in recs], np.int64)
        stamps = np.array([r.stamp_ns for r in recs], np.int64)
        decoded = [decode(r.descriptor) for r in recs]
        out.update({"map_keyframes": n0, "mode": mode, "min_score": min_score, "queries": min(queries, n0)})
        out.update(map_laps(recs, queries, exclude_recent_s))

        def loader(i: int) -> Any:
            if hasattr(store, "keyframe_descriptor"):  # as FloorIndex.from_store reads it back
                blob = store.keyframe_descriptor(int(src_ids[i % n0]))[0]
            else:  # the code before it (a baseline run from an older checkout)
                blob = store.keyframe(int(src_ids[i % n0])).descriptor
            assert blob is not None
            return getattr(fi, "decode_local", decode)(blob)  # in two steps where the code has it

        qrows = list(range(n0 - min(queries, n0), n0))
        tmp = tempfile.TemporaryDirectory()
        big = Path(tmp.name) / "repeated.sqlite"
        kf_ids: list[int] = []
        for n in sorted(sizes):
            kf_of = np.asarray(grow_repeated_map(big, [r.descriptor for r in recs], mode, n, kf_ids),
                               np.int64)  # the map repeated, as the daemon loads it
            mstore = MapStore.open(big, create=False, read_only=True)
            # each setting with the whole shortlist scored (IndexParams.enough off: the code
            # before the query stopped at k candidates reaching min_score), with the resident
            # descriptors scored first (IndexParams.resident_first) and as the default
            variants: dict[str, FloorIndex] = {
                "in RAM, whole shortlist": FloorIndex(IndexParams(shortlist=shortlist, enough=False)),
                "in RAM": FloorIndex(IndexParams(shortlist=shortlist))}
            for r in residents:
                variants[f"read back, {r} resident, whole shortlist"] = FloorIndex(
                    IndexParams(shortlist=shortlist, resident=r, enough=False), loader=loader)
                variants[f"read back, {r} resident, resident first"] = FloorIndex(
                    IndexParams(shortlist=shortlist, resident=r, resident_first=True), loader=loader)
                variants[f"read back, {r} resident"] = FloorIndex(IndexParams(shortlist=shortlist, resident=r),
                                                                  loader=loader)
            if adaptive is not None:
                variants["in RAM" + tag] = FloorIndex(IndexParams(shortlist=shortlist))
            for index in variants.values():
                for i in range(n):
                    index.add(i, decoded[i % n0])
            for r in residents:  # as the daemon holds it: FloorIndex.from_store on the map
                variants[f"from the map, {r} resident"] = FloorIndex.from_store(
                    mstore, mode, IndexParams(shortlist=shortlist, resident=r))
                if adaptive is not None:
                    variants[f"from the map, {r} resident" + tag] = FloorIndex.from_store(
                        mstore, mode, IndexParams(shortlist=shortlist, resident=r))
            ids = np.arange(n)
            ms: dict[str, list[float]] = {k: [] for k in variants}
            loads0 = {k: getattr(v, "loads", 0) for k, v in variants.items()}
            loops = {k: 0 for k in variants}  # candidates at or above min_score: the loops declared
            digest = {k: hashlib.sha256() for k in variants}  # every query's candidates and scores
            loop_digest = {k: hashlib.sha256() for k in variants}  # every loop's inlier pairs
            for q in qrows:
                excluded = ids[np.abs(stamps[ids % n0] - stamps[q]) < int(exclude_recent_s * 1e9)]
                for name, index in variants.items():
                    ex = kf_of[excluded] if name.startswith("from the map") else excluded
                    t0 = time.thread_time()
                    got = index.query(decoded[q], k=5, min_score=min_score, exclude_ids=ex,
                                      **({"match_params": adaptive} if name.endswith(tag) else {}))
                    ms[name].append((time.thread_time() - t0) * 1e3)
                    loops[name] += sum(c.score >= min_score for c in got)
                    back = (lambda kf: int(np.searchsorted(kf_of, kf))) if name.startswith("from the map") else int
                    digest[name].update(repr([(back(c.keyframe_id), c.global_score, c.score) for c in got]).encode())
                    for c in got:
                        if c.score >= min_score:
                            loop_digest[name].update(np.stack([c.local.inliers_a, c.local.inliers_b]).tobytes())
            row: dict[str, Any] = {"keyframes": n, "variants": {},
                                   **pairs_per_query(variants["in RAM"], qrows, decoded, ids, stamps, n0,
                                                     min_score, exclude_recent_s)}
            for name, index in variants.items():
                row["variants"][name] = {"query_ms": {"median": statistics.median(ms[name]),
                                                      "p99": float(np.quantile(ms[name], 0.99))},
                                         "reads_per_query": (index.loads - loads0[name]) / len(qrows),
                                         "loops": loops[name], "candidates_sha256": digest[name].hexdigest(),
                                         "loops_sha256": loop_digest[name].hexdigest(),
                                         "index_mb": index.nbytes / 1e6,
                                         "descriptors_mb": index.descriptors_nbytes / 1e6}
                print(f"residency: {n} keyframes, {name}: query {statistics.median(ms[name]):.2f} ms median, "
                      f"{row['variants'][name]['reads_per_query']:.2f} reads per query, {loops[name]} loops, "
                      f"index {index.nbytes / 1e6:.1f} MB", flush=True)
            print(f"residency: {n} keyframes, per query (in RAM): {row['local_scores_per_query']:.2f} local scores, "
                  f"{row['geometric_checks_per_query']:.2f} checked geometrically", flush=True)
            out["sizes"].append(row)
            del variants
            mstore.close()
        tmp.cleanup()
    return out


def map_laps(recs: list[Any], queries: int, exclude_recent_s: float) -> dict[str, Any]:
    """How a map's last ``queries`` keyframes repeat its earlier ones: the map's distinct
    descriptors, the queries with a byte-identical keyframe outside their ``exclude_recent_s``
    window, and each query's distance to the nearest keyframe there (stored poses, m)."""
    blobs = [r.descriptor for r in recs]
    xy = np.array([(r.x_m, r.y_m) for r in recs])
    stamps = np.array([r.stamp_ns for r in recs], np.int64)
    same, nearest = 0, []
    for q in range(len(recs) - min(queries, len(recs)), len(recs)):
        other = np.flatnonzero(np.abs(stamps - stamps[q]) >= int(exclude_recent_s * 1e9))
        if not len(other):
            continue
        same += any(blobs[i] == blobs[q] for i in other)
        nearest.append(float(np.min(np.hypot(*(xy[other] - xy[q]).T))))
    return {"distinct_descriptors": len(set(blobs)), "queries_with_identical_keyframe": same,
            "nearest_keyframe_m": ({"median": statistics.median(nearest), "max": max(nearest)} if nearest else None)}


def pairs_per_query(index: Any, qrows: list[int], decoded: list[Any], ids: np.ndarray, stamps: np.ndarray,
                    n0: int, min_score: float, exclude_recent_s: float) -> dict[str, float]:
    """The queries of :func:`query_residency` again (untimed) on ``index``, each local score
    counted: pairs scored per query, and those checked geometrically (past the ``min_score``
    bound: a loop, or refused by the geometric check)."""
    from robotd.floor import match

    reasons: collections.Counter[str] = collections.Counter()
    score = match.Matcher.score

    def counted(self: Any, b: Any, min_score: float = 0.0) -> Any:
        r = score(self, b, min_score)
        reasons[str(r.reason)] += 1
        return r

    many = getattr(match.Matcher, "score_many", None)  # the code since the query scores in batches

    def counted_many(self: Any, bs: Any, min_score: float = 0.0) -> Any:
        out = many(self, bs, min_score)  # type: ignore[misc]
        for r in out:
            if isinstance(r, match.MatchResult):
                reasons[str(r.reason)] += 1
        return out

    match.Matcher.score = counted  # type: ignore[method-assign]
    if many is not None:
        match.Matcher.score_many = counted_many  # type: ignore[attr-defined]
    try:
        for q in qrows:
            excluded = ids[np.abs(stamps[ids % n0] - stamps[q]) < int(exclude_recent_s * 1e9)]
            index.query(decoded[q], k=5, min_score=min_score, exclude_ids=excluded)
    finally:
        match.Matcher.score = score  # type: ignore[method-assign]
        if many is not None:
            match.Matcher.score_many = many  # type: ignore[attr-defined]
    dismissed = {str(match.BELOW_MIN_SCORE), str(match.MatchReason.TOO_FEW_MATCHES),
                 str(match.MatchReason.TOO_FEW_FEATURES)}
    total = sum(reasons.values())
    return {"local_scores_per_query": total / len(qrows),
            "geometric_checks_per_query": sum(v for k, v in reasons.items() if k not in dismissed) / len(qrows),
            "local_score_reasons": dict(reasons)}


_LOAD_CHILD = r"""
import ctypes, json, sys, time
import numpy as np
from robotd.floor.descriptor import decode
from robotd.floor.index import FloorIndex
from robotd.io.store import MapStore

def rss():
    with open("/proc/self/status", encoding="ascii") as f:
        return next(int(l.split()[1]) / 1024 for l in f if l.startswith("VmRSS:"))

path, mode, queries, min_score, exclude = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]), int(sys.argv[5])
with MapStore.open(path, create=False, read_only=True) as store:
    ids = [r.id for r in store.keyframes()]
    qblobs = [store.keyframe_descriptor(i)[0] for i in ids[-queries:]]
    rss0 = rss()
    c0, w0 = time.process_time(), time.perf_counter()
    index = FloorIndex.from_store(store, mode)
    c1, w1 = time.process_time(), time.perf_counter()
    rss1 = rss()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:
        pass
    rss1t = rss()
    nbytes, dbytes = index.nbytes, index.descriptors_nbytes
    got, ms = [], []
    for i, b in zip(ids[-queries:], qblobs):
        q = decode(b)
        t0 = time.thread_time()
        cands = index.query(q, k=5, min_score=min_score, exclude_after_id=i - exclude)
        ms.append((time.thread_time() - t0) * 1e3)
        got.append([(c.keyframe_id, c.global_score, c.score) for c in cands])
    print(json.dumps({"load_cpu_s": c1 - c0, "load_wall_s": w1 - w0, "rss_before_mb": rss0, "rss_after_mb": rss1,
                      "rss_after_trim_mb": rss1t, "index_mb": nbytes / 1e6, "descriptors_mb": dbytes / 1e6,
                      "rss_after_queries_mb": rss(), "query_ms_median": float(np.median(ms)), "loads": index.loads,
                      "candidates": got}))
"""


def map_load(map_path: Path, sizes: list[int], trees: dict[str, Path], rounds: int, queries: int,
             exclude: int = 200) -> dict[str, Any]:
    """``FloorIndex.from_store``'s load of a map at each size: CPU and wall time, the
    process's resident memory before and after it (and after ``malloc_trim``), the index's
    bytes, then ``queries`` queries of the map's last keyframes (the loop threshold, the
    ``exclude`` keyframes before each left out) to check that every code tree returns the
    same candidates. Each measurement in a fresh process, the trees (``label -> checkout``)
    alternating round by round, on maps of ``map_path``'s descriptors repeated under new ids."""
    from robotd.app.demo import shipped_calibration
    from robotd.io.calibfile import read_calibration
    from robotd.io.store import MapStore

    with MapStore.open(map_path, create=False, read_only=True) as store:
        recs = [(r.descriptor, int(r.descriptor_mode)) for r in store.keyframes() if r.descriptor is not None]
    mode = recs[0][1]
    calib = read_calibration(shipped_calibration())
    min_score = (calib.loop.for_mode(mode) if calib.loop is not None else None) or 0.0
    out: dict[str, Any] = {"map": str(map_path), "map_keyframes": len(recs), "mode": mode, "rounds": rounds,
                           "queries": queries, "trees": {k: str(v) for k, v in trees.items()}, "sizes": []}
    with tempfile.TemporaryDirectory() as tmp:
        for n in sorted(sizes):
            path = Path(tmp) / f"map-{n}.sqlite"
            with MapStore.open(path, synchronous="NORMAL") as store:
                run = store.begin_run("", started_ns=0)
                for i in range(n):
                    blob, m = recs[i % len(recs)]
                    store.add_keyframe(run, i, (0.0, 0.0, 0.0), np.eye(3), None, blob, m)
            runs: dict[str, list[dict[str, Any]]] = {k: [] for k in trees}
            for r in range(rounds):
                for label, tree in (list(trees.items()) if r % 2 == 0 else list(trees.items())[::-1]):
                    res = subprocess.run([sys.executable, "-c", _LOAD_CHILD, str(path), str(mode), str(queries),
                                          repr(min_score), str(exclude)], check=True, capture_output=True, cwd=tree,
                                         text=True, env={**os.environ, "PYTHONPATH": str(tree)})
                    runs[label].append(json.loads(res.stdout.strip().splitlines()[-1]))
                    x = runs[label][-1]
                    print(f"load: {n} keyframes, {label}: {x['load_cpu_s']:.2f} s CPU, RSS {x['rss_before_mb']:.0f}"
                          f" -> {x['rss_after_mb']:.0f} MB ({x['rss_after_trim_mb']:.0f} trimmed), index "
                          f"{x['index_mb']:.1f} MB", flush=True)
            first = next(iter(runs.values()))[0]["candidates"]
            same = all(x["candidates"] == first for v in runs.values() for x in v)
            row: dict[str, Any] = {"keyframes": n, "same_candidates": same, "trees": {}}
            for label, v in runs.items():
                row["trees"][label] = {k: [x[k] for x in v] for k in v[0] if k != "candidates"}
            out["sizes"].append(row)
    return out


def _load_section(p: dict[str, Any]) -> list[str]:
    """A ``--load`` payload's section of the memory page."""
    r, m = p["load"], p["machine"]
    labels = list(r["trees"])
    lines = _section_head(p.get("label") or "The map's load (`FloorIndex.from_store`)", m) + [
        f"`--load`: the {r['map_keyframes']} keyframes of `{r['map']}` (mode {r['mode']}) repeated to each "
        f"size in a map; `FloorIndex.from_store` (the daemon's index, descriptors read back) run in a fresh "
        f"process, {r['rounds']} rounds alternating " + " and ".join(f"{k} (`{v}`)" for k, v in r["trees"].items())
        + f"; medians over the rounds. Resident memory of the process before the load and after it; then "
        f"{r['queries']} queries of the map's last keyframes with the loop threshold, whose candidates and "
        "scores are compared across every run.", "",
        "| keyframes | code | load CPU s | load wall s | RSS before MB | RSS after MB | growth MB | after malloc_trim MB "
        "| index MB | of it descriptors MB | query ms median | same candidates |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    med = statistics.median
    for row in r["sizes"]:
        for label in labels:
            t = row["trees"][label]
            growth = [a - b for a, b in zip(t["rss_after_mb"], t["rss_before_mb"])]
            lines.append(f"| {row['keyframes']} | {label} | {med(t['load_cpu_s']):.3f} | {med(t['load_wall_s']):.3f} | "
                         f"{med(t['rss_before_mb']):.1f} | {med(t['rss_after_mb']):.1f} | {med(growth):.1f} | "
                         f"{med(t['rss_after_trim_mb']):.1f} | {med(t['index_mb']):.1f} | {med(t['descriptors_mb']):.1f} | "
                         f"{med(t['query_ms_median']):.2f} | {'yes' if row['same_candidates'] else 'no'} |")
    return lines


def memory_markdown(*payloads: dict[str, Any]) -> str:
    """``docs/benchmarks/daemon-memory.md`` from ``--memory`` JSON payloads (a section each)."""
    lines = ["# The whole daemon's memory as its map grows (`bench/bench_daemon.py --memory N`)", "",
             "Generated by `bench/bench_daemon.py --memory-page JSON... --doc FILE` from the JSON files",
             "beside it; see `memory_run` in the script. The daemon is assembled as `robotd replay`",
             "assembles it and the recorded drive's floor frames are fed to it lap after lap (each lap a",
             "revisit: loops are declared and closed, or, with `localise_mapped`, the keyframes over",
             "mapped ground are matched and not stored), with the keyframe poses from the recorded",
             "ground truth."]
    for p in payloads:
        lines += [""] + (_residency_section(p) if "residency" in p else
                         _residency_maps_section(p) if "residency_maps" in p else
                         _load_section(p) if "load" in p else
                         _forward_section(p) if "forward_memory" in p else
                         _scale_section(p) if "scale" in p and "memory" not in p else _memory_section(p))
    return "\n".join(lines) + "\n"


def _recordings(value: str | list[str]) -> str:
    """The run's recording(s) for a page, each distinct one once (older JSON holds a list of
    paths printed as one string)."""
    if isinstance(value, str) and value.startswith("[") and "Path(" in value:
        value = re.findall(r"Path\('([^']*)'\)", value)
    paths = [value] if isinstance(value, str) else value
    return ", ".join(f"`{path}`" for path in dict.fromkeys(paths))


def _section_head(title: str, m: dict[str, Any]) -> list[str]:
    """A memory page section's first lines: its title and the machine it ran on."""
    return [f"## {title}", "",
            f"Machine: {m['platform']}, {m['cpu_count']} CPUs, Python {m['python']}, numpy {m['numpy']}."]


def _scale_section(p: dict[str, Any]) -> list[str]:
    """A ``--scale-only`` payload's section of the memory page: the floor query of
    ``./dev bench daemon`` in RAM and on the daemon's index (descriptors read back)."""
    sc, m = p["scale"], p["machine"]
    lines = _section_head(p.get('label') or 'The floor query at 1,000 and 10,000 keyframes, as the daemon holds them',
                          m) + [
             f"`--scale-only` on `{p['recording']}`: the recording's frames described (and turned or mirrored "
             "copies, repeated beyond the distinct ones), the drive's own frames queried with the loop threshold, "
             "the 20 s around each left out; each query timed (thread CPU) on an index with every descriptor in "
             "RAM and then on the daemon's (the 1024 most recently used decoded, the others decoded again when "
             "shortlisted)" + (", decoded from their bytes (\"read back\") and as `FloorIndex.from_store` holds "
                               "them, read from a map of the same descriptors (\"from the map\")."
                               if any("query_from_map_ms" in row for row in sc["sizes"]) else "."), ""]
    lines += _scale_table(sc)
    return lines


def _scale_table(sc: dict[str, Any]) -> list[str]:
    """The scale part's tables: query times by index, and where the time goes by part."""
    from_map = any("query_from_map_ms" in row for row in sc["sizes"])
    held = any("index_mb" in row.get("query_from_map_ms", {}) for row in sc["sizes"])
    lines = ["| keyframes | of them distinct | in RAM, median ms | p99 | as the daemon, median ms | p99 | "
             "against in RAM | descriptors read back per query |"
             + (" from the map, median ms | p99 | against in RAM | reads per query | same candidates |"
                if from_map else "") + (" from the map, index MB after the queries |" if held else ""),
             "|---:|---:|---:|---:|---:|---:|---:|---:|" + ("---:|---:|---:|---:|---|" if from_map else "")
             + ("---:|" if held else "")]
    for row in sc["sizes"]:
        q, rb, fm = row["query_ms"], row.get("query_read_back_ms"), row.get("query_from_map_ms")
        if rb is None:
            continue
        line = (f"| {row['keyframes']} | {row.get('distinct', row['keyframes'])} | {q['median']:.2f} | "
                f"{q['p99']:.2f} | {rb['median']:.2f} | {rb['p99']:.2f} | {rb['median'] / q['median']:.2f} | "
                f"{rb['reads_per_query']:.1f} |")
        if from_map:
            line += (f" {fm['median']:.2f} | {fm['p99']:.2f} | {fm['median'] / q['median']:.2f} | "
                     f"{fm['reads_per_query']:.1f} | {'yes' if row.get('same_candidates') else 'no'} |"
                     if fm else " - | - | - | - | - |")
        if held:
            line += f" {fm['index_mb']:.1f} |" if fm and "index_mb" in fm else " - |"
        lines.append(line)
    return lines + _parts_table(sc)


def _parts_table(sc: dict[str, Any]) -> list[str]:
    """Where the scale part's queries spend their time, by index and part (empty for a run without it)."""
    lines: list[str] = []
    if any("parts_ms" in row for row in sc["sizes"]):
        lines += ["", "Where a query's time goes (a second pass on indexes built afresh, each part timed; CPU ms "
                      "per query, mean): the shortlist (global scan and ranking), the map's read, the decode, the "
                      "local score (with the query side's preparation) and the rest (candidates, the resident set, "
                      "the timers themselves).", "",
                  "| keyframes | index | shortlist | read | decode | local score | other | total |",
                  "|---:|---|---:|---:|---:|---:|---:|---:|"]
        for row in sc["sizes"]:
            for name, v in row.get("parts_ms", {}).items():
                lines.append(f"| {row['keyframes']} | {name} | {v['shortlist']:.2f} | {v['read']:.2f} | "
                             f"{v['decode']:.2f} | {v['local score']:.2f} | {v['other']:.2f} | {v['total']:.2f} |")
    return lines


def _forward_section(p: dict[str, Any]) -> list[str]:
    """A ``--forward-memory`` payload's section of the memory page."""
    r, m = p["forward_memory"], p["machine"]
    lines = _section_head(p.get('label') or 'The forward detector on: the whole daemon as its forward memory grows',
                          m) + [
             f"`--forward-memory`: the daemon assembled with the forward detector on, its detector given the "
             f"images of `{r.get('forward_dir', '?')}` lap after lap (each lap changed), target "
             f"{r['images_target']} images; the floor stages idle. Before the first image: "
             f"{r['rss_before_mb']:.0f} MB." + (
                 " Each image is written to the map as the stage writes it, and the detector keeps the "
                 "features of its newest images only, reading older ones back when it verifies them "
                 "(`read back`: images read back so far)." if any("read_back" in row for row in r["samples"])
                 else " The images were not written to the map: every image's features stayed in memory."), "",
             "| images | laps | process RSS MB | after malloc_trim MB | RSS anonymous | malloc in use | "
             "the detector's own MB | loops | read back | CPU s so far |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in r["samples"]:
        own = row.get("detector_bytes")
        own_mb = f"{sum(own.values()) / 1e6:.1f}" if isinstance(own, dict) else "-"
        lines.append(f"| {row['images']} | {row['laps']} | {row['rss_mb']:.0f} | {row['rss_trimmed_mb']:.0f} | "
                     f"{row.get('RssAnon', math.nan):.0f} | {row.get('malloc_used_mb', math.nan):.0f} | {own_mb} | "
                     f"{row['loops']} | {row.get('read_back', '-')} | {row['cpu_s']:.0f} |")
    last = r["samples"][-1]["images"] if r["samples"] else 0
    if last < r["images_target"]:
        lines += ["", f"The run was stopped at {last} images, before its target of {r['images_target']}."]
    return lines


def _residency_section(p: dict[str, Any]) -> list[str]:
    """A ``--residency`` payload's section of the memory page."""
    r, m = p["residency"], p["machine"]
    lines = _section_head(p.get('label') or 'The floor query with its descriptors read back from the map', m) + [
             f"`--residency`: the {r['map_keyframes']} keyframes of `{r['map']}` (mode {r['mode']}) repeated to "
             f"each size, its last {r['queries']} keyframes queried in the order driven; thread CPU, the "
             "variants in turn query by query.", "",
             "The ratio is against the descriptors in RAM with the whole shortlist scored where the run has "
             "that variant; \"whole shortlist\": `IndexParams.enough` off (every shortlisted keyframe "
             "scored), otherwise a query stops once 5 candidates reach the loop threshold; \"resident "
             "first\": `IndexParams.resident_first` on (the resident descriptors scored first), otherwise "
             "the shortlist in order of global similarity; \"ransac C\": RANSAC's adaptive stop at "
             "confidence C (`MatchParams.confidence`). Loops: the candidates at or above the threshold "
             "over all the queries; digests (first 8 hex digits): every query's candidates and scores, "
             "and every loop's inlier pairs.", "",
             "| keyframes | descriptors | query ms median | p99 | against in RAM | reads per query | loops | "
             "candidates digest | loops digest | index MB |",
             "|---:|---|---:|---:|---:|---:|---:|---|---|---:|"]
    for row in r["sizes"]:
        base = row["variants"].get("in RAM, whole shortlist", row["variants"]["in RAM"])["query_ms"]["median"]
        for name, v in row["variants"].items():
            q = v["query_ms"]
            lines.append(f"| {row['keyframes']} | {name} | {q['median']:.2f} | {q['p99']:.2f} | "
                         f"{q['median'] / base:.2f} | {v['reads_per_query']:.2f} | {v.get('loops', '-')} | "
                         f"{v.get('candidates_sha256', '-')[:8]} | {v.get('loops_sha256', '-')[:8]} | "
                         f"{v['index_mb']:.1f} |")
    return lines


def _residency_maps_section(p: dict[str, Any]) -> list[str]:
    """A ``--residency`` payload of several maps: each map's floor query as the daemon holds
    it (from the map) and in RAM, round by round, and the medians' ratio to the first map's."""
    runs, m = p["residency_maps"], p["machine"]
    labels = list(dict.fromkeys(r["label"] for r in runs))
    lines = _section_head(p.get("label") or "The floor query on several maps, in turn", m)
    lines += ["", "`--residency` of several maps in the same run: each map's keyframes repeated to each "
              "size, its last keyframes queried in the order driven, the maps in turn, round after round "
              "(thread CPU). \"From the map\": `FloorIndex.from_store` on the map, as the daemon holds it; "
              "loops: candidates at or above the loop threshold per query; local scores and geometric "
              "checks per query counted on the in-RAM index (the same candidates).", "",
              "| map | keyframes in the map | distinct descriptors | queries with a byte-identical keyframe | "
              "nearest other keyframe, median / max m |", "|---|---:|---:|---:|---|"]
    for label in labels:
        r = next(x for x in runs if x["label"] == label)
        near = r.get("nearest_keyframe_m") or {}
        lines.append(f"| {label} | {r['map_keyframes']} | {r.get('distinct_descriptors', '-')} | "
                     f"{r.get('queries_with_identical_keyframe', '-')} of {r['queries']} | "
                     f"{near.get('median', math.nan):.3f} / {near.get('max', math.nan):.3f} |")
    lines += ["", "| keyframes | map | round | load | from the map, ms median | in RAM, ms median | "
              f"from the map / {labels[0]}'s | loops per query | local scores per query | "
              "geometric checks per query |", "|---:|---|---:|---|---:|---:|---:|---:|---:|---:|"]
    sizes = sorted({row["keyframes"] for r in runs for row in r["sizes"]})

    def from_map(row: dict[str, Any]) -> dict[str, Any]:
        return next(v for k, v in row["variants"].items() if k.startswith("from the map"))

    for n in sizes:
        for r in runs:
            row = next(x for x in r["sizes"] if x["keyframes"] == n)
            first = next(x for x in runs if x["label"] == labels[0] and x["round"] == r["round"])
            base = from_map(next(x for x in first["sizes"] if x["keyframes"] == n))["query_ms"]["median"]
            fm = from_map(row)
            lines.append(f"| {n} | {r['label']} | {r['round']} | {r['load_average'][0]:.1f} | "
                         f"{fm['query_ms']['median']:.2f} | {row['variants']['in RAM']['query_ms']['median']:.2f} | "
                         f"{fm['query_ms']['median'] / base:.2f} | {fm['loops'] / r['queries']:.2f} | "
                         f"{row.get('local_scores_per_query', math.nan):.2f} | "
                         f"{row.get('geometric_checks_per_query', math.nan):.2f} |")
        for label in labels:
            med = statistics.median(from_map(next(x for x in r["sizes"] if x["keyframes"] == n))["query_ms"]["median"]
                                    for r in runs if r["label"] == label)
            lines.append(f"| {n} | {label} | median of the rounds | | **{med:.2f}** | | | | | |")
    return lines


def _labelled(arg: str) -> dict[str, Any]:
    """A ``--memory-page`` argument, ``FILE`` or ``LABEL=FILE``: the JSON payload, with
    the label (shown in its section's heading) if given."""
    label, sep, path = arg.partition("=")
    payload = json.loads(Path(path if sep else arg).read_text(encoding="utf-8"))
    if sep:
        payload["label"] = label
    return payload


def _memory_section(p: dict[str, Any]) -> list[str]:
    r, m = p["memory"], p["machine"]
    c = r["config"]
    setting = "localise_mapped on" if c.get("localise_mapped") else "every keyframe stored (the code's default)"
    if not c.get("localise_mapped") and any("graph_loops" in row for row in r["samples"]):
        thinned = c.get("loop_spacing", 0) or any("graph_held_loops" in row for row in r["samples"])
        setting += (f", the pose graph's loops thinned (loop_spacing {c.get('loop_spacing', 10)}, loops_per_keyframe "
                    f"{c.get('loops_per_keyframe', 2)})" if thinned else ", every loop in the pose graph")
    if p.get("label"):
        setting = f"{p['label']}: {setting}"
    if c.get("fold", 1) > 1:
        setting += f", iSAM2's keyframes folded after each full solve (fold {c['fold']})"
    if c.get("resident"):
        setting += f", floor descriptors read back from the map ({c['resident']} kept decoded)"
    lines = _section_head(setting, m) + [
             f"Recording: {_recordings(p['recording'])}, {r['laps']} laps; spacing "
             f"{c['keyframe_distance_m'] * 100:g} cm, mode {c['mode']}, shortlist {c['shortlist']}"
             f"{', localise_mapped' if c.get('localise_mapped') else ''}.", "",
             "| keyframes | of them stored | process RSS MB | after malloc_trim MB | of it the floor index MB "
             "| laps | CPU s so far | graph loops in / left out | iSAM2 factors (keyframes folded) "
             "| floor query ms median (descriptors read) |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in r["samples"]:
        trimmed = f"{row['rss_trimmed_mb']:.0f}" if "rss_trimmed_mb" in row else "-"
        graph = f"{row['graph_loops']} / {row.get('graph_held_loops', 0)}" if "graph_loops" in row else "-"
        isam = (f"{row['graph_factors']}" + (f" ({row['graph_folded']})" if "graph_folded" in row else "")
                if "graph_factors" in row else "-")
        query = (f"{row['query_ms_median']:.1f} ({row.get('index_loads', 0)})"
                 if not math.isnan(row.get("query_ms_median", math.nan)) else "-")
        lines.append(f"| {row['keyframes']} | {row.get('stored', row['keyframes'])} | {row['rss_mb']:.0f} | "
                     f"{trimmed} | {row['index_mb']:.1f} | {row['laps']} | {row['cpu_s']:.0f} | {graph} | "
                     f"{isam} | {query} |")
    if any("malloc_used_mb" in row for row in r["samples"]):
        lines += ["", "Where the resident memory is (`/proc/self/status` and glibc's `mallinfo2`, MB): anonymous "
                      "(the heap, mappings, Python's own arenas) and file-backed (the libraries' pages); of the C "
                      "allocator's heap, the bytes in use (live allocations: GTSAM's C++, numpy's arrays, Python's "
                      "objects over 512 bytes, SQLite) and the bytes it holds free, before and after "
                      "`malloc_trim(0)` (the trim hands the free pages back, so RSS falls, but leaves them counted "
                      "free), and its own mappings (arrays above its threshold).", "",
                  "| keyframes | RSS anonymous | RSS file | malloc in use | malloc free (after the trim) | malloc mmap "
                  "| SQLite | iSAM2 factors | Bayes tree entries |",
                  "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for row in r["samples"]:
            if "malloc_used_mb" not in row:
                continue
            lines.append(f"| {row['keyframes']} | {row.get('RssAnon', math.nan):.0f} | "
                         f"{row.get('RssFile', math.nan):.0f} | {row['malloc_used_mb']:.0f} | "
                         f"{row.get('malloc_free_mb', math.nan):.0f} ({row.get('malloc_free_mb_trimmed', math.nan):.0f})"
                         f" | {row.get('malloc_mmap_mb', math.nan):.0f} | {row.get('sqlite_mb', math.nan):.1f} | "
                         f"{row.get('graph_factors', '-')} | {row.get('graph_tree_nnz', '-')} |")
    if r.get("released"):
        lines += ["", "Attribution by removal at the end of the run (each part let go in turn, then a "
                      "collection and `malloc_trim`): " + "; ".join(
                          f"{x['what']}: malloc in use {x['malloc_used_mb']:.1f} MB, RSS {x['rss_mb']:.1f} MB"
                          for x in r["released"]) + "."]
    before = ("" if r.get("rss_before_mb") is None else
              f"Before the first frame: {r['rss_before_mb']:.0f} MB (the daemon assembled, its map open). ")
    if "rss_after_mb" not in r:  # the partial JSON of a run stopped before its target
        last = r["samples"][-1] if r["samples"] else {"keyframes": 0}
        lines += ["", f"{before}The run was stopped at {last['keyframes']} keyframes, before its target of "
                      f"{r['keyframes_target']}."]
        return lines
    lines += ["", f"{before}"
                  f"After {r['keyframes']} keyframes ({r.get('keyframes_stored', r['keyframes'])} stored): "
                  f"{r['rss_after_mb']:.0f} MB resident ({r.get('rss_trimmed_after_mb', math.nan):.0f} MB "
                  f"after malloc_trim), peak "
                  f"{r['peak_rss_mb']:.0f} MB; the map file {r['map_file_mb']:.0f} MB; {r['loop_edges']} loop edges."]
    if "graph_loops" in r:
        lines[-1] += (f" The pose graph: {r['graph_loops']} loop edges in it, {r.get('graph_held_loops', 0)} left out"
                      f" (in the map only); its Bayes tree {r['graph_cliques']} cliques, {r['graph_tree_nnz']} "
                      f"conditional entries; an update {r.get('graph_update_median_us', 0) / 1e3:.1f} ms median, "
                      f"{r.get('graph_update_p99_us', 0) / 1e3:.1f} ms p99; the last full solve "
                      f"{r.get('graph_solve_ms', 0) / 1e3:.1f} s.")
    return lines


# ------------------------------------------------------------------------------ main


def markdown(p: dict[str, Any]) -> str:
    """``docs/benchmarks/daemon.md`` from the JSON payload."""
    r, m = p["replay"], p["machine"]
    load = p.get("load_average")
    lines = ["# The whole daemon on a recorded drive (`./dev bench daemon`)", "",
             "Generated from `daemon.json` by `bench/bench_daemon.py --doc`; see the script's docstring for",
             "what is measured. Timings are CPU seconds of this machine's cores (a Raspberry Pi 4/5 core",
             "is 2-3x slower), under whatever else ran at the time: compare ratios within one run.", "",
             f"Machine: {m['platform']}, {m['cpu_count']} CPUs, Python {m['python']}, numpy {m['numpy']}"
             + (f"; load average {load['start']} at the start, {load['end']} at the end." if load else "."),
             f"Recording: `{p['recording']}`: {r['robot_s']:.1f} s of robot time, "
             f"{p['judge']['distance_m']:.1f} m, {r['keyframes']} keyframes "
             f"(spacing {r['config']['keyframe_distance_m'] * 100:g} cm, mode {r['config']['mode']}, "
             f"shortlist {r['config']['shortlist']}, forward detector "
             f"{'on' if r['config']['forward'] else 'off'}).", "",
             "| stage | CPU s | CPU s per robot s | CPU s per metre |", "|---|---:|---:|---:|"]
    dist = p["judge"]["distance_m"]
    for name, s in r["stage_cpu_s"].items():
        lines.append(f"| {name} | {s:.2f} | {s / r['robot_s']:.4f} | {s / dist:.4f} |")
    lines.append(f"| **whole process** (user {r['user_s']:.1f} + system {r['system_s']:.1f}) | "
                 f"**{r['process_cpu_s']:.2f}** | **{r['process_cpu_s'] / r['robot_s']:.3f}** | "
                 f"**{r['process_cpu_s'] / dist:.3f}** |")
    b = p.get("baseline")
    lines += ["", "Per keyframe (CPU ms of the pipeline thread):", "",
              "| | median | p99 |", "|---|---:|---:|",
              f"| everything a keyframe causes | {r['keyframe_ms']['median']:.1f} | {r['keyframe_ms']['p99']:.1f} |",
              f"| floor describe (alone) | {r['describe_ms']['median']:.2f} | {r['describe_ms']['p99']:.2f} |",
              f"| floor query (alone) | {r['query_ms']['median']:.2f} | {r['query_ms']['p99']:.2f} |"]
    if b:
        lines += [f"| baseline: ORB extraction (500) | {b['orb_extract_ms']['median']:.2f} | "
                  f"{b['orb_extract_ms']['p99']:.2f} |",
                  f"| baseline: ORB brute-force Hamming + RANSAC against the shortlist | "
                  f"{b['orb_match_shortlist_ms']['median']:.2f} | {b['orb_match_shortlist_ms']['p99']:.2f} |"]
        if b.get("describe_default_ms"):
            lines += ["", "The same keyframe images described outside the pipeline, interleaved with ORB's extraction "
                          "(CPU ms):", "", "| | median | p99 |", "|---|---:|---:|"]
            for key, label in (("describe_default_ms", "floor describe, default"),
                               ("describe_full_resolution_ms", "floor describe, `FULL_RESOLUTION` (selectable)"),
                               ("describe_quarter_ms", "floor describe, `QUARTER` (selectable)"),
                               ("orb_extract_ms", "ORB extraction (500)")):
                if key not in b:  # a run before QUARTER
                    continue
                lines.append(f"| {label} | {b[key]['median']:.2f} | {b[key]['p99']:.2f} |")
    j = p["judge"]
    ate = j["ate_loop_corrected_m"]
    lines += ["", f"Resident memory: {r['rss_after_mb']:.0f} MB after the replay, peak {r['peak_rss_mb']:.0f} MB "
                  f"(the process before the replay: {r['rss_before_mb']:.0f} MB).", "",
              f"Found: {j['loop_edges']} loop edges, {j['loop_edges_true']} truly overlapping (J >= 0.33), "
              f"{j['loop_edges_false']} not; {j['revisits_closed']} of {j['revisits']} revisiting keyframes "
              f"closed by a loop edge; APE RMS of the keyframes (anchored at the first): odometry {j['ate_odometry_m'] * 1e3:.1f} mm, "
              f"loop-corrected {ate * 1e3:.1f} mm." if ate is not None else "loop-corrected: none."]
    s = p.get("scale")
    if s:
        lines += ["", f"Floor index at larger maps (frames of the recording and their turned and mirrored "
                      f"copies; describe median {s['describe_ms']['median']:.2f} ms, p99 "
                      f"{s['describe_ms']['p99']:.2f} ms over {s['describe_ms']['n']} images):", "",
                  "| keyframes | of them distinct | query median ms | query p99 ms | as the daemon: read back, "
                  "median ms (reads per query) | from the map, median ms | index MB | process RSS MB |",
                  "|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for row in s["sizes"]:
            rb, fm = row.get("query_read_back_ms"), row.get("query_from_map_ms")
            lines.append(f"| {row['keyframes']} | {row.get('distinct', row['keyframes'])} | "
                         f"{row['query_ms']['median']:.2f} | {row['query_ms']['p99']:.2f} | "
                         + (f"{rb['median']:.2f} ({rb['reads_per_query']:.1f}) | " if rb else "- | ")
                         + (f"{fm['median']:.2f} | " if fm else "- | ")
                         + f"{row['index_mb']:.1f} | {row['rss_mb']:.0f} |")
        if any("parts_ms" in row for row in s["sizes"]):
            lines += _parts_table(s)
    return "\n".join(lines) + "\n"


def comparison(paths: list[Path]) -> str:
    """A markdown table of several runs' JSON (e.g. a keyframe-spacing sweep), one row each."""
    lines = ["# The whole daemon at several settings (`bench/bench_daemon.py --compare`)", "",
             "Generated from the JSON files named in the first column; each row is a separate run",
             "(on a shared machine: read CPU to within about 20 %). Loop edges are judged by the",
             "ground-truth footprint overlap J; a revisiting keyframe has a truly overlapping",
             "keyframe older than 20 s and is closed when it got a loop edge; APE is the RMS position",
             "error of the stored keyframes, anchored at the first (evo --align_origin).", "",
             "| run | spacing, shortlist | keyframes stored | CPU s | per robot s | per metre | "
             "per keyframe median / p99 (ms) | query median (ms) | loop edges | J < 0.33 | revisits closed | "
             "APE anchored, loop-corrected / odometry (mm) | RSS after (MB) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for path in paths:
        p = json.loads(Path(path).read_text(encoding="utf-8"))
        r, j, c = p["replay"], p["judge"], p["replay"]["config"]
        setting = f"{c['keyframe_distance_m'] * 100:g} cm, {c['shortlist']}"
        if c.get("localise_mapped"):
            setting += ", localise_mapped"
        ate = j["ate_loop_corrected_m"]
        lines.append(
            f"| {Path(path).name} | {setting} | {j['keyframes']} | {r['process_cpu_s']:.1f} | "
            f"{r['process_cpu_s'] / r['robot_s']:.3f} | {r['process_cpu_s'] / j['distance_m']:.2f} | "
            f"{r['keyframe_ms']['median']:.1f} / {r['keyframe_ms']['p99']:.1f} | {r['query_ms']['median']:.1f} | "
            f"{j['loop_edges']} | {j['loop_edges_false']} | {j['revisits_closed']} / {j['revisits']} | "
            f"{'-' if ate is None else f'{ate * 1e3:.1f}'} / {j['ate_odometry_m'] * 1e3:.1f} | "
            f"{r['rss_after_mb']:.0f} |")
    return "\n".join(lines) + "\n"


def stage_comparison(args: list[str]) -> str:
    """A markdown page of runs of two or more trees alternated (``LABEL=JSON ...``, e.g.
    the code before and after a change, each run a separate process): each run's CPU by
    stage, then the mean of each label's runs and its ratio to the first label's."""
    runs = []
    for arg in args:
        label, sep, path = arg.partition("=")
        if not sep:
            label, path = "", arg
        runs.append((label, Path(path).name, json.loads(Path(path).read_text(encoding="utf-8"))))
    rows = ("input (replay, queues, main loop)", "keyframes", "store", "odometry", "floor describe",
            "floor query", "visual odometry", "pose graph")
    machine = runs[0][2].get("machine", {})
    lines = ["# The whole daemon, trees alternated (`bench/bench_daemon.py --compare-stages`)", "",
             "Generated from the JSON files named in the table; each row is a run in a process of its",
             f"own, the labels' runs alternated on one machine ({machine.get('platform', '?')}), so read",
             "the ratio of the means, not absolute figures. CPU seconds over the whole replay",
             "(`--no-baseline --scale=`); \"input\" is the process's CPU less the stages' (the",
             "recording's reading and decoding in the source thread, the queues, the main loop, and",
             "any thread of a library's own, such as OpenCV's worker). Each JSON names its tree's",
             "commit.", "",
             "| label | run | load (1 min) | " + " | ".join(rows) + " | whole process | per robot s |",
             "|---|---|---:|" + "---:|" * (len(rows) + 2)]
    sums: dict[str, list[list[float]]] = collections.defaultdict(list)
    for label, name, p in runs:
        r = p["replay"]
        values = [r["stage_cpu_s"][k] for k in rows] + [r["process_cpu_s"], r["process_cpu_s"] / r["robot_s"]]
        sums[label].append(values)
        load = p.get("load_average", {})
        first = load.get("start", [None])[0] if isinstance(load, dict) else None
        lines.append(f"| {label} | {name} | {'-' if first is None else f'{first:.1f}'} | "
                     + " | ".join(f"{v:.3f}" for v in values) + " |")
    lines += ["", "| label | runs | " + " | ".join(rows) + " | whole process | per robot s |",
              "|---|---:|" + "---:|" * (len(rows) + 2)]
    base = None
    for label, vals in sums.items():
        mean = [statistics.mean(col) for col in zip(*vals)]
        base = base or mean
        lines.append(f"| {label} | {len(vals)} | " + " | ".join(
            f"{m:.3f}" + ("" if m is base[i] else f" ({m / base[i]:.2f}x)" if base[i] else "")
            for i, m in enumerate(mean)) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recording", type=Path, default=None, help="replay this MCAP instead of the cached drive")
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "robotd-bench",
                    help="where the recorded drive is kept (default ~/.cache/robotd-bench)")
    ap.add_argument("--route", default="office")
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of the route (default 60)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--full", action="store_true", help="the whole route, and the index at 1,000 and 10,000 keyframes")
    ap.add_argument("--forward", action="store_true", help="forward detector on (records with a forward camera)")
    ap.add_argument("--keyframe-distance", type=float, default=None, metavar="M",
                    help="[keyframes] distance_m (default: the config's)")
    ap.add_argument("--shortlist", type=int, default=None, help="[floor_detector] shortlist (default: the config's)")
    ap.add_argument("--candidates", type=int, default=None,
                    help="[floor_detector] candidates, the loops a query stops at (default: the config's)")
    ap.add_argument("--localise-mapped", action="store_true", help="[pose_graph] localise_mapped = true")
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--keep-map", type=Path, default=None, metavar="FILE",
                    help="copy the replay's map here (for further analysis)")
    ap.add_argument("--scale", default="1000,10000", help="index sizes to time queries at, comma-separated "
                                                         "(default 1000,10000; '' for none)")
    ap.add_argument("--distinct", type=int, default=1000,
                    help="images described for the index-scale maps (default 1000; --full: 10000)")
    ap.add_argument("--scale-only", action="store_true",
                    help="only the index at larger maps (--scale), without the replay (writes NAME-scale.json)")
    ap.add_argument("--queries", type=int, default=100, help="queries per index size (default 100)")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results")
    ap.add_argument("--name", default="daemon", help="JSON file name (default daemon)")
    ap.add_argument("--doc", type=Path, default=None, help="also write the markdown page here")
    ap.add_argument("--compare", type=Path, nargs="+", default=None, metavar="JSON",
                    help="only print a markdown table comparing these runs' JSON (to --doc if given)")
    ap.add_argument("--memory", type=int, default=0, metavar="N",
                    help="only the memory part: the whole daemon fed until N keyframes are stored "
                         "(writes NAME-memory.json; --doc writes its page)")
    ap.add_argument("--memory-seeds", default=None, metavar="S,S,...",
                    help="with --memory: lap k is the route recorded with the k-th of these seeds in turn, on "
                         "the robot of --seed (robotd record --seed S --base-seed SEED; cached), every third "
                         "frame fed (lap k: frame counts k mod 3); the floor is drawn from the seed, so laps "
                         "of the same rooms repeat it: 0,0,0 gives laps of new frames of one floor (default: "
                         "the one recording every lap, every frame)")
    ap.add_argument("--memory-every", type=int, default=1000, metavar="K",
                    help="sample the memory every K keyframes (default 1000)")
    ap.add_argument("--memory-trace", action="store_true",
                    help="with --memory: tracemalloc on, the Python side's allocations by file at each sample "
                         "(slower; its own overhead is reported)")
    ap.add_argument("--memory-trace-from", type=int, default=0, metavar="K",
                    help="with --memory: tracemalloc on from the first sample at K keyframes or more, so that "
                         "the traced allocations of later samples are those made since and still alive")
    ap.add_argument("--residency", nargs="+", default=None, metavar="[LABEL=]MAP",
                    help="only the floor query's time with its descriptors in RAM and read back from MAP "
                         "(sizes from --scale; writes NAME-residency.json); several maps: each in turn, "
                         "--rounds times, in the same run")
    ap.add_argument("--ransac-confidence", type=float, default=0.0, metavar="C",
                    help="[floor_detector] ransac_confidence of the replay (0: the config's); with --residency: also time the "
                         "query with RANSAC's adaptive stop at confidence C (MatchParams.confidence, in (0, 1); "
                         "the variants '..., ransac C')")
    ap.add_argument("--resident", default="256,1024", help="with --residency: decoded descriptors kept, "
                                                          "comma-separated (default 256,1024)")
    ap.add_argument("--load", type=Path, default=None, metavar="MAP",
                    help="only the map's load (FloorIndex.from_store) at the --scale sizes, MAP's descriptors "
                         "repeated, each in a fresh process (writes NAME-load.json)")
    ap.add_argument("--before", type=Path, default=None, metavar="DIR",
                    help="with --load: a checkout of the code before, alternated with this one")
    ap.add_argument("--rounds", type=int, default=3, help="with --load: rounds per tree (default 3); with "
                                                          "--residency of several maps: rounds of the maps")
    ap.add_argument("--forward-memory", type=int, default=0, metavar="N",
                    help="only the whole daemon's memory as its forward detector takes N images of --forward-dir "
                         "(writes NAME-forward-memory.json)")
    ap.add_argument("--forward-dir", type=Path, default=Path("/tmp/fwd/office"),
                    help="a rendered forward sequence (bench_forward_scale.py's): PNGs and poses.csv")
    ap.add_argument("--compare-stages", nargs="+", default=None, metavar="LABEL=JSON",
                    help="only write a page (--doc) of runs of trees alternated: CPU by stage per run, "
                         "each label's mean and its ratio to the first label's")
    ap.add_argument("--memory-page", nargs="+", default=None, metavar="[LABEL=]JSON",
                    help="only write the memory page (--doc) from these --memory JSON files, partial or not "
                         "(LABEL= heads its section)")
    args = ap.parse_args(argv)
    load_start = [round(v, 2) for v in os.getloadavg()]
    if args.memory_page is not None:
        page = memory_markdown(*(_labelled(f) for f in args.memory_page))
        if args.doc is not None:
            args.doc.parent.mkdir(parents=True, exist_ok=True)
            args.doc.write_text(page, encoding="utf-8")
        print(page, end="")
        return 0
    if args.forward_memory:
        fpayload: dict[str, Any] = {"machine": machine_info(), "args": {k: str(v) for k, v in vars(args).items()}}

        def fpartial(so_far: dict[str, Any]) -> None:
            write_json(args.out / f"{args.name}-forward-memory.json", {**fpayload, "forward_memory": so_far})

        fpayload["forward_memory"] = forward_memory_run(args, args.forward_memory, args.forward_dir, fpartial)
        print(f"wrote {write_json(args.out / f'{args.name}-forward-memory.json', fpayload)}")
        return 0
    if args.load is not None:
        trees = {"this code": REPO_ROOT} if args.before is None else {"before": args.before, "this code": REPO_ROOT}
        ld = map_load(args.load, [int(v) for v in args.scale.split(",") if v.strip()], trees, args.rounds,
                      args.queries)
        out = write_json(args.out / f"{args.name}-load.json", {"machine": machine_info(), "load": ld})
        print(f"wrote {out}")
        return 0
    if not 0 <= args.ransac_confidence < 1:
        ap.error(f"--ransac-confidence: in [0, 1), not {args.ransac_confidence}")
    if args.residency is not None:
        sizes = [int(v) for v in args.scale.split(",") if v.strip()]
        residents = [int(v) for v in args.resident.split(",") if v.strip()]
        from robotd.floor.detector import FloorDetectorParams

        maps = [(a.partition("=")[0], Path(a.partition("=")[2])) if "=" in a else (a, Path(a))
                for a in args.residency]
        for _label, path in maps:
            if not path.is_file():
                ap.error(f"--residency: no map at {path}")
        shortlist = args.shortlist or FloorDetectorParams().shortlist
        if len(maps) == 1:
            res = query_residency(maps[0][1], sizes, residents, args.queries, shortlist,
                                  confidence=args.ransac_confidence)
            out = write_json(args.out / f"{args.name}-residency.json", {"machine": machine_info(), "residency": res})
            print(f"wrote {out}")
            return 0
        runs: list[dict[str, Any]] = []
        for rnd in range(args.rounds):  # the maps in turn, round after round: the same load for each
            for label, path in maps:
                print(f"residency: round {rnd + 1}, map {label}", flush=True)
                runs.append({"label": label, "round": rnd + 1, "load_average": [round(v, 2) for v in os.getloadavg()],
                             **query_residency(path, sizes, residents, args.queries, shortlist,
                                               confidence=args.ransac_confidence)})
                write_json(args.out / f"{args.name}-residency.json",
                           {"machine": machine_info(), "residency_maps": runs, "load_start": load_start})
        out = write_json(args.out / f"{args.name}-residency.json",
                         {"machine": machine_info(), "residency_maps": runs, "load_start": load_start,
                          "load_end": [round(v, 2) for v in os.getloadavg()]})
        print(f"wrote {out}")
        print("\n".join(_residency_maps_section({"residency_maps": runs, "machine": machine_info()})))
        return 0
    if args.memory:
        if args.duration == 60.0 and args.recording is None:
            args.duration = None  # the whole route: more ground per lap
        recording: Path | list[Path]
        if args.memory_seeds is not None:
            try:
                seeds = [int(v) for v in args.memory_seeds.split(",") if v.strip()]
            except ValueError:
                ap.error(f"--memory-seeds: comma-separated integers, not {args.memory_seeds!r}")
            if not seeds or args.forward or args.recording is not None:
                ap.error("--memory-seeds: at least one seed, and neither --forward nor --recording")
            recording = [ensure_recording(args, s) for s in seeds]
        else:
            recording = ensure_recording(args)
        payload = {"machine": machine_info(),
                   "recording": [str(r) for r in recording] if isinstance(recording, list) else str(recording),
                   "args": {k: str(v) for k, v in vars(args).items()}}

        def partial(so_far: dict[str, Any]) -> None:  # kept if the run is stopped
            write_json(args.out / f"{args.name}-memory-partial.json", {**payload, "memory": so_far})

        payload["memory"] = memory_run(args, recording, args.memory, partial)
        out = write_json(args.out / f"{args.name}-memory.json", payload)
        (args.out / f"{args.name}-memory-partial.json").unlink(missing_ok=True)
        print(f"wrote {out}")
        if args.doc is not None:
            args.doc.parent.mkdir(parents=True, exist_ok=True)
            args.doc.write_text(memory_markdown(payload), encoding="utf-8")
            print(f"wrote {args.doc}")
        return 0
    if args.compare_stages or args.compare:
        page = stage_comparison(args.compare_stages) if args.compare_stages else comparison(args.compare)
        if args.doc is not None:
            args.doc.parent.mkdir(parents=True, exist_ok=True)
            args.doc.write_text(page, encoding="utf-8")
        print(page, end="")
        return 0
    if args.full:
        args.duration = None
        args.distinct = max(args.distinct, 10000)
    recording = ensure_recording(args)
    if args.scale_only:
        from drivers.recording.reader import RecordingReader
        from robotd.floor.detector import FloorDetectorParams

        fd = FloorDetectorParams()
        with RecordingReader(recording) as rr:
            span = rr.time_range_ns
        assert span is not None
        sizes = [int(v) for v in args.scale.split(",") if v.strip()]
        sc = scale(recording, sizes, args.queries, fd.descriptor_mode, args.shortlist or fd.shortlist,
                   (span[1] - span[0]) / 1e9, args.distinct)
        for row in sc["sizes"]:
            print(f"index {row['keyframes']}: query {row['query_ms']['median']:.2f} ms median "
                  f"({row['query_read_back_ms']['median']:.2f} ms as the daemon, "
                  f"{row['query_read_back_ms']['reads_per_query']:.1f} descriptors read back per query)")
        out = write_json(args.out / f"{args.name}-scale.json", {"machine": machine_info(), "recording": str(recording),
                                                                 "args": {k: str(v) for k, v in vars(args).items()},
                                                                 "scale": sc})
        print(f"wrote {out}")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        map_path = Path(tmp) / "map.sqlite"
        r = replay(args, recording, map_path)
        print(f"replayed: {r['process_cpu_s']:.1f} s of CPU for {r['robot_s']:.1f} s of robot time", flush=True)
        truth = read_truth(recording)
        j = judge(map_path, truth, 20.0)
        print("judged against the ground truth", flush=True)
        if args.keep_map is not None:
            import shutil

            shutil.copyfile(map_path, args.keep_map)
        b = None if args.no_baseline else baseline(recording, map_path, 20.0, r["config"]["shortlist"],
                                                   r["config"]["mode"])
    sizes = [int(s) for s in args.scale.split(",") if s.strip()]
    sc = (scale(recording, sizes, args.queries, r["config"]["mode"], r["config"]["shortlist"], r["robot_s"],
                args.distinct)
          if sizes else None)
    payload = {"machine": machine_info(), "recording": str(recording), "args": {k: str(v) for k, v in vars(args).items()},
               "replay": r, "judge": j, "baseline": b, "scale": sc,
               "load_average": {"start": load_start, "end": [round(v, 2) for v in os.getloadavg()]}}
    rows = [(name, round(s, 2), round(s / r["robot_s"], 4), round(s / j["distance_m"], 4))
            for name, s in r["stage_cpu_s"].items()]
    rows.append(("whole process", round(r["process_cpu_s"], 2), round(r["process_cpu_s"] / r["robot_s"], 4),
                 round(r["process_cpu_s"] / j["distance_m"], 4)))
    print()
    print_table(["stage", "CPU s", "per robot s", "per metre"], rows)
    print(f"\n{r['keyframes']} keyframes, {j['distance_m']:.1f} m in {r['robot_s']:.1f} s; wall {r['wall_s']:.1f} s")
    print(f"per keyframe: {r['keyframe_ms']['median']:.1f} ms median, {r['keyframe_ms']['p99']:.1f} ms p99; "
          f"describe {r['describe_ms']['median']:.2f} ms, query {r['query_ms']['median']:.2f} ms (medians)")
    if b:
        print(f"baseline ORB: extract {b['orb_extract_ms']['median']:.2f} ms, match shortlist "
              f"{b['orb_match_shortlist_ms']['median']:.2f} ms (medians); interleaved with it, describe "
              f"{b['describe_default_ms']['median']:.2f} ms, FULL_RESOLUTION "
              f"{b['describe_full_resolution_ms']['median']:.2f} ms")
    print(f"RSS {r['rss_after_mb']:.0f} MB after, peak {r['peak_rss_mb']:.0f} MB")
    print(f"loops: {j['loop_edges']} edges, {j['loop_edges_true']} true, {j['loop_edges_false']} false; "
          f"revisits closed {j['revisits_closed']}/{j['revisits']}; APE RMS anchored: odometry {j['ate_odometry_m'] * 1e3:.1f} mm, "
          f"loop-corrected {(j['ate_loop_corrected_m'] or math.nan) * 1e3:.1f} mm")
    if sc:
        for row in sc["sizes"]:
            print(f"index {row['keyframes']}: query {row['query_ms']['median']:.2f} ms median "
                  f"({row['query_read_back_ms']['median']:.2f} ms as the daemon, descriptors read back), "
                  f"index {row['index_mb']:.1f} MB, RSS {row['rss_mb']:.0f} MB")
    out = write_json(args.out / f"{args.name}.json", payload)
    print(f"wrote {out}")
    if args.doc is not None:
        args.doc.parent.mkdir(parents=True, exist_ok=True)
        args.doc.write_text(markdown(payload), encoding="utf-8")
        print(f"wrote {args.doc}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
