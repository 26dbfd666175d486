"""Where the downward floor camera sits on the robot, measured from a chessboard on the floor.

The user lays a chessboard face up on the floor at a known place relative to the robot
and takes one picture with the floor camera. With the camera's intrinsics, the board's
corners fix the camera's pose over the floor plane (``cv2.solvePnPGeneric``, IPPE); in the
conventions of :class:`robotd.base.camera.FloorCameraModel` that pose is the mount: lens
height, forward tilt, image yaw and the lens position in the robot frame. The height and
the tilt come from the picture alone; the position and the yaw are only as good as the
board's placement (they are measured *relative to the board*).

Board frame (what ``board_pose_robot`` refers to)
-------------------------------------------------
A board with ``(cols, rows)`` inner corners, one count odd and one even (9x6 is fine),
has black squares at both ends of one side and white squares at both ends of the opposite
side, so its orientation can be told from a picture. Lay it face up and stand at
the black corner square from which the board's ``cols`` side runs straight ahead of
you with the board on your left. The board origin is the inner corner diagonally in
from that black corner square; the board's x axis runs straight ahead (along the
``cols`` inner corners), its y axis to the left (along the ``rows`` inner corners).
``board_pose_robot = (x_m, y_m, yaw_deg)`` is that origin in the robot frame (REP-103:
x forward, y left) and the direction of the board's x axis, degrees counter-clockwise
from robot forward. OpenCV's corner order varies with the view; it is brought into this
frame by the corner handedness in the image and the colour of the corner squares.

The model has no sideways lean (roll) of the optical axis; the unconstrained pose's
lean is reported as ``roll_deg``, and the mount is the best fit of the five model
parameters to the corners (Levenberg-Marquardt on the reprojection error through
``FloorCameraModel`` itself, so the reported error is that of the model the daemon uses).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from robotd.io.calibfile import CalibrationFile, FloorMount, read_calibration, update_calibration
from calibration.intrinsics import board_object_points, find_board_corners, parse_board
from robotd.base.errors import CalibrationError
from robotd.base.camera import CameraIntrinsics, FloorCameraModel, polygon_area_signed
from robotd.base.geometry import transform_points

logger = logging.getLogger(__name__)

__all__ = [
    "FloorMountResult",
    "add_floor_mount_arguments",
    "board_corners_robot",
    "canonical_board_corners",
    "measure_floor_mount",
    "parse_board_pose",
    "run_floor_mount",
]


@dataclass(frozen=True, eq=False)
class FloorMountResult:
    """The measured mount (FloorCameraModel conventions) and how well it fits.

    Fields:
        height_m: lens centre above the floor, metres.
        tilt_deg: optical axis pitch from straight down towards robot forward, degrees.
        yaw_deg: image rotation about the optical axis, counter-clockwise seen from above,
            degrees in (-180, 180].
        x_m, y_m: lens centre in the robot frame, metres.
        reprojection_error_px: RMS distance between the detected corners and the corners
            projected through the fitted model, pixels.
        roll_deg: sideways lean of the optical axis in the unconstrained camera pose,
            degrees (towards robot left positive); the model assumes 0.
        corners_px: ``(cols * rows, 2) float64`` detected corners in board-frame order
            (row-major from the board origin), pixels.
    """

    height_m: float
    tilt_deg: float
    yaw_deg: float
    x_m: float
    y_m: float
    reprojection_error_px: float
    roll_deg: float
    corners_px: np.ndarray

    @property
    def mount(self) -> FloorMount:
        """The calibration-file part of this result."""
        return FloorMount(height_m=self.height_m, tilt_deg=self.tilt_deg, x_m=self.x_m, y_m=self.y_m,
                          yaw_deg=self.yaw_deg)

    def camera_model(self, intrinsics: CameraIntrinsics) -> FloorCameraModel:
        """The floor camera model with these intrinsics and this mount."""
        return _camera(intrinsics, self.height_m, math.radians(self.tilt_deg), math.radians(self.yaw_deg),
                       self.x_m, self.y_m)


def _camera(intr: CameraIntrinsics, h: float, tilt_rad: float, yaw_rad: float, x: float,
            y: float) -> FloorCameraModel:
    return FloorCameraModel(intrinsics=intr, height_m=h, tilt_rad=tilt_rad, offset_x_m=x, offset_y_m=y, yaw_rad=yaw_rad)


# ------------------------------------------------------------------ board frame


def board_corners_robot(board_inner_corners: tuple[int, int], square_size_m: float,
                        board_pose_robot: Sequence[float]) -> np.ndarray:
    """Inner corners on the floor in the robot frame, ``(cols * rows, 2) float64`` metres.

    Row-major from the board origin (see the module docstring); ``board_pose_robot`` is
    ``(x_m, y_m, yaw_deg)`` of the origin and the board's x axis.
    """
    bx, by, yaw_deg = (float(v) for v in board_pose_robot)
    pts = board_object_points(board_inner_corners, square_size_m)[:, :2].astype(np.float64)
    return transform_points(np.array([bx, by, math.radians(yaw_deg)]), pts)


def _square_brightness(gray: np.ndarray, centre: np.ndarray, radius_px: float) -> float | None:
    """Mean grey level in a disc, or None when the disc leaves the image."""
    h, w = gray.shape
    r = max(1.0, radius_px)
    x0, x1 = int(math.floor(centre[0] - r)), int(math.ceil(centre[0] + r))
    y0, y1 = int(math.floor(centre[1] - r)), int(math.ceil(centre[1] + r))
    if x0 < 0 or y0 < 0 or x1 >= w or y1 >= h:
        return None
    yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
    inside = (xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 <= r * r
    return float(gray[y0:y1 + 1, x0:x1 + 1][inside].mean())


def _outer_square_contrast(gray: np.ndarray, grid: np.ndarray) -> float | None:
    """Brightness of the corner square diagonally outside ``grid[0, 0]`` minus that of its
    two neighbours along the board's edges (opposite colour); None when out of the image.

    Negative when that corner square is black.
    """
    c00, c01, c10 = grid[0, 0], grid[0, 1], grid[1, 0]
    dx, dy = c01 - c00, c10 - c00
    radius = 0.25 * min(float(np.linalg.norm(dx)), float(np.linalg.norm(dy)))
    corner = _square_brightness(gray, c00 - 0.5 * dx - 0.5 * dy, radius)
    along_x = _square_brightness(gray, c00 + 0.5 * dx - 0.5 * dy, radius)
    along_y = _square_brightness(gray, c00 - 0.5 * dx + 0.5 * dy, radius)
    if corner is None or along_x is None or along_y is None:
        return None
    return corner - 0.5 * (along_x + along_y)


def canonical_board_corners(gray: np.ndarray, corners_px: np.ndarray,
                            board_inner_corners: tuple[int, int]) -> np.ndarray:
    """Reorder OpenCV's corners into the board frame of the module docstring.

    ``corners_px``: ``(cols * rows, 2)`` as found (row-major, any of the grid's symmetric
    orders). Returns ``(cols * rows, 2)``, row-major from the origin next to the black
    corner square, with the board's y axis to the left of its x axis seen from above.
    Raises :class:`~robotd.base.errors.CalibrationError` when the orientation cannot be told.
    """
    cols, rows = board_inner_corners
    if (cols + rows) % 2 == 0:
        raise CalibrationError(
            f"a {cols}x{rows} board looks the same turned around; use one with an odd and an even "
            "number of inner corners (e.g. 9x6) so its orientation is unambiguous")
    grid = np.asarray(corners_px, dtype=np.float64).reshape(rows, cols, 2)
    ex, ey = grid[0, -1] - grid[0, 0], grid[-1, 0] - grid[0, 0]
    # A camera above the floor sees a right-handed board (z up) counter-clockwise from
    # x to y; in image coordinates (v down) that is a negative cross product.
    if ex[0] * ey[1] - ex[1] * ey[0] > 0.0:
        grid = grid[:, ::-1]
    turned = grid[::-1, ::-1]
    # The origin's corner square is black, the opposite corner's white.
    a = _outer_square_contrast(gray, grid)
    b = _outer_square_contrast(gray, turned)
    if a is None and b is None:
        raise CalibrationError("cannot tell the board's orientation: its corner squares are outside the image")
    score = (a if a is not None else -b) - (b if b is not None else -a)  # type: ignore[operator]
    if abs(score) < 20.0:  # grey levels; a printed board gives about 2 x 150
        raise CalibrationError("cannot tell the board's orientation: its corner squares are not clearly "
                               "black at one end and white at the other")
    choice = grid if score < 0.0 else turned
    return choice.reshape(-1, 2).copy()


# ------------------------------------------------------------------- measuring


def _as_intrinsics(intrinsics: CameraIntrinsics | tuple[np.ndarray, Sequence[float]],
                   image_wh: tuple[int, int]) -> CameraIntrinsics:
    if isinstance(intrinsics, CameraIntrinsics):
        if (intrinsics.width_px, intrinsics.height_px) != image_wh:
            raise CalibrationError(
                f"the intrinsics are for {intrinsics.width_px}x{intrinsics.height_px} images, "
                f"the picture is {image_wh[0]}x{image_wh[1]}")
        return intrinsics
    k, dist = intrinsics
    try:
        return CameraIntrinsics.from_camera_matrix(np.asarray(k, dtype=np.float64), dist, image_wh[0], image_wh[1])
    except ValueError as exc:
        raise CalibrationError(str(exc)) from None


def _params_from_pose(rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, float]:
    """Model parameters ``(h, tilt, yaw, x, y)`` and the roll (rad) of a PnP pose."""
    r_cam_from_robot, _ = cv2.Rodrigues(rvec)
    r = r_cam_from_robot.T  # robot_from_camera: columns = camera axes in the robot frame
    centre = -r @ np.asarray(tvec, dtype=np.float64).reshape(3)
    axis = r[:, 2]  # optical axis; the model has (sin t, 0, -cos t)
    tilt = math.atan2(axis[0], -axis[2])
    roll = math.asin(max(-1.0, min(1.0, axis[1])))
    e = r[:, 0]  # image right; the model has (sin y cos t, -cos y, sin y sin t)
    yaw = math.atan2(e[0] * math.cos(tilt) + e[2] * math.sin(tilt), -e[1])
    return np.array([centre[2], tilt, yaw, centre[0], centre[1]]), roll


def _fit_model(intr: CameraIntrinsics, p0: np.ndarray, floor_xy: np.ndarray, uv: np.ndarray,
               iterations: int = 50) -> tuple[np.ndarray, float]:
    """Levenberg-Marquardt on the 5 model parameters; returns them and the RMS error (px)."""

    def residuals(p: np.ndarray) -> np.ndarray | None:
        if not (p[0] > 0.0 and abs(p[1]) < 0.5 * math.pi - 1e-6):
            return None
        proj = _camera(intr, p[0], p[1], p[2], p[3], p[4]).floor_robot_to_pixel(floor_xy)
        res = (proj - uv).ravel()
        return res if np.all(np.isfinite(res)) else None

    p = np.asarray(p0, dtype=np.float64).copy()
    r = residuals(p)
    if r is None:
        return p, math.inf
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(iterations):
        jac = np.empty((len(r), 5))
        for i in range(5):
            step = 1e-7 * max(1.0, abs(p[i]))
            dp = np.zeros(5)
            dp[i] = step
            rp, rm = residuals(p + dp), residuals(p - dp)
            if rp is None or rm is None:
                return p, math.sqrt(cost / (len(r) // 2))
            jac[:, i] = (rp - rm) / (2.0 * step)
        a = jac.T @ jac
        g = jac.T @ r
        improved = False
        while lam < 1e12:
            delta = np.linalg.solve(a + lam * np.diag(np.diag(a) + 1e-12), -g)
            r_new = residuals(p + delta)
            if r_new is not None and float(r_new @ r_new) < cost:
                p, r, cost = p + delta, r_new, float(r_new @ r_new)
                lam = max(lam * 0.1, 1e-12)
                improved = True
                break
            lam *= 10.0
        if not improved or np.max(np.abs(delta) / np.maximum(1.0, np.abs(p))) < 1e-12:
            break
    return p, math.sqrt(cost / (len(r) // 2))


def measure_floor_mount(
    image: np.ndarray,
    intrinsics: CameraIntrinsics | tuple[np.ndarray, Sequence[float]],
    board_inner_corners: tuple[int, int] = (9, 6),
    square_size_m: float = 0.025,
    board_pose_robot: Sequence[float] = (0.0, 0.0, 0.0),
) -> FloorMountResult:
    """Measure the floor camera's mount from one picture of a chessboard lying on the floor.

    ``image``: ``(H, W)`` or ``(H, W, 3)`` uint8 picture from the floor camera;
    ``intrinsics``: a :class:`~robotd.base.camera.CameraIntrinsics` or ``(K, dist)`` (K
    ``(3, 3)``, dist k1 k2 p1 p2 k3); ``board_inner_corners``: ``(cols, rows)``;
    ``square_size_m``: square side, metres; ``board_pose_robot``: ``(x_m, y_m, yaw_deg)``
    of the board origin in the robot frame (module docstring).

    Raises :class:`~robotd.base.errors.CalibrationError` when no board is found, its
    orientation cannot be told, or no camera pose above the floor explains the corners.
    """
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise CalibrationError(f"expected an 8-bit grey or BGR picture, got shape {img.shape} {img.dtype}")
    intr = _as_intrinsics(intrinsics, (img.shape[1], img.shape[0]))
    if not (math.isfinite(square_size_m) and square_size_m > 0.0):
        raise CalibrationError(f"square size must be positive, got {square_size_m}")
    cols, rows = int(board_inner_corners[0]), int(board_inner_corners[1])
    found = find_board_corners(img, (cols, rows))
    if found is None:
        raise CalibrationError(f"no {cols}x{rows} chessboard found in the picture")
    uv = canonical_board_corners(img, found, (cols, rows))
    floor_xy = board_corners_robot((cols, rows), square_size_m, board_pose_robot)
    obj = np.column_stack([floor_xy, np.zeros(len(floor_xy))])

    # Both poses a planar target allows (IPPE); each is fitted within the model and the
    # better fit whose lens is above the floor wins.
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, uv.reshape(-1, 1, 2), intr.camera_matrix(), intr.distortion_array(),
                                                 flags=cv2.SOLVEPNP_IPPE)
    except cv2.error as exc:
        raise CalibrationError(f"OpenCV could not solve the camera pose: {str(exc).strip().splitlines()[-1]}") from None
    best: tuple[float, np.ndarray, float] | None = None
    for rvec, tvec in zip(rvecs[:n], tvecs[:n]):
        rvec, tvec = cv2.solvePnPRefineLM(obj, uv.reshape(-1, 1, 2), intr.camera_matrix(), intr.distortion_array(),
                                          rvec.copy(), tvec.copy())
        p0, roll = _params_from_pose(rvec, tvec)
        if p0[0] <= 0.0:
            continue
        p, err = _fit_model(intr, p0, floor_xy, uv)
        logger.debug("pose candidate: h %.4f m, tilt %.3f deg, roll %.3f deg -> fit %.3f px",
                     p0[0], math.degrees(p0[1]), math.degrees(roll), err)
        if best is None or err < best[0]:
            best = (err, p, roll)
    if best is None or not math.isfinite(best[0]):
        raise CalibrationError("no camera pose above the floor explains the board's corners "
                               "(wrong intrinsics, or the board is not lying flat on the floor)")
    err, p, roll = best
    yaw_deg = math.degrees(p[2]) % 360.0
    if yaw_deg > 180.0:  # (-180, 180]
        yaw_deg -= 360.0
    return FloorMountResult(height_m=float(p[0]), tilt_deg=math.degrees(p[1]), yaw_deg=yaw_deg,
                            x_m=float(p[3]), y_m=float(p[4]), reprojection_error_px=float(err),
                            roll_deg=math.degrees(roll), corners_px=uv)


# ---------------------------------------------------------------------------- CLI


def parse_board_pose(text: str) -> tuple[float, float, float]:
    """``"0.30,-0.10,90"`` -> ``(0.30, -0.10, 90.0)``: board origin x, y (metres), yaw (degrees)."""
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"board pose must be X_M,Y_M,YAW_DEG, e.g. 0.3,-0.1,90; got {text!r}")
    return values[0], values[1], values[2]


def add_floor_mount_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``robotd calibrate floor-mount``."""
    parser.add_argument("image", type=Path, metavar="IMAGE", help="floor camera picture of the board on the floor")
    parser.add_argument("--calibration", type=Path, required=True, metavar="FILE",
                        help="calibration file with the camera intrinsics; the mount is merged into it")
    parser.add_argument("--board", type=parse_board, default=(9, 6), metavar="COLSxROWS",
                        help="inner corners of the chessboard (default: 9x6)")
    parser.add_argument("--square", type=float, default=0.025, metavar="METRES",
                        help="side of one board square, metres (default: 0.025)")
    parser.add_argument("--board-pose", type=parse_board_pose, required=True, metavar="X,Y,YAW_DEG",
                        help="board origin in the robot frame (metres, x forward, y left) and the direction "
                             "of its first side (degrees, counter-clockwise from forward); the origin is the "
                             "inner corner next to the black corner square with the board on its left; write "
                             "--board-pose=-0.1,0,90 when X is negative")


def format_mount_report(result: FloorMountResult, camera: FloorCameraModel) -> str:
    """The mount and the footprint it gives, as text."""
    lines = [
        f"height          {result.height_m * 1000:.1f} mm",
        f"tilt            {result.tilt_deg:.2f} deg (towards forward)",
        f"yaw             {result.yaw_deg:.2f} deg (image up from robot forward, counter-clockwise)",
        f"position        x {result.x_m * 1000:.1f} mm, y {result.y_m * 1000:.1f} mm (robot frame)",
        f"fit             {result.reprojection_error_px:.3f} px RMS over {len(result.corners_px)} corners",
    ]
    if abs(result.roll_deg) > 1.0:
        lines.append(f"warning         the camera leans {result.roll_deg:.2f} deg sideways; the model assumes 0 "
                     "(level the mount, or expect errors at the image sides)")
    try:
        fp = camera.footprint_robot()
    except ValueError:
        lines.append("footprint       part of the view does not see the floor")
    else:
        ext = fp.max(axis=0) - fp.min(axis=0)
        lines.append(f"footprint       {ext[0] * 1000:.0f} mm along x (forward) x {ext[1] * 1000:.0f} mm along y, "
                     f"area {polygon_area_signed(fp):.4f} m^2, {camera.metres_per_px_at_centre() * 1000:.3f} mm/px "
                     "at the image centre")
    return "\n".join(lines)


def run_floor_mount(args: argparse.Namespace) -> int:
    """``robotd calibrate floor-mount``: measure, print, merge the mount into the file."""
    calib = read_calibration(args.calibration)
    if calib.intrinsics is None:
        raise CalibrationError(f"{args.calibration}: has no camera intrinsics; run 'robotd calibrate intrinsics' first")
    path = os.fspath(args.image)
    image = cv2.imread(path, cv2.IMREAD_GRAYSCALE) if os.path.isfile(path) else None
    if image is None:
        raise CalibrationError(f"{path}: cannot read the picture (missing or not an image)")
    result = measure_floor_mount(image, calib.intrinsics, tuple(args.board), float(args.square),
                                 tuple(args.board_pose))
    print(format_mount_report(result, result.camera_model(calib.intrinsics)))
    update_calibration(args.calibration, CalibrationFile(mount=result.mount))
    print(f"wrote the mount into {args.calibration}")
    if result.reprojection_error_px > 1.0:
        print("note: the fit is poor (> 1 px): check the intrinsics and that the board lies flat")
    return 0
