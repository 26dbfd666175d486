"""Named routes for the virtual robot and the true motion along them.

A :class:`Route` is a polyline of waypoints (metres, world frame, REP-103) and a corner
style: ``"arc"`` rounds each corner with a clothoid-arc-clothoid curve (the curvature ramps
so that the angular acceleration stays within the limits) and keeps driving; ``"turn"``
stops at each corner and turns in place. Corners sharper than
``Route.max_arc_deflection_rad`` are always turned in place (a U-turn in a corridor).

:func:`plan_motion` turns a route into a :class:`Motion`: the true pose, speed and yaw
rate at a fixed time step, with a standstill at the start (the gyro bias calibration of
paper 003's robot, and of ours) and at the end. Speeds follow trapezoidal profiles within
:class:`MotionLimits`. The pose arrays are the exact integral of the per-step constant
``(v, w)``, so the wheel and gyro models derived from ``(v, w)`` agree with the ground
truth to rounding error.

Every route lies inside the bounding box of its waypoints (rounded corners cut inside
the corner, turns happen in place); :meth:`Route.bounds_m` returns it with a margin, and
the floor generator covers that box.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from robotd.base.errors import ConfigError
from robotd.base.geometry import compose, wrap_angle
from robotd.odometry.kinematics import arc_increment

__all__ = [
    "Motion",
    "kidnapped",
    "MotionLimits",
    "ROUTES",
    "Route",
    "RouteEntry",
    "build_route",
    "plan_motion",
]


@dataclass(frozen=True, slots=True)
class MotionLimits:
    """Kinematic limits of the planned motion (Turtlebot 2 defaults).

    ``v_max_mps``: forward speed, m/s (the Kobuki's rated maximum is 0.7; Turtlebot 2
    software limits it to 0.5). ``w_max_radps``: yaw rate, rad/s. ``a_max_mps2``: linear
    acceleration and deceleration, m/s^2. ``alpha_max_radps2``: angular acceleration,
    rad/s^2. Accelerations are kept below what the base can do, as a careful driver would.
    """

    v_max_mps: float = 0.5
    w_max_radps: float = 1.5
    a_max_mps2: float = 0.5
    alpha_max_radps2: float = 2.0

    def __post_init__(self) -> None:
        for name in ("v_max_mps", "w_max_radps", "a_max_mps2", "alpha_max_radps2"):
            value = getattr(self, name)
            if not (value > 0.0 and math.isfinite(value)):
                raise ValueError(f"{name} must be positive and finite, got {value!r}")


@dataclass(frozen=True)
class Route:
    """A polyline of waypoints and how to take its corners.

    ``waypoints_m``: ``((x, y), ...)`` metres; the robot starts at the first waypoint
    facing the second. ``corner``: ``"arc"`` or ``"turn"``. ``corner_radius_m``: radius of
    the circular part of a rounded corner. ``max_arc_deflection_rad``: corners turning more
    than this are turned in place even in ``"arc"`` style.
    """

    name: str
    waypoints_m: tuple[tuple[float, float], ...]
    corner: str = "arc"
    corner_radius_m: float = 0.5
    max_arc_deflection_rad: float = 2.0 * math.pi / 3.0
    description: str = ""

    def __post_init__(self) -> None:
        if self.corner not in ("arc", "turn"):
            raise ValueError(f"corner must be 'arc' or 'turn', got {self.corner!r}")
        pts = self.points()
        if pts.shape[0] < 2:
            raise ValueError("a route needs at least two waypoints")
        if np.any(np.linalg.norm(np.diff(pts, axis=0), axis=1) < 1e-9):
            raise ValueError(f"route {self.name!r} repeats a waypoint")

    def points(self) -> np.ndarray:
        """The waypoints as ``(N, 2) float64``, metres."""
        return np.asarray(self.waypoints_m, dtype=float).reshape(-1, 2)

    @property
    def polyline_length_m(self) -> float:
        """Length of the polyline through the waypoints (rounded corners make the path shorter)."""
        return float(np.linalg.norm(np.diff(self.points(), axis=0), axis=1).sum())

    def bounds_m(self, margin_m: float = 0.0) -> tuple[float, float, float, float]:
        """``(x_min, y_min, x_max, y_max)`` that contains the whole path, plus ``margin_m``.

        The robot's centre never leaves the waypoints' bounding box; add the robot's and
        the camera footprint's reach (about 0.5 m) as a margin when generating a floor.
        """
        p = self.points()
        lo, hi = p.min(axis=0) - margin_m, p.max(axis=0) + margin_m
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


@dataclass(frozen=True, eq=False)
class Motion:
    """The true motion at a fixed step ``dt_s``.

    All arrays are ``(N,) float64``: ``t_s`` seconds from the start; ``x_m``, ``y_m``,
    ``yaw_rad`` (wrapped to [-pi, pi)) the pose at ``t_s``; ``v_mps`` and ``w_radps`` the
    constant speed and yaw rate over ``[t_s[k], t_s[k] + dt_s)`` (zero in the last
    sample). ``yaw_unwrapped_rad`` is the continuous heading.
    """

    t_s: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    v_mps: np.ndarray
    w_radps: np.ndarray
    yaw_unwrapped_rad: np.ndarray
    dt_s: float
    route_name: str = ""
    lifted: np.ndarray | None = None
    """``(N,) bool``: the robot is off the floor over ``[t_s[k], t_s[k] + dt_s)`` (carried,
    :func:`kidnapped`); None: never."""

    @classmethod
    def from_velocities(cls, v_mps: np.ndarray, w_radps: np.ndarray, dt_s: float,
                        start_pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
                        route_name: str = "") -> Motion:
        """Integrate per-step constant ``(v, w)`` exactly from ``start_pose``.

        ``v_mps`` and ``w_radps`` (``(N,)``) hold over each step; the result has ``N + 1``
        samples, the last one at rest.
        """
        v = np.asarray(v_mps, dtype=float)
        w = np.asarray(w_radps, dtype=float)
        if v.shape != w.shape or v.ndim != 1:
            raise ValueError("v_mps and w_radps must be 1-D arrays of the same length")
        x0, y0, yaw0 = (float(a) for a in start_pose)
        n = v.shape[0]
        yaw = yaw0 + np.concatenate([[0.0], np.cumsum(w * dt_s)])
        inc = arc_increment(v * dt_s, w * dt_s)  # (n, 3), in each step's start frame
        c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
        dx = c * inc[:, 0] - s * inc[:, 1]
        dy = s * inc[:, 0] + c * inc[:, 1]
        x = x0 + np.concatenate([[0.0], np.cumsum(dx)])
        y = y0 + np.concatenate([[0.0], np.cumsum(dy)])
        return cls(
            t_s=np.arange(n + 1) * dt_s, x_m=x, y_m=y, yaw_rad=wrap_angle(yaw),
            v_mps=np.concatenate([v, [0.0]]), w_radps=np.concatenate([w, [0.0]]),
            yaw_unwrapped_rad=yaw, dt_s=float(dt_s), route_name=route_name,
        )

    @property
    def duration_s(self) -> float:
        """Time from the first to the last sample, seconds."""
        return float(self.t_s[-1] - self.t_s[0])

    @property
    def length_m(self) -> float:
        """Distance travelled by the base centre, metres."""
        return float(np.sum(np.abs(self.v_mps[:-1])) * self.dt_s)

    @property
    def poses(self) -> np.ndarray:
        """``(N, 3)`` true poses ``(x_m, y_m, yaw_rad)``."""
        return np.stack([self.x_m, self.y_m, self.yaw_rad], axis=-1)

    def truncated(self, duration_s: float) -> Motion:
        """The first ``duration_s`` seconds of the motion (the robot may still be moving)."""
        n = int(np.searchsorted(self.t_s, self.t_s[0] + duration_s, side="right"))
        n = max(1, n)
        return Motion(self.t_s[:n], self.x_m[:n], self.y_m[:n], self.yaw_rad[:n],
                      self.v_mps[:n], self.w_radps[:n], self.yaw_unwrapped_rad[:n],
                      self.dt_s, self.route_name, None if self.lifted is None else self.lifted[:n])

    def lifted_at(self, t_s: float | np.ndarray) -> bool | np.ndarray:
        """Whether the robot is off the floor at ``t_s`` (a bool, or ``(M,) bool``)."""
        if self.lifted is None:
            return np.zeros(np.shape(t_s), dtype=bool) if np.ndim(t_s) else False
        t = np.asarray(t_s, dtype=float)
        k = np.clip(np.floor((t - self.t_s[0]) / self.dt_s).astype(int), 0, len(self.t_s) - 1)
        out = self.lifted[k]
        return bool(out) if np.ndim(t_s) == 0 else out

    def velocity_at(self, t_s: float) -> tuple[float, float]:
        """``(v_mps, w_radps)`` of the step that contains ``t_s`` (zero past the end)."""
        if t_s < self.t_s[0] or t_s >= self.t_s[-1]:
            return 0.0, 0.0
        k = min(int((t_s - self.t_s[0]) / self.dt_s), len(self.t_s) - 1)
        return float(self.v_mps[k]), float(self.w_radps[k])

    def poses_at(self, t_s: np.ndarray) -> np.ndarray:
        """``(M, 3)`` true poses at the times ``t_s`` ``(M,)``; see :meth:`pose_at`."""
        return np.asarray(self.pose_at(np.atleast_1d(np.asarray(t_s, dtype=float)))).reshape(-1, 3)

    def pose_at(self, t_s: float | np.ndarray) -> np.ndarray:
        """True pose at ``t_s`` (clamped to the motion's span): ``(3,)`` or ``(M, 3)``.

        Between samples the step's constant ``(v, w)`` is integrated exactly from the
        sample before, so the yaw moves along the circle (through +-pi when it must).
        """
        t = np.clip(np.asarray(t_s, dtype=float), self.t_s[0], self.t_s[-1])
        k = np.clip(np.floor((t - self.t_s[0]) / self.dt_s).astype(int), 0, len(self.t_s) - 1)
        tau = t - self.t_s[k]
        start = np.stack([self.x_m[k], self.y_m[k], self.yaw_unwrapped_rad[k]], axis=-1)
        return compose(start, arc_increment(self.v_mps[k] * tau, self.w_radps[k] * tau))


def kidnapped(motion: Motion, at_s: float, to_s: float, carry_s: float = 5.0) -> Motion:
    """``motion`` with a kidnapping: at ``at_s`` the robot is lifted and held where it was
    for ``carry_s`` (wheels still, :attr:`Motion.lifted` set), then put down at the pose
    ``motion`` has at ``to_s`` and drives on from there to the end (at the speed the motion
    has there). Times after the lift are shifted by ``carry_s - (to_s - at_s)``.
    ValueError unless ``0 < at_s`` and both times lie inside the motion, ``carry_s > 0``."""
    dt = motion.dt_s
    end = float(motion.t_s[-1])
    if not (0.0 < at_s < end and 0.0 <= to_s < end and carry_s > 0.0):
        raise ValueError(f"a kidnapping at {at_s} s to {to_s} s (carried {carry_s} s) does not fit a "
                         f"motion of {end:.1f} s")
    i_at = int(round((at_s - motion.t_s[0]) / dt))
    i_to = int(round((to_s - motion.t_s[0]) / dt))
    n_carry = max(1, int(round(carry_s / dt)))
    keep_a, keep_b = slice(0, i_at), slice(i_to, len(motion.t_s))
    hold = np.full(n_carry, 1.0)

    def join(a: np.ndarray, held: float, b: np.ndarray) -> np.ndarray:
        return np.concatenate([a[keep_a], held * hold, b[keep_b]])

    n = i_at + n_carry + (len(motion.t_s) - i_to)
    lifted = np.zeros(n, dtype=bool)
    lifted[i_at:i_at + n_carry] = True
    if motion.lifted is not None:
        lifted[:i_at] |= motion.lifted[keep_a]
        lifted[i_at + n_carry:] |= motion.lifted[keep_b]
    return Motion(
        t_s=motion.t_s[0] + np.arange(n) * dt,
        x_m=join(motion.x_m, motion.x_m[i_at], motion.x_m),
        y_m=join(motion.y_m, motion.y_m[i_at], motion.y_m),
        yaw_rad=join(motion.yaw_rad, motion.yaw_rad[i_at], motion.yaw_rad),
        v_mps=join(motion.v_mps, 0.0, motion.v_mps),
        w_radps=join(motion.w_radps, 0.0, motion.w_radps),
        yaw_unwrapped_rad=join(motion.yaw_unwrapped_rad, motion.yaw_unwrapped_rad[i_at],
                               motion.yaw_unwrapped_rad),
        dt_s=dt, route_name=motion.route_name, lifted=lifted)


# --------------------------------------------------------------------------------------
# Motion primitives. Each gives distance and heading change as functions of the time
# since its own start; plan_motion samples them on one global grid.
# --------------------------------------------------------------------------------------


class _Piece(Protocol):
    duration_s: float
    distance_m: float
    heading_rad: float

    def distance(self, tau: np.ndarray) -> np.ndarray: ...

    def heading(self, tau: np.ndarray) -> np.ndarray: ...


@dataclass
class _Stand:
    duration_s: float
    distance_m: float = 0.0
    heading_rad: float = 0.0

    def distance(self, tau: np.ndarray) -> np.ndarray:
        return np.zeros_like(tau)

    def heading(self, tau: np.ndarray) -> np.ndarray:
        return np.zeros_like(tau)


@dataclass
class _Spin:
    """Turn in place by ``angle_rad`` with a trapezoidal (or triangular) yaw-rate profile."""

    angle_rad: float
    w_max: float
    alpha_max: float
    duration_s: float = field(init=False)
    distance_m: float = 0.0
    heading_rad: float = field(init=False)

    def __post_init__(self) -> None:
        phi = abs(self.angle_rad)
        if phi >= self.w_max ** 2 / self.alpha_max:
            self._ta = self.w_max / self.alpha_max
            self._tc = (phi - self.w_max ** 2 / self.alpha_max) / self.w_max
        else:
            self._ta = math.sqrt(phi / self.alpha_max)
            self._tc = 0.0
        self._wp = self.alpha_max * self._ta
        self.duration_s = 2.0 * self._ta + self._tc
        self.heading_rad = self.angle_rad

    def distance(self, tau: np.ndarray) -> np.ndarray:
        return np.zeros_like(tau)

    def heading(self, tau: np.ndarray) -> np.ndarray:
        a, ta, tc, total = self.alpha_max, self._ta, self._tc, self.duration_s
        tau = np.clip(tau, 0.0, total)
        up = 0.5 * a * tau ** 2
        cruise = 0.5 * a * ta ** 2 + self._wp * (tau - ta)
        down = abs(self.angle_rad) - 0.5 * a * (total - tau) ** 2
        out = np.where(tau < ta, up, np.where(tau < ta + tc, cruise, down))
        return math.copysign(1.0, self.angle_rad) * out


@dataclass
class _Element:
    """A path element with curvature varying linearly from ``k0`` to ``k1`` (1/m)."""

    length_m: float
    k0: float
    k1: float
    v_lim: float


class _Drive:
    """Drive along a chain of elements from standstill to standstill.

    The speed profile is trapezoidal along the path: accelerate at ``a_max``, cruise at
    the element's speed limit, brake at ``a_max`` before slower elements and the stop.
    """

    def __init__(self, elements: list[_Element], a_max: float, ds_m: float = 0.002) -> None:
        s_nodes, k_nodes, vlim_nodes = [0.0], [elements[0].k0], [0.0]
        for el in elements:
            n = max(1, math.ceil(el.length_m / ds_m))
            u = np.linspace(0.0, el.length_m, n + 1)[1:]
            s0 = s_nodes[-1]
            vlim_nodes[-1] = min(vlim_nodes[-1], el.v_lim) if len(s_nodes) > 1 else 0.0
            s_nodes.extend((s0 + u).tolist())
            k_nodes.extend((el.k0 + (el.k1 - el.k0) * u / el.length_m).tolist())
            vlim_nodes.extend([el.v_lim] * n)
        s = np.asarray(s_nodes)
        k = np.asarray(k_nodes)
        vlim = np.asarray(vlim_nodes)
        vlim[-1] = 0.0
        h = np.diff(s)
        # Heading at the nodes: curvature is linear within each interval.
        dk = np.diff(k)
        theta = np.concatenate([[0.0], np.cumsum(k[:-1] * h + 0.5 * dk * h)])
        # Forward then backward pass of the trapezoidal speed profile.
        v = vlim.copy()
        v[0] = 0.0
        for i in range(len(h)):
            v[i + 1] = min(v[i + 1], math.sqrt(v[i] ** 2 + 2.0 * a_max * h[i]))
        for i in range(len(h) - 1, -1, -1):
            v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2.0 * a_max * h[i]))
        dt = 2.0 * h / (v[:-1] + v[1:])
        self._s, self._k, self._theta, self._v = s, k, theta, v
        self._h = h
        self._acc = (v[1:] ** 2 - v[:-1] ** 2) / (2.0 * h)
        self._t = np.concatenate([[0.0], np.cumsum(dt)])
        self.duration_s = float(self._t[-1])
        self.distance_m = float(s[-1])
        self.heading_rad = float(theta[-1])

    def distance(self, tau: np.ndarray) -> np.ndarray:
        i = np.clip(np.searchsorted(self._t, tau, side="right") - 1, 0, len(self._h) - 1)
        u = np.clip(tau - self._t[i], 0.0, None)
        s = self._s[i] + self._v[i] * u + 0.5 * self._acc[i] * u ** 2
        return np.clip(s, self._s[i], self._s[i + 1])

    def heading(self, tau: np.ndarray) -> np.ndarray:
        return self.heading_of_s(self.distance(tau))

    def heading_of_s(self, s: np.ndarray) -> np.ndarray:
        i = np.clip(np.searchsorted(self._s, s, side="right") - 1, 0, len(self._h) - 1)
        u = s - self._s[i]
        dk = (self._k[i + 1] - self._k[i]) / self._h[i]
        return self._theta[i] + self._k[i] * u + 0.5 * dk * u ** 2


def _corner(phi: float, radius_m: float, transition_m: float, v_lim: float
            ) -> tuple[list[_Element], float]:
    """A symmetric clothoid-arc-clothoid turning by ``phi``; returns elements and tangent length.

    The curve leaves the incoming line ``T`` before the corner vertex and joins the
    outgoing line ``T`` after it (symmetry about the bisector), so
    ``T = Y / sin(phi)`` with ``Y`` the curve's lateral displacement.
    """
    sign = math.copysign(1.0, phi)
    big = abs(phi)
    if big >= transition_m / radius_m:
        kappa = sign / radius_m
        arc = radius_m * (big - transition_m / radius_m)
        elements = [_Element(transition_m, 0.0, kappa, v_lim)]
        if arc > 1e-9:
            elements.append(_Element(arc, kappa, kappa, v_lim))
        elements.append(_Element(transition_m, kappa, 0.0, v_lim))
    else:
        kappa = sign * big / transition_m
        elements = [_Element(transition_m, 0.0, kappa, v_lim),
                    _Element(transition_m, kappa, 0.0, v_lim)]
    # Lateral displacement by quadrature of the exact (piecewise quadratic) heading.
    y, theta0 = 0.0, 0.0
    for el in elements:
        u = np.linspace(0.0, el.length_m, 4001)
        th = theta0 + el.k0 * u + 0.5 * (el.k1 - el.k0) / el.length_m * u ** 2
        y += float(np.trapezoid(np.sin(th), u))
        theta0 = float(th[-1])
    return elements, y / math.sin(phi)


def _pieces(route: Route, limits: MotionLimits) -> list[_Piece]:
    pts = route.points()
    seg = np.diff(pts, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    seg_dir = np.arctan2(seg[:, 1], seg[:, 0])
    radius = route.corner_radius_m
    v_corner = min(limits.v_max_mps, 0.75 * limits.w_max_radps * radius)
    # Curvature ramp long enough that v^2 * dkappa/ds uses at most half the angular
    # acceleration budget; the other half covers a * kappa when speeding up in a corner.
    transition = v_corner ** 2 / (radius * 0.5 * limits.alpha_max_radps2)

    n_seg = len(seg_len)
    # Per vertex between segments i-1 and i: a corner (elements, T) or a spin angle.
    corners: dict[int, tuple[list[_Element], float]] = {}
    spins: dict[int, float] = {}
    for i in range(1, n_seg):
        phi = float(wrap_angle(seg_dir[i] - seg_dir[i - 1]))
        if abs(phi) >= math.pi - 1e-9:
            phi = math.pi  # a U-turn: turn left
        if abs(phi) < 1e-9:
            continue
        if route.corner == "turn" or abs(phi) > route.max_arc_deflection_rad:
            spins[i] = phi
        else:
            corners[i] = _corner(phi, radius, transition, v_corner)

    pieces: list[_Piece] = []
    elements: list[_Element] = []
    for i in range(n_seg):
        t_in = corners[i][1] if i in corners else 0.0
        t_out = corners[i + 1][1] if (i + 1) in corners else 0.0
        straight = seg_len[i] - t_in - t_out
        if straight < -1e-9:
            raise ValueError(
                f"route {route.name!r}: segment {i} ({seg_len[i]:.2f} m) is too short for "
                f"its rounded corners ({t_in + t_out:.2f} m); use a smaller corner radius")
        if straight > 1e-9:
            elements.append(_Element(straight, 0.0, 0.0, limits.v_max_mps))
        if (i + 1) in corners:
            elements.extend(corners[i + 1][0])
        if (i + 1) in spins or i == n_seg - 1:
            pieces.append(_Drive(elements, limits.a_max_mps2))
            elements = []
            if (i + 1) in spins:
                pieces.append(_Spin(spins[i + 1], limits.w_max_radps, limits.alpha_max_radps2))
    return pieces


def plan_motion(route: Route, limits: MotionLimits = MotionLimits(), dt_s: float = 0.002,
                standstill_s: float = 2.0) -> Motion:
    """The true motion along ``route``: standstill, drive, standstill, sampled every ``dt_s``.

    The robot starts at the first waypoint facing the second. Straights are driven at
    ``v_max_mps``; rounded corners at ``min(v_max, 0.75 * w_max * radius)``; turns in place
    at ``w_max_radps``; every change of speed or yaw rate is a ramp at ``a_max_mps2`` or
    ``alpha_max_radps2`` at most. The per-step ``(v, w)`` are the exact averages of the
    continuous profile over each step, and the poses are their exact integral.
    """
    if dt_s <= 0.0 or standstill_s < 0.0:
        raise ValueError("dt_s must be > 0 and standstill_s >= 0")
    pieces: list[_Piece] = [_Stand(standstill_s), *_pieces(route, limits), _Stand(standstill_s)]
    starts = np.concatenate([[0.0], np.cumsum([p.duration_s for p in pieces])])
    total = float(starts[-1])
    n_steps = math.ceil(total / dt_s - 1e-9)
    t = np.arange(n_steps + 1) * dt_s
    dist = np.full(t.shape, sum(p.distance_m for p in pieces))
    head = np.full(t.shape, sum(p.heading_rad for p in pieces))
    d0 = h0 = 0.0
    for p, t0, t1 in zip(pieces, starts[:-1], starts[1:]):
        sel = (t >= t0) & (t < t1)
        if np.any(sel):
            dist[sel] = d0 + p.distance(t[sel] - t0)
            head[sel] = h0 + p.heading(t[sel] - t0)
        d0 += p.distance_m
        h0 += p.heading_rad
    v = np.diff(dist) / dt_s
    w = np.diff(head) / dt_s
    pts = route.points()
    d = pts[1] - pts[0]
    start = (float(pts[0, 0]), float(pts[0, 1]), math.atan2(d[1], d[0]))
    return Motion.from_velocities(v, w, dt_s, start, route_name=route.name)


# --------------------------------------------------------------------------------------
# The named routes.
# --------------------------------------------------------------------------------------


def _office() -> Route:
    # A 10 x 6 m office floor: a corridor runs round the outside, a 3.5 x 3.5 m room sits in
    # the south-west corner, and a cross corridor at x = 5 m. Driven: the corridor loop
    # counter-clockwise, the room counter-clockwise, a U-turn, the room clockwise, the
    # corridor clockwise, a U-turn, then the west half (via the cross corridor)
    # counter-clockwise back to the start. Every loop is seen in both directions, and the
    # room's south wall also in the same direction as the corridor's.
    w, h, r = 10.0, 6.0, 3.5
    pts = [
        (0.0, 0.0), (w, 0.0), (w, h), (0.0, h), (0.0, 0.0),      # corridor loop, ccw
        (r, 0.0), (r, r), (0.0, r), (0.0, 0.0),                   # room loop, ccw
        (0.0, r), (r, r), (r, 0.0), (0.0, 0.0),                   # U-turn, room loop, cw
        (0.0, h), (w, h), (w, 0.0), (0.0, 0.0),                   # corridor loop, cw
        (5.0, 0.0), (5.0, h), (0.0, h), (0.0, 0.0),               # U-turn, west loop, ccw
    ]
    return Route("office", tuple(pts), corner="arc", corner_radius_m=0.5,
                 description=ROUTES["office"].description)


def _square() -> Route:
    pts = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)] * 2 + [(0.0, 0.0)]
    return Route("square", tuple(pts), corner="turn", description=ROUTES["square"].description)


def _figure8() -> Route:
    pts = [(0.0, 0.0), (2.0, 2.0), (4.0, 2.0), (4.0, -2.0), (2.0, -2.0), (0.0, 0.0),
           (-2.0, 2.0), (-4.0, 2.0), (-4.0, -2.0), (-2.0, -2.0), (0.0, 0.0)]
    return Route("figure8", tuple(pts), corner="arc", corner_radius_m=0.5,
                 description=ROUTES["figure8"].description)


#: Laps of the figure eight in the calibration drive (:func:`_calibration`).
CALIBRATION_LAPS = 4


def _calibration() -> Route:
    # The figure eight driven CALIBRATION_LAPS times without stopping: the turns both ways
    # and the straights that the odometry model needs (robotd calibrate odometry; one
    # figure eight pins the wheel base to about 0.1 % only), and the revisits the loop
    # curve learns from (robotd calibrate loop-curve trains no mode on one).
    pts = list(_figure8().waypoints_m)
    return Route("calibration", tuple(pts + pts[1:] * (CALIBRATION_LAPS - 1)), corner="arc",
                 corner_radius_m=0.5, description=ROUTES["calibration"].description)


def _straight() -> Route:
    return Route("straight", ((0.0, 0.0), (10.0, 0.0)), corner="turn",
                 description=ROUTES["straight"].description)


def _corridor() -> Route:
    return Route("corridor", ((0.0, 0.0), (8.0, 0.0), (0.0, 0.0)), corner="turn",
                 description=ROUTES["corridor"].description)


@dataclass(frozen=True)
class RouteEntry:
    """A named route's builder and its one-line description."""

    build: Callable[[], Route]
    description: str


ROUTES: dict[str, RouteEntry] = {
    "office": RouteEntry(_office, "about 110 m in a 10 x 6 m office: corridor and room loops, "
                                  "each driven both ways, back to the start (paper 003 Sec. V)"),
    "square": RouteEntry(_square, "a 2 m square driven twice counter-clockwise, turning in "
                                  "place (16 m)"),
    "figure8": RouteEntry(_figure8, "a figure eight of two 4 x 4 m loops, one each way, "
                                    "rounded corners"),
    "calibration": RouteEntry(_calibration, "the figure eight driven four times (about 100 m): a "
                                            "calibration drive for the loop curve and the odometry model"),
    "straight": RouteEntry(_straight, "10 m straight ahead (paper 003 Sec. IV-A similarity "
                                      "matrices)"),
    "corridor": RouteEntry(_corridor, "8 m down a corridor, a U-turn in place, and back (16 m)"),
}


def build_route(name: str) -> Route:
    """The named route; an unknown name is a :class:`~robotd.base.errors.ConfigError`."""
    try:
        entry = ROUTES[name]
    except KeyError:
        raise ConfigError(f"unknown route {name!r}; known: {', '.join(sorted(ROUTES))}") from None
    return entry.build()


#: Another name for :func:`build_route`.
