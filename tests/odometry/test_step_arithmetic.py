"""The odometry filter's per-step arithmetic against a frozen copy of the code before it was
written out for speed: the prediction's ``F P F^T + Q`` as matrix products, the wheel and
gyro updates' Joseph form as ``(I - K H) P (I - K H)^T + K R K^T`` of full matrices, the
error maps multiplied step by step and the pose clone carried through every step. The two
orders of the same arithmetic must agree to rounding on a drive with late visual steps
(the journal's rewinds, the clone, the twin's edges)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import robotd.odometry.ekf as ekf
import robotd.odometry.fusion as fusion
from robotd.base.geometry import between, wrap_angle
from robotd.base.messages import WheelTicks
from robotd.odometry.ekf import H_GYRO, H_WHEELS, IV, IW, IYAW, EkfParams, EkfState, RateUpdate
from robotd.odometry.relative import PoseClone, clone_after_predict
from sim.emulators.kobuki import driver_messages, simulate_kobuki
from sim.route import MotionLimits, build_route, plan_motion
from sim.sensors import BaseSensorParams

_EYE = np.eye(6)


def _old_predict_with_jacobian(state: EkfState, t_ns: int, params: EkfParams) -> tuple[EkfState, np.ndarray]:
    """The prediction as it was: the arc's Jacobian as a matrix, ``F P F^T + Q`` by products."""
    dt_ns = int(t_ns) - state.stamp_ns
    if dt_ns == 0:
        return state, _EYE.copy()
    dt = dt_ns * 1e-9
    x, y, yaw, v, w, bias = state.mean.tolist()
    ds, dth = v * dt, w * dt
    u = 0.5 * dth
    if abs(u) < 1e-4:
        f, df = 1.0 - u * u / 6.0, -u / 6.0
    else:
        f, df = math.sin(u) / u, 0.5 * (u * math.cos(u) - math.sin(u)) / (u * u)
    phi = yaw + 0.5 * dth
    c, s = math.cos(phi), math.sin(phi)
    mean = np.array([x + ds * f * c, y + ds * f * s, wrap_angle(yaw + dth), v, w, bias])
    jac = _EYE.copy()
    jac[0, 2], jac[1, 2], jac[0, 3], jac[1, 3] = -ds * f * s, ds * f * c, dt * f * c, dt * f * s
    jac[0, 4], jac[1, 4], jac[2, 4] = ds * dt * (df * c - 0.5 * f * s), ds * dt * (df * s + 0.5 * f * c), dt
    qa = params.angular_accel_noise_density_radps2_per_sqrt_hz ** 2
    ql = params.accel_noise_density_mps2_per_sqrt_hz ** 2
    d2, d3 = dt * dt / 2.0, dt ** 3 / 3.0
    if params.rate_only_process:
        d2 = d3 = 0.0
    q = np.array([[ql * d3 * c * c, ql * d3 * c * s, 0.0, ql * d2 * c, 0.0, 0.0],
                  [ql * d3 * c * s, ql * d3 * s * s, 0.0, ql * d2 * s, 0.0, 0.0],
                  [0.0, 0.0, qa * d3, 0.0, qa * d2, 0.0],
                  [ql * d2 * c, ql * d2 * s, 0.0, ql * dt, 0.0, 0.0],
                  [0.0, 0.0, qa * d2, 0.0, qa * dt, 0.0],
                  [0.0, 0.0, 0.0, 0.0, 0.0, params.gyro_bias_walk_radps_per_sqrt_s ** 2 * dt]])
    cov = jac @ state.cov @ jac.T + q
    return EkfState(int(t_ns), mean, 0.5 * (cov + cov.T)), jac


def _old_update(state: EkfState, innovation: np.ndarray, h: np.ndarray, r: np.ndarray,
                smooth_pose: bool = False) -> RateUpdate:
    """The rate update as it was: ``K = P H^T S^-1``, the Joseph form of full matrices."""
    p = state.cov
    ph = p @ h.T
    gain = np.linalg.solve(h @ ph + r, ph.T).T
    if smooth_pose:
        gain[:3] = 0.0
    mean = state.mean + gain @ innovation
    mean[IYAW] = wrap_angle(mean[IYAW])
    a = _EYE - gain @ h
    cov = a @ p @ a.T + gain @ r @ gain.T
    return RateUpdate(EkfState(state.stamp_ns, mean, 0.5 * (cov + cov.T)), gain, r, a)


class _StepByStep(fusion.OdometryFilter):
    """The filter with the error maps multiplied and the pose clone carried at every step."""

    def _step_map(self, step: np.ndarray) -> None:
        self._map = step @ self._map
        if self._clone is not None:
            self._clone = clone_after_predict(self._clone, step)

    def _clone_now(self) -> PoseClone | None:
        return self._clone

    def _clone_follows_map(self) -> None:
        pass


def _drive(seed: int = 3) -> tuple[list, list]:
    """The square route's Kobuki messages, and a visual step every 25 wheel readings (the
    true motion between the keyframes plus noise), each arriving 6 readings late."""
    motion = plan_motion(build_route("square"), MotionLimits())
    msgs = driver_messages(simulate_kobuki(motion, BaseSensorParams(), np.random.default_rng(seed)))
    rng = np.random.default_rng(seed)
    return msgs, [rng.normal(0.0, 1e-3, 3) for _ in range(len(msgs))], motion  # type: ignore[return-value]


def _run(cls: type, msgs: list, noise: list, motion) -> dict[str, list[np.ndarray]]:
    f = cls(vo_twin=True)
    out: dict[str, list[np.ndarray]] = {"pose": [], "twin": [], "edge": []}
    pending: list[tuple[int, int | None]] = []
    wheels, prev = 0, None
    for m in msgs:
        if not isinstance(m, WheelTicks):
            f.on_yaw_rate(m)
            continue
        f.on_wheels(m)
        p = f.pose()
        out["pose"].append(np.concatenate([[p.x_m, p.y_m, p.yaw_rad], p.covariance.ravel()]))
        s = f.wheel_gyro.state
        out["twin"].append(np.concatenate([s.mean, s.cov.ravel()]))
        wheels += 1
        if wheels % 25 == 0:
            stamp = int(m.stamp_ns) - 10_000_000
            edge = f.keyframe_edge(stamp)
            if edge is not None:
                out["edge"].append(np.concatenate([edge[0], edge[1].ravel()]))
            pending.append((stamp, prev))
            prev = stamp
        if pending and wheels % 25 == 6:  # the step comes a few readings late: the journal rewinds
            stamp, before = pending.pop(0)
            delta = None
            if before is not None:
                a, b = motion.pose_at(np.array([before, stamp]) * 1e-9)
                delta = between(a, b) + noise[wheels] * np.array([1.0, 1.0, 0.5])
            f.on_visual_odometry(stamp, before, delta, None if delta is None else np.diag([1e-6, 1e-6, 2.5e-7]))
    out["counters"] = [np.array([f.counters.vo_fused, f.counters.vo_rejected, f.counters.wheel_msgs])]
    return out


def test_the_written_out_steps_agree_with_the_matrix_products_to_rounding(monkeypatch: pytest.MonkeyPatch) -> None:
    msgs, noise, motion = _drive()
    with monkeypatch.context() as mp:
        mp.setattr(fusion, "predict_with_jacobian", _old_predict_with_jacobian)
        mp.setattr(ekf, "_update", _old_update)
        old = _run(_StepByStep, msgs, noise, motion)
    new = _run(fusion.OdometryFilter, msgs, noise, motion)
    assert new["counters"][0].tolist() == old["counters"][0].tolist()
    assert new["counters"][0][0] > 40  # visual steps fused (the clone and the rewinds ran)
    assert len(new["edge"]) == len(old["edge"]) > 40
    for key, n_pose in (("pose", 3), ("twin", 6), ("edge", 3)):
        a, b = np.array(new[key]), np.array(old[key])
        assert np.abs(a[:, :2] - b[:, :2]).max() < 1e-10  # m (the whole drive's, ~1e-14 seen)
        assert np.abs(a[:, 2] - b[:, 2]).max() < 1e-10  # rad
        if key == "twin":
            assert np.abs(a[:, 3:n_pose] - b[:, 3:n_pose]).max() < 1e-10  # v, w, bias
        cov_a, cov_b = a[:, n_pose:], b[:, n_pose:]
        scale = np.abs(cov_b).max(axis=1, keepdims=True)
        assert (np.abs(cov_a - cov_b) / scale).max() < 1e-9  # relative to the matrix's largest entry
        if key != "edge":  # the filter's covariance stays exactly symmetric
            m = cov_a.reshape(-1, n_pose, n_pose)
            assert np.array_equal(m, m.transpose(0, 2, 1))


def test_the_written_out_gyro_and_wheel_updates_keep_h_and_r_as_given() -> None:
    """The written-out update is the products' for both measurement rows, at rest (the
    pose rows of the gain held) and moving, with a stated variance."""
    rng = np.random.default_rng(1)
    a = rng.normal(size=(6, 6))
    state = EkfState(0, rng.normal(size=6), a @ a.T + np.eye(6))
    for h, r, inn in ((H_WHEELS, np.diag([0.02, 0.3]), np.array([0.1, -0.2])), (H_GYRO, np.array([[1e-3]]), np.array([0.05]))):
        for smooth in (False, True):
            got, want = ekf._update(state, inn, h, r, smooth), _old_update(state, inn, h, r, smooth)
            assert got.state.mean == pytest.approx(want.state.mean, abs=1e-12)
            assert np.abs(got.state.cov - want.state.cov).max() < 1e-12
            assert np.abs(got.error_map - want.error_map).max() < 1e-12
            assert np.abs(got.gain - want.gain).max() < 1e-12
            if smooth:
                assert not got.gain[:3].any() and got.state.mean[:2].tolist() == state.mean[:2].tolist()
                assert got.state.mean[2] == wrap_angle(float(state.mean[2]))
    assert IV == 3 and IW == 4  # the wheels' columns are adjacent (the update slices them)
