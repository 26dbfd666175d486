"""The forward detector's levers, one at a time, on the development data.

Two sequences, never one alone: the real corridor of ``../shared/data/forward/rtabmap_samples``
(84 images, its ``ground_truth.bmp``; no poses) and the virtual office route (1139 images:
0.4 m or 30 deg keyframes, four laps, aliasing on; written with
:func:`sim.forward_sequence.write_forward_sequence` into ``--dir`` unless it is there
already). The office images come with the robot's own odometry, never the true poses,
which the detector gets with each image: the pose the daemon gives its forward keyframes
(:func:`office_fused_odometry`: the fused wheel + gyro + floor visual odometry of the
daemon's pipeline over the same motion), or for the configurations whose name ends in
``wheel + gyro pose`` the virtual base's wheel and gyro alone through the daemon's wheel +
gyro filter (:func:`office_odometry`); rtabmap_samples has none. Every
configuration runs over the same images; the features of each kind are extracted once per image and their extraction time is added
to every configuration's time per image (features included, as the issue's targets count
them). OpenCV's own ORB extraction of the same images (``cv2.ORB_create``,
``detectAndCompute``), timed in the same run, is the baseline column.

Printed per sequence and configuration: recall at 100 % precision, false positives at the
operating point, precision, and time per image (median, p99) with its ratio to OpenCV's
ORB; on rtabmap_samples also the brute-force baseline of ``robotd eval forward``
(SIFT + RANSAC against every past image) in the same run. Written: JSON (machine,
versions, commit, every figure), read by ``tools/forward_benchmark_doc.py`` to make ``docs/benchmarks/forward.md``.

Run: ``.venv/bin/python bench/bench_forward_ablation.py --dir /tmp/office``. By default:
every configuration on rtabmap_samples (a few minutes), and on the office route the
default, the default with the odometry likelihood on each pose, and the daemon's levers on
the fused pose (about 2 minutes each on the shared 2-core development machine at moderate
load; ten under heavy load). The fused pose is computed once (the daemon's pipeline over
the four laps, the floor camera rendered at each floor keyframe: about 15 minutes on a quiet
machine, an hour under heavy load) and kept beside the images as ``odometry_fused.csv``.
``--full`` runs every configuration on the office route too, the paper's SIFT detector
included (about ten minutes more for it alone), and ORB 1000.
``--configs "A;B"`` picks configurations.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

try:
    from bench.common import machine_info, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, write_json

from robotd.forward import LOOP, FeatureExtractor, ForwardDetector, method_params
from robotd.forward.evaluation import score_decisions
from robotd.forward.detector import OdometryParams, bounded_verification, daemon_params
from robotd.forward.features import FeatureParams
from robotd.forward.verify import camera_matrix_guess
from robotd.io.sequence import list_images, load_ground_truth, read_image

REPO = Path(__file__).resolve().parent.parent
DATA = REPO.parent / "shared" / "data"
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "forward_ablation.json"


def configurations(full: bool) -> dict[str, object]:
    """Name -> DetectorParams: the paper, the default, the default without odometry (the
    one before it), the default before that (k = 2, total p > 0.5, no odometry) with one
    lever changed at a time (its name says which), then levers on the default without
    odometry and on the default."""
    paper = method_params("paper")
    dflt = method_params("default")
    base = replace(dflt, odometry=OdometryParams())  # the default without odometry
    prev = replace(base, consistency=2, filter=replace(base.filter, loop_threshold=0.5))
    f = prev.filter
    odo = OdometryParams(use=True)
    v = prev.verify
    sc = replace(base, decision="score", score_normalisation="previous", score_threshold=0.3)  # no filter
    cfgs = {
        "paper (SIFT)": paper,
        "default": dflt,
        "default without odometry": base,
        "previous default (k = 2)": prev,
        "previous default, total p > 0.3": replace(prev, filter=replace(f, loop_threshold=0.3)),
        "previous default, total p > 0.7": replace(prev, filter=replace(f, loop_threshold=0.7)),
        "previous default, k = 3": replace(prev, consistency=3),
        "previous default, no purge": replace(prev, vocabulary=replace(prev.vocabulary, purge_after=0)),
        "previous default, ORB 500": replace(prev, features=FeatureParams(kind="orb", max_features=500)),
        "previous default, score/previous > 0.3": replace(sc, consistency=2),
        "previous default, score/previous > 0.3, islands": replace(sc, islands=True, consistency=2),
        "previous default, places merged by pose": replace(prev, odometry=replace(OdometryParams(),
                                                                                 merge_places=True)),
        "previous default, odometry": replace(prev, odometry=odo),
        "previous default, odometry x4 variance": replace(prev, odometry=replace(odo, variance_scale=4.0)),
        "previous default, odometry, no support test when it agrees": replace(
            prev, odometry=replace(odo, agree_min_support_area=0.0)),
        "previous default, odometry, 3 verifications": replace(prev, odometry=odo, verify_tries=3),
        "previous default, 15 inliers": replace(prev, verify=replace(v, min_inliers=15)),
        "previous default, no support test": replace(prev, verify=replace(v, min_support_area=0.0)),
        "default without odometry, total p > 0.5": replace(base, filter=replace(base.filter, loop_threshold=0.5)),
        "default without odometry, score/previous > 0.3, islands": replace(sc, islands=True),
    }
    # The metric levers, one at a time on the default without odometry, with the pose the
    # daemon gives its forward keyframes (the fused odometry: wheel + gyro + floor visual
    # odometry) or the wheel + gyro pose (WHEEL in the name); then on the default, whose
    # odometry likelihood with no support test when it agrees and 3 verifications are the
    # levers kept.
    fo = OdometryParams(use=True)
    cfgs.update({
        "default without odometry, odometry": replace(base, odometry=fo),
        f"default without odometry, odometry, {WHEEL}": replace(base, odometry=fo),
        "default without odometry, places merged by pose": replace(base, odometry=replace(OdometryParams(),
                                                                                         merge_places=True)),
        "default without odometry, neighbours by distance": replace(
            base, odometry=replace(OdometryParams(), metric_neighbours=True)),
        "default without odometry, metric neighbours verified (3)": replace(
            base, odometry=replace(OdometryParams(), verify_place=True), verify_tries=3),
        "default without odometry, odometry, 3 verifications": replace(base, odometry=fo, verify_tries=3),
        "default without odometry, all metric levers": replace(
            base, odometry=replace(fo, merge_places=True, metric_neighbours=True, verify_place=True),
            verify_tries=3),
        f"default, {WHEEL}": dflt,
        "default, 1 verification": replace(dflt, verify_tries=1),
        "default, general verification": replace(dflt, verify=replace(dflt.verify, model="general")),
        # the planar verification with its work per image bounded (USAC near the level motion,
        # the fallback in a 10 px band, once per image), and without it (RANSAC near the level
        # motion, the fallback over all the matches for every view tried: the default's own)
        "default, bounded verification": bounded_verification(dflt),
        "default, previous planar verification": replace(
            dflt, verify=replace(dflt.verify, guided_estimator=None, fallback_band_px=None), verify_fallbacks=None),
        f"default, 1 verification, {WHEEL}": replace(dflt, verify_tries=1),
        "default, neighbours by distance": replace(dflt, odometry=replace(dflt.odometry, metric_neighbours=True)),
        "default, places merged by pose": replace(dflt, odometry=replace(dflt.odometry, merge_places=True)),
        "default as the daemon runs it": daemon_params(dflt),
        # the bounded fallback's cap (the tail of the daemon's forward keyframes: docs/forward.md,
        # "The p99 in the daemon now"), and no fallback at all
        "default, fallback 100 samples": replace(dflt, verify=replace(dflt.verify, fallback_max_iterations=100)),
        "default, fallback 50 samples": replace(dflt, verify=replace(dflt.verify, fallback_max_iterations=50)),
        "default, no fallback": replace(dflt, verify=replace(dflt.verify, fallback_inliers=None)),
        # the band fallback screened by USAC first (it can only refuse: RANSAC decides what passes)
        "default, fallback screened": replace(dflt, verify=replace(dflt.verify, fallback_screen="usac")),
        "default as the daemon runs it, fallback screened": daemon_params(
            replace(dflt, verify=replace(dflt.verify, fallback_screen="usac"))),
    })
    if full:
        cfgs["default, ORB 1000"] = replace(dflt, features=FeatureParams(kind="orb", max_features=1000))
    # cheaper ORB settings (docs/forward.md, "Time and memory": the features)
    for name, change in (("ORB 4 levels", {"orb_levels": 4}), ("ORB 5 levels x1.3", {"orb_levels": 5, "orb_scale_factor": 1.3}),
                         ("image x0.75", {"image_scale": 0.75}), ("image x0.8, 6 levels", {"image_scale": 0.8, "orb_levels": 6})):
        cfgs[f"default, {name}"] = replace(dflt, features=replace(dflt.features, **change))
    return cfgs


#: In a configuration's name: the office route's images come with the wheel + gyro
#: odometry (:func:`office_odometry`); every other configuration there gets the pose the
#: daemon gives its forward keyframes, the fused odometry (:func:`office_fused_odometry`),
#: used only by the configurations with metric levers.
WHEEL = "wheel + gyro pose"


def pose_source(name: str) -> str:
    """Which odometry the office route's images come with in configuration ``name``:
    ``"wheel + gyro"`` or ``"fused"``."""
    return "wheel + gyro" if name.endswith(WHEEL) else "fused"


def extract_timed(features: FeatureParams, images: list[np.ndarray]) -> list[tuple[object, float]]:
    """Each image's features and the seconds their extraction took."""
    ex = FeatureExtractor(features)
    out = []
    for im in images:
        t0 = time.perf_counter()
        fe = ex(im)
        out.append((fe, time.perf_counter() - t0))
    return out


def office_sequence(folder: Path) -> Path:
    """The virtual office sequence in ``folder`` (written when ``gt.npy`` is missing)."""
    if not (folder / "gt.npy").exists():
        from sim.forward_sequence import SequenceSettings, write_forward_sequence

        print(f"writing the virtual office sequence to {folder} ...", flush=True)
        write_forward_sequence(folder, SequenceSettings(step_m=0.4, turn_rad=math.radians(30.0), repeats=4))
    return folder


def office_odometry(folder: Path, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The robot's own odometry at the office sequence's images: ``(N, 3)`` poses
    ``(x_m, y_m, yaw_rad)`` and ``(N, 3, 3)`` their covariances, as the daemon's wheel + gyro
    filter (:mod:`robotd.odometry.ekf`) estimates them from the virtual base's sensors
    (:mod:`sim.sensors`: wheel radius, wheel base, slip, gyro bias and noise, drawn with
    ``seed``) along the motion the sequence was rendered from, encoders quantised to ticks.
    Never the true poses: those are only the ground truth. Written beside the images as
    ``odometry.csv``, the file ``robotd eval forward --odometry`` reads (the sequence's
    ``sequence.json`` names the route), and read from there when it exists."""

    from robotd.app.forward_eval import read_odometry

    cache = folder / "odometry.csv"
    settings, times = _sequence_settings_and_times(folder)
    if cache.exists():
        return read_odometry(cache, len(times))
    from robotd.odometry import ekf
    from robotd.odometry.kinematics import DiffDriveParams
    from sim.forward_sequence import _repeated_route
    from sim.route import MotionLimits, plan_motion
    from sim.sensors import BaseSensorParams, draw_errors, simulate_sensors

    motion = plan_motion(_repeated_route(settings["route"], settings["repeats"]), MotionLimits())
    rng = np.random.default_rng(seed)
    sp = BaseSensorParams()
    s = simulate_sensors(motion, sp, draw_errors(sp, rng), rng)
    geo = DiffDriveParams()
    ticks = np.round(s.wheel_angle_rad * geo.ticks_per_rev / (2 * math.pi))
    dist = ticks * geo.metres_per_tick_left  # the nominal geometry: the base's errors are unknown
    params = ekf.EkfParams()
    events = sorted([(float(t), 0, i) for i, t in enumerate(s.t_s[1:], 1)]
                    + [(float(t), 1, i) for i, t in enumerate(s.gyro_t_s)])
    state = ekf.initial_state(int(round(s.t_s[0] * 1e9)), params)
    pose = np.zeros((len(times), 3))
    cov = np.zeros((len(times), 3, 3))
    k = 0
    at_rest = False
    for t, kind, i in events:
        while k < len(times) and times[k] <= t:
            st = ekf.predict(state, max(state.stamp_ns, int(round(times[k] * 1e9))), params)
            pose[k], cov[k] = st.pose_xyyaw, st.pose_cov
            k += 1
        state = ekf.predict(state, max(state.stamp_ns, int(round(t * 1e9))), params)
        if kind == 0:
            dt = s.t_s[i] - s.t_s[i - 1]
            dl, dr = dist[i] - dist[i - 1]
            at_rest = dl == 0 and dr == 0
            state = ekf.update_wheels(state, (dl + dr) / 2 / dt, (dr - dl) / geo.wheel_base_m / dt, params,
                                      stationary=at_rest)
        else:
            state = ekf.update_gyro(state, float(s.gyro_radps[i, 2]), params, at_rest=at_rest)
    while k < len(times):
        pose[k], cov[k] = state.pose_xyyaw, state.pose_cov
        k += 1
    write_odometry(cache, pose, cov)
    return pose, cov


class _FusedRecorder:
    """Pipeline observer: every fused odometry update's stamp, pose and covariance."""

    name = "fused_recorder"

    def __init__(self) -> None:
        self.stamp_ns: list[int] = []
        self.pose: list[tuple[float, float, float]] = []
        self.cov: list[np.ndarray] = []

    def subscriptions(self) -> dict[type, object]:
        from robotd.base.messages import OdometryUpdate

        return {OdometryUpdate: self.on_odometry}

    def on_odometry(self, u) -> None:
        f = u.fused
        self.stamp_ns.append(int(f.stamp_ns))
        self.pose.append((f.x_m, f.y_m, f.yaw_rad))
        self.cov.append(np.asarray(f.covariance, np.float64).copy())


class _RenderedFrame:
    """Builds a floor :class:`~robotd.base.messages.Frame` whose image is rendered the
    first time it is read (the keyframe stage reads only its keyframes' images), the way a
    replay's frames decode when first read."""

    @staticmethod
    def make(stamp_ns: int, seq: int, render):
        from drivers.recording.reader import EncodedFrame

        class Rendered(EncodedFrame):
            __slots__ = ("_render",)

            @property
            def image(self) -> np.ndarray:
                if self._decoded is None:
                    object.__setattr__(self, "_decoded", self._render())
                return self._decoded

        f = Rendered(stamp_ns, "floor", seq=seq, encoded=np.zeros(1, np.uint8))
        object.__setattr__(f, "_render", render)
        return f


def fused_odometry_stream(route: str, repeats: int, seed: int = 0, work: Path | None = None,
                          duration_s: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every fused odometry update of the daemon's pipeline over the virtual robot driving
    ``route`` ``repeats`` times in a row (see :func:`office_fused_odometry`): stamps ``(M,)``
    int64 ns (the robot's clock: the route's time), poses ``(M, 3)``, covariances
    ``(M, 3, 3)``; ``duration_s``: only the route's first seconds.

    The pipeline is the daemon's (:func:`robotd.app.assemble.build_pipeline`: odometry,
    keyframes, floor visual odometry fused into the wheel + gyro filter, map writer; the
    floor loop detector and the pose graph off), with ``robotd demo``'s configuration and
    shipped calibration, fed in-process with what the demo's virtual robot (``seed``) sends
    its driver: the Kobuki's wheel and gyro messages (:meth:`sim.emulators.kobuki` 's
    ``messages``, the driver's decoding without the pty) and the floor camera's frames at
    its frame rate, each rendered only when the keyframe stage takes it (the demo renders
    every frame; the frames between keyframes are never looked at)."""
    import heapq
    import tempfile

    from robotd.app.assemble import build_pipeline, load_calibration, open_map
    from robotd.app.demo import shipped_calibration
    from robotd.base.camera import FloorCameraModel
    from robotd.base.clock import ManualClock
    from robotd.base.config import Config, with_virtual_floor_camera
    from robotd.base.config import replace as cfg_replace
    from robotd.base.configfile import to_toml
    from sim.cameras.floor import FloorRenderer, RenderParams
    from sim.emulators.kobuki import simulate_kobuki
    from sim.forward_sequence import _repeated_route
    from sim.route import MotionLimits, plan_motion
    from sim.sensors import BaseSensorParams
    from sim.world.floor import Floor

    cfg = Config()
    calibration = shipped_calibration()
    if calibration is not None:
        cfg = cfg_replace(cfg, "calibration", path=str(calibration))
    cfg = with_virtual_floor_camera(cfg)
    cfg = cfg_replace(cfg, "floor_detector", enabled=False)
    cfg = cfg_replace(cfg, "pose_graph", enabled=False)
    cfg = cfg_replace(cfg, "visual_odometry", enabled=True, role="fused")
    motion = plan_motion(_repeated_route(route, repeats), MotionLimits())
    if duration_s is not None:
        motion = motion.truncated(duration_s)
    feedback = simulate_kobuki(motion, BaseSensorParams(), np.random.default_rng(seed))
    base_msgs = feedback.messages(cfg.base.yaw_source)
    cam = FloorCameraModel.from_config(cfg.floor_camera)
    renderer = FloorRenderer(Floor.default(seed=seed, metres_per_px=0.001), cam, RenderParams(),
                             np.random.default_rng(seed + 1))

    def render_at(t_s: float):
        def render() -> np.ndarray:
            v, w = motion.velocity_at(t_s)
            return renderer.render(motion.pose_at(t_s), v, w, t_s)
        return render

    frame_t = np.arange(0.0, float(motion.t_s[-1]), 1.0 / cfg.floor_camera.fps)
    rec = _FusedRecorder()
    clock = ManualClock()
    with tempfile.TemporaryDirectory() as tmp:
        cfg = cfg_replace(cfg, "map", path=str((work or Path(tmp)) / "map.sqlite"))
        calib = load_calibration(cfg)
        with open_map(cfg, clock=clock) as store:
            run_id = store.begin_run(to_toml(cfg))
            pipe = build_pipeline(cfg, clock, store, run_id, lossless=True, calibration=calib,
                                  observers=[rec], floor_detector=False, pose_graph=False)
            events = heapq.merge(((int(m.stamp_ns), 0, i) for i, m in enumerate(base_msgs)),
                                 ((int(round(t * 1e9)), 1, i) for i, t in enumerate(frame_t)))
            for stamp, kind, i in events:
                clock.set_ns(max(clock.now_ns(), stamp))
                msg = base_msgs[i] if kind == 0 else _RenderedFrame.make(stamp, i, render_at(float(frame_t[i])))
                pipe.feed(msg)
                pipe.poll()
            for st in pipe._stages.values():
                if hasattr(st, "finish"):
                    st.finish()
            store.end_run(run_id)
    return np.asarray(rec.stamp_ns, np.int64), np.asarray(rec.pose), np.asarray(rec.cov)


def office_fused_odometry(folder: Path, seed: int = 0, work: Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The pose the daemon gives its forward keyframes, at the office sequence's images:
    ``(N, 3)`` poses and ``(N, 3, 3)`` covariances of the fused odometry (wheel + gyro +
    the floor camera's visual odometry, :mod:`robotd.odometry.fusion`), as ``robotd demo``
    computes it: the virtual robot (``seed``) drives the sequence's own motion (its route
    repeated, the same planner, so the robot's clock is the sequence's ``t_s``) with its
    Kobuki bytes read by the real driver, the daemon assembled with the demo's shipped
    calibration, floor visual odometry fused (``[visual_odometry] role = "fused"``). The
    floor loop detector and the pose graph are off: they do not change the fused odometry
    (no loop correction reaches it) and cost time. Each image takes the last fused update
    at or before its time (wheel readings every 20 ms). Never the true pose. Written
    beside the images as ``odometry_fused.csv`` (the ``--odometry`` format) and read from
    there when it exists. ``work``: folder for the demo's outputs (default a temporary one)."""

    from robotd.app.forward_eval import read_odometry

    cache = folder / "odometry_fused.csv"
    settings, times = _sequence_settings_and_times(folder)
    if cache.exists():
        return read_odometry(cache, len(times))
    stamps, allp, allc = fused_odometry_stream(settings["route"], settings["repeats"], seed, work)
    k = np.searchsorted(stamps, np.round(times * 1e9).astype(np.int64), side="right") - 1
    k = np.clip(k, 0, len(stamps) - 1)
    pose, cov = allp[k], allc[k]
    write_odometry(cache, pose, cov)
    return read_odometry(cache, len(times))


def _sequence_settings_and_times(folder: Path) -> tuple[dict, np.ndarray]:
    """A rendered sequence's settings (``sequence.json``) and its images' times ``(N,)`` in
    seconds (``poses.csv``'s second column)."""
    import json

    settings = json.loads((folder / "sequence.json").read_text())["settings"]
    return settings, np.loadtxt(folder / "poses.csv", delimiter=",", skiprows=1, usecols=1, ndmin=1)


def write_odometry(path: Path, pose: np.ndarray, cov: np.ndarray) -> None:
    """``pose (N, 3)`` and the diagonals of ``cov (N, 3, 3)`` as the CSV of ``robotd eval
    forward --odometry``."""
    var = np.stack([cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]], axis=1)
    np.savetxt(path, np.column_stack([pose, var]), delimiter=",", fmt="%.9g",
               header="x_m,y_m,yaw_rad,var_x_m2,var_y_m2,var_yaw_rad2", comments="")


def run_sequence(name: str, folder: Path, truth_path: Path, cfgs: dict[str, object], skip: set[str],
                 recent: int = 10, only: list[str] | None = None,
                 odometry: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
                 brute_force: bool = False, progress=None) -> dict[str, object]:
    """Every configuration of ``cfgs`` (but ``skip``, and only ``only`` when given) over the
    sequence; ``odometry``: by :func:`pose_source` name, ``(N, 3)`` poses and ``(N, 3, 3)``
    covariances given to the detector with each image (None: the sequence has none; a
    configuration whose source is missing is skipped); ``brute_force``: also the
    brute-force baseline of ``robotd eval forward`` (SIFT matching and RANSAC against every
    past image, :class:`robotd.forward.baselines.BruteForceMatcher`; its time grows with the
    square of the sequence); ``progress``: called with the results so far after each row
    (the JSON is written as the run goes, so an interrupted run keeps its rows)."""
    files = list_images(folder, exclude=(truth_path,))
    truth = load_ground_truth(truth_path, len(files))
    images = [read_image(p) for p in files]  # decoded once (grey office images: 300 kB each)
    h, w = images[0].shape[:2]
    k = camera_matrix_guess(w, h, 525.0 if name == "office" else None)
    # OpenCV's own ORB on the same images: the baseline of the time column.
    orb = cv2.ORB_create(nfeatures=300)
    cv_ms = []
    for im in images:
        g = cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im
        t0 = time.perf_counter()
        orb.detectAndCompute(g, None)
        cv_ms.append((time.perf_counter() - t0) * 1e3)
    cv_median = float(np.median(cv_ms))
    feats: dict[FeatureParams, list] = {}
    out: dict[str, object] = {"images": len(files), "opencv_orb_ms": {"median": cv_median,
                                                                       "p99": float(np.percentile(cv_ms, 99))},
                              "configurations": {}}
    print(f"\n{name}: {len(files)} images ({w}x{h}); OpenCV ORB (300) extraction: median {cv_median:.1f} ms")
    print(f"{'configuration':<32}{'R@100%P':>9}{'FP':>5}{'prec.':>7}{'loops':>7}{'ms med':>8}{'p99':>8}"
          f"{'x ORB':>7}{'words':>8}{'B/image':>9}")
    names = list(cfgs) if only is None else [c for c in only if c in cfgs]  # in the order asked
    for cname in names:
        params = cfgs[cname]
        if cname in skip:
            continue
        fk = params.features  # every field: the extraction differs with any of them
        if fk not in feats:
            feats[fk] = extract_timed(params.features, images)
        src = pose_source(cname) if odometry is not None else "none"
        if odometry is not None and src not in odometry:
            continue
        odo = None if odometry is None else odometry[src]
        det = ForwardDetector(params, camera_matrix=k)
        n = len(files)
        cand, conf, decl = np.full(n, -1), np.zeros(n), np.zeros(n, bool)
        total = np.zeros(n)
        for t, (fe, fs) in enumerate(feats[fk]):
            d = (det.process_features(fe, fs) if odo is None
                 else det.process_features(fe, fs, odo[0][t], odo[1][t]))
            total[t] = d.times_s["total"] * 1e3
            if d.candidate_id is not None:
                cand[t], conf[t], decl[t] = d.candidate_id, d.candidate_probability, d.status == LOOP
        s = score_decisions(cand, conf, decl, truth, recent)
        med, p99 = float(np.median(total)), float(np.percentile(total, 99))
        mem = det.memory_bytes()
        per_image = sum(mem.values()) / n
        row = {**s.as_dict(), "pose": src, "ms_median": med, "ms_p99": p99, "ratio_to_opencv_orb": med / cv_median,
               "words": len(det.vocabulary), "searchable_words": det.vocabulary.n_searchable,
               "bytes_per_image": per_image, "bytes_per_image_by_part": {k: v / n for k, v in mem.items()}}
        out["configurations"][cname] = row
        if progress is not None:
            progress(out)
        print(f"{cname:<32}{s.recall_at_full_precision:>9.3f}{s.false_positives:>5}{s.precision:>7.3f}"
              f"{s.declared:>7}{med:>8.1f}{p99:>8.1f}{med / cv_median:>7.1f}{det.vocabulary.n_searchable:>8}"
              f"{per_image:>9.0f}", flush=True)
    if brute_force:
        from robotd.forward.baselines import BruteForceMatcher

        sift = method_params("paper").features
        fk = sift
        if fk not in feats:
            ex = FeatureExtractor(sift)
            feats[fk] = []
            for im in images:
                t0 = time.perf_counter()
                fe = ex(im)
                feats[fk].append((fe, time.perf_counter() - t0))
        bf = BruteForceMatcher(method_params("paper").verify, recent, k)
        n = len(files)
        cand, conf, decl = np.full(n, -1), np.zeros(n), np.zeros(n, bool)
        total = np.zeros(n)
        for t, (fe, fs) in enumerate(feats[fk]):
            b = bf.process_features(fe)
            total[t] = (fs + b.time_s) * 1e3
            if b.candidate_id is not None:
                cand[t], conf[t], decl[t] = b.candidate_id, b.n_inliers, b.loop
        s = score_decisions(cand, conf, decl, truth, recent)
        med, p99 = float(np.median(total)), float(np.percentile(total, 99))
        out["brute_force"] = {**s.as_dict(), "ms_median": med, "ms_p99": p99,
                              "ratio_to_opencv_orb": med / cv_median}
        if progress is not None:
            progress(out)
        print(f"{'baseline: brute-force SIFT':<32}{s.recall_at_full_precision:>9.3f}{s.false_positives:>5}"
              f"{s.precision:>7.3f}{s.declared:>7}{med:>8.1f}{p99:>8.1f}{med / cv_median:>7.1f}", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", type=Path, required=True, help="folder of the virtual office sequence")
    ap.add_argument("--full", action="store_true",
                    help="every configuration on the office route too, the paper's SIFT detector included")
    ap.add_argument("--data", type=Path, default=DATA,
                    help="the shared data folder (default ../shared/data from the project root)")
    ap.add_argument("--only", choices=("rtabmap", "office"), default=None)
    ap.add_argument("--configs", default=None,
                    help="configuration names to run, separated by semicolons (default: all)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    cfgs = configurations(args.full)
    only = None if args.configs is None else [c.strip() for c in args.configs.split(";")]
    unknown = [c for c in only or () if c not in cfgs]
    if unknown:
        ap.error(f"unknown configuration(s): {', '.join(unknown)}")
    import usearch

    result: dict[str, object] = {"machine": {**machine_info(), "opencv": cv2.__version__,
                                             "usearch": usearch.__version__}, "sequences": {}}
    rtabmap = args.data / "forward" / "rtabmap_samples"
    if args.only in (None, "rtabmap"):
        result["sequences"]["rtabmap_samples"] = run_sequence(
            "rtabmap_samples", rtabmap, rtabmap / "ground_truth.bmp", cfgs, set(), only=only, brute_force=True,
            progress=lambda o: (result["sequences"].__setitem__("rtabmap_samples", o), write_json(args.out, result)))
    if args.only in (None, "office"):
        office = office_sequence(args.dir)
        office_only = only if (only is not None or args.full) else [
            "default", f"default, {WHEEL}", "default without odometry", "default without odometry, odometry",
            "default as the daemon runs it"]
        odo = {}
        if any(pose_source(c) == "wheel + gyro" for c in (office_only or cfgs)):
            odo["wheel + gyro"] = office_odometry(office)
        if any(pose_source(c) == "fused" for c in (office_only or cfgs)):
            odo["fused"] = office_fused_odometry(office)
        result["sequences"]["office"] = run_sequence("office", office, office / "gt.npy", cfgs, set(),
                                                     only=office_only, odometry=odo,
                                                     progress=lambda o: (result["sequences"].__setitem__("office", o),
                                                                         write_json(args.out, result)))
    print(f"wrote {write_json(args.out, result)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
