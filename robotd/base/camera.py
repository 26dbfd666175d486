"""Pinhole model of the downward-facing floor camera mounted on the robot.

Pure geometry, no I/O: the virtual robot renders through it, and calibration and the
floor loop detector reuse it to map pixels to metric floor points and to project a
view's field of view onto the floor (paper 003, Sec. III: loop = footprint overlap).

Frames
------
Robot frame: REP-103, x forward, y left, z up, origin on the floor below the robot's
centre. Camera frame: OpenCV convention, x = image right (increasing ``u``),
y = image down (increasing ``v``), z = optical axis.

Image orientation: with ``tilt_rad = 0`` and ``yaw_rad = 0`` the camera looks straight
down, image "up" (decreasing ``v``) is the robot's forward direction (+x) and image
"right" (increasing ``u``) is the robot's right (-y). The image is then what a person
standing on the robot, facing forward and looking down, would see: the floor moves
*down* the image when the robot drives forward. ``yaw_rad`` turns the camera about its
optical axis counter-clockwise seen from above: image "up" points along robot heading
``yaw_rad``. ``tilt_rad`` pitches the optical axis away from straight down towards the
robot's forward direction (applied after ``yaw_rad``, so it always leans forward).

Pixel coordinates follow OpenCV: ``(u, v)`` with the centre of the top-left pixel at
``(0, 0)``; the image border lies at ``u = -0.5`` and ``u = width_px - 0.5``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Iterable

import numpy as np


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics and lens distortion of one camera at one image size.

    The one intrinsics type of robotd: the camera model, the calibration file and the
    calibration tools all use it. Invalid values raise ``ValueError``.

    Fields:
        width_px, height_px: image size the intrinsics belong to, pixels (> 0).
        fx_px, fy_px: focal lengths, pixels (> 0).
        cx_px, cy_px: principal point, pixels (OpenCV convention: top-left pixel centre = 0).
        distortion: ``(k1, k2, p1, p2, k3)``, OpenCV's order (Brown-Conrady model on
            normalised coordinates), dimensionless; a tuple so the type stays hashable.
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        dist = tuple(_finite("distortion coefficient", d) for d in self.distortion)
        if len(dist) != 5:
            raise ValueError(f"distortion: need 5 coefficients (k1 k2 p1 p2 k3), got {len(dist)}")
        object.__setattr__(self, "distortion", dist)
        if int(self.width_px) != self.width_px or int(self.height_px) != self.height_px \
                or self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"image size must be positive integers, got {self.width_px}x{self.height_px}")
        object.__setattr__(self, "width_px", int(self.width_px))
        object.__setattr__(self, "height_px", int(self.height_px))
        for name in ("fx_px", "fy_px", "cx_px", "cy_px"):
            object.__setattr__(self, name, _finite(name, getattr(self, name)))
        if self.fx_px <= 0.0 or self.fy_px <= 0.0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx_px}, fy={self.fy_px}")

    @classmethod
    def from_config(cls, cfg: object) -> CameraIntrinsics:
        """From a ``[floor_camera]`` config section (duck-typed): its ``width_px, height_px,
        fx_px, fy_px, cx_px, cy_px, distortion`` keys."""
        return cls(
            width_px=int(cfg.width_px),  # type: ignore[attr-defined]
            height_px=int(cfg.height_px),  # type: ignore[attr-defined]
            fx_px=float(cfg.fx_px),  # type: ignore[attr-defined]
            fy_px=float(cfg.fy_px),  # type: ignore[attr-defined]
            cx_px=float(cfg.cx_px),  # type: ignore[attr-defined]
            cy_px=float(cfg.cy_px),  # type: ignore[attr-defined]
            distortion=tuple(cfg.distortion),  # type: ignore[attr-defined]
        )

    @classmethod
    def from_camera_matrix(cls, camera_matrix: np.ndarray, distortion: Iterable[float], width_px: int,
                           height_px: int) -> CameraIntrinsics:
        """From an OpenCV ``(3, 3)`` camera matrix K and 4, 5 or more distortion coefficients.

        Coefficients past k3 (OpenCV's rational, thin-prism and tilt models) must be zero:
        the floor camera model is Brown-Conrady with five coefficients. A camera matrix with
        skew or a bottom row other than ``(0, 0, 1)`` is rejected for the same reason.
        """
        k = np.asarray(camera_matrix, dtype=np.float64)
        if k.shape != (3, 3):
            raise ValueError(f"camera_matrix must be 3x3, got shape {k.shape}")
        if not np.all(np.isfinite(k)):
            raise ValueError("camera_matrix has non-finite entries")
        if abs(k[0, 1]) > 1e-9 * abs(k[0, 0]) or abs(k[1, 0]) > 0.0 or np.any(k[2] != (0.0, 0.0, 1.0)):
            raise ValueError(f"camera_matrix must be [[fx 0 cx] [0 fy cy] [0 0 1]] (no skew), got {k.tolist()}")
        d = np.asarray(list(distortion), dtype=np.float64).ravel()
        if d.size == 4:
            d = np.append(d, 0.0)
        if d.size < 4:
            raise ValueError(f"distortion_coefficients: need at least 4, got {d.size}")
        if d.size > 5 and np.any(d[5:] != 0.0):
            raise ValueError(
                f"distortion_coefficients: {d.size} coefficients with non-zero k4.. (OpenCV's rational or "
                "thin-prism model) are not supported; calibrate with the 5-coefficient model")
        return cls(width_px=width_px, height_px=height_px, fx_px=float(k[0, 0]), fy_px=float(k[1, 1]),
                   cx_px=float(k[0, 2]), cy_px=float(k[1, 2]),
                   distortion=(float(d[0]), float(d[1]), float(d[2]), float(d[3]), float(d[4])))

    def camera_matrix(self) -> np.ndarray:
        """``(3, 3) float64`` OpenCV camera matrix K, pixels."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    def distortion_array(self) -> np.ndarray:
        """``(5,) float64`` distortion coefficients, OpenCV's order (for ``cv2`` calls)."""
        return np.array(self.distortion, dtype=np.float64)


def _finite(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return value


@dataclass(frozen=True)
class FloorCameraModel:
    """Intrinsics, lens distortion and mounting of the downward floor camera.

    Fields:
        intrinsics: image size, focal lengths, principal point and distortion.
        height_m: height of the lens centre above the floor, metres (> 0).
        tilt_rad: pitch of the optical axis away from straight down, towards the robot's
            forward direction, radians (0 = straight down; must stay below pi/2).
        offset_x_m, offset_y_m: lens position in the robot frame, metres.
        yaw_rad: rotation of the image about the optical axis, radians, counter-clockwise
            seen from above (see the module docstring).
    """

    intrinsics: CameraIntrinsics
    height_m: float = 0.40
    tilt_rad: float = 0.0
    offset_x_m: float = 0.0
    offset_y_m: float = 0.0
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.intrinsics, CameraIntrinsics):
            raise TypeError(f"intrinsics must be a CameraIntrinsics, got {type(self.intrinsics).__name__}")
        if self.height_m <= 0:
            raise ValueError("height_m must be positive (lens above the floor)")
        if not -math.pi / 2 < self.tilt_rad < math.pi / 2:
            raise ValueError("tilt_rad must lie in (-pi/2, pi/2)")

    @property
    def width_px(self) -> int:
        """Image width, pixels (from the intrinsics)."""
        return self.intrinsics.width_px

    @property
    def height_px(self) -> int:
        """Image height, pixels (from the intrinsics)."""
        return self.intrinsics.height_px

    @classmethod
    def default(cls) -> FloorCameraModel:
        """The virtual robot's floor camera: 640x480, wide lens, 1 mm of floor per pixel.

        Lens 0.40 m above the floor, fx = fy = 400 px (77 x 62 degree field of view), mild
        barrel distortion (k1 = -0.05), above the robot centre, looking straight down
        (the same values as the commented default config). The image covers about
        0.64 x 0.48 m of floor (0.48 m along the robot's heading) at 1.0 mm per pixel at
        the centre.

        Trade-off (DESIGN.md, "The virtual robot"): a narrow view of 0.3 x 0.2 m would
        need about 2000 floor-texture pixels per metre, far beyond what real photographs
        of 512 to 2048 px can supply over a 10 x 10 m floor without upsampling (blur) or
        tiling (exact repeats). A wider lens sees 1000 px/m instead: every image pixel
        is one native photo pixel, so the floor keeps real photo detail, and the bigger
        footprint holds more keypoints and overlaps longer along a path. The price is
        coarser metric resolution (visual odometry and calibration work at 1 mm/px, not
        0.5 mm/px), more lens distortion to model, and a footprint wider than the
        Turtlebot's 0.35 m base: the virtual robot ignores self-occlusion, a real mount
        would need a boom or a camera under a raised deck.
        """
        return cls(
            intrinsics=CameraIntrinsics(width_px=640, height_px=480, fx_px=400.0, fy_px=400.0, cx_px=319.5,
                                        cy_px=239.5, distortion=(-0.05, 0.0, 0.0, 0.0, 0.0)),
            height_m=0.40,
            tilt_rad=0.0,
            offset_x_m=0.0,
            offset_y_m=0.0,
            yaw_rad=0.0,
        )

    @classmethod
    def from_config(cls, cfg: object) -> FloorCameraModel:
        """Build the model from a ``[floor_camera]`` config section (duck-typed).

        Intrinsics through :meth:`CameraIntrinsics.from_config`; the mount from
        ``mount_height_m, mount_tilt_deg, mount_x_m, mount_y_m, mount_yaw_deg``.
        """
        return cls(
            intrinsics=CameraIntrinsics.from_config(cfg),
            height_m=float(cfg.mount_height_m),  # type: ignore[attr-defined]
            tilt_rad=math.radians(float(cfg.mount_tilt_deg)),  # type: ignore[attr-defined]
            offset_x_m=float(cfg.mount_x_m),  # type: ignore[attr-defined]
            offset_y_m=float(cfg.mount_y_m),  # type: ignore[attr-defined]
            yaw_rad=math.radians(float(cfg.mount_yaw_deg)),  # type: ignore[attr-defined]
        )

    # ------------------------------------------------------------------ frames

    @cached_property
    def rotation_robot_from_camera(self) -> np.ndarray:
        """``(3, 3)`` rotation taking camera-frame vectors to robot-frame vectors.

        Columns are the camera's x (image right), y (image down) and z (optical axis)
        axes expressed in the robot frame.
        """
        t = self.tilt_rad
        # Straight-down camera tilted forward: image down = -forward (tilted with the
        # axis), image right = -left, optical axis down and leaning forward.
        base = np.array(
            [
                [0.0, -math.cos(t), math.sin(t)],
                [-1.0, 0.0, 0.0],
                [0.0, -math.sin(t), -math.cos(t)],
            ]
        )
        # Rotation about the optical axis. The optical axis points down, so a camera
        # turn that is counter-clockwise seen from above is a negative turn about +z_cam.
        c, s = math.cos(-self.yaw_rad), math.sin(-self.yaw_rad)
        about_axis = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        rot = base @ about_axis
        rot.setflags(write=False)
        return rot

    @property
    def position_robot_m(self) -> np.ndarray:
        """``(3,)`` lens centre in the robot frame, metres."""
        return np.array([self.offset_x_m, self.offset_y_m, self.height_m])

    # -------------------------------------------------------------- distortion

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Brown-Conrady distortion of normalised coordinates (OpenCV's model)."""
        k1, k2, p1, p2, k3 = self.intrinsics.distortion
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return xd, yd

    def _undistort(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Invert :meth:`_distort` by Newton's method (converges to ~1e-15 for sane lenses).

        Each iteration evaluates :meth:`_distort` and its Jacobian with their common terms
        computed once (``r^2``, the radial factor, ``2 x x``, ``2 x y``, ...), each one by
        the same operations in the same order as written out in full, so the same values to
        the bit (``tests/base/test_camera.py`` holds it against the written-out form)."""
        k1, k2, p1, p2, k3 = self.intrinsics.distortion
        if not any(self.intrinsics.distortion):
            return xd.copy(), yd.copy()
        x, y = xd.copy(), yd.copy()
        tp1, tp2, sp1, sp2, tk2, kk3 = 2.0 * p1, 2.0 * p2, 6.0 * p1, 6.0 * p2, 2.0 * k2, 3.0 * k3
        for _ in range(50):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dradial = k1 + r2 * (tk2 + kk3 * r2)  # d radial / d r2
            x2 = 2.0 * x
            xx, xy, yy = x2 * x, x2 * y, 2.0 * y * y  # 2 x x, 2 x y, 2 y y
            p1x, p2y = tp1 * x, tp2 * y
            # _distort(x, y) - (xd, yd), its terms shared with the Jacobian
            ex = x * radial + p1x * y + p2 * (r2 + xx) - xd
            ey = y * radial + p1 * (r2 + yy) + tp2 * x * y - yd
            # Jacobian of the distortion (symmetric: j21 = j12)
            j11 = radial + xx * dradial + tp1 * y + sp2 * x
            j12 = xy * dradial + p1x + p2y
            j22 = radial + yy * dradial + sp1 * y + tp2 * x
            det = j11 * j22 - j12 * j12
            dx = (j22 * ex - j12 * ey) / det
            dy = (-j12 * ex + j11 * ey) / det
            x -= dx
            y -= dy
            # max |d| < 1e-15 over the non-NaN entries (none: 0), as nanmax with initial 0
            if not (np.abs(dx) >= 1e-15).any() and not (np.abs(dy) >= 1e-15).any():
                break
        return x, y

    @cached_property
    def _max_radius_sq(self) -> float:
        """Largest undistorted r^2 over which radial distortion is still monotonic.

        Beyond it the polynomial folds back and far-away points would wrongly land
        inside the image; projections there are reported as invalid.
        """
        k1, k2, _, _, k3 = self.intrinsics.distortion
        r = np.linspace(0.0, 10.0, 20001)
        r2 = r * r
        rd = r * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        falling = np.nonzero(np.diff(rd) <= 0.0)[0]
        return float(r2[falling[0]]) if falling.size else math.inf

    # -------------------------------------------------------------- projection

    def pixel_rays_robot(self, uv: np.ndarray) -> np.ndarray:
        """Viewing rays of pixels, ``(N, 2)`` px -> ``(N, 3)`` directions in the robot frame.

        Directions are not normalised: they are ``R @ (x_n, y_n, 1)`` with ``(x_n, y_n)``
        the undistorted normalised coordinates; NaN for pixels beyond the radius where
        the lens model stops being one-to-one (an invalid calibration for that image).
        """
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        k = self.intrinsics
        xd = (uv[:, 0] - k.cx_px) / k.fx_px
        yd = (uv[:, 1] - k.cy_px) / k.fy_px
        xn, yn = self._undistort(xd, yd)
        # Past the fold of the radial polynomial the pixel has no true preimage.
        bad = ~(xn * xn + yn * yn <= self._max_radius_sq)
        xn[bad] = np.nan
        yn[bad] = np.nan
        rays_cam = np.stack([xn, yn, np.ones_like(xn)], axis=1)
        return rays_cam @ self.rotation_robot_from_camera.T

    def _rays_to_floor(self, rays_robot: np.ndarray) -> np.ndarray:
        c = self.position_robot_m
        dz = rays_robot[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(dz < 0.0, -c[2] / dz, np.nan)
        return c[:2] + rays_robot[..., :2] * s[..., None]

    def pixel_to_floor_robot(self, uv: np.ndarray) -> np.ndarray:
        """Floor points seen by pixels: ``(N, 2)`` px -> ``(N, 2) float64`` metres, robot frame.

        Undistorts, then intersects each viewing ray with the floor plane z = 0. Pixels
        whose ray does not hit the floor in front of the lens (above the horizon) give NaN.
        """
        return self._rays_to_floor(self.pixel_rays_robot(uv))

    def floor_robot_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """Project floor points: ``(N, 2)`` metres, robot frame -> ``(N, 2) float64`` px.

        Applies lens distortion. Points behind the lens, or so far off-axis that the
        distortion polynomial no longer maps them one-to-one, give NaN. Points that
        project outside the image are returned as they are (not clipped).
        """
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        p = np.column_stack([xy, np.zeros(len(xy))]) - self.position_robot_m
        pc = p @ self.rotation_robot_from_camera  # R^T applied to row vectors
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = np.where(z > 0.0, pc[:, 0] / z, np.nan)
            yn = np.where(z > 0.0, pc[:, 1] / z, np.nan)
        r2 = xn * xn + yn * yn
        with np.errstate(invalid="ignore"):
            fold = r2 > self._max_radius_sq
        xn[fold] = np.nan
        yn[fold] = np.nan
        xd, yd = self._distort(xn, yn)
        k = self.intrinsics
        return np.column_stack([k.fx_px * xd + k.cx_px, k.fy_px * yd + k.cy_px])

    def footprint_robot(self, samples_per_edge: int = 16) -> np.ndarray:
        """Outline of the image border on the floor, ``(4 * samples_per_edge, 2)`` metres.

        Robot frame, counter-clockwise, not closed (the first point is not repeated).
        The border is the outer edge of the pixels (``-0.5`` to ``width_px - 0.5``), so
        the outline curves with the lens distortion when ``samples_per_edge > 1``.
        Raises ``ValueError`` when part of the border does not see the floor.
        """
        n = int(samples_per_edge)
        if n < 1:
            raise ValueError("samples_per_edge must be >= 1")
        u0, u1 = -0.5, self.width_px - 0.5
        v0, v1 = -0.5, self.height_px - 0.5
        t = np.arange(n) / n
        top = np.column_stack([u0 + (u1 - u0) * t, np.full(n, v0)])
        right = np.column_stack([np.full(n, u1), v0 + (v1 - v0) * t])
        bottom = np.column_stack([u1 - (u1 - u0) * t, np.full(n, v1)])
        left = np.column_stack([np.full(n, u0), v1 - (v1 - v0) * t])
        poly = self.pixel_to_floor_robot(np.vstack([top, right, bottom, left]))
        if not np.all(np.isfinite(poly)):
            raise ValueError("part of the image border does not see the floor (camera tilted above the horizon)")
        if polygon_area_signed(poly) < 0.0:
            poly = poly[::-1].copy()
        return poly

    def footprint_reach_m(self, samples_per_edge: int = 8) -> float:
        """Twice the farthest footprint point from the robot's origin, metres: two robot
        poses further apart than this cannot see a common patch of floor (whatever their
        headings)."""
        return _reach_m(self.footprint_robot(samples_per_edge))

    def metres_per_px_at_centre(self) -> float:
        """Floor distance covered by one pixel at the principal point, metres.

        The mean of the horizontal and vertical pixel sizes (they differ under tilt);
        equals ``height_m / fx`` for an untilted camera with ``fx = fy``.
        """
        c = np.array([[self.intrinsics.cx_px, self.intrinsics.cy_px]])
        pts = self.pixel_to_floor_robot(
            np.vstack([c - [0.5, 0.0], c + [0.5, 0.0], c - [0.0, 0.5], c + [0.0, 0.5]])
        )
        du = float(np.linalg.norm(pts[1] - pts[0]))
        dv = float(np.linalg.norm(pts[3] - pts[2]))
        return 0.5 * (du + dv)

    # ------------------------------------------------------- precomputed grids

    @cached_property
    def _pixel_grid(self) -> tuple[np.ndarray, np.ndarray]:
        u, v = np.meshgrid(np.arange(self.width_px, dtype=np.float64), np.arange(self.height_px, dtype=np.float64))
        uv = np.column_stack([u.ravel(), v.ravel()])
        rays = self.pixel_rays_robot(uv).reshape(self.height_px, self.width_px, 3)
        floor = self._rays_to_floor(rays)
        rays.setflags(write=False)
        floor.setflags(write=False)
        return rays, floor

    def undistorted_rays(self) -> np.ndarray:
        """Viewing ray of every pixel centre, ``(height_px, width_px, 3) float64``, robot frame.

        Computed once per model and cached (read-only); see :meth:`pixel_rays_robot`.
        """
        return self._pixel_grid[0]

    def pixel_floor_grid_robot(self) -> np.ndarray:
        """Floor point of every pixel centre, ``(height_px, width_px, 2) float64`` metres.

        Robot frame; NaN where a pixel does not see the floor. Computed once per model
        and cached (read-only): a renderer only has to apply the robot's pose to it.
        """
        return self._pixel_grid[1]


def polygon_area_signed(poly_xy: np.ndarray) -> float:
    """Shoelace area of a simple polygon ``(N, 2)``, positive when counter-clockwise."""
    p = np.asarray(poly_xy, dtype=np.float64)
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


# ----------------------------------------------------------- footprints on the floor


def footprint_world(camera: FloorCameraModel, pose_xyyaw: np.ndarray,
                    samples_per_edge: int = 16) -> np.ndarray:
    """The image's footprint on the floor at robot pose ``pose_xyyaw``: ``(M, 2)`` metres.

    World frame, counter-clockwise. The outline follows the lens distortion, so with
    barrel distortion it is pincushion-shaped (not convex).
    """
    from robotd.base.geometry import transform_points

    return transform_points(np.asarray(pose_xyyaw, dtype=float),
                            camera.footprint_robot(samples_per_edge))


def overlap_ratio(poly_a: np.ndarray, poly_b: np.ndarray) -> float:
    """J = area(A and B) / area(A or B) of two simple polygons ``(M, 2)`` (paper 003, eq. 3).

    Exact polygon intersection (GEOS, through Shapely), valid for non-convex outlines.
    """
    import shapely

    a, b = shapely.polygons(np.asarray(poly_a, float)), shapely.polygons(np.asarray(poly_b, float))
    inter = shapely.area(shapely.intersection(a, b))
    union = shapely.area(a) + shapely.area(b) - inter
    return float(inter / union) if union > 0 else 0.0


def _reach_m(footprint: np.ndarray) -> float:
    """See :meth:`FloorCameraModel.footprint_reach_m`; ``footprint (M, 2)`` robot frame."""
    return 2.0 * float(np.max(np.hypot(footprint[:, 0], footprint[:, 1])))


def overlap_ratios(camera: FloorCameraModel, poses_a: np.ndarray, poses_b: np.ndarray,
                   samples_per_edge: int = 8) -> np.ndarray:
    """J for many pose pairs at once: ``(N, 3)`` and ``(N, 3)`` poses -> ``(N,)``.

    Pairs whose centres are further apart than the footprint's diameter are 0 without any
    polygon work; the rest are intersected exactly, vectorised through Shapely.
    """
    import shapely

    from robotd.base.geometry import compose, inverse

    pa = np.asarray(poses_a, float).reshape(-1, 3)
    pb = np.asarray(poses_b, float).reshape(-1, 3)
    out = np.zeros(len(pa))
    fp = camera.footprint_robot(samples_per_edge)  # (M, 2), robot frame
    reach = _reach_m(fp)
    near = np.hypot(pa[:, 0] - pb[:, 0], pa[:, 1] - pb[:, 1]) < reach
    if not np.any(near):
        return out
    # Work in A's frame: A is the fixed footprint, B is moved by the relative pose.
    rel = compose(inverse(pa[near]), pb[near])
    c, s = np.cos(rel[:, 2]), np.sin(rel[:, 2])
    bx = rel[:, None, 0] + c[:, None] * fp[None, :, 0] - s[:, None] * fp[None, :, 1]
    by = rel[:, None, 1] + s[:, None] * fp[None, :, 0] + c[:, None] * fp[None, :, 1]
    poly_a = shapely.polygons(fp)
    polys_b = shapely.polygons(np.stack([bx, by], axis=-1))
    inter = shapely.area(shapely.intersection(poly_a, polys_b))
    area = shapely.area(poly_a)
    out[near] = inter / (2.0 * area - inter)
    return out

