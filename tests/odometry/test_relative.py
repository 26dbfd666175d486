"""Relative-pose (visual odometry) measurements in the EKF by stochastic cloning: a
hand-derived yaw correction, the shift to the filter's times, and the stream filter
pulled back onto the truth by exact visual increments."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.base.geometry import between, compose
from robotd.base.messages import WheelTicks, YawRate
from robotd.odometry.ekf import IYAW
from robotd.odometry.fusion import OdometryFilter
from robotd.odometry.relative import (
    clone_after_predict,
    clone_after_update,
    clone_pose,
    relative_pose_jacobians,
    shift_measurement,
    update_relative_pose,
)


def _drifted_since_clone(mean0: np.ndarray, b: float, q: float, delta: float):
    """A keyframe clone of ``mean0`` (yaw variance ``b``), then the state after the yaw
    drifted by ``delta`` and gained independent variance ``q`` (cross terms unchanged)."""
    cov0 = np.diag([1e-3, 1e-3, b, 0.01, 0.01, 1e-4])
    clone = clone_pose(mean0, cov0, keyframe_stamp_ns=5)
    mean1 = mean0.copy()
    mean1[IYAW] += delta
    cov1 = cov0.copy()
    cov1[IYAW, IYAW] += q
    return clone, mean1, cov1

def test_yaw_drift_pulled_back_by_the_hand_derived_gain():
    """Clone at yaw 0.3 with variance b; since then the yaw gained variance q and drifted
    by delta. VO says the yaw did not change (variance r). In the joint (pose, clone)
    the yaw innovation's variance is (b + q) + b - 2 b + r = q + r, so the gain on the
    current yaw is (b + q - b) / (q + r) = q / (q + r): it does not depend on b. (Treating
    the clone as known with R inflated by b would give (b + q) / (2 b + q + r).)"""
    b, q, r, delta = 0.04, 1e-4, 1e-4, 0.02
    clone, mean1, cov1 = _drifted_since_clone(np.array([1.0, 2.0, 0.3, 0.2, 0.0, 0.0]), b, q, delta)
    new_mean, new_cov, nis = update_relative_pose(mean1, cov1, clone, np.zeros(3), np.diag([1e-6, 1e-6, r]))
    k = q / (q + r)
    assert new_mean[IYAW] == pytest.approx(0.3 + delta - k * delta, abs=1e-12)
    assert new_cov[IYAW, IYAW] == pytest.approx(b + q - q * q / (q + r), rel=1e-9)
    assert nis == pytest.approx(delta ** 2 / (q + r), rel=1e-6)
    assert new_mean[[0, 1, 3, 4, 5]] == pytest.approx(mean1[[0, 1, 3, 4, 5]], abs=1e-12)


def test_jacobians_match_finite_differences():
    c, p = np.array([0.5, -1.0, 2.5]), np.array([0.7, -0.8, 2.9])
    h, jp, jc = relative_pose_jacobians(c, p)
    assert h == pytest.approx(between(c, p))
    eps = 1e-7
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        assert jp[:, i] == pytest.approx((between(c, p + d) - between(c, p - d)) / (2 * eps), abs=1e-6)
        assert jc[:, i] == pytest.approx((between(c + d, p) - between(c - d, p)) / (2 * eps), abs=1e-6)


def test_shift_measurement_to_the_filter_times():
    truth = [np.array([0.0, 0.0, 0.1]), np.array([0.003, 0.0, 0.11]), np.array([0.05, 0.01, 0.2]),
             np.array([0.055, 0.012, 0.21])]  # keyframe k-1, filter at clone, keyframe k, filter now
    z = between(truth[0], truth[2])
    zs, rs = shift_measurement(z, np.eye(3) * 1e-6, between(truth[0], truth[1]), between(truth[2], truth[3]))
    assert zs == pytest.approx(between(truth[1], truth[3]), abs=1e-12)
    assert np.linalg.eigvalsh(rs) == pytest.approx([1e-6] * 3, rel=0.05)


def test_cross_covariance_follows_predict_and_update():
    cov = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    cl = clone_pose(np.zeros(6), cov, 0)
    f = np.eye(6)
    f[0, 3] = 0.1
    assert clone_after_predict(cl, f).cross == pytest.approx(f @ cov[:, :3])
    h = np.zeros((1, 6))
    h[0, 2] = 1.0
    upd = clone_after_update(cl, cov, h, np.array([[3.0]]))
    assert upd.cross[2, 2] == pytest.approx(3.0 - 3.0 * 3.0 / 6.0)  # (1 - K) b, K = 1/2
    assert upd.cross[0, 0] == 1.0


# ----------------------------------------------------------------- the stream filter

def _drive(f: OdometryFilter, n_packets: int, w_gyro_radps: float, t0_ns: int = 0, ticks0: int = 0) -> int:
    """Drive straight at ~0.2 m/s (equal ticks) while the gyro reports a false turn rate
    ``w_gyro_radps`` (a bias the filter does not know): the fused yaw drifts."""
    ticks = ticks0
    for k in range(n_packets):
        t = t0_ns + k * 20_000_000
        ticks += 23
        f.on_yaw_rate(YawRate(t - 5_000_000, w_gyro_radps))
        f.on_wheels(WheelTicks(t, ticks % 65536, ticks % 65536))
    return ticks


def test_filter_learns_the_gyro_bias_from_vo_and_counts():
    """The gyro reports 0.05 rad/s of turn that the wheels (straight) cannot confirm well
    (their yaw-rate noise grows with speed): without VO the fused heading drifts ~2.5 deg
    per second. The floor says "straight ahead" at every keyframe (1 s apart): the first
    fusion already moves the bias estimate most of the way, after four it is within
    0.008 rad/s of 0.05 (measured 0.047) and the yaw rate within 0.01 of 0."""
    f = OdometryFilter()
    ticks = _drive(f, 50, 0.0)
    t_prev = f.latest_stamp_ns() - 20_000_000
    assert not f.on_visual_odometry(t_prev, None, None, None)  # first keyframe: clone only
    assert f.counters.vo_missing == 1
    step_m = 50 * 23 * f.drive.metres_per_tick
    biases = []
    for k in range(4):
        ticks = _drive(f, 50, 0.05, t0_ns=f.latest_stamp_ns() + 20_000_000, ticks0=ticks)
        t = f.latest_stamp_ns() - 20_000_000
        if k == 0:
            assert f.state.mean[IYAW] > 0.02  # drifted by the false turn
        assert f.on_visual_odometry(t, t_prev, np.array([step_m, 0.0, 0.0]), np.eye(3) * 1e-6)
        biases.append(f.state.gyro_bias_radps)
        t_prev = t
    assert f.counters.vo_fused == 4
    assert biases[0] > 0.025 and abs(biases[-1] - 0.05) < 0.008
    assert abs(f.state.mean[4]) < 0.01
    # A measurement whose previous keyframe is not the clone's is refused, and counted.
    assert not f.on_visual_odometry(t_prev + 1, t_prev - 5, np.zeros(3), np.eye(3) * 1e-6)
    assert f.counters.vo_no_clone == 1
    # A wildly wrong measurement fails the gate.
    _drive(f, 10, 0.05, t0_ns=f.latest_stamp_ns() + 20_000_000, ticks0=ticks)
    t = f.latest_stamp_ns() - 20_000_000
    assert not f.on_visual_odometry(t, t_prev + 1, np.array([1.0, 0.5, 1.0]), np.eye(3) * 1e-6)
    assert f.counters.vo_rejected == 1
    # A stamp beyond the filter's time has no pose: counted, the clone is dropped.
    assert not f.on_visual_odometry(f.latest_stamp_ns() + 10**9, t, np.zeros(3), np.eye(3))
    assert f.counters.vo_no_pose == 1


def test_fused_filter_edges_come_from_its_wheel_and_gyro_twin():
    """With ``vo_twin`` the fused filter's keyframe edges are those of a filter that never
    saw visual odometry (same messages, same keyframes), while its own pose was pulled by
    the visual steps; without the twin an edge with a fused step in it is None (the map
    writer's fallback)."""
    fused, plain, bare = OdometryFilter(vo_twin=True), OdometryFilter(), OdometryFilter()
    ticks = [0, 0, 0]
    step_m = 50 * 23 * fused.drive.metres_per_tick
    t_prev = None
    edges = []
    for k in range(5):
        for i, f in enumerate((fused, plain, bare)):
            t0 = 0 if f.latest_stamp_ns() is None else f.latest_stamp_ns() + 20_000_000
            ticks[i] = _drive(f, 50, 0.05, t0_ns=t0, ticks0=ticks[i])
        t = fused.latest_stamp_ns() - 20_000_000
        got = [fused.keyframe_edge(t), plain.keyframe_edge(t), bare.keyframe_edge(t)]
        delta = None if t_prev is None else np.array([step_m, 0.0, 0.0])
        fused.on_visual_odometry(t, t_prev, delta, None if delta is None else np.eye(3) * 1e-6)
        bare.on_visual_odometry(t, t_prev, delta, None if delta is None else np.eye(3) * 1e-6)
        edges.append(got)
        t_prev = t
    assert fused.counters.vo_fused == 4 and bare.counters.vo_fused == 4
    assert all(e[0] is None and e[1] is None for e in edges[:1])
    for e_fused, e_plain, _ in edges[1:]:
        assert e_fused[0] == pytest.approx(e_plain[0], abs=1e-12)
        assert e_fused[1] == pytest.approx(e_plain[1], rel=1e-9, abs=1e-18)
    assert edges[1][2] is not None  # no visual step fused in its interval yet
    assert all(e[2] is None for e in edges[2:])
    # The fused pose was pulled straight; the twin's (and the plain filter's) was not.
    assert abs(fused.state.mean[IYAW]) < 0.3 * abs(plain.state.mean[IYAW])
    # Keyframes are posed on the twin: the plain filter's poses, whatever VO did.
    assert plain.wheel_gyro is plain and fused.wheel_gyro is not fused
    t = fused.settled_stamp_ns()
    assert t == plain.settled_stamp_ns()
    p_twin, p_plain = fused.wheel_gyro.pose_at(t), plain.pose_at(t)
    assert (p_twin.x_m, p_twin.y_m, p_twin.yaw_rad) == (p_plain.x_m, p_plain.y_m, p_plain.yaw_rad)
    assert fused.pose_at(t).yaw_rad != pytest.approx(p_plain.yaw_rad, abs=1e-3)


def _run_with_latency(f: OdometryFilter, latencies: list[int], n_packets: int = 600,
                      every: int = 25) -> list[tuple[int, float, float, float]]:
    """Drive a gentle S-bend (wheel ticks and a gyro with a bias the filter does not know)
    for ``n_packets`` 20 ms packets; a keyframe every ``every`` packets, its visual step
    (the true motion, slightly noisy) handed over ``latencies[k]`` packets after its
    frame, in keyframe order. Returns the fused pose after every packet."""
    rng = np.random.default_rng(3)
    truth = np.zeros(3)
    poses = {}
    due: list[tuple[int, int, int | None, np.ndarray | None]] = []  # (packet, stamp, prev, delta)
    ticks_l = ticks_r = 0
    out = []
    kf_prev = None
    for k in range(n_packets):
        t = k * 20_000_000
        w = 0.3 * np.sin(k / 80.0)
        dl, dr = 23 - round(25 * w), 23 + round(25 * w)
        ticks_l, ticks_r = ticks_l + dl, ticks_r + dr
        ds = 0.5 * (dl + dr) * f.drive.metres_per_tick
        dyaw = (dr - dl) * f.drive.metres_per_tick / f.drive.wheel_base_m
        truth = truth + np.array([ds * np.cos(truth[2] + 0.5 * dyaw), ds * np.sin(truth[2] + 0.5 * dyaw), dyaw])
        f.on_yaw_rate(YawRate(t - 5_000_000, dyaw / 0.02 + 0.04))
        f.on_wheels(WheelTicks(t, ticks_l % 65536, ticks_r % 65536))
        if k % every == 10:
            poses[t] = truth.copy()
            n = len(poses) - 1
            delta = None if kf_prev is None else between(poses[kf_prev], truth) + rng.normal(0, 1e-4, 3)
            at = max(k + latencies[n % len(latencies)], due[-1][0] if due else 0)
            due.append((at, t, kf_prev, delta))
            kf_prev = t
        while due and due[0][0] <= k:
            _, ts, prev, delta = due.pop(0)
            f.on_visual_odometry(ts, prev, delta, None if delta is None else np.eye(3) * 1e-8)
        s = f.state
        out.append((s.stamp_ns, float(s.mean[0]), float(s.mean[1]), float(s.mean[2])))
    for _, ts, prev, delta in due:  # the steps still pending at the end
        f.on_visual_odometry(ts, prev, delta, None if delta is None else np.eye(3) * 1e-8)
    s = f.state
    out.append((s.stamp_ns, float(s.mean[0]), float(s.mean[1]), float(s.mean[2])))
    return out


def test_a_late_visual_step_gives_the_same_filter_as_an_immediate_one():
    """The pipeline reaches a keyframe's visual step when the filter is up to a second past
    its frame. With ``vo_twin`` the filter goes back to the frame's time, applies the step
    there and replays the messages since: whatever the latency (here 0 to 1.2 s, random per
    keyframe, often beyond the next keyframe), the filter ends bit for bit where it ends
    when every step comes at once, and so do its pose history and counters. The filter
    without the journal applies the step to its current state instead, and ends elsewhere."""
    rng = np.random.default_rng(0)
    late = [int(x) for x in rng.integers(0, 60, 40)]
    now, later = OdometryFilter(vo_twin=True, vo_rate_only=True), OdometryFilter(vo_twin=True, vo_rate_only=True)
    track_now = _run_with_latency(now, [0])
    track_late = _run_with_latency(later, late)
    assert now.counters.vo_fused == later.counters.vo_fused == 23
    assert now.counters == later.counters
    assert np.array_equal(now.state.mean, later.state.mean)
    assert np.array_equal(now.state.cov, later.state.cov)
    t = now.settled_stamp_ns() - 700_000_000
    assert (now.pose_at(t).x_m, now.pose_at(t).yaw_rad) == (later.pose_at(t).x_m, later.pose_at(t).yaw_rad)
    # While a step is pending the live pose differs; it is the same again once applied.
    assert track_now[-1] == track_late[-1]
    assert any(a != b for a, b in zip(track_now, track_late))
    # The twin and the wheel-only odometry saw every message exactly once.
    assert now.wheel_gyro.counters == later.wheel_gyro.counters
    assert now.wheel_pose().x_m == later.wheel_pose().x_m  # (PoseStamped has no ==)
    # Without the journal the late steps land on the current state: another end pose.
    # (The same noise model as the fused filter's: with vo_rate_only its pose follows its
    # rates, with its own angular process noise.)
    rates = now.params
    assert rates.rate_only_process
    bare_now, bare_late = OdometryFilter(params=rates), OdometryFilter(params=rates)
    _run_with_latency(bare_now, [0])
    _run_with_latency(bare_late, late)
    # (Here its chi-square gate even refuses some of them: the motion since the frame,
    # taken as exact, is not.)
    assert bare_now.counters.vo_fused == 23 and bare_now.counters.vo_rejected == 0
    assert np.abs(bare_now.state.mean[:3] - bare_late.state.mean[:3]).max() > 1e-4
    # Immediate steps: the journal changes nothing.
    assert np.allclose(bare_now.state.mean, now.state.mean, atol=1e-12)


def test_visual_steps_teach_the_fused_filter_the_gyro_bias_and_the_twin_keeps_its_noise_model():
    """The gyro reads 0.04 rad/s too much and the drive has no standstill: the twin (wheels
    and gyro) learns it only slowly from the wheels; the fused filter learns it from the
    visual steps' heading through the clone's cross-covariance. With ``vo_rate_only`` the
    filter's pose follows its rates (``rate_only_process``); the twin, whose edges the pose
    graph uses, keeps the noise model it was given. By default the pose keeps its own
    process noise."""
    f = OdometryFilter(vo_twin=True, vo_rate_only=True)
    assert f.params.rate_only_process and not f.wheel_gyro.params.rate_only_process
    assert not OdometryFilter(vo_twin=True).params.rate_only_process
    assert not OdometryFilter().params.rate_only_process
    _run_with_latency(f, [0], n_packets=600)
    assert abs(f.state.gyro_bias_radps - 0.04) < 1e-3
    assert abs(f.wheel_gyro.state.gyro_bias_radps - 0.04) > 5e-3
    # The default pose (its own process noise) learns it from the steps as well.
    own = OdometryFilter(vo_twin=True)
    _run_with_latency(own, [0], n_packets=600)
    assert abs(own.state.gyro_bias_radps - 0.04) < 1e-3


def _spin_up(f: OdometryFilter, alpha_radps2: float, n_packets: int) -> float:
    """Turn on the spot with constant angular acceleration from rest, as the Kobuki reports
    it: per 20 ms packet, the raw gyro's mean over the packet stamped in its middle, then the
    ticks at its end. Returns the true yaw at the last packet, rad."""
    half_base = 0.5 * f.drive.wheel_base_m
    ticks = 0
    for k in range(1, n_packets + 1):
        t0, t1 = (k - 1) * 0.02, k * 0.02
        f.on_yaw_rate(YawRate(int(round((t1 - 0.01) * 1e9)), alpha_radps2 * 0.5 * (t0 + t1)))
        ticks = round(0.5 * alpha_radps2 * t1 ** 2 * half_base / f.drive.metres_per_tick)
        f.on_wheels(WheelTicks(int(round(t1 * 1e9)), (-ticks) % 65536, ticks % 65536))
    return 0.5 * alpha_radps2 * (n_packets * 0.02) ** 2


def test_the_fused_pose_follows_the_readings_by_the_trapezoid_rule():
    """A packet's readings are means over it: moved by the rates before each reading, the
    fused heading lagged the truth by about 5 ms of yaw rate while the base turned faster
    (5 mrad at 1 rad/s); moved half by the rates before and half by the rates after, it
    follows the truth to a tenth of that. (The gyro bias is known here, so that only the
    integration differs.)"""
    known = (0.0, 1e-7)
    now = OdometryFilter(vo_twin=True, vo_rate_only=True, initial_bias=known, pose_after_rates=True)
    before = OdometryFilter(vo_twin=True, vo_rate_only=True, initial_bias=known)
    assert now.params.rate_only_process and before.params.rate_only_process
    errors = []
    for f in (now, before):
        truth = _spin_up(f, 1.0, 50)  # 1 s: 1 rad/s at the end
        errors.append(float(f.state.mean[IYAW]) - truth)
    assert abs(errors[0]) < 1e-3
    assert errors[1] < -4e-3


def test_a_consider_update_leaves_the_bias_and_gives_the_yaw_its_optimal_gain():
    """The yaw drifted by delta since the clone and is correlated with the bias (the gyro's
    integral): the optimal update moves the bias too; with the bias considered (its gain
    row zeroed) the bias's mean and variance stay as they were, and the yaw gets the same
    correction as with the optimal gain (a gain row depends only on its own row of P H^T)."""
    b, q, r, delta = 0.04, 1e-4, 1e-4, 0.02
    clone, mean1, cov1 = _drifted_since_clone(np.array([1.0, 2.0, 0.3, 0.2, 0.0, 0.01]), b, q, delta)
    cov1[IYAW, 5] = cov1[5, IYAW] = 0.5e-4  # the yaw since the clone knows the bias
    z, rr = np.zeros(3), np.diag([1e-6, 1e-6, r])
    opt_mean, _, nis = update_relative_pose(mean1, cov1, clone, z, rr)
    con_mean, con_cov, nis_c = update_relative_pose(mean1, cov1, clone, z, rr, consider=(5,))
    assert abs(opt_mean[5] - mean1[5]) > 1e-3  # the optimal update moves the bias
    assert con_mean[5] == mean1[5] and con_cov[5, 5] == pytest.approx(cov1[5, 5], rel=1e-12)
    assert con_mean[IYAW] == pytest.approx(opt_mean[IYAW], abs=1e-12)
    assert nis_c == nis
    assert np.all(np.linalg.eigvalsh(con_cov) > 0)


def test_visual_steps_that_leave_the_bias_alone_still_hold_the_heading():
    """``vo_bias_update=False``: the same drive as above (the gyro 0.04 rad/s off, no
    standstill); the visual steps no longer teach the fused filter the bias, but they still
    correct its heading, which ends far nearer the one of a filter that knows the bias than
    the twin's does."""
    f = OdometryFilter(vo_twin=True, vo_rate_only=True, vo_bias_update=False)
    learnt = OdometryFilter(vo_twin=True, vo_rate_only=True)
    track = _run_with_latency(f, [0], n_packets=600)
    _run_with_latency(learnt, [0], n_packets=600)
    assert f.counters.vo_fused == learnt.counters.vo_fused == 23
    assert abs(learnt.state.gyro_bias_radps - 0.04) < 1e-3
    assert abs(f.state.gyro_bias_radps - 0.04) > 5e-3
    # The reference: wheels and gyro with the bias known (no visual steps).
    known = _run_with_latency(OdometryFilter(initial_bias=(0.04, 1e-9)), [0], n_packets=600)
    end, twin_end = track[-1][3], f.wheel_gyro.state.mean[IYAW]
    assert abs(end - known[-1][3]) < 0.2 * abs(twin_end - known[-1][3])


def test_the_combined_edges_as_the_live_pose_do_not_depend_on_when_the_steps_come():
    """``live_pose = "combined_edges"``: the live pose is the chain of the graph's combined
    edges (the twin's edge and the visual step) up to the last keyframe, then the twin's
    motion since. The chain is the same whenever the steps arrive; the live pose is its
    end composed with the twin's motion; the precise steps hold the heading that the
    twin, 0.04 rad/s of unknown gyro bias, loses."""
    with pytest.raises(ValueError, match="live_pose"):
        OdometryFilter(vo_twin=True, live_pose="graph")
    now = OdometryFilter(vo_twin=True, live_pose="combined_edges")
    late = OdometryFilter(vo_twin=True, live_pose="combined_edges")
    _run_with_latency(now, [0])
    _run_with_latency(late, [0, 3, 1, 7])
    a, b = now.chain_pose(), late.chain_pose()
    assert a is not None and b is not None and a.stamp_ns == b.stamp_ns
    assert (a.x_m, a.y_m, a.yaw_rad) == (b.x_m, b.y_m, b.yaw_rad)
    assert np.array_equal(a.covariance, b.covariance) and np.all(np.linalg.eigvalsh(a.covariance) > 0)
    twin = now.wheel_gyro
    at_kf = twin.pose_at(a.stamp_ns)
    motion = between(np.array([at_kf.x_m, at_kf.y_m, at_kf.yaw_rad]), twin.state.mean[:3])
    live = now.pose()
    expected = compose(np.array([a.x_m, a.y_m, a.yaw_rad]), motion)
    assert np.array([live.x_m, live.y_m, live.yaw_rad]) == pytest.approx(expected, abs=1e-12)
    assert OdometryFilter(vo_twin=True).chain_pose() is None
    known = _run_with_latency(OdometryFilter(initial_bias=(0.04, 1e-9)), [0], n_packets=600)
    assert abs(live.yaw_rad - known[-1][3]) < 0.2 * abs(twin.state.mean[IYAW] - known[-1][3])
