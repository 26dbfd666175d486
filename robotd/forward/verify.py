"""Epipolar verification of a loop candidate (paper 000 Sec. IV-C, ref. [9]).

The two images' descriptors are matched (nearest neighbour with Lowe's ratio test), the
essential matrix is estimated by Nister's five-point method inside RANSAC
(``cv2.findEssentialMat``), and the relative pose is recovered from it
(``cv2.recoverPose``, the cheirality check keeps the one of four decompositions that puts
the points in front of both cameras). The loop is accepted when enough matches agree with
one epipolar geometry and lie in front of both cameras.

Monocular geometry gives the rotation and only the *direction* of the translation: the
scale is unknown (it would come from odometry). Without a calibration the camera matrix is
a guess: focal length = image width (about 53 degrees of horizontal field of view), the
principal point at the centre; the inlier test is in pixels and tolerates that.

Expected failures are values (:class:`Verification` with a reason), not exceptions.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from robotd.forward.features import Features

__all__ = ["ACCEPTED", "NO_GEOMETRIC_CONSISTENCY", "TOO_FEW_MATCHES", "Verification",
           "VerifyParams", "camera_matrix_guess", "match_features", "verify_pair"]

ACCEPTED = "ACCEPTED"
TOO_FEW_MATCHES = "TOO_FEW_MATCHES"
NO_GEOMETRIC_CONSISTENCY = "NO_GEOMETRIC_CONSISTENCY"


@dataclass(frozen=True)
class VerifyParams:
    """Parameters of :func:`verify_pair`.

    Fields:
        ratio: Lowe's ratio test, nearest / second-nearest descriptor distance.
        min_inliers: accept when at least this many matches fit the essential matrix and
            lie in front of both cameras (20, as RTAB-Map's ``Vis/MinInliers``; on the
            rtabmap_samples corridor the best wrong image pair reaches 16).
        ransac_threshold_px: largest distance of a point from its epipolar line, pixels.
        ransac_confidence: RANSAC's confidence of having drawn one all-inlier sample.
        seed: OpenCV's random generator is seeded with this before RANSAC, so a run is
            reproducible (OpenCV's generator is process-wide state).
    """

    ratio: float = 0.8
    min_inliers: int = 20
    ransac_threshold_px: float = 1.0
    ransac_confidence: float = 0.999
    seed: int = 0


@dataclass(frozen=True, eq=False)
class Verification:
    """The outcome of one verification.

    ``accepted`` and ``reason`` (``ACCEPTED``, ``TOO_FEW_MATCHES``,
    ``NO_GEOMETRIC_CONSISTENCY``); ``n_matches`` after the ratio test, ``n_inliers`` after
    RANSAC and the cheirality check. When a pose was recovered: ``rotation (3, 3)`` and
    ``translation_dir (3,)`` (unit length) such that a point X_old in the old image's
    camera frame is ``rotation @ X_old + s * translation_dir`` in the new image's camera
    frame, for an unknown scale s > 0 (OpenCV camera axes: x right, y down, z forward).
    """

    accepted: bool
    reason: str
    n_matches: int
    n_inliers: int
    rotation: np.ndarray | None = None
    translation_dir: np.ndarray | None = None


def camera_matrix_guess(width_px: int, height_px: int, focal_px: float | None = None) -> np.ndarray:
    """A ``(3, 3)`` pinhole camera matrix: ``focal_px`` (default: the image width) and the
    principal point at the image centre."""
    f = float(width_px if focal_px is None else focal_px)
    return np.array([[f, 0.0, width_px / 2.0], [0.0, f, height_px / 2.0], [0.0, 0.0, 1.0]])


def match_features(a: Features, b: Features, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Matched keypoints ``(M, 2), (M, 2)`` float32 of ``a`` and ``b``: each of ``a``'s
    descriptors against ``b``'s, kept when the nearest is clearly nearer than the second
    (Lowe's ratio test), at most one match per keypoint of ``b`` (the nearer one)."""
    empty = np.zeros((0, 2), np.float32)
    if len(a) < 2 or len(b) < 2:
        return empty, empty
    binary = a.descriptors.dtype == np.uint8
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING if binary else cv2.NORM_L2)
    pairs = matcher.knnMatch(a.descriptors, b.descriptors, k=2)
    best: dict[int, tuple[float, int]] = {}
    for p in pairs:
        if len(p) == 2 and p[0].distance < ratio * p[1].distance:
            m = p[0]
            if m.trainIdx not in best or m.distance < best[m.trainIdx][0]:
                best[m.trainIdx] = (m.distance, m.queryIdx)
    if not best:
        return empty, empty
    ib = np.fromiter(best.keys(), np.int64, len(best))
    ia = np.fromiter((v[1] for v in best.values()), np.int64, len(best))
    return a.keypoints_px[ia], b.keypoints_px[ib]


def verify_pair(old: Features, new: Features, params: VerifyParams = VerifyParams(),
                camera_matrix: np.ndarray | None = None) -> Verification:
    """Check that ``new`` and ``old`` see one 3D scene (epipolar geometry) and return the
    relative pose. ``camera_matrix (3, 3)``: intrinsics shared by both images (default
    :func:`camera_matrix_guess` for ``new``'s size)."""
    p_old, p_new = match_features(old, new, params.ratio)
    n = len(p_old)
    if n < max(5, params.min_inliers):
        return Verification(False, TOO_FEW_MATCHES, n, 0)
    k = camera_matrix if camera_matrix is not None else camera_matrix_guess(*new.image_size_px)
    cv2.setRNGSeed(params.seed)
    e, mask = cv2.findEssentialMat(p_old, p_new, k, method=cv2.RANSAC,
                                   prob=params.ransac_confidence,
                                   threshold=params.ransac_threshold_px)
    if e is None or mask is None or e.shape[0] < 3:
        return Verification(False, NO_GEOMETRIC_CONSISTENCY, n, 0)
    e = e[:3]  # the five-point method may return up to ten solutions stacked; RANSAC keeps one
    n_inl, r, t, mask2 = cv2.recoverPose(e, p_old, p_new, k, mask=mask.copy())
    n_inl = int(n_inl)
    t = np.asarray(t, np.float64).reshape(3)
    t_dir = t / max(float(np.linalg.norm(t)), 1e-12)
    if n_inl < params.min_inliers:
        return Verification(False, NO_GEOMETRIC_CONSISTENCY, n, n_inl, np.asarray(r, np.float64), t_dir)
    return Verification(True, ACCEPTED, n, n_inl, np.asarray(r, np.float64), t_dir)
