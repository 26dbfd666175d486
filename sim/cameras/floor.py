"""Rendering the virtual robot's downward floor camera.

Every pixel's floor point in the robot frame is computed once per camera model
(:meth:`robotd.base.camera.FloorCameraModel.pixel_floor_grid_robot`: undistortion, tilt,
mount). A frame then costs one 2-D rigid transform of that grid into floor-patch pixel
coordinates (``cv2.transform``) and one bilinear ``cv2.remap`` per exposure sample, plus
gain and sensor noise. Motion blur is rendered physically: the exposure is split into
sub-exposures spaced at most ``blur_step_px`` apart in the image, each rendered at the
robot's pose at that instant (constant ``v``, ``w`` arc), and averaged. That handles
translation, rotation and their mix, with the tilt and distortion of the real lens.

Photometry, in grey levels (0..255) of the floor photo:
``I = gain(t) * vignette(u, v) * mean over the exposure of floor(u, v)``, with
``gain(t) = exposure_s / reference_exposure_s * (1 + drift_amplitude * sin(2 pi t /
drift_period_s + drift_phase_rad))``; then shot noise of variance ``I /
electrons_per_level`` and read noise of sigma ``noise_sigma``, rounding and clipping.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, fields

import cv2
import numpy as np

from robotd.base.errors import ConfigError
from robotd.base.camera import FloorCameraModel
from robotd.base.geometry import compose
from sim.cameras.device import VirtualCamera
from sim.route import Motion
from sim.world.floor import FloorSource

__all__ = ["FloorRenderer", "RenderParams", "floor_camera"]


@dataclass(frozen=True)
class RenderParams:
    """Floor camera exposure, blur and sensor model.

    Fields:
        exposure_s: exposure time, seconds. Sets both motion blur and brightness.
        reference_exposure_s: exposure, seconds, at which the image has the floor photo's
            own grey levels (gain 1 without drift).
        motion_blur: render the motion during the exposure (sub-exposure averaging).
        blur_step_px: largest image-space spacing between sub-exposure samples, pixels.
        max_blur_samples: cap on the sub-exposures per frame (cost grows linearly).
        noise_sigma: read noise, grey levels (1 sigma); 0 disables it.
        shot_noise: add photon shot noise (variance proportional to brightness).
        electrons_per_level: sensor conversion gain, electrons per grey level; shot-noise
            variance in grey levels^2 is ``I / electrons_per_level``.
        drift_amplitude: relative amplitude of the slow gain drift (auto-exposure hunting,
            lighting), e.g. 0.15 for +-15 %; 0 disables it.
        drift_period_s: period of the drift, seconds.
        drift_phase_rad: phase of the drift at ``t_s = 0``, radians.
        vignetting: relative brightness loss at the image corners (cos^4-like radial
            fall-off); 0 disables it, 0.3 is a typical wide lens.
    """

    exposure_s: float = 0.004
    reference_exposure_s: float = 0.004
    motion_blur: bool = True
    blur_step_px: float = 1.0
    max_blur_samples: int = 9
    noise_sigma: float = 2.0
    shot_noise: bool = True
    electrons_per_level: float = 40.0
    drift_amplitude: float = 0.15
    drift_period_s: float = 40.0
    drift_phase_rad: float = 0.0
    vignetting: float = 0.0

    def __post_init__(self) -> None:
        ok = {
            "exposure_s": self.exposure_s >= 0.0,
            "reference_exposure_s": self.reference_exposure_s > 0.0,
            "blur_step_px": self.blur_step_px > 0.0,
            "max_blur_samples": self.max_blur_samples >= 1,
            "noise_sigma": self.noise_sigma >= 0.0,
            "electrons_per_level": self.electrons_per_level > 0.0,
            "drift_amplitude": 0.0 <= self.drift_amplitude < 1.0,
            "drift_period_s": self.drift_period_s > 0.0,
            "vignetting": 0.0 <= self.vignetting < 1.0,
        }
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise ConfigError(f"render parameter {f.name} must be finite, got {v!r}")
        for name, good in ok.items():
            if not good:
                raise ConfigError(f"render parameter {name} out of range: {getattr(self, name)!r}")


def _remap(src: np.ndarray, maps: np.ndarray) -> np.ndarray:
    """``src`` sampled (bilinear, zero outside) at ``maps`` ``(H, W, 2) float32`` pixel
    coordinates. OpenCV's stubs require a second map, which ``cv2.remap`` documents as
    empty when the first holds (x, y) pairs."""
    out: np.ndarray = cv2.remap(src, maps, None, cv2.INTER_LINEAR,  # type: ignore[call-overload]
                                borderMode=cv2.BORDER_CONSTANT)
    return out


class FloorRenderer:
    """Renders ``(height_px, width_px) uint8`` floor-camera frames at given robot poses.

    ``floor`` is any :class:`~sim.world.floor.FloorSource` (normally a
    :class:`~sim.world.floor.Floor`); ``rng`` draws the sensor noise, so the same seed and
    the same sequence of calls give the same frames. Floor pixels are fetched in patches
    ``patch_margin_m`` larger than the view on every side and reused while the view stays
    inside, so tile lookups happen about once per ``patch_margin_m`` of travel. Pixels
    that see no floor, or floor farther than ``max_range_m`` from the robot (a camera
    tilted towards the horizon), are rendered black.
    """

    def __init__(
        self,
        floor: FloorSource,
        camera: FloorCameraModel,
        params: RenderParams,
        rng: np.random.Generator,
        patch_margin_m: float = 0.3,
        max_range_m: float = 1.5,
    ) -> None:
        self.floor = floor
        self.camera = camera
        self.params = params
        self._rng = rng
        self._margin_m = float(patch_margin_m)
        grid = camera.pixel_floor_grid_robot()
        valid = np.all(np.isfinite(grid), axis=2)
        with np.errstate(invalid="ignore"):
            valid &= np.hypot(grid[..., 0], grid[..., 1]) <= max_range_m
        if not valid.any():
            raise ConfigError("the floor camera sees no floor (tilted above the horizon)")
        self._grid = np.where(valid[..., None], grid, 0.0).astype(np.float32)
        self._invalid = None if valid.all() else ~valid
        r = np.hypot(grid[..., 0], grid[..., 1])
        self._reach_m = float(np.max(r[valid]))  # farthest floor point from the robot origin
        self._mpp_centre = camera.metres_per_px_at_centre()
        self._vignette = self._vignette_map() if params.vignetting > 0.0 else None
        self._patch: np.ndarray | None = None  # float32 floor pixels
        self._patch_affine = np.zeros((2, 3))
        self._patch_box = (math.inf, math.inf, -math.inf, -math.inf)
        self.patches_fetched = 0

    # ------------------------------------------------------------------ model

    def gain_at(self, t_s: float) -> float:
        """Photometric gain at time ``t_s`` (exposure ratio times the slow drift)."""
        p = self.params
        drift = 1.0 + p.drift_amplitude * math.sin(2.0 * math.pi * t_s / p.drift_period_s + p.drift_phase_rad)
        return p.exposure_s / p.reference_exposure_s * drift

    def blur_extent_px(self, v_mps: float, w_radps: float) -> float:
        """Upper bound of how far any pixel's floor point moves during the exposure, pixels."""
        travel_m = self.params.exposure_s * (abs(v_mps) + abs(w_radps) * self._reach_m)
        return travel_m / self._mpp_centre

    def blur_samples(self, v_mps: float, w_radps: float) -> int:
        """Number of sub-exposures rendered for this motion (1 = no blur)."""
        p = self.params
        extent = self.blur_extent_px(v_mps, w_radps)
        if not p.motion_blur or extent < 0.5 * p.blur_step_px:
            return 1
        return int(min(p.max_blur_samples, math.ceil(extent / p.blur_step_px) + 1))

    def _vignette_map(self) -> np.ndarray:
        c = self.camera.intrinsics
        u, v = np.meshgrid(np.arange(c.width_px) - c.cx_px, np.arange(c.height_px) - c.cy_px)
        r2 = (u / c.fx_px) ** 2 + (v / c.fy_px) ** 2
        corner = max(
            ((0 - c.cx_px) / c.fx_px) ** 2 + ((0 - c.cy_px) / c.fy_px) ** 2,
            ((c.width_px - 1 - c.cx_px) / c.fx_px) ** 2 + ((c.height_px - 1 - c.cy_px) / c.fy_px) ** 2,
            ((0 - c.cx_px) / c.fx_px) ** 2 + ((c.height_px - 1 - c.cy_px) / c.fy_px) ** 2,
            ((c.width_px - 1 - c.cx_px) / c.fx_px) ** 2 + ((0 - c.cy_px) / c.fy_px) ** 2,
        )
        # cos^4 law shape, scaled so the corner loses exactly `vignetting`.
        fall = 1.0 / (1.0 + r2) ** 2
        fall_corner = 1.0 / (1.0 + corner) ** 2
        m = 1.0 - self.params.vignetting * (1.0 - fall) / (1.0 - fall_corner)
        return m.astype(np.float32)

    # ---------------------------------------------------------------- patches

    def _ensure_patch(self, x_m: float, y_m: float, extra_m: float) -> None:
        need = self._reach_m + extra_m + 4.0 * self.floor.metres_per_px
        x0, y0, x1, y1 = self._patch_box
        if x0 <= x_m - need and y0 <= y_m - need and x1 >= x_m + need and y1 >= y_m + need:
            return
        half = need + self._margin_m
        img, affine = self.floor.patch(x_m - half, y_m - half, x_m + half, y_m + half)
        self._patch = img.astype(np.float32)
        self._patch_affine = np.asarray(affine, dtype=np.float64)
        self._patch_box = (x_m - half, y_m - half, x_m + half, y_m + half)
        self.patches_fetched += 1

    def _maps_at(self, pose: np.ndarray) -> np.ndarray:
        """Patch pixel coordinates of every image pixel at robot pose, ``(H, W, 2) float32``."""
        c, s = math.cos(pose[2]), math.sin(pose[2])
        a = self._patch_affine
        rot = np.array([[c, -s], [s, c]])
        m = np.empty((2, 3))
        m[:, :2] = a[:, :2] @ rot
        m[:, 2] = a[:, :2] @ pose[:2] + a[:, 2]
        return cv2.transform(self._grid, m)

    # ----------------------------------------------------------------- render

    def render_clean(self, pose_xyyaw: np.ndarray, v_mps: float = 0.0, w_radps: float = 0.0) -> np.ndarray:
        """The exposure-averaged floor radiance before gain and noise, ``(H, W) float32``.

        ``pose_xyyaw`` is the robot pose at mid-exposure, ``(x_m, y_m, yaw_rad)``;
        ``v_mps`` and ``w_radps`` its forward and turn rates, held during the exposure.
        """
        pose = np.asarray(pose_xyyaw, dtype=np.float64).reshape(3)
        p = self.params
        n = self.blur_samples(v_mps, w_radps)
        half_t = 0.5 * p.exposure_s if n > 1 else 0.0
        self._ensure_patch(float(pose[0]), float(pose[1]), abs(v_mps) * half_t)
        assert self._patch is not None
        if n == 1:
            out = _remap(self._patch, self._maps_at(pose))
        else:
            images = (_remap(self._patch, self._maps_at(compose(pose, _arc(v_mps, w_radps, tau))))
                      for tau in (-half_t + 2.0 * half_t * k / (n - 1) for k in range(n)))
            out = next(images)
            for img in images:
                out = cv2.add(out, img)
            out *= np.float32(1.0 / n)
        if self._invalid is not None:
            out[self._invalid] = 0.0
        return out

    def render(self, pose_xyyaw: np.ndarray, v_mps: float, w_radps: float, t_s: float) -> np.ndarray:
        """One camera frame, ``(height_px, width_px) uint8``.

        ``pose_xyyaw``: the robot pose at mid-exposure (world frame, metres, radians);
        ``v_mps``, ``w_radps``: its forward speed and turn rate during the exposure;
        ``t_s``: the frame time, seconds (drives the slow gain drift).
        """
        p = self.params
        img = self.render_clean(pose_xyyaw, v_mps, w_radps)
        gain = np.float32(self.gain_at(t_s))
        if self._vignette is not None:
            img = cv2.multiply(img, self._vignette, scale=float(gain))
        else:
            img *= gain
        if p.shot_noise or p.noise_sigma > 0.0:
            z = self._rng.standard_normal(img.shape, dtype=np.float32)
            if p.shot_noise:
                var = np.maximum(img, 0.0) * np.float32(1.0 / p.electrons_per_level)
                var += np.float32(p.noise_sigma**2)
                z *= np.sqrt(var)
            else:
                z *= np.float32(p.noise_sigma)
            img += z
        img += np.float32(0.5)
        np.clip(img, 0.0, 255.0, out=img)
        return img.astype(np.uint8)


def _arc(v_mps: float, w_radps: float, dt_s: float) -> np.ndarray:
    """Body-frame displacement ``(dx_m, dy_m, dyaw_rad)`` after ``dt_s`` at constant ``v``, ``w``."""
    th = w_radps * dt_s
    if abs(th) < 1e-9:
        return np.array([v_mps * dt_s, 0.0, th])
    r = v_mps / w_radps
    return np.array([r * math.sin(th), r * (1.0 - math.cos(th)), th])


def floor_camera(renderer: FloorRenderer, motion: Motion, fps: float, *, capacity: int,
                 lossless: bool, stop: threading.Event | None = None) -> VirtualCamera:
    """The downward floor camera along ``motion``: frames every ``1 / fps`` s from 0 to the
    end of the motion (excluded), each rendered at the true pose and velocity of its time
    (black while the robot is carried, :attr:`sim.route.Motion.lifted`); see :class:`~sim.cameras.device.VirtualCamera` for the hand-over."""
    def render(t_s: float) -> np.ndarray:
        v, w = motion.velocity_at(t_s)
        image = renderer.render(motion.pose_at(t_s), v, w, t_s)
        return np.zeros_like(image) if motion.lifted_at(t_s) else image  # carried: covered

    times_s = np.arange(0.0, float(motion.t_s[-1]), 1.0 / fps)
    return VirtualCamera("floor", times_s, render, capacity=capacity, lossless=lossless, stop=stop)
