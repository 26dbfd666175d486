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

The stream of messages is run through these functions by
:class:`robotd.odometry.fusion.OdometryFilter`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from robotd.base.config import OdometryConfig
from robotd.base.geometry import wrap_angle
from robotd.base.messages import PoseStamped

__all__ = [
    "H_GYRO",
    "H_WHEELS",
    "IB",
    "IV",
    "IW",
    "IX",
    "IY",
    "IYAW",
    "STATE_SIZE",
    "EkfParams",
    "EkfState",
    "RateUpdate",
    "advance_pose",
    "initial_state",
    "predict",
    "predict_rates",
    "predict_with_jacobian",
    "slip_variances",
    "sub_gate_slip_variances",
    "speed_changing",
    "turning",
    "update_gyro",
    "update_gyro_with_gain",
    "update_wheels",
    "update_wheels_with_gain",
    "wheel_noise",
]

_log = logging.getLogger(__name__)

STATE_SIZE = 6
IX, IY, IYAW, IV, IW, IB = range(STATE_SIZE)

H_WHEELS = np.zeros((2, STATE_SIZE))
H_WHEELS[0, IV] = 1.0
H_WHEELS[1, IW] = 1.0
H_GYRO = np.zeros((1, STATE_SIZE))
H_GYRO[0, IW] = 1.0
H_GYRO[0, IB] = 1.0
_EYE = np.eye(STATE_SIZE)
_EYE_LOWER = tuple(_EYE[3:].ravel().tolist())  # the rows v, w, bias of the identity
_WHEEL_COLUMNS = [IV, IW]
_CONFIG = OdometryConfig()


@dataclass(frozen=True, slots=True)
class EkfParams:
    """Noise model of the filter: process noises as spectral densities (square roots of
    the power spectral densities), measurement noises 1-sigma per reading.

    The first ten fields are the keys of the ``[odometry]`` table of the configuration
    file (but its ``noise_model`` and ``slip_gate_sigma``, which
    :func:`robotd.app.assemble.build_odometry` reads), defaults included (taken from :class:`~robotd.base.config.OdometryConfig`, the
    one place they are written): :meth:`from_config` builds the params from that table.

    - ``accel_noise_density_mps2_per_sqrt_hz``: white linear acceleration driving ``v``,
      m/s^2 per sqrt(Hz) (the velocity's variance grows by its square times ``dt``).
    - ``angular_accel_noise_density_radps2_per_sqrt_hz``: white angular acceleration
      driving ``w``, rad/s^2 per sqrt(Hz).
    - ``gyro_bias_walk_radps_per_sqrt_s``: gyro bias random walk, rad/s per sqrt(s).
    - ``wheel_v_noise_mps`` + ``wheel_v_noise_frac * |v|``: noise of the speed from
      one tick delta, m/s (tick quantisation, then scale error and slip growing with speed).
    - ``wheel_slip_var_m2_per_m`` (default 0: none): each wheel's continuous slip, the
      variance of its distance per metre of its own travel (m^2/m, the calibration's wheel
      slip density squared). Over a reading of ``dt`` seconds the two wheels travel
      ``|v -+ w h| dt`` (``h`` = ``slip_half_base_m``, half the wheel base; 0: a straight's
      ``|v| dt`` each) and slip independently, so the speed (their mean) gets the variance
      ``q (|v - w h| + |v + w h|) / (4 dt)`` in quadrature with the ticks' noise. It grows
      with the wheels' travel, not the base's speed: a turn on the spot slips too.
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
    - ``smooth_pose`` (default True): at rest (the zero-velocity updates and the gyro
      readings paired with them) the measurements update ``v``, ``w`` and the bias but do
      not move the pose. The optimal gain would also move it along the pose's correlation
      with the bias, and that correlation spans the whole run: at a stop, where the bias
      becomes observable, each gyro reading then shifted the heading and, through it, the
      position, by up to 8 cm per reading at the end of the 110 m office route (the
      heading's lever arm over the route), back and forth, so the pose "moved" while the
      robot stood still and keyframes taken at rest got those jumps as odometry edges. An
      odometry frame must be continuous (REP 105): the gain with the pose rows zeroed is a
      Schmidt ("consider") update, and the Joseph form keeps the covariance right for it.
      Moving, the optimal gain is kept.
    - ``rate_only_process`` (default False): the pose gets no process noise of its own;
      only the rates ``v`` and ``w`` (and the bias) do, and the pose follows them. The
      white acceleration's exact discretisation gives the pose ``q dt^3 / 3`` for how the
      rate varied *within* a step; but both sensors report rates averaged over their
      packet (ticks counted over 20 ms, the gyro's samples averaged per packet), whose
      integral is the pose's change, so that term counts unmodelled motion the readings
      have already measured. On the office route it is most of an edge's yaw variance
      with the default noise model, which makes a floor visual odometry step's heading
      look 10 times less surprising than it is and keeps it from the bias.
    - ``slip_gate_sigma`` (default 0: off), ``slip_half_base_m``, ``slip_yaw_rate_noise_radps``:
      the wheel slip test (:func:`slip_variances`). A wheel that slips (over-rotates while
      the base speeds up, under-rotates while it brakes) reports a yaw rate the gyro does
      not see, and half its extra travel as speed. A moving wheel reading whose yaw rate
      disagrees with the filter's (the gyro's, bias-corrected) by more than
      ``slip_gate_sigma`` times that difference's 1-sigma (the filter's yaw-rate variance
      plus ``slip_yaw_rate_noise_radps`` squared, the wheels' own yaw-rate noise: their
      tick quantisation) is taken as slip: its speed variance grows by ``(slip_half_base_m
      * z)^2`` (``z`` the disagreement; one wheel's extra travel ``b z`` moves the base by
      half of it, on either wheel), its yaw-rate variance by ``z^2``. Used with the
      calibration's noise model, whose wheel speed noise is the ticks' alone.
    - ``wheel_increments`` (default False): a moving wheel reading is the distance and the
      heading change its ticks measured over their packet, an integrated measurement of
      the state augmented over the packet (:mod:`robotd.odometry.packet`), and the pose
      advances by them; otherwise the ticks' mean rates update ``v`` and ``w`` as the rates
      at the reading, and the pose, moved over the packet with the rates before it, trails
      the truth where the speed changes. Only a filter that keeps no journal (the wheel +
      gyro twin, or the filter without visual odometry:
      :class:`robotd.odometry.fusion.OdometryFilter`) uses it.
    - ``wheel_rounding`` (default False; with ``wheel_increments`` only): the ticks'
      quantisation as what it is rather than white noise per packet. A count is the wheel's
      travel rounded to a tick, so the distance over a packet is the true one minus the
      rounding at its end plus the rounding at its start: each rounding enters two
      neighbouring packets with opposite signs, and over many packets only the end ones
      remain. The filter carries the last count's roundings of the distance and the heading
      change as state from packet to packet (each fresh one uniform, variance ``tick^2 /
      12`` per wheel: :func:`robotd.odometry.packet.rounding_variances`), and the wheel
      noise keeps only what exceeds the two roundings' variance.
    - ``slip_event_rate_hz`` (default 0: none), ``slip_event_duration_s``: the slip events
      the slip test lets through (:func:`sub_gate_slip_variances`), with the test only:
      events a second of accelerating or turning and their RMS duration, s.
    - ``edge_floor_m`` (default 1e-4): the floor on the 1-sigma of a keyframe edge's
      position, m (:func:`robotd.odometry.increments.floor_covariance`).
    """

    accel_noise_density_mps2_per_sqrt_hz: float = _CONFIG.accel_noise_density_mps2_per_sqrt_hz
    angular_accel_noise_density_radps2_per_sqrt_hz: float = _CONFIG.angular_accel_noise_density_radps2_per_sqrt_hz
    gyro_bias_walk_radps_per_sqrt_s: float = _CONFIG.gyro_bias_walk_radps_per_sqrt_s
    wheel_v_noise_mps: float = _CONFIG.wheel_v_noise_mps
    wheel_v_noise_frac: float = _CONFIG.wheel_v_noise_frac
    wheel_w_noise_radps: float = _CONFIG.wheel_w_noise_radps
    wheel_w_noise_frac: float = _CONFIG.wheel_w_noise_frac
    wheel_w_noise_per_mps: float = _CONFIG.wheel_w_noise_per_mps
    gyro_noise_radps: float = _CONFIG.gyro_noise_radps
    initial_gyro_bias_sigma_radps: float = _CONFIG.initial_gyro_bias_sigma_radps
    stationary_noise_mps: float = 1e-3
    stationary_noise_radps: float = 1e-3
    initial_speed_sigma_mps: float = 0.5
    initial_yaw_rate_sigma_radps: float = 1.0
    initial_pose_sigma: float = 1e-5
    smooth_pose: bool = True
    rate_only_process: bool = False
    slip_gate_sigma: float = 0.0
    slip_half_base_m: float = 0.0
    slip_yaw_rate_noise_radps: float = 0.0
    wheel_slip_var_m2_per_m: float = 0.0
    wheel_increments: bool = False
    wheel_rounding: bool = False
    slip_event_rate_hz: float = _CONFIG.slip_event_rate_hz
    slip_event_duration_s: float = _CONFIG.slip_event_duration_s
    edge_floor_m: float = _CONFIG.edge_floor_m

    @classmethod
    def from_config(cls, section: OdometryConfig, **others: Any) -> EkfParams:
        """The params of an ``[odometry]`` table; ``others``: the fields it does not hold."""
        return cls(**{f.name: getattr(section, f.name) for f in dataclasses.fields(section)
                      if f.name not in ("noise_model", "slip_gate_sigma")}, **others)

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

    @classmethod
    def _own(cls, stamp_ns: int, mean: np.ndarray, cov: np.ndarray) -> EkfState:
        """A state of arrays the caller made for it and hands over (float64, of the
        state's shapes, referenced nowhere else): made read-only, not copied. The filter's
        own steps build their states this way; the constructor copies."""
        mean.setflags(write=False)
        cov.setflags(write=False)
        state = object.__new__(cls)
        object.__setattr__(state, "stamp_ns", stamp_ns)
        object.__setattr__(state, "mean", mean)
        object.__setattr__(state, "cov", cov)
        return state

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
                  pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
                  bias: tuple[float, float] | None = None) -> EkfState:
    """The belief before any measurement: at ``pose``, speed and bias unknown (priors).
    ``bias``: the gyro bias's prior mean and 1-sigma, rad/s, in place of 0 and
    ``initial_gyro_bias_sigma_radps``."""
    b0, b_sigma = (0.0, params.initial_gyro_bias_sigma_radps) if bias is None else bias
    mean = np.array([pose[0], pose[1], wrap_angle(float(pose[2])), 0.0, 0.0, float(b0)])
    sig = np.array([params.initial_pose_sigma] * 3 + [
        params.initial_speed_sigma_mps, params.initial_yaw_rate_sigma_radps, float(b_sigma)])
    return EkfState(stamp_ns, mean, np.diag(sig ** 2))


def _sinc_half_and_derivative(dth: float) -> tuple[float, float]:
    """``f = sin(dth/2)/(dth/2)`` and ``df/d(dth)``, accurate near zero."""
    u = 0.5 * dth
    if abs(u) < 1e-4:
        return 1.0 - u * u / 6.0, -u / 6.0
    s, c = math.sin(u), math.cos(u)
    return s / u, 0.5 * (u * c - s) / (u * u)


def _arc(mean_in: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The state moved along the arc of its ``v``, ``w`` over ``dt`` seconds: the new mean,
    the ``(6, 6)`` Jacobian of the move, and the cosine and sine of the arc's mid heading
    (the direction of travel, which the process noise of :func:`predict` follows)."""
    x, y, yaw, v, w, bias = mean_in.tolist()  # Python floats: the same arithmetic, faster
    ds, dth = v * dt, w * dt
    f, df = _sinc_half_and_derivative(dth)
    phi = yaw + 0.5 * dth
    c, s = math.cos(phi), math.sin(phi)
    mean = np.array([x + ds * f * c, y + ds * f * s, wrap_angle(yaw + dth), v, w, bias])
    jac = _EYE.copy()
    jac[IX, IYAW] = -ds * f * s
    jac[IY, IYAW] = ds * f * c
    jac[IX, IV] = dt * f * c
    jac[IY, IV] = dt * f * s
    jac[IX, IW] = ds * dt * (df * c - 0.5 * f * s)
    jac[IY, IW] = ds * dt * (df * s + 0.5 * f * c)
    jac[IYAW, IW] = dt
    return mean, jac, c, s


def predict(state: EkfState, t_ns: int, params: EkfParams = EkfParams()) -> EkfState:
    """Propagate ``state`` to ``t_ns`` (>= its stamp) with the constant-rate model.

    ``dt = 0`` returns ``state`` unchanged; a negative ``dt`` is a ``ValueError``.
    """
    return predict_with_jacobian(state, t_ns, params)[0]


def predict_with_jacobian(state: EkfState, t_ns: int,
                          params: EkfParams = EkfParams()) -> tuple[EkfState, np.ndarray]:
    """:func:`predict` and its ``(6, 6)`` state Jacobian (a pose clone's cross-covariance
    follows it, :mod:`robotd.odometry.relative`).

    ``F P F^T + Q`` is written out on Python floats: ``F`` is the identity but for seven
    entries (the pose's rows on yaw, ``v`` and ``w``, and yaw's on ``w``), and NumPy's cost
    per call on a ``(6, 6)`` matrix was most of the odometry stage's time."""
    dt_ns = int(t_ns) - state.stamp_ns
    if dt_ns < 0:
        raise ValueError(f"cannot predict backwards ({t_ns} < {state.stamp_ns})")
    if dt_ns == 0:
        return state, _EYE.copy()
    dt = dt_ns * 1e-9
    x, y, yaw, v, w, bias = state.mean.tolist()
    ds, dth = v * dt, w * dt
    f, df = _sinc_half_and_derivative(dth)
    phi = yaw + 0.5 * dth
    c, s = math.cos(phi), math.sin(phi)
    mean = np.array([x + ds * f * c, y + ds * f * s, wrap_angle(yaw + dth), v, w, bias])
    # F's entries off the diagonal (_arc's Jacobian)
    f02, f12 = -ds * f * s, ds * f * c
    f03, f13 = dt * f * c, dt * f * s
    f04, f14 = ds * dt * (df * c - 0.5 * f * s), ds * dt * (df * s + 0.5 * f * c)
    jac = np.fromiter((1.0, 0.0, f02, f03, f04, 0.0, 0.0, 1.0, f12, f13, f14, 0.0,
                       0.0, 0.0, 1.0, 0.0, dt, 0.0) + _EYE_LOWER, float, 36).reshape(6, 6)

    qa = params.angular_accel_noise_density_radps2_per_sqrt_hz ** 2
    ql = params.accel_noise_density_mps2_per_sqrt_hz ** 2
    d2, d3 = dt * dt / 2.0, dt ** 3 / 3.0
    if params.rate_only_process:  # the pose follows the rates: no noise of its own
        d2 = d3 = 0.0
    # B = F P: rows 3-5 are P's
    p0, p1, p2, p3, p4, p5 = state.cov.tolist()
    b0 = [a + f02 * b + f03 * e + f04 * g for a, b, e, g in zip(p0, p2, p3, p4)]
    b1 = [a + f12 * b + f13 * e + f14 * g for a, b, e, g in zip(p1, p2, p3, p4)]
    b2 = [a + dt * g for a, g in zip(p2, p4)]
    # C = B F^T + Q, its upper triangle (C is symmetric): columns 0-2 as B's rows, 3-5 B's
    c00 = b0[0] + f02 * b0[2] + f03 * b0[3] + f04 * b0[4] + ql * d3 * c * c
    c01 = b0[1] + f12 * b0[2] + f13 * b0[3] + f14 * b0[4] + ql * d3 * c * s
    c02 = b0[2] + dt * b0[4]
    c11 = b1[1] + f12 * b1[2] + f13 * b1[3] + f14 * b1[4] + ql * d3 * s * s
    c12 = b1[2] + dt * b1[4]
    c22 = b2[2] + dt * b2[4] + qa * d3
    c03, c04, c05 = b0[3] + ql * d2 * c, b0[4], b0[5]
    c13, c14, c15 = b1[3] + ql * d2 * s, b1[4], b1[5]
    c23, c24, c25 = b2[3], b2[4] + qa * d2, b2[5]
    c33, c34, c35 = p3[3] + ql * dt, p3[4], p3[5]
    c44, c45 = p4[4] + qa * dt, p4[5]
    c55 = p5[5] + params.gyro_bias_walk_radps_per_sqrt_s ** 2 * dt
    cov = np.fromiter((c00, c01, c02, c03, c04, c05, c01, c11, c12, c13, c14, c15,
                       c02, c12, c22, c23, c24, c25, c03, c13, c23, c33, c34, c35,
                       c04, c14, c24, c34, c44, c45, c05, c15, c25, c35, c45, c55), float, 36).reshape(6, 6)
    return EkfState._own(int(t_ns), mean, cov), jac


def rate_gain(cov: np.ndarray, h: np.ndarray, r: np.ndarray, smooth_pose: bool) -> np.ndarray:
    """The gain of a rate measurement: ``P H^T S^-1``, with the pose rows zeroed when
    ``smooth_pose`` (:class:`EkfParams`)."""
    if h is H_WHEELS:  # P H^T and H P H^T are columns and entries of P (the same numbers)
        ph = cov[:, _WHEEL_COLUMNS]
        s = ph[_WHEEL_COLUMNS] + r
    elif h is H_GYRO:
        ph = cov[:, IW:IW + 1] + cov[:, IB:IB + 1]
        s = ph[IW:IW + 1] + ph[IB:IB + 1] + r
    else:
        ph = cov @ h.T
        s = h @ ph + r
    if s.shape == (1, 1):  # one reading (the gyro): S^-1 is a division
        gain = ph / s[0, 0]
    elif s.shape == (2, 2):  # the wheels' (v, w): the 2x2 inverse in closed form
        a, b, c, d = s[0, 0], s[0, 1], s[1, 0], s[1, 1]
        det = a * d - b * c
        gain = ph @ (np.array([[d, -b], [-c, a]]) / det)
    else:
        gain = np.linalg.solve(s, ph.T).T  # = P H^T S^-1 (S is symmetric)
    if smooth_pose:
        gain[:3] = 0.0
    return gain


class RateUpdate(NamedTuple):
    """A rate measurement's update with what the fused filter carries along: the new
    ``state``, the ``gain`` ``(6, m)``, the measurement noise ``noise`` ``(m, m)`` and
    ``error_map = I - K H`` ``(6, 6)``, the linear map of the state's error through it (a
    pose clone's cross-covariance and the keyframe edges follow it)."""

    state: EkfState
    gain: np.ndarray
    noise: np.ndarray
    error_map: np.ndarray


def _update(state: EkfState, innovation: np.ndarray, h: np.ndarray, r: np.ndarray,
            smooth_pose: bool = False) -> RateUpdate:
    """Linear(ised) measurement update in Joseph form (valid for any gain, so also for the
    pose-frozen one of ``smooth_pose``). The wheels' and the gyro's (:data:`H_WHEELS`,
    :data:`H_GYRO`) are written out on Python floats (:func:`_joseph_columns`)."""
    if h is H_WHEELS or h is H_GYRO:
        return _joseph_columns(state, innovation, h, r, smooth_pose)
    p = state.cov
    gain = rate_gain(p, h, r, smooth_pose)
    mean = state.mean + gain @ innovation
    mean[IYAW] = wrap_angle(mean[IYAW])
    a = _EYE - gain @ h
    cov = a @ p @ a.T
    cov += gain @ r @ gain.T
    cov += cov.T
    cov *= 0.5
    return RateUpdate(EkfState._own(state.stamp_ns, mean, cov), gain, r, a)


def _joseph_columns(state: EkfState, innovation: np.ndarray, h: np.ndarray, r: np.ndarray,
                    smooth_pose: bool) -> RateUpdate:
    """:func:`_update` of the wheels' ``(v, w)`` (``h`` :data:`H_WHEELS`) or the gyro's ``w +
    bias`` (:data:`H_GYRO`), ``r`` diagonal, in few NumPy calls: ``P H^T`` and ``H P`` are
    columns and rows of ``P`` (summed for the gyro), the gain is :func:`rate_gain`'s (the
    2 x 2 inverse in closed form), and the Joseph form ``A P A^T + K R K^T`` with ``A = I - K
    H`` is ``B = P - K (H P)`` then ``B - (B H^T - K R) K^T``, the same products with ``H``'s
    zeros left out. ``A`` is the identity with ``K`` taken from the measured columns."""
    p = state.cov
    amap = _EYE.copy()
    if h is H_WHEELS:
        ph = p[:, IV:IW + 1]
        (a, b), (c, d) = (ph[IV:IW + 1] + r).tolist()
        det = a * d - b * c
        gain = ph @ np.array([[d / det, -b / det], [-c / det, a / det]])
        if smooth_pose:
            gain[:3] = 0.0
        bm = p - gain @ p[IV:IW + 1]
        bh = bm[:, IV:IW + 1]
        amap[:, IV:IW + 1] -= gain
    else:
        ph = p[:, IW:IW + 1] + p[:, IB:IB + 1]
        gain = ph / (float(ph[IW, 0] + ph[IB, 0]) + float(r[0, 0]))
        if smooth_pose:
            gain[:3] = 0.0
        bm = p - gain @ ph.T
        bh = bm[:, IW:IW + 1] + bm[:, IB:IB + 1]
        amap[:, IW:IB + 1] -= gain
    mean = state.mean + gain @ innovation
    mean[IYAW] = wrap_angle(float(mean[IYAW]))
    cov = bm - (bh - gain * r.diagonal()) @ gain.T
    cov += cov.T
    cov *= 0.5
    return RateUpdate(EkfState._own(state.stamp_ns, mean, cov), gain, r, amap)


def slip_speed_variance(v_mps: Any, w_radps: Any, slip_var_m2_per_m: float, half_base_m: float,
                        dt_s: float) -> Any:
    """The variance (m^2/s^2) the wheels' continuous slip adds to the speed over a reading of
    ``dt_s`` seconds (``wheel_slip_var_m2_per_m`` in :class:`EkfParams`): the two wheels
    travel ``|v -+ w h| dt`` (``h`` = ``half_base_m``) and slip independently, so their mean
    gets ``q (|v - w h| + |v + w h|) / (4 dt)``. Floats or arrays alike."""
    turn = w_radps * half_base_m
    return slip_var_m2_per_m * (abs(v_mps - turn) + abs(v_mps + turn)) / (4.0 * dt_s)


def wheel_noise(v_mps: float, w_radps: float, params: EkfParams,
                stationary: bool = False, speed_var_m2ps2: float | None = None,
                yaw_rate_var_rad2ps2: float | None = None,
                dt_s: float | None = None) -> tuple[float, float]:
    """1-sigma noise ``(sigma_v_mps, sigma_w_radps)`` of one wheel speed measurement.

    ``dt_s``: the reading's interval (s), for the wheels' continuous slip
    (``wheel_slip_var_m2_per_m`` in :class:`EkfParams`, in quadrature with the speed's
    noise); without it, or with a stated speed variance, no slip term.

    ``speed_var_m2ps2`` / ``yaw_rate_var_rad2ps2``: variances the source stated with the
    measurement (a ROS 2 odometry's twist covariance, checked valid by its driver); each
    replaces the noise model's value for its component. At standstill the zero-velocity
    noise is used whatever the source said: it is the filter's own knowledge (no tick
    moved), not the source's.
    """
    if stationary:
        return params.stationary_noise_mps, params.stationary_noise_radps
    sv = (params.wheel_v_noise_mps + params.wheel_v_noise_frac * abs(v_mps)
          if speed_var_m2ps2 is None else math.sqrt(speed_var_m2ps2))
    q = params.wheel_slip_var_m2_per_m
    if q > 0.0 and dt_s is not None and dt_s > 0.0 and speed_var_m2ps2 is None:
        sv = math.sqrt(sv * sv + slip_speed_variance(v_mps, w_radps, q, params.slip_half_base_m, dt_s))
    sw = (params.wheel_w_noise_radps + params.wheel_w_noise_frac * abs(w_radps)
          + params.wheel_w_noise_per_mps * abs(v_mps)
          if yaw_rate_var_rad2ps2 is None else math.sqrt(yaw_rate_var_rad2ps2))
    return sv, sw


def gyro_noise_var(params: EkfParams, yaw_rate_var_rad2ps2: float | None = None) -> np.ndarray:
    """``(1, 1)`` noise covariance of one gyro reading, (rad/s)^2: the variance the source
    stated (a ROS 2 IMU's, checked valid by its driver), else ``gyro_noise_radps**2``."""
    var = params.gyro_noise_radps ** 2 if yaw_rate_var_rad2ps2 is None else yaw_rate_var_rad2ps2
    return np.array([[var]])


def update_wheels(state: EkfState, v_mps: float, w_radps: float,
                  params: EkfParams = EkfParams(), stationary: bool = False,
                  speed_var_m2ps2: float | None = None,
                  yaw_rate_var_rad2ps2: float | None = None) -> EkfState:
    """Measurement ``(v, w)`` from the encoders: ``h(x) = (x[v], x[w])``.

    ``stationary=True`` (no tick moved over the interval) uses the much smaller
    zero-velocity noise: the base is not moving, which is what makes the bias observable.
    The variances, when given, are the source's (:func:`wheel_noise`).
    """
    return update_wheels_with_gain(state, v_mps, w_radps, params, stationary, speed_var_m2ps2,
                                   yaw_rate_var_rad2ps2).state


def update_wheels_with_gain(state: EkfState, v_mps: float, w_radps: float,
                            params: EkfParams = EkfParams(), stationary: bool = False,
                            speed_var_m2ps2: float | None = None,
                            yaw_rate_var_rad2ps2: float | None = None,
                            dt_s: float | None = None) -> RateUpdate:
    """:func:`update_wheels` with its gain, noise and error map (:class:`RateUpdate`);
    ``dt_s``: the reading's interval (:func:`wheel_noise`)."""
    sv, sw = wheel_noise(v_mps, w_radps, params, stationary, speed_var_m2ps2, yaw_rate_var_rad2ps2, dt_s)
    m = state.mean
    innovation = np.array([v_mps - m[IV], w_radps - m[IW]])
    var_v, var_w = sv * sv, sw * sw
    if not stationary and params.slip_gate_sigma > 0.0 and speed_var_m2ps2 is None:
        changes = speed_changing(float(innovation[0]), float(state.cov[IV, IV]) + var_v, params)
        add_v, add_w = slip_variances(float(innovation[1]), float(state.cov[IW, IW]), params, dt_s,
                                      turning(w_radps, params), changes)
        var_v += add_v
        var_w += add_w
    return _update(state, innovation, H_WHEELS, np.array([[var_v, 0.0], [0.0, var_w]]),
                   stationary and params.smooth_pose)


def speed_changing(speed_innovation_mps: float, speed_innovation_var_m2ps2: float, params: EkfParams) -> bool:
    """Whether a moving wheel reading shows the base accelerating or braking: its speed
    disagrees with the filter's by more than ``slip_gate_sigma`` times that disagreement's
    1-sigma (``speed_innovation_var_m2ps2`` its variance: the speed changed beyond its
    noise)."""
    g = params.slip_gate_sigma
    return speed_innovation_mps * speed_innovation_mps > g * g * speed_innovation_var_m2ps2


def turning(w_radps: float, params: EkfParams) -> bool:
    """Whether a moving wheel reading's yaw rate ``w_radps`` is above ``slip_gate_sigma``
    times the wheels' own yaw-rate noise (``slip_yaw_rate_noise_radps``): a turn the ticks
    resolve."""
    return abs(w_radps) > params.slip_gate_sigma * params.slip_yaw_rate_noise_radps


def slip_variances(yaw_rate_innovation_radps: float, yaw_rate_var_rad2ps2: float,
                   params: EkfParams, dt_s: float | None = None,
                   turns: bool = False, speed_changes: bool = False) -> tuple[float, float]:
    """The variances ``(m^2/s^2, rad^2/s^2)`` a slipping wheel adds to a moving wheel
    reading's speed and yaw rate; when the reading passes the slip test
    (``slip_gate_sigma`` in :class:`EkfParams`) while the base turns or its speed changes
    (``turns``, :func:`turning`; ``speed_changes``, :func:`speed_changing`: where a wheel's
    grip is asked for more than rolling), those of the slip events the test lets through
    (:func:`sub_gate_slip_variances`, over the reading's interval ``dt_s``); else ``(0, 0)``.

    ``yaw_rate_innovation_radps``: the wheels' yaw rate minus the filter's (after the gyro's
    readings up to it); ``yaw_rate_var_rad2ps2``: the filter's yaw-rate variance. One wheel
    slipping by ``d`` metres over the reading's interval ``dt`` adds ``+-d / b / dt`` to the
    wheels' yaw rate and ``d / 2 / dt`` to their speed (``b`` the wheel base): the speed's
    error is ``+-(b / 2) z``, its sign the slipping wheel's, which the reading cannot tell
    (so the variance, not the mean, takes it).

    With the slip events modelled (``slip_event_rate_hz`` above 0) a slip the test sees is
    part of an event of ``slip_event_duration_s`` (RMS, ``T``): its readings' slips have
    one sign and add up, the distance off by ``(b / 2) z T`` over the event, where
    independent readings' variances would give ``T / dt`` times less. Spread over the
    event's ``T / dt`` readings as white noise (as :func:`sub_gate_slip_variances`), each
    reading's variances are ``T / dt`` times the one reading's (at least once). Not while
    the speed changes: there the readings are what tells the filter the speed, and
    readings widened that much leave it to the white acceleration, which does not expect
    a ramp (a start's or a stop's distance then lags)."""
    z2 = yaw_rate_innovation_radps * yaw_rate_innovation_radps
    s = yaw_rate_var_rad2ps2 + params.slip_yaw_rate_noise_radps ** 2
    if params.slip_gate_sigma <= 0.0:
        return 0.0, 0.0
    if z2 <= params.slip_gate_sigma ** 2 * s:
        return sub_gate_slip_variances(s, params, dt_s) if (turns or speed_changes) else (0.0, 0.0)
    if params.slip_event_rate_hz > 0.0 and dt_s is not None and dt_s > 0.0 and not speed_changes:
        z2 *= max(1.0, params.slip_event_duration_s / dt_s)
    return params.slip_half_base_m ** 2 * z2, z2


def sub_gate_slip_variances(test_var_rad2ps2: float, params: EkfParams,
                            dt_s: float | None) -> tuple[float, float]:
    """The variances ``(m^2/s^2, rad^2/s^2)`` that the slip events the slip test lets through
    add to a moving wheel reading's speed and yaw rate over its interval ``dt_s`` (s);
    ``(0, 0)`` without the test, without events (``slip_event_rate_hz`` 0) or ``dt_s``.

    A slip event is one wheel over- or under-rotating for a while (``slip_event_duration_s``,
    RMS), at ``slip_event_rate_hz`` events a second while the base accelerates or turns
    (where a wheel's grip is asked for more than rolling). While it lasts the wheels'
    yaw rate is off by ``z`` and their speed by ``(b / 2) z`` (one wheel's extra travel,
    ``b`` the wheel base, :func:`slip_variances`). A reading that passes the test has
    ``|z|`` at most ``g sqrt(S)`` (``g`` = ``slip_gate_sigma``, ``S`` = ``test_var_rad2ps2``
    the test's variance); nothing favours one value below that bound over another, so
    ``z`` is taken uniform below it: variance ``g^2 S / 3``. An event is one slip over its
    whole duration ``T``, the distance off by ``(b / 2) z T`` and the heading by ``z T``;
    events arriving at rate ``r`` make a shot noise whose integral over a span much longer
    than ``T`` has the variance ``r E[z^2] E[T^2]`` per second, and over a shorter span
    less (the events' share then grows as the span squared, not linearly). As white
    noise of that density on each reading (the filter's wheel noise is white) the variance
    over a span is right from a few events' durations on and too large below. Per reading
    of ``dt`` seconds the yaw rate's variance is ``r E[z^2] T^2 / dt``, the speed's
    ``(b / 2)^2`` times it."""
    if (params.slip_gate_sigma <= 0.0 or params.slip_event_rate_hz <= 0.0 or dt_s is None
            or dt_s <= 0.0):
        return 0.0, 0.0
    z2 = params.slip_gate_sigma ** 2 * test_var_rad2ps2 / 3.0
    add_w = params.slip_event_rate_hz * z2 * params.slip_event_duration_s ** 2 / dt_s
    return params.slip_half_base_m ** 2 * add_w, add_w


def update_gyro(state: EkfState, w_radps: float, params: EkfParams = EkfParams(),
                at_rest: bool = False, yaw_rate_var_rad2ps2: float | None = None) -> EkfState:
    """Measurement of the gyro's yaw rate: ``h(x) = x[w] + x[bias]`` (``at_rest``: paired
    with a zero-velocity update, see ``smooth_pose`` in :class:`EkfParams`; the variance,
    when given, is the source's: :func:`gyro_noise_var`)."""
    return update_gyro_with_gain(state, w_radps, params, at_rest, yaw_rate_var_rad2ps2).state


def update_gyro_with_gain(state: EkfState, w_radps: float, params: EkfParams = EkfParams(),
                          at_rest: bool = False, yaw_rate_var_rad2ps2: float | None = None) -> RateUpdate:
    """:func:`update_gyro` with its gain, noise and error map (:class:`RateUpdate`)."""
    m = state.mean
    innovation = np.array([w_radps - m[IW] - m[IB]])
    r = gyro_noise_var(params, yaw_rate_var_rad2ps2)
    return _update(state, innovation, H_GYRO, r, at_rest and params.smooth_pose)


def predict_rates(state: EkfState, t_ns: int, params: EkfParams = EkfParams()) -> EkfState:
    """The rates' half of a prediction to ``t_ns`` (>= its stamp): ``v``, ``w`` and the bias
    get their process noise (``ql dt``, ``qa dt``, ``gyro_bias_walk^2 dt``), the pose stays
    where it is; :func:`advance_pose` moves it. The state Jacobian of this half is the
    identity. Only for a filter whose pose has no process noise of its own
    (``rate_only_process``).

    Why: the fused filter (:class:`robotd.odometry.fusion.OdometryFilter`, ``pose_after_rates``)
    moves its pose over the interval to a reading by the trapezoid rule, half with the rates
    before the reading and half with the rates the reading leaves. :func:`predict` moves it
    with the rates before the reading alone, and the Kobuki's readings are means over their
    packet (the raw gyro's stamped in its middle, the ticks at its end): the heading then
    lagged the truth by about 5 ms of yaw rate while the base turned faster (on the office
    route, 70 % of the heading error of a keyframe interval)."""
    dt_ns = int(t_ns) - state.stamp_ns
    if dt_ns < 0:
        raise ValueError(f"cannot predict backwards ({t_ns} < {state.stamp_ns})")
    if dt_ns == 0:
        return state
    dt = dt_ns * 1e-9
    cov = state.cov.copy()
    cov[IV, IV] += params.accel_noise_density_mps2_per_sqrt_hz ** 2 * dt
    cov[IW, IW] += params.angular_accel_noise_density_radps2_per_sqrt_hz ** 2 * dt
    cov[IB, IB] += params.gyro_bias_walk_radps_per_sqrt_s ** 2 * dt
    return EkfState._own(int(t_ns), state.mean.copy(), cov)


def advance_pose(state: EkfState, dt_s: float) -> tuple[EkfState, np.ndarray]:
    """The pose moved along the arc of the state's ``v``, ``w`` over ``dt_s`` seconds (no
    noise; the stamp is left as it is, the caller knows which interval it moves over:
    :func:`predict_rates`), and the ``(6, 6)`` state Jacobian of that move (the same arc and
    Jacobian as :func:`predict`)."""
    if dt_s <= 0.0:
        return state, _EYE.copy()
    mean, jac, _, _ = _arc(state.mean, dt_s)
    cov = jac @ state.cov @ jac.T
    cov += cov.T
    cov *= 0.5
    return EkfState._own(state.stamp_ns, mean, cov), jac


# --------------------------------------------------------------------------------------
# The filter over a message stream (what the daemon runs).
# --------------------------------------------------------------------------------------
