"""Shared helpers of the calibration tests: a chessboard lying on the virtual floor.

The board is drawn geometrically (each floor pixel area-averaged over a supersampled
grid) in world coordinates, laid on the floor with ``ImageFloor`` and seen through
``FloorRenderer`` (no noise, no blur), so every picture comes with its exact geometry.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from robotd.base.camera import FloorCameraModel
from robotd.base.geometry import compose
from sim.world.floor import ImageFloor
from sim.cameras.floor import FloorRenderer, RenderParams

#: ../shared/data next to the repository (absent outside the project's workspace and CI).
SHARED_DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"

CLEAN = RenderParams(noise_sigma=0.0, shot_noise=False, drift_amplitude=0.0, motion_blur=False)


def chessboard_floor(cols: int, rows: int, square_m: float, board_pose_world: np.ndarray,
                     metres_per_px: float = 0.001, supersample: int = 4, margin_squares: float = 1.0,
                     floor_grey: int = 90) -> ImageFloor:
    """A floor with a ``cols x rows`` inner-corner chessboard at ``(x_m, y_m, yaw_rad)``.

    Board frame as in :mod:`calibration.floor_mount`: the origin is the inner corner
    diagonally in from a black corner square, x along the ``cols`` side, y to its left.
    Square ``(i, j)`` (``i = 0..cols``, ``j = 0..rows``) covers board coordinates
    ``[(i - 1) s, i s] x [(j - 1) s, j s]`` and is black when ``i + j`` is even. A white
    margin of ``margin_squares`` squares surrounds the board; the rest is grey.
    """
    bx, by, yaw = (float(v) for v in board_pose_world)
    lo = -square_m * (1.0 + margin_squares)
    hi_x, hi_y = square_m * (cols + margin_squares), square_m * (rows + margin_squares)
    c, s = math.cos(yaw), math.sin(yaw)
    outline = np.array([[lo, lo], [hi_x, lo], [hi_x, hi_y], [lo, hi_y]]) @ np.array([[c, s], [-s, c]]) + (bx, by)
    x0, y0 = outline.min(axis=0) - 0.01
    x1, y1 = outline.max(axis=0) + 0.01
    ncol, nrow = int(math.ceil((x1 - x0) / metres_per_px)), int(math.ceil((y1 - y0) / metres_per_px))
    cc, rr = np.meshgrid(np.arange(ncol), np.arange(nrow))
    acc = np.zeros((nrow, ncol))
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    for oy in offsets:
        for ox in offsets:
            wx = x0 + (cc + ox) * metres_per_px - bx
            wy = y1 - (rr + oy) * metres_per_px - by
            qx, qy = c * wx + s * wy, -s * wx + c * wy
            i, j = np.floor(qx / square_m) + 1, np.floor(qy / square_m) + 1
            on_board = (i >= 0) & (i <= cols) & (j >= 0) & (j <= rows)
            on_paper = (qx >= lo) & (qx <= hi_x) & (qy >= lo) & (qy <= hi_y)
            value = np.where(on_paper, 255.0, float(floor_grey))
            acc += np.where(on_board, np.where((i + j) % 2 == 0, 0.0, 255.0), value)
    img = np.clip(acc / supersample**2 + 0.5, 0, 255).astype(np.uint8)
    return ImageFloor(img, metres_per_px, (x0, y1), fill=floor_grey)


def centred_board_pose(camera: FloorCameraModel, cols: int, rows: int, square_m: float, yaw_deg: float,
                       at_px: tuple[float, float] | None = None) -> tuple[float, float, float]:
    """Board pose ``(x_m, y_m, yaw_deg)`` in the robot frame with the board's centre seen at
    pixel ``at_px`` (default: the principal point)."""
    uv = (camera.intrinsics.cx_px, camera.intrinsics.cy_px) if at_px is None else at_px
    centre = camera.pixel_to_floor_robot(np.array([uv], dtype=float))[0]
    a = math.radians(yaw_deg)
    half = np.array([(cols - 1) * square_m / 2.0, (rows - 1) * square_m / 2.0])
    origin = centre - np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]) @ half
    return float(origin[0]), float(origin[1]), float(yaw_deg)


def render_board(camera: FloorCameraModel, cols: int, rows: int, square_m: float,
                 board_pose_robot: tuple[float, float, float],
                 robot_pose_world: tuple[float, float, float] = (1.0, -0.5, 0.3)) -> np.ndarray:
    """``(H, W) uint8`` floor-camera picture of the board at ``board_pose_robot`` (x, y, yaw_deg).

    The robot stands at ``robot_pose_world`` (not the origin, so that the test exercises
    the world-to-robot transform too); the board is placed relative to it.
    """
    bx, by, yaw_deg = board_pose_robot
    board_world = compose(np.asarray(robot_pose_world, float), np.array([bx, by, math.radians(yaw_deg)]))
    floor = chessboard_floor(cols, rows, square_m, board_world)
    renderer = FloorRenderer(floor, camera, CLEAN, np.random.default_rng(0))
    img = renderer.render_clean(np.asarray(robot_pose_world, float))
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)
