"""Floor-camera frames with known poses, for training and benchmarking the floor detector.

Ground truth comes from the poses and the footprints (:func:`robotd.base.camera.overlap_ratios`),
never from image content.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robotd.base.camera import FloorCameraModel, overlap_ratios
from sim.cameras.floor import FloorRenderer, RenderParams
from sim.world.floor import FloorSource


@dataclass(frozen=True, eq=False)
class FramePairs:
    """``images_a[i]`` and ``images_b[i]`` seen from ``poses_a[i]`` and ``poses_b[i]``.

    ``poses_* (N, 3)`` world ``(x_m, y_m, yaw_rad)``; ``overlap (N,)`` the footprint
    overlap J (paper 003, eq. 3); images ``(H, W) uint8``.
    """

    images_a: list[np.ndarray]
    images_b: list[np.ndarray]
    poses_a: np.ndarray
    poses_b: np.ndarray
    overlap: np.ndarray


def render_at(renderer: FloorRenderer, poses: np.ndarray, rng: np.random.Generator,
              max_speed_mps: float = 0.3) -> list[np.ndarray]:
    """Render one frame per pose, each with a random forward speed (motion blur) and time."""
    speeds = rng.uniform(0.0, max_speed_mps, len(poses))
    times = rng.uniform(0.0, 600.0, len(poses))
    return [renderer.render(p, float(v), 0.0, float(t)) for p, v, t in zip(poses, speeds, times)]


def random_pairs(floor: FloorSource, camera: FloorCameraModel, n_pairs: int, rng: np.random.Generator,
                 area_m: tuple[float, float, float, float] = (-2.5, -2.5, 2.5, 2.5),
                 near_fraction: float = 0.6, max_offset_m: float = 0.6,
                 render_params: RenderParams | None = None) -> FramePairs:
    """Pairs of frames: a ``near_fraction`` share with B within ``max_offset_m`` of A and
    any heading (J spread over [0, 1]), the rest anywhere in ``area_m`` (almost all J = 0).
    """
    x0, y0, x1, y1 = area_m
    pa = np.column_stack([rng.uniform(x0, x1, n_pairs), rng.uniform(y0, y1, n_pairs),
                          rng.uniform(-np.pi, np.pi, n_pairs)])
    pb = np.column_stack([rng.uniform(x0, x1, n_pairs), rng.uniform(y0, y1, n_pairs),
                          rng.uniform(-np.pi, np.pi, n_pairs)])
    near = rng.random(n_pairs) < near_fraction
    r = max_offset_m * np.sqrt(rng.random(n_pairs))
    phi = rng.uniform(-np.pi, np.pi, n_pairs)
    pb[near, 0] = pa[near, 0] + r[near] * np.cos(phi[near])
    pb[near, 1] = pa[near, 1] + r[near] * np.sin(phi[near])
    renderer = FloorRenderer(floor, camera, render_params or RenderParams(), rng)
    return FramePairs(render_at(renderer, pa, rng), render_at(renderer, pb, rng), pa, pb,
                      overlap_ratios(camera, pa, pb))


def straight_run(floor: FloorSource, camera: FloorCameraModel, rng: np.random.Generator,
                 start_xyyaw: tuple[float, float, float] = (0.0, 0.0, 0.0), length_m: float = 10.0,
                 spacing_m: float = 0.05, speed_mps: float = 0.3,
                 render_params: RenderParams | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    """Frames every ``spacing_m`` along a straight line (paper 003 Sec. IV-A's 10 m runs).

    Returns ``poses (N, 3)`` and the images.
    """
    n = int(round(length_m / spacing_m)) + 1
    s = np.arange(n) * spacing_m
    x0, y0, yaw = start_xyyaw
    poses = np.column_stack([x0 + s * np.cos(yaw), y0 + s * np.sin(yaw), np.full(n, yaw)])
    renderer = FloorRenderer(floor, camera, render_params or RenderParams(), rng)
    images = [renderer.render(p, speed_mps, 0.0, i * spacing_m / speed_mps) for i, p in enumerate(poses)]
    return poses, images
