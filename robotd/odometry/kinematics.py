"""Differential-drive kinematics: encoder ticks -> travelled distance and heading change.

REP-103 conventions: x forward, y left, yaw counter-clockwise, SI units. A step of the
wheels is an arc of constant curvature (both wheels turn at constant speed over one
encoder sample), so :func:`integrate_pose` is exact for that motion; paper 003, Sec. III,
eqs. (1)-(2) write the same step as a rotation followed by a translation.

This module owns the maths of one drive step; the SE(2) composition itself lives in
:mod:`robotd.base.geometry`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from robotd.base.config import RobotConfig
from robotd.base.geometry import compose, wrap_angle
from robotd.base.messages import PoseStamped, WheelTicks

__all__ = [
    "DiffDriveParams",
    "WheelOdometry",
    "arc_increment",
    "integrate_pose",
    "unwrap_ticks_delta",
    "wheel_increment",
]


def unwrap_ticks_delta(prev: int, cur: int, bits: int = 16) -> int:
    """The shortest signed difference ``cur - prev`` of two wrapping ``bits``-bit counters.

    The result lies in ``[-2**(bits-1), 2**(bits-1))``: a wheel can move at most half the
    counter range between two readings (32767 ticks, about 2.8 m on a Kobuki) before the
    direction becomes ambiguous. ``unwrap_ticks_delta(65535, 0) == 1``.
    """
    modulus = 1 << bits
    half = modulus >> 1
    return (int(cur) - int(prev) + half) % modulus - half


@dataclass(frozen=True, slots=True)
class DiffDriveParams:
    """Geometry of a differential-drive base (Kobuki defaults).

    ``wheel_radius_m``: wheel radius, metres. ``wheel_base_m``: distance between the two
    wheels' contact points, metres. ``ticks_per_rev``: encoder ticks per wheel turn
    (the Kobuki's is 2578.33: a 52:1 gearbox behind a ~49.6-tick motor encoder).
    ``wheel_radius_left_m`` / ``wheel_radius_right_m``: each wheel's own rolling radius
    when calibrated (``robotd calibrate odometry``), else None: both are
    ``wheel_radius_m``.
    """

    wheel_radius_m: float = RobotConfig.wheel_radius_m
    wheel_base_m: float = RobotConfig.wheel_base_m
    ticks_per_rev: float = RobotConfig.ticks_per_rev
    wheel_radius_left_m: float | None = None
    wheel_radius_right_m: float | None = None

    @classmethod
    def from_config(cls, section: RobotConfig, **calibrated: float | None) -> DiffDriveParams:
        """The geometry of a ``[robot]`` table (the defaults are its defaults);
        ``calibrated``: what the calibration file replaces (``wheel_base_m``, the wheel
        radii)."""
        values = {"wheel_radius_m": section.wheel_radius_m, "wheel_base_m": section.wheel_base_m,
                  "ticks_per_rev": section.ticks_per_rev}
        return cls(**{**values, **calibrated})  # type: ignore[arg-type]

    def __post_init__(self) -> None:
        for name in ("wheel_radius_m", "wheel_base_m", "ticks_per_rev", "wheel_radius_left_m",
                     "wheel_radius_right_m"):
            value = getattr(self, name)
            if value is None and name.startswith("wheel_radius_"):
                continue
            if not (value > 0.0 and math.isfinite(value)):
                raise ValueError(f"{name} must be positive and finite, got {value!r}")

    @property
    def metres_per_tick(self) -> float:
        """Distance the wheel rim travels per encoder tick, metres (the larger wheel's when
        the two differ: it bounds how far a wheel moves)."""
        return max(self.metres_per_tick_left, self.metres_per_tick_right)

    @property
    def metres_per_tick_left(self) -> float:
        """The left wheel's rim travel per tick, metres."""
        r = self.wheel_radius_m if self.wheel_radius_left_m is None else self.wheel_radius_left_m
        return 2.0 * math.pi * r / self.ticks_per_rev

    @property
    def metres_per_tick_right(self) -> float:
        """The right wheel's rim travel per tick, metres."""
        r = self.wheel_radius_m if self.wheel_radius_right_m is None else self.wheel_radius_right_m
        return 2.0 * math.pi * r / self.ticks_per_rev


def wheel_increment(d_left_ticks: int | float, d_right_ticks: int | float,
                    params: DiffDriveParams = DiffDriveParams()) -> tuple[float, float]:
    """Distance travelled by the base centre and its heading change for one tick step.

    ``ds_m = (s_l + s_r) / 2`` and ``dyaw_rad = (s_r - s_l) / B`` with ``s_i`` the rim
    distance of wheel ``i`` and ``B`` the wheel base. Returns ``(ds_m, dyaw_rad)``.
    """
    s_l = float(d_left_ticks) * params.metres_per_tick_left
    s_r = float(d_right_ticks) * params.metres_per_tick_right
    return 0.5 * (s_l + s_r), (s_r - s_l) / params.wheel_base_m


def _sinc_half(dyaw: np.ndarray | float) -> np.ndarray | float:
    """``sin(dyaw/2) / (dyaw/2)``, exact near zero (``np.sinc`` is ``sin(pi x)/(pi x)``)."""
    return np.sinc(np.asarray(dyaw, dtype=float) / (2.0 * math.pi))


def arc_increment(ds_m: float | np.ndarray, dyaw_rad: float | np.ndarray) -> np.ndarray:
    """The relative pose of a constant-curvature step, in the frame of its start pose.

    A step of arc length ``ds_m`` turning by ``dyaw_rad`` ends at the chord
    ``ds * sinc(dyaw/2)`` in direction ``dyaw/2``: ``(dx, dy, dyaw)``, shape ``(3,)``, or
    ``(N, 3)`` for arrays of steps. Exact for any ``dyaw`` (a turn in place has ``ds = 0``).
    """
    ds = np.asarray(ds_m, dtype=float)
    dth = np.asarray(dyaw_rad, dtype=float)
    chord = ds * _sinc_half(dth)
    half = 0.5 * dth
    return np.stack([chord * np.cos(half), chord * np.sin(half), dth], axis=-1)


def integrate_pose(pose: np.ndarray, ds_m: float, dyaw_rad: float) -> np.ndarray:
    """``pose (+) arc_increment(ds, dyaw)``: the pose ``(x_m, y_m, yaw_rad)`` after one step.

    Arc-exact (the midpoint heading with the chord length); yaw is wrapped to [-pi, pi).
    """
    return compose(np.asarray(pose, dtype=float), arc_increment(ds_m, dyaw_rad))


@dataclass
class WheelOdometry:
    """Dead reckoning from :class:`~robotd.base.messages.WheelTicks` alone (no gyro).

    The first message only sets the tick reference; every later one adds the arc of its
    tick deltas. The covariance over ``(x, y, yaw)`` follows the usual independent-wheel
    model: each wheel's rim distance has variance ``noise_m_per_sqrt_m**2 * |s_i|``
    (slip and tyre noise growing with distance); systematic errors (scale, wheel base)
    are not in it. It is the baseline the fused filter is compared against.
    """

    params: DiffDriveParams = field(default_factory=DiffDriveParams)
    initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    noise_m_per_sqrt_m: float = 0.003

    def __post_init__(self) -> None:
        self._pose = np.array(self.initial_pose, dtype=float)
        self._cov = np.zeros((3, 3))
        self._ref: tuple[int, int] | None = None
        self._stamp_ns: int | None = None
        self.distance_m = 0.0

    @property
    def started(self) -> bool:
        """True once a first message has set the tick reference."""
        return self._ref is not None

    def rebase(self, msg: WheelTicks) -> None:
        """Take ``msg``'s counters as the new reference without moving (after a long gap)."""
        self._ref = (int(msg.left_ticks), int(msg.right_ticks))
        self._stamp_ns = int(msg.stamp_ns)

    def update(self, msg: WheelTicks) -> PoseStamped:
        """Advance by the tick deltas since the previous message; return the new pose."""
        if self._ref is None:
            self.rebase(msg)
            return self.pose()
        dl = unwrap_ticks_delta(self._ref[0], msg.left_ticks)
        dr = unwrap_ticks_delta(self._ref[1], msg.right_ticks)
        self._ref = (int(msg.left_ticks), int(msg.right_ticks))
        self._stamp_ns = int(msg.stamp_ns)
        if dl or dr:
            self._step(dl, dr)
        return self.pose()

    def _step(self, dl: int, dr: int) -> None:
        p = self.params
        s_l, s_r = dl * p.metres_per_tick_left, dr * p.metres_per_tick_right
        ds, dth = 0.5 * (s_l + s_r), (s_r - s_l) / p.wheel_base_m
        phi = self._pose[2] + 0.5 * dth
        c, s = math.cos(phi), math.sin(phi)
        f = ds * float(_sinc_half(dth))
        jac_pose = np.array([[1.0, 0.0, -f * s], [0.0, 1.0, f * c], [0.0, 0.0, 1.0]])
        # d(x, y, yaw) / d(s_l, s_r), midpoint approximation of the chord.
        a, b = 0.5, ds / (2.0 * p.wheel_base_m)
        jac_wheels = np.array([
            [a * c + b * s, a * c - b * s],
            [a * s - b * c, a * s + b * c],
            [-1.0 / p.wheel_base_m, 1.0 / p.wheel_base_m],
        ])
        q = self.noise_m_per_sqrt_m ** 2
        wheel_cov = np.diag([q * abs(s_l), q * abs(s_r)])
        cov = jac_pose @ self._cov @ jac_pose.T + jac_wheels @ wheel_cov @ jac_wheels.T
        self._cov = 0.5 * (cov + cov.T)
        self._pose = integrate_pose(self._pose, ds, dth)
        self.distance_m += abs(ds)

    def pose(self) -> PoseStamped:
        """The current dead-reckoned pose (stamp 0 before the first message)."""
        return PoseStamped(
            stamp_ns=self._stamp_ns if self._stamp_ns is not None else 0,
            x_m=float(self._pose[0]), y_m=float(self._pose[1]),
            yaw_rad=float(wrap_angle(float(self._pose[2]))), covariance=self._cov.copy(),
        )
