"""``robotd graph optimize|export``: the pose graph from the command line.

``optimize`` reads a g2o file, runs the batch solver (LAGO, robust Levenberg-Marquardt, then graduated
non-convexity) and writes the optimised graph; ``export`` turns a map file into g2o and TUM files.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, TYPE_CHECKING

from robotd.base.errors import GraphError, OutputError, RobotdError
from robotd.base.files import check_output_file, check_output_folder, nonempty_path

if TYPE_CHECKING:  # the real imports happen in the commands, so `robotd --help` skips gtsam
    from robotd.graph import BatchResult, PoseGraph
    from robotd.io.store import MapStore


def add_arguments(sub: argparse._SubParsersAction[Any]) -> None:
    """Register ``graph optimize`` and ``graph export`` under ``sub``."""
    gr = sub.add_parser("graph", help="optimise or export pose graphs (g2o, TUM)")
    gsub = gr.add_subparsers(dest="graph_command", metavar="ACTION", required=True)
    opt = gsub.add_parser(
        "optimize", help="optimise a g2o 2D pose graph",
        description="Optimise a g2o 2D pose graph (VERTEX_SE2, EDGE_SE2, FIX): LAGO initialisation, "
                    "then Levenberg-Marquardt with loop edges under a DCS robust kernel, then "
                    "graduated non-convexity (--robust). Prints the "
                    "initial and final objective, the iterations and the time.")
    opt.add_argument("input", type=nonempty_path, metavar="IN.g2o")
    opt.add_argument("--out", type=nonempty_path, required=True, metavar="OUT.g2o")
    opt.add_argument("--isotropic", action="store_true",
                     help="SE-Sync's isotropic noise per edge and its objective (benchmark tables)")
    opt.add_argument("--no-robust", action="store_true", help="plain least squares on every edge")
    opt.add_argument("--robust", choices=("gnc", "dcs", "cauchy"), default="gnc",
                     help="how wrong loops are resisted: gnc (default; graduated non-convexity, "
                          "truncated least squares, started from the DCS solution), or only the "
                          "dcs or cauchy kernel under Levenberg-Marquardt")
    opt.add_argument("--force", action="store_true", help="overwrite OUT.g2o")
    opt.set_defaults(func=run_optimize)
    exp = gsub.add_parser(
        "export", help="write a map's pose graph as g2o and its trajectories as TUM",
        description="Write DIR/graph.g2o (keyframes at their odometry poses, odometry and loop links), "
                    "DIR/odometry.tum and DIR/optimized.tum (after the batch solver).")
    exp.add_argument("map", type=nonempty_path, metavar="MAP.sqlite")
    exp.add_argument("--out", type=nonempty_path, required=True, metavar="DIR")
    exp.add_argument("--force", action="store_true", help="overwrite existing output files")
    exp.set_defaults(func=run_export)


def _check_input(path: Path, what: str) -> None:
    from robotd.base.files import describe_path_kind

    kind = describe_path_kind(path)
    if kind == "missing":
        raise RobotdError(f"{what} {path}: no such file")
    if kind != "a regular file":
        raise RobotdError(f"{what} {path} is {kind}, not a file")


def _summary(result: BatchResult) -> None:
    out = sys.stdout
    n_loops = len(result.loop_weights)
    down = int((result.loop_weights < 0.5).sum())
    print(f"initial objective  {result.initial_objective:.6e}", file=out)
    print(f"start objective    {result.start_objective:.6e}  (after initialisation, "
          f"{result.init_time_s:.3f} s)", file=out)
    print(f"final objective    {result.final_objective:.6e}", file=out)
    print(f"iterations         {result.iterations}", file=out)
    print(f"time               {result.time_s:.3f} s", file=out)
    if result.gnc_time_s:
        print(f"  of which GNC     {result.gnc_time_s:.3f} s", file=out)
    print(f"loops down-weighted by the optimiser: {down} of {n_loops} (weight < 0.5)", file=out)
    if n_loops and result.final_objective > result.start_objective:
        print("(the objectives are the plain sum over every edge, no robust kernel: with loops "
              "down-weighted the robust cost falls while this one may rise)", file=out)


def run_optimize(args: argparse.Namespace) -> int:
    """``robotd graph optimize``."""
    from robotd.graph import BatchParams, optimize_batch
    from robotd.io.g2o import read_g2o, write_g2o

    _check_input(args.input, "input")
    check_output_file(args.out, force=args.force, inputs=[args.input])
    graph = read_g2o(args.input)
    params = BatchParams(noise="isotropic" if args.isotropic else "full", robust=not args.no_robust,
                         kernel=getattr(args, "robust", "gnc"))
    n_loops = sum(e.kind == "loop" for e in graph.edges)
    kernel = ("none" if args.no_robust else
              f"gnc (TLS, inlier chi2 {params.inlier_chi2:g}, from dcs width {params.kernel_width:g})"
              if params.kernel == "gnc" else f"{params.kernel} (width {params.kernel_width:g})")
    print(f"{args.input}: {len(graph)} poses, {len(graph.edges)} edges ({n_loops} loops); "
          f"{params.noise} noise, robust kernel {kernel}")
    result = optimize_batch(graph, params)
    _summary(result)
    write_g2o(args.out, graph, result.poses)
    print(f"wrote {args.out}")
    return 0


def graph_from_map(store: MapStore) -> tuple[PoseGraph, list[int]]:
    """The map's keyframes (at their odometry poses) and links as a pose graph, and the
    keyframes' stamps (ns) in id order."""
    from robotd.graph import PoseGraph

    graph = PoseGraph()
    stamps = []
    for kf in store.keyframes():
        graph.add_pose(kf.id, (kf.x_m, kf.y_m, kf.yaw_rad))
        stamps.append(kf.stamp_ns)
    if not len(graph):
        raise GraphError(f"map {store.path} has no keyframes")
    for link in store.links():
        try:
            graph.add_edge(link.from_id, link.to_id, (link.dx_m, link.dy_m, link.dyaw_rad),
                           link.information, link.kind)  # type: ignore[arg-type]
        except GraphError as exc:
            raise GraphError(f"map {store.path}, link {link.id}: {exc}") from None
    return graph, stamps


def run_export(args: argparse.Namespace) -> int:
    """``robotd graph export``."""
    import numpy as np

    from robotd.graph import optimize_batch
    from robotd.io.g2o import write_g2o
    from robotd.io.store import MapStore
    from robotd.io.trajectory import write_tum

    out: Path = args.out
    check_output_folder(out, "graph.g2o, odometry.tum and optimized.tum")
    targets = [out / "graph.g2o", out / "odometry.tum", out / "optimized.tum"]
    if out.is_dir():
        for t in targets:
            check_output_file(t, force=args.force, inputs=[args.map])
    with MapStore.open(args.map, create=False, read_only=True) as store:
        graph, stamps = graph_from_map(store)
    result = optimize_batch(graph)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create the output folder {out}: {exc.strerror or exc}") from None
    write_g2o(targets[0], graph)
    write_tum(targets[1], np.asarray(stamps, np.int64), graph.poses())
    write_tum(targets[2], np.asarray(stamps, np.int64), result.poses)
    n_loops = len(result.loop_weights)
    print(f"{args.map}: {len(graph)} keyframes, {len(graph.edges) - n_loops} odometry and "
          f"{n_loops} loop links")
    _summary(result)
    print(f"wrote {', '.join(str(t) for t in targets)}")
    return 0
