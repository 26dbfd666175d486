"""Judging floor-loop candidates against ground-truth footprint overlap (paper 003 Sec. III-A).

Ground truth is J, the overlap of two keyframes' footprints from their true poses; a pair
is a loop when J >= r (r = 0.33 in the paper). Nothing here looks at images.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

from robotd.base.camera import FloorCameraModel, overlap_ratios


def overlap_matrix(camera: FloorCameraModel, poses: np.ndarray) -> np.ndarray:
    """``(N, N) float32`` J of every pair of poses ``(N, 3)``; symmetric, 1 on the diagonal.

    Only pairs whose centres are within the footprint's reach are intersected.
    """
    n = len(poses)
    i, j = np.tril_indices(n, -1)
    reach = camera.footprint_reach_m()
    near = np.hypot(poses[i, 0] - poses[j, 0], poses[i, 1] - poses[j, 1]) < reach
    out = np.zeros((n, n), np.float32)
    jj = overlap_ratios(camera, poses[i[near]], poses[j[near]])
    out[i[near], j[near]] = jj
    out[j[near], i[near]] = jj
    np.fill_diagonal(out, 1.0)
    return out


@dataclass(frozen=True)
class CandidateScore:
    """One returned candidate: query and candidate as row indices, its local score, true J."""

    query: int
    candidate: int
    local_score: float
    overlap: float


@dataclass(frozen=True)
class CandidateReport:
    """How the map queries did against ground truth.

    ``queries_with_true_loop``: queries for which some earlier, non-excluded keyframe has
    J >= r; ``found``: of those, how many had such a keyframe among their candidates;
    ``top1_true``/``top1_total``: top-1 candidates that are true loops, of all top-1s.
    """

    r: float
    queries: int
    queries_with_true_loop: int
    found: int
    top1_true: int
    top1_total: int
    candidates: list[CandidateScore]

    @property
    def recall(self) -> float:
        return self.found / self.queries_with_true_loop if self.queries_with_true_loop else float("nan")

    def precision_above(self, score: float) -> tuple[int, int]:
        """(true loops, all) among top-1 candidates whose local score is >= ``score``."""
        top1: dict[int, CandidateScore] = {}
        for c in self.candidates:
            if c.query not in top1 or c.local_score > top1[c.query].local_score:
                top1[c.query] = c
        sel = [c for c in top1.values() if c.local_score >= score]
        return sum(c.overlap >= self.r for c in sel), len(sel)


def candidate_report(overlap: np.ndarray, stamps_ns: np.ndarray,
                     queries: Iterable[tuple[int, Sequence[tuple[int, float]]]],
                     exclude_recent_s: float, r: float = 0.33) -> CandidateReport:
    """Score the queries' candidates.

    ``overlap`` is :func:`overlap_matrix` of the keyframes (row = keyframe index),
    ``stamps_ns (N,)`` their times, ``queries`` pairs of (query index, [(candidate index,
    local score), ...]); candidates younger than ``exclude_recent_s`` were not eligible.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    cands: list[CandidateScore] = []
    n_q = with_loop = found = top1_true = top1_total = 0
    for q, cs in queries:
        n_q += 1
        eligible = stamps < stamps[q] - int(exclude_recent_s * 1e9)
        true_loop = bool(np.any(overlap[q, eligible] >= r))
        with_loop += true_loop
        scored = [CandidateScore(q, c, float(s), float(overlap[q, c])) for c, s in cs]
        cands.extend(scored)
        if true_loop and any(c.overlap >= r for c in scored):
            found += 1
        if scored:
            best = max(scored, key=lambda c: c.local_score)
            top1_total += 1
            top1_true += best.overlap >= r
    return CandidateReport(r, n_q, with_loop, found, top1_true, top1_total, cands)
