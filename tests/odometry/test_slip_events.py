"""The slip events' rate and duration, estimated from the events a calibration drive's
heading windows see (robotd.odometry.slip_events)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from robotd.odometry.slip_events import SeenSlipEvents, SlipDrive, estimate_slip_events

B = 0.23
DT = 0.02
RATE, T_LO, T_HI, RHO_LO, RHO_HI = 0.3, 0.05, 0.3, 0.02, 0.08
TRIALS, SEED_BASE = 60, 1000


def _profile(seconds: float = 300.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A drive's mean wheel speed every 20 ms (m/s) and which readings are demanding: runs of
    a few seconds alternate between cruising (0.4 m/s, not demanding) and demanding driving
    at a speed drawn from 0.02-0.4 m/s (slow turns, starts, stops)."""
    rng = np.random.default_rng(seed)
    n = int(seconds / DT)
    speed = np.empty(n)
    demand = np.zeros(n, bool)
    k = 0
    while k < n:
        m = min(n, k + int(rng.uniform(1.0, 4.0) / DT))
        if rng.random() < 0.5:
            speed[k:m] = 0.4
        else:
            speed[k:m] = rng.uniform(0.02, 0.4)
            demand[k:m] = True
        k = m
    return np.arange(n + 1) * DT, np.concatenate([[0.0], np.cumsum(speed * DT)]), demand


def _synthetic(rng: np.random.Generator, t_s, travel_m, demand, threshold_rad: float):
    """Events at RATE a second of demanding driving, durations and slip ratios uniform, seen
    when the ratio times their largest travel in one 0.2 s window turns the heading by more
    than ``threshold_rad``; returns what the windows saw, the drive, and the true count
    and RMS duration."""
    starts_all = t_s[:-1][demand]
    drive = SlipDrive(demand_t_s=starts_all, demand_s=float(demand.sum()) * DT, travel_t_s=t_s,
                      travel_m=travel_m, window_edges_s=np.arange(0.0, t_s[-1] + 1e-9, 0.2),
                      threshold_rad=threshold_rad, wheel_base_m=B)
    n = int(rng.poisson(RATE * drive.demand_s))
    start = rng.choice(starts_all, n)
    dur = rng.uniform(T_LO, T_HI, n)
    rho = rng.uniform(RHO_LO, RHO_HI, n)
    seen = np.zeros(n, bool)
    for i in range(n):
        one = dataclasses.replace(drive, demand_t_s=np.array([start[i]]))
        seen[i] = rho[i] * float(one.max_window_travel(float(dur[i]))[0]) / B > threshold_rad
    jump = rho[seen] * (np.interp(start[seen] + dur[seen], t_s, travel_m)
                        - np.interp(start[seen], t_s, travel_m)) / B
    events = SeenSlipEvents(start[seen], dur[seen], jump, rho[seen])
    return events, drive, n, float(np.sqrt(np.mean(dur ** 2)))


def test_the_rate_and_duration_are_recovered_within_their_own_sigma():
    """Monte Carlo over synthetic drives where the gate misses about a third of the events
    (the slow and short ones): the estimate's error in its own bootstrap sigmas averages
    near 0 with a spread near 1, where the events seen alone would be far too few."""
    t_s, travel, demand = _profile()
    z_rate, z_dur, z_naive, missed = [], [], [], []
    for trial in range(TRIALS):
        rng = np.random.default_rng(SEED_BASE + trial)
        seen, drive, n_true, rms_true = _synthetic(rng, t_s, travel, demand, threshold_rad=3e-3)
        fit = estimate_slip_events(seen, drive, bootstrap=60, rng=np.random.default_rng(trial))
        assert not fit.refused
        z_rate.append((fit.rate_hz - RATE) / fit.rate_sigma_hz)
        z_dur.append((fit.duration_s - math.sqrt((T_HI ** 3 - T_LO ** 3) / (3 * (T_HI - T_LO)))) / fit.duration_sigma_s)
        z_naive.append((len(seen) / drive.demand_s - RATE) / fit.rate_sigma_hz)
        missed.append(1.0 - len(seen) / n_true)
    assert 0.15 < float(np.mean(missed)) < 0.4
    for z in (np.asarray(z_rate), np.asarray(z_dur)):
        assert abs(float(np.mean(z))) < 0.5, z
        assert 0.5 < float(np.sqrt(np.mean(z ** 2))) < 1.5, z
    assert float(np.mean(z_naive)) < -1.0  # the seen events alone: the rate too low by over a sigma


def test_too_few_events_are_refused_naming_them():
    t_s, travel, demand = _profile(60.0)
    seen, drive, _n, _rms = _synthetic(np.random.default_rng(3), t_s, travel, demand, threshold_rad=1.6e-3)
    assert 0 < len(seen) < 10
    fit = estimate_slip_events(seen, drive, min_events=10)
    assert fit.refused == f"{len(seen)} slip events seen (needs 10)"
    assert fit.rate_hz == 0.0 and fit.duration_s == 0.0 and fit.events_seen == len(seen)


def test_the_largest_part_in_one_window_is_the_travel_of_the_window_it_fills_most():
    t = np.array([0.0, 1.0])
    d = SlipDrive(np.array([0.1, 0.35]), 1.0, t, np.array([0.0, 1.0]), np.array([0.0, 0.2, 0.4, 0.6]), 1e-3, B)
    # 1 m/s: 0.1-0.4 s splits 0.1 / 0.2 (0.2 fills the second window); 0.35-0.65 s 0.05 / 0.2 / 0.05.
    assert d.max_window_travel(0.3) == pytest.approx([0.2, 0.2])
    assert d.max_window_travel(0.05) == pytest.approx([0.05, 0.05])
