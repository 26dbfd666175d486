"""A route's forward-camera images and their same-place ground truth, as a folder.

:func:`write_forward_sequence` drives a named route (:mod:`sim.route`) through its world
(:mod:`sim.world.rooms`), keeps a keyframe whenever the robot has moved ``step_m`` or
turned ``turn_rad`` since the last one, renders each keyframe with the forward camera
(:mod:`sim.cameras.forward`), and writes what ``robotd eval forward --images DIR
--ground-truth DIR/gt.npy`` reads:

* ``000000.png`` ... one grey 640x480 image per keyframe, in natural name order;
* ``gt.npy``: ``(N, N) uint8``, 1 where two images show the same place on a revisit
  (:func:`sim.cameras.forward.same_place_matrix`), symmetric;
* ``overlap.npy``: ``(N, N) float16`` view overlap behind it, to re-threshold;
* ``poses.csv``: ``index,t_s,x_m,y_m,yaw_rad`` true robot pose of every image;
* ``sequence.json``: the settings and counts; ``world/top_view.png``: the top view with
  the route drawn (in a subfolder: every image in the folder itself is a sequence image).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from robotd.base.errors import ConfigError
from robotd.base.geometry import wrap_angle
from sim.cameras.forward import (
    ForwardCameraModel,
    ForwardRenderer,
    ForwardRenderParams,
    same_place_matrix,
    view_histograms,
    view_overlap,
)
from sim.route import Motion, MotionLimits, Route, build_route, plan_motion
from sim.world.rooms import WallWorld, WorldParams, world_for_route

__all__ = ["SequenceSettings", "keyframe_times", "write_forward_sequence"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SequenceSettings:
    """What to write. ``step_m`` and ``turn_rad``: keyframe spacing (distance travelled,
    heading change); ``threshold``, ``leave_below``: see
    :func:`~sim.cameras.forward.same_place_matrix`; ``repeats``: drive the route this many
    times in a row (more images of the same world)."""

    route: str = "office"
    seed: int = 0
    step_m: float = 0.1
    turn_rad: float = math.radians(10.0)
    threshold: float = 0.2
    leave_below: float = 0.1
    repeats: int = 1
    noise_sigma: float = 2.0


def keyframe_times(motion: Motion, step_m: float, turn_rad: float, rate_hz: float = 30.0) -> np.ndarray:
    """``(N,) float64`` times of the keyframes along ``motion``: the first sample, then each
    sample (at ``rate_hz``) where the robot has travelled ``step_m`` or turned ``turn_rad``
    since the previous keyframe."""
    t = np.arange(0.0, float(motion.t_s[-1]), 1.0 / rate_hz)
    p = motion.poses_at(t)
    keep = [0]
    last = p[0]
    for i in range(1, len(t)):
        if (math.hypot(p[i, 0] - last[0], p[i, 1] - last[1]) >= step_m
                or abs(float(wrap_angle(p[i, 2] - last[2]))) >= turn_rad):
            keep.append(i)
            last = p[i]
    return t[np.asarray(keep)]


def _repeated_route(name: str, times: int) -> Route:
    """The named route driven ``times`` times in a row: its waypoints repeated (the planner
    turns the robot at each lap's start, so every lap starts from the same pose)."""
    route = build_route(name)
    if times == 1:
        return route
    pts = list(route.waypoints_m)
    joined = list(pts)
    for _ in range(times - 1):
        joined += pts[1:] if pts[0] == joined[-1] else pts
    return replace(route, name=f"{name}x{times}", waypoints_m=tuple(joined))


def write_forward_sequence(out_dir: str | Path, settings: SequenceSettings = SequenceSettings(),
                           camera: ForwardCameraModel = ForwardCameraModel(),
                           world_params: WorldParams = WorldParams()) -> dict[str, object]:
    """Write the sequence to ``out_dir`` (created); returns a summary (also written as
    ``sequence.json``): image count, positives, render and ground-truth times."""
    import time

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    world = world_for_route(settings.route, settings.seed, world_params)
    motion = plan_motion(_repeated_route(settings.route, settings.repeats), MotionLimits())
    times = keyframe_times(motion, settings.step_m, settings.turn_rad)
    poses = motion.poses_at(times)
    outside = [i for i, p in enumerate(poses) if not world.contains(p[0], p[1])]
    if outside:
        raise ConfigError(f"route {settings.route!r} leaves its world at {len(outside)} keyframes "
                          f"(first: {poses[outside[0], :2].round(2).tolist()})")
    renderer = ForwardRenderer(world, camera, ForwardRenderParams(noise_sigma=settings.noise_sigma),
                               np.random.default_rng(settings.seed + 2))
    t0 = time.perf_counter()
    for i, pose in enumerate(poses):
        cv2.imwrite(str(out / f"{i:06d}.png"), renderer.render(pose, float(times[i])))
    t_render = time.perf_counter() - t0
    t0 = time.perf_counter()
    overlap = view_overlap(view_histograms(renderer, poses))
    truth = same_place_matrix(overlap, settings.threshold, settings.leave_below)
    t_truth = time.perf_counter() - t0
    np.save(out / "gt.npy", truth.astype(np.uint8))
    np.save(out / "overlap.npy", overlap.astype(np.float16))
    with open(out / "poses.csv", "w", encoding="utf-8") as f:
        f.write("index,t_s,x_m,y_m,yaw_rad\n")
        for i, (t, p) in enumerate(zip(times, poses)):
            f.write(f"{i},{t:.4f},{p[0]:.5f},{p[1]:.5f},{p[2]:.6f}\n")
    (out / "world").mkdir(exist_ok=True)
    cv2.imwrite(str(out / "world" / "top_view.png"), _overview_with_route(world, poses))
    summary = {
        "settings": asdict(settings), "images": int(len(poses)),
        "images_with_a_revisit": int(truth.any(axis=1).sum()),
        "same_place_pairs": int(np.triu(truth, 1).sum()),
        "route_length_m": float(motion.length_m), "route_duration_s": float(motion.duration_s),
        "walls": world.n_walls, "wall_cells": world.n_cells,
        "camera": {"height_m": camera.height_m, "x_m": camera.x_m, "fx_px": camera.intrinsics.fx_px,
                   "fy_px": camera.intrinsics.fy_px, "width_px": camera.intrinsics.width_px,
                   "height_px": camera.intrinsics.height_px},
        "render_s": t_render, "ground_truth_s": t_truth,
    }
    (out / "sequence.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    return summary


def _overview_with_route(world: WallWorld, poses: np.ndarray, px_per_m: float = 40.0, margin_m: float = 0.5) -> np.ndarray:
    img = world.overview(px_per_m, margin_m)
    x0, _, _, y1 = world.bounds_m
    pts = np.column_stack([(poses[:, 0] - x0 + margin_m) * px_per_m, (y1 + margin_m - poses[:, 1]) * px_per_m])
    cv2.polylines(img, [np.round(pts).astype(np.int32)], False, (200, 0, 200), 1)
    return img
