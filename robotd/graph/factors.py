"""GTSAM factor graphs built from a :class:`~robotd.graph.model.PoseGraph` (keys are the
keyframe ids), the robust kernels of loop edges, and conversions of GTSAM values."""

from __future__ import annotations

from collections.abc import Collection
from typing import Literal

import gtsam
import numpy as np

from robotd.graph.model import Edge, PoseGraph

Kernel = Literal["dcs", "cauchy"]

# Prior standard deviation that pins the anchor vertices (m and rad): only the gauge.
ANCHOR_SIGMA = 1e-8


#: The loop-edge M-estimators of :func:`robust_kernel` (their ``weight(e)`` is the weight of
#: an edge at whitened error ``e``).
RobustKernel = gtsam.noiseModel.mEstimator.DCS | gtsam.noiseModel.mEstimator.Cauchy


def robust_kernel(kernel: Kernel, width_chi2: float) -> RobustKernel:
    """The loop-edge M-estimator. ``width_chi2`` is the edge chi2 (``e^T I e``) below which
    an edge keeps full weight: DCS's Phi (Agarwal et al., ICRA 2013, eq. 16), or the square
    of the Cauchy width."""
    if not width_chi2 > 0:
        raise ValueError(f"kernel width must be positive, got {width_chi2}")
    if kernel == "dcs":
        return gtsam.noiseModel.mEstimator.DCS.Create(float(width_chi2))
    if kernel == "cauchy":
        return gtsam.noiseModel.mEstimator.Cauchy.Create(float(np.sqrt(width_chi2)))
    raise ValueError(f"unknown kernel {kernel!r} (dcs or cauchy)")


def between_factor(edge: Edge, kernel: gtsam.noiseModel.mEstimator.Base | None = None,
                   diagonal: bool = False) -> gtsam.BetweenFactorPose2:
    """``BetweenFactor<Pose2>`` of one edge with its full information (or, ``diagonal``,
    the conditional standard deviations ``1 / sqrt(diag(I))``, as LAGO needs: the marginal
    ones blow up when x and y are strongly correlated, as in CSAIL), wrapped in ``kernel``
    if given."""
    model: gtsam.noiseModel.Base
    if diagonal:
        sigmas = 1.0 / np.sqrt(np.diag(edge.information))
        model = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    else:
        model = gtsam.noiseModel.Gaussian.Information(np.array(edge.information))
    if kernel is not None:
        model = gtsam.noiseModel.Robust.Create(kernel, model)
    d = edge.delta
    return gtsam.BetweenFactorPose2(edge.from_id, edge.to_id, gtsam.Pose2(d[0], d[1], d[2]), model)


def anchor_factor(keyframe_id: int, pose: np.ndarray) -> gtsam.PriorFactorPose2:
    """A tight prior holding ``keyframe_id`` at ``pose`` (the gauge, or a FIX vertex)."""
    return gtsam.PriorFactorPose2(int(keyframe_id), gtsam.Pose2(*map(float, pose)),
                                  gtsam.noiseModel.Isotropic.Sigma(3, ANCHOR_SIGMA))


def factor_graph(graph: PoseGraph, kernel: gtsam.noiseModel.mEstimator.Base | None = None,
                 diagonal: bool = False, skip: Collection[int] = ()) -> gtsam.NonlinearFactorGraph:
    """Every edge as a factor (loop edges through ``kernel`` when given; the edges whose
    indices are in ``skip`` left out), then the anchors."""
    fg = gtsam.NonlinearFactorGraph()
    for n, e in enumerate(graph.edges):
        if n in skip:
            continue
        fg.add(between_factor(e, kernel if e.kind == "loop" else None, diagonal))
    for kid in graph.anchors():
        fg.add(anchor_factor(kid, graph.pose(kid)))
    return fg


def to_values(ids: np.ndarray, poses: np.ndarray) -> gtsam.Values:
    """GTSAM values of ``poses (N, 3)`` keyed by ``ids (N,)``."""
    values = gtsam.Values()
    for kid, p in zip(ids, poses):
        values.insert(int(kid), gtsam.Pose2(float(p[0]), float(p[1]), float(p[2])))
    return values


def from_values(values: gtsam.Values, ids: np.ndarray) -> np.ndarray:
    """Poses ``(N, 3)`` of keys ``ids`` from GTSAM values."""
    out = np.empty((len(ids), 3))
    for n, kid in enumerate(ids):
        p = values.atPose2(int(kid))
        out[n] = (p.x(), p.y(), p.theta())
    return out
