"""Wheel + gyro extended Kalman filter, written as pure functions of its state.

State (REP-103, SI units), ``n = 6``::

    [x_m, y_m, yaw_rad, v_mps, w_radps, gyro_bias_radps]

Why this state. Both sensors measure *rates*: the encoders give the base's speed ``v`` and
yaw rate ``w`` over each 20 ms packet, the gyro gives ``w + bias``. Keeping ``v`` and
``w`` in the state lets each sensor be an ordinary measurement at its own time and rate
(50 Hz wheels, ~100 Hz gyro samples), with no need to pair them up. The gyro bias must be
in the state: a bias of 0.2 deg/s left alone turns into 10 deg of heading error in under a
minute. It is observable where the wheels pin ``w`` down: at standstill (no tick moves,
so ``w = 0``). While driving, the wheel yaw rate is *systematically* wrong: unequal wheel
diameters add ``c * v`` (``c`` up to ~0.01 rad/m for a 0.2 % difference) and the
effective wheel base scales every turn by 1-2 %. A white-noise model cannot represent a
constant error; if the wheels' yaw-rate noise were only their random part, the filter
would average ``c * v`` into the bias while driving (on the 110 m office route, the seed
whose wheels differ by 0.18 % ends 5.8 deg off with 0.05 rad/s per m/s, 2.1 deg with 0.5;
the median over 5 seeds is about the same). So the wheel yaw-rate noise grows with speed
(``wheel_w_noise_per_mps``, 0.5 rad/s per m/s) until five minutes of 50 Hz wheel data at
0.5 m/s constrain the bias no better than ``c * v`` itself: the heading follows the
bias-corrected gyro, the wheels provide the distance and, at standstill, the bias. A
7-state filter with ``c`` in the state would calibrate it online; it is not needed for
the accuracy the loop labelling uses (paper 003, Sec. IV-C), and it would make the bias
depend on the robot reaching different speeds.

The alternative of feeding the wheel increments in as a control input to an ``(x, y,
yaw)`` filter cannot estimate the bias, and treating the gyro as the control input hides
its noise from the bias estimate. Paper 003 (Sec. IV-C) labels its training pairs with a
Kalman filter of wheel odometry and the robot's gyroscope.

Motion model: constant ``v`` and ``w`` over a step, integrated along the arc (exact for
constant curvature, see :func:`robotd.odometry.kinematics.arc_increment`), driven by
white linear and angular acceleration; the bias is a random walk. The process noise is
the exact discretisation of that white acceleration for the ``(yaw, w)`` pair and for the
along-track ``(position, v)`` pair::

    Q[yaw, w]   = qa * [[dt^3/3, dt^2/2], [dt^2/2, dt]]          qa = angular_accel_noise^2
    Q[xy, v]    = ql * [[dt^3/3 u u^T, dt^2/2 u], [., dt]]      ql = accel_noise^2, u = heading
    Q[bias]     = gyro_bias_walk^2 * dt

Updates use the Joseph form and are symmetrised, so the covariance stays symmetric
positive definite. Yaw is kept wrapped to [-pi, pi); no measurement involves yaw, so no
innovation needs wrapping.

Every function returns a new :class:`EkfState` (GTSAM style), which makes each step
testable against a hand-derived answer.

:class:`OdometryFilter` runs these functions over the message stream the daemon sees:
:class:`~robotd.base.messages.WheelTicks` and :class:`~robotd.base.messages.YawRate` in stamp order,
with a wheel-only :class:`~robotd.odometry.kinematics.WheelOdometry` alongside for
comparison and the last couple of seconds of fused poses, so a camera frame gets the pose
at its own timestamp (paper 003, Sec. IV-C pairs floor images with this odometry).
Messages that cannot be used are values, not exceptions: ``on_wheels`` and
``on_yaw_rate`` return False and count why in :class:`FilterCounters`.

Standstill is where the bias is learnt, so it is detected with care: an interval counts
as still only when no tick moved in it *and* in the interval before (a decelerating wheel
can go ~30 ms without a tick while the base still creeps). Gyro readings wait for the
wheel message that covers their stamp (at most one packet, 20 ms) so the filter knows
whether they were taken at rest; each reading at rest is paired with a zero-velocity
update at its own time, unless it disagrees with the bias estimate by more than
``still_gate_sigma`` (the base was still turning). Without the pairing the white angular
acceleration lets ``w`` wander between the 50 Hz wheel updates and a 2 s standstill
teaches the filter almost nothing about the bias.
"""

from __future__ import annotations

import bisect
import collections
import logging
import math
from dataclasses import dataclass, field

import numpy as np

from robotd.base.geometry import between, interpolate_poses, wrap_angle
from robotd.base.messages import PoseStamped, WheelTicks, YawRate
from robotd.odometry.kinematics import (
    DiffDriveParams,
    WheelOdometry,
    integrate_pose,
    unwrap_ticks_delta,
    wheel_increment,
)
from robotd.odometry.relative import (
    PoseClone,
    clone_after_predict,
    clone_after_update,
    clone_pose,
    shift_measurement,
    update_relative_pose,
)

__all__ = [
    "IB",
    "IV",
    "IW",
    "IX",
    "IY",
    "IYAW",
    "STATE_SIZE",
    "EkfParams",
    "EkfState",
    "FilterCounters",
    "OdometryFilter",
    "initial_state",
    "predict",
    "predict_with_jacobian",
    "update_gyro",
    "update_wheels",
    "wheel_noise",
]

_log = logging.getLogger(__name__)

STATE_SIZE = 6
IX, IY, IYAW, IV, IW, IB = range(STATE_SIZE)

_H_WHEELS = np.zeros((2, STATE_SIZE))
_H_WHEELS[0, IV] = 1.0
_H_WHEELS[1, IW] = 1.0
_H_GYRO = np.zeros((1, STATE_SIZE))
_H_GYRO[0, IW] = 1.0
_H_GYRO[0, IB] = 1.0
_EYE = np.eye(STATE_SIZE)


@dataclass(frozen=True, slots=True)
class EkfParams:
    """Noise model of the filter; all values are 1-sigma.

    The first nine fields have the names and defaults of the ``[odometry]`` table of the
    configuration file, so ``EkfParams(**dataclasses.asdict(config.odometry))`` works.

    - ``accel_noise_mps2``: white linear acceleration driving ``v``, m/s^2 per sqrt(Hz)
      (the velocity's variance grows by ``accel_noise_mps2**2 * dt``).
    - ``angular_accel_noise_radps2``: white angular acceleration driving ``w``,
      rad/s^2 per sqrt(Hz).
    - ``gyro_bias_walk_radps_sqrt_s``: gyro bias random walk, rad/s per sqrt(s).
    - ``wheel_v_noise_mps`` + ``wheel_v_noise_frac * |v|``: noise of the speed from
      one tick delta, m/s (tick quantisation, then scale error and slip growing with speed).
    - ``wheel_w_noise_radps`` + ``wheel_w_noise_frac * |w|`` + ``wheel_w_noise_per_mps *
      |v|``: noise of the wheel yaw rate, rad/s (quantisation; wheel-base error growing
      with the turn rate; unequal wheels and slip growing with speed).
    - ``gyro_noise_radps``: white noise of one gyro reading, rad/s.
    - ``initial_gyro_bias_sigma_radps``: prior on the bias before any standstill, rad/s.
    - ``stationary_noise_mps`` / ``stationary_noise_radps``: noise of the wheel speed and
      yaw rate when no tick moved over the interval (zero-velocity update), m/s and rad/s.
    - ``initial_speed_sigma_mps`` / ``initial_yaw_rate_sigma_radps``: prior on ``v``, ``w``.
    - ``initial_pose_sigma``: prior on ``x``, ``y`` (m) and ``yaw`` (rad); the start pose
      defines the odometry frame (paper 003, Sec. III), so this is tiny but keeps the
      covariance positive definite.
    """

    accel_noise_mps2: float = 0.5
    angular_accel_noise_radps2: float = 0.3
    gyro_bias_walk_radps_sqrt_s: float = 2e-5
    wheel_v_noise_mps: float = 0.01
    wheel_v_noise_frac: float = 0.02
    wheel_w_noise_radps: float = 0.05
    wheel_w_noise_frac: float = 0.05
    gyro_noise_radps: float = 0.003
    initial_gyro_bias_sigma_radps: float = 0.01
    wheel_w_noise_per_mps: float = 0.5
    stationary_noise_mps: float = 1e-3
    stationary_noise_radps: float = 1e-3
    initial_speed_sigma_mps: float = 0.5
    initial_yaw_rate_sigma_radps: float = 1.0
    initial_pose_sigma: float = 1e-5

    def __post_init__(self) -> None:
        for name in self.__slots__:
            value = getattr(self, name)
            if not (value >= 0.0 and math.isfinite(value)):
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        for name in ("wheel_v_noise_mps", "wheel_w_noise_radps", "gyro_noise_radps",
                     "stationary_noise_mps", "stationary_noise_radps", "initial_pose_sigma",
                     "initial_gyro_bias_sigma_radps", "initial_speed_sigma_mps",
                     "initial_yaw_rate_sigma_radps"):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"{name} must be > 0")


@dataclass(frozen=True, slots=True, eq=False)
class EkfState:
    """The filter's belief at ``stamp_ns``: ``mean`` ``(6,)`` and ``cov`` ``(6, 6)``, float64.

    The arrays are read-only; every filter function returns a new state.
    """

    stamp_ns: int
    mean: np.ndarray
    cov: np.ndarray

    def __post_init__(self) -> None:
        mean = np.array(self.mean, dtype=float).reshape(STATE_SIZE)
        cov = np.array(self.cov, dtype=float).reshape(STATE_SIZE, STATE_SIZE)
        mean.setflags(write=False)
        cov.setflags(write=False)
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "cov", cov)
        object.__setattr__(self, "stamp_ns", int(self.stamp_ns))

    @property
    def pose_xyyaw(self) -> np.ndarray:
        """``(3,)`` the pose ``(x_m, y_m, yaw_rad)``."""
        return self.mean[:3].copy()

    @property
    def pose_cov(self) -> np.ndarray:
        """``(3, 3)`` covariance of ``(x_m, y_m, yaw_rad)``."""
        return self.cov[:3, :3].copy()

    @property
    def gyro_bias_radps(self) -> float:
        """The estimated gyro bias, rad/s."""
        return float(self.mean[IB])

    def pose(self) -> PoseStamped:
        """The pose part as a :class:`~robotd.base.messages.PoseStamped`."""
        m = self.mean
        return PoseStamped(self.stamp_ns, float(m[IX]), float(m[IY]), float(m[IYAW]),
                           self.pose_cov)


def initial_state(stamp_ns: int, params: EkfParams = EkfParams(),
                  pose: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> EkfState:
    """The belief before any measurement: at ``pose``, speed and bias unknown (priors)."""
    mean = np.array([pose[0], pose[1], wrap_angle(float(pose[2])), 0.0, 0.0, 0.0])
    sig = np.array([params.initial_pose_sigma] * 3 + [
        params.initial_speed_sigma_mps, params.initial_yaw_rate_sigma_radps,
        params.initial_gyro_bias_sigma_radps])
    return EkfState(stamp_ns, mean, np.diag(sig ** 2))


def _sinc_half_and_derivative(dth: float) -> tuple[float, float]:
    """``f = sin(dth/2)/(dth/2)`` and ``df/d(dth)``, accurate near zero."""
    u = 0.5 * dth
    if abs(u) < 1e-4:
        return 1.0 - u * u / 6.0, -u / 6.0
    s, c = math.sin(u), math.cos(u)
    return s / u, 0.5 * (u * c - s) / (u * u)


def predict(state: EkfState, t_ns: int, params: EkfParams = EkfParams()) -> EkfState:
    """Propagate ``state`` to ``t_ns`` (>= its stamp) with the constant-rate model.

    ``dt = 0`` returns ``state`` unchanged; a negative ``dt`` is a ``ValueError``.
    """
    return predict_with_jacobian(state, t_ns, params)[0]


def predict_with_jacobian(state: EkfState, t_ns: int,
                          params: EkfParams = EkfParams()) -> tuple[EkfState, np.ndarray]:
    """:func:`predict` and its ``(6, 6)`` state Jacobian (a pose clone's cross-covariance
    follows it, :mod:`robotd.odometry.relative`)."""
    dt_ns = int(t_ns) - state.stamp_ns
    if dt_ns < 0:
        raise ValueError(f"cannot predict backwards ({t_ns} < {state.stamp_ns})")
    if dt_ns == 0:
        return state, _EYE.copy()
    dt = dt_ns * 1e-9
    m = state.mean
    yaw, v, w = m[IYAW], m[IV], m[IW]
    ds, dth = v * dt, w * dt
    f, df = _sinc_half_and_derivative(dth)
    phi = yaw + 0.5 * dth
    c, s = math.cos(phi), math.sin(phi)
    mean = m.copy()
    mean[IX] += ds * f * c
    mean[IY] += ds * f * s
    mean[IYAW] = wrap_angle(yaw + dth)

    jac = _EYE.copy()
    jac[IX, IYAW] = -ds * f * s
    jac[IY, IYAW] = ds * f * c
    jac[IX, IV] = dt * f * c
    jac[IY, IV] = dt * f * s
    jac[IX, IW] = ds * dt * (df * c - 0.5 * f * s)
    jac[IY, IW] = ds * dt * (df * s + 0.5 * f * c)
    jac[IYAW, IW] = dt

    q = np.zeros((STATE_SIZE, STATE_SIZE))
    qa = params.angular_accel_noise_radps2 ** 2
    ql = params.accel_noise_mps2 ** 2
    d2, d3 = dt * dt / 2.0, dt ** 3 / 3.0
    q[IYAW, IYAW] = qa * d3
    q[IYAW, IW] = q[IW, IYAW] = qa * d2
    q[IW, IW] = qa * dt
    ux, uy = c, s
    q[IX, IX] = ql * d3 * ux * ux
    q[IY, IY] = ql * d3 * uy * uy
    q[IX, IY] = q[IY, IX] = ql * d3 * ux * uy
    q[IX, IV] = q[IV, IX] = ql * d2 * ux
    q[IY, IV] = q[IV, IY] = ql * d2 * uy
    q[IV, IV] = ql * dt
    q[IB, IB] = params.gyro_bias_walk_radps_sqrt_s ** 2 * dt

    cov = jac @ state.cov @ jac.T + q
    return EkfState(int(t_ns), mean, 0.5 * (cov + cov.T)), jac


def _update(state: EkfState, innovation: np.ndarray, h: np.ndarray, r: np.ndarray) -> EkfState:
    """Linear(ised) measurement update in Joseph form."""
    p = state.cov
    ph = p @ h.T
    s = h @ ph + r
    gain = np.linalg.solve(s, ph.T).T  # = P H^T S^-1 (S is symmetric)
    mean = state.mean + gain @ innovation
    mean[IYAW] = wrap_angle(mean[IYAW])
    a = _EYE - gain @ h
    cov = a @ p @ a.T + gain @ r @ gain.T
    return EkfState(state.stamp_ns, mean, 0.5 * (cov + cov.T))


def wheel_noise(v_mps: float, w_radps: float, params: EkfParams,
                stationary: bool = False) -> tuple[float, float]:
    """1-sigma noise ``(sigma_v_mps, sigma_w_radps)`` of one wheel speed measurement."""
    if stationary:
        return params.stationary_noise_mps, params.stationary_noise_radps
    sv = params.wheel_v_noise_mps + params.wheel_v_noise_frac * abs(v_mps)
    sw = (params.wheel_w_noise_radps + params.wheel_w_noise_frac * abs(w_radps)
          + params.wheel_w_noise_per_mps * abs(v_mps))
    return sv, sw


def update_wheels(state: EkfState, v_mps: float, w_radps: float,
                  params: EkfParams = EkfParams(), stationary: bool = False) -> EkfState:
    """Measurement ``(v, w)`` from the encoders: ``h(x) = (x[v], x[w])``.

    ``stationary=True`` (no tick moved over the interval) uses the much smaller
    zero-velocity noise: the base is not moving, which is what makes the bias observable.
    """
    sv, sw = wheel_noise(v_mps, w_radps, params, stationary)
    z = np.array([v_mps, w_radps], dtype=float)
    innovation = z - state.mean[[IV, IW]]
    return _update(state, innovation, _H_WHEELS, np.diag([sv * sv, sw * sw]))


def update_gyro(state: EkfState, w_radps: float, params: EkfParams = EkfParams()) -> EkfState:
    """Measurement of the gyro's yaw rate: ``h(x) = x[w] + x[bias]``."""
    innovation = np.array([w_radps - state.mean[IW] - state.mean[IB]])
    r = np.array([[params.gyro_noise_radps ** 2]])
    return _update(state, innovation, _H_GYRO, r)


# --------------------------------------------------------------------------------------
# The filter over a message stream (what the daemon runs).
# --------------------------------------------------------------------------------------


@dataclass
class FilterCounters:
    """What the filter did with its input.

    ``wheel_msgs``/``yaw_msgs``: messages used. ``out_of_order``: dropped because older
    than what was already processed (beyond ``late_tolerance_ns``). ``duplicates``:
    dropped because their stream already had a message with that stamp. ``late``: used
    at the filter's current time although slightly older. ``gaps``: wheel intervals
    longer than ``max_gap_s``. ``resets``: gaps so long the tick counters may have
    wrapped ambiguously; the wheel reference was restarted without motion.
    ``still_updates``: wheel intervals taken as standstill (zero-velocity updates).
    ``still_rejected``: gyro readings at standstill that disagreed with it (gate).
    Visual odometry (:meth:`OdometryFilter.on_visual_odometry`): ``vo_fused`` used,
    ``vo_missing`` keyframes without a measurement, ``vo_no_clone`` measurements whose
    previous keyframe is not the filter's last, ``vo_no_pose`` keyframes outside the
    pose history, ``vo_rejected`` measurements that failed the chi-square gate.
    """

    wheel_msgs: int = 0
    yaw_msgs: int = 0
    still_updates: int = 0
    still_rejected: int = 0
    out_of_order: int = 0
    duplicates: int = 0
    late: int = 0
    gaps: int = 0
    resets: int = 0
    vo_fused: int = 0
    vo_missing: int = 0
    vo_no_clone: int = 0
    vo_no_pose: int = 0
    vo_rejected: int = 0


@dataclass
class OdometryFilter:
    """Wheel + gyro EKF over a message stream, with a wheel-only twin and a pose history.

    ``drive``: the base geometry. ``params``: the EKF noise model. ``initial_pose``: the
    pose at the first message (the start defines the odometry frame). ``history_s``: how
    far back :meth:`pose_at` can look. ``max_gap_s``: a longer wheel interval is a gap.
    ``late_tolerance_ns``: a message at most this much older than the filter's time is
    still used, at the filter's time (a driver may emit a packet's gyro samples after its
    wheel ticks); older ones are dropped. ``max_wheel_speed_mps``: bounds how far a wheel
    can turn in a gap before the 16-bit counters become ambiguous. ``max_gyro_wait_s``:
    how long gyro readings wait for a wheel message before they are applied anyway.
    ``still_gate_sigma``: at rest, a gyro reading further than this many sigma from the
    bias estimate is not paired with a zero-velocity update. ``vo_gate_nis``: a visual
    odometry measurement whose normalised innovation squared exceeds this (chi-square, 3
    degrees of freedom; 16.27 = 99.9 %) is rejected.
    """

    drive: DiffDriveParams = field(default_factory=DiffDriveParams)
    params: EkfParams = field(default_factory=EkfParams)
    initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    history_s: float = 2.0
    max_gap_s: float = 0.25
    late_tolerance_ns: int = 20_000_000
    max_wheel_speed_mps: float = 0.7
    max_gyro_wait_s: float = 0.1
    still_gate_sigma: float = 3.0
    vo_gate_nis: float = 16.27

    def __post_init__(self) -> None:
        self.counters = FilterCounters()
        self._state: EkfState | None = None
        self._wheel = WheelOdometry(self.drive, self.initial_pose)
        self._wheel_ref: WheelTicks | None = None
        self._last_yaw_ns: int | None = None
        self._gyro_buf: collections.deque[YawRate] = collections.deque()
        self._was_still = False
        self._clone: PoseClone | None = None  # the pose at the last keyframe (relative.py)
        self._max_gyro_wait_ns = int(self.max_gyro_wait_s * 1e9)
        self._hist_t: list[int] = []
        self._hist_pose: list[np.ndarray] = []
        self._hist_cov: list[np.ndarray] = []
        self._history_ns = int(self.history_s * 1e9)
        # A wheel turning at max speed covers half the counter range in this time.
        half_range_m = 32767 * self.drive.metres_per_tick
        self._max_unwrap_ns = int(half_range_m / self.max_wheel_speed_mps * 1e9)

    # ---- input --------------------------------------------------------------------------

    def on_wheels(self, msg: WheelTicks) -> bool:
        """Use one encoder reading; False (and counted) when it was dropped.

        Gyro readings buffered up to this stamp are applied first, in stamp order; when no
        tick moved over this interval and the one before, the base was standing still and
        each of them is paired with a zero-velocity update (this calibrates the bias).
        """
        t = int(msg.stamp_ns)
        ref = self._wheel_ref
        if ref is not None:
            if t == ref.stamp_ns:
                self.counters.duplicates += 1
                return False
            if t < ref.stamp_ns:
                self.counters.out_of_order += 1
                return False
        if not self._admit(t):
            return False
        self.counters.wheel_msgs += 1
        self._wheel_ref = msg
        if ref is None:
            self._wheel.update(msg)
            self._flush_gyro(t, stationary=False)
            self._advance_to(t)
            self._record()
            return True

        dt_ns = t - ref.stamp_ns
        if dt_ns > self._max_unwrap_ns:
            self.counters.gaps += 1
            self.counters.resets += 1
            _log.warning("wheel gap of %.1f s: tick counters may have wrapped; restarting "
                         "the wheel reference", dt_ns * 1e-9)
            self._wheel.rebase(msg)
            self._flush_gyro(t, stationary=False)
            self._advance_to(t)
            self._record()
            return True

        dl = unwrap_ticks_delta(ref.left_ticks, msg.left_ticks)
        dr = unwrap_ticks_delta(ref.right_ticks, msg.right_ticks)
        self._wheel.update(msg)
        ds, dyaw = wheel_increment(dl, dr, self.drive)
        dt = dt_ns * 1e-9
        v, w = ds / dt, dyaw / dt
        # At rest: no tick over this interval and the one before (a decelerating wheel
        # can go ~30 ms without a tick while the base still creeps).
        still_now = dl == 0 and dr == 0
        stationary = still_now and self._was_still
        self._was_still = still_now
        if dt_ns > self.max_gap_s * 1e9:
            self.counters.gaps += 1
            state = self._state
            no_gyro = not self._gyro_buf or self._gyro_buf[0].stamp_ns > t
            if state is not None and state.stamp_ns <= ref.stamp_ns and no_gyro:
                # Nothing arrived during the gap: the constant-rate prediction knows
                # nothing of what happened, the ticks do. Move the mean along the wheel
                # arc and keep the predicted (grown) covariance.
                pred, jac = predict_with_jacobian(state, t, self.params)
                mean = pred.mean.copy()
                mean[:3] = integrate_pose(state.mean[:3], ds, dyaw)
                mean[IV], mean[IW] = v, w
                self._state = EkfState(t, mean, pred.cov)
                if self._clone is not None:
                    self._clone = clone_after_predict(self._clone, jac)
        self._flush_gyro(t, stationary)
        self.counters.still_updates += int(stationary)
        self._advance_to(t)
        self._apply_wheels(v, w, stationary)
        self._record()
        return True

    def on_yaw_rate(self, msg: YawRate) -> bool:
        """Take one gyro reading; False (and counted) when it was dropped.

        Readings wait (at most ``max_gyro_wait_s``) for the wheel message that covers
        their stamp, which tells whether the base was standing still.
        """
        t = int(msg.stamp_ns)
        if self._last_yaw_ns is not None:
            if t == self._last_yaw_ns:
                self.counters.duplicates += 1
                return False
            if t < self._last_yaw_ns:
                self.counters.out_of_order += 1
                return False
        if not self._admit(t):
            return False
        self._last_yaw_ns = t
        self.counters.yaw_msgs += 1
        self._gyro_buf.append(msg)
        if t - self._gyro_buf[0].stamp_ns > self._max_gyro_wait_ns:
            # No wheel message for a while: use what we have without the standstill test.
            self._flush_gyro(t, stationary=False)
        return True

    def _flush_gyro(self, t: int, stationary: bool) -> None:
        """Apply the buffered gyro readings stamped at or before ``t``."""
        buf = self._gyro_buf
        while buf and buf[0].stamp_ns <= t:
            msg = buf.popleft()
            ts = int(msg.stamp_ns)
            if self._state is None:
                self._state = initial_state(ts, self.params, self.initial_pose)
            self._advance_to(ts)
            rate = float(msg.yaw_rate_radps)
            if stationary and self._still_gate(rate):
                self._apply_wheels(0.0, 0.0, True)
            prior = self._state
            self._state = update_gyro(prior, rate, self.params)
            if self._clone is not None:
                r = np.array([[self.params.gyro_noise_radps ** 2]])
                self._clone = clone_after_update(self._clone, prior.cov, _H_GYRO, r)
            self._record()

    def _apply_wheels(self, v: float, w: float, stationary: bool) -> None:
        """The wheel update, carrying a pose clone's cross-covariance along."""
        prior = self._state
        assert prior is not None
        self._state = update_wheels(prior, v, w, self.params, stationary=stationary)
        if self._clone is not None:
            sv, sw = wheel_noise(v, w, self.params, stationary)
            self._clone = clone_after_update(self._clone, prior.cov, _H_WHEELS, np.diag([sv * sv, sw * sw]))

    def _still_gate(self, rate_radps: float) -> bool:
        """True when the gyro agrees with a base at rest (within ``still_gate_sigma``).

        Ticks stop about 30 ms before a decelerating turn does (the last tick is 85 um of
        rim), so a reading can come from a base that still turns a little: pinning its
        yaw rate to zero then would push the error into the bias estimate.
        """
        s = self._state
        assert s is not None
        p = self.params
        var = s.cov[IB, IB] + p.gyro_noise_radps ** 2 + p.stationary_noise_radps ** 2
        resid = rate_radps - s.mean[IB]
        if resid * resid <= self.still_gate_sigma ** 2 * var:
            return True
        self.counters.still_rejected += 1
        return False

    def _admit(self, t: int) -> bool:
        """False (counted) when ``t`` is too far behind the filter's time."""
        if self._state is None:
            self._state = initial_state(t, self.params, self.initial_pose)
            return True
        if t >= self._state.stamp_ns:
            return True
        if self._state.stamp_ns - t <= self.late_tolerance_ns:
            self.counters.late += 1
            return True
        self.counters.out_of_order += 1
        return False

    def _advance_to(self, t: int) -> None:
        assert self._state is not None
        if t > self._state.stamp_ns:
            self._state, jac = predict_with_jacobian(self._state, t, self.params)
            if self._clone is not None:
                self._clone = clone_after_predict(self._clone, jac)

    def on_visual_odometry(self, stamp_ns: int, prev_stamp_ns: int | None, delta: np.ndarray | None,
                           covariance: np.ndarray | None) -> bool:
        """Fuse the motion between the keyframes at ``prev_stamp_ns`` and ``stamp_ns``.

        ``delta (3,)``: the pose at ``stamp_ns`` in the robot frame of the pose at
        ``prev_stamp_ns`` (``dx_m, dy_m, dyaw_rad``, floor visual odometry, paper 003 Sec.
        IV-D); ``covariance (3, 3)``. Call it for every keyframe, in order, once the filter
        has reached its stamp; ``delta=None`` (the step failed) leaves the wheel + gyro
        estimate alone. Either way the pose at ``stamp_ns`` becomes the clone the next
        measurement refers to (stochastic cloning, :mod:`robotd.odometry.relative`).
        Returns True when fused; otherwise False and counted (:class:`FilterCounters`).
        """
        s = self._state
        kf = self.pose_at(stamp_ns) if s is not None else None
        if s is None or kf is None:
            self.counters.vo_no_pose += 1
            self._clone = None
            return False
        offset = between(np.array([kf.x_m, kf.y_m, kf.yaw_rad]), s.mean[:3])
        fused = False
        c = self._clone
        if delta is None or covariance is None or not np.all(np.isfinite(delta)):
            self.counters.vo_missing += 1
        elif c is None or c.keyframe_stamp_ns != prev_stamp_ns:
            self.counters.vo_no_clone += 1
        else:
            z, r = shift_measurement(delta, covariance, c.offset, offset)
            mean, cov, nis = update_relative_pose(s.mean, s.cov, c, z, r)
            if nis > self.vo_gate_nis:
                self.counters.vo_rejected += 1
            else:
                self._state = EkfState(s.stamp_ns, mean, cov)
                self._record()
                self.counters.vo_fused += 1
                fused = True
        self._clone = clone_pose(self._state.mean, self._state.cov, stamp_ns, offset)
        return fused

    def _record(self) -> None:
        s = self._state
        assert s is not None
        t = s.stamp_ns
        pose, cov = s.mean[:3].copy(), s.cov[:3, :3].copy()
        if self._hist_t and self._hist_t[-1] == t:
            self._hist_pose[-1], self._hist_cov[-1] = pose, cov
            return
        self._hist_t.append(t)
        self._hist_pose.append(pose)
        self._hist_cov.append(cov)
        if len(self._hist_t) > 64 and t - self._hist_t[0] > 2 * self._history_ns:
            cut = bisect.bisect_left(self._hist_t, t - self._history_ns)
            cut = min(cut, len(self._hist_t) - 2)
            del self._hist_t[:cut], self._hist_pose[:cut], self._hist_cov[:cut]

    # ---- output -------------------------------------------------------------------------

    @property
    def state(self) -> EkfState | None:
        """The full EKF state (None before the first message)."""
        return self._state

    def latest_stamp_ns(self) -> int | None:
        """The filter's time: the newest stamp it has processed (None before any)."""
        return None if self._state is None else self._state.stamp_ns

    def settled_stamp_ns(self) -> int | None:
        """The newest stamp up to which :meth:`pose_at` is final (None before two poses).

        The newest recorded pose can still change: a gyro reading of its own stamp, or a
        late one, is applied to it when the next wheel message arrives. Every pose before it
        is fixed, so a frame stamped up to here gets the same pose whatever arrives later
        (a replay then reproduces the live keyframes exactly).
        """
        return self._hist_t[-2] if len(self._hist_t) >= 2 else None

    def pose(self) -> PoseStamped:
        """The fused pose and its 3x3 covariance (the initial pose before any message)."""
        if self._state is None:
            return initial_state(0, self.params, self.initial_pose).pose()
        return self._state.pose()

    def wheel_pose(self) -> PoseStamped:
        """The wheel-only dead-reckoned pose, for comparison."""
        return self._wheel.pose()

    def pose_at(self, stamp_ns: int) -> PoseStamped | None:
        """The fused pose at ``stamp_ns``, interpolated between the two recorded poses around it.

        Position and covariance are interpolated linearly, yaw along the shorter arc.
        None when ``stamp_ns`` is newer than the filter's time or older than the history.
        """
        ts = self._hist_t
        if not ts or stamp_ns > ts[-1] or stamp_ns < ts[0]:
            return None
        i = bisect.bisect_left(ts, stamp_ns)
        if ts[i] == stamp_ns:
            p, c = self._hist_pose[i], self._hist_cov[i]
            return PoseStamped(int(stamp_ns), float(p[0]), float(p[1]), float(p[2]), c.copy())
        t0, t1 = ts[i - 1], ts[i]
        f = (stamp_ns - t0) / (t1 - t0)
        x, y, yaw = interpolate_poses(np.array([t0, t1], dtype=np.int64),
                                      np.array([self._hist_pose[i - 1], self._hist_pose[i]]),
                                      np.array([stamp_ns], dtype=np.int64))[0]
        cov = (1.0 - f) * self._hist_cov[i - 1] + f * self._hist_cov[i]
        return PoseStamped(int(stamp_ns), float(x), float(y), float(yaw), cov)
