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

**A check the paper does not have: the support of the geometry.** Paper 000 accepts a
loop on the essential matrix's inlier count alone. That count means little when the inliers
lie on one plane (a poster, a door, one wall) or the camera only turned: a homography then
explains the matches, the essential matrix is degenerate (a family of E fits any
homography), and five-point RANSAC finds a consistent E, with many inliers, for a repeated
poster on another wall as easily as for the same one. Measured on the virtual office route
(1139 images, repeated posters, checkers and doors), every false loop the detector verified
was of that kind: 43-73 inliers, 90-100 % of them on one homography, covering 0.5-1.4 % of
the image (the checker strip under a repeated poster). A true revisit is recognised by the
scene around the object as well. So, after the paper's test, :func:`verify_pair` fits a
homography to the essential matrix's inliers (RANSAC, ``homography_threshold_px``); when it
holds at least ``planar_fraction`` of them, the inliers are taken to be one plane and only
the homography's inliers count as support; otherwise (real parallax: points off the plane
fix the epipolar geometry) all inliers do. The support must cover at least
``min_support_area`` of each image (convex hull of its points, as a fraction of the image),
else the candidate is refused as ``SMALL_SUPPORT``. ``min_support_area = 0`` turns the check
off and gives the paper's verification exactly. The check cannot refuse a copy that fills
the view (two identical doors seen square-on): only the Bayes filter's temporal consistency
keeps those out. The support is all the inliers or the homography's among them, whose convex
hull lies inside theirs: when all the inliers already cover less than ``min_support_area``,
the check is refused without fitting the homography (the same decision; RANSAC's homography
runs its 2000 samples when the inliers are not one plane, milliseconds per check), and
``n_plane_inliers`` and ``planar`` stay 0 and False.

**The range from the floor (not in the paper).** The essential matrix fixes only the
translation's direction, and a wrong loop can still fit one: on the virtual office route,
two places 2.5-2.9 m apart along a corridor, with no wall in common, see the same floor
tiles and ceiling panels (both repeat every metre or two); the floor matches and the
ceiling matches then each fit a forward translation of their own length, and along one
direction the epipolar constraint cannot tell lengths apart. Five-point RANSAC accepts 26
of 81 such pairs (heading right to a degree, bearing wrong by 60-180 deg). That is what the
daemon's wrong forward loops were, not a reversed sign: the from/to convention checks out
against the virtual camera's truth (``tests/forward/test_verify_virtual.py``). A robot's
forward camera is at a known height above the floor, so the floor fixes the scale: with
``camera_height_m`` set, the inliers are triangulated with a unit baseline, the largest
group of points below the camera at one height (within ``floor_band_log`` in log height)
is taken as the floor, and ``range_m = camera_height_m / that height``. On the pairs above
it reads 0.1-0.5 m where the truth is 2.5 m; on true loops it is within a factor 1.7 of
the truth. The pose graph then weighs the measured range (:mod:`robotd.forward.planar`),
so its gate sees the contradiction.

**Time (not in the paper).** The search for the essential matrix is the verification's
cost, and on a loaded robot CPU the tail of the per-image time. OpenCV's RANSAC draws up to
1000 samples of five matches; a candidate whose matches hold no consensus (most refused
candidates) draws all 1000, and each sample costs a five-point solve (measured on the
virtual office route: 255 of its 1139 images verified a candidate for the full 1000
samples, about 0.25 s each on a quiet machine, which made the 99th percentile). Two
changes, each the same test as before:

- *iteration bound* (both estimators): a candidate is accepted only with ``min_inliers``
  inliers, so the search stops once a consensus of that size would have been found with
  ``ransac_confidence`` (:func:`ransac_iterations`): 34 samples for 28 matches instead of
  1000;
- ``estimator = "usac"`` (the default detector's search near the level motion,
  ``guided_estimator``, below): OpenCV's USAC framework set to the same
  test (uniform samples, the inlier count within ``ransac_threshold_px``) whose five-point
  solver costs about a tenth of the classic one per sample, with a local optimisation of
  each new best model on its inliers (which finds the consensus in fewer samples, so the
  adaptive stop comes earlier). The paper's detector keeps ``"ransac"``.

**The planar model (not in the paper).** A robot's forward camera turns about its vertical
axis and moves in the floor plane: two degrees of freedom (heading change, bearing of the
translation) instead of the essential matrix's five. With ``model = "planar"`` (the default
detector's) the verification first finds the level motion most matches agree with
(:func:`robotd.forward.planefit.ransac_planar`: samples of two matches, at most two motions
each, every batch of hypotheses scored against every match at once, within
``guide_threshold_px``): for a quarter of the matches to be inliers it needs about 100
samples where five-point RANSAC needs about 7000 (so it stops, where the five-point search
ran to its cap of 1000). The essential matrix is then searched among the matches within
``guide_threshold_px`` of that motion only (mostly inliers: the five-point search stops
after a few samples; at most the samples that would draw five inliers were half of them
inliers), its inliers counted over all the matches, and the rest is the general model's
test (cheirality, support, the refined motion): the planar search only chooses where the
five-point search looks. A camera a few degrees off level (the real corridor of
rtabmap_samples, held by hand) leaves some inliers outside the neighbourhood: when the
search there fails and the level motion's consensus reached ``fallback_inliers`` (10), the
general search runs over all the matches with at most ``fallback_max_iterations`` (200)
samples. The work per verification is so bounded by rule, not by a timer: at most
``2 planar_max_samples`` level hypotheses times the matches, 218 five-point samples near the
level motion and 200 over all the matches. The default detector makes both searches
cheaper: the one near the level motion by OpenCV's USAC (``guided_estimator``: the same
test, a tenth of RANSAC's cost per sample; it is most of the median image's verification),
the fallback's samples drawn within ``fallback_band_px`` (10) of the level motion (fewer
outliers among them; its inliers still counted over all the matches), and the detector runs
the fallback for at most one view per image
(:attr:`robotd.forward.detector.DetectorParams.verify_fallbacks`): the fallback was the
99th percentile of the time per image. USAC in the fallback let a false loop through on
the office route without a pose, so the fallback keeps RANSAC. ``fallback_screen = "usac"``
runs USAC in the band first and refuses the candidate when its best essential matrix has
fewer than ``min_inliers`` inliers in front of both cameras, RANSAC deciding otherwise (so no
acceptance is USAC's): measured, it refuses most of the fallbacks RANSAC accepts on the
office route (views with little parallax, where many essential matrices fit the matches and
the one drawn decides how many points lie in front) and one on rtabmap_samples, so it is off. ``model = "planar_motion"`` takes the level
motion itself as the verified motion (no five-point search when it passes): measured, it
passes aliased views (a wall's repeated pattern seen from a sideways shift) that the
general test refuses, so it is not the default. ``model = "general"`` is the paper's
search over all the matches (the paper's detector and the baselines keep it).

**The fallback run later (not in the paper).** A detector that verifies several views of one
place (:attr:`robotd.forward.detector.DetectorParams.fallbacks_last`) need not run a view's
general search before it has checked the next views near their level motion: with
``defer_fallback`` a check whose search near the level motion failed with the general search
due returns as a :class:`DueFallback` (the failed check, and what that search needs: the
matches, their normalised coordinates, the level search), and :func:`fallback_verification`
runs the search later with the answer it would have given at once. The general search is the
costliest part of a check (RANSAC's five-point samples in the band, all 200 when no consensus
is there), and a view that passes near its level motion is a fraction of it.

Expected failures are values (:class:`Verification` with a reason), not exceptions.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from enum import StrEnum

import cv2
import numpy as np

from robotd.forward.features import FeatureSet
from robotd.forward.planar import INLIER_NOISE_FACTOR, fit_motion, normalised_points
from robotd.forward.planefit import PlanarSearch, ransac_planar

__all__ = ["ACCEPTED", "NO_GEOMETRIC_CONSISTENCY", "SMALL_SUPPORT", "TOO_FEW_MATCHES", "Verification", "VerifyReason",
           "VerifyParams", "DueFallback", "FallbackWork", "camera_matrix_guess", "essential_matrix", "fallback_verification", "floor_range",
           "match_features", "match_indices",
           "matched_points", "ransac_iterations", "support_area", "verify_pair"]

class VerifyReason(StrEnum):
    """The outcome of a verification (a :class:`~enum.StrEnum`: equal to its text)."""

    ACCEPTED = "ACCEPTED"
    TOO_FEW_MATCHES = "TOO_FEW_MATCHES"
    NO_GEOMETRIC_CONSISTENCY = "NO_GEOMETRIC_CONSISTENCY"
    SMALL_SUPPORT = "SMALL_SUPPORT"  # enough inliers, but on one small plane (not in the paper)


ACCEPTED = VerifyReason.ACCEPTED
TOO_FEW_MATCHES = VerifyReason.TOO_FEW_MATCHES
NO_GEOMETRIC_CONSISTENCY = VerifyReason.NO_GEOMETRIC_CONSISTENCY
SMALL_SUPPORT = VerifyReason.SMALL_SUPPORT


#: The searches for the essential matrix (:attr:`VerifyParams.estimator`).
ESTIMATORS = ("ransac", "usac")

#: The screens before the band fallback's general search (:attr:`VerifyParams.fallback_screen`).
SCREENS = ("usac",)

#: The motion models of the verification (:attr:`VerifyParams.model`).
MODELS = ("general", "planar", "planar_motion")


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
        min_support_area: the inliers that support the geometry must cover at least this
            fraction of each image (convex hull); 0 = off, the paper's check (module notes).
            0.03: the false loops of the virtual office route covered at most 0.014, the
            true loops the detector verified on rtabmap_samples at least 0.047.
        planar_fraction: the inliers are one plane when a homography holds at least this
            fraction of them (then only its inliers are support).
        homography_threshold_px: largest transfer error of a homography inlier, pixels.
        camera_height_m: the camera's optical centre above the floor, metres; when set, the
            range is measured from the floor points (module notes), else ``range_m`` is None.
        min_floor_points: inliers that must agree on the floor's height to give a range.
        floor_band_log: floor points agree within this in log height (0.1: +-10 %).
        estimator: how the essential matrix is searched for: ``"ransac"``, OpenCV's
            ``findEssentialMat`` with RANSAC (the paper's check), or ``"usac"``, OpenCV's
            USAC framework set to the same test (uniform samples of five, inliers counted
            within ``ransac_threshold_px``, the same confidence and iteration bound) with
            its local optimisation of each new best model and its faster five-point solver
            (module notes, "Time").
        local_optimisation: with ``estimator = "usac"``, each new best model is refined
            on its inliers (OpenCV's inner local optimisation); False: none, the same test
            as RANSAC with only the cheaper sample.
        max_iterations: the most samples either search draws (OpenCV's own cap, 1000,
            by default); fewer bound the verification's time at the cost of missing more
            consensus sets of few inliers among many matches (measured on both development
            sequences by ``bench/bench_forward_scale.py``, not the default).
        model: how the motion is searched for (module notes, "The planar model"):
            ``"general"``, the essential matrix of any rigid motion over all the matches
            (five-point RANSAC, ``estimator``; the paper's check); ``"planar"`` (the default
            detector's), a level camera's motion (heading change and bearing,
            :func:`robotd.forward.planefit.ransac_planar`, samples of two matches) found
            first, the essential matrix then searched among the matches within
            ``guide_threshold_px`` of it and checked over all the matches as the general
            model's, and the general search after it, at most ``fallback_max_iterations``
            samples, when that fails and the planar consensus reached ``fallback_inliers``;
            ``"planar_motion"``: the planar motion itself is the verified motion when it
            passes the checks (the general search after it as in ``"planar"``, its
            consensus counted within ``ransac_threshold_px``): measured, not the default
            (it passes aliased views the general check refuses).
        planar_max_samples: the most samples of two matches the planar search draws (its
            work is at most twice this many hypotheses, each scored against every match).
        guide_threshold_px: with ``"planar"``, the planar search's inlier threshold and
            the neighbourhood of the level motion in which the essential matrix is
            searched, pixels (wider than ``ransac_threshold_px``: a camera a few degrees
            off level still has its inliers within it).
        fallback_inliers: with a planar model, the general search over all the matches
            is tried only when the planar search's best consensus has at least this many
            matches; None: never (a camera known to be level); 0: always.
        fallback_max_iterations: the most samples that general search draws.
        guided_estimator: with a planar model, the estimator of the five-point search
            among the matches near the level motion (None: ``estimator``). ``"usac"``:
            OpenCV's USAC with the same test (module notes, "Time"), whose five-point
            solve costs about a tenth of RANSAC's per sample; that search is most of the
            median image's verification.
        fallback_estimator: with a planar model, the estimator of the general search over
            all the matches after it (None: ``estimator``); that search is the tail.
        fallback_band_px: with a planar model, that general search draws its samples
            among the matches within this distance of the level motion only (a camera a
            few degrees off level keeps its inliers near the level motion; fewer outliers
            among the samples let RANSAC's adaptive stop come earlier), its inliers still
            counted over all the matches; None: among all the matches.
        fallback_screen: with a planar model and ``fallback_band_px``, a cheaper search
            run in the band before that general search, which can only refuse: when the
            essential matrix it finds (``"usac"``: OpenCV's USAC, the same test and
            iteration bound as the search it screens, a tenth of its cost per sample) has
            fewer than ``min_inliers`` inliers over all the matches in front of both
            cameras, the candidate is refused without the general search; otherwise the
            general search runs as without the screen and decides. So every acceptance is
            the general search's own; a consensus the screen misses and RANSAC would find
            is lost (module notes, "The planar model"). None: no screen.
        defer_fallback: with a planar model, stop where the general search after a failed
            search near the level motion would run, and return that failed check with what
            the general search needs (a :class:`DueFallback`), so that the caller
            runs it later, or not at all, by :func:`fallback_verification` (the same answer
            as the search run at once; module notes, "The fallback run later"). False: run it
            at once.
    """

    ratio: float = 0.8
    min_inliers: int = 20
    ransac_threshold_px: float = 1.0
    ransac_confidence: float = 0.999
    seed: int = 0
    min_support_area: float = 0.03
    planar_fraction: float = 0.8
    homography_threshold_px: float = 3.0
    camera_height_m: float | None = None
    min_floor_points: int = 4
    floor_band_log: float = 0.1
    estimator: str = "ransac"
    local_optimisation: bool = True
    max_iterations: int = 1000
    model: str = "general"
    planar_max_samples: int = 500
    guide_threshold_px: float = 3.0
    fallback_inliers: int | None = 10
    fallback_max_iterations: int = 200
    guided_estimator: str | None = None
    fallback_estimator: str | None = None
    fallback_band_px: float | None = None
    fallback_screen: str | None = None
    defer_fallback: bool = False

    def __post_init__(self) -> None:
        if self.camera_height_m is not None and not self.camera_height_m > 0.0:
            raise ValueError(f"camera_height_m must be positive, got {self.camera_height_m}")
        if self.min_floor_points < 2:
            raise ValueError(f"min_floor_points must be >= 2, got {self.min_floor_points}")
        if not 0.0 <= self.min_support_area < 1.0:
            raise ValueError(f"min_support_area must be in [0, 1), got {self.min_support_area}")
        if not 0.0 < self.planar_fraction <= 1.0:
            raise ValueError(f"planar_fraction must be in (0, 1], got {self.planar_fraction}")
        if not self.homography_threshold_px > 0.0:
            raise ValueError(f"homography_threshold_px must be positive, got {self.homography_threshold_px}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations}")
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {', '.join(MODELS)}, got {self.model!r}")
        if self.planar_max_samples < 1:
            raise ValueError(f"planar_max_samples must be >= 1, got {self.planar_max_samples}")
        if not self.guide_threshold_px > 0.0:
            raise ValueError(f"guide_threshold_px must be positive, got {self.guide_threshold_px}")
        if self.fallback_max_iterations < 1:
            raise ValueError(f"fallback_max_iterations must be >= 1, got {self.fallback_max_iterations}")
        if self.fallback_band_px is not None and not self.fallback_band_px > 0.0:
            raise ValueError(f"fallback_band_px must be positive or None, got {self.fallback_band_px}")
        if self.fallback_inliers is not None and self.fallback_inliers < 0:
            raise ValueError(f"fallback_inliers must be >= 0 or None, got {self.fallback_inliers}")
        if self.fallback_screen is not None and self.fallback_screen not in SCREENS:
            raise ValueError(f"fallback_screen must be one of {', '.join(SCREENS)} or None, got {self.fallback_screen!r}")
        for name in ("estimator", "guided_estimator", "fallback_estimator"):
            value = getattr(self, name)
            if (value is not None or name == "estimator") and value not in ESTIMATORS:
                raise ValueError(f"{name} must be one of {', '.join(ESTIMATORS)}, got {value!r}")


@dataclass(frozen=True, eq=False)
class Verification:
    """The outcome of one verification.

    ``accepted`` and ``reason`` (``ACCEPTED``, ``TOO_FEW_MATCHES``,
    ``NO_GEOMETRIC_CONSISTENCY``, ``SMALL_SUPPORT``); ``n_matches`` after the ratio test,
    ``n_inliers`` after RANSAC and the cheirality check; ``n_plane_inliers`` of those on
    the best homography, ``planar`` when they are at least ``planar_fraction`` of them, and
    ``support_area`` the smaller fraction of the two images the support covers (these three
    only when the support check ran); ``range_m`` the distance between the camera centres
    measured on the floor, metres, and ``n_floor_points`` the inliers it rests on (with
    ``camera_height_m``, when enough inliers agree); ``sigma_bearing_rad`` and
    ``sigma_yaw_rad`` how well the inliers fix the bearing and the heading change of
    :func:`robotd.forward.planar.planar_motion` (1-sigma, from their epipolar errors
    ``noise_px``: :func:`robotd.forward.planar.motion_uncertainty`; ``inf`` when not
    computed); ``planarity_chi2`` the motion's out-of-plane part against its covariance
    (:class:`robotd.forward.planar.MotionFit`; NaN when not computed); ``fallback`` whether
    a planar model's general search was due (it ran, or with ``fallback_band_px`` the band
    held fewer than ``min_inliers`` matches to run it on; either counts against
    :attr:`robotd.forward.detector.DetectorParams.verify_fallbacks`); ``level_yaw_rad`` the
    heading change of the level motion the planar model's search found first (the two-point
    search that guides the others, :func:`robotd.forward.planefit.ransac_planar`; NaN when
    it found none or the model is not ``"planar"``); ``screened`` whether the band
    fallback's screen refused the candidate before its general search
    (:attr:`VerifyParams.fallback_screen`); ``match_index`` the matches' indices
    into the old and the new image's keypoints (two ``(M,)`` int arrays, the order of the
    matched pixels the search ran on: :func:`match_indices`; None when not matched here), so
    that a user of the verification reads the same matches without matching again. When a pose was recovered: ``rotation (3, 3)`` and
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
    n_plane_inliers: int = 0
    planar: bool = False
    support_area: float = 0.0
    range_m: float | None = None
    n_floor_points: int = 0
    sigma_bearing_rad: float = float("inf")
    sigma_yaw_rad: float = float("inf")
    noise_px: float = float("nan")
    planarity_chi2: float = float("nan")
    fallback: bool = False
    level_yaw_rad: float = float("nan")
    match_index: tuple[np.ndarray, np.ndarray] | None = None
    screened: bool = False


def camera_matrix_guess(width_px: int, height_px: int, focal_px: float | None = None) -> np.ndarray:
    """A ``(3, 3)`` pinhole camera matrix: ``focal_px`` (default: the image width) and the
    principal point at the image centre."""
    f = float(width_px if focal_px is None else focal_px)
    return np.array([[f, 0.0, width_px / 2.0], [0.0, f, height_px / 2.0], [0.0, 0.0, 1.0]])


def match_indices(a: FeatureSet, b: FeatureSet, ratio: float = 0.8,
                  by_distance: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The matches of ``a`` and ``b`` as indices into their keypoints, ``(M,), (M,)``
    int64: each of ``a``'s descriptors against ``b``'s, kept when the nearest is clearly
    nearer than the second (Lowe's ratio test), at most one match per keypoint of ``b``
    (the nearer one); in ``b``'s order of first match, or nearest descriptor first with
    ``by_distance`` (PROSAC's order)."""
    empty = np.zeros(0, np.int64)
    if len(a) < 2 or len(b) < 2:
        return empty, empty
    if a.descriptors.dtype == np.uint8:
        # the two nearest as arrays: the distances and indices OpenCV's brute-force
        # matcher's knnMatch computes (by this same call), without its DMatch objects
        dist, nidx = cv2.batchDistance(a.descriptors, b.descriptors, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=2)
        d1, d2, train = dist[:, 0], dist[:, 1], nidx[:, 0]
        query = np.arange(len(d1))
        paired = nidx[:, 1] >= 0
    else:
        pairs = [p for p in cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.descriptors, b.descriptors, k=2) if len(p) == 2]
        d1 = np.fromiter((p[0].distance for p in pairs), np.float64, len(pairs))
        d2 = np.fromiter((p[1].distance for p in pairs), np.float64, len(pairs))
        train = np.fromiter((p[0].trainIdx for p in pairs), np.int64, len(pairs))
        query = np.fromiter((p[0].queryIdx for p in pairs), np.int64, len(pairs))
        paired = np.ones(len(pairs), bool)
    q = np.flatnonzero(paired & (d1 < ratio * d2.astype(np.float64)))
    if not len(q):
        return empty, empty
    j, dq = train[q].astype(np.int64), d1[q]
    # per keypoint of b: the nearest match, the first in a's order among equals; in b's
    # order of first match
    order = np.lexsort((np.arange(len(j)), dq, j))
    js = j[order]
    head = np.ones(len(js), bool)
    head[1:] = js[1:] != js[:-1]
    pick = order[head]                                   # by b's index
    pick = pick[np.argsort(np.unique(j, return_index=True)[1], kind="stable")]
    ia, ib = query[q[pick]].astype(np.int64), j[pick]
    if by_distance:
        o = np.argsort(dq[pick], kind="stable")
        ia, ib = ia[o], ib[o]
    return ia, ib


def match_features(a: FeatureSet, b: FeatureSet, ratio: float = 0.8,
                   by_distance: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Matched keypoints ``(M, 2), (M, 2)`` float32 of ``a`` and ``b``
    (:func:`match_indices`)."""
    return matched_points(a, b, match_indices(a, b, ratio, by_distance))


def matched_points(a: FeatureSet, b: FeatureSet,
                   index: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The keypoints ``(M, 2), (M, 2)`` float32 of ``a`` and ``b`` at the matches' indices
    ``index`` (:func:`match_indices`, or a :class:`Verification`'s ``match_index``)."""
    ia, ib = index
    if not len(ia):
        empty = np.zeros((0, 2), np.float32)
        return empty, empty
    return a.keypoints_px[ia], b.keypoints_px[ib]


def verify_pair(old: FeatureSet, new: FeatureSet, params: VerifyParams = VerifyParams(),
                camera_matrix: np.ndarray | None = None) -> Verification:
    """Check that ``new`` and ``old`` see one 3D scene (epipolar geometry) and return the
    relative pose. ``camera_matrix (3, 3)``: intrinsics shared by both images (default
    :func:`camera_matrix_guess` for ``new``'s size). The matches' indices come back with it
    (:attr:`Verification.match_index`)."""
    ia, ib = match_indices(old, new, params.ratio)
    if len(ia):
        p_old, p_new = old.keypoints_px[ia], new.keypoints_px[ib]
    else:
        p_old = p_new = np.zeros((0, 2), np.float32)
    return replace(_verify_matched(old, new, p_old, p_new, params, camera_matrix), match_index=(ia, ib))


def _verify_matched(old: FeatureSet, new: FeatureSet, p_old: np.ndarray, p_new: np.ndarray, params: VerifyParams,
                    camera_matrix: np.ndarray | None) -> Verification:
    """:func:`verify_pair` of the matched pixels ``p_old, p_new (N, 2)``."""
    n = len(p_old)
    if n < max(5, params.min_inliers):
        return Verification(False, TOO_FEW_MATCHES, n, 0)
    k = camera_matrix if camera_matrix is not None else camera_matrix_guess(*new.image_size_px)
    # The matches through K^-1 once: every step below reads these rows (or a subset of them).
    xs = normalised_points(p_old, p_new, k)
    if params.model == "planar":
        _, search = ransac_planar(p_old, p_new, k, threshold_px=params.guide_threshold_px,
                                  min_inliers=params.min_inliers, confidence=params.ransac_confidence,
                                  max_samples=params.planar_max_samples, seed=params.seed, refine=False,
                                  normalised=xs)
        near = search.inliers(p_old, p_new, k, params.guide_threshold_px, xs) if search.best_inliers else None
        guided: _Motion | Verification = Verification(False, NO_GEOMETRIC_CONSISTENCY, n, 0)
        if near is not None and int(near.sum()) >= params.min_inliers:
            gp = params if params.guided_estimator is None else replace(params, estimator=params.guided_estimator)
            guided = _general_motion(p_old, p_new, k, gp, n, near, normalised=xs)
            if not isinstance(guided, Verification):
                guided = _checked(old, new, p_old, p_new, k, params, guided)
        assert isinstance(guided, Verification)
        if search.best_inliers:
            guided = replace(guided, level_yaw_rad=search.yaw_rad)
        if guided.accepted or params.fallback_inliers is None or search.best_inliers < params.fallback_inliers:
            return guided
        work = FallbackWork(old, new, p_old, p_new, k, params, xs, search, guided)
        if params.defer_fallback:
            return DueFallback(**{f.name: getattr(guided, f.name) for f in fields(Verification)}, work=work)
        return _fallback(work)
    elif params.model == "planar_motion":
        motion = _planar_motion(p_old, p_new, k, params)
        if isinstance(motion, int):
            best = motion
            refused = Verification(False, NO_GEOMETRIC_CONSISTENCY, n, 0)
        else:
            refused = _checked(old, new, p_old, p_new, k, params, motion)
            if refused.accepted:
                return refused
            best = refused.n_inliers
        # Not level, or no consensus: the general model only where the planar search found
        # a consensus of at least fallback_inliers (module notes, "The planar model").
        if params.fallback_inliers is None or best < params.fallback_inliers:
            return refused
        params = replace(params, max_iterations=min(params.max_iterations, params.fallback_max_iterations),
                         estimator=params.fallback_estimator or params.estimator)
        return replace(_general_verification(old, new, p_old, p_new, k, params, n), fallback=True)
    return _general_verification(old, new, p_old, p_new, k, params, n)


@dataclass(frozen=True, eq=False)
class FallbackWork:
    """What a planar model's general search after a failed search near the level motion
    needs, kept from that check (:attr:`VerifyParams.defer_fallback`): the two images, their
    matched pixels ``p_old, p_new (N, 2)``, the camera matrix ``k (3, 3)``, the parameters,
    the matches through ``K^-1`` (``xs``), the level search that guided the check and the
    check's own (failed) verification."""

    old: FeatureSet
    new: FeatureSet
    p_old: np.ndarray
    p_new: np.ndarray
    k: np.ndarray
    params: VerifyParams
    xs: tuple[np.ndarray, np.ndarray]
    search: PlanarSearch
    guided: Verification


@dataclass(frozen=True, eq=False)
class DueFallback(Verification):
    """A failed check whose general search is due (:attr:`VerifyParams.defer_fallback`): the
    check's :class:`Verification` and ``work``, what that search needs
    (:func:`fallback_verification` runs it)."""

    work: FallbackWork | None = None

    def checked(self) -> Verification:
        """The check itself, without the work (a plain :class:`Verification`)."""
        return Verification(**{f.name: getattr(self, f.name) for f in fields(Verification)})


def fallback_verification(v: DueFallback) -> Verification:
    """The verification ``v`` (a failed check whose general search is due, returned by
    :attr:`VerifyParams.defer_fallback`) finished: its general search run now, the answer
    :func:`verify_pair` without ``defer_fallback`` gives (its ``match_index`` kept)."""
    if v.work is None:
        raise ValueError("fallback_verification: this verification has no general search due")
    return replace(_fallback(v.work), match_index=v.match_index)


def _fallback(work: FallbackWork) -> Verification:
    """The planar model's general search over all the matches after its search near the
    level motion failed (module notes, "The planar model"), checked as the general model's."""
    old, new, p_old, p_new, k, xs, search, guided = (work.old, work.new, work.p_old, work.p_new, work.k, work.xs,
                                                     work.search, work.guided)
    n = len(p_old)
    # Not found near a level motion: the general search over all the matches, with at
    # most fallback_max_iterations samples (the stated cap on the work per image).
    params = replace(work.params, max_iterations=min(work.params.max_iterations, work.params.fallback_max_iterations),
                     estimator=work.params.fallback_estimator or work.params.estimator)
    if params.fallback_band_px is not None:
        band = search.inliers(p_old, p_new, k, params.fallback_band_px, xs)
        if int(band.sum()) < params.min_inliers:
            return replace(guided, fallback=True)
        if params.fallback_screen is not None and not _screen_passes(p_old, p_new, k, params, band, xs):
            return replace(guided, fallback=True, screened=True)
        banded = _general_motion(p_old, p_new, k, params, n, band, half_inliers=False, normalised=xs)
        checked = banded if isinstance(banded, Verification) else _checked(old, new, p_old, p_new, k, params,
                                                                            banded)
        return replace(checked, fallback=True, level_yaw_rad=guided.level_yaw_rad)
    return replace(_general_verification(old, new, p_old, p_new, k, params, n, xs), fallback=True,
                   level_yaw_rad=guided.level_yaw_rad)


def _general_verification(old: FeatureSet, new: FeatureSet, p_old: np.ndarray, p_new: np.ndarray, k: np.ndarray,
                          params: VerifyParams, n: int,
                          normalised: tuple[np.ndarray, np.ndarray] | None = None) -> Verification:
    """The general model over all the matches, checked (:func:`_checked`)."""
    general = _general_motion(p_old, p_new, k, params, n, normalised=normalised)
    if isinstance(general, Verification):
        return general
    return _checked(old, new, p_old, p_new, k, params, general)


def _checked(old: FeatureSet, new: FeatureSet, p_old: np.ndarray, p_new: np.ndarray, k: np.ndarray,
             params: VerifyParams, motion: _Motion) -> Verification:
    """The verification of a motion with at least ``min_inliers`` inliers: the range on the
    floor, the support check (module notes)."""
    n = len(p_old)
    inl, r, t_dir, sig_b, sig_y, noise, chi2 = motion
    n_inl = int(inl.sum())
    range_m, n_floor = (None, 0)
    if params.camera_height_m is not None:
        range_m, n_floor = floor_range(p_old[inl], p_new[inl], r, t_dir, k, params)
    if params.min_support_area <= 0.0:  # the paper's verification
        return Verification(True, ACCEPTED, n, n_inl, r, t_dir, range_m=range_m, n_floor_points=n_floor,
                            sigma_bearing_rad=sig_b, sigma_yaw_rad=sig_y, noise_px=noise,
                            planarity_chi2=chi2)
    # Not in the paper: the inliers must not be one small plane (module notes).
    s_old, s_new = p_old[inl], p_new[inl]
    # The support is all the inliers or a subset of them (its convex hull inside theirs): when
    # all of them cover too little, the check fails whatever the homography (not fitted).
    whole = _hull_support(s_old, s_new, old.image_size_px, new.image_size_px)
    if whole < params.min_support_area:
        return Verification(False, SMALL_SUPPORT, n, n_inl, r, t_dir, support_area=whole, range_m=range_m,
                            n_floor_points=n_floor, sigma_bearing_rad=sig_b, sigma_yaw_rad=sig_y, noise_px=noise,
                            planarity_chi2=chi2)
    _, hmask = cv2.findHomography(s_old, s_new, cv2.RANSAC, params.homography_threshold_px)
    on_plane = np.zeros(len(s_old), bool) if hmask is None else np.asarray(hmask).ravel() > 0
    n_plane = int(on_plane.sum())
    planar = n_plane >= params.planar_fraction * len(s_old)
    if planar:
        s_old, s_new = s_old[on_plane], s_new[on_plane]
    area = min(support_area(s_old, old.image_size_px), support_area(s_new, new.image_size_px))
    ok = area >= params.min_support_area
    return Verification(ok, ACCEPTED if ok else SMALL_SUPPORT, n, n_inl, r, t_dir,
                        n_plane_inliers=n_plane, planar=bool(planar), support_area=area,
                        range_m=range_m, n_floor_points=n_floor, sigma_bearing_rad=sig_b,
                        sigma_yaw_rad=sig_y, noise_px=noise, planarity_chi2=chi2)


def _hull_support(s_old: np.ndarray, s_new: np.ndarray, size_old: tuple[int, int], size_new: tuple[int, int]) -> float:
    """The support all the inliers ``s_old, s_new (M, 2)`` give: the smaller fraction of the two
    images their convex hulls cover (:func:`support_area`), an upper bound of the support test's."""
    return min(support_area(s_old, size_old), support_area(s_new, size_new))


#: A verified motion: (inlier mask (N,), rotation (3, 3), translation_dir (3,), sigma_bearing_rad,
#: sigma_yaw_rad, noise_px, planarity_chi2), as :class:`Verification` holds them.
_Motion = tuple[np.ndarray, np.ndarray, np.ndarray, float, float, float, float]


def _general_motion(p_old: np.ndarray, p_new: np.ndarray, k: np.ndarray, params: VerifyParams,
                    n: int, near: np.ndarray | None = None, half_inliers: bool = True,
                    normalised: tuple[np.ndarray, np.ndarray] | None = None) -> _Motion | Verification:
    """The general model: the essential matrix (``params.estimator``), ``cv2.recoverPose``'s
    cheirality check, the motion refined on the inliers (:func:`robotd.forward.planar.fit_motion`);
    a refused :class:`Verification` when it fails. With ``near (N,) bool`` the essential
    matrix is searched among those matches only and its inliers then counted among all
    (``"planar_guided"``): at most the samples that would draw five inliers were half of
    them inliers, or with ``half_inliers`` False RANSAC's own bound for ``min_inliers``
    (:func:`ransac_iterations`) up to ``params.max_iterations``. ``normalised``: the matches
    through ``K^-1`` (:func:`robotd.forward.planar.normalised_points`), not computed again."""
    if near is None:
        e, mask = essential_matrix(p_old, p_new, k, params)
    else:
        # Samples enough to draw five of the subset's inliers were half of it inliers.
        m = int(near.sum())
        sub = params if not half_inliers else replace(params, max_iterations=min(
            params.max_iterations, ransac_iterations(m, max(params.min_inliers, (m + 1) // 2), params.ransac_confidence)))
        e, _ = essential_matrix(p_old[near], p_new[near], k, sub)
        mask = None if e is None or e.shape[0] < 3 else _epipolar_mask(p_old, p_new, k, e[:3], params.ransac_threshold_px,
                                                                       normalised)
    if e is None or mask is None or e.shape[0] < 3:
        return Verification(False, NO_GEOMETRIC_CONSISTENCY, n, 0)
    e = e[:3]  # the five-point method may return up to ten solutions stacked; RANSAC keeps one
    n_inl, r, t, mask2 = cv2.recoverPose(e, p_old, p_new, k, mask=mask.copy())
    n_inl = int(n_inl)
    t = np.asarray(t, np.float64).reshape(3)
    t_dir = t / max(float(np.linalg.norm(t)), 1e-12)
    r = np.asarray(r, np.float64)
    if n_inl < params.min_inliers:
        return Verification(False, NO_GEOMETRIC_CONSISTENCY, n, n_inl, r, t_dir)
    inl = np.asarray(mask2).ravel() > 0
    # Not in the paper: the motion refined on all the inliers, and its uncertainty.
    fit = fit_motion(p_old[inl], p_new[inl], r, t_dir, k,
                     normalised=None if normalised is None else (normalised[0][inl], normalised[1][inl]))
    return (inl, fit.rotation, fit.translation_dir, fit.sigma_bearing_rad, fit.sigma_yaw_rad, fit.noise_px,
            fit.planarity_chi2)


def _screen_passes(p_old: np.ndarray, p_new: np.ndarray, k: np.ndarray, params: VerifyParams, band: np.ndarray,
                   normalised: tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether the band fallback's screen (``params.fallback_screen``) finds an essential
    matrix among the matches in ``band (N,) bool`` with at least ``min_inliers`` inliers
    over all the matches in front of both cameras (the test the general search after it
    must pass); the same iteration bound as that search. It only decides whether that
    search runs: its own matrix is never the verified one."""
    sp = replace(params, estimator=params.fallback_screen or params.estimator)
    e, _ = essential_matrix(p_old[band], p_new[band], k, sp)
    if e is None or e.shape[0] < 3:
        return False
    e = e[:3]
    mask = _epipolar_mask(p_old, p_new, k, e, params.ransac_threshold_px, normalised)
    if int(mask.sum()) < params.min_inliers:
        return False
    n_inl, _, _, _ = cv2.recoverPose(e, p_old, p_new, k, mask=mask.copy())
    return int(n_inl) >= params.min_inliers


def _epipolar_mask(p_old: np.ndarray, p_new: np.ndarray, k: np.ndarray, e: np.ndarray,
                   threshold_px: float, normalised: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """``(N, 1) uint8``: the matches within ``threshold_px`` (Sampson distance) of the essential
    matrix ``e (3, 3)``, as OpenCV's inlier masks (``normalised``: the matches through
    ``K^-1``, :func:`robotd.forward.planar.normalised_points`)."""
    xo, xn = normalised_points(p_old, p_new, k) if normalised is None else normalised
    ex = xo @ e.T
    etx = xn @ e
    d = 0.5 * (k[0, 0] + k[1, 1]) * np.abs(np.einsum("ij,ij->i", xn, ex)) / np.sqrt(
        np.maximum(ex[:, 0] ** 2 + ex[:, 1] ** 2 + etx[:, 0] ** 2 + etx[:, 1] ** 2, 1e-30))
    return (d < threshold_px).astype(np.uint8).reshape(-1, 1)


def _planar_motion(p_old: np.ndarray, p_new: np.ndarray, k: np.ndarray, params: VerifyParams) -> _Motion | int:
    """The planar model (:func:`robotd.forward.planefit.ransac_planar`), or the best planar
    consensus' size when it has fewer than ``min_inliers`` in front of both cameras. Its
    sigmas are given as the general fit gives them, the inliers' own noise (the planar
    fit's divided by :data:`robotd.forward.planar.INLIER_NOISE_FACTOR`, which its user
    applies); its out-of-plane part is zero by construction (``planarity_chi2`` 0)."""
    fit, search = ransac_planar(p_old, p_new, k, threshold_px=params.ransac_threshold_px,
                                min_inliers=params.min_inliers, confidence=params.ransac_confidence,
                                max_samples=params.planar_max_samples, seed=params.seed)
    if fit is None or fit.n_inliers < params.min_inliers:
        return search.best_inliers
    inl = fit.inliers
    kinv = np.linalg.inv(k)
    xo = np.hstack([p_old[inl], np.ones((int(inl.sum()), 1))]) @ kinv.T
    xn = np.hstack([p_new[inl], np.ones((int(inl.sum()), 1))]) @ kinv.T
    e = np.cross(fit.translation_dir, fit.rotation.T).T  # [t]x R, column by column
    ex = xo @ e.T
    etx = xn @ e
    focal = 0.5 * (k[0, 0] + k[1, 1])
    d = focal * np.einsum("ij,ij->i", xn, ex) / np.sqrt(np.maximum(ex[:, 0] ** 2 + ex[:, 1] ** 2 + etx[:, 0] ** 2
                                                                     + etx[:, 1] ** 2, 1e-30))
    noise = float(np.sqrt(float(d @ d) / max(len(d) - 2, 1)))
    return (inl, fit.rotation, fit.translation_dir, fit.sigma_bearing_rad / INLIER_NOISE_FACTOR,
            fit.sigma_yaw_rad / INLIER_NOISE_FACTOR, noise, 0.0)


_NO_DISTORTION = np.zeros(5)


def essential_matrix(p_old: np.ndarray, p_new: np.ndarray, camera_matrix: np.ndarray,
                     params: VerifyParams) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(E, inlier mask)`` of the matches ``p_old, p_new (N, 2)`` as OpenCV returns them
    (E may stack several solutions; None when none was found), searched with
    ``params.estimator``, ``ransac_confidence``, ``ransac_threshold_px`` and at most
    :func:`ransac_iterations` samples; OpenCV's generator seeded with ``params.seed``."""
    iters = ransac_iterations(len(p_old), params.min_inliers, params.ransac_confidence, cap=params.max_iterations)
    if params.estimator == "ransac":
        cv2.setRNGSeed(params.seed)
        e, mask = cv2.findEssentialMat(p_old, p_new, camera_matrix, cv2.RANSAC, params.ransac_confidence,
                                       params.ransac_threshold_px, iters)
        return e, mask
    u = cv2.UsacParams()
    u.confidence = params.ransac_confidence
    u.threshold = params.ransac_threshold_px
    u.maxIterations = iters
    u.sampler = cv2.SAMPLING_UNIFORM
    u.score = cv2.SCORE_METHOD_RANSAC          # the inlier count, as RANSAC
    # each new best model refined on its inliers, or none (RANSAC's test, a cheaper sample)
    u.loMethod = cv2.LOCAL_OPTIM_INNER_LO if params.local_optimisation else cv2.LOCAL_OPTIM_NULL
    u.final_polisher = cv2.NONE_POLISHER
    u.randomGeneratorState = params.seed
    u.isParallel = False
    k = np.asarray(camera_matrix, np.float64)
    e, mask = cv2.findEssentialMat(p_old, p_new, k, k, _NO_DISTORTION, _NO_DISTORTION, u)
    return e, mask


#: OpenCV's own cap on RANSAC iterations (``findEssentialMat``'s ``maxIters`` default).
MAX_RANSAC_ITERATIONS = 1000


def ransac_iterations(n_matches: int, min_inliers: int, confidence: float,
                      sample: int = 5, cap: int = MAX_RANSAC_ITERATIONS) -> int:
    """RANSAC iterations after which a model with ``min_inliers`` of ``n_matches``
    inliers would have been found with probability ``confidence`` (``log(1 - confidence) /
    log(1 - w^sample)``, ``w = min_inliers / n_matches``), at most ``cap``. A candidate
    needs ``min_inliers`` to be accepted, so RANSAC need not search longer for a smaller
    consensus: with few matches it stops after tens of samples instead of OpenCV's 1000
    (not in the paper; module notes, "Time")."""
    if n_matches <= 0:
        return 1
    w = min(1.0, min_inliers / n_matches)
    miss = 1.0 - w ** sample
    if miss <= 0.0:
        return 1
    if miss >= 1.0:
        return cap
    return int(max(1, min(cap, np.ceil(np.log(1.0 - confidence) / np.log(miss)))))


def floor_range(p_old: np.ndarray, p_new: np.ndarray, rotation: np.ndarray, translation_dir: np.ndarray,
                camera_matrix: np.ndarray, params: VerifyParams) -> tuple[float | None, int]:
    """``(range_m, n_floor_points)``: the distance between the two camera centres, metres,
    from the inliers on the floor (module notes), or ``(None, n)`` when fewer than
    ``params.min_floor_points`` agree. ``p_old, p_new (M, 2)`` inlier pixels; ``rotation``,
    ``translation_dir`` as :class:`Verification`; the camera is level (OpenCV y down)."""
    if params.camera_height_m is None or len(p_old) < params.min_floor_points:
        return None, 0
    k = np.asarray(camera_matrix, np.float64)
    p1 = k @ np.hstack([np.eye(3), np.zeros((3, 1))])
    p2 = k @ np.hstack([np.asarray(rotation, np.float64), np.asarray(translation_dir, np.float64).reshape(3, 1)])
    x = cv2.triangulatePoints(p1, p2, np.asarray(p_old, np.float64).T, np.asarray(p_new, np.float64).T)
    w = x[3]
    ok = np.abs(w) > 1e-12
    y = np.where(ok, x[1] / np.where(ok, w, 1.0), -1.0)
    z = np.where(ok, x[2] / np.where(ok, w, 1.0), -1.0)
    below = (y > 0.0) & (z > 0.0)  # in front of the camera and below its optical centre
    if int(below.sum()) < params.min_floor_points:
        return None, 0
    ly = np.log(y[below])
    # The largest group at one height: for each point, the points within the band around it.
    near = np.abs(ly[:, None] - ly[None, :]) <= params.floor_band_log
    counts = near.sum(axis=1)
    best = int(np.argmax(counts))
    n_floor = int(counts[best])
    if n_floor < params.min_floor_points:
        return None, n_floor
    height_unit = float(np.exp(np.median(ly[near[best]])))  # floor depth below the camera, baseline 1
    return params.camera_height_m / height_unit, n_floor


def support_area(points_px: np.ndarray, image_size_px: tuple[int, int]) -> float:
    """The fraction of an image (``(width, height)``) covered by the convex hull of
    ``points_px (N, 2)``; 0 for fewer than three points."""
    if len(points_px) < 3:
        return 0.0
    w, h = image_size_px
    hull = cv2.convexHull(np.asarray(points_px, np.float32).reshape(-1, 1, 2))
    return float(cv2.contourArea(hull)) / float(w * h)
