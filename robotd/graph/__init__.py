"""The pose graph (algorithm layer, no I/O): SE(2) keyframe poses, odometry and loop edges,
batch optimisation (LAGO then robust Levenberg-Marquardt) and incremental iSAM2 updates."""

from robotd.graph.batch import BatchParams, BatchResult, lago_initialise, objective, optimize_batch
from robotd.graph.incremental import IncrementalGraph, IncrementalParams
from robotd.graph.model import (Edge, PoseGraph, chain_poses, check_information, chi2, edge_chi2,
                                edge_errors, isotropic_graph, isotropic_objective,
                                isotropic_weights, make_edge)

__all__ = [
    "BatchParams", "BatchResult", "Edge", "IncrementalGraph", "IncrementalParams", "PoseGraph", "chain_poses", "check_information", "chi2",
    "edge_chi2", "edge_errors", "isotropic_graph", "isotropic_objective", "isotropic_weights",
    "lago_initialise", "make_edge", "objective", "optimize_batch",
]
