"""Floor visual odometry: the rigid motion between consecutive keyframes (paper 003, Sec. IV-D).

For keyframes ``k-1`` and ``k`` (paper 003, Sec. IV-D):

1. their compact descriptors are matched (:func:`robotd.floor.match.local_score`: ratio
   test, orientation histogram, 2-point RANSAC in pixels: the "geometric consistency"
   CDVS already performs);
2. the matched pixels become metric floor points in each keyframe's robot frame through
   the camera-to-floor calibration (:meth:`FloorCameraModel.pixel_to_floor_robot`),
   ``P_{k-1}`` and ``P_k``; by default the pixels are where the detector found the
   keypoints (``keypoint_positions = "detected"``, kept beside the descriptor), not the
   descriptor's coordinate grid, whose quantisation (4 mm of floor on the default camera)
   would otherwise set the step's precision; ``"coded"`` is the paper's reuse of the
   descriptor as it is;
3. "a few RANSAC cycles remove possible remaining outliers": 2-point rigid hypotheses on
   the floor points, inliers within ``ransac_threshold_m`` (metres, not pixels: the
   camera's distortion and tilt no longer matter here);
4. the rigid transform is refined on all inliers by the closed-form least-squares fit
   (centroids, then the rotation of the cross-covariance: the paper's SVD, in 2-D a
   single ``atan2``; :func:`robotd.base.geometry.rigid_fit_2d`), twice;
5. its covariance comes from the fit residuals and the inlier count
   (:func:`robotd.base.geometry.rigid_fit_2d_covariance`).

The result ``delta = (dx_m, dy_m, dyaw_rad)`` is the pose of keyframe ``k`` in the robot
frame of keyframe ``k-1`` (``P_{k-1} ~ R(dyaw) P_k + (dx, dy)``), the quantity a pose-graph
odometry edge and :func:`robotd.base.geometry.compose` chain.

Expected failures are values, not exceptions (``VoResult.reason``): ``NO_PREVIOUS_KEYFRAME``
(the first step), ``TOO_FEW_MATCHES`` (the descriptor matcher dismissed the pair, or fewer
than ``min_inliers`` matches reach the floor), ``TOO_FEW_INLIERS`` (the metric RANSAC
keeps fewer than ``min_inliers``), ``DEGENERATE_GEOMETRY`` (the inliers are bunched
within ``min_spread_m``, so the rotation is not determined).

:func:`integrate` chains the steps into vision-only odometry (paper 003, Sec. V, Fig. 7);
where a step failed it takes a wheel + gyro increment instead, when one is given, and
counts it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any

import numpy as np

from robotd.base.config import FloorDetectorConfig, VisualOdometryConfig
from robotd.base.geometry import (compose, rigid_fit_2d, rigid_fit_2d_covariance,
                                  rigid_from_two_pairs, transform_points)
from robotd.floor.descriptor import MODES, FloorDescriptor, decode, extract_with_positions
from robotd.floor.match import MatchParams, local_score

__all__ = ["DEGENERATE_GEOMETRY", "KEYPOINT_POSITIONS", "NO_PREVIOUS_KEYFRAME", "TOO_FEW_INLIERS", "TOO_FEW_MATCHES",
           "FloorVisualOdometry", "VoParams", "VoReason", "VoResult", "VoTrack", "estimate_motion",
           "floor_motion", "floor_point_pairs", "integrate", "with_detected_positions"]

class VoReason(StrEnum):
    """Why a visual step failed (a :class:`~enum.StrEnum`: equal to its text; ``OK``, the
    empty text, is false)."""

    OK = ""
    NO_PREVIOUS_KEYFRAME = "NO_PREVIOUS_KEYFRAME"
    TOO_FEW_MATCHES = "TOO_FEW_MATCHES"
    TOO_FEW_INLIERS = "TOO_FEW_INLIERS"
    DEGENERATE_GEOMETRY = "DEGENERATE_GEOMETRY"


KEYPOINT_POSITIONS = ("detected", "coded")

NO_PREVIOUS_KEYFRAME = VoReason.NO_PREVIOUS_KEYFRAME
TOO_FEW_MATCHES = VoReason.TOO_FEW_MATCHES
TOO_FEW_INLIERS = VoReason.TOO_FEW_INLIERS
DEGENERATE_GEOMETRY = VoReason.DEGENERATE_GEOMETRY


@dataclass(frozen=True)
class VoParams:
    """Parameters of floor visual odometry.

    Fields:
        descriptor_mode: descriptor mode 1-6 (``[floor_detector] descriptor_mode``) of images given to :meth:`FloorVisualOdometry.step`
            (descriptors carry their own mode; consecutive ones must share it).
        min_inliers: fewest metric inliers of a usable step (and fewest matches worth a
            RANSAC); at least 3, so the residuals say something about the noise.
        ransac_threshold_m: largest distance, metres on the floor, between a point of
            keyframe ``k`` mapped by a hypothesis and its match in ``k-1`` (default 3 mm:
            about three pixels of the default camera, whose coded keypoint positions are
            on a 2 px grid).
        iterations: RANSAC hypotheses (2-point samples) per step.
        seed: seed of the RANSAC sampling; every step starts from it, so a step depends
            only on its two keyframes.
        min_spread_m: the inliers' RMS distance from their centroid must reach this,
            metres, or the step is ``DEGENERATE_GEOMETRY`` (rotation not determined).
        min_sigma_m: floor on the residual sigma per coordinate, metres, in the
            covariance (the position quantisation alone is ~0.6 mm on the default camera).
        keypoint_positions: ``"detected"`` (default): the keypoints where the detector found
            them (sub-pixel), when the step has them: an image described here, or
            positions given beside the descriptor (:meth:`FloorVisualOdometry.step`);
            ``"coded"``: the descriptor's grid positions, as paper 003 reuses the
            keyframe's descriptor. The matcher is the same either way; only the metric
            fit's points differ.
        min_sigma_detected_m: :attr:`min_sigma_m` for a step between two keyframes with
            detected positions (no grid's quantisation; a tenth of a pixel of the default
            camera).
        match: the descriptor matcher's parameters (step 1).
    """

    descriptor_mode: int = FloorDetectorConfig.descriptor_mode
    min_inliers: int = VisualOdometryConfig.min_inliers
    ransac_threshold_m: float = VisualOdometryConfig.ransac_threshold_m
    iterations: int = 100
    seed: int = 0
    min_spread_m: float = 0.02
    min_sigma_m: float = 0.0005
    keypoint_positions: str = VisualOdometryConfig.keypoint_positions
    min_sigma_detected_m: float = 0.0001
    match: MatchParams = field(default_factory=MatchParams)

    @classmethod
    def from_config(cls, section: VisualOdometryConfig, descriptor_mode: int) -> VoParams:
        """The params of a ``[visual_odometry]`` table (whose defaults these are), on
        descriptors of ``[floor_detector] descriptor_mode`` (the keyframe's are reused)."""
        return cls(descriptor_mode=descriptor_mode, min_inliers=section.min_inliers,
                   ransac_threshold_m=section.ransac_threshold_m,
                   keypoint_positions=section.keypoint_positions)

    def __post_init__(self) -> None:
        if self.descriptor_mode not in MODES:
            raise ValueError(f"descriptor_mode must be one of {sorted(MODES)}, got {self.descriptor_mode!r}")
        if not (self.min_inliers >= 3 and self.ransac_threshold_m > 0 and self.iterations >= 1
                and self.min_spread_m >= 0 and self.min_sigma_m > 0 and self.min_sigma_detected_m > 0):
            raise ValueError(f"visual odometry parameters out of range: {self}")
        if self.keypoint_positions not in KEYPOINT_POSITIONS:
            raise ValueError(f"keypoint_positions must be one of {KEYPOINT_POSITIONS}, "
                             f"got {self.keypoint_positions!r}")


@dataclass(frozen=True, eq=False)
class VoResult:
    """One visual odometry step between keyframes ``k-1`` and ``k``.

    Fields:
        delta: ``(3,) float64`` pose of ``k`` in the robot frame of ``k-1``
            ``(dx_m, dy_m, dyaw_rad)``; NaN when the step failed.
        covariance: ``(3, 3) float64`` its covariance (m^2, m rad, rad^2); NaN on failure.
        n_matches: descriptor matches handed on by the matcher (its pixel inliers).
        n_inliers: metric RANSAC inliers the transform was fitted on (0 on failure).
        residual_m: residual sigma per coordinate of the fit, metres (NaN on failure).
        reason: '' on success, else why the step failed (the module's reason constants).
        detail: for ``TOO_FEW_MATCHES`` from the matcher, the matcher's own reason.
    """

    delta: np.ndarray
    covariance: np.ndarray
    n_matches: int
    n_inliers: int
    residual_m: float
    reason: VoReason
    detail: str = ""

    @property
    def ok(self) -> bool:
        """True when the step gave a motion."""
        return self.reason == ""


def _failed(reason: VoReason, n_matches: int = 0, detail: str = "") -> VoResult:
    return VoResult(np.full(3, np.nan), np.full((3, 3), np.nan), n_matches, 0, math.nan, reason, detail)


def floor_point_pairs(camera: Any, xy_a_px: np.ndarray, xy_b_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Matched pixels of two images -> ``(K, 2)`` metric floor points in each robot frame.

    ``xy_*_px``: ``(N, 2)`` pixels; ``camera``: a
    :class:`~robotd.base.camera.FloorCameraModel`. Pairs where either pixel sees no floor
    are dropped (K <= N).
    """
    pa = camera.pixel_to_floor_robot(np.asarray(xy_a_px, float).reshape(-1, 2))
    pb = camera.pixel_to_floor_robot(np.asarray(xy_b_px, float).reshape(-1, 2))
    ok = np.isfinite(pa).all(axis=1) & np.isfinite(pb).all(axis=1)
    return pa[ok], pb[ok]


def _ransac(src: np.ndarray, dst: np.ndarray, p: VoParams) -> np.ndarray:
    """``(N,) bool`` inliers of the best 2-point rigid hypothesis ``dst ~ R src + t``.

    Hypotheses are scored MSAC-style (sum of ``min(r^2, threshold^2)``), which prefers the
    tighter of two hypotheses with as many inliers.
    """
    n = len(src)
    rng = np.random.default_rng(p.seed)
    i = rng.integers(n, size=p.iterations)
    j = (i + 1 + rng.integers(n - 1, size=p.iterations)) % n
    hyp = rigid_from_two_pairs(src[i], src[j], dst[i], dst[j])  # (K, 3)
    c, s = np.cos(hyp[:, 2]), np.sin(hyp[:, 2])
    # Residuals of every hypothesis at every pair, (K, N).
    rx = c[:, None] * src[:, 0] - s[:, None] * src[:, 1] + hyp[:, 0:1] - dst[:, 0]
    ry = s[:, None] * src[:, 0] + c[:, None] * src[:, 1] + hyp[:, 1:2] - dst[:, 1]
    r2 = np.minimum(rx * rx + ry * ry, p.ransac_threshold_m ** 2)
    best = int(np.argmin(r2.sum(axis=1)))
    return np.asarray(r2[best] < p.ransac_threshold_m ** 2)


def floor_motion(p_prev: np.ndarray, p_cur: np.ndarray, params: VoParams | None = None,
                 n_matches: int | None = None, *, min_sigma_m: float | None = None) -> VoResult:
    """Steps 3-5 on matched floor points: ``(N, 2)`` metres in the robot frames of keyframes
    ``k-1`` and ``k`` -> the pose of ``k`` in ``k-1``'s frame, its covariance, or a reason.
    ``min_sigma_m``: the residual sigma's floor (default ``params.min_sigma_m``)."""
    p = params or VoParams()
    src = np.asarray(p_cur, float).reshape(-1, 2)
    dst = np.asarray(p_prev, float).reshape(-1, 2)
    n = len(src) if n_matches is None else n_matches
    if len(src) < p.min_inliers:
        return _failed(TOO_FEW_MATCHES, n)
    inl = _ransac(src, dst, p)
    pose = None
    for _ in range(2):  # refine on all inliers, re-select, refine again (Sec. IV-D)
        if inl.sum() < 2:
            break
        pose = rigid_fit_2d(src[inl], dst[inl])
        r = transform_points(pose, src) - dst
        inl = np.einsum("ij,ij->i", r, r) < p.ransac_threshold_m ** 2
    k = int(inl.sum())
    if pose is None or k < p.min_inliers:
        return _failed(TOO_FEW_INLIERS, n)
    pose = rigid_fit_2d(src[inl], dst[inl])
    centred = src[inl] - src[inl].mean(axis=0)
    if math.sqrt(float(np.mean(np.sum(centred * centred, axis=1)))) < p.min_spread_m:
        return _failed(DEGENERATE_GEOMETRY, n)
    cov, sigma = rigid_fit_2d_covariance(src[inl], dst[inl], pose,
                                         p.min_sigma_m if min_sigma_m is None else min_sigma_m)
    return VoResult(pose, cov, n, k, sigma, VoReason.OK)


def estimate_motion(prev: FloorDescriptor, cur: FloorDescriptor, camera: Any,
                    params: VoParams | None = None) -> VoResult:
    """Steps 1-5 for two decoded descriptors of the same mode (``prev`` = keyframe ``k-1``).
    Their ``xy_px`` are the points fitted: the grid's, or the detector's
    (:func:`with_detected_positions`; the residual floor is then
    ``params.min_sigma_detected_m`` when both have them)."""
    p = params or VoParams()
    m = local_score(prev, cur, p.match)
    if m.reason:
        return _failed(TOO_FEW_MATCHES, m.n_matches, m.reason)
    p_prev, p_cur = floor_point_pairs(camera, m.xy_a, m.xy_b)
    detected = prev.position_step_px == 0 and cur.position_step_px == 0
    return floor_motion(p_prev, p_cur, p, m.n_inliers,
                        min_sigma_m=p.min_sigma_detected_m if detected else p.min_sigma_m)


def with_detected_positions(desc: FloorDescriptor, xy_px: np.ndarray) -> FloorDescriptor:
    """``desc`` with its keypoints where the detector found them
    (:func:`robotd.floor.descriptor.extract_with_positions`'s ``(N, 2)`` pixels, in the
    coded order) in place of the grid's; ``position_step_px`` 0 says so. Raises
    ``ValueError`` when the positions cannot be this descriptor's (another count, not
    finite, or farther than one grid step from the cells the descriptor codes)."""
    xy = np.asarray(xy_px, np.float32)
    if xy.shape != desc.xy_px.shape or not np.isfinite(xy).all():
        raise ValueError(f"detected positions {xy.shape} do not fit a descriptor of {len(desc)} keypoints")
    if len(xy) and float(np.max(np.abs(xy - desc.xy_px))) > desc.position_step_px:
        raise ValueError("detected positions are not this descriptor's (beyond its coordinate grid's cells)")
    return replace(desc, xy_px=xy, position_step_px=0.0)


class FloorVisualOdometry:
    """Visual odometry over a stream of keyframes: each :meth:`step` matches the new
    keyframe against the previous one, which it then replaces (also after a failed step,
    so the chain goes on from the newest keyframe)."""

    def __init__(self, camera: Any, params: VoParams | None = None) -> None:
        """``camera``: the floor camera model (calibration) that maps pixels to the floor."""
        self.camera = camera
        self.params = params or VoParams()
        self._prev: FloorDescriptor | None = None

    @property
    def previous(self) -> FloorDescriptor | None:
        """The last keyframe's decoded descriptor (None before the first step)."""
        return self._prev

    def reset(self) -> None:
        """Forget the previous keyframe (the next step is a new chain's first)."""
        self._prev = None

    def describe(self, keyframe: np.ndarray | bytes | FloorDescriptor,
                 positions: np.ndarray | None = None) -> FloorDescriptor:
        """A keyframe as a decoded descriptor: an image ``(H, W) uint8`` is described in
        ``params.descriptor_mode``, bytes are decoded, a descriptor is passed through.
        With ``keypoint_positions = "detected"``, ``positions`` (the detector's, beside a
        descriptor) or an image's own replace the grid's; ``"coded"`` ignores them."""
        detected = self.params.keypoint_positions == "detected"
        if isinstance(keyframe, FloorDescriptor):
            desc = keyframe
        elif isinstance(keyframe, (bytes, bytearray, memoryview)):
            desc = decode(bytes(keyframe))
        else:  # an image: its positions come with its description, at no cost
            coded, own = extract_with_positions(np.asarray(keyframe), self.params.descriptor_mode)
            desc = decode(coded)
            positions = own if positions is None else positions
        return with_detected_positions(desc, positions) if detected and positions is not None else desc

    def step(self, keyframe: np.ndarray | bytes | FloorDescriptor, positions: np.ndarray | None = None) -> VoResult:
        """The motion from the previous keyframe to ``keyframe``
        (``NO_PREVIOUS_KEYFRAME`` on the first call); ``positions`` as :meth:`describe`."""
        cur = self.describe(keyframe, positions)
        prev, self._prev = self._prev, cur
        if prev is None:
            return _failed(NO_PREVIOUS_KEYFRAME)
        return estimate_motion(prev, cur, self.camera, self.params)


@dataclass(frozen=True, eq=False)
class VoTrack:
    """Vision-only odometry: the chained steps.

    Fields:
        poses: ``(N + 1, 3)`` keyframe poses ``(x_m, y_m, yaw_rad)``, the first the start.
        sources: ``(N,)`` what each step used: ``"vo"``, ``"fallback"`` (the wheel + gyro
            increment) or ``"none"`` (failed without a fallback: no motion assumed).
        n_vo, n_fallback, n_lost: how many steps of each kind.
    """

    poses: np.ndarray
    sources: tuple[str, ...]
    n_vo: int
    n_fallback: int
    n_lost: int


def integrate(steps: Sequence[VoResult], fallback: np.ndarray | None = None,
              start_xyyaw: Sequence[float] = (0.0, 0.0, 0.0)) -> VoTrack:
    """Chain ``N`` visual odometry steps into poses (paper 003, Sec. V: vision-only odometry).

    ``fallback``: ``(N, 3)`` the wheel + gyro increments of the same steps
    (``(dx_m, dy_m, dyaw_rad)`` in the previous keyframe's frame, e.g.
    :func:`robotd.base.geometry.between` of the filter's poses); a failed step takes its
    row instead (a NaN row counts as missing). Without one, a failed step adds no motion.
    """
    n = len(steps)
    if fallback is not None:
        fallback = np.asarray(fallback, float).reshape(-1, 3)
        if len(fallback) != n:
            raise ValueError(f"need one fallback increment per step ({n}), got {len(fallback)}")
    poses = np.empty((n + 1, 3))
    poses[0] = np.asarray(start_xyyaw, float)
    sources = []
    for k, r in enumerate(steps):
        if r.ok:
            d, src = r.delta, "vo"
        elif fallback is not None and np.all(np.isfinite(fallback[k])):
            d, src = fallback[k], "fallback"
        else:
            d, src = np.zeros(3), "none"
        poses[k + 1] = compose(poses[k], d)
        sources.append(src)
    return VoTrack(poses, tuple(sources), sources.count("vo"), sources.count("fallback"),
                   sources.count("none"))
