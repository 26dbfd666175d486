"""The virtual Kobuki's wheel encoders and gyro, with realistic errors.

:func:`simulate_base` turns a true :class:`~sim.route.Motion` into what the base
reports in its 50 Hz feedback packets (the fields of sub-payloads 1, 4 and 13 that the
odometry uses), plus the true pose at each packet. Every error source is listed here and
in :class:`BaseSensorParams`; the values actually drawn for one seed are returned in
:class:`BaseErrors`.

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
- Quantisation: the encoder counts whole ticks (2578.33 per turn, 85 um of rim each) in
  a 16-bit counter that wraps, starting at a random value.

Gyro (a consumer MEMS rate gyro, L3G4200D class, on the yaw axis):

- Turn-on bias of magnitude drawn in ``gyro_bias_degps_range`` (0.1-0.3 deg/s), random
  sign, then a random walk (``gyro_bias_walk_degps_sqrt_s``, 0.001 deg/s per sqrt(s), so
  ~0.017 deg/s after five minutes: warm-up and temperature).
- White rate noise of density ``gyro_noise_density_degps_sqrt_hz`` (0.03 deg/s/sqrt(Hz),
  the datasheet's typical value); a sample at rate ``fs`` has standard deviation
  ``density * sqrt(fs / 2)`` (the noise fills the band up to Nyquist).
- Scale error, uniform in +-``gyro_scale_error_max`` (0.3 %).
- Sampled at ``gyro_rate_hz`` (108 Hz: a nominal 100 Hz output rate on the sensor's own
  oscillator) so a 20 ms packet carries 2 or 3 raw samples, quantised to 0.00875 deg/s
  per digit (sub-payload 13 reports the uncompensated digits). The x and y axes read
  their own zero-rate offset (standard deviation ``gyro_xy_offset_degps``) and the same
  white noise; nothing rotates about them on a flat floor.
- The firmware's inertial sub-payload (4): the firmware subtracts the bias it measured
  at power-on (the true turn-on bias plus an error of ``firmware_bias_cal_sigma_degps``,
  0.02 deg/s;
  it does not follow the random walk), integrates the samples into a heading in
  0.01 deg that starts at a random value and wraps at +-180 deg (an s16 of 0.01 deg
  cannot hold a full turn; the Kobuki driver treats it as a wrapped heading), and
  reports the mean compensated rate of the packet's samples in 0.01 deg/s.

Time: packets every ``1 / rate_hz`` of simulation time; ``device_ms`` is the base's 16-bit
millisecond clock, starting at a random boot value and wrapping.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from robotd.base.messages import WheelTicks, YawRate
from robotd.odometry.kinematics import DiffDriveParams
from sim.route import Motion

__all__ = ["BaseErrors", "BaseSensorParams", "BaseStream", "simulate_base"]

#: Inertial sub-payload units.
ANGLE_UNIT_DEG = 0.01
RATE_UNIT_DEGPS = 0.01
#: The motion counts as "accelerating or turning" (slip events possible) above these.
_SLIP_ACCEL_MPS2 = 0.05
_SLIP_TURN_RADPS = 0.1


@dataclass(frozen=True, slots=True)
class BaseSensorParams:
    """Error model of the Kobuki's encoders and gyro; see the module docstring for each source.

    Relative errors are fractions (0.005 = 0.5 %). Ranges are ``(low, high)`` of a
    uniform draw made once per seed.
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
    gyro_digit_degps: float = 0.00875
    gyro_xy_offset_degps: float = 0.5
    firmware_bias_cal_sigma_degps: float = 0.02

    def __post_init__(self) -> None:
        for name in ("wheel_base_error_range", "slip_event_ratio_range",
                     "slip_event_duration_s_range", "gyro_bias_degps_range"):
            lo, hi = getattr(self, name)
            if not 0.0 <= lo <= hi:
                raise ValueError(f"{name} must satisfy 0 <= low <= high, got {(lo, hi)}")
        if self.gyro_rate_hz <= 0.0 or self.gyro_digit_degps <= 0.0:
            raise ValueError("gyro_rate_hz and gyro_digit_degps must be positive")

    @classmethod
    def ideal(cls) -> BaseSensorParams:
        """No errors but quantisation (for tests of the pipeline itself)."""
        return cls(wheel_scale_error_max=0.0, wheel_diff_error_max=0.0,
                   wheel_base_error_range=(0.0, 0.0),
                   slip_noise_m_per_sqrt_m=0.0, slip_event_rate_hz=0.0,
                   gyro_bias_degps_range=(0.0, 0.0), gyro_bias_walk_degps_sqrt_s=0.0,
                   gyro_noise_density_degps_sqrt_hz=0.0, gyro_scale_error_max=0.0,
                   gyro_xy_offset_degps=0.0, firmware_bias_cal_sigma_degps=0.0)


@dataclass(frozen=True, slots=True)
class BaseErrors:
    """The errors drawn for one seed (relative errors as fractions, rates in deg/s)."""

    left_radius_error: float
    right_radius_error: float
    wheel_base_error: float
    gyro_bias0_degps: float
    gyro_scale_error: float
    firmware_bias_degps: float
    left_ticks0: int
    right_ticks0: int
    device_ms0: int
    angle0_deg: float
    slip_events: int


@dataclass(frozen=True, eq=False)
class BaseStream:
    """What the base reports, one row per feedback packet (``N`` packets).

    ``t_s`` ``(N,) float64`` simulation time, s; ``stamp_ns`` ``(N,) int64`` the same in ns;
    ``device_ms`` ``(N,) uint16`` the base's clock; ``left_ticks``/``right_ticks``
    ``(N,) uint16`` encoder counters; ``angle_cdeg`` ``(N,) int16`` firmware heading,
    0.01 deg, in [-18000, 18000); ``angle_rate_cdegps`` ``(N,) int16`` firmware yaw rate,
    0.01 deg/s; ``gyro_count`` ``(N,) int64`` raw gyro samples in the packet (2 or 3);
    ``gyro_digits`` ``(N, K, 3) int16`` raw x, y, z digits (0.00875 deg/s), zero past
    ``gyro_count``; ``gyro_t_s`` ``(N, K) float64`` the samples' true times (NaN padding);
    ``true_pose`` ``(N, 3) float64`` the true ``(x_m, y_m, yaw_rad)`` at each packet.
    """

    t_s: np.ndarray
    stamp_ns: np.ndarray
    device_ms: np.ndarray
    left_ticks: np.ndarray
    right_ticks: np.ndarray
    angle_cdeg: np.ndarray
    angle_rate_cdegps: np.ndarray
    gyro_count: np.ndarray
    gyro_digits: np.ndarray
    gyro_t_s: np.ndarray
    true_pose: np.ndarray
    errors: BaseErrors
    params: BaseSensorParams

    @property
    def gyro_z_digits(self) -> np.ndarray:
        """``(N, K) int16`` raw yaw-axis digits (counter-clockwise positive), zero-padded."""
        return self.gyro_digits[:, :, 2]

    @functools.cached_property
    def raw_gyro_z(self) -> list[np.ndarray]:
        """Per packet, the raw yaw-axis digits it carries (2 or 3 of them), ``int16``."""
        return [row[:n] for row, n in zip(self.gyro_z_digits, self.gyro_count)]

    def wheel_ticks(self) -> list[WheelTicks]:
        """One :class:`WheelTicks` per packet."""
        return [WheelTicks(int(s), int(l), int(r), int(d)) for s, l, r, d in
                zip(self.stamp_ns, self.left_ticks, self.right_ticks, self.device_ms)]

    def yaw_rates(self, source: str = "raw_gyro") -> list[YawRate]:
        """Yaw-rate messages, as a driver would make them from the packets.

        ``"raw_gyro"``: one per packet, the mean of its raw yaw digits times 0.00875 deg/s,
        at the packet's stamp (the inertial rate when a packet has no raw sample), as
        :class:`drivers.kobuki.driver.KobukiDriver` does. ``"raw_gyro_samples"``: one per raw
        sample, at the sample's true time. ``"inertial"``: one per packet from
        ``angle_rate_cdegps``.
        """
        inertial = np.deg2rad(self.angle_rate_cdegps.astype(float) * RATE_UNIT_DEGPS)
        digit = self.params.gyro_digit_degps
        if source == "inertial":
            return [YawRate(int(s), float(w), "inertial") for s, w in zip(self.stamp_ns, inertial)]
        if source == "raw_gyro":
            sums = self.gyro_z_digits.astype(float).sum(axis=1)
            mean = np.deg2rad(sums / np.maximum(self.gyro_count, 1) * digit)
            rates = np.where(self.gyro_count > 0, mean, inertial)
            return [YawRate(int(s), float(w), "raw_gyro") for s, w in zip(self.stamp_ns, rates)]
        if source != "raw_gyro_samples":
            raise ValueError("source must be 'raw_gyro', 'raw_gyro_samples' or 'inertial', "
                             f"got {source!r}")
        mask = np.arange(self.gyro_digits.shape[1])[None, :] < self.gyro_count[:, None]
        stamps = np.round(self.gyro_t_s[mask] * 1e9).astype(np.int64)
        rates = np.deg2rad(self.gyro_z_digits[mask].astype(float) * digit)
        return [YawRate(int(s), float(w), "raw_gyro") for s, w in zip(stamps, rates)]

    def messages(self, yaw_source: str = "raw_gyro") -> list[WheelTicks | YawRate]:
        """Wheel and yaw-rate messages merged in stamp order (wheels first on equal stamps,
        as the driver emits a packet's messages)."""
        keyed: list[tuple[int, int, int, WheelTicks | YawRate]] = [
            (m.stamp_ns, 0, i, m) for i, m in enumerate(self.wheel_ticks())]
        keyed += [(m.stamp_ns, 1, i, m) for i, m in enumerate(self.yaw_rates(yaw_source))]
        keyed.sort(key=lambda k: (k[0], k[1], k[2]))
        return [k[3] for k in keyed]


def _draw_sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def _wheel_slip(ds: np.ndarray, accel_like: np.ndarray, demanding: np.ndarray, dt_s: float,
                params: BaseSensorParams, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Slip distance of each wheel per step, ``(K, 2)`` metres, and the number of events."""
    slip = params.slip_noise_m_per_sqrt_m * np.sqrt(np.abs(ds)) * rng.standard_normal(ds.shape)
    p_event = params.slip_event_rate_hz * dt_s
    starts = np.flatnonzero(demanding & (rng.random(demanding.shape) < p_event))
    lo_r, hi_r = params.slip_event_ratio_range
    lo_d, hi_d = params.slip_event_duration_s_range
    for k in starts:
        wheel = int(rng.integers(2))
        ratio = rng.uniform(lo_r, hi_r)
        n = max(1, round(rng.uniform(lo_d, hi_d) / dt_s))
        trend = accel_like[k, wheel]
        sign = math.copysign(1.0, trend) if abs(trend) > 1e-9 else _draw_sign(rng)
        slip[k:k + n, wheel] += sign * ratio * ds[k:k + n, wheel]
    return slip, len(starts)


def simulate_base(motion: Motion, params: BaseSensorParams, rng: np.random.Generator,
                  rate_hz: float = 50.0) -> BaseStream:
    """Simulate the base's feedback packets at ``rate_hz`` along ``motion``; see the module doc."""
    p = params
    dt = motion.dt_s
    nominal = p.drive
    # ---- errors drawn for this seed --------------------------------------------------
    e_common = rng.uniform(-p.wheel_scale_error_max, p.wheel_scale_error_max)
    e_diff = rng.uniform(-p.wheel_diff_error_max, p.wheel_diff_error_max)
    e_left, e_right = e_common - e_diff, e_common + e_diff
    e_base = _draw_sign(rng) * rng.uniform(*p.wheel_base_error_range)
    bias0 = _draw_sign(rng) * rng.uniform(*p.gyro_bias_degps_range)
    g_scale = rng.uniform(-p.gyro_scale_error_max, p.gyro_scale_error_max)
    fw_bias = bias0 + p.firmware_bias_cal_sigma_degps * rng.standard_normal()
    ticks0 = rng.integers(0, 1 << 16, 2)
    tick_phase = rng.random(2)
    device_ms0 = int(rng.integers(0, 1 << 16))
    angle0 = rng.uniform(-180.0, 180.0)

    # ---- wheels ------------------------------------------------------------------------
    v = motion.v_mps[:-1]
    w = motion.w_radps[:-1]
    base_true = nominal.wheel_base_m * (1.0 + e_base)
    wheel_speed = np.stack([v - 0.5 * w * base_true, v + 0.5 * w * base_true], axis=-1)
    ds = wheel_speed * dt  # (K, 2) ground distance of each contact point
    speed_trend = np.diff(np.abs(wheel_speed), axis=0, prepend=0.0)
    accel = np.abs(np.diff(v, prepend=0.0)) / dt
    demanding = (accel > _SLIP_ACCEL_MPS2) | (np.abs(w) > _SLIP_TURN_RADPS)
    slip, n_events = _wheel_slip(ds, speed_trend, demanding, dt, p, rng)
    radius = nominal.wheel_radius_m * (1.0 + np.array([e_left, e_right]))
    dticks = (ds + slip) / (2.0 * math.pi * radius) * nominal.ticks_per_rev
    ticks = np.concatenate([np.zeros((1, 2)), np.cumsum(dticks, axis=0)])  # at motion.t_s

    t_end = float(motion.t_s[-1])
    n_pk = int(math.floor(t_end * rate_hz + 1e-9)) + 1
    t_pk = motion.t_s[0] + np.arange(n_pk) / rate_hz
    ticks_pk = np.stack([np.interp(t_pk, motion.t_s, ticks[:, i]) for i in range(2)], axis=-1)
    counters = (np.floor(ticks_pk + tick_phase).astype(np.int64) + ticks0) % (1 << 16)
    device_ms = (device_ms0 + np.round((t_pk - t_pk[0]) * 1000.0).astype(np.int64)) % (1 << 16)

    # ---- gyro --------------------------------------------------------------------------
    fs = p.gyro_rate_hz
    t_first = t_pk[0] - 1.0 / rate_hz + rng.uniform(0.0, 1.0 / fs)
    t_g = t_first + np.arange(int(math.floor((t_end - t_first) * fs)) + 1) / fs
    step = np.clip(np.floor((t_g - motion.t_s[0]) / dt).astype(np.int64), 0, len(w) - 1)
    w_true_degps = np.rad2deg(np.where(t_g >= motion.t_s[0], w[step], 0.0))
    walk = p.gyro_bias_walk_degps_sqrt_s * math.sqrt(1.0 / fs) * rng.standard_normal(t_g.shape)
    bias = bias0 + np.cumsum(walk)
    sigma = p.gyro_noise_density_degps_sqrt_hz * math.sqrt(fs / 2.0)
    rate_z = (1.0 + g_scale) * w_true_degps + bias + sigma * rng.standard_normal(t_g.shape)
    xy_off = p.gyro_xy_offset_degps * rng.standard_normal(2)
    rate_xy = xy_off + sigma * rng.standard_normal((len(t_g), 2))
    digits = np.clip(np.round(np.column_stack([rate_xy, rate_z]) / p.gyro_digit_degps),
                     -32768, 32767).astype(np.int16)
    # Firmware: bias-compensated rate, integrated into the heading at the sample rate.
    comp = digits[:, 2].astype(float) * p.gyro_digit_degps - fw_bias
    angle_fw = angle0 + np.cumsum(comp) / fs
    # Samples in (t_pk[j-1], t_pk[j]] belong to packet j.
    owner = np.searchsorted(t_pk, t_g, side="left")
    keep = owner < n_pk
    owner, t_g, digits, comp, angle_fw = (owner[keep], t_g[keep], digits[keep], comp[keep],
                                          angle_fw[keep])
    count = np.bincount(owner, minlength=n_pk)
    k_max = max(1, int(count.max()))
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    slot = np.arange(len(owner)) - first[owner]
    g_digits = np.zeros((n_pk, k_max, 3), dtype=np.int16)
    g_digits[owner, slot] = digits
    g_t = np.full((n_pk, k_max), np.nan)
    g_t[owner, slot] = t_g
    # Heading at each packet: after its last sample (the value before the first sample
    # is angle0). Rate: mean compensated rate of the packet's samples (held if none).
    last = first + count - 1
    filled = np.maximum.accumulate(np.where(count > 0, np.arange(n_pk), -1))
    valid = filled >= 0
    angle_pk = np.full(n_pk, angle0)
    angle_pk[valid] = angle_fw[last[filled[valid]]]
    rate_sum = np.bincount(owner, weights=comp, minlength=n_pk)
    rate_pk = np.zeros(n_pk)
    rate_pk[valid] = (rate_sum / np.maximum(count, 1))[filled[valid]]
    angle_wrapped = (angle_pk + 180.0) % 360.0 - 180.0
    angle_cdeg = np.round(angle_wrapped / ANGLE_UNIT_DEG).astype(np.int64)
    angle_cdeg = np.where(angle_cdeg >= 18000, angle_cdeg - 36000, angle_cdeg).astype(np.int16)
    rate_cdeg = np.clip(np.round(rate_pk / RATE_UNIT_DEGPS), -32768, 32767).astype(np.int16)

    errors = BaseErrors(
        left_radius_error=float(e_left), right_radius_error=float(e_right),
        wheel_base_error=float(e_base), gyro_bias0_degps=float(bias0),
        gyro_scale_error=float(g_scale), firmware_bias_degps=float(fw_bias),
        left_ticks0=int(ticks0[0]), right_ticks0=int(ticks0[1]), device_ms0=device_ms0,
        angle0_deg=float(angle0), slip_events=int(n_events),
    )
    return BaseStream(
        t_s=t_pk, stamp_ns=np.round(t_pk * 1e9).astype(np.int64),
        device_ms=device_ms.astype(np.uint16),
        left_ticks=counters[:, 0].astype(np.uint16), right_ticks=counters[:, 1].astype(np.uint16),
        angle_cdeg=angle_cdeg, angle_rate_cdegps=rate_cdeg, gyro_count=count.astype(np.int64),
        gyro_digits=g_digits, gyro_t_s=g_t, true_pose=motion.pose_at(t_pk),
        errors=errors, params=p,
    )
