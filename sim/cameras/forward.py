"""Rendering the virtual robot's forward camera in a :class:`~sim.world.rooms.WallWorld`.

A column raycaster, exact for this world (vertical walls on 2-D segments, a flat floor and
ceiling) and a level pinhole camera (optical axis horizontal, no roll): a vertical line in
the world stays a vertical image column, so one ray per column finds everything that
column sees.

Per frame (all numpy/OpenCV, no Python loop over pixels):

1. Column ``u`` looks along ``d_u = f + x_u r`` (``f`` the camera heading, ``r`` its right,
   ``x_u = (u - cx) / fx``): an unnormalised direction whose forward component is 1, so the
   ray parameter of a hit *is* the depth ``z`` along the optical axis. All ``W x K`` ray-wall
   intersections are solved at once (2-D cross products); the nearest hit with ``t > 0``
   and the wall parameter in ``[0, 1]`` is the column's wall, depth and texture column.
2. Row ``v`` of that column sees the wall at height ``h = h_cam - (v - cy) z / fy``; it is
   a wall pixel when ``0 <= h <= wall height``, which is the same as "the wall is nearer
   than the floor or ceiling point the pixel would otherwise see", ``z < z_plane(v)`` with
   ``z_plane = h_cam fy / (v - cy)`` below the horizon and ``(H - h_cam) fy / (cy - v)``
   above it. Floor and ceiling pixels look up their world point ``o + z_plane d_u`` in a
   tiled texture.
3. Every pixel's atlas coordinate (wall texel, or floor / ceiling texel wrapped into the
   tile's central copy) at the mip level matching its texel-per-pixel rate, then one
   bilinear ``cv2.remap`` of the atlas, and sensor noise.

Ground truth: :meth:`ForwardRenderer.visible_cells` gives the wall cell each column sees;
:func:`view_histograms`, :func:`view_overlap` and :func:`same_place_matrix` turn those
into the ``N x N`` same-place matrix of :mod:`robotd.forward.evaluation`.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import cv2
import numpy as np

from robotd.base.camera import CameraIntrinsics
from robotd.base.errors import ConfigError
from sim.cameras.device import VirtualCamera
from sim.route import Motion
from sim.world.rooms import MIP_LEVELS, WallWorld

__all__ = ["ColumnHits", "ForwardCameraModel", "ForwardRenderParams", "ForwardRenderer",
           "forward_camera", "same_place_matrix", "view_histograms", "view_overlap"]


def _default_intrinsics() -> CameraIntrinsics:
    # A Kinect / Astra-like RGB camera: 62.7 deg horizontal, 49 deg vertical field of view.
    return CameraIntrinsics(width_px=640, height_px=480, fx_px=525.0, fy_px=525.0,
                            cx_px=319.5, cy_px=239.5)


@dataclass(frozen=True)
class ForwardCameraModel:
    """The forward camera: pinhole intrinsics and its mount on the robot.

    Fields:
        intrinsics: image size, focal lengths, principal point; distortion must be zero
            (the raycaster renders straight lines).
        height_m: height of the optical centre above the floor, metres.
        x_m, y_m: position of the optical centre in the robot frame (REP-103: x forward,
            y left), metres.
        yaw_rad: heading of the optical axis relative to the robot's x axis, radians. The
            axis is level (no pitch, no roll): a column raycaster needs vertical walls to
            stay vertical in the image.
    """

    intrinsics: CameraIntrinsics = field(default_factory=_default_intrinsics)
    height_m: float = 0.6
    x_m: float = 0.1
    y_m: float = 0.0
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        if any(self.intrinsics.distortion):
            raise ConfigError("forward camera: lens distortion is not rendered; use zero distortion")
        for name in ("height_m", "x_m", "y_m", "yaw_rad"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError(f"forward camera {name} must be finite")
        if self.height_m <= 0.0:
            raise ConfigError(f"forward camera height_m must be positive, got {self.height_m}")

    def camera_pose(self, pose_xyyaw: np.ndarray) -> tuple[float, float, float]:
        """World ``(x_m, y_m, heading_rad)`` of the optical centre at robot pose ``(x, y, yaw)``."""
        x, y, yaw = (float(a) for a in np.asarray(pose_xyyaw, float).reshape(3))
        c, s = math.cos(yaw), math.sin(yaw)
        return x + c * self.x_m - s * self.y_m, y + s * self.x_m + c * self.y_m, yaw + self.yaw_rad


@dataclass(frozen=True)
class ForwardRenderParams:
    """Photometry of the forward camera.

    Fields:
        noise_sigma: Gaussian read noise, grey levels (1 sigma); 0 disables it.
        gain: multiplies the world's grey levels (exposure).
        mipmap: pick the atlas level per pixel from its texel rate (no aliasing shimmer on
            distant walls); off renders everything from the full-resolution level.
    """

    noise_sigma: float = 2.0
    gain: float = 1.0
    mipmap: bool = True

    def __post_init__(self) -> None:
        if not (self.noise_sigma >= 0.0 and math.isfinite(self.noise_sigma)):
            raise ConfigError(f"forward render noise_sigma must be >= 0, got {self.noise_sigma!r}")
        if not (self.gain > 0.0 and math.isfinite(self.gain)):
            raise ConfigError(f"forward render gain must be positive, got {self.gain!r}")


@dataclass(frozen=True)
class ColumnHits:
    """What each image column sees, ``(W,)`` arrays: ``wall`` index (-1: none), ``depth_m``
    along the optical axis (inf: none), ``tex_m`` position on the wall measured from its
    end ``b`` (the texture's column 0), metres."""

    wall: np.ndarray
    depth_m: np.ndarray
    tex_m: np.ndarray


class ForwardRenderer:
    """Renders ``(height_px, width_px) uint8`` grey forward-camera frames at robot poses.

    ``rng`` draws the sensor noise: the same seed and the same calls give the same frames.
    """

    def __init__(self, world: WallWorld, camera: ForwardCameraModel = ForwardCameraModel(),
                 params: ForwardRenderParams = ForwardRenderParams(),
                 rng: np.random.Generator | None = None) -> None:
        self.world = world
        self.camera = camera
        self.params = params
        self._rng = rng if rng is not None else np.random.default_rng(0)
        # Read noise: four frames' worth of rounded Gaussian samples drawn once; each frame
        # adds a window starting at a random offset (drawing 300k normals per frame would
        # cost more than rendering the frame).
        n_px = camera.intrinsics.width_px * camera.intrinsics.height_px
        self._noise_pool = np.rint(self._rng.standard_normal(4 * n_px) * params.noise_sigma
                                   ).astype(np.int16) if params.noise_sigma > 0.0 else np.zeros(0, np.int16)
        k = camera.intrinsics
        self._xn = ((np.arange(k.width_px) - k.cx_px) / k.fx_px).astype(np.float64)
        self._vv = (np.arange(k.height_px) - k.cy_px).astype(np.float32)  # (H,)
        wp = world.params
        h_cam = camera.height_m
        if h_cam >= wp.wall_height_m:
            raise ConfigError("forward camera is above the ceiling")
        with np.errstate(divide="ignore"):
            z_floor = h_cam * k.fy_px / self._vv
            z_ceil = (wp.wall_height_m - h_cam) * k.fy_px / -self._vv
        below = self._vv > 0
        self._below = below
        self._z_plane = np.where(below, z_floor, z_ceil).astype(np.float64)
        self._z_plane[~np.isfinite(self._z_plane) | (self._z_plane < 0)] = 1e6
        self._z_plane = np.minimum(self._z_plane, 1e6)
        self._e = world.b_m - world.a_m  # (K, 2)
        self._len = np.linalg.norm(self._e, axis=1)
        # Per-row plane texture constants: texels per metre, period and tile origin.
        self._plane_ppm = np.where(below, wp.floor_px_per_m, wp.ceiling_px_per_m).astype(np.float32)
        self._period = np.where(below[:, None], np.array(world.floor_period_px, np.float32),
                                np.array(world.ceiling_period_px, np.float32)).astype(np.float32)  # (H, 2)
        self._origin = np.where(below[:, None], world.floor_origin, world.ceiling_origin)  # (H, 2)
        # Plane mip level per row: the larger of the along-row and across-row texel rates.
        zp = self._z_plane
        rate_u = self._plane_ppm * zp / k.fx_px
        rate_v = self._plane_ppm * zp ** 2 / (np.where(below, h_cam, wp.wall_height_m - h_cam) * k.fy_px)
        self._plane_level = self._level(np.maximum(rate_u, rate_v))
        self._inv_period = (1.0 / self._period).astype(np.float32)
        self._z_plane32 = self._z_plane.astype(np.float32)
        lp = self._plane_level
        sp = 0.5 ** lp
        offp = world.level_offsets[lp]
        # Level-l coordinate of level-0 coordinate c is (c + 0.5) 2^-l - 0.5; c = origin + p - 0.5.
        self._plane_scale = sp.astype(np.float32)[:, None]
        self._plane_bx = (offp[:, 0] + self._origin[:, 0] * sp - 0.5).astype(np.float32)[:, None]
        self._plane_by = (offp[:, 1] + self._origin[:, 1] * sp - 0.5).astype(np.float32)[:, None]

    # ---------------------------------------------------------------- geometry

    def _level(self, rate: np.ndarray) -> np.ndarray:
        if not self.params.mipmap:
            return np.zeros(np.shape(rate), np.int64)
        with np.errstate(divide="ignore"):
            lv = np.floor(np.log2(np.maximum(rate, 1.0)))
        return np.clip(lv, 0, MIP_LEVELS - 1).astype(np.int64)

    def column_rays(self, pose_xyyaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera centre ``(2,)`` and per-column directions ``(W, 2)`` (forward component 1)."""
        x, y, h = self.camera.camera_pose(pose_xyyaw)
        f = np.array([math.cos(h), math.sin(h)])
        r = np.array([math.sin(h), -math.cos(h)])
        return np.array([x, y]), f[None, :] + self._xn[:, None] * r[None, :]

    def cast(self, pose_xyyaw: np.ndarray) -> ColumnHits:
        """Intersect every column's ray with every wall; the nearest hit per column."""
        o, d = self.column_rays(pose_xyyaw)
        e = self._e
        w = self.world.a_m - o  # (K, 2)
        denom = d[:, 0:1] * e[None, :, 1] - d[:, 1:2] * e[None, :, 0]  # d x e, (W, K)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0])[None, :] / denom
            sig = (w[None, :, 0] * d[:, 1:2] - w[None, :, 1] * d[:, 0:1]) / denom
            ok = (t > 1e-9) & (sig >= 0.0) & (sig <= 1.0)
        t = np.where(ok, t, np.inf)
        k = np.argmin(t, axis=1)
        cols = np.arange(len(k))
        depth = t[cols, k]
        hit = np.isfinite(depth)
        tex_m = (1.0 - sig[cols, k]) * self._len[k]
        return ColumnHits(np.where(hit, k, -1), depth, np.where(hit, tex_m, 0.0))

    def visible_cells(self, pose_xyyaw: np.ndarray) -> np.ndarray:
        """``(W,) int64``: the ground-truth wall cell each column sees (-1: none)."""
        hits = self.cast(pose_xyyaw)
        return self.cells_of(hits)

    def cells_of(self, hits: ColumnHits) -> np.ndarray:
        """``(W,) int64`` wall cells of :meth:`cast`'s hits (-1 where no wall)."""
        wp = self.world.params
        k = np.maximum(hits.wall, 0)
        n_k = np.ceil(self._len[k] / wp.cell_m - 1e-9).astype(np.int64)
        idx = np.clip(np.floor(hits.tex_m / wp.cell_m).astype(np.int64), 0, n_k - 1)
        return np.where(hits.wall >= 0, self.world.cell0[k] + idx, -1)

    # ----------------------------------------------------------------- render

    def maps(self, pose_xyyaw: np.ndarray, hits: ColumnHits | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Atlas coordinates of every pixel, ``map_x``, ``map_y`` ``(H, W) float32``, and the
        wall mask ``(H, W) bool`` (True where the pixel shows a wall)."""
        if hits is None:
            hits = self.cast(pose_xyyaw)
        world, k_int = self.world, self.camera.intrinsics
        wp = world.params
        ppm = wp.px_per_m
        o, d = self.column_rays(pose_xyyaw)
        kw = np.maximum(hits.wall, 0)
        z = np.where(hits.wall >= 0, hits.depth_m, 1e7)
        # Wall texel coordinates at level 0 (texel centres at integers).
        tx = world.tex_x0[kw] + hits.tex_m * ppm - 0.5  # (W,)
        rate_v = z * ppm / k_int.fy_px
        rate_h = np.abs(np.gradient(tx))
        same = np.ones_like(rate_h, bool)
        same[1:-1] = (kw[:-2] == kw[1:-1]) & (kw[1:-1] == kw[2:])
        rate = np.maximum(rate_v, np.where(same, rate_h, 0.0))
        lw = self._level(rate)
        scale = 0.5 ** lw
        off = world.level_offsets[lw]  # (W, 2)
        # Level-l coordinate of a level-0 coordinate c: (c + 0.5) * 2^-l - 0.5.
        wx = (off[:, 0] + (tx + 0.5) * scale - 0.5).astype(np.float32)
        y_top = world.tex_y0[kw] + (wp.wall_height_m - self.camera.height_m) * ppm - 0.5
        wy0 = (off[:, 1] + (y_top + 0.5) * scale - 0.5).astype(np.float32)
        wy1 = (rate_v * scale).astype(np.float32)
        wall_y = wy0[None, :] + self._vv[:, None] * wy1[None, :]
        # Floor and ceiling: world point of each pixel in the tile's texels, wrapped.
        a = (self._z_plane * self._plane_ppm).astype(np.float32)  # (H,) texels per unit of d
        px = (o[0] * self._plane_ppm).astype(np.float32)[:, None] + a[:, None] * d[None, :, 0].astype(np.float32)
        py = (-o[1] * self._plane_ppm).astype(np.float32)[:, None] - a[:, None] * d[None, :, 1].astype(np.float32)
        # Wrap into [0, period): a - floor(a / P) * P (several times faster than np.mod).
        px -= np.floor(px * self._inv_period[:, 0:1]) * self._period[:, 0:1]
        py -= np.floor(py * self._inv_period[:, 1:2]) * self._period[:, 1:2]
        # Texel centre of plane coordinate p sits at p - 0.5 in the tile's central copy.
        px *= self._plane_scale
        px += self._plane_bx
        py *= self._plane_scale
        py += self._plane_by
        # Select wall or plane without np.where (a blend by a 0/1 mask is 5x cheaper).
        mask = z.astype(np.float32)[None, :] < self._z_plane32[:, None]
        mf = mask.astype(np.float32)
        map_x = px + mf * (wx[None, :] - px)
        map_y = py + mf * (wall_y - py)
        return map_x, map_y, mask

    def render_clean(self, pose_xyyaw: np.ndarray) -> np.ndarray:
        """The noiseless frame, ``(H, W) uint8``."""
        mx, my, _ = self.maps(pose_xyyaw)
        out = cv2.remap(self.world.atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if self.params.gain != 1.0:
            out = cv2.convertScaleAbs(out, alpha=self.params.gain)
        return out

    def render(self, pose_xyyaw: np.ndarray, t_s: float = 0.0) -> np.ndarray:
        """One camera frame at robot pose ``(x_m, y_m, yaw_rad)``, ``(H, W) uint8``.

        ``t_s`` is the frame time (unused today: no motion blur or gain drift)."""
        img = self.render_clean(pose_xyyaw)
        if self.params.noise_sigma > 0.0:
            n = img.size
            start = int(self._rng.integers(0, len(self._noise_pool) - n))
            noisy = img.astype(np.int16).ravel()
            noisy += self._noise_pool[start:start + n]
            np.clip(noisy, 0, 255, out=noisy)
            img = noisy.astype(np.uint8).reshape(img.shape)
        return img


# ---------------------------------------------------------------- ground truth


def view_histograms(renderer: ForwardRenderer, poses: np.ndarray) -> np.ndarray:
    """``(N, n_cells) float32``: per robot pose ``(N, 3)``, the fraction of image columns
    that see each wall cell (rows sum to the fraction of columns that see a wall)."""
    poses = np.asarray(poses, float).reshape(-1, 3)
    w = renderer.camera.intrinsics.width_px
    out = np.zeros((len(poses), renderer.world.n_cells), np.float32)
    for i, pose in enumerate(poses):
        cells = renderer.visible_cells(pose)
        cells = cells[cells >= 0]
        out[i] = np.bincount(cells, minlength=renderer.world.n_cells) / w
    return out


def view_overlap(hist: np.ndarray, block: int = 256) -> np.ndarray:
    """``(N, N) float32`` weighted Jaccard overlap of views: ``sum_c min(h_i, h_j) /
    sum_c max(h_i, h_j)`` over wall cells ``c``. 1 for the same view, 0 when the two
    images see no wall cell in common; a cell seen over fewer columns (farther away, more
    obliquely) counts less."""
    h = np.asarray(hist, np.float32)
    n = len(h)
    tot = h.sum(axis=1)
    out = np.zeros((n, n), np.float32)
    for i0 in range(0, n, block):
        hi = h[i0:i0 + block]
        mins = np.minimum(hi[:, None, :], h[None, :, :]).sum(axis=2)
        maxs = tot[i0:i0 + block, None] + tot[None, :] - mins
        with np.errstate(invalid="ignore", divide="ignore"):
            out[i0:i0 + block] = np.where(maxs > 0, mins / maxs, 0.0)
    return out


def same_place_matrix(overlap: np.ndarray, threshold: float = 0.2, leave_below: float = 0.1,
                      ) -> np.ndarray:
    """``(N, N) bool`` symmetric "same place on a revisit" labels from :func:`view_overlap`.

    Images ``j < i`` show the same place when their overlap is at least ``threshold`` *and*
    the robot left the place in between: some image ``k``, ``j < k < i``, overlaps ``j``
    by less than ``leave_below``. Without that condition every image would be "the same
    place" as the images just before it while the robot drives down a corridor, which is
    not a loop closure (the ground truth of paper 000's and RTAB-Map's sequences marks
    revisits only). The diagonal is False.
    """
    ov = np.asarray(overlap, np.float32)
    n = len(ov)
    if ov.shape != (n, n):
        raise ValueError(f"overlap must be square, got {ov.shape}")
    # left[j, i]: some k in (j, i) with ov[j, k] < leave_below; first such k per j.
    low = ov < leave_below
    idx = np.arange(n)
    low &= idx[None, :] > idx[:, None]
    first_leave = np.where(low.any(axis=1), np.argmax(low, axis=1), n)  # (N,) per j
    later = idx[None, :] > first_leave[:, None]  # [j, i]: i after j's first departure
    same = (ov >= threshold) & later
    same = same | same.T
    np.fill_diagonal(same, False)
    return same


# ----------------------------------------------------------------- the device


def forward_camera(renderer: ForwardRenderer, motion: Motion, fps: float, *, capacity: int,
                   lossless: bool, stop: threading.Event | None = None) -> VirtualCamera:
    """The forward camera along ``motion``: frames every ``1 / fps`` s from 0 to the end of
    the motion (excluded), each rendered at the true pose of its time (black while the robot
    is carried)."""
    def render(t_s: float) -> np.ndarray:
        image = renderer.render(motion.pose_at(t_s), t_s)
        return np.zeros_like(image) if motion.lifted_at(t_s) else image  # carried: covered

    times_s = np.arange(0.0, float(motion.t_s[-1]), 1.0 / fps)
    return VirtualCamera("forward", times_s, render, capacity=capacity, lossless=lossless, stop=stop)
