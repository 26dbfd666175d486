"""The odometry model of one robot, fitted to a calibration drive.

A calibration drive (the loop curve's drive: floor loops and floor visual odometry) gives a
reference trajectory at its keyframes, the loop-corrected pose graph's, far better than
the wheels or the gyro alone. Against it this module fits the classic systematic errors of
a differential drive (UMBmark, Borenstein and Feng 1996; here jointly, by least squares
over every keyframe interval) and the random ones:

- the left and right wheels' rolling radii ``r_L``, ``r_R`` (m) and the effective wheel
  base ``B`` (m). Over the interval ``k`` between keyframes ``k-1`` and ``k`` the wheels
  turned ``dphi_L``, ``dphi_R`` (rad); the model says the heading changed by
  ``(r_R dphi_R - r_L dphi_L) / B`` and the base moved by the sum of the per-sample arcs
  ``(r_L dphi_L + r_R dphi_R) / 2`` along the heading, expressed in keyframe ``k-1``'s
  frame. Straight driving fixes ``r_R / B - r_L / B`` (a curving straight), turns fix
  ``r_R / B + r_L / B`` and distance fixes ``r_L + r_R``: three numbers, three unknowns.
- the gyro's scale ``s`` (dimensionless, measured = ``s`` x true rate + bias) and its
  turn-on bias ``b0`` (rad/s) with a linear drift ``b1`` (rad/s^2) standing in for the
  bias walk over the drive: the gyro's integral over an interval is
  ``s dyaw_ref + b0 dt + b1 d(t^2/2)``, linear in the three. Turns both ways separate the
  scale from the bias (a drive turning one way only confounds them with time).
- the noise densities: the gyro's white rate noise (rad/s per sqrt(Hz)), from the spread
  of its readings while the base stands still (no tick moved); the wheels' slip noise
  (m per sqrt(m) of travel), from the distance residuals after the fit, whose variance
  grows with the interval's travel (``var = q |ds| + c``, ``c`` the reference's own).
- the filter's white accelerations (its process noise: m/s^2 and rad/s^2 per sqrt(Hz),
  :class:`robotd.odometry.ekf.EkfParams`), by maximum likelihood on the innovations of the
  wheels' and the gyro's readings through the filter's rate states with the calibrated
  geometry and the fitted sensor noise (:func:`fit_process_noise`; Mehra 1970's
  innovation likelihood). No measurement involves the pose, so the rate states ``v`` and
  ``(w, bias)`` form two small linear filters whose likelihood depends on one density
  each; their uncertainty is the likelihood's curvature.
- the wheel slip events' rate (a second of accelerating or turning, as the filter's slip
  test calls it) and RMS duration, from the heading windows the wheel fit leaves out as
  slip, the events its gate misses modelled from the drive's own travel per window
  (:mod:`robotd.odometry.slip_events`); refused (the fit's other values kept) when the
  windows see fewer than ``min_slip_events``.

Uncertainties are the least-squares covariances, each scaled by the fit's reduced chi2
when that exceeds one (the weights then understated the residuals). A drive that cannot
make these observable is refused (:func:`missing_observability`) before any fit.

No I/O here: the caller reads the recording and the reference trajectory
(:mod:`calibration.odometry`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from robotd.base.errors import CalibrationError
from robotd.base.geometry import rot2
from robotd.odometry.ekf import EkfParams, slip_speed_variance
from robotd.odometry.packet import rounding_variances
from robotd.odometry.slip_events import SlipDrive, SlipEventFit, estimate_slip_events, find_slip_events

__all__ = [
    "CalibrationDrive",
    "OdometryFit",
    "OdometryFitParams",
    "ProcessNoiseFit",
    "fit_odometry",
    "fit_process_noise",
    "missing_observability",
    "sensor_noise_params",
]

#: Readings a second of the Kobuki's wheel packets and of its raw gyro (one mean rate per
#: packet): the rate at which the fit's densities become per-reading noises.
READINGS_HZ = 50.0
#: The Kobuki's encoder ticks per wheel turn (``[robot] ticks_per_rev``'s default).
TICKS_PER_REV = 2578.33


@dataclass(frozen=True, slots=True, eq=False)
class CalibrationDrive:
    """What the fit reads from a drive (SI units, stamps in ns, non-decreasing).

    wheel_stamp_ns ``(N,) int64``; wheel_angle_rad ``(N, 2)`` cumulative unwrapped angle of
    the left and right wheel (ticks x 2 pi / ticks per turn); gyro_stamp_ns ``(M,) int64``;
    gyro_radps ``(M,)`` yaw-rate readings as the gyro gave them; ref_stamp_ns ``(K,) int64``
    and ref_pose ``(K, 3)`` the reference trajectory (x_m, y_m, yaw_rad) at its keyframes.
    """

    wheel_stamp_ns: np.ndarray
    wheel_angle_rad: np.ndarray
    gyro_stamp_ns: np.ndarray
    gyro_radps: np.ndarray
    ref_stamp_ns: np.ndarray
    ref_pose: np.ndarray


@dataclass(frozen=True, slots=True)
class OdometryFitParams:
    """Refusal thresholds and fit settings.

    min_turn_deg: the drive must turn at least this much in total to each side (the gyro
        scale against its bias, the wheel base against the radii), default 180.
    min_distance_m: and travel at least this far (the radii), default 10.
    min_still_s: and stand still (no tick moving) for at least this long in all (the gyro's
        noise and turn-on bias), default 1.
    min_keyframes: reference keyframes needed, default 30.
    still_margin_s: readings this close to the start or end of a still period are left out
        of the gyro's noise (the base may still creep), default 0.2.
    slip_gate_sigma: heading windows whose wheel-against-gyro residual exceeds this many
        (robust) sigma are slip events, left out with their neighbours and the keyframe
        intervals they fall in, default 4.
    window_s: length of the heading windows, default 0.2 s.
    event_test_sigma: the wheel slip test's gate (``[odometry] slip_gate_sigma``) whose
        accelerating or turning readings the slip events' rate is counted a second of,
        default 3 (:mod:`robotd.odometry.slip_events`).
    min_slip_events: slip events the heading windows must see for their rate and duration
        to be fitted, default 10 (fewer: :attr:`OdometryFit.slip_events` says so).
    """

    min_turn_deg: float = 180.0
    min_distance_m: float = 10.0
    min_still_s: float = 1.0
    min_keyframes: int = 30
    still_margin_s: float = 0.2
    slip_gate_sigma: float = 4.0
    window_s: float = 0.2
    event_test_sigma: float = 3.0
    min_slip_events: int = 10


@dataclass(frozen=True, slots=True, eq=False)
class OdometryFit:
    """The fitted model, each value with its 1-sigma uncertainty (``*_sigma``).

    wheel_radius_left_m, wheel_radius_right_m, wheel_base_m: m. gyro_scale: measured rate
    over true rate. gyro_bias_radps: the bias at the drive's first reading (turn-on), rad/s;
    gyro_bias_drift_radps2 its fitted drift. gyro_noise_radps_sqrt_hz: white rate noise
    density; wheel_noise_m_sqrt_m: slip noise per sqrt(m) of travel.
    residuals_before / residuals_after ``(K-1, 4)``: per keyframe interval, the residual of
    the wheels' dx, dy (m, in the interval's start frame), the wheels' heading change and
    the gyro's heading change (rad), with the nominal model (``nominal``: radius, base;
    gyro scale 1, bias 0 beyond the one the still periods show) and with the fitted one.
    interval_end_s ``(K-1,)``: each interval's end, s from the first keyframe.
    used ``(K-1,)`` bool: intervals kept by the slip gate; slip_windows: heading windows
    left out as slip (with their neighbours), of heading_windows. turn_left_deg, turn_right_deg,
    distance_m, still_s: what the drive offered. slip_events: the slip events' rate and
    duration (:mod:`robotd.odometry.slip_events`; its ``refused`` says why not).
    """

    wheel_radius_left_m: float
    wheel_radius_right_m: float
    wheel_base_m: float
    wheel_radius_left_sigma: float
    wheel_radius_right_sigma: float
    wheel_base_sigma: float
    gyro_scale: float
    gyro_scale_sigma: float
    gyro_bias_radps: float
    gyro_bias_sigma: float
    gyro_bias_drift_radps2: float
    gyro_noise_radps_sqrt_hz: float
    wheel_noise_m_sqrt_m: float
    residuals_before: np.ndarray
    residuals_after: np.ndarray
    interval_end_s: np.ndarray
    used: np.ndarray
    slip_windows: int
    heading_windows: int
    turn_left_deg: float
    turn_right_deg: float
    distance_m: float
    still_s: float
    process: ProcessNoiseFit | None = None
    slip_events: SlipEventFit | None = None


@dataclass(frozen=True, slots=True)
class ProcessNoiseFit:
    """The filter's white accelerations fitted to a drive, with 1-sigma uncertainties.

    accel_mps2_sqrt_hz: white linear acceleration density (m/s^2 per sqrt(Hz));
    angular_accel_radps2_sqrt_hz: white angular acceleration density (rad/s^2 per
    sqrt(Hz)); ``*_sigma``: their 1-sigma from the log-likelihood's curvature in the log
    of the density. wheel_v_noise_mps, wheel_v_noise_frac, gyro_noise_radps: the
    measurement noise the likelihood was computed with (:func:`sensor_noise_params`).
    """

    accel_mps2_sqrt_hz: float
    accel_sigma: float
    angular_accel_radps2_sqrt_hz: float
    angular_accel_sigma: float
    wheel_v_noise_mps: float
    wheel_v_noise_frac: float
    gyro_noise_radps: float


def sensor_noise_params(base: EkfParams, gyro_noise_radps_sqrt_hz: float, wheel_noise_m_sqrt_m: float,
                        tick_m: float, accel_mps2_sqrt_hz: float | None = None,
                        angular_accel_radps2_sqrt_hz: float | None = None,
                        readings_hz: float = READINGS_HZ, wheel_base_m: float = 0.0,
                        slip_gate_sigma: float = 0.0) -> EkfParams:
    """``base`` with the sensors' own noise: the gyro's white noise per reading (``density
    * sqrt(fs / 2)``, the convention :func:`fit_odometry` measures the density in), the
    wheel speed's tick quantisation (``tick_m``: m of travel per tick; the speed is the
    mean of the two wheels' counts, each the difference of two roundings over one packet,
    variance ``tick^2 / 6`` per wheel: ``tick / dt / sqrt(12)``), each wheel's continuous
    slip (``wheel_noise_m_sqrt_m`` squared, per metre of that wheel's own travel, as
    :func:`fit_odometry` measures it from the wheels' heading against the gyro:
    ``wheel_slip_var_m2_per_m`` in :class:`~robotd.odometry.ekf.EkfParams`, in quadrature
    with the ticks', in place of ``base``'s slip fraction), and the white accelerations
    when given (else ``base``'s). The wheel yaw-rate noise and the bias walk stay
    ``base``'s. With ``wheel_base_m`` (m) above 0 the slip's wheel travel takes the turn
    into account (half the wheel base); with ``slip_gate_sigma`` above 0 as well, the wheel
    slip test (``slip_gate_sigma`` in :class:`~robotd.odometry.ekf.EkfParams`): the
    slipping wheel's lever is half the wheel base, and the wheels' own yaw-rate noise is
    their tick quantisation (each wheel's ``tick / dt / sqrt(6)``, the yaw rate ``sqrt(2)``
    times it over the wheel base)."""
    dt = 1.0 / readings_hz
    wheel_tick_mps = tick_m / dt / math.sqrt(6.0)  # one wheel's count difference
    out = dataclasses.replace(
        base, gyro_noise_radps=gyro_noise_radps_sqrt_hz * math.sqrt(readings_hz / 2.0),
        wheel_v_noise_mps=wheel_tick_mps / math.sqrt(2.0), wheel_v_noise_frac=0.0,
        wheel_slip_var_m2_per_m=wheel_noise_m_sqrt_m ** 2)
    if wheel_base_m > 0.0:
        out = dataclasses.replace(out, slip_half_base_m=0.5 * wheel_base_m)
    if wheel_base_m > 0.0 and slip_gate_sigma > 0.0:
        out = dataclasses.replace(out, slip_gate_sigma=slip_gate_sigma,
                                  slip_yaw_rate_noise_radps=math.sqrt(2.0) * wheel_tick_mps / wheel_base_m)
    if accel_mps2_sqrt_hz is not None:
        out = dataclasses.replace(out, accel_noise_density_mps2_per_sqrt_hz=accel_mps2_sqrt_hz)
    if angular_accel_radps2_sqrt_hz is not None:
        out = dataclasses.replace(out, angular_accel_noise_density_radps2_per_sqrt_hz=angular_accel_radps2_sqrt_hz)
    return out


def _rate_readings(drive: CalibrationDrive, radius_left_m: float, radius_right_m: float,
                   base_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per wheel interval: its end (s), the speed (m/s) and yaw rate (rad/s) the wheels
    give, and whether the base stood still (no tick over it and the one before, as
    :class:`robotd.odometry.fusion.OdometryFilter` decides)."""
    t = np.asarray(drive.wheel_stamp_ns, np.int64)
    dphi = np.diff(np.asarray(drive.wheel_angle_rad, float), axis=0)
    dt = np.diff(t) * 1e-9
    v = 0.5 * (radius_left_m * dphi[:, 0] + radius_right_m * dphi[:, 1]) / dt
    w = (radius_right_m * dphi[:, 1] - radius_left_m * dphi[:, 0]) / base_m / dt
    still_now = ~np.any(np.abs(dphi) > 1e-12, axis=1)
    stationary = still_now & np.concatenate([[False], still_now[:-1]])
    return (t[1:] - t[0]) * 1e-9, v, w, stationary


def _nll_speed(q_l: float, t_s: np.ndarray, v: np.ndarray, r_var: np.ndarray, p0: float) -> float:
    """Negative log-likelihood (up to a constant) of the wheel speeds under a random-walk
    speed of density ``q_l`` (variance per s) read with noise ``r_var``."""
    x, p, prev, nll = 0.0, p0, 0.0, 0.0
    for tk, z, r in zip(t_s.tolist(), v.tolist(), r_var.tolist()):
        p += q_l * (tk - prev)
        prev = tk
        s = p + r
        nu = z - x
        nll += math.log(s) + nu * nu / s
        k = p / s
        x += k * nu
        p -= k * p
    return 0.5 * nll


def _nll_turn(q_a: float, q_b: float, events: list[tuple[float, int, float, float]],
              p0: tuple[float, float]) -> float:
    """The same for the yaw rate ``w`` (density ``q_a``) and the gyro bias (random walk
    ``q_b``): ``events`` in time order, ``(t_s, kind, reading, noise variance)`` with kind 0
    a gyro reading of ``w + bias`` and 1 a wheel reading of ``w``."""
    w = b = 0.0
    pww, pwb, pbb = p0[0], 0.0, p0[1]
    prev, nll = 0.0, 0.0
    for tk, kind, z, r in events:
        dt = tk - prev
        prev = tk
        pww += q_a * dt
        pbb += q_b * dt
        if kind == 0:  # H = [1, 1]
            hp_w, hp_b = pww + pwb, pwb + pbb
            s = hp_w + hp_b + r
            nu = z - w - b
        else:  # H = [1, 0]
            hp_w, hp_b = pww, pwb
            s = pww + r
            nu = z - w
        nll += math.log(s) + nu * nu / s
        kw, kb = hp_w / s, hp_b / s
        w += kw * nu
        b += kb * nu
        pww -= kw * hp_w
        pwb -= kw * hp_b
        pbb -= kb * hp_b
    return 0.5 * nll


def _ml_density(nll: Callable[[float], float], lo: float = 1e-4, hi: float = 10.0) -> tuple[float, float]:
    """The density ``sigma`` in ``[lo, hi]`` minimising ``nll(sigma^2)`` (golden section in
    ``ln sigma`` after a coarse grid) and its 1-sigma from the curvature in ``ln sigma``."""
    grid = np.linspace(math.log(lo), math.log(hi), 15)
    vals = [nll(math.exp(2 * u)) for u in grid]
    i = int(np.argmin(vals))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    g = (math.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = nll(math.exp(2 * c)), nll(math.exp(2 * d))
    while b - a > 1e-3:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = nll(math.exp(2 * c))
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = nll(math.exp(2 * d))
    u = 0.5 * (a + b)
    h = 0.05
    f0 = nll(math.exp(2 * u))
    curv = (nll(math.exp(2 * (u + h))) - 2 * f0 + nll(math.exp(2 * (u - h)))) / (h * h)
    sigma = math.exp(u)
    return sigma, (sigma / math.sqrt(curv) if curv > 0 else math.inf)


def fit_process_noise(drive: CalibrationDrive, radius_left_m: float, radius_right_m: float, base_m: float,
                      gyro_scale: float, gyro_noise_radps_sqrt_hz: float, wheel_noise_m_sqrt_m: float,
                      ticks_per_rev: float, noise: EkfParams = EkfParams()) -> ProcessNoiseFit:
    """The white accelerations of the filter by maximum likelihood on the drive's readings
    (module notes): the wheels' speed and yaw rate with the calibrated radii and base, the
    gyro's readings divided by ``gyro_scale``, the measurement noise of
    :func:`sensor_noise_params` (``ticks_per_rev``: the encoders') on ``noise``'s wheel
    yaw-rate noise, bias walk and zero-velocity noise."""
    t_w, v, w, still = _rate_readings(drive, radius_left_m, radius_right_m, base_m)
    tick_rad = 2.0 * math.pi / ticks_per_rev
    dt_w = float(np.median(np.diff(np.asarray(drive.wheel_stamp_ns, np.int64)))) * 1e-9
    params = sensor_noise_params(noise, gyro_noise_radps_sqrt_hz, wheel_noise_m_sqrt_m,
                                 tick_rad * 0.5 * (radius_left_m + radius_right_m), readings_hz=1.0 / dt_w)
    slip = slip_speed_variance(v, w, params.wheel_slip_var_m2_per_m, 0.5 * base_m, dt_w)
    sv = np.where(still, params.stationary_noise_mps, np.sqrt(params.wheel_v_noise_mps ** 2 + slip))
    sw = np.where(still, params.stationary_noise_radps, params.wheel_w_noise_radps
                  + params.wheel_w_noise_frac * np.abs(w) + params.wheel_w_noise_per_mps * np.abs(v))
    t0 = int(drive.wheel_stamp_ns[0])
    t_g = (np.asarray(drive.gyro_stamp_ns, np.int64) - t0) * 1e-9
    keep = (t_g >= 0.0) & (t_g <= t_w[-1])
    g = np.asarray(drive.gyro_radps, float)[keep] / gyro_scale
    fs_g = 1.0 / (float(np.median(np.diff(np.asarray(drive.gyro_stamp_ns, np.int64)))) * 1e-9)
    r_g = gyro_noise_radps_sqrt_hz ** 2 * fs_g / 2.0  # per reading at the drive's own gyro rate
    events = sorted([(float(t), 0, float(z), r_g) for t, z in zip(t_g[keep], g)]
                    + [(float(t), 1, float(z), float(s) ** 2) for t, z, s in zip(t_w, w, sw)],
                    key=lambda e: (e[0], e[1]))
    accel, accel_sigma = _ml_density(lambda q: _nll_speed(q, t_w, v, sv ** 2, params.initial_speed_sigma_mps ** 2))
    q_b = params.gyro_bias_walk_radps_per_sqrt_s ** 2
    p0 = (params.initial_yaw_rate_sigma_radps ** 2, params.initial_gyro_bias_sigma_radps ** 2)
    angular, angular_sigma = _ml_density(lambda q: _nll_turn(q, q_b, events, p0))
    return ProcessNoiseFit(accel_mps2_sqrt_hz=accel, accel_sigma=accel_sigma,
                           angular_accel_radps2_sqrt_hz=angular, angular_accel_sigma=angular_sigma,
                           wheel_v_noise_mps=params.wheel_v_noise_mps,
                           wheel_v_noise_frac=params.wheel_v_noise_frac, gyro_noise_radps=params.gyro_noise_radps)


def _unwrap_yaw(yaw: np.ndarray) -> np.ndarray:
    return np.unwrap(np.asarray(yaw, float))


def _gyro_integral(drive: CalibrationDrive, t0_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Knot times (s from ``t0_ns``) and the gyro's integral at them (rad), linear in
    between. Each reading is the mean rate over its own span, from the midpoint to the
    previous reading's stamp to the midpoint to the next one's (the first and last spans
    as wide on both sides): the Kobuki driver's raw-gyro reading is its packet's mean rate,
    stamped at the packet's middle, so its span is the packet; a reading of one instant
    gets the midpoint rule. The trapezoid rule between the readings would spread each
    change of rate over two packets and bias the gyro scale low at every turn's ends
    (docs/odometry.md, "The fit against the simulator's known errors")."""
    t = (np.asarray(drive.gyro_stamp_ns, np.int64) - t0_ns) * 1e-9
    w = np.asarray(drive.gyro_radps, float)
    mid = 0.5 * (t[1:] + t[:-1])
    knots = np.concatenate([[2.0 * t[0] - mid[0]], mid, [2.0 * t[-1] - mid[-1]]])
    return knots, np.concatenate([[0.0], np.cumsum(w * np.diff(knots))])


def _still_mask(drive: CalibrationDrive) -> np.ndarray:
    """Per wheel interval (``(N-1,)``): True when neither wheel moved over it."""
    d = np.abs(np.diff(np.asarray(drive.wheel_angle_rad, float), axis=0))
    return ~np.any(d > 1e-12, axis=1)


def _still_periods(drive: CalibrationDrive, margin_s: float) -> list[tuple[int, int]]:
    """Still periods as (start_ns, end_ns), shrunk by ``margin_s`` at each end."""
    still = _still_mask(drive)
    t = np.asarray(drive.wheel_stamp_ns, np.int64)
    out = []
    n = 0
    margin = int(margin_s * 1e9)
    while n < len(still):
        if not still[n]:
            n += 1
            continue
        m = n
        while m < len(still) and still[m]:
            m += 1
        a, b = int(t[n]) + margin, int(t[m]) - margin
        if b > a:
            out.append((a, b))
        n = m
    return out


def _turns_deg(drive: CalibrationDrive) -> tuple[float, float, float]:
    """Total reference turn to the left and to the right (deg) and reference path length (m)."""
    yaw = _unwrap_yaw(drive.ref_pose[:, 2])
    d = np.diff(yaw)
    d = d[np.abs(d) > math.radians(0.5)]  # not the reference's jitter while driving straight
    dist = float(np.sum(np.hypot(*np.diff(drive.ref_pose[:, :2], axis=0).T)))
    return math.degrees(float(d[d > 0].sum())), math.degrees(float(np.abs(d[d < 0]).sum())), dist


def missing_observability(drive: CalibrationDrive, params: OdometryFitParams = OdometryFitParams(),
                          ) -> list[str]:
    """What the drive lacks for the fit, one phrase each (empty: it can be fitted)."""
    lacks = []
    k = len(drive.ref_stamp_ns)
    if k < params.min_keyframes:
        lacks.append(f"{k} reference keyframes (needs {params.min_keyframes})")
        if k < 2:
            return lacks
    if len(drive.wheel_stamp_ns) < 2 or len(drive.gyro_stamp_ns) < 2:
        lacks.append("wheel and gyro readings")
        return lacks
    left, right, dist = _turns_deg(drive)
    if left < params.min_turn_deg:
        lacks.append(f"turns to the left ({left:.0f} deg in all, needs {params.min_turn_deg:.0f})")
    if right < params.min_turn_deg:
        lacks.append(f"turns to the right ({right:.0f} deg in all, needs {params.min_turn_deg:.0f})")
    if dist < params.min_distance_m:
        lacks.append(f"distance ({dist:.1f} m, needs {params.min_distance_m:g})")
    still = sum(b - a for a, b in _still_periods(drive, params.still_margin_s)) * 1e-9
    if still < params.min_still_s:
        lacks.append(f"standing still ({still:.1f} s, needs {params.min_still_s:g})")
    return lacks


@dataclass(frozen=True, slots=True, eq=False)
class _Intervals:
    dt_s: np.ndarray         # (J,) interval durations
    t_end_s: np.ndarray      # (J,) interval ends, s from the first keyframe
    dyaw_ref: np.ndarray     # (J,)
    d_ref: np.ndarray        # (J, 2) reference displacement in the interval's start frame
    dphi: np.ndarray         # (J, 2) left, right wheel angle over the interval
    gyro: np.ndarray         # (J,) gyro integral over the interval
    tsq: np.ndarray          # (J,) d(t^2 / 2) over the interval (the bias drift's regressor)


def _intervals(drive: CalibrationDrive) -> _Intervals:
    t0 = int(drive.ref_stamp_ns[0])
    tk = (np.asarray(drive.ref_stamp_ns, np.int64) - t0) * 1e-9
    tw = (np.asarray(drive.wheel_stamp_ns, np.int64) - t0) * 1e-9
    phi = np.asarray(drive.wheel_angle_rad, float)
    phi_k = np.stack([np.interp(tk, tw, phi[:, i]) for i in range(2)], axis=-1)
    tg, g = _gyro_integral(drive, t0)
    g_k = np.interp(tk, tg, g)
    yaw = _unwrap_yaw(drive.ref_pose[:, 2])
    pose = np.asarray(drive.ref_pose, float)
    d_ref = np.stack([rot2(float(yaw[k])).T @ (pose[k + 1, :2] - pose[k, :2])
                      for k in range(len(tk) - 1)]) if len(tk) > 1 else np.zeros((0, 2))
    return _Intervals(dt_s=np.diff(tk), t_end_s=tk[1:], dyaw_ref=np.diff(yaw), d_ref=d_ref,
                      dphi=np.diff(phi_k, axis=0), gyro=np.diff(g_k), tsq=np.diff(0.5 * tk ** 2))


def _arc_regressors(drive: CalibrationDrive, heading_of_t: Callable[[np.ndarray], np.ndarray],
                    t0_ns: int) -> np.ndarray:
    """Per keyframe interval, ``(J, 2, 2)``: the displacement (in the interval's start frame)
    per metre of wheel radius, for the left (``[:, :, 0]``) and right wheel: the sum over the
    wheel samples inside the interval of ``dphi_i / 2 * (cos, sin)(heading - heading_start)``
    at each sample's mid-time (the part of a sample before or after the interval counts pro
    rata)."""
    tk = (np.asarray(drive.ref_stamp_ns, np.int64) - t0_ns) * 1e-9
    tw = (np.asarray(drive.wheel_stamp_ns, np.int64) - t0_ns) * 1e-9
    phi = np.asarray(drive.wheel_angle_rad, float)
    # Split the wheel timeline at the keyframe stamps so every piece lies in one interval.
    inside = (tk > tw[0]) & (tk < tw[-1])
    knots = np.union1d(tw, tk[inside])
    phi_knots = np.stack([np.interp(knots, tw, phi[:, i]) for i in range(2)], axis=-1)
    dphi = np.diff(phi_knots, axis=0)
    mid = 0.5 * (knots[1:] + knots[:-1])
    which = np.searchsorted(tk, mid, side="right") - 1  # interval index of each piece
    ok = (which >= 0) & (which < len(tk) - 1)
    rel = heading_of_t(mid) - heading_of_t(tk[np.clip(which, 0, len(tk) - 1)])
    cs = np.stack([np.cos(rel), np.sin(rel)], axis=-1)  # (P, 2)
    out = np.zeros((len(tk) - 1, 2, 2))
    for wheel in range(2):
        contrib = 0.5 * dphi[:, wheel, None] * cs
        for axis in range(2):
            out[:, axis, wheel] = np.bincount(which[ok], weights=contrib[ok, axis], minlength=len(tk) - 1)
    return out


def _weighted_lstsq(a: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted linear least squares: the solution, its covariance scaled by the reduced
    chi2 when that exceeds one, and the reduced chi2."""
    sw = np.sqrt(w)
    x, *_ = np.linalg.lstsq(a * sw[:, None], y * sw, rcond=None)
    r = (y - a @ x) * sw
    dof = max(len(y) - a.shape[1], 1)
    red = float(r @ r / dof)
    cov = np.linalg.inv((a * w[:, None]).T @ a) * max(red, 1.0)
    return x, cov, red


def fit_odometry(drive: CalibrationDrive, nominal_radius_m: float, nominal_base_m: float,
                 params: OdometryFitParams = OdometryFitParams(), noise: EkfParams = EkfParams(),
                 ticks_per_rev: float = TICKS_PER_REV) -> OdometryFit:
    """Fit the odometry model to ``drive`` (see the module notes); the nominal radius and
    wheel base (m) give the "before" residuals and the first linearisation; ``noise``: the
    filter's noise model (the ``[odometry]`` table) whose wheel yaw-rate noise, bias walk
    and priors the white accelerations' likelihood keeps, ``ticks_per_rev`` the encoders'
    (:func:`fit_process_noise`). Raises
    :class:`CalibrationError` naming what the drive lacks when it cannot be fitted."""
    lacks = missing_observability(drive, params)
    if lacks:
        raise CalibrationError("the drive lacks " + "; ".join(lacks))
    t0 = int(drive.ref_stamp_ns[0])
    iv = _intervals(drive)
    gyro_density, b_still = _gyro_still(drive, params)
    q_g = gyro_density ** 2
    (s, b0, b1), cov_g = _fit_gyro(iv, q_g)

    def heading(t_s: np.ndarray) -> np.ndarray:
        """The calibrated gyro's heading (rad, from 0 at the first keyframe)."""
        tgi, gi = _gyro_integral(drive, t0)
        return (np.interp(t_s, tgi, gi) - b0 * t_s - 0.5 * b1 * t_s ** 2) / s

    wheels = _fit_wheels(drive, iv, _arc_regressors(drive, heading, t0), heading, nominal_radius_m,
                         nominal_base_m, q_g, params, ticks_per_rev)
    p, cov_w = wheels.p, wheels.cov
    # The wheel base is measured against the gyro: its scale's uncertainty carries over.
    cov_w[2, 2] += (p[2] * math.sqrt(cov_g[0, 0]) / s) ** 2
    before = _residuals_nominal(drive, iv, nominal_radius_m, nominal_base_m, b_still)
    gyro_after = (iv.gyro - b0 * iv.dt_s - b1 * iv.tsq) / s - iv.dyaw_ref
    after = np.column_stack([wheels.residuals, gyro_after])
    left, right, dist = _turns_deg(drive)
    still = sum(b - a for a, b in _still_periods(drive, params.still_margin_s)) * 1e-9
    process = fit_process_noise(drive, float(p[0]), float(p[1]), float(p[2]), s, gyro_density,
                                float(math.sqrt(wheels.q_w)), ticks_per_rev, noise)
    events = _slip_events(drive, wheels, heading, process, params, ticks_per_rev)
    return OdometryFit(
        wheel_radius_left_m=float(p[0]), wheel_radius_right_m=float(p[1]), wheel_base_m=float(p[2]),
        wheel_radius_left_sigma=float(math.sqrt(cov_w[0, 0])),
        wheel_radius_right_sigma=float(math.sqrt(cov_w[1, 1])),
        wheel_base_sigma=float(math.sqrt(cov_w[2, 2])),
        gyro_scale=s, gyro_scale_sigma=float(math.sqrt(cov_g[0, 0])),
        gyro_bias_radps=b0, gyro_bias_sigma=float(math.sqrt(cov_g[1, 1])), gyro_bias_drift_radps2=b1,
        gyro_noise_radps_sqrt_hz=gyro_density, wheel_noise_m_sqrt_m=float(math.sqrt(wheels.q_w)),
        residuals_before=before, residuals_after=after, interval_end_s=iv.t_end_s, used=wheels.used,
        slip_windows=wheels.slip_windows, heading_windows=wheels.heading_windows,
        turn_left_deg=left, turn_right_deg=right, distance_m=dist, still_s=still, process=process,
        slip_events=events,
    )


def _demanding(drive: CalibrationDrive, p: np.ndarray, process: ProcessNoiseFit, wheel_noise_m_sqrt_m: float,
               gate: float, ticks_per_rev: float) -> tuple[np.ndarray, np.ndarray]:
    """Per wheel reading: its interval's start (s from the drive's first wheel reading) and
    whether the filter's slip test calls it accelerating or turning
    (:func:`robotd.odometry.ekf.turning`: the wheels' yaw rate beyond ``gate`` times the
    ticks' own yaw-rate noise; :func:`robotd.odometry.ekf.speed_changing`: the speed beyond
    ``gate`` sigmas of the speed's prediction, by the speed's own filter with the fitted
    white acceleration, as :func:`fit_process_noise` runs it)."""
    rl, rr, bb = (float(x) for x in p)
    t_w, v, w, still = _rate_readings(drive, rl, rr, bb)
    dt = np.diff(np.concatenate([[0.0], t_w]))
    dt_w = float(np.median(dt))
    tick_m = 2.0 * math.pi * 0.5 * (rl + rr) / ticks_per_rev
    wheel_tick_mps = tick_m / dt_w / math.sqrt(6.0)
    turning = np.abs(w) > gate * math.sqrt(2.0) * wheel_tick_mps / bb
    r_v = (wheel_tick_mps ** 2 / 2.0
           + slip_speed_variance(v, w, wheel_noise_m_sqrt_m ** 2, 0.5 * bb, dt_w))
    q_l = process.accel_mps2_sqrt_hz ** 2
    changing = np.zeros(len(v), bool)
    x, var = 0.0, 1.0
    for i in range(len(v)):
        var += q_l * dt[i]
        if still[i]:
            x, var = 0.0, 1e-8
            continue
        s_i = var + r_v[i]
        nu = v[i] - x
        changing[i] = nu * nu > gate * gate * s_i
        k = var / s_i
        x += k * nu
        var -= k * var
    return t_w - dt, ~still & (turning | changing)


def _slip_events(drive: CalibrationDrive, wheels: _WheelFit, heading: Callable[[np.ndarray], np.ndarray],
                 process: ProcessNoiseFit, params: OdometryFitParams, ticks_per_rev: float) -> SlipEventFit:
    """The slip events' rate and duration from the heading windows the wheel fit left out
    (:mod:`robotd.odometry.slip_events`)."""
    t0 = int(drive.ref_stamp_ns[0])
    rl, rr, bb = (float(x) for x in wheels.p)
    tw = (np.asarray(drive.wheel_stamp_ns, np.int64) - t0) * 1e-9
    phi = np.asarray(drive.wheel_angle_rad, float)
    residual = (rr * phi[:, 1] - rl * phi[:, 0]) / bb - heading(tw)
    step = np.abs(np.diff(phi, axis=0)) * np.array([rl, rr])
    travel = np.concatenate([[0.0], np.cumsum(0.5 * step.sum(axis=1))])
    seen = find_slip_events(wheels.window_t0, wheels.window_t1, wheels.flagged, tw, residual, travel, bb)
    start_s, demanding = _demanding(drive, wheels.p, process, math.sqrt(wheels.q_w), params.event_test_sigma,
                                    ticks_per_rev)
    start_s = start_s + (int(drive.wheel_stamp_ns[0]) - t0) * 1e-9
    inside = (start_s >= wheels.window_edges[0]) & (start_s < wheels.window_edges[-1])
    dt = np.diff(tw)
    sel = demanding & inside
    sd = SlipDrive(demand_t_s=start_s[sel], demand_s=float(dt[sel].sum()), travel_t_s=tw, travel_m=travel,
                   window_edges_s=wheels.window_edges, threshold_rad=params.slip_gate_sigma * wheels.sig_h,
                   wheel_base_m=bb)
    return estimate_slip_events(seen, sd, params.min_slip_events)


def _gyro_still(drive: CalibrationDrive, params: OdometryFitParams) -> tuple[float, float]:
    """The gyro's white rate noise density (rad/s per sqrt(Hz)) from the spread of its
    readings about each still period's own mean (the bias moves between them), and the
    mean reading over all still periods (rad/s, 0 without any)."""
    tg = np.asarray(drive.gyro_stamp_ns, np.int64)
    w = np.asarray(drive.gyro_radps, float)
    still_sel = np.zeros(len(tg), bool)
    resid = []
    for lo_ns, hi_ns in _still_periods(drive, params.still_margin_s):
        sel = (tg >= lo_ns) & (tg <= hi_ns)
        still_sel |= sel
        if sel.sum() >= 3:
            resid.append(w[sel] - w[sel].mean())
    fs = 1.0 / float(np.median(np.diff(tg)) * 1e-9)
    density = float(np.std(np.concatenate(resid), ddof=1) / math.sqrt(fs / 2.0))
    return density, float(w[still_sel].mean()) if still_sel.any() else 0.0


def _fit_gyro(iv: _Intervals, q_g: float) -> tuple[tuple[float, float, float], np.ndarray]:
    """The gyro's scale ``s``, turn-on bias ``b0`` (rad/s) and drift ``b1`` (rad/s^2), and
    the covariance ``(4, 4)`` of ``(s, b0, b1, c)``. Its integral from the first keyframe
    to keyframe k is ``G_k = s Y_k + b0 t_k + b1 t_k^2 / 2 + c`` (Y: the reference's
    unwrapped heading). The errors are the reference's own heading noise (white, sigma_ref
    per keyframe) and the gyro's white noise integrated (a random walk, ``q_g t``):
    generalised least squares with that covariance, sigma_ref first estimated from the
    increments (their variance is ``2 sigma_ref^2 + q_g dt``)."""
    a_inc = np.column_stack([iv.dyaw_ref, iv.dt_s, iv.tsq])
    x_inc, *_ = np.linalg.lstsq(a_inc, iv.gyro, rcond=None)
    res = iv.gyro - a_inc @ x_inc
    var_ref = max(0.5 * float(np.mean(res ** 2 - q_g * iv.dt_s)), 1e-12)
    tk = np.concatenate([[0.0], iv.t_end_s])
    g_lev = np.concatenate([[0.0], np.cumsum(iv.gyro)])
    y_lev = np.concatenate([[0.0], np.cumsum(iv.dyaw_ref)])
    a_lev = np.column_stack([y_lev, tk, 0.5 * tk ** 2, np.ones_like(tk)])
    cov_lev = var_ref * np.eye(len(tk)) + q_g * np.minimum.outer(tk, tk)
    chol = np.linalg.cholesky(cov_lev)
    a_w = np.linalg.solve(chol, a_lev)
    g_w = np.linalg.solve(chol, g_lev)
    x_g, *_ = np.linalg.lstsq(a_w, g_w, rcond=None)
    r_w = g_w - a_w @ x_g
    red_g = float(r_w @ r_w / max(len(g_w) - 4, 1))
    cov_g = np.linalg.inv(a_w.T @ a_w) * max(red_g, 1.0)
    s, b0, b1 = (float(v) for v in x_g[:3])
    return (s, b0, b1), cov_g


@dataclass(frozen=True, slots=True, eq=False)
class _WheelFit:
    p: np.ndarray            # (3,) r_L, r_R, B (m)
    cov: np.ndarray          # (3, 3)
    residuals: np.ndarray    # (J, 3) dx, dy (m), heading (rad) per keyframe interval
    used: np.ndarray         # (J,) bool: intervals kept by the slip gate
    q_w: float               # slip noise variance per metre (m^2 / m)
    slip_windows: int
    heading_windows: int
    window_t0: np.ndarray    # (W,) the heading windows' starts, s from the first keyframe
    window_t1: np.ndarray    # (W,) their ends
    flagged: np.ndarray      # (W,) bool: beyond the gate (before their neighbours were added)
    sig_h: float             # the windows' robust heading sigma (rad)
    window_edges: np.ndarray  # the window grid's edges inside the reference (s)


def slip_density_from_windows(heading_error_rad: np.ndarray, travel_m: np.ndarray, span_s: np.ndarray,
                              gyro_q: float, geometry: np.ndarray, ticks_per_rev: float) -> float:
    """The wheels' continuous slip variance per metre of a wheel's own travel (m^2 / m) from
    the wheels' heading change over short windows against the calibrated gyro's
    (``heading_error_rad`` ``(W,)``, slip events left out), each window's mean wheel travel
    ``travel_m`` ``(W,)`` and span ``span_s`` ``(W,)``. Each window's squared error is
    modelled as ``2 q travel / B^2 + gyro_q span + c``: each wheel's slip (variance ``q``
    per metre) moves the heading by its distance over the wheel base ``B``, the gyro's white
    noise (``gyro_q``, (rad/s)^2 / Hz) integrates over the span, and ``c`` is the rounding of
    the ticks (``ticks_per_rev``) at both ends of the window on both wheels, ``(r_L^2 +
    r_R^2) tick^2 / (6 B^2)``. ``q`` is the method-of-moments ratio: the windows' squared
    errors less the gyro's and the ticks' parts, summed, over their modelled slope summed
    (0 when the rest leaves nothing). ``geometry``: ``(r_L, r_R, B)`` in metres."""
    rl, rr, bb = (float(v) for v in geometry)
    tick_rad = 2.0 * math.pi / ticks_per_rev
    c = 2.0 * float(rounding_variances(rl * tick_rad, rr * tick_rad, bb)[1])  # one count's rounding at each end
    excess = np.asarray(heading_error_rad, float) ** 2 - gyro_q * np.asarray(span_s, float) - c
    slope = 2.0 * np.asarray(travel_m, float) / bb ** 2
    total = float(slope.sum())
    return max(float(excess.sum()) / total, 0.0) if total > 0 else 0.0


def _fit_wheels(drive: CalibrationDrive, iv: _Intervals, arcs: np.ndarray,
                heading: Callable[[np.ndarray], np.ndarray], nominal_radius_m: float,
                nominal_base_m: float, q_g: float, params: OdometryFitParams,
                ticks_per_rev: float = TICKS_PER_REV) -> _WheelFit:
    """The wheels: unknowns (r_L, r_R, B), solved by Gauss-Newton over two blocks of
    residuals: the displacement over each keyframe interval against the reference (the
    radii; ``arcs`` from :func:`_arc_regressors`), and the heading change over short
    windows of the wheel timeline against the calibrated gyro (``heading``: the wheel base,
    and the radii's difference). The gyro, once calibrated, is better than the reference
    over a fraction of a second, and it shows a slip event (a wheel over- or under-rotating
    by a few percent for a fraction of a second) as a jump of tens of its own sigmas: such
    windows and their neighbours are left out of both blocks. Left in, a handful of them
    moves the wheel base by 0.1-0.4 % on a 26 m drive."""
    t0 = int(drive.ref_stamp_ns[0])
    n = len(iv.dt_s)

    def residuals(p: np.ndarray) -> np.ndarray:
        rl, rr, bb = p
        pos = arcs[:, :, 0] * rl + arcs[:, :, 1] * rr - iv.d_ref      # (J, 2)
        yaw = (rr * iv.dphi[:, 1] - rl * iv.dphi[:, 0]) / bb - iv.dyaw_ref
        return np.column_stack([pos, yaw])

    tw = (np.asarray(drive.wheel_stamp_ns, np.int64) - t0) * 1e-9
    phi = np.asarray(drive.wheel_angle_rad, float)
    step_w = max(1, int(round(params.window_s / float(np.median(np.diff(tw))))))
    cut = np.arange(0, len(tw), step_w)
    w_t0, w_t1 = tw[cut[:-1]], tw[cut[1:]]
    w_dphi = phi[cut[1:]] - phi[cut[:-1]]
    inside = (w_t0 >= 0.0) & (w_t1 <= iv.t_end_s[-1]) & (np.abs(w_dphi).sum(axis=1) > 0)
    edges = tw[cut]
    edges = edges[(edges >= 0.0) & (edges <= iv.t_end_s[-1])]
    w_t0, w_t1, w_dphi = w_t0[inside], w_t1[inside], w_dphi[inside]
    w_y = heading(w_t1) - heading(w_t0)
    interval_of = np.searchsorted(iv.t_end_s, 0.5 * (w_t0 + w_t1))  # keyframe interval of each window

    def heading_res(p: np.ndarray) -> np.ndarray:
        rl, rr, bb = p
        return (rr * w_dphi[:, 1] - rl * w_dphi[:, 0]) / bb - w_y

    def heading_jac(p: np.ndarray) -> np.ndarray:
        rl, rr, bb = p
        return np.column_stack([-w_dphi[:, 0] / bb, w_dphi[:, 1] / bb,
                                -(rr * w_dphi[:, 1] - rl * w_dphi[:, 0]) / bb ** 2])

    travel = np.maximum(np.abs(iv.dphi).mean(axis=1) * nominal_radius_m, 1e-6)
    p = np.array([nominal_radius_m, nominal_radius_m, nominal_base_m])
    used = np.ones(n, bool)
    clean = np.ones(len(w_y), bool)
    sig_pos = np.full(n, 1e-3)
    sig_h = 1e-3

    def system(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r_pos = residuals(p)[used, :2] / sig_pos[used, None]
        j_pos = np.zeros((int(used.sum()), 2, 3))
        j_pos[:, :, 0] = arcs[used, :, 0]
        j_pos[:, :, 1] = arcs[used, :, 1]
        j_pos /= sig_pos[used, None, None]
        y = np.concatenate([r_pos.reshape(-1), heading_res(p)[clean] / sig_h])
        a = np.concatenate([j_pos.reshape(-1, 3), heading_jac(p)[clean] / sig_h])
        return a, y

    for _rnd in range(4):
        for _ in range(10):
            a, y = system(p)
            step, *_ = np.linalg.lstsq(a, -y, rcond=None)
            p = p + step
            if np.all(np.abs(step) < 1e-12 + 1e-10 * np.abs(p)):
                break
        e = heading_res(p)
        mad = float(np.median(np.abs(e[clean] - np.median(e[clean])))) * 1.4826
        sig_h = max(mad, 1e-9)
        flagged = np.abs(e) > params.slip_gate_sigma * sig_h
        slip = flagged | np.roll(flagged, 1) | np.roll(flagged, -1)
        clean = ~slip
        used = np.ones(n, bool)
        used[np.unique(interval_of[slip])] = False
        # The displacement's noise: var = q |ds| + c per axis (c: the reference's own).
        r = residuals(p)
        e2 = 0.5 * (r[used, 0] ** 2 + r[used, 1] ** 2)
        design = np.column_stack([travel[used], np.ones(int(used.sum()))])
        coef, *_ = np.linalg.lstsq(design, e2, rcond=None)
        c_pos = max(float(coef[1]), 1e-12)
        sig_pos = np.sqrt(max(float(coef[0]), 1e-12) * travel + c_pos)
    a, y = system(p)
    red = float(y @ y / max(len(y) - 3, 1))
    cov_w = np.linalg.inv(a.T @ a) * max(red, 1.0)
    # The wheels' slip noise from the heading windows (the displacement's residuals are the
    # reference's own at this scale): var = 2 q |ds| / B^2 + q_g dt + c, with slip events out.
    # c is the ticks' rounding at both ends of a window on both wheels, known from the
    # encoders, not fitted: a drive at one cruising speed gives every window nearly the same
    # travel, and a free c would then trade with q on the few slow windows alone.
    e = heading_res(p)[clean]
    w_travel = np.abs(w_dphi[clean]).mean(axis=1) * 0.5 * (p[0] + p[1])
    q_w = slip_density_from_windows(e, w_travel, (w_t1 - w_t0)[clean], q_g, p, ticks_per_rev)
    return _WheelFit(p=p, cov=cov_w, residuals=residuals(p), used=used, q_w=q_w,
                     slip_windows=int((~clean).sum()), heading_windows=len(clean), window_t0=w_t0,
                     window_t1=w_t1, flagged=flagged, sig_h=sig_h, window_edges=edges)


def _residuals_nominal(drive: CalibrationDrive, iv: _Intervals, nominal_radius_m: float,
                       nominal_base_m: float, b_still: float) -> np.ndarray:
    """The residuals ``(J, 4)`` of the nominal model (nominal wheels; the raw gyro but for
    the still periods' mean level ``b_still``), as :attr:`OdometryFit.residuals_before`."""
    t0 = int(drive.ref_stamp_ns[0])
    r, b = nominal_radius_m, nominal_base_m

    def nominal_heading(t_s: np.ndarray) -> np.ndarray:
        tgi, gi = _gyro_integral(drive, t0)
        return np.interp(t_s, tgi, gi) - b_still * t_s

    arcs_nom = _arc_regressors(drive, nominal_heading, t0)
    pos_nom = arcs_nom[:, :, 0] * r + arcs_nom[:, :, 1] * r - iv.d_ref
    yaw_nom = (r * iv.dphi[:, 1] - r * iv.dphi[:, 0]) / b - iv.dyaw_ref
    gyro_nom = (iv.gyro - b_still * iv.dt_s) - iv.dyaw_ref
    return np.column_stack([pos_nom, yaw_nom, gyro_nom])
