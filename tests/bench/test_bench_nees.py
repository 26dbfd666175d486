"""bench_nees's split of the single edges at a start or a stop, on edges whose lag is known."""

from __future__ import annotations

import numpy as np
import pytest

from bench.bench_nees import speed_change_edges


def _straight_edges(speeds: np.ndarray, tau_s: float) -> dict:
    """Keyframes 5 cm apart on the x axis at ``speeds``; each edge measures its length
    short by ``tau_s`` times the speed gained over it (a pose trailing the truth by tau)."""
    n = len(speeds)
    truth = np.zeros((n, 3))
    truth[:, 0] = 0.05 * np.arange(n)
    dv = np.diff(speeds)
    delta = np.zeros((n - 1, 3))
    delta[:, 0] = 0.05 - tau_s * dv
    cov = np.tile(np.diag([1e-6, 1e-6, 1e-6]), (n - 1, 1, 1))
    return {"delta": delta, "cov": cov, "truth": truth, "speed_mps": speeds}


def test_the_lag_of_the_edges_across_a_speed_change_is_recovered():
    speeds = np.array([0.0, 0.2, 0.4, 0.4, 0.4, 0.4, 0.1, 0.0, 0.0])
    out = speed_change_edges(_straight_edges(speeds, tau_s=0.007))
    assert out["edges"] == 4 and out["others"] == 4  # |dv| 0.2, 0.2, 0.3, 0.1 against 0
    assert out["tau_ms"] == pytest.approx(7.0, rel=1e-9)
    assert out["others_nees"] == pytest.approx(0.0, abs=1e-12)
    # the errors are tau * dv = 1.4, 1.4, 2.1, 0.7 mm under a 1 mm sigma: NEES e^2 / 1e-6
    assert out["nees"] == pytest.approx(np.mean(np.square([1.4, 1.4, 2.1, 0.7])), rel=1e-6)
    assert out["nees_position"] == pytest.approx(out["nees"], rel=1e-9)


def test_a_leading_pose_gives_a_negative_lag():
    speeds = np.array([0.0, 0.3, 0.3, 0.0])
    assert speed_change_edges(_straight_edges(speeds, tau_s=-0.004))["tau_ms"] == pytest.approx(-4.0, rel=1e-9)
