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


def _sinc_half_scalar(dyaw: float) -> float:
    """:func:`_sinc_half` of one float, by the same arithmetic as ``np.sinc``."""
    y = math.pi * (dyaw / (2.0 * math.pi) or 1.0e-20)
    return math.sin(y) / y


def _symmetric3(upper: tuple[float, ...]) -> np.ndarray:
    """The ``(3, 3)`` symmetric matrix of an upper triangle ``(a00, a01, a02, a11, a12, a22)``."""
    a00, a01, a02, a11, a12, a22 = upper
    return np.array([[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]])


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
        # Scalars, not arrays: one step per wheel message, where NumPy's per-call overhead
        # on 3-vectors and 3x3 matrices cost ten times the arithmetic.
        x, y, yaw = (float(v) for v in self.initial_pose)
        self._pose = (x, y, yaw)
        self._cov = (0.0,) * 6  # the upper triangle: xx, xy, xyaw, yy, yyaw, yawyaw
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
        self.advance(msg)
        return self.pose()

    def advance(self, msg: WheelTicks) -> None:
        """:meth:`update` without building the pose (the fused filter's twin runs this per
        wheel message and reads the pose only when asked)."""
        if self._ref is None:
            self.rebase(msg)
            return
        dl = unwrap_ticks_delta(self._ref[0], msg.left_ticks)
        dr = unwrap_ticks_delta(self._ref[1], msg.right_ticks)
        self._ref = (int(msg.left_ticks), int(msg.right_ticks))
        self._stamp_ns = int(msg.stamp_ns)
        if dl or dr:
            self._step(dl, dr)

    def _step(self, dl: int, dr: int) -> None:
        """One tick step: ``cov' = Jp cov Jp^T + Jw diag(q |s_l|, q |s_r|) Jw^T`` and the pose
        composed with the arc (:func:`integrate_pose`), in scalars."""
        p = self.params
        s_l, s_r = dl * p.metres_per_tick_left, dr * p.metres_per_tick_right
        ds, dth = 0.5 * (s_l + s_r), (s_r - s_l) / p.wheel_base_m
        x0, y0, yaw0 = self._pose
        phi = yaw0 + 0.5 * dth
        c, s = math.cos(phi), math.sin(phi)
        f = ds * _sinc_half_scalar(dth)
        # Jp = I except Jp[0, 2] = u, Jp[1, 2] = v.
        u, v = -f * s, f * c
        cxx, cxy, cxt, cyy, cyt, ctt = self._cov
        # d(x, y, yaw) / d(s_l, s_r), midpoint approximation of the chord.
        a, b = 0.5, ds / (2.0 * p.wheel_base_m)
        w00, w01 = a * c + b * s, a * c - b * s
        w10, w11 = a * s - b * c, a * s + b * c
        w20, w21 = -1.0 / p.wheel_base_m, 1.0 / p.wheel_base_m
        q = self.noise_m_per_sqrt_m ** 2
        ql, qr = q * abs(s_l), q * abs(s_r)
        # Jp cov Jp^T (symmetric: the upper triangle).
        pxt, pyt = cxt + u * ctt, cyt + v * ctt
        nxx = cxx + u * cxt + u * pxt
        nxy = cxy + v * cxt + u * pyt
        nyy = cyy + v * cyt + v * pyt
        self._cov = (nxx + w00 * ql * w00 + w01 * qr * w01,
                     nxy + w00 * ql * w10 + w01 * qr * w11,
                     pxt + w00 * ql * w20 + w01 * qr * w21,
                     nyy + w10 * ql * w10 + w11 * qr * w11,
                     pyt + w10 * ql * w20 + w11 * qr * w21,
                     ctt + w20 * ql * w20 + w21 * qr * w21)
        # integrate_pose: the pose composed with the arc's chord at the midpoint heading.
        half = 0.5 * dth
        ix, iy = f * math.cos(half), f * math.sin(half)
        c0, s0 = math.cos(yaw0), math.sin(yaw0)
        self._pose = (x0 + c0 * ix - s0 * iy, y0 + s0 * ix + c0 * iy, wrap_angle(yaw0 + dth))
        self.distance_m += abs(ds)

    def pose(self) -> PoseStamped:
        """The current dead-reckoned pose (stamp 0 before the first message)."""
        return PoseStamped(
            stamp_ns=self._stamp_ns if self._stamp_ns is not None else 0,
            x_m=self._pose[0], y_m=self._pose[1], yaw_rad=wrap_angle(self._pose[2]),
            covariance=_symmetric3(self._cov),
        )
