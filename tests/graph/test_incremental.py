"""iSAM2 updates agree with the batch solver; a re-solve restarts from the batch result."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.base.errors import GraphError
from robotd.graph import BatchParams, IncrementalGraph, optimize_batch

INFO = np.diag([400.0, 400.0, 2500.0])


def _drive(inc: IncrementalGraph, n: int = 24, seed: int = 1) -> None:
    """A noisy ring of n keyframes, closing back on keyframe 0 and once across."""
    rng = np.random.default_rng(seed)
    step = 2 * math.pi / n
    chord = 2 * 5 * math.sin(step / 2)
    inc.add_first(100)
    for k in range(1, n):
        inc.add_keyframe(100 + 2 * k, 100 + 2 * (k - 1),
                         (chord + rng.normal(0, 0.05), rng.normal(0, 0.05), step + rng.normal(0, 0.02)),
                         INFO)
    inc.add_loop(100 + 2 * (n - 1), 100, (chord, 0.0, step), INFO)
    inc.add_loop(100 + 2 * (n // 4), 100 + 2 * (3 * n // 4), (0.0, 10.0, math.pi), INFO)


def test_incremental_matches_batch_on_a_small_graph():
    inc = IncrementalGraph()
    _drive(inc)
    batch = optimize_batch(inc.graph, BatchParams(robust=False))
    ids, poses = inc.estimate()
    assert np.array_equal(ids, batch.ids)
    assert np.allclose(poses[:, :2], batch.poses[:, :2], atol=5e-4)  # iSAM2 relinearises above 0.01
    assert np.allclose(np.cos(poses[:, 2] - batch.poses[:, 2]), 1.0, atol=1e-7)
    assert np.allclose(poses[0], 0.0)


def test_resolve_returns_the_batch_result_and_keeps_going():
    inc = IncrementalGraph()
    _drive(inc)
    result = inc.resolve()
    ids, poses = inc.estimate()
    assert np.allclose(poses, result.poses, atol=1e-4)  # one iSAM2 step past LM's stop
    last = inc.add_keyframe(999, int(ids[-1]), (1.0, 0.0, 0.0), INFO)
    assert np.allclose(last[:2], poses[-1, :2] + [math.cos(poses[-1, 2]), math.sin(poses[-1, 2])], atol=1e-6)


def test_odometry_from_an_unknown_keyframe_is_an_error():
    inc = IncrementalGraph()
    inc.add_first(0)
    with pytest.raises(GraphError, match="unknown keyframe 5"):
        inc.add_keyframe(6, 5, (1, 0, 0), INFO)
