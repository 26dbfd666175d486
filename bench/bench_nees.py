"""Are the covariances the map's edges carry honest? NEES of odometry and loop edges
against the virtual robot's truth.

The normalised estimation error squared of an edge is ``e^T C^-1 e``, ``e`` its error
against the truth in the frame the pose graph measures it in (the edge's end, as
:func:`robotd.base.geometry.between_error_covariance`), ``C`` its covariance; over many
edges its mean is 3 when the covariances are right (3 degrees of freedom), below when they
are too cautious, above when too confident.

**Odometry edges** (part 1). For each seed the office route (about 110 m, paper 003 Sec.
V) is driven by the virtual Kobuki (:mod:`sim.sensors` defaults: per-seed wheel radii,
wheel base, gyro scale and turn-on bias, bias walk, slip), its messages run through the
wheel + gyro filter as the daemon builds it (nominal model), and keyframes are taken as the
daemon takes them (``--keyframe-m`` or 10 deg, floor frames at 30 Hz) with their edges
(:meth:`robotd.odometry.fusion.OdometryFilter.keyframe_edge`). Per horizon ``N``: every
chain of ``N`` consecutive edges (a window every ``N/5`` edges) composed as the pose graph
composes independent edges, its covariance the sum of theirs carried to the chain's end;
the mean NEES over the windows, and of the yaw and the position parts alone (expected 1
and 2). The same windows under five models of what the edges share: independent edges (the
pose graph today); the bias as one variable per window of :data:`WINDOW_EDGES` edges from
the first (:func:`robotd.graph.bias.bias_window_factor`), marginalised; the edges given the
gyro bias at their start with the bias as variables of the graph (:mod:`robotd.graph.bias`:
AR(1) bias steps from the filter), marginalised;
the same with the wheels' and the gyro's scale errors as variables every edge shares
(prior: the simulated base's spreads, :data:`SCALE_SIGMA`), marginalised; and the filter's
own covariance of the motion between the two keyframes (its joint covariance, carried
through every filter step). ``--ekf NAME=VALUE`` runs the filter with another noise model;
``--daemon-model`` starts from the daemon's (the wheel + gyro twin's, with the demo's
calibration); ``--shipped-geometry`` gives the filter the shipped calibration's wheel radii,
wheel base and gyro scale on every seed's base, as ``robotd demo --seed N`` runs it, and
``--daemon-models`` picks the ``[pose_graph] odometry_model`` values ``--daemon-graph``
feeds (``bias_scale_window``: with the scale variable's prior of the shipped calibration
and the default ``scale_wear``; ``--scale-wear WHEEL,GYRO`` another). One interval is
decomposed by kind (straight, arc, turn on the spot, start or stop) and component (along
the track, across it, yaw): the true error against the filter's own covariance and the
edge's (:func:`interval_parts`). The pose graph's cost of the bias-sharing factors (``--cost-seeds``,
``--cost-models``): iSAM2 per keyframe and batch Levenberg-Marquardt against independent
edges, loop edges from the truth, same run.

**Loop edges** (part 2). Per floor (the printed planks, the paper's worst case, and the
default floor of real photographs) ``--pairs`` frame pairs are rendered with the second
frame within 0.25 m of the first at any heading (``sim.pairs.random_pairs``); per descriptor
mode the pairs the floor loop detector would declare loops (local score at the demo
calibration's threshold, footprint overlap at least ``LOOP_R``) and whose transform is
right (within 5 cm of the truth, as the loop-closure benchmark counts a loop false) get
their loop edge (:func:`robotd.floor.detector.loop_transform`). NEES of the covariance the
detector gives now, and of the rigid fit's covariance alone (what it gave before the
shared error of the frame pair was modelled: the baseline, in the same run); the position
part by the turn between the two frames; and the loop edge's noise model fitted by maximum
likelihood over modes 1-6 (:func:`loop_noise_ml`: the floor on the inliers' residual sigma,
the offset the two views share in the camera's frame, which the turn makes a translation
error, and a constant shared term beside it).

Run from the repo root: ``.venv/bin/python bench/bench_nees.py [--seeds 5] [--pairs 120]
[--floors planks,mixed] [--ekf NAME=VALUE ...] [--cost-seeds 1] [--compare OTHER.json]
[--skip-odometry] [--skip-loops] [--out bench/results/nees.json] [--markdown
docs/benchmarks/nees.md]``. The default takes about 10 minutes on a quiet
2-core machine (rendering the pairs is most of it); ``--full``: 10 seeds, 400 pairs.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

try:
    from bench.common import machine_info, print_table, write_json, write_page
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, write_json, write_page

from robotd.base.geometry import between, between_error_covariance, compose, wrap_angle
from robotd.base.messages import WheelTicks
from robotd.graph.bias import scale_jacobian
from robotd.keyframes import KeyframeSelector
from robotd.odometry.ekf import EkfParams
from robotd.odometry.fusion import OdometryFilter
from robotd.odometry.relative import PoseClone, relative_pose_covariance
from sim.emulators.kobuki import driver_messages, simulate_kobuki
from sim.route import MotionLimits, build_route, plan_motion
from sim.sensors import BaseSensorParams

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "nees.json"
HORIZONS = (1, 10, 50, 200, 500, 1000)
FRAME_HZ = 30.0
#: A loop edge farther than this from the truth is false (bench_loop_closure's rule).
FALSE_LOOP_M = 0.05


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- odometry


class _Recorder:
    """Every state the filter records, with the linear map of its error since the one
    before (what :class:`robotd.odometry.history.PoseHistory` keeps for two seconds)."""

    def __init__(self, f: OdometryFilter) -> None:
        self.t: list[int] = []
        self.mean: list[np.ndarray] = []
        self.cov: list[np.ndarray] = []
        self.step: list[np.ndarray] = []
        hist = f._history  # the bench looks inside: the daemon never needs the whole run
        orig = hist.record

        def record(state: Any, step: np.ndarray, ext_cov: np.ndarray | None = None) -> None:
            # ext_cov (wheel_rounding): the covariance of [state, rounding], step its map
            cov = state.cov if ext_cov is None else ext_cov
            if self.t and self.t[-1] == state.stamp_ns:
                self.mean[-1], self.cov[-1] = state.mean, cov
                self.step[-1] = step @ self.step[-1]
            else:
                self.t.append(state.stamp_ns)
                self.mean.append(state.mean)
                self.cov.append(cov)
                self.step.append(step)
            orig(state, step, ext_cov)

        hist.record = record  # type: ignore[method-assign]


def drive_edges(route: str, seed: int, keyframe_m: float, sensors: BaseSensorParams,
                params: EkfParams | None = None, true_model: bool = False,
                geometry: tuple[Any, float] | None = None) -> dict[str, Any]:
    """Drive ``route`` with seed ``seed``'s base; the keyframe edges, the truth at the
    keyframes, and the filter's own states at them (for the joint covariance).
    ``true_model``: the filter has the base's true wheel radii, wheel base and gyro scale
    (what a calibration within its targets gives) instead of the nominal ones.
    ``geometry``: ``(DiffDriveParams, gyro_scale)`` the filter has instead (the demo's
    shipped calibration, :func:`shipped_geometry`: seed 0's base, on every seed's)."""
    from robotd.odometry.kinematics import DiffDriveParams

    motion = plan_motion(build_route(route), MotionLimits())
    stream = simulate_kobuki(motion, sensors, np.random.default_rng(seed))
    msgs = driver_messages(stream)
    kw: dict[str, Any] = {} if params is None else {"params": params}
    if true_model:
        e, d = stream.sensors.errors, sensors.drive
        r0 = d.wheel_radius_m
        kw["drive"] = DiffDriveParams(wheel_radius_m=r0, wheel_base_m=d.wheel_base_m * (1 + e.wheel_base_error),
                                      wheel_radius_left_m=r0 * (1 + e.left_radius_error),
                                      wheel_radius_right_m=r0 * (1 + e.right_radius_error))
        kw["gyro_scale"] = 1 + e.gyro_scale_error
    elif geometry is not None:
        kw["drive"], kw["gyro_scale"] = geometry
    f = OdometryFilter(**kw)
    rec = _Recorder(f)
    selector = KeyframeSelector(keyframe_m, math.radians(10.0))
    frames_ns = (np.arange(0.0, float(motion.t_s[-1]), 1.0 / FRAME_HZ) * 1e9).round().astype(np.int64)
    stamps, edges = [], []
    i = 0
    for n, m in enumerate(msgs):
        (f.on_wheels if isinstance(m, WheelTicks) else f.on_yaw_rate)(m)
        if n % 16:  # the daemon drains its queues in batches; the edges do not depend on it
            continue
        settled = f.settled_stamp_ns()
        while settled is not None and i < len(frames_ns) and frames_ns[i] <= settled:
            t = int(frames_ns[i])
            p = f.pose_at(t)
            if p is not None and selector.offer(np.array([p.x_m, p.y_m, p.yaw_rad])):
                stamps.append(t)
                edges.append(f.keyframe_edge_terms(t))
            i += 1
    rec_t = np.asarray(rec.t, np.int64)
    at = np.minimum(np.searchsorted(rec_t, np.asarray(stamps, np.int64)), len(rec_t) - 1)
    # The error map from each keyframe's recorded state to the next one's.
    maps = []
    for a, b in zip(at[:-1], at[1:]):
        m6 = np.eye(rec.step[0].shape[0])
        for s in rec.step[a + 1:b + 1]:
            m6 = s @ m6
        maps.append(m6)
    return {
        "delta": np.array([e[0] for e in edges[1:]]), "cov": np.array([e[1] for e in edges[1:]]),
        "terms": [e[2] for e in edges[1:]],
        "truth": motion.pose_at(np.asarray(stamps) * 1e-9),
        "rec_mean": np.array([rec.mean[k] for k in at]), "rec_cov": np.array([rec.cov[k] for k in at]),
        "rec_truth": motion.pose_at(rec_t[at] * 1e-9), "maps": np.array(maps),
        "drawn": stream.sensors.errors,
        "speed_mps": np.interp(np.asarray(stamps) * 1e-9, motion.t_s[:-1], motion.v_mps[:-1]),
    }


#: An edge whose two keyframes' true speeds differ by more than this spans a start or a stop.
SPEED_CHANGE_MPS = 0.05


def speed_change_edges(d: dict[str, Any], min_dv_mps: float = SPEED_CHANGE_MPS) -> dict[str, float]:
    """Single edges across a change of speed (their two keyframes' true speeds differ by
    more than ``min_dv_mps``: the starts and stops) against the others: their count, mean
    NEES (all, position part) and the lag ``tau_ms`` that fits their error along the track
    as ``-tau * dv`` (least squares; a pose that trails the truth by ``tau`` gives it)."""
    delta, cov, truth, v = d["delta"], d["cov"], d["truth"], d["speed_mps"]
    dv = np.diff(v)
    parts, along = [], []
    for k in range(len(delta)):
        e = between(delta[k], between(truth[k], truth[k + 1]))
        e[2] = wrap_angle(e[2])
        parts.append(_nees_parts(e, cov[k]))
        along.append(-e[0])  # the edge's error along its own track (delta minus truth)
    n, a = np.array(parts), np.array(along)
    big = np.abs(dv) > min_dv_mps
    tau = -float(np.sum(a[big] * dv[big]) / np.sum(dv[big] ** 2)) if big.any() else float("nan")
    return {"edges": int(big.sum()), "nees": float(n[big, 0].mean()) if big.any() else float("nan"),
            "nees_position": float(n[big, 2].mean()) if big.any() else float("nan"),
            "others": int((~big).sum()), "others_nees": float(n[~big, 0].mean()),
            "others_nees_position": float(n[~big, 2].mean()), "all_nees": float(n[:, 0].mean()),
            "tau_ms": 1e3 * tau}


def _adjoint(p: np.ndarray) -> np.ndarray:
    """SE(2) adjoint of pose ``p``: moves a right perturbation at ``p`` into the parent frame."""
    c, s = math.cos(float(p[2])), math.sin(float(p[2]))
    return np.array([[c, -s, float(p[1])], [s, c, -float(p[0])], [0.0, 0.0, 1.0]])


def _nees_parts(e: np.ndarray, c: np.ndarray) -> tuple[float, float, float]:
    return (float(e @ np.linalg.solve(c, e)), float(e[2] ** 2 / c[2, 2]),
            float(e[:2] @ np.linalg.solve(c[:2, :2], e[:2])))


def chained_nees(d: dict[str, Any], horizons: tuple[int, ...] = HORIZONS) -> dict[int, dict[str, float]]:
    """Per horizon ``N``: mean NEES (all, yaw, position) of chains of ``N`` edges taken as
    independent (the pose graph without loops) and of the filter's joint covariance of the
    same motion."""
    delta, cov, truth = d["delta"], d["cov"], d["truth"]
    m = len(delta)
    pose = np.zeros((m + 1, 3))
    acc = np.zeros((m + 1, 3, 3))  # sum of the edges' covariances in the start's frame
    for k in range(m):
        pose[k + 1] = compose(pose[k], delta[k])
        a = _adjoint(pose[k + 1])
        acc[k + 1] = acc[k] + a @ cov[k] @ a.T
    bacc, bu, bp, bar = bias_chain_covariances(d, pose)
    sw, sg = scale_jacobians(delta, pose)
    wm = _window_model(bp, bar, WINDOW_EDGES)
    out: dict[int, dict[str, float]] = {}
    for h in horizons:
        if h > m:
            continue
        graph, joint, bias, scale, win = [], [], [], [], []
        for i in range(0, m - h + 1, max(1, h // 5)):
            j = i + h
            e = between(between(pose[i], pose[j]), between(truth[i], truth[j]))
            e[2] = wrap_angle(e[2])
            back = np.linalg.inv(_adjoint(pose[j]))
            graph.append(_nees_parts(e, back @ (acc[j] - acc[i]) @ back.T))
            cb = _bias_window_cov(bacc, bu, bp, bar, i, j)
            bias.append(_nees_parts(e, back @ cb @ back.T))
            uw, ug = sw[j] - sw[i], sg[j] - sg[i]
            cs = cb + SCALE_SIGMA["wheel"] ** 2 * np.outer(uw, uw) + SCALE_SIGMA["gyro"] ** 2 * np.outer(ug, ug)
            scale.append(_nees_parts(e, back @ cs @ back.T))
            joint.append(_joint_nees(d, i, j))
            cw = _window_chain_cov(bacc, bu, wm, i, j)
            win.append(_nees_parts(e, back @ cw @ back.T))
        g, jn, bn, sn = np.array(graph), np.array(joint), np.array(bias), np.array(scale)
        wn = np.array(win)
        out[h] = {"windows": len(g), "graph": float(g[:, 0].mean()), "graph_yaw": float(g[:, 1].mean()),
                  "graph_position": float(g[:, 2].mean()), "filter": float(jn[:, 0].mean()),
                  "filter_yaw": float(jn[:, 1].mean()), "filter_position": float(jn[:, 2].mean()),
                  "bias": float(bn[:, 0].mean()), "bias_yaw": float(bn[:, 1].mean()),
                  "bias_position": float(bn[:, 2].mean()), "scales": float(sn[:, 0].mean()),
                  "scales_yaw": float(sn[:, 1].mean()), "scales_position": float(sn[:, 2].mean()),
                  "window": float(wn[:, 0].mean()), "window_yaw": float(wn[:, 1].mean()),
                  "window_position": float(wn[:, 2].mean())}
    return out


def _window_model(p: np.ndarray, ar: np.ndarray, w: int) -> dict[str, np.ndarray]:
    """The bias model of :func:`robotd.graph.bias.bias_window_factor` over windows of ``w``
    edges from the first: per edge ``alpha`` (its bias error's coefficient on the window
    start's) and ``nu`` (the variance of the walk since the window's start); per window
    the start's variance ``P``, the AR(1) coefficient ``A`` to the next window's start and
    the step's variance ``V`` (:func:`robotd.graph.bias.window_chain_edge`)."""
    m = len(p)
    alpha, nu = np.ones(m), np.zeros(m)
    for k in range(m):
        if k % w:
            alpha[k] = alpha[k - 1] * ar[k - 1]
            nu[k] = ar[k - 1] ** 2 * nu[k - 1] + max(p[k] - ar[k - 1] ** 2 * p[k - 1], 1e-14)
    starts = np.arange(0, m, w)
    big_a = np.array([alpha[min(s + w, m) - 1] * ar[min(s + w, m) - 1] for s in starts])
    return {"alpha": alpha, "nu": nu, "ar": ar, "P": p[starts], "A": big_a, "w": np.array([w])}


def _window_chain_cov(acc: np.ndarray, u: list[np.ndarray], wm: dict[str, np.ndarray], i: int, j: int) -> np.ndarray:
    """Covariance (start frame) of edges ``i..j-1`` chained under the windowed bias model
    (:func:`_window_model`), the bias errors marginalised: the edges' conditional
    covariances, the walk inside each window, and the window starts' AR(1) errors."""
    w = int(wm["w"][0])
    alpha, nu, ar = wm["alpha"], wm["nu"], wm["ar"]
    v = acc[j] - acc[i]
    t = np.zeros(3)
    for win in range(i // w, (j - 1) // w + 1):
        ks = range(max(i, win * w), min(j, (win + 1) * w))
        big_u = np.zeros(3)
        for k in ks:
            big_u += u[k] * alpha[k]
            c = nu[k]
            for mm in range(k, ks.stop):  # Cov(nu_k, nu_mm) = nu_k * prod(a_k .. a_{mm-1})
                if c:
                    blk = c * np.outer(u[k], u[mm])
                    v += blk if mm == k else blk + blk.T
                c *= ar[mm]
        pw = wm["P"][win]
        tp = wm["A"][win - 1] * t if win > i // w else np.zeros(3)
        v += pw * np.outer(big_u, big_u) + np.outer(tp, big_u) + np.outer(big_u, tp)
        t = tp + big_u * pw
    return v


def bias_chain_covariances(d: dict[str, Any], pose: np.ndarray) -> tuple[np.ndarray, list[np.ndarray], np.ndarray, np.ndarray]:
    """What the pose graph with bias variables (:mod:`robotd.graph.bias`) gives a chain
    without loops, the bias marginalised: per edge ``k`` its covariance given the bias
    carried to the run's start frame (cumulated, ``(m + 1, 3, 3)``), the bias Jacobian so
    carried ``u_k (3,)``, the bias error's variance at the edge's start ``P_k`` and the AR(1)
    coefficient ``a_k`` to the next edge's."""
    terms = d["terms"]
    m = len(terms)
    acc = np.zeros((m + 1, 3, 3))
    u = []
    for k, t in enumerate(terms):
        a = _adjoint(pose[k + 1])
        acc[k + 1] = acc[k] + a @ t.cov_given_bias @ a.T
        u.append(a @ t.jac_bias)
    p = np.array([t.bias_var for t in terms])
    ar = np.array([t.bias_cov / t.bias_var for t in terms])
    return acc, u, p, ar


#: 1-sigma of the relative scale errors the scale-aware model marginalises, the uniform
#: spreads of the simulated base (:class:`sim.sensors.BaseSensorParams`: wheels +-0.5 %,
#: gyro +-0.3 %) as standard deviations: what an uncalibrated base is known to within.
SCALE_SIGMA = {"wheel": 0.005 / math.sqrt(3.0), "gyro": 0.003 / math.sqrt(3.0)}


def scale_jacobians(delta: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per edge the change of its error per unit relative scale error of the wheels'
    distance and of the gyro (:func:`robotd.graph.bias.scale_jacobian`), carried to the
    run's start frame as the edges' covariances are and cumulated: ``(m + 1, 3)`` each."""
    jw, jg = [], []
    for k, d in enumerate(delta):
        j = _adjoint(pose[k + 1]) @ scale_jacobian(d)
        jw.append(j[:, 0])
        jg.append(j[:, 1])
    return np.cumsum([np.zeros(3)] + jw, axis=0), np.cumsum([np.zeros(3)] + jg, axis=0)


def _bias_window_cov(acc: np.ndarray, u: list[np.ndarray], p: np.ndarray, ar: np.ndarray,
                     i: int, j: int) -> np.ndarray:
    """Covariance (start frame) of edges ``i..j-1`` chained, the bias errors ``db_k``
    (AR(1): ``db_{k+1} = a_k db_k + n_k``, ``Var db_k = P_k``) marginalised: the sum of the
    conditional covariances plus ``Var(sum_k u_k db_k)``, by the recursion over ``k`` of
    ``T_k = sum_{l<=k} u_l Cov(db_l, db_k)``."""
    v = np.zeros((3, 3))
    t = np.zeros(3)
    for k in range(i, j):
        tp = ar[k - 1] * t if k > i else np.zeros(3)
        uk = u[k]
        v += p[k] * np.outer(uk, uk) + np.outer(tp, uk) + np.outer(uk, tp)
        t = tp + uk * p[k]
    return acc[j] - acc[i] + v


def _joint_nees(d: dict[str, Any], i: int, j: int) -> tuple[float, float, float]:
    """NEES of the filter's motion between keyframes ``i`` and ``j`` (its recorded states)
    against its joint covariance (the clone of :mod:`robotd.odometry.relative` over the
    whole window)."""
    return _nees_parts(*_joint_error(d, i, j))


def _joint_error(d: dict[str, Any], i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
    """The error ``(3,)`` of the filter's motion between keyframes ``i`` and ``j`` against
    the truth and its joint covariance ``(3, 3)``, unfloored (:func:`_joint_nees`)."""
    phi = np.eye(d["maps"].shape[1])
    for m6 in d["maps"][i:j]:
        phi = m6 @ phi
    mean_a, cov_a = d["rec_mean"][i], d["rec_cov"][i]
    # (the records' error may be longer than the state's: wheel_rounding's [state, rounding])
    clone = PoseClone(0, mean_a[:3], cov_a[:3, :3], (phi @ cov_a[:, :3])[:6], np.zeros(3))
    mean_b, cov_b = d["rec_mean"][j], d["rec_cov"][j]
    h, c = relative_pose_covariance(mean_b[:3], cov_b[:3, :3], clone)
    c = between_error_covariance(h, c)
    e = between(h, between(d["rec_truth"][i], d["rec_truth"][j]))
    e[2] = wrap_angle(e[2])
    return e, c


#: The kinds of single interval :func:`interval_parts` tells apart, then all of them.
INTERVAL_KINDS = ("straight", "arc", "turn on the spot", "start or stop", "all")
#: An interval whose true heading change is below this is a straight; one whose true
#: translation is below ``SPOT_M`` a turn on the spot.
STRAIGHT_RAD = math.radians(1.0)
SPOT_M = 0.01


def _interval_kind(true_delta: np.ndarray, dv_mps: float) -> str:
    if abs(dv_mps) > SPEED_CHANGE_MPS:
        return "start or stop"
    if math.hypot(float(true_delta[0]), float(true_delta[1])) < SPOT_M:
        return "turn on the spot"
    return "straight" if abs(float(true_delta[2])) < STRAIGHT_RAD else "arc"


def interval_parts(d: dict[str, Any], scale_sigmas: tuple[float, float]) -> dict[str, dict[str, float]]:
    """One interval decomposed, per kind (:data:`INTERVAL_KINDS`): the true error of the
    filter's motion along the track (x of the edge's end frame), across it (y) and in yaw,
    RMS (um, urad), against the 1-sigma the filter's own covariance claims (unfloored, the
    median) and each component's mean ``e_i^2 / C_ii``; the mean NEES (all, yaw, position)
    of the filter's own covariance, of the edge as the graph gets it (floored,
    :func:`robotd.odometry.increments.floor_covariance`), and of the edge with the scale
    variable's prior marginalised (``scale_sigmas``: wheels, gyro; the daemon graph's
    ``bias_scale_window`` over one edge); and the median 1-sigma the edge claims."""
    delta, cov, truth, v = d["delta"], d["cov"], d["truth"], d["speed_mps"]
    sw, sg = scale_sigmas
    rows: dict[str, list[tuple[Any, ...]]] = {k: [] for k in INTERVAL_KINDS}
    for k in range(len(delta)):
        t = between(truth[k], truth[k + 1])
        e_f, c_f = _joint_error(d, k, k + 1)
        e = between(delta[k], t)
        e[2] = wrap_angle(e[2])
        js = scale_jacobian(delta[k])
        c_s = cov[k] + sw ** 2 * np.outer(js[:, 0], js[:, 0]) + sg ** 2 * np.outer(js[:, 1], js[:, 1])
        row = (e_f, c_f, _nees_parts(e_f, c_f), _nees_parts(e, cov[k]), _nees_parts(e, c_s), cov[k])
        rows[_interval_kind(t, float(v[k + 1] - v[k]))].append(row)
        rows["all"].append(row)
    out: dict[str, dict[str, float]] = {}
    for kind, rs in rows.items():
        if not rs:
            continue
        err = np.array([r[0] for r in rs])
        var = np.array([np.diag(r[1]) for r in rs])
        edge_var = np.array([np.diag(r[5]) for r in rs])
        rms = np.sqrt((err ** 2).mean(axis=0)) * 1e6
        sd = np.sqrt(np.median(var, axis=0)) * 1e6
        sd_edge = np.sqrt(np.median(edge_var, axis=0)) * 1e6
        comp = (err ** 2 / var).mean(axis=0)
        res: dict[str, float] = {"intervals": len(rs)}
        for n, name in enumerate(("along", "across", "yaw")):
            res[f"{name}_rms"], res[f"{name}_sigma"], res[f"{name}_nees"] = float(rms[n]), float(sd[n]), float(comp[n])
            res[f"{name}_sigma_edge"] = float(sd_edge[n])
        for col, name in ((2, "filter"), (3, "edge"), (4, "edge_scale")):
            n3 = np.array([r[col] for r in rs]).mean(axis=0)
            res[name], res[f"{name}_yaw"], res[f"{name}_position"] = (float(x) for x in n3)
        out[kind] = res
    return out


#: What ``--without`` can take out of the simulated base (:class:`sim.sensors.BaseSensorParams`).
WITHOUT = {
    "gyro_bias": {"gyro_bias_degps_range": (0.0, 0.0), "gyro_bias_walk_degps_sqrt_s": 0.0},
    "scales": {"wheel_scale_error_max": 0.0, "wheel_diff_error_max": 0.0, "gyro_scale_error_max": 0.0},
    "slip_events": {"slip_event_rate_hz": 0.0},
}


def _calibration(path: Path | None = None) -> Any:
    """The calibration file at ``path`` (default: the demo's shipped one), read."""
    from robotd.app.demo import shipped_calibration
    from robotd.io.calibfile import read_calibration

    path = path if path is not None else shipped_calibration()
    if path is None:
        raise SystemExit("the demo's shipped calibration is missing")
    if not Path(path).is_file():
        raise SystemExit(f"{path}: no such calibration file")
    return read_calibration(path)


def daemon_params(noise_model: str = "config", slip_gate_sigma: float = 0.0,
                  calibration: Path | None = None) -> EkfParams:
    """The noise model of the daemon's wheel + gyro filter with the demo's calibration
    (:func:`robotd.app.assemble.build_odometry`: the config's ``[odometry]`` with the
    calibration's gyro noise density; ``noise_model``: ``[odometry] noise_model``, with
    "calibration" the calibration's fitted sensor noise and white accelerations;
    ``slip_gate_sigma``: ``[odometry] slip_gate_sigma``, the wheel slip test);
    ``calibration``: another calibration file than the demo's."""
    from robotd.base.config import replace
    from robotd.app.assemble import build_odometry
    from robotd.base.config import Config

    # the wheel + gyro filter whose edges the graph gets (the twin when visual odometry is fused)
    cfg = replace(Config(), "odometry", noise_model=noise_model, slip_gate_sigma=slip_gate_sigma)
    return build_odometry(cfg, _calibration(calibration)).wheel_gyro.params


def shipped_geometry(calibration: Path | None = None) -> tuple[Any, float]:
    """The wheel radii, wheel base and gyro scale the daemon's filter takes from the demo's
    shipped calibration (or the file ``calibration``; :func:`robotd.app.assemble.build_odometry`):
    ``(DiffDriveParams, gyro_scale)``."""
    from robotd.base.config import Config
    from robotd.odometry.kinematics import DiffDriveParams

    model = _calibration(calibration).odometry
    if model is None:
        raise SystemExit(f"{calibration or 'the shipped calibration'}: no odometry model")
    drive = DiffDriveParams.from_config(Config().robot, wheel_base_m=model.wheel_base_m,
                                        wheel_radius_left_m=model.wheel_radius_left_m,
                                        wheel_radius_right_m=model.wheel_radius_right_m)
    return drive, model.gyro_scale


def daemon_scale_sigmas(calibration: Path | None = None,
                        wear: tuple[float, float] | None = None) -> tuple[float, float]:
    """The prior of the daemon graph's scale variable with the demo's shipped calibration
    (or the file ``calibration``) and the default ``[pose_graph] scale_wear`` and
    ``scale_wear_gyro`` (``wear``: those two instead; :func:`robotd.app.assemble.scale_prior_sigmas`)."""
    from robotd.app.assemble import scale_prior_sigmas
    from robotd.base.config import Config, replace

    cfg = Config()
    if wear is not None:
        cfg = replace(cfg, "pose_graph", scale_wear=wear[0], scale_wear_gyro=wear[1])
    return scale_prior_sigmas(cfg, _calibration(calibration))


def geometry_errors(calibration: Path | None, drawn: Any) -> dict[str, float]:
    """The calibration's wheel radii, wheel base and gyro scale against the base's drawn
    values (relative errors), its mean radius (the wheels' distance scale) and gyro scale
    against theirs, and its own 1-sigmas of the wheel base and gyro scale."""
    r0, b0 = BaseSensorParams().drive.wheel_radius_m, BaseSensorParams().drive.wheel_base_m
    m = _calibration(calibration).odometry
    tl, tr = r0 * (1 + drawn.left_radius_error), r0 * (1 + drawn.right_radius_error)
    tb, ts = b0 * (1 + drawn.wheel_base_error), 1 + drawn.gyro_scale_error
    return {"left_radius": m.wheel_radius_left_m / tl - 1, "right_radius": m.wheel_radius_right_m / tr - 1,
            "distance": (m.wheel_radius_left_m + m.wheel_radius_right_m) / (tl + tr) - 1,
            "wheel_base": m.wheel_base_m / tb - 1, "gyro_scale": m.gyro_scale / ts - 1,
            "wheel_base_sigma": m.wheel_base_sigma_m / m.wheel_base_m, "gyro_scale_sigma": m.gyro_scale_sigma / m.gyro_scale}


def odometry_part(seeds: int, route: str, keyframe_m: float, without: tuple[str, ...] = (),
                  ekf: dict[str, float] | None = None, cost_seeds: int = 0,
                  true_model: bool = False, daemon_model: bool = False,
                  cost_models: tuple[str, ...] = ("independent", "bias_window", "bias"),
                  daemon_graph_seeds: int = 0, noise_model: str = "config",
                  slip_gate_sigma: float = 0.0, shipped: bool = False,
                  daemon_models: tuple[str, ...] = ("independent", "bias_window"),
                  own_calibration: str | None = None,
                  scale_wear: tuple[float, float] | None = None) -> dict[str, Any]:
    """``scale_wear``: ``[pose_graph] scale_wear`` and ``scale_wear_gyro`` for the daemon
    graph's scale prior (default: the config's defaults). ``own_calibration``: a calibration file per seed (``{seed}`` in the name: what that
    seed's own calibration drive gave, ``robotd calibrate odometry``), whose wheel radii,
    wheel base and gyro scale the filter takes on that seed's base, with its noise model
    (``daemon_model``) and its scale prior (``daemon_graph``), as ``robotd demo --seed N``
    runs with that file; ``shipped``: the demo's shipped file on every seed."""
    sensors = BaseSensorParams()
    for name in without:  # the same base without these errors: what each costs
        sensors = dataclasses.replace(sensors, **WITHOUT[name])

    def seed_params(cal: Path | None) -> EkfParams:
        return (EkfParams(**(ekf or {})) if not daemon_model
                else dataclasses.replace(daemon_params(noise_model, slip_gate_sigma, cal), **(ekf or {})))

    params = seed_params(None)
    per_seed = []
    for seed in range(seeds):
        t0 = time.monotonic()
        cal = Path(own_calibration.format(seed=seed)) if own_calibration is not None else None
        p_seed = seed_params(cal) if cal is not None else params
        d = drive_edges(route, seed, keyframe_m, sensors, p_seed, true_model,
                        shipped_geometry(cal) if (shipped or cal is not None) else None)
        res = chained_nees(d)
        sigmas = daemon_scale_sigmas(cal, scale_wear)
        cost = graph_cost(d, seed, (SCALE_SIGMA["wheel"], SCALE_SIGMA["gyro"]), cost_models) if seed < cost_seeds else None
        e = d["drawn"]
        sc = speed_change_edges(d)
        per_seed.append({"seed": seed, "edges": len(d["delta"]), "horizons": {str(k): v for k, v in res.items()},
                         "cost": cost, "speed_change": sc, "interval": interval_parts(d, sigmas),
                         "daemon_graph": (daemon_graph(d, seed, models=daemon_models, scale_sigmas=sigmas)
                                          if seed < daemon_graph_seeds else None),
                         "calibration": str(cal) if cal is not None else ("shipped" if shipped else None),
                         "scale_sigmas": list(sigmas),
                         "params": dataclasses.asdict(p_seed) if cal is not None else None,
                         "geometry_errors": (geometry_errors(cal, e) if (shipped or cal is not None) else None),
                         "drawn": {"wheel_base_error": e.wheel_base_error,
                                   "radius_error_left": e.left_radius_error,
                                   "radius_error_right": e.right_radius_error,
                                   "gyro_scale_error": e.gyro_scale_error,
                                   "gyro_bias0_degps": math.degrees(e.gyro_bias0_radps)}})
        log(f"seed {seed}: {len(d['delta'])} edges, " + ", ".join(
            f"N={h} {v['graph']:.2f}/{v['scales']:.2f}" for h, v in res.items())
            + f"  [{time.monotonic() - t0:.0f} s]")
        log(f"seed {seed}: {sc['edges']} single edges across a start or stop (speed change > {SPEED_CHANGE_MPS} m/s): "
            f"NEES {sc['nees']:.2f} (position {sc['nees_position']:.2f}), lag {sc['tau_ms']:.1f} ms; "
            f"the other {sc['others']}: {sc['others_nees']:.2f} ({sc['others_nees_position']:.2f})")
    return {"route": route, "keyframe_m": keyframe_m, "without": list(without), "ekf": ekf or {},
            "true_model": true_model, "daemon_model": daemon_model, "noise_model": noise_model,
            "slip_gate_sigma": slip_gate_sigma, "shipped_geometry": shipped, "own_calibration": own_calibration,
            "daemon_models": list(daemon_models), "scale_sigmas": list(daemon_scale_sigmas(None, scale_wear)),
            "scale_wear": list(scale_wear) if scale_wear is not None else None,
            "params": dataclasses.asdict(params), "per_seed": per_seed}


#: The chain models the bench compares (keys of a horizon's results) and their names.
MODELS = {"graph": "independent edges", "window": "bias per window of 10 edges", "bias": "bias variables",
          "scales": "bias + scale variables", "filter": "filter's joint covariance"}


def odometry_rows(part: dict[str, Any], kind: str = "scales") -> tuple[list[str], list[list[Any]]]:
    """Per seed and horizon the mean NEES of the chains of ``kind`` (a key of :data:`MODELS`)."""
    head = ["seed", "edges"] + [f"N={h}" for h in HORIZONS]
    rows: list[list[Any]] = []
    for r in part["per_seed"]:
        hz = r["horizons"]
        rows.append([r["seed"], r["edges"]] + [f"{hz[str(h)][kind]:.2f}" if str(h) in hz else "-" for h in HORIZONS])
    means = []
    for h in HORIZONS:
        g = [r["horizons"][str(h)][kind] for r in part["per_seed"] if str(h) in r["horizons"]]
        means.append(f"{np.mean(g):.2f}" if g else "-")
    rows.append(["mean", ""] + means)
    return head, rows


def geometry_rows(part: dict[str, Any]) -> tuple[list[str], list[list[Any]]]:
    """Per seed the calibration's geometry against the base's drawn values and the scale prior
    (empty for a run with the nominal or the true geometry, or written before they were stored)."""
    head = ["seed", "calibration", "left radius", "right radius", "distance (mean radius)", "wheel base",
            "gyro scale", "scale prior (wheels, gyro)"]
    rows: list[list[Any]] = []
    for r in part["per_seed"]:
        g = r.get("geometry_errors")
        if not g:
            continue
        rows.append([r["seed"], f"`{r['calibration']}`", f"{100 * g['left_radius']:+.3f} %",
                     f"{100 * g['right_radius']:+.3f} %", f"{100 * g['distance']:+.3f} %",
                     f"{100 * g['wheel_base']:+.3f} % ({100 * g['wheel_base_sigma']:.3f})",
                     f"{100 * g['gyro_scale']:+.3f} % ({100 * g['gyro_scale_sigma']:.3f})",
                     f"{100 * r['scale_sigmas'][0]:.3f} %, {100 * r['scale_sigmas'][1]:.3f} %"])
    return head, rows


def speed_change_rows(part: dict[str, Any]) -> tuple[list[str], list[list[Any]]]:
    """Per seed the single edges across a start or a stop against the others
    (:func:`speed_change_edges`); empty for a result written before they were stored."""
    head = ["seed", "edges across a start or stop", "their NEES (position part)", "lag tau (ms)",
            "other edges", "their NEES (position part)"]
    rows: list[list[Any]] = []
    for r in part["per_seed"]:
        sc = r.get("speed_change")
        if sc:
            rows.append([r["seed"], sc["edges"], f"{sc['nees']:.2f} ({sc['nees_position']:.2f})", f"{sc['tau_ms']:.1f}",
                         sc["others"], f"{sc['others_nees']:.2f} ({sc['others_nees_position']:.2f})"])
    return head, rows


def interval_rows(part: dict[str, Any]) -> tuple[list[str], list[list[Any]]]:
    """One interval decomposed (:func:`interval_parts`), per kind pooled over the seeds
    (weighted by their intervals; the claimed 1-sigma the seeds' mean median), then per seed
    all its intervals; empty for a result written before it was stored."""
    head = ["kind", "intervals", "along: true RMS / filter's 1-sigma / edge's (um), NEES",
            "across: the same", "yaw: true RMS / filter's / edge's (urad), NEES",
            "filter's own (yaw, position)", "edge, floored", "edge + scale prior"]
    runs = [r for r in part["per_seed"] if r.get("interval")]
    if not runs:
        return head, []

    def row(label: Any, parts: list[dict[str, float]]) -> list[Any]:
        n = np.array([p["intervals"] for p in parts], float)
        w = n / n.sum()
        cells: list[Any] = [label, int(n.sum())]
        for name in ("along", "across", "yaw"):
            rms = math.sqrt(float(np.sum(w * np.array([p[f"{name}_rms"] ** 2 for p in parts]))))
            sd = float(np.mean([p[f"{name}_sigma"] for p in parts]))
            sde = float(np.mean([p[f"{name}_sigma_edge"] for p in parts]))
            cells.append(f"{rms:.0f} / {sd:.0f} / {sde:.0f}, {float(np.sum(w * [p[f'{name}_nees'] for p in parts])):.2f}")
        for key in ("filter", "edge", "edge_scale"):
            m = [float(np.sum(w * [p[key + sfx] for p in parts])) for sfx in ("", "_yaw", "_position")]
            cells.append(f"{m[0]:.2f} ({m[1]:.2f}, {m[2]:.2f})")
        return cells

    rows = [row(kind, [r["interval"][kind] for r in runs if kind in r["interval"]])
            for kind in INTERVAL_KINDS if any(kind in r["interval"] for r in runs)]
    rows += [row(f"seed {r['seed']}, all", [r["interval"]["all"]]) for r in runs]
    return head, rows


def odometry_model_rows(part: dict[str, Any]) -> tuple[list[str], list[list[Any]]]:
    """Per horizon and model: the mean over seeds (yaw part, position part) and the seeds' range."""
    head = ["N edges"] + list(MODELS.values())
    rows = []
    for h in HORIZONS:
        rs = [r["horizons"][str(h)] for r in part["per_seed"] if str(h) in r["horizons"]]
        if not rs:
            continue
        row: list[Any] = [h]
        for k in MODELS:
            v = [r[k] for r in rs]
            row.append(f"{np.mean(v):.2f} ({np.mean([r[k + '_yaw'] for r in rs]):.2f}, "
                       f"{np.mean([r[k + '_position'] for r in rs]):.2f}) [{min(v):.2f}-{max(v):.2f}]")
        rows.append(row)
    return head, rows


def cost_rows(part: dict[str, Any]) -> tuple[list[str], list[list[Any]]]:
    head = ["seed", "keyframes", "loops", "model", "iSAM2 ms / keyframe", "batch LM s", "ATE iSAM2 (m)",
            "ATE batch (m)", "ATE odometry (m)"]
    rows: list[list[Any]] = []
    for r in part["per_seed"]:
        c = r.get("cost")
        if not c:
            continue
        base = c["independent"]
        for model in ("independent", "bias_window", "bias", "bias_scales"):
            if model not in c:
                continue
            m = c[model]
            ratio = "" if model == "independent" else (
                f" (x{m['isam2_ms_per_keyframe'] / base['isam2_ms_per_keyframe']:.1f})")
            lm_ratio = "" if model == "independent" else f" (x{m['batch_lm_s'] / base['batch_lm_s']:.0f})"
            rows.append([r["seed"], c["keyframes"], c["loops"], model,
                         f"{m['isam2_ms_per_keyframe']:.2f}{ratio}", f"{m['batch_lm_s']:.2f}{lm_ratio}",
                         f"{m['ate_isam2_m']:.4f}", f"{m['ate_batch_m']:.4f}", f"{m['ate_odometry_m']:.3f}"])
    return head, rows


# --------------------------------------------------------------------------- graph cost


def _loops_from_truth(truth: np.ndarray, rng: np.random.Generator, every: int = 25,
                      min_gap: int = 200, radius_m: float = 0.2, sigma: float = 1e-3
                      ) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """Loop edges as the floor camera would give them on a revisit: every ``every``-th
    keyframe, to the nearest one at least ``min_gap`` keyframes before it within
    ``radius_m``, the true relative pose with ``sigma`` (m and rad) of noise."""
    loops = []
    cov = np.eye(3) * sigma * sigma
    for j in range(min_gap, len(truth), every):
        dist = np.hypot(truth[:j - min_gap, 0] - truth[j, 0], truth[:j - min_gap, 1] - truth[j, 1])
        if not len(dist) or dist.min() > radius_m:
            continue
        i = int(np.argmin(dist))
        delta = between(truth[i], truth[j]) + sigma * rng.standard_normal(3)
        loops.append((i, j, delta, cov))
    return loops


#: Edges per window of the windowed bias model (``bias_window``): iSAM2's fold (:class:`robotd.graph.incremental.IncrementalParams`).
WINDOW_EDGES = 10


def graph_cost(d: dict[str, Any], seed: int, scale_sigmas: tuple[float, float],
               models: tuple[str, ...] = ("independent", "bias_window", "bias", "bias_scales"),
               window_edges: int = WINDOW_EDGES) -> dict[str, Any]:
    """Build the seed's keyframes one at a time into iSAM2 (with loop edges from the
    truth, :func:`_loops_from_truth`), once with independent edges (``BetweenFactor``, the
    daemon's) and once with the bias variables (:mod:`robotd.graph.bias`, with a shared
    scale variable when ``scale_sigmas``): time per keyframe, the final batch
    Levenberg-Marquardt's time from the odometry guess, and each estimate's ATE (m)."""
    import gtsam

    from robotd.graph.bias import (
        BiasEdge,
        bias_chain_factor,
        bias_edge_factor,
        bias_key,
        bias_prior_factor,
        bias_window_factor,
        scale_key,
        scale_prior_factor,
        window_chain_edge,
    )
    from robotd.graph.factors import anchor_factor

    truth = d["truth"]
    deltas, covs, terms = d["delta"], d["cov"], d["terms"]
    loops = _loops_from_truth(truth, np.random.default_rng(seed))
    by_end: dict[int, list[tuple[int, int, np.ndarray, np.ndarray]]] = {}
    for lp in loops:
        by_end.setdefault(lp[1], []).append(lp)
    # The pose graph's frame is the first keyframe's truth (the anchor).
    out: dict[str, Any] = {"keyframes": len(deltas) + 1, "loops": len(loops)}
    for model in models:
        scales = scale_sigmas if model == "bias_scales" else None
        window: list[tuple[BiasEdge, int]] = []  # the open window's edges, their plain factors' indices
        prev_window: list[BiasEdge] = []
        isam = gtsam.ISAM2()
        batch = gtsam.NonlinearFactorGraph()
        guess = gtsam.Values()
        p = gtsam.Pose2(*map(float, truth[0]))
        t_inc = 0.0
        for k in range(len(deltas) + 1):
            fg = gtsam.NonlinearFactorGraph()
            vals = gtsam.Values()
            remove: list[int] = []
            if k == 0:
                fg.add(anchor_factor(0, truth[0]))
                vals.insert(0, p)
                if model in ("bias", "bias_scales"):
                    fg.add(bias_prior_factor(0, terms[0].bias_radps, terms[0].bias_var))
                    vals.insert(bias_key(0), np.array([terms[0].bias_radps]))
                    if scales is not None:
                        fg.add(scale_prior_factor(0, scales))
                        vals.insert(scale_key(0), np.zeros(2))
            else:
                dk = deltas[k - 1]
                p = p.compose(gtsam.Pose2(*map(float, dk)))
                vals.insert(k, p)
                if model == "independent" or (model == "bias_window" and len(window) + 1 < window_edges):
                    fg.add(gtsam.BetweenFactorPose2(k - 1, k, gtsam.Pose2(*map(float, dk)),
                                                    gtsam.noiseModel.Gaussian.Covariance(covs[k - 1])))
                if model == "bias_window":
                    t = terms[k - 1]
                    window.append((BiasEdge(k - 1, k, dk, t.cov_given_bias, t.jac_bias, t.bias_radps, t.bias_var,
                                            t.bias_end_radps, t.bias_end_var, t.bias_cov), -1))
                    if len(window) == window_edges:  # closed: one factor replaces the window's plain edges
                        w_edges = [e for e, _ in window]
                        remove = [i for _, i in window[:-1]]
                        fg.add(bias_window_factor(w_edges))
                        start = w_edges[0].from_id
                        vals.insert(bias_key(start), np.array([w_edges[0].bias_radps]))
                        if prev_window:
                            fg.add(bias_chain_factor(window_chain_edge(prev_window)))
                        else:
                            fg.add(bias_prior_factor(start, w_edges[0].bias_radps, w_edges[0].bias_var))
                        prev_window, window = w_edges, []
                elif model != "independent":
                    t = terms[k - 1]
                    e = BiasEdge(k - 1, k, dk, t.cov_given_bias, t.jac_bias, t.bias_radps, t.bias_var,
                                 t.bias_end_radps, t.bias_end_var, t.bias_cov)
                    fg.add(bias_edge_factor(e, None if scales is None else 0))
                    fg.add(bias_chain_factor(e))
                    vals.insert(bias_key(k), np.array([t.bias_end_radps]))
            for i, j, delta, cov in by_end.get(k, []):
                fg.add(gtsam.BetweenFactorPose2(i, j, gtsam.Pose2(*map(float, delta)),
                                                gtsam.noiseModel.Gaussian.Covariance(cov)))
            t0 = time.perf_counter()
            res = isam.update(fg, vals, remove) if remove else isam.update(fg, vals)
            t_inc += time.perf_counter() - t0
            if model == "bias_window" and k > 0 and window:  # the open window's newest plain edge
                window[-1] = (window[-1][0], int(res.getNewFactorsIndices()[0]))
            for n in range(fg.size()):
                # the batch keeps what iSAM2 ends with: a closed window's factor, not its plain edges
                if not (model == "bias_window" and n == 0 and k > 0 and window):
                    batch.add(fg.at(n))
            guess.insert(vals)
        for e, _ in window:  # the open window's plain edges stay
            batch.add(gtsam.BetweenFactorPose2(e.from_id, e.to_id, gtsam.Pose2(*map(float, e.delta)),
                                               gtsam.noiseModel.Gaussian.Covariance(covs[e.from_id])))
        est = isam.calculateEstimate()
        t0 = time.perf_counter()
        lm = gtsam.LevenbergMarquardtOptimizer(batch, guess).optimize()
        t_lm = time.perf_counter() - t0

        def ate(values: Any) -> float:
            xy = np.array([[values.atPose2(k).x(), values.atPose2(k).y()] for k in range(len(truth))])
            return float(np.sqrt(np.mean(np.sum((xy - truth[:, :2]) ** 2, axis=1))))

        out[model] = {"isam2_ms_per_keyframe": 1e3 * t_inc / (len(deltas) + 1), "batch_lm_s": t_lm,
                      "ate_isam2_m": ate(est), "ate_batch_m": ate(lm), "ate_odometry_m": ate(guess)}
    return out


# --------------------------------------------------------------------------- the daemon's graph

#: The daemon's odometry models (``[pose_graph] odometry_model``) the daemon-graph part runs.
DAEMON_MODELS = ("independent", "bias_window", "bias_scale_window")


def daemon_graph(d: dict[str, Any], seed: int, max_chains: int = 400, solve_every: int = 200,
                 horizons: tuple[int, ...] = HORIZONS,
                 models: tuple[str, ...] = ("independent", "bias_window"),
                 scale_sigmas: tuple[float, float] | None = None) -> dict[str, Any]:
    """The seed's edges (with their bias terms) in the daemon's own graph,
    :class:`robotd.graph.incremental.IncrementalGraph`, once per ``odometry_model``.

    NEES: the keyframes added one at a time without loops; per horizon ``N`` the chains
    ``i -> i + N`` of :func:`chained_nees` (one every ``N/5`` edges), at most ``max_chains``
    of them evenly spread over the drive (over 1 and 10 edges), the relative pose's
    covariance from iSAM2's joint marginal of the two keyframes (in the end's frame, as
    :meth:`IncrementalGraph.loop_chi2` forms it), its error against the truth.
    Cost: the same keyframes with loop edges from the truth (:func:`_loops_from_truth`)
    and a full solve every ``solve_every`` keyframes and at the end (which folds iSAM2),
    as the pose-graph stage runs it: CPU seconds (this process) of the keyframe and loop
    updates per keyframe, of the full solves, and the final ATE (m). ``models``: of
    :data:`DAEMON_MODELS`; ``"bias_scale_window"`` with the prior ``scale_sigmas`` (default
    :func:`daemon_scale_sigmas`; the scale variable's estimate at the end is reported, ``scale``)."""
    from robotd.graph.incremental import IncrementalGraph, IncrementalParams

    deltas, covs, terms, truth = d["delta"], d["cov"], d["terms"], d["truth"]
    m = len(deltas)
    loops = _loops_from_truth(truth, np.random.default_rng(seed))
    by_end: dict[int, list[tuple[int, int, np.ndarray, np.ndarray]]] = {}
    for lp in loops:
        by_end.setdefault(lp[1], []).append(lp)
    infos = [np.linalg.inv(c) for c in covs]
    out: dict[str, Any] = {"keyframes": m + 1, "loops": len(loops)}
    gp = {"scale_sigmas": scale_sigmas if scale_sigmas is not None else daemon_scale_sigmas()}
    for model in models:
        res: dict[str, Any] = {}
        g = IncrementalGraph(IncrementalParams(odometry_model=model, **gp))
        g.add_first(0, truth[0])
        for k in range(m):
            g.add_keyframe(k + 1, k, deltas[k], infos[k], tuple(terms[k]))
        ids, est = g.estimate()
        nees: dict[str, dict[str, float]] = {}
        for h in horizons:
            if h > m:
                continue
            parts = []
            starts = np.arange(0, m - h + 1, max(1, h // 5))
            if len(starts) > max_chains:
                starts = starts[np.linspace(0, len(starts) - 1, max_chains).round().astype(int)]
            for i in starts.tolist():
                j = i + h
                hp = between(est[i], est[j])
                jm = g.joint_marginal_covariance(i, j)
                a = np.hstack([-np.linalg.inv(_adjoint(hp)), np.eye(3)])  # [-Ad(h^-1), I]
                c = a @ jm @ a.T
                e = between(hp, between(truth[i], truth[j]))
                e[2] = wrap_angle(e[2])
                parts.append(_nees_parts(e, c))
            pn = np.array(parts)
            nees[str(h)] = {"chains": len(pn), "all": float(pn[:, 0].mean()), "yaw": float(pn[:, 1].mean()),
                            "position": float(pn[:, 2].mean())}
        res["nees"] = nees
        g = IncrementalGraph(IncrementalParams(odometry_model=model, **gp))
        t_kf = t_solve = 0.0
        solves = 0
        t0 = time.process_time()
        g.add_first(0, truth[0])
        t_kf += time.process_time() - t0
        for k in range(m):
            t0 = time.process_time()
            g.add_keyframe(k + 1, k, deltas[k], infos[k], tuple(terms[k]))
            for i, j, delta, cov in by_end.get(k + 1, []):
                g.add_loop(i, j, delta, np.linalg.inv(cov))
            t_kf += time.process_time() - t0
            if (k + 1) % solve_every == 0 or k + 1 == m:
                t0 = time.process_time()
                g.resolve()
                t_solve += time.process_time() - t0
                solves += 1
        ids, est = g.estimate()
        res["cpu_ms_per_keyframe"] = 1e3 * t_kf / (m + 1)
        res["solve_cpu_s"] = t_solve
        res["solves"] = solves
        res["ate_m"] = float(np.sqrt(np.mean(np.sum((est[:, :2] - truth[ids, :2]) ** 2, axis=1))))
        scale = g.scale_estimate()
        res["scale"] = None if scale is None else [float(x) for x in scale]
        out[model] = res
        log(f"seed {seed} daemon graph {model}: " + ", ".join(f"N={h} {v['all']:.2f}" for h, v in nees.items())
            + f"; {res['cpu_ms_per_keyframe']:.2f} ms/keyframe, solves {t_solve:.1f} s, ATE {res['ate_m']:.4f} m")
    return out


def daemon_graph_rows(part: dict[str, Any]) -> tuple[list[str], list[list[Any]]]:
    """Per horizon and model: the mean NEES over seeds in the daemon's graph (yaw, position) [seeds]."""
    runs = [r["daemon_graph"] for r in part["per_seed"] if r.get("daemon_graph")]
    models = _daemon_models(part)
    head = ["N edges"] + [f"`{m}`" for m in models] + [f"`{m}` pooled" for m in models]
    rows: list[list[Any]] = []
    for h in HORIZONS:
        row: list[Any] = [h]
        pooled: list[Any] = []
        for model in models:
            v = [r[model]["nees"][str(h)] for r in runs if str(h) in r[model]["nees"]]
            if not v:
                row.append("-")
                pooled.append("-")
                continue
            a = [x["all"] for x in v]
            row.append(f"{np.mean(a):.2f} ({np.mean([x['yaw'] for x in v]):.2f}, "
                       f"{np.mean([x['position'] for x in v]):.2f}) [{min(a):.2f}-{max(a):.2f}]")
            pooled.append(f"{pooled_nees(v):.2f}")
        rows.append(row + pooled)
    return head, rows


def _daemon_models(part: dict[str, Any]) -> list[str]:
    """The daemon-graph models a run measured (runs before ``--daemon-models``: the first two)."""
    return list(part.get("daemon_models", DAEMON_MODELS[:2]))


def pooled_nees(per_seed: list[dict[str, float]]) -> float:
    """The NEES of all the seeds' chains together (each seed's mean weighted by its chains)."""
    n = np.array([x["chains"] for x in per_seed], float)
    return float(np.sum(n * np.array([x["all"] for x in per_seed])) / np.sum(n))


def daemon_graph_seed_rows(part: dict[str, Any], model: str) -> tuple[list[str], list[list[Any]]]:
    head = ["seed"] + [f"N={h}" for h in HORIZONS]
    rows: list[list[Any]] = []
    per_h: dict[int, list[float]] = {h: [] for h in HORIZONS}
    for r in part["per_seed"]:
        dg = r.get("daemon_graph")
        if dg:
            nees = dg[model]["nees"]
            rows.append([r["seed"]] + [f"{nees[str(h)]['all']:.2f}" if str(h) in nees else "-" for h in HORIZONS])
            for h in HORIZONS:
                if str(h) in nees:
                    per_h[h].append(nees[str(h)]["all"])
    if len(rows) > 1:
        rows.append(["mean"] + [f"{np.mean(per_h[h]):.2f}" if per_h[h] else "-" for h in HORIZONS])
    return head, rows


def honest_spread(edges: int, horizon: int) -> dict[str, float]:
    """What an honest model's mean NEES over one drive's chains of ``horizon`` edges can
    be: the drive holds ``k = edges // horizon`` disjoint chains, each error's NEES chi2 with
    3 degrees of freedom, so their mean is chi2(3k) / k (the overlapping chains the bench
    also takes add little; an error every chain shares, as the scale, widens it further).
    ``k``, its 5 and 95 % points and the chance it falls within 2-4."""
    from scipy.stats import chi2

    k = max(1, edges // horizon)
    return {"k": k, "p5": float(chi2.ppf(0.05, 3 * k) / k), "p95": float(chi2.ppf(0.95, 3 * k) / k),
            "within_2_4": float(chi2.cdf(4 * k, 3 * k) - chi2.cdf(2 * k, 3 * k))}


def honest_spread_rows(part: dict[str, Any]) -> tuple[list[str], list[list[Any]]]:
    """Per horizon the spread of an honest per-seed mean (:func:`honest_spread`) at the
    seeds' fewest edges, and the chance that every seed falls within 2-4."""
    edges = min(r["edges"] for r in part["per_seed"])
    n = len(part["per_seed"])
    head = ["N edges", "disjoint chains per seed", "90 % of an honest seed's mean", "chance within 2-4",
            f"chance all {n} seeds within 2-4"]
    rows: list[list[Any]] = []
    for h in HORIZONS:
        if h > edges:
            continue
        sp = honest_spread(edges, h)
        rows.append([h, sp["k"], f"{sp['p5']:.2f}-{sp['p95']:.2f}", f"{sp['within_2_4']:.2f}",
                     f"{sp['within_2_4'] ** n:.2f}"])
    return head, rows


def daemon_cost_rows(part: dict[str, Any]) -> tuple[list[str], list[list[Any]]]:
    head = ["seed", "keyframes", "loops", "model", "CPU ms / keyframe", "full solves CPU s", "ATE (m)",
            "scale estimate (wheel, gyro)"]
    rows: list[list[Any]] = []
    for r in part["per_seed"]:
        dg = r.get("daemon_graph")
        if not dg:
            continue
        base = dg["independent"]
        for model in _daemon_models(part):
            m = dg[model]
            ratio = "" if model == "independent" else f" (x{m['cpu_ms_per_keyframe'] / base['cpu_ms_per_keyframe']:.2f})"
            sratio = "" if model == "independent" else f" (x{m['solve_cpu_s'] / base['solve_cpu_s']:.1f})"
            rows.append([r["seed"], dg["keyframes"], dg["loops"], f"`{model}`",
                         f"{m['cpu_ms_per_keyframe']:.2f}{ratio}", f"{m['solve_cpu_s']:.2f}{sratio} ({m['solves']})",
                         f"{m['ate_m']:.4f}",
                         "-" if m.get("scale") is None else f"{100 * m['scale'][0]:+.3f} %, {100 * m['scale'][1]:+.3f} %"])
    return head, rows


# --------------------------------------------------------------------------- loops


def _floor(name: str) -> Any:
    try:
        from bench.floor_common import bench_floors, printed_floor
    except ImportError:  # run as a script
        from floor_common import bench_floors, printed_floor
    if name == "planks":
        return printed_floor(0).floor
    return next(f.floor for f in bench_floors() if f.name == name)


def loop_part(floors: list[str], n_pairs: int, seed: int) -> dict[str, Any]:
    """Per floor and mode: the NEES of the loop edges the detector would give for rendered
    pairs, with its covariance and with the rigid fit's alone."""
    from robotd.app.demo import shipped_calibration
    from robotd.base.camera import FloorCameraModel
    from robotd.base.geometry import rigid_fit_2d, rigid_fit_2d_covariance
    from robotd.evaluation.groundtruth import LOOP_R
    from robotd.floor.descriptor import decode, extract
    from robotd.floor.detector import MIN_POINT_SIGMA_M, loop_transform
    from robotd.floor.match import local_score
    from robotd.floor.vo import floor_point_pairs
    from robotd.io.calibfile import read_calibration
    from sim.pairs import random_pairs

    path = shipped_calibration()
    loop_cal = read_calibration(path).loop if path is not None else None
    if loop_cal is None:
        raise SystemExit("the demo's shipped calibration (loop thresholds) is missing")
    cam = FloorCameraModel.default()
    out: dict[str, Any] = {}
    shared: dict[str, dict[str, float]] = {}
    for name in floors:
        samples: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]] = []  # see loop_noise_ml
        t0 = time.monotonic()
        pairs = random_pairs(_floor(name), cam, n_pairs, np.random.default_rng(seed),
                             near_fraction=1.0, max_offset_m=0.25)
        log(f"{name}: {n_pairs} pairs rendered in {time.monotonic() - t0:.0f} s")
        per_mode = {}
        for mode in range(1, 7):
            threshold = loop_cal.for_mode(mode)
            if threshold is None:
                continue
            da = [decode(extract(im, mode)) for im in pairs.images_a]
            db = [decode(extract(im, mode)) for im in pairs.images_b]
            now, fit, inliers, false, by_turn = [], [], [], 0, [[], [], []]
            for k, (a, b) in enumerate(zip(da, db)):
                if pairs.overlap[k] < LOOP_R:
                    continue
                match = local_score(a, b)
                if match.score < threshold:
                    continue
                edge = loop_transform(cam, match.xy_a, match.xy_b)  # a: the query, b: the old frame
                if edge is None:
                    continue
                delta, info = edge
                e = between(between(pairs.poses_b[k], pairs.poses_a[k]), delta)
                e[2] = wrap_angle(e[2])
                if math.hypot(e[0], e[1]) > FALSE_LOOP_M:
                    false += 1
                    continue
                po, pq = floor_point_pairs(cam, match.xy_b, match.xy_a)
                cov_raw, sigma = rigid_fit_2d_covariance(pq, po, rigid_fit_2d(pq, po), 0.0)
                cov_fit = cov_raw * (max(sigma, MIN_POINT_SIGMA_M) / sigma) ** 2
                now.append(float(e @ info @ e))
                cov_edge = np.linalg.inv(info)
                by_turn[int(np.searchsorted(TURN_BINS_RAD, abs(delta[2])))].append(
                    float(e[:2] @ np.linalg.solve(cov_edge[:2, :2], e[:2])))
                cov_fit = between_error_covariance(delta, cov_fit)
                fit.append(float(e @ np.linalg.solve(cov_fit, e)))
                samples.append((e, cov_raw / sigma ** 2, delta, sigma ** 2))
                inliers.append(len(pq))
            per_mode[str(mode)] = {
                "loops": len(now), "false": false, "inliers_median": float(np.median(inliers)) if inliers else None,
                "nees": float(np.mean(now)) if now else None, "nees_median": float(np.median(now)) if now else None,
                "nees_fit_only": float(np.mean(fit)) if fit else None,
                "nees_fit_only_median": float(np.median(fit)) if fit else None,
                "position_nees_by_turn": [float(np.mean(b)) if b else None for b in by_turn],
                "loops_by_turn": [len(b) for b in by_turn]}
            r = per_mode[str(mode)]
            log(f"{name} mode {mode}: {len(now)} loops ({false} false), NEES {r['nees']} (fit alone {r['nees_fit_only']})")
        out[name] = per_mode
        shared[name] = loop_noise_ml(samples)
        log(f"{name}: the loop edge's noise model, maximum likelihood over modes 1-6: "
            + ", ".join(f"{k} {v * 1e3:.4f} mm" for k, v in shared[name].items()))
    return {"pairs": n_pairs, "seed": seed, "max_offset_m": 0.25, "floors": out, "noise_ml_m": shared}


#: Edges of the turn bins (radians) the position part of the loop edges' NEES is shown by.
TURN_BINS_RAD = (0.8, 1.7)


def loop_noise_ml(samples: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]]) -> dict[str, float]:
    """Maximum-likelihood values (metres) of the loop edge's noise model, given each loop's
    error ``e (3,)``, its rigid fit's covariance per unit residual variance ``A (3, 3)``, its
    transform ``delta (3,)`` and its residual variance ``s2``: ``e ~ N(0, J (max(s2, a^2) A +
    (c^2 + 4 sin^2(dyaw / 2) b^2) diag(1, 1, 0)) J^T)``, ``J`` the turn into the edge's end
    frame (:func:`robotd.base.geometry.between_error_covariance`): ``min_point_sigma_m`` (a),
    ``turn_sigma_m`` (b, :data:`robotd.floor.detector.TURN_SIGMA_M`) and ``shared_sigma_m``
    (c, a constant shared translation error). Nelder-Mead on their logarithms from three
    starts."""
    from scipy.optimize import minimize

    if not samples:
        return {"min_point_sigma_m": math.nan, "turn_sigma_m": math.nan, "shared_sigma_m": math.nan}
    e = np.array([s[0] for s in samples])
    a = np.array([between_error_covariance(s[2], s[1]) for s in samples])
    b = np.array([between_error_covariance(s[2], np.diag([1.0, 1.0, 0.0])) for s in samples])
    turn = np.array([4.0 * math.sin(0.5 * float(s[2][2])) ** 2 for s in samples])
    s2 = np.array([s[3] for s in samples])

    def nll(logp: np.ndarray) -> float:
        floor, turn_sigma, const = np.exp(logp)
        c = (np.maximum(s2, floor * floor)[:, None, None] * a
             + (const * const + turn_sigma * turn_sigma * turn)[:, None, None] * b)
        x = np.linalg.solve(c, e[:, :, None])[:, :, 0]
        return 0.5 * float(np.sum(np.einsum("ij,ij->i", e, x)) + np.sum(np.linalg.slogdet(c)[1]))

    best = None
    for start in ((1e-3, 5e-5, 5e-5), (8e-4, 5e-5, 1e-5), (9e-4, 2e-5, 3e-5)):
        r = minimize(nll, np.log(start), method="Nelder-Mead",
                     options={"xatol": 1e-4, "fatol": 1e-6, "maxiter": 4000})
        if best is None or r.fun < best.fun:
            best = r
    floor, turn_sigma, const = (float(v) for v in np.exp(best.x))
    return {"min_point_sigma_m": floor, "turn_sigma_m": turn_sigma, "shared_sigma_m": const}


def loop_rows(part: dict[str, Any]) -> list[list[Any]]:
    rows = []
    for name, per_mode in part["floors"].items():
        for mode, r in per_mode.items():
            if not r["loops"]:
                rows.append([name, mode, 0, r["false"], "-", "-", "-", "-"])
                continue
            turns = r.get("position_nees_by_turn")
            by_turn = "-" if turns is None else " / ".join(
                "-" if v is None else f"{v:.2f} ({k})" for v, k in zip(turns, r["loops_by_turn"], strict=True))
            rows.append([name, int(mode), r["loops"], r["false"], round(r["inliers_median"]),
                         f"{r['nees']:.2f} / {r['nees_median']:.2f}",
                         f"{r['nees_fit_only']:.2f} / {r['nees_fit_only_median']:.2f}", by_turn])
    return rows


LOOP_HEAD = ["floor", "mode", "loops", "false", "inliers (median)", "NEES mean / median",
             "rigid fit alone: mean / median",
             f"position part by turn (loops): < {TURN_BINS_RAD[0]} / {TURN_BINS_RAD[0]}-{TURN_BINS_RAD[1]} / "
             f"> {TURN_BINS_RAD[1]} rad"]
ODO_PART_HEAD = ["N edges", "NEES", "yaw part", "position part"]


# --------------------------------------------------------------------------- report


def odometry_markdown(odo: dict[str, Any], table: Any, lines: list[str]) -> None:
    """The page's section of one odometry part."""
    without = f", the base without {', '.join(odo['without'])}" if odo.get("without") else ""
    ekf = odo.get("ekf") or {}
    noise = ("the filter's default noise model" if not ekf else
             "the filter's noise model with " + ", ".join(f"`{k}` = {v}" for k, v in ekf.items()))
    if odo.get("daemon_model"):
        noise = ("the daemon's noise model with the demo's calibration (`[odometry]` and the calibration's "
                 "gyro noise density)" + (", and " + ", ".join(f"`{k}` = {v}" for k, v in ekf.items()) if ekf else ""))
        if odo.get("noise_model", "config") != "config":
            p = odo["params"]
            noise = (f"the daemon's noise model with `[odometry] noise_model = \"{odo['noise_model']}\"` and the "
                     + ("seed's own calibration (its own fitted sensor noise and white accelerations; the demo's: "
                        if odo.get("own_calibration") else
                        "demo's calibration (its fitted sensor noise and white accelerations: ")
                     + f"{p['accel_noise_density_mps2_per_sqrt_hz']:.4f} m/s^2 and "
                     f"{p['angular_accel_noise_density_radps2_per_sqrt_hz']:.4f} rad/s^2 per sqrt(Hz), wheel "
                     f"speed {p['wheel_v_noise_mps']:.5f} m/s, gyro {p['gyro_noise_radps']:.5f} rad/s per reading"
                     + (f", each wheel's slip {1e3 * math.sqrt(p['wheel_slip_var_m2_per_m']):.2f} mm per sqrt(m)"
                        if "wheel_slip_var_m2_per_m" in p else "") + ")"
                     + (f", the wheel slip test at `slip_gate_sigma = {odo['slip_gate_sigma']:g}`"
                        if odo.get("slip_gate_sigma") else ", no slip test")
                     + (", and " + ", ".join(f"`{k}` = {v}" for k, v in ekf.items()) if ekf else ""))
    fitted = [(ps["seed"], ps["params"]) for ps in odo.get("per_seed", []) if ps.get("params")]
    if ("slip_event_rate_hz" not in ekf and fitted
            and any(pr.get("slip_event_rate_hz", 0.0) > 0.0 for _seed, pr in fitted)):
        noise += (", the slip events each seed's file holds (`robotd calibrate odometry`'s fit; rate a second of "
                  "accelerating or turning, RMS duration: " + "; ".join(
                      f"seed {seed} {pr['slip_event_rate_hz']:.3f}, {pr['slip_event_duration_s']:.3f} s"
                      for seed, pr in fitted) + ")")
    model = (", the filter with each base's true wheel radii, wheel base and gyro scale (a calibrated model)"
             if odo.get("true_model") else
             ", the filter with the demo's shipped calibration's wheel radii, wheel base and gyro scale (seed 0's "
             "base) on every seed's base, as `robotd demo --seed N` runs it" if odo.get("shipped_geometry") else
             ", each seed's base with its own calibration file (`" + str(odo["own_calibration"]) + "`), its wheel "
             "radii, wheel base and gyro scale, noise model and scale prior, as `robotd demo --seed N` runs with "
             "that file"
             if odo.get("own_calibration") else "")
    lines += [f"## Odometry edges ({odo['route']} route, keyframes every {odo['keyframe_m']} m or 10 deg, "
              f"{noise}{without}{model})", "",
              "Mean NEES over seeds of chains of N consecutive edges, per model of what the edges share "
              "(in brackets the yaw and position parts, expected 1 and 2; in square brackets the "
              "seeds' range): independent edges (the pose graph today); the gyro bias as one variable "
              "per window of 10 edges (`robotd.graph.bias.bias_window_factor`), marginalised; the edges "
              "given the gyro bias at their start with the bias as variables (`robotd.graph.bias`), marginalised; "
              "the same with the wheels' and the gyro's scale errors as variables of prior sigma "
              + ", ".join(f"{k} {v * 100:.2f} %" for k, v in SCALE_SIGMA.items())
              + " (the simulated base's spreads), marginalised; the filter's own joint covariance "
              "of the motion.", ""]
    if odo.get("daemon_model"):
        pass
    elif ekf and "gyro_noise_radps" in ekf:
        lines += ["Not the daemon's noise model: the calibration's fitted densities (demo calibration: gyro "
                  "noise density 0.00056 rad/s per sqrt(Hz), i.e. 2.8 mrad/s per 50 Hz reading; wheel slip "
                  "noise 0, leaving the tick quantisation) with the sensor-level process noise.", ""]
    elif ekf:
        lines += ["Not the daemon's noise model: the filter run with these fields changed, to see what the "
                  "models give when the white noise is about the simulated sensors' own (docs/concepts.md, "
                  "\"Odometry edges the gate can trust\").", ""]
    table(*odometry_model_rows(odo))
    head, rows = geometry_rows(odo)
    if rows:
        lines += ["The calibration's geometry on each seed's base, relative to the base's drawn values (its own "
                  "1-sigma in brackets), and the daemon graph's scale prior (wheels, gyro: the calibration's "
                  "uncertainty with " + _wear_words(odo) + "):", ""]
        table(head, rows)
    lines += ["Per seed, bias + scale variables:", ""]
    table(*odometry_rows(odo, "scales"))
    if all("window" in r["horizons"]["1"] for r in odo["per_seed"]):
        lines += ["Per seed, bias per window of 10 edges:", ""]
        table(*odometry_rows(odo, "window"))
        lines += ["Per seed, independent edges:", ""]
        table(*odometry_rows(odo, "graph"))
    head, rows = interval_rows(odo)
    if rows:
        lines += ["One interval decomposed (`interval_parts`): per kind of interval (a straight: true heading "
                  f"change below {math.degrees(STRAIGHT_RAD):.0f} deg; a turn on the spot: true translation below "
                  f"{SPOT_M * 100:.0f} cm; a start or stop: the keyframes' true speeds {SPEED_CHANGE_MPS} m/s apart), "
                  "the true error of the filter's motion along the track, across it and in yaw (the edge's end "
                  "frame) against the 1-sigma the filter's own covariance claims (unfloored) and the edge's "
                  "(floored, as the graph gets it), medians, and each component's mean `e^2 / sigma^2` "
                  "against the filter's own (expected 1); then the mean NEES (yaw, position) of the filter's "
                  "own covariance, of the edge, and of the edge with the daemon graph's scale prior "
                  "marginalised (`bias_scale_window` over one edge):", ""]
        table(head, rows)
    head, rows = speed_change_rows(odo)
    if rows:
        lines += [f"Single edges whose two keyframes' true speeds differ by more than {SPEED_CHANGE_MPS} m/s "
                  "(the starts and stops) against the others: mean NEES over one edge (position part), and "
                  "the lag `tau` that fits their error along the track as `-tau * dv` (`dv` the change of "
                  "speed over the edge):", ""]
        table(head, rows)
    head, rows = cost_rows(odo)
    if rows:
        lines += ["Cost in the pose graph: the seed's keyframes built one at a time into iSAM2 with loop "
                  "edges from the truth (1 mm, every 25th keyframe that revisits a place): independent "
                  "edges; the bias per window of 10 edges (`bias_window`: the open window's edges "
                  "independent, replaced by one factor on its 11 poses and the bias at its start when it "
                  "closes, `robotd.graph.bias.bias_window_factor`); the bias variables per edge (`bias`) "
                  "and the bias + scale variables (`bias_scales`); all but the first Python "
                  "`CustomFactor`s; in brackets the ratio to independent edges, same run.", ""]
        table(head, rows)
    head, rows = daemon_cost_rows(odo)
    if rows:
        lines += ["In the daemon's own graph (`robotd.graph.incremental.IncrementalGraph`, each "
                  "`[pose_graph] odometry_model`): the seed's edges with their bias terms added one keyframe "
                  "at a time. NEES without loops, from iSAM2's joint marginal of a chain's two ends (the chains "
                  "above, at most 400 per horizon spread over the drive; in brackets the yaw and position parts, in square "
                  "brackets the seeds' range; pooled: all the seeds' chains together):", ""]
        table(*daemon_graph_rows(odo))
        for m in _daemon_models(odo)[1:]:
            lines += [f"Per seed, `{m}` in the daemon's graph"
                      + ((" (the scale variable's prior: each seed's calibration's uncertainty and "
                          + _wear_words(odo) + ", above)") if m == "bias_scale_window" and odo.get("own_calibration")
                         else " (the scale variable's prior: wheels {:.3f} %, gyro {:.4f} %, the shipped calibration's "
                         "uncertainty and {})".format(*(100 * x for x in odo["scale_sigmas"]), _wear_words(odo))
                         if m == "bias_scale_window" else "")
                      + ":", ""]
            table(*daemon_graph_seed_rows(odo, m))
        lines += ["How far one seed's mean can be from 3 when the covariances are right: a drive of the seeds' "
                  "fewest edges holds this many disjoint chains per horizon, whose NEES are independent chi2 "
                  "with 3 degrees of freedom (`honest_spread`; an error all of a seed's chains share widens it):", ""]
        table(*honest_spread_rows(odo))
        lines += ["CPU in the daemon's graph, with loop edges from the truth (as above) and a full solve every "
                  "200 keyframes and at the end, as the pose-graph stage runs it (the fold after each): CPU "
                  "time of this process per keyframe (keyframe and loop updates), of the full solves (their "
                  "count in brackets), the ATE at the end (and with `bias_scale_window` the scale variable's "
                  "estimate); in brackets the ratio to independent edges, same run.", ""]
        table(head, rows)


def _wear_words(odo: dict[str, Any]) -> str:
    """How a run's scale prior was widened: the default ``[pose_graph] scale_wear`` and
    ``scale_wear_gyro``, or the ones it was given (``--scale-wear``)."""
    wear = odo.get("scale_wear")
    if not wear:
        return "the default `[pose_graph] scale_wear` and `scale_wear_gyro`"
    return f"`[pose_graph] scale_wear` {wear[0]:g} and `scale_wear_gyro` {wear[1]:g} (`--scale-wear`)"


def markdown(payload: dict[str, Any]) -> list[str]:
    lines = ["# NEES of the map's edges", "",
             "Generated by `bench/bench_nees.py` (see its docstring for the method); "
             "3 is right (3 degrees of freedom; the yaw part alone 1, the position part 2), "
             "below too cautious, above too confident.", ""]
    m = payload["machine"]
    lines += [f"Machine: {m['machine']}, {m['cpu_count']} cores, Python {m['python']}.", ""]

    def table(head: list[str], rows: list[list[Any]]) -> None:
        lines.append("| " + " | ".join(head) + " |")
        lines.append("|" + "---|" * len(head))
        for row in rows:
            lines.append("| " + " | ".join(str(c) for c in row) + " |")
        lines.append("")

    for odo in [payload.get("odometry")] + [c.get("odometry") for c in payload.get("compare", [])]:
        if odo:
            odometry_markdown(odo, table, lines)
    loops = payload.get("loops")
    if loops:
        lines += [f"## Loop edges ({loops['pairs']} rendered pairs per floor, second frame within "
                  f"{loops['max_offset_m']} m)", "",
                  "Pairs declared loops at the demo calibration's thresholds whose transform is right "
                  f"(within {FALSE_LOOP_M * 100:.0f} cm; the false ones counted apart).", ""]
        table(LOOP_HEAD, loop_rows(loops))
        ml = loops.get("noise_ml_m", {})
        if ml:
            lines += ["The loop edge's noise model by maximum likelihood over modes 1-6 (`loop_noise_ml`; "
                      "`robotd.floor.detector.MIN_POINT_SIGMA_M` and `TURN_SIGMA_M` are the plank floor's on "
                      "another sample): " + "; ".join(
                          f"{k}: floor on the inliers' sigma {v['min_point_sigma_m'] * 1e3:.3f} mm, offset the "
                          f"views share {v['turn_sigma_m'] * 1e3:.4f} mm, constant shared term "
                          f"{v['shared_sigma_m'] * 1e3:.4f} mm" for k, v in ml.items()) + ".", ""]
    return lines


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--full", action="store_true", help="10 seeds and 400 pairs per floor")
    ap.add_argument("--seeds", type=int, default=None, help="seeds 0..N-1 of the virtual base (default 5)")
    ap.add_argument("--route", default="office")
    ap.add_argument("--keyframe-m", type=float, default=0.05,
                    help="keyframe spacing for the odometry edges (0.05: the horizons of 1000 edges fit the route)")
    ap.add_argument("--pairs", type=int, default=None, help="rendered frame pairs per floor (default 120)")
    ap.add_argument("--floors", default="planks,mixed")
    ap.add_argument("--seed", type=int, default=0, help="seed of the rendered pairs")
    ap.add_argument("--without", default="",
                    help="odometry: comma-separated errors the simulated base leaves out (what each costs): "
                         + ", ".join(WITHOUT))
    ap.add_argument("--ekf", action="append", default=[], metavar="NAME=VALUE",
                    help="odometry: a field of the filter's noise model (robotd.odometry.ekf.EkfParams) "
                         "changed from its default (repeat for several)")
    ap.add_argument("--true-model", action="store_true",
                    help="odometry: the filter with each base's true wheel radii, wheel base and gyro scale "
                         "(a calibrated model) instead of the nominal ones")
    ap.add_argument("--daemon-model", action="store_true",
                    help="odometry: the daemon's noise model with the demo's calibration (the config's "
                         "[odometry] and the calibration's gyro noise density), --ekf changes on top")
    ap.add_argument("--noise-model", choices=("config", "calibration"), default="config",
                    help="with --daemon-model: [odometry] noise_model (calibration: the demo calibration's "
                         "fitted sensor noise and white accelerations)")
    ap.add_argument("--slip-gate", type=float, default=0.0, metavar="SIGMA",
                    help="with --daemon-model and --noise-model calibration: [odometry] slip_gate_sigma, "
                         "the wheel slip test (default 0: off)")
    ap.add_argument("--cost-seeds", type=int, default=1,
                    help="odometry: time the pose graph with each model on this many seeds (default 1)")
    ap.add_argument("--daemon-graph", type=int, default=0, metavar="SEEDS",
                    help="odometry: on this many seeds also feed the edges to the daemon's own graph "
                         "(IncrementalGraph, each [pose_graph] odometry_model): NEES from iSAM2's marginals, "
                         "CPU per keyframe with loops and full solves")
    ap.add_argument("--daemon-models", default="independent,bias_window",
                    help="with --daemon-graph: the [pose_graph] odometry_model values run (of "
                         + ", ".join(DAEMON_MODELS) + "; the first is the cost baseline, keep it independent)")
    ap.add_argument("--shipped-geometry", action="store_true",
                    help="odometry: the filter with the demo's shipped calibration's wheel radii, wheel base and "
                         "gyro scale (seed 0's base) on every seed's base, as the demo runs it")
    ap.add_argument("--own-calibration", default=None, metavar="PATTERN",
                    help="odometry: each seed's base with its own calibration file (PATTERN with {seed}: what "
                         "`robotd calibrate odometry` made from that base's calibration drive): its wheel radii, "
                         "wheel base and gyro scale, its noise model (--daemon-model) and scale prior")
    ap.add_argument("--scale-wear", default=None, metavar="WHEEL,GYRO",
                    help="[pose_graph] scale_wear and scale_wear_gyro for the daemon graph's scale prior "
                         "(default: the config's, 0.003,0.002)")
    ap.add_argument("--cost-models", default="independent,bias_window,bias",
                    help="odometry: the graph-cost models timed (of independent, bias_window, bias, bias_scales)")
    ap.add_argument("--compare", type=Path, action="append", default=[],
                    help="another run's JSON whose odometry section the page shows too")
    ap.add_argument("--page-from", type=Path, default=None,
                    help="measure nothing: write --markdown from this run's JSON (and --compare)")
    ap.add_argument("--skip-odometry", action="store_true")
    ap.add_argument("--skip-loops", action="store_true")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--markdown", type=Path, default=None, help="also write this Markdown page")
    args = ap.parse_args(argv)
    seeds = args.seeds or (10 if args.full else 5)
    without = tuple(w for w in args.without.split(",") if w)
    if not set(without) <= set(WITHOUT):
        ap.error(f"--without takes {', '.join(WITHOUT)}")
    n_pairs = args.pairs or (400 if args.full else 120)
    scale_wear = None
    if args.scale_wear is not None:
        try:
            scale_wear = tuple(float(x) for x in args.scale_wear.split(","))
        except ValueError:
            scale_wear = ()
        if len(scale_wear) != 2 or not all(1e-6 <= x <= 0.5 for x in scale_wear):
            ap.error("--scale-wear takes WHEEL,GYRO, each within [1e-6, 0.5] (the config's bounds)")
    if args.own_calibration is not None:
        if args.shipped_geometry or args.true_model:
            ap.error("--own-calibration takes the place of --shipped-geometry and --true-model")
        if "{seed}" not in args.own_calibration:
            ap.error("--own-calibration needs {seed} in its PATTERN")
        missing = [args.own_calibration.format(seed=n) for n in range(seeds)
                   if not Path(args.own_calibration.format(seed=n)).is_file()]
        if missing and args.page_from is None and not args.skip_odometry:
            ap.error(f"--own-calibration: no calibration file {missing[0]}")
    if args.page_from is not None:
        import json

        if args.markdown is None:
            ap.error("--page-from needs --markdown")
        page = dict(json.loads(args.page_from.read_text()),
                    compare=[json.loads(p.read_text()) for p in args.compare])
        write_page(args.markdown, markdown(page))
        log(f"wrote {args.markdown}")
        return 0
    payload: dict[str, Any] = {"benchmark": "nees", "machine": machine_info(),
                               "args": {k: (str(v) if isinstance(v, Path) else [str(x) for x in v] if k == "compare" else v)
                                        for k, v in vars(args).items()}}
    if not args.skip_odometry:
        ekf: dict[str, float] = {}
        for item in args.ekf:
            name, _, value = item.partition("=")
            if name not in EkfParams.__dataclass_fields__ or not value:
                ap.error(f"--ekf takes NAME=VALUE with NAME a field of EkfParams, got {item!r}")
            ekf[name] = float(value)
        payload["odometry"] = odometry_part(seeds, args.route, args.keyframe_m, without, ekf, args.cost_seeds,
                                            args.true_model, args.daemon_model,
                                            tuple(m for m in args.cost_models.split(",") if m), args.daemon_graph,
                                            args.noise_model, args.slip_gate, args.shipped_geometry,
                                            tuple(m for m in args.daemon_models.split(",") if m),
                                            args.own_calibration, scale_wear)
        print(f"\nodometry edges, {args.route}: mean NEES of N chained edges per model (yaw, position) [seeds]")
        print_table(*odometry_model_rows(payload["odometry"]))
        print("\nper seed, bias + scale variables")
        print_table(*odometry_rows(payload["odometry"]))
        print("\ngraph cost, same run")
        print_table(*cost_rows(payload["odometry"]))
        if args.daemon_graph:
            print("\nthe daemon's graph: mean NEES per [pose_graph] odometry_model (yaw, position) [seeds]")
            print_table(*daemon_graph_rows(payload["odometry"]))
            print("\nthe daemon's graph: CPU, same run")
            print_table(*daemon_cost_rows(payload["odometry"]))
    if not args.skip_loops:
        payload["loops"] = loop_part([f for f in args.floors.split(",") if f], n_pairs, args.seed)
        print("\nloop edges from rendered pairs")
        print_table(LOOP_HEAD, loop_rows(payload["loops"]))
        for k, v in payload["loops"]["noise_ml_m"].items():
            print(f"{k}: the loop edge's noise model (maximum likelihood, modes 1-6): "
                  + ", ".join(f"{name} {x * 1e3:.4f} mm" for name, x in v.items()))
    path = write_json(args.out, payload)
    log(f"wrote {path}")
    if args.markdown is not None:
        import json

        page = dict(payload, compare=[json.loads(p.read_text()) for p in args.compare])
        write_page(args.markdown, markdown(page))
        log(f"wrote {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
