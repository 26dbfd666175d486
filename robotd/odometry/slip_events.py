"""The wheel slip events of a calibration drive: their rate and duration.

A slip event is one wheel losing grip for a moment: its surface runs ahead of the floor
(spinning up) or behind it (skidding) by a fraction of its own motion, its slip ratio
``rho``, for a duration ``T`` of tenths of a second. It happens where the wheel's grip is
asked for more than rolling, while the base accelerates, brakes or turns. The wheels'
heading then departs from the (calibrated) gyro's by ``rho d / B`` over the event (``d``
the wheel's travel over it, ``B`` the wheel base). The filter's model of the events
(:func:`robotd.odometry.ekf.sub_gate_slip_variances`) needs their rate ``r`` a second of
such driving and their RMS duration; this module estimates both from the drive's heading
windows (:func:`robotd.odometry.calibration.fit_odometry`), which see an event when its
jump in one window exceeds the windows' gate.

What the windows miss. The ratio is a property of the tyre on the floor under that
traction demand, not of how far the wheel rolls, so its distribution is the same at every
speed; the heading jump is the ratio times the travel, so the events the gate misses are
those over little travel (slow, short, or split between two windows), which the drive's
own speed profile says how often to expect. The ratio is taken uniform over the range the
seen events span (widened by one expected spacing of ``n`` uniform draws at each end:
nothing seen favours one ratio over another inside it; below the lowest seen the wheels'
continuous slip, :mod:`robotd.odometry.calibration`'s density, takes over). An event of
duration ``T`` starting at a moment of demanding driving ``t`` is seen when ``rho`` times
the largest part of its travel in one window exceeds the gate's heading over ``B``; the
probability ``p(T)`` averages that over the drive's demanding moments (events start
anywhere in them, the model's rate). Each seen event then stands for ``1 / p(T_i)``
events (Horvitz and Thompson 1952): the rate is ``sum 1 / p_i`` over the demanding time,
the mean square duration ``sum T_i^2 / p_i / sum 1 / p_i`` (long events are seen more
often, and this undoes it). Uncertainties by the bootstrap: the count drawn Poisson, the
events drawn again, the whole estimate (the ratio's range included) made again.

Not modelled: two events within one event's span are seen as one longer event (the rate
low and the duration long by about the rate times the duration), and the travel is the
wheels' mean where one wheel slips (on an arc the inner wheel travels less).

No I/O here.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "SeenSlipEvents",
    "SlipDrive",
    "SlipEventFit",
    "estimate_slip_events",
    "find_slip_events",
]


@dataclass(frozen=True, slots=True, eq=False)
class SeenSlipEvents:
    """The slip events the heading windows saw (``(n,)`` arrays each).

    start_s: the event's start, s (the drive's time base); duration_s: its length, s;
    jump_rad: the wheels' heading against the gyro's over it (rad, signed); ratio: its
    slip ratio, ``|jump| B / travel`` (dimensionless; travel: the wheels' mean travel over
    the event, m)."""

    start_s: np.ndarray
    duration_s: np.ndarray
    jump_rad: np.ndarray
    ratio: np.ndarray

    def __len__(self) -> int:
        return len(self.duration_s)


@dataclass(frozen=True, slots=True, eq=False)
class SlipDrive:
    """What the detection model needs of the drive.

    demand_t_s ``(M,)``: the moments (s) of demanding driving an event may start at (the
    wheel readings the filter's slip test calls accelerating or turning); demand_s: their
    total time (s); travel_t_s ``(N,)``, travel_m ``(N,)``: the wheels' mean travel from the
    drive's start (m, non-decreasing) at those times; window_edges_s ``(K+1,)``: the heading
    windows' edges (s, increasing); threshold_rad: the windows' gate in heading (rad);
    wheel_base_m: m."""

    demand_t_s: np.ndarray
    demand_s: float
    travel_t_s: np.ndarray
    travel_m: np.ndarray
    window_edges_s: np.ndarray
    threshold_rad: float
    wheel_base_m: float

    def max_window_travel(self, duration_s: float) -> np.ndarray:
        """``(M,)``: for an event of ``duration_s`` starting at each demanding moment, the
        largest part of the wheels' travel over it (m) that falls in one window."""
        t0 = np.asarray(self.demand_t_s, float)
        t1 = t0 + duration_s
        edges = np.asarray(self.window_edges_s, float)
        k0 = np.clip(np.searchsorted(edges, t0, side="right") - 1, 0, len(edges) - 2)
        best = np.zeros(len(t0))
        k = k0.copy()
        lo = t0
        while True:
            hi = np.minimum(t1, edges[np.minimum(k + 1, len(edges) - 1)])
            part = (np.interp(hi, self.travel_t_s, self.travel_m)
                    - np.interp(lo, self.travel_t_s, self.travel_m))
            best = np.maximum(best, np.where(hi > lo, part, 0.0))
            more = (hi < t1) & (k + 1 < len(edges) - 1)
            if not more.any():
                return best
            k = np.where(more, k + 1, k)
            lo = np.where(more, hi, t1)


@dataclass(frozen=True, slots=True)
class SlipEventFit:
    """The slip events' rate and duration, with their 1-sigma (bootstrap).

    rate_hz: events a second of demanding driving, all of them (those the windows missed
    included); duration_s: their RMS duration (s); events_seen: the events the windows
    saw; events_estimated: all the drive held, by the model (``rate_hz * demand_s``);
    demand_s: the drive's time of demanding driving (s); ratio_lo, ratio_hi: the slip
    ratio's range the model takes; refused: why no estimate was made ("" when made; the
    numbers then 0)."""

    rate_hz: float
    rate_sigma_hz: float
    duration_s: float
    duration_sigma_s: float
    events_seen: int
    events_estimated: float
    demand_s: float
    ratio_lo: float
    ratio_hi: float
    refused: str = ""


def _ramp_fit(t_s: np.ndarray, c: np.ndarray) -> tuple[int, int]:
    """The indices ``(a, b)``, ``a < b``, of the flat-ramp-flat curve (level before ``a``,
    linear from ``a`` to ``b``, level after) nearest ``c`` ``(n,)`` in least squares."""
    n = len(c)
    a, b = np.triu_indices(n, 1)
    span = t_s[b] - t_s[a]
    ramp = np.clip((t_s[None, :] - t_s[a, None]) / span[:, None], 0.0, 1.0)  # (P, n)
    f0, f1 = 1.0 - ramp, ramp
    s00, s01, s11 = (f0 * f0).sum(1), (f0 * f1).sum(1), (f1 * f1).sum(1)
    y0, y1 = f0 @ c, f1 @ c
    det = s00 * s11 - s01 * s01
    c0 = (s11 * y0 - s01 * y1) / det
    c1 = (s00 * y1 - s01 * y0) / det
    sse = ((c[None, :] - c0[:, None] * f0 - c1[:, None] * f1) ** 2).sum(1)
    i = int(np.argmin(sse))
    return int(a[i]), int(b[i])


def find_slip_events(window_t0_s: np.ndarray, window_t1_s: np.ndarray, flagged: np.ndarray,
                     t_s: np.ndarray, heading_residual_rad: np.ndarray, travel_m: np.ndarray,
                     wheel_base_m: float) -> SeenSlipEvents:
    """The events behind the flagged heading windows.

    ``window_t0_s``, ``window_t1_s`` ``(K,)``: the windows' spans (s); ``flagged`` ``(K,)``
    bool: those whose heading residual passed the gate; ``t_s`` ``(N,)``: the wheel
    readings' times (s), ``heading_residual_rad`` ``(N,)`` the wheels' heading minus the
    calibrated gyro's at them (rad, cumulative), ``travel_m`` ``(N,)`` the wheels' mean
    travel (m, cumulative). A run of flagged windows that touch is one event; over the run
    and one window either side the residual is fitted by a level, a ramp and a level
    (:func:`_ramp_fit`): the ramp is the event, its rise the jump."""
    starts, durations, jumps, ratios = [], [], [], []
    k = 0
    n = len(flagged)
    while k < n:
        if not flagged[k]:
            k += 1
            continue
        m = k
        while m + 1 < n and flagged[m + 1] and abs(window_t0_s[m + 1] - window_t1_s[m]) < 1e-9:
            m += 1
        w = window_t1_s[k] - window_t0_s[k]
        lo, hi = window_t0_s[k] - w, window_t1_s[m] + w
        sel = np.flatnonzero((t_s >= lo - 1e-9) & (t_s <= hi + 1e-9))
        k = m + 1
        if len(sel) < 3:
            continue
        a, b = _ramp_fit(t_s[sel], heading_residual_rad[sel])
        ia, ib = sel[a], sel[b]
        jump = float(heading_residual_rad[ib] - heading_residual_rad[ia])
        travel = float(travel_m[ib] - travel_m[ia])
        if travel <= 0.0:
            continue
        starts.append(float(t_s[ia]))
        durations.append(float(t_s[ib] - t_s[ia]))
        jumps.append(jump)
        ratios.append(abs(jump) * wheel_base_m / travel)
    return SeenSlipEvents(np.asarray(starts), np.asarray(durations), np.asarray(jumps), np.asarray(ratios))


def _ratio_range(ratio: np.ndarray) -> tuple[float, float]:
    """The uniform range behind ``n`` draws: their extremes widened by one expected spacing
    ``(max - min) / (n - 1)`` at each end (the extremes of ``n`` uniform draws fall that far
    inside it on average)."""
    lo, hi = float(ratio.min()), float(ratio.max())
    pad = (hi - lo) / max(len(ratio) - 1, 1)
    return max(lo - pad, 0.0), hi + pad


def _seen_probability(parts: np.ndarray, lo: float, hi: float, threshold_rad: float,
                      wheel_base_m: float) -> np.ndarray:
    """``(n,)``: each event's chance to be seen, its ratio uniform on ``[lo, hi]``, from
    ``parts`` ``(n, M)`` (:meth:`SlipDrive.max_window_travel` per event)."""
    need = threshold_rad * wheel_base_m / np.maximum(parts, 1e-12)  # the ratio it takes
    if hi <= lo:
        return (need < hi).mean(axis=1)
    return np.clip((hi - need) / (hi - lo), 0.0, 1.0).mean(axis=1)


def _estimate(duration_s: np.ndarray, ratio: np.ndarray, parts: np.ndarray,
              drive: SlipDrive) -> tuple[float, float, float, float, float]:
    lo, hi = _ratio_range(ratio)
    p = np.maximum(_seen_probability(parts, lo, hi, drive.threshold_rad, drive.wheel_base_m), 1e-3)
    weight = 1.0 / p
    n_all = float(weight.sum())
    return (n_all / drive.demand_s, math.sqrt(float((weight * duration_s ** 2).sum()) / n_all),
            n_all, lo, hi)


def estimate_slip_events(seen: SeenSlipEvents, drive: SlipDrive, min_events: int = 10,
                         bootstrap: int = 200, rng: np.random.Generator | None = None,
                         max_moments: int = 2000) -> SlipEventFit:
    """The events' rate (a second of ``drive.demand_s``) and RMS duration from the ``seen``
    ones (see the module notes), with their bootstrap 1-sigma (``bootstrap`` draws;
    ``rng``: the bootstrap's generator, seeded 0 when not given; at most ``max_moments``
    of the drive's demanding moments, evenly spread, stand for them all). Fewer than
    ``min_events`` seen, or no demanding time: refused (:attr:`SlipEventFit.refused`)."""
    n = len(seen)
    if n < min_events or drive.demand_s <= 0.0:
        why = (f"{n} slip events seen (needs {min_events})" if n < min_events
               else "no accelerating or turning")
        return SlipEventFit(0.0, 0.0, 0.0, 0.0, n, 0.0, float(drive.demand_s), 0.0, 0.0, refused=why)
    rng = np.random.default_rng(0) if rng is None else rng
    if len(drive.demand_t_s) > max_moments:  # an even subsample stands for them all
        pick = np.linspace(0, len(drive.demand_t_s) - 1, max_moments).round().astype(int)
        drive = dataclasses.replace(drive, demand_t_s=np.asarray(drive.demand_t_s)[pick])
    dur = np.asarray(seen.duration_s, float)
    ratio = np.asarray(seen.ratio, float)
    # The events' travel per window is the drive's; only the duration picks which.
    parts = np.stack([drive.max_window_travel(float(t)) for t in dur])
    rate, rms, n_all, lo, hi = _estimate(dur, ratio, parts, drive)
    rates, rmss = [], []
    for _ in range(bootstrap):
        m = int(rng.poisson(n))
        if m < 2:
            continue
        idx = rng.integers(0, n, m)
        r_b, t_b, *_ = _estimate(dur[idx], ratio[idx], parts[idx], drive)
        rates.append(r_b)
        rmss.append(t_b)
    return SlipEventFit(rate_hz=rate, rate_sigma_hz=float(np.std(rates, ddof=1)), duration_s=rms,
                        duration_sigma_s=float(np.std(rmss, ddof=1)), events_seen=n, events_estimated=n_all,
                        demand_s=float(drive.demand_s), ratio_lo=lo, ratio_hi=hi)
