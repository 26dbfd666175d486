"""The virtual base's wheel encoders and yaw gyro as SI ground truth, with realistic errors.

:func:`draw_errors` draws the errors of one base (per seed); :func:`simulate_sensors` then
turns a true :class:`~sim.route.Motion` into what the sensors measure, in SI units: the
cumulative angle each wheel has turned (rad) at the base's sampling times, the gyro's
angular-rate samples (rad/s) at their own times, the base's device clock (s), and the true
pose at each wheel sample. Nothing here knows a protocol: encoding these into the
Kobuki's ticks, digits and 16-bit counters is :mod:`sim.emulators.kobuki`'s job, and so
is the firmware's own processing (its bias compensation and heading integration).

Wheels (what makes wheel-only dead reckoning drift):

- Rolling radius: the wheels' effective radius differs from the nominal 0.035 m by a
  common relative error, uniform in +-``wheel_scale_error_max`` (0.5 %: tyre wear, load,
  manufacturing; a distance scale error), and the two wheels differ from each other by
  a further +-``wheel_diff_error_max`` each (0.1 %, so the diameter ratio is off by up
  to 0.2 %). Unequal wheels curve every straight: 0.1 % of difference turns the base
  by 0.25 deg per metre, so over 100 m this is the largest wheel-only heading error.
  UMBmark (Borenstein and Feng, 1996) finds diameter ratios of this order, and wheel
  base errors of a few percent, on uncalibrated bases.
- Effective wheel base: the tyres touch the floor over a patch ~2 cm wide, so the
  distance between the effective contact points differs from the nominal 0.23 m; the
  relative error's magnitude is drawn per seed in ``wheel_base_error_range`` (1-2 %),
  with a random sign. Every turn is then mis-measured by that fraction.
- Slip: a small continuous slip on each wheel (floor and tyre noise: standard deviation
  ``slip_noise_m_per_sqrt_m * sqrt(distance)``, 0.5 mm per sqrt(m)), and slip events
  while the base accelerates (> 0.05 m/s^2), brakes or turns (> 0.1 rad/s): at
  ``slip_event_rate_hz`` (0.3 per second of such driving), one wheel over-rotates
  (speeding up) or under-rotates (braking) by a fraction in ``slip_event_ratio_range`` of
  its motion for a time in ``slip_event_duration_s_range``.

The wheel angle is what the wheel really turned (ground distance plus slip, over the
wheel's true radius), from 0 at the first sample; the encoder's resolution is the
emulator's.

Gyro (a consumer MEMS rate gyro, L3G4200D class, on the yaw axis):

- Turn-on bias of magnitude drawn in ``gyro_bias_degps_range`` (0.1-0.3 deg/s), random
  sign, then a random walk (``gyro_bias_walk_degps_sqrt_s``, 0.001 deg/s per sqrt(s), so
  ~0.017 deg/s after five minutes: warm-up and temperature).
- White rate noise of density ``gyro_noise_density_degps_sqrt_hz`` (0.03 deg/s/sqrt(Hz),
  the datasheet's typical value); a sample at rate ``fs`` has standard deviation
  ``density * sqrt(fs / 2)`` (the noise fills the band up to Nyquist).
- Scale error, uniform in +-``gyro_scale_error_max`` (0.3 %).
- Sampled at ``gyro_rate_hz`` (108 Hz: a nominal 100 Hz output rate on the sensor's own
  oscillator), from a random phase within the first base period. The x and y axes read
  their own zero-rate offset (standard deviation ``gyro_xy_offset_degps``) and the same
  white noise; nothing rotates about them on a flat floor.

Time: the base samples its wheels every ``1 / rate_hz`` of simulation time; its device
clock starts at 0 at the first sample and runs at the simulation's rate (no drift is
modelled; the emulator's counter adds its boot value).

Random draws come in a fixed order (errors, then slip, then gyro) so a seed always gives
the same run; :func:`sim.emulators.kobuki.simulate_kobuki` draws the base's power-on
state between :func:`draw_errors` and :func:`simulate_sensors`, as the model always has.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np

from robotd.odometry.kinematics import DiffDriveParams
from sim.route import Motion

__all__ = ["BaseErrors", "BaseSensorParams", "BaseSensorStreams", "draw_errors",
           "simulate_sensors"]

#: The motion counts as "accelerating or turning" (slip events possible) above these.
_SLIP_ACCEL_MPS2 = 0.05
_SLIP_TURN_RADPS = 0.1


@dataclass(frozen=True, slots=True)
class BaseSensorParams:
    """Error model of the base's encoders and gyro; see the module docstring for each source.

    Relative errors are fractions (0.005 = 0.5 %). Ranges are ``(low, high)`` of a
    uniform draw made once per seed. ``drive`` is the nominal geometry (the true one
    differs by the drawn errors).
    """

    drive: DiffDriveParams = field(default_factory=DiffDriveParams)
    wheel_scale_error_max: float = 0.005
    wheel_diff_error_max: float = 0.001
    wheel_base_error_range: tuple[float, float] = (0.01, 0.02)
    slip_noise_m_per_sqrt_m: float = 5e-4
    slip_event_rate_hz: float = 0.3
    slip_event_ratio_range: tuple[float, float] = (0.02, 0.08)
    slip_event_duration_s_range: tuple[float, float] = (0.05, 0.3)
    gyro_bias_degps_range: tuple[float, float] = (0.1, 0.3)
    gyro_bias_walk_degps_sqrt_s: float = 0.001
    gyro_noise_density_degps_sqrt_hz: float = 0.03
    gyro_scale_error_max: float = 0.003
    gyro_rate_hz: float = 108.0
    gyro_xy_offset_degps: float = 0.5

    def __post_init__(self) -> None:
        for name in ("wheel_base_error_range", "slip_event_ratio_range",
                     "slip_event_duration_s_range", "gyro_bias_degps_range"):
            lo, hi = getattr(self, name)
            if not 0.0 <= lo <= hi:
                raise ValueError(f"{name} must satisfy 0 <= low <= high, got {(lo, hi)}")
        if self.gyro_rate_hz <= 0.0:
            raise ValueError("gyro_rate_hz must be positive")

    @classmethod
    def ideal(cls) -> BaseSensorParams:
        """No errors at all (for tests of the pipeline itself; the emulator still quantises)."""
        return cls(wheel_scale_error_max=0.0, wheel_diff_error_max=0.0,
                   wheel_base_error_range=(0.0, 0.0),
                   slip_noise_m_per_sqrt_m=0.0, slip_event_rate_hz=0.0,
                   gyro_bias_degps_range=(0.0, 0.0), gyro_bias_walk_degps_sqrt_s=0.0,
                   gyro_noise_density_degps_sqrt_hz=0.0, gyro_scale_error_max=0.0,
                   gyro_xy_offset_degps=0.0)


@dataclass(frozen=True, slots=True)
class BaseErrors:
    """The errors drawn for one base: relative errors as fractions, the gyro's turn-on
    bias in rad/s (counter-clockwise positive)."""

    left_radius_error: float
    right_radius_error: float
    wheel_base_error: float
    gyro_bias0_radps: float
    gyro_scale_error: float


@dataclass(frozen=True, eq=False)
class BaseSensorStreams:
    """What the sensors measured along one motion, SI units.

    Wheel samples (``N``, every ``1 / rate_hz``): ``t_s`` ``(N,) float64`` simulation
    time, s; ``stamp_ns`` ``(N,) int64`` the same in ns; ``device_clock_s`` ``(N,)
    float64`` the base's own clock, s; ``wheel_angle_rad`` ``(N, 2) float64`` cumulative
    angle turned by the left and right wheel since the first sample, rad (forward
    positive); ``true_pose`` ``(N, 3) float64`` the true ``(x_m, y_m, yaw_rad)``.
    Gyro samples (``M``, every ``1 / gyro_rate_hz``): ``gyro_t_s`` ``(M,) float64``,
    s; ``gyro_radps`` ``(M, 3) float64`` angular rate about the robot's x, y and z axes
    (z up: the yaw rate, counter-clockwise positive), rad/s, with every modelled error.
    ``slip_events`` counts the slip events of the run, ``slip_event_durations_s`` ``(E,)``
    their durations (s).
    """

    t_s: np.ndarray
    stamp_ns: np.ndarray
    device_clock_s: np.ndarray
    wheel_angle_rad: np.ndarray
    true_pose: np.ndarray
    gyro_t_s: np.ndarray
    gyro_radps: np.ndarray
    slip_events: int
    slip_event_durations_s: np.ndarray
    errors: BaseErrors
    params: BaseSensorParams
    rate_hz: float


def _draw_sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def draw_errors(params: BaseSensorParams, rng: np.random.Generator) -> BaseErrors:
    """The per-seed errors of one base (five draws from ``rng``, always in this order)."""
    p = params
    e_common = rng.uniform(-p.wheel_scale_error_max, p.wheel_scale_error_max)
    e_diff = rng.uniform(-p.wheel_diff_error_max, p.wheel_diff_error_max)
    e_base = _draw_sign(rng) * rng.uniform(*p.wheel_base_error_range)
    bias0_degps = _draw_sign(rng) * rng.uniform(*p.gyro_bias_degps_range)
    g_scale = rng.uniform(-p.gyro_scale_error_max, p.gyro_scale_error_max)
    return BaseErrors(left_radius_error=float(e_common - e_diff),
                      right_radius_error=float(e_common + e_diff),
                      wheel_base_error=float(e_base),
                      gyro_bias0_radps=math.radians(bias0_degps),
                      gyro_scale_error=float(g_scale))


def _wheel_slip(ds: np.ndarray, accel_like: np.ndarray, demanding: np.ndarray, dt_s: float,
                params: BaseSensorParams, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Slip distance of each wheel per step, ``(K, 2)`` metres, and each event's duration
    ``(E,)`` s."""
    slip = params.slip_noise_m_per_sqrt_m * np.sqrt(np.abs(ds)) * rng.standard_normal(ds.shape)
    p_event = params.slip_event_rate_hz * dt_s
    starts = np.flatnonzero(demanding & (rng.random(demanding.shape) < p_event))
    lo_r, hi_r = params.slip_event_ratio_range
    lo_d, hi_d = params.slip_event_duration_s_range
    durations = np.zeros(len(starts))
    for i, k in enumerate(starts):
        wheel = int(rng.integers(2))
        ratio = rng.uniform(lo_r, hi_r)
        n = max(1, round(rng.uniform(lo_d, hi_d) / dt_s))
        durations[i] = min(n, len(ds) - int(k)) * dt_s
        trend = accel_like[k, wheel]
        sign = math.copysign(1.0, trend) if abs(trend) > 1e-9 else _draw_sign(rng)
        slip[k:k + n, wheel] += sign * ratio * ds[k:k + n, wheel]
    return slip, durations


def _wheel_angles(motion: Motion, params: BaseSensorParams, errors: BaseErrors,
                  t_s: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative wheel angles ``(N, 2)`` rad at ``t_s``, and the slip events' durations ``(E,)`` s."""
    dt = motion.dt_s
    nominal = params.drive
    v = motion.v_mps[:-1]
    w = motion.w_radps[:-1]
    base_true = nominal.wheel_base_m * (1.0 + errors.wheel_base_error)
    wheel_speed = np.stack([v - 0.5 * w * base_true, v + 0.5 * w * base_true], axis=-1)
    ds = wheel_speed * dt  # (K, 2) ground distance of each contact point
    speed_trend = np.diff(np.abs(wheel_speed), axis=0, prepend=0.0)
    accel = np.abs(np.diff(v, prepend=0.0)) / dt
    demanding = (accel > _SLIP_ACCEL_MPS2) | (np.abs(w) > _SLIP_TURN_RADPS)
    slip, durations = _wheel_slip(ds, speed_trend, demanding, dt, params, rng)
    radius = nominal.wheel_radius_m * (1.0 + np.array([errors.left_radius_error,
                                                       errors.right_radius_error]))
    angle = np.concatenate([np.zeros((1, 2)), np.cumsum((ds + slip) / radius, axis=0)])
    at_t = np.stack([np.interp(t_s, motion.t_s, angle[:, i]) for i in range(2)], axis=-1)
    return at_t, durations


def _gyro(motion: Motion, params: BaseSensorParams, errors: BaseErrors, t0_s: float,
          period_s: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Gyro sample times ``(M,)`` s and rates ``(M, 3)`` rad/s about the robot's x, y, z.

    The first sample falls at a random phase within the base period before ``t0_s``; the
    samples run to the end of the motion. Computed in deg/s (the units of the error
    model's parameters) and converted once at the end.
    """
    p = params
    fs = p.gyro_rate_hz
    w = motion.w_radps[:-1]
    t_end = float(motion.t_s[-1])
    t_first = t0_s - period_s + rng.uniform(0.0, 1.0 / fs)
    t_g = t_first + np.arange(int(math.floor((t_end - t_first) * fs)) + 1) / fs
    step = np.clip(np.floor((t_g - motion.t_s[0]) / motion.dt_s).astype(np.int64), 0, len(w) - 1)
    w_true_degps = np.rad2deg(np.where(t_g >= motion.t_s[0], w[step], 0.0))
    walk = p.gyro_bias_walk_degps_sqrt_s * math.sqrt(1.0 / fs) * rng.standard_normal(t_g.shape)
    bias = math.degrees(errors.gyro_bias0_radps) + np.cumsum(walk)
    sigma = p.gyro_noise_density_degps_sqrt_hz * math.sqrt(fs / 2.0)
    rate_z = ((1.0 + errors.gyro_scale_error) * w_true_degps + bias
              + sigma * rng.standard_normal(t_g.shape))
    xy_off = p.gyro_xy_offset_degps * rng.standard_normal(2)
    rate_xy = xy_off + sigma * rng.standard_normal((len(t_g), 2))
    return t_g, np.deg2rad(np.column_stack([rate_xy, rate_z]))


def simulate_sensors(motion: Motion, params: BaseSensorParams, errors: BaseErrors,
                     rng: np.random.Generator, rate_hz: float = 50.0,
                     draws_of: Motion | None = None) -> BaseSensorStreams:
    """What a base with ``errors`` measures along ``motion``, wheels sampled at ``rate_hz``;
    see the module doc. Draws the slip, then the gyro's phase, bias walk and noise.

    ``draws_of``: the motion whose slip draws the gyro's follow (default ``motion``). A
    kidnapped drive (:func:`sim.route.kidnapped`) passes the same drive without the
    kidnapping: the number of slip draws depends on the whole motion, so the gyro's phase,
    bias walk and noise would otherwise be other draws than that drive's from the first
    sample on; so they are that drive's (the same sample for sample when both motions
    are as long, as under the demo's ``--duration``). The wheels' own draws are
    ``motion``'s either way (the same as that drive's until the lift)."""
    t_end = float(motion.t_s[-1])
    n = int(math.floor(t_end * rate_hz + 1e-9)) + 1
    t_s = motion.t_s[0] + np.arange(n) / rate_hz
    gyro_rng = rng
    if draws_of is not None and draws_of is not motion:
        gyro_rng = copy.deepcopy(rng)
        n_of = int(math.floor(float(draws_of.t_s[-1]) * rate_hz + 1e-9)) + 1
        _wheel_angles(draws_of, params, errors, draws_of.t_s[0] + np.arange(n_of) / rate_hz, gyro_rng)
    wheel_angle_rad, durations = _wheel_angles(motion, params, errors, t_s, rng)
    gyro_t_s, gyro_radps = _gyro(motion, params, errors, float(t_s[0]), 1.0 / rate_hz, gyro_rng)
    if gyro_rng is not rng:  # the caller's generator ends where that drive's would
        rng.bit_generator.state = gyro_rng.bit_generator.state
    return BaseSensorStreams(
        t_s=t_s, stamp_ns=np.round(t_s * 1e9).astype(np.int64), device_clock_s=t_s - t_s[0],
        wheel_angle_rad=wheel_angle_rad, true_pose=motion.pose_at(t_s),
        gyro_t_s=gyro_t_s, gyro_radps=gyro_radps, slip_events=len(durations),
        slip_event_durations_s=durations,
        errors=errors, params=params, rate_hz=float(rate_hz))
