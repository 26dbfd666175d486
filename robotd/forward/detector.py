"""The forward loop detector: one image in, one decision out (paper 000 Sec. III-IV).

For image I_t (t = 0, 1, 2, ... in arrival order), :meth:`ForwardDetector.process`:

1. extracts its features (SIFT by default);
2. finds its words in the vocabulary Z_t, creating words for descriptors that match none
   (they are part of Z_t+1; they cannot vote, no past image has them);
3. votes through the inverted index: a tf-idf score for every past image and for the
   virtual no-loop image; the hypotheses' likelihood factors follow
   (:mod:`robotd.forward.likelihood`);
4. runs the Bayes filter over the hypotheses -1, 0 .. t - p (:mod:`robotd.forward.filter`)
   and picks a candidate when its neighbourhood's posterior exceeds 0.8;
5. verifies the candidate with epipolar geometry (:mod:`robotd.forward.verify`; beyond the
   paper, the inliers must also not be one small plane, such as a repeated poster); a
   rejected candidate is only dismissed for this image: its posterior is left as it is and
   diffuses on (Sec. IV-C).

Then I_t is added to the inverted index. Each stage is timed with the injected timer (paper
Fig. 7). The :class:`Detection` says why an image closed no loop, as DLoopDetector does.

The features of every image are kept for the verification: in memory, or, with a
``loader`` (the daemon's map), only those of the last ``resident`` images and of the few
read back lately, the older ones read back from the map when a candidate needs them. By
default the inverted index, the votes and the filter grow with the run, as in the paper.
With ``DetectorParams.memory.max_places`` (or ``time_budget_s``) set, a working memory
(:mod:`robotd.forward.memory`) bounds them: only the places in it vote and are hypotheses
(the filter runs over their ids, :func:`robotd.forward.filter.predict_ids`); after each
image the memory stage links a verified loop's places, retrieves long-term places next to
a place being recognised, and moves the least useful places out to keep the bound.
"""

from __future__ import annotations

import math
import sys
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import TypedDict, Unpack

import numpy as np

from robotd.forward.features import (CompactFeatures, FeatureExtractor, FeatureParams, Features, LentFeatures, compact,
                                     lend, without_words)
from robotd.forward.filter import (FilterParams, diffusion_weights, predict, predict_ids, select_candidate,
                                   select_candidate_ids, update)
from robotd.forward.likelihood import LikelihoodMethod, adjust_likelihood
from robotd.forward.memory import MemoryParams, WorkingMemory
from robotd.forward.verify import (TOO_FEW_MATCHES, DueFallback, Verification, VerifyParams, fallback_verification,
                                   verify_pair)
from robotd.forward.vocabulary import InvertedIndex, Vocabulary, VocabularyParams

__all__ = ["ACCEPT_PENDING", "VERIFY_PENDING", "Detection", "DetectionStatus", "DetectorParams", "ForwardDetector", "LOOP", "METHODS", "NO_HYPOTHESES",
           "LOW_POSTERIOR", "NOT_CONSISTENT_YET", "NO_GEOMETRIC_CONSISTENCY", "OdometryParams", "STAGES",
           "bounded_verification", "daemon_params", "method_params", "odometry_factor", "pose_agreement", "predict_metric",
           "unbounded_verification"]

class DetectionStatus(StrEnum):
    """Why an image closed a loop or did not (a :class:`~enum.StrEnum`: equal to its text)."""

    LOOP = "LOOP"
    NO_HYPOTHESES = "NO_HYPOTHESES"          # t < p: no past image can be a loop yet
    LOW_POSTERIOR = "LOW_POSTERIOR"          # no neighbourhood's posterior above the threshold
    NO_GEOMETRIC_CONSISTENCY = "NO_GEOMETRIC_CONSISTENCY"  # the candidate failed verification
    NOT_CONSISTENT_YET = "NOT_CONSISTENT_YET"  # fewer than k consistent candidates in a row
    ACCEPT_PENDING = "ACCEPT_PENDING"  # a view verified, its ``accept`` test left for :meth:`ForwardDetector.resume`
    VERIFY_PENDING = "VERIFY_PENDING"  # the image's check budget spent, its views left for :meth:`ForwardDetector.resume`


LOOP = DetectionStatus.LOOP
NO_HYPOTHESES = DetectionStatus.NO_HYPOTHESES
LOW_POSTERIOR = DetectionStatus.LOW_POSTERIOR
NO_GEOMETRIC_CONSISTENCY = DetectionStatus.NO_GEOMETRIC_CONSISTENCY
NOT_CONSISTENT_YET = DetectionStatus.NOT_CONSISTENT_YET
ACCEPT_PENDING = DetectionStatus.ACCEPT_PENDING
VERIFY_PENDING = DetectionStatus.VERIFY_PENDING

#: The detectors ``[forward_detector] method`` and ``robotd eval forward --method`` select.
METHODS = ("default", "paper")

#: Timed stages, in order (seconds in :attr:`Detection.times_s`, plus ``"total"``).
STAGES = ("features", "words", "likelihood", "filter", "verify", "memory")


@dataclass(frozen=True)
class OdometryParams:
    """The keyframe's odometry as a second likelihood (beyond the paper: its Sec. VI names
    the robot's metric pose as the next step).

    With ``use`` and a pose given to :meth:`ForwardDetector.process_features`, each image
    hypothesis j's likelihood factor is multiplied by ``exp(-d^2 / 2)``, where d is the
    Mahalanobis distance between the current pose and image j's pose, per component
    (x, y, yaw; yaw wrapped), over the variance that odometry accumulated between the two
    images (the current covariance's diagonal minus image j's, never negative: odometry
    drift is a random walk, so what j already had does not separate them) plus the size of
    a place (``place_sigma_m``, ``place_sigma_yaw_rad``: how far apart two views of one
    place may be). The no-loop hypothesis keeps its factor: odometry says nothing about a
    new place. A hypothesis far beyond the accumulated uncertainty (an aliased corridor at
    the other end of the map) gets a factor near 0; as drift grows, the factor flattens
    towards 1 and the detector falls back to appearance alone. Images without a pose get
    factor 1.

    Fields:
        use: whether the odometry likelihood multiplies in (False: the paper).
        place_sigma_m: metres, the spread in x and y of one place's views.
        place_sigma_yaw_rad: radians, the spread of headings of one place's views.
        agree_factor: a candidate whose odometry factor is at least this "agrees" with
            odometry (0.6: within about one standard deviation).
        agree_min_inliers, agree_min_support_area: the verification's ``min_inliers`` and
            ``min_support_area`` (:class:`~robotd.forward.verify.VerifyParams`) for a
            candidate that agrees with odometry (None: the verification's own): two
            independent sensors agreeing need less geometric evidence than appearance alone.
        merge_places: views of one place merged by their metric pose (the paper's Sec. VI
            next step): the candidate is picked among places instead of time
            neighbourhoods, a place being the hypotheses within ``filter.neighbours``
            images of an image or whose odometry factor against it (their poses and the
            variance odometry accumulated between them) is at least ``agree_factor`` (the
            same spot seen on another lap); the place with the largest summed posterior
            wins, its most probable image is the candidate and, with the neighbourhood
            rule, that sum is its probability. Works whether or not ``use`` multiplies the
            likelihood; images without a pose are merged by time only.
        metric_neighbours: neighbours by distance in the filter's transition (the paper's
            Sec. VI next step): the mass of a probable hypothesis j (one of the 32 most
            probable) moves to the images whose pose is near j's, a Gaussian in the pose
            difference over ``neighbour_sigma_m``, ``neighbour_sigma_yaw_rad`` plus the
            variance odometry accumulated between the two images (the same spot on another
            lap is a neighbour as much as the next image), with the ``filter.neighbours``
            images around j kept at least at their time Gaussian (so images without a pose
            still get theirs); instead of the ``filter.neighbours`` images around j only.
            Images without a pose, and the rest of the mass, diffuse over image indexes as
            in the paper.
        neighbour_sigma_m, neighbour_sigma_yaw_rad: metres and radians, the spread of that
            Gaussian (0.4 m, 0.5 rad: about one keyframe step).
        verify_place: with ``verify_tries > 1``, the images tried after a failed candidate
            are the candidate's metric neighbours (its place: the hypotheses whose pose
            agrees with the candidate's, factor at least ``agree_factor`` over the place
            sizes and the variance accumulated between them), most probable first, instead
            of its time neighbours that agree with the current pose. Needs the images'
            poses, not ``use``; without them only the candidate is verified.
        variance_scale: the accumulated odometry variance is multiplied by this
            (dimensionless, >= 1) before it is compared: a filter's covariance that is
            too confident over a long run (on the office route the wheel + gyro filter's
            lateral error after three laps is twice its claimed sigma) makes the factor
            favour the place where the drifted odometry puts the robot over the true one.
    """

    use: bool = False
    place_sigma_m: float = 1.0
    place_sigma_yaw_rad: float = 0.6
    agree_factor: float = 0.6
    agree_min_inliers: int | None = None
    agree_min_support_area: float | None = None
    merge_places: bool = False
    metric_neighbours: bool = False
    neighbour_sigma_m: float = 0.4
    neighbour_sigma_yaw_rad: float = 0.5
    verify_place: bool = False
    variance_scale: float = 1.0

    def __post_init__(self) -> None:
        if not (self.place_sigma_m > 0 and self.place_sigma_yaw_rad > 0):
            raise ValueError("place_sigma_m and place_sigma_yaw_rad must be positive")
        if not (self.neighbour_sigma_m > 0 and self.neighbour_sigma_yaw_rad > 0):
            raise ValueError("neighbour_sigma_m and neighbour_sigma_yaw_rad must be positive")
        if not 0.0 < self.agree_factor <= 1.0:
            raise ValueError(f"agree_factor must be in (0, 1], got {self.agree_factor}")
        if not (math.isfinite(self.variance_scale) and self.variance_scale >= 1.0):
            raise ValueError(f"variance_scale must be >= 1, got {self.variance_scale}")
        if self.agree_min_inliers is not None and self.agree_min_inliers < 5:
            raise ValueError(f"agree_min_inliers must be >= 5 (the five-point solver), got {self.agree_min_inliers}")


def odometry_factor(pose: np.ndarray, pose_var: np.ndarray, poses: np.ndarray, poses_var: np.ndarray,
                    params: OdometryParams) -> np.ndarray:
    """The odometry likelihood factors of :class:`OdometryParams`: ``pose (3,)`` and
    ``pose_var (3,)`` (x_m, y_m, yaw_rad and their variances) of the current image against
    ``poses (n, 3)``, ``poses_var (n, 3)`` of the hypotheses; returns ``(n,)`` in (0, 1]
    (1 where either pose is unknown: NaN)."""
    d = np.asarray(poses, np.float64) - np.asarray(pose, np.float64)[None, :]
    d[:, 2] = (d[:, 2] + np.pi) % (2.0 * np.pi) - np.pi
    acc = np.maximum(np.asarray(pose_var, np.float64)[None, :] - np.asarray(poses_var, np.float64), 0.0)
    acc *= params.variance_scale
    place = np.array([params.place_sigma_m ** 2] * 2 + [params.place_sigma_yaw_rad ** 2])
    d2 = (d * d / (acc + place[None, :])).sum(axis=1)
    return np.where(np.isfinite(d2), np.exp(-0.5 * np.where(np.isfinite(d2), d2, 0.0)), 1.0)


def pose_agreement(poses: np.ndarray, poses_var: np.ndarray, j: int, sigma: np.ndarray,
                   variance_scale: float = 1.0) -> np.ndarray:
    """``exp(-d^2 / 2)`` of every stored image against image ``j``: ``poses (n, 3)``,
    ``poses_var (n, 3)`` (x_m, y_m, yaw_rad and their variances; NaN: unknown), d the
    Mahalanobis distance per component over ``sigma (3,)`` (variances: the size of a place)
    plus the variance odometry accumulated between the two images (the difference of their
    variances, times ``variance_scale``); ``(n,)`` in [0, 1], 0 where a pose is unknown."""
    d = poses - poses[j][None, :]
    d[:, 2] = (d[:, 2] + np.pi) % (2.0 * np.pi) - np.pi
    d2 = (d * d / (variance_scale * np.abs(poses_var - poses_var[j][None, :]) + sigma[None, :])).sum(axis=1)
    return np.where(np.isfinite(d2), np.exp(-0.5 * np.where(np.isfinite(d2), d2, 0.0)), 0.0)


def predict_metric(posterior: np.ndarray, n_new: int, poses: np.ndarray, poses_var: np.ndarray,
                   p: DetectorParams, top: int = 32, min_mass: float = 1e-6) -> np.ndarray:
    """The filter's prediction with neighbours by distance (:attr:`OdometryParams.metric_neighbours`):
    ``posterior (1 + n_prev,)`` over no loop and images 0 .. n_prev - 1, ``n_new``
    hypotheses at t, the images' ``poses (>= n_new, 3)`` and ``poses_var``; returns the
    prior ``(1 + n_new,)``, with the posterior's sum. The ``top`` most probable images with
    a pose (and at least ``min_mass``) spread their mass by pose; the rest by index
    (:func:`robotd.forward.filter.predict`)."""
    post = np.asarray(posterior, np.float64)
    img = post[1:]
    n_prev = len(img)
    f, o = p.filter, p.odometry
    if n_prev == 0 or n_new == 0:
        return predict(post, n_new, f)
    cand = np.argsort(-img, kind="stable")[:top]
    cand = cand[(img[cand] > min_mass) & np.isfinite(poses[cand]).all(axis=1)]
    rest = post.copy()
    rest[1 + cand] = 0.0
    prior = predict(rest, n_new, f)
    if not len(cand):
        return prior
    prior[0] += f.p_loop_ends * float(img[cand].sum())
    sigma = np.array([o.neighbour_sigma_m ** 2] * 2 + [o.neighbour_sigma_yaw_rad ** 2])
    g = diffusion_weights(f)
    g = g / g.max()
    idx = np.arange(n_new)
    hp, hv = poses[:n_new], poses_var[:n_new]
    for j in cand.tolist():
        w = pose_agreement(hp, hv, j, sigma, o.variance_scale)
        k = idx - j
        near = np.abs(k) <= f.neighbours
        w[near] = np.maximum(w[near], g[k[near] + f.neighbours])
        w[w < 1e-3] = 0.0
        prior[1:] += (1.0 - f.p_loop_ends) * img[j] * w / w.sum()
    return prior


@dataclass(frozen=True)
class DetectorParams:
    """All parameters of the forward detector, with the paper's values as defaults.

    Fields:
        features: feature kind and count (:class:`~robotd.forward.features.FeatureParams`).
        vocabulary: word radius and search (:class:`~robotd.forward.vocabulary.VocabularyParams`).
        filter: transition model and loop threshold (:class:`~robotd.forward.filter.FilterParams`).
        verify: epipolar check (:class:`~robotd.forward.verify.VerifyParams`; its
            ``min_support_area = 0`` is the paper's check without the support test).
        verify_tries: when the candidate fails verification, its neighbours (the images
            within ``filter.neighbours`` of it: other views of the same place) whose
            odometry agrees (factor at least ``odometry.agree_factor``; none without
            odometry) are verified in turn, most probable first, up to this many images in
            all (1: the paper, only the candidate); the first accepted is the loop.
        recent_excluded: p, the last images that are never hypotheses (10, Sec. IV).
        likelihood: ``"paper"`` (default) or RTAB-Map's ``"rtabmap"`` normalisation.
        memory: the working memory (:class:`~robotd.forward.memory.MemoryParams`; no bound
            by default, the paper's detector).
        consistency: k, candidates of this many images in a row, each within
            ``consistency_gap`` images of the one before, before the candidate is verified
            (DLoopDetector's temporal consistency; 1 = the paper: every candidate is
            verified).
        consistency_gap: how far (images) a candidate may be from the previous image's to
            count as the same loop continuing.
        decision: ``"filter"`` (the paper's Bayes filter picks the candidate) or
            ``"score"``: the best-scoring hypothesis is the candidate when its normalised
            score exceeds ``score_threshold`` (no filter; DLoopDetector's decision, issue
            24). The candidate's probability is then that normalised score.
        score_normalisation: ``"virtual"``: the best score over the virtual no-loop
            image's vote; ``"previous"``: over the vote of the image just before
            (DLoopDetector's normalisation by the best score one can expect).
        score_threshold: the normalised score a candidate must exceed.
        islands: with the score decision, group the images whose normalised score
            exceeds ``score_threshold`` into islands (runs of images at most
            ``consistency_gap`` apart, DLoopDetector's temporal islands); the island with the
            largest summed normalised score wins and its best image is the candidate, with
            that sum as its probability. False: the single best image.
        odometry: the keyframes' odometry as a second likelihood
            (:class:`OdometryParams`; off by default, the paper).
        verify_fallbacks: the most fallbacks (a planar verification's general search,
            :class:`~robotd.forward.verify.VerifyParams`; ``Verification.fallback``) one image
            runs over its ``verify_tries`` views; once they ran, the views after are verified
            near their level motion only. None: no bound (each may fall back).
        fallbacks_last: the fallbacks after every view's check near its level motion: the
            image's views are checked near their level motion first, in order, and only when
            none passes do the fallbacks that were due run, in the views' order, at most
            ``verify_fallbacks`` of them (:attr:`~robotd.forward.verify.VerifyParams.defer_fallback`).
            A view's fallback no longer runs before a later view's check near its level
            motion, which is a fraction of its cost (``docs/forward.md``, "The verification").
            False: each view's fallback right after its own check.
    """

    features: FeatureParams = field(default_factory=FeatureParams)
    vocabulary: VocabularyParams = field(default_factory=VocabularyParams)
    filter: FilterParams = field(default_factory=FilterParams)
    verify: VerifyParams = field(default_factory=VerifyParams)
    verify_tries: int = 1
    recent_excluded: int = 10
    likelihood: LikelihoodMethod = "paper"
    memory: MemoryParams = field(default_factory=MemoryParams)
    consistency: int = 1
    consistency_gap: int = 3
    decision: str = "filter"
    score_normalisation: str = "virtual"
    score_threshold: float = 1.0
    islands: bool = False
    odometry: OdometryParams = field(default_factory=OdometryParams)
    verify_fallbacks: int | None = None
    fallbacks_last: bool = False

    def __post_init__(self) -> None:
        if self.verify_fallbacks is not None and self.verify_fallbacks < 0:
            raise ValueError(f"verify_fallbacks must be >= 0 or None, got {self.verify_fallbacks}")
        if self.decision not in ("filter", "score"):
            raise ValueError(f"decision must be 'filter' or 'score', got {self.decision!r}")
        if self.score_normalisation not in ("virtual", "previous"):
            raise ValueError(f"score_normalisation must be 'virtual' or 'previous', got {self.score_normalisation!r}")
        if self.decision == "score" and self.memory.bounded:
            raise ValueError("the score decision runs without a working memory bound")
        if self.consistency < 1:
            raise ValueError(f"consistency must be >= 1, got {self.consistency}")
        if self.consistency_gap < 0:
            raise ValueError(f"consistency_gap must be >= 0, got {self.consistency_gap}")
        if self.verify_tries < 1:
            raise ValueError(f"verify_tries must be >= 1, got {self.verify_tries}")
        if self.recent_excluded < 1:
            raise ValueError(f"recent_excluded must be >= 1, got {self.recent_excluded}")


class DetectorOverrides(TypedDict, total=False):
    """Fields of :class:`DetectorParams` that :func:`method_params` may replace (by keyword;
    mypy checks each against the field it replaces)."""

    features: FeatureParams
    vocabulary: VocabularyParams
    filter: FilterParams
    verify: VerifyParams
    verify_tries: int
    recent_excluded: int
    likelihood: LikelihoodMethod
    memory: MemoryParams
    consistency: int
    consistency_gap: int
    decision: str
    score_normalisation: str
    score_threshold: float
    islands: bool
    odometry: OdometryParams
    verify_fallbacks: int | None
    fallbacks_last: bool


@dataclass(eq=False)
class PendingVerification:
    """An image's verification stopped at a view whose epipolar check passed, before the
    detector's ``accept`` test (:meth:`ForwardDetector.process_features` with
    ``defer_accept``), or before its next view's epipolar check when the call's
    ``max_checks`` were spent; :meth:`ForwardDetector.resume` goes on with it. It holds what the views
    still to try need, taken when the image was run (its features, the views in order, which
    of them odometry agrees with), so finishing it later gives the answer finishing it at
    once would have (the detector's state after the image is not read; with a bounded
    working memory the loop's places are linked when it finishes).

    Fields: ``image_id`` (the image verified), ``candidate`` (the filter's), ``view`` and
    ``verification`` (the view awaiting ``accept`` and its check), ``order`` (every view to
    try, in order), ``next`` (the first not yet verified), ``agreed`` (views odometry agrees
    with: their ``VerifyParams`` relaxed), ``fallbacks`` (general searches run so far),
    ``failed`` (the checks of the views that failed, in the views' order), ``due`` (with
    :attr:`DetectorParams.fallbacks_last`, the failed checks whose fallback is due, each
    with its place in ``failed``), ``checks`` (epipolar checks run for it so far, over every
    call: a check near the level motion and a fallback run later count one each)."""

    image_id: int
    candidate: int
    feats: Features
    order: list[int]
    agreed: frozenset[int]
    next: int = 0
    fallbacks: int = 0
    failed: list[Verification] = field(default_factory=list)
    view: int | None = None
    verification: Verification | None = None
    checks: int = 0
    due: list[tuple[int, int, DueFallback]] = field(default_factory=list)

    @property
    def finished(self) -> bool:
        """Nothing left: no view awaiting its test, none to check, no fallback due."""
        return self.view is None and self.next >= len(self.order) and not self.due


@dataclass(frozen=True, eq=False)
class Detection:
    """What the detector decided for one image.

    Fields:
        image_id: t, the image's number (0 for the first).
        status: ``LOOP``, ``NO_HYPOTHESES``, ``LOW_POSTERIOR``, ``NOT_CONSISTENT_YET``,
            ``NO_GEOMETRIC_CONSISTENCY`` or, asked to defer the ``accept`` test,
            ``ACCEPT_PENDING`` (:attr:`pending` then holds the rest of the verification),
            or, its ``max_checks`` spent with views left, ``VERIFY_PENDING`` (the same).
        loop_id: the past image it closes a loop with (status ``LOOP``), else None.
        candidate_id: the filter's candidate (verified or not), else None.
        candidate_probability: the largest posterior summed over a neighbourhood.
        scores: ``(t,)`` tf-idf votes of every past image 0 .. t - 1 (the last p included,
            for plots and the best-score baseline; they are not hypotheses); 0 for a place
            in long-term memory.
        virtual_score: the vote of the virtual no-loop image.
        likelihood: ``(1 + n,)`` factors of the hypotheses: no loop, then the images
            ``hypothesis_ids`` (0 .. t - p without a working memory).
        posterior: ``(1 + n,)`` p(S_t | z^t) over the same hypotheses.
        verification: the epipolar check of the candidate, when one was made (with
            ``ACCEPT_PENDING``, the view's awaiting the ``accept`` test).
        n_features: keypoints in the image; new_words: words it created;
        vocabulary_size: words after it.
        times_s: seconds per stage (:data:`STAGES`) and ``"total"``.
        hypothesis_ids: ``(n,)`` the image of each hypothesis, sorted.
        working_memory: places in the working memory after this image (all past images
            without a bound); retrieved, transferred: the places that came back from and
            went to long-term memory after it.
        pending: with ``ACCEPT_PENDING`` or ``VERIFY_PENDING``, the verification to
            finish with :meth:`ForwardDetector.resume`; else None.
        checks: the epipolar checks (:func:`~robotd.forward.verify.verify_pair` calls, and the
            fallbacks run after them, :func:`~robotd.forward.verify.fallback_verification`) run
            for the image in this call.
    """

    image_id: int
    status: DetectionStatus
    loop_id: int | None
    candidate_id: int | None
    candidate_probability: float
    scores: np.ndarray
    virtual_score: float
    likelihood: np.ndarray
    posterior: np.ndarray
    verification: Verification | None
    n_features: int
    new_words: int
    vocabulary_size: int
    times_s: dict[str, float]
    hypothesis_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    working_memory: int = 0
    retrieved: tuple[int, ...] = ()
    transferred: tuple[int, ...] = ()
    pending: PendingVerification | None = None
    checks: int = 0

    @property
    def n_hypotheses(self) -> int:
        """Image hypotheses at this step (t - p + 1, or 0)."""
        return len(self.posterior) - 1


READ_BACK_KEPT = 32
"""Past images whose features, read back by a :class:`ForwardDetector`'s loader, it keeps
(the most recently used): a place being revisited is verified again image after image."""


class ForwardDetector:
    """The incremental Bayesian loop-closure detector of paper 000.

    ``camera_matrix (3, 3)``: the forward camera's intrinsics for verification (default: a
    guess from the image size, :func:`robotd.forward.verify.camera_matrix_guess`);
    ``timer``: a monotonic clock in seconds, for the stage times; ``accept(image, its
    verification)``: a further test an accepted verification of a past image must pass to
    be a loop (the daemon's: the motion is a level camera's,
    :mod:`robotd.app.stages.forward_loops`); one that fails it counts as a failed
    verification, so the next image of ``verify_tries`` is tried (None: none). It runs
    after the current image joined the detector (``features_of(len(self) - 1)``).

    ``loader(image)``: the stored features of a past image that :meth:`mark_stored` named
    (the daemon's: read from the map); with one, only the features of the last ``resident``
    images and of the :data:`READ_BACK_KEPT` read back most recently stay in memory. It
    raises LookupError when it cannot give them (then that image fails its verification).
    """

    def __init__(self, params: DetectorParams = DetectorParams(),
                 camera_matrix: np.ndarray | None = None,
                 timer: Callable[[], float] = time.perf_counter,
                 accept: Callable[[int, Verification], bool] | None = None,
                 loader: Callable[[int], CompactFeatures] | None = None, resident: int = 1024) -> None:
        if resident < 1:
            raise ValueError(f"resident must be >= 1, got {resident}")
        self.params = params
        self.camera_matrix = camera_matrix
        self._timer = timer
        self.accept = accept
        self.loader = loader
        self.resident = resident
        self._in_store = bytearray()  # per image: 1 once the loader can give its features
        self._size: tuple[int, int] = (0, 0)  # the latest lent image's size
        self._latest_words = np.zeros(0, np.uint32)  # the latest image's word ids (its record keeps none)
        self._read_back: OrderedDict[int, CompactFeatures] = OrderedDict()  # the latest read back
        self.read_back = 0  # images whose features the loader gave
        self.read_back_failed = 0  # images it could not give (their verification failed)
        self._extract = FeatureExtractor(params.features)
        fp = params.features
        self.vocabulary = Vocabulary(dim=fp.descriptor_size, binary=fp.binary, params=params.vocabulary)
        self.index = InvertedIndex()
        self.memory = WorkingMemory(self.index, params.memory,
                                    protect_recent=params.recent_excluded + params.filter.neighbours,
                                    neighbours=params.filter.neighbours)
        # per image: its features (lent: their founding descriptors read from the word
        # search, :meth:`_keep`); None: out of memory, the loader's
        self._features: list[CompactFeatures | LentFeatures | None] = []
        # (t, 3) x_m, y_m, yaw_rad of each image (NaN: unknown) and their variances: views
        # of the first t rows of growing buffers (no copy of every pose per image)
        self._pose_buf = np.zeros((0, 3))
        self._var_buf = np.zeros((0, 3))
        self._poses = self._pose_buf
        self._poses_var = self._var_buf
        self._posterior = np.ones(1)
        self._hyp_ids = np.zeros(0, np.int64)
        self._run = 0                      # consecutive images with consistent candidates
        self._last_candidate: int | None = None

    def __len__(self) -> int:
        """Images processed."""
        return len(self._features)

    def features_of(self, image_id: int) -> CompactFeatures:
        """The stored features of a processed image (compact: word ids, keypoints in 1/16
        px, descriptors; they read like :class:`Features`); the word ids for the latest
        image only (empty for the others: the inverted index holds them). An image that
        lends descriptors to the word search (the latest too) is put together anew (equal
        at each call, not the same object). Those out of memory come from the
        :attr:`loader` (LookupError when it cannot give them)."""
        kept = self._features[image_id]
        if isinstance(kept, LentFeatures):
            lo, _ = self.vocabulary.image_words(image_id)
            kept = kept.with_descriptors(self.vocabulary.word_descriptors(lo + kept.lent_rank.astype(np.int64)))
        if kept is not None:
            if image_id == len(self._features) - 1 and len(self._latest_words):
                return replace(kept, words=self._latest_words.astype(np.uint32))
            return kept
        f = self._read_back.get(image_id)
        if f is not None:
            self._read_back.move_to_end(image_id)
            return f
        if self.loader is None:  # never: only a loader's images leave memory
            raise LookupError(f"forward image {image_id} is not in memory")
        f = without_words(self.loader(image_id))
        self.read_back += 1
        self._read_back[image_id] = f
        if len(self._read_back) > READ_BACK_KEPT:
            self._read_back.popitem(last=False)
        return f

    def _keep(self, image_id: int, f: CompactFeatures,
              made_at: np.ndarray | None = None) -> CompactFeatures | LentFeatures:
        """What stays in memory of image ``image_id``'s features ``f`` (with its word ids)
        once it is not the latest: no word ids (the inverted index holds them), and when
        the word search lends (:attr:`Vocabulary.lends`), not the descriptors that made
        words it still holds either: each word's descriptor is its founding keypoint's
        (the image's first keypoint with that word), so those are read back from it.
        ``made_at``: the founding keypoints in the order of the words they made
        (:attr:`Vocabulary.last_new_at` of the image's add), else found from the words."""
        voc = self.vocabulary
        if not voc.lends or not len(f.words):
            return without_words(f)
        if f.image_size_px != self._size:  # one tuple for all the images of a size (its ints are objects)
            self._size = f.image_size_px
        lo, hi = voc.image_words(image_id)
        if made_at is not None and len(made_at) == hi - lo:
            at, rank = made_at, np.arange(hi - lo, dtype=np.int64)
        else:
            w = f.words.astype(np.int64)
            pos = np.flatnonzero((w >= lo) & (w < hi))
            made, first = np.unique(w[pos], return_index=True)
            at, rank = pos[first], made - lo
        ok = voc.searchable(lo + rank)  # not purged meanwhile (a purge after a single image)
        return lend(f, at[ok], rank[ok], self._size)

    def _give_back(self, words: np.ndarray, descriptors: np.ndarray) -> None:
        """Words ``words`` left the word search with their ``descriptors``: the images in
        memory that lent them keep those descriptors again."""
        born = self.vocabulary.born(words)
        for t in np.unique(born).tolist():
            kept = self._features[t]
            if isinstance(kept, LentFeatures):
                mine = born == t
                lo, _ = self.vocabulary.image_words(t)
                self._features[t] = kept.give_back(words[mine] - lo, descriptors[mine])

    def mark_stored(self, image_id: int) -> None:
        """The :attr:`loader` can now give ``image_id``'s features: they may leave memory
        once ``resident`` newer images have come."""
        if self.loader is None:
            return
        self._in_store[image_id] = 1
        self._release(image_id)

    def _release(self, image_id: int) -> None:
        """Let ``image_id``'s features go when the loader has them and they are not recent."""
        if (self.loader is not None and 0 <= image_id < len(self._features) - self.resident
                and self._in_store[image_id]):
            self._features[image_id] = None

    def restore(self, images: list[CompactFeatures], word_descriptors: np.ndarray, word_born: np.ndarray,
                word_purged: np.ndarray, stored: bool = False) -> None:
        """Take up the memory of an earlier run: its images in order (as
        :meth:`features_of` gave them) and its words (descriptors, the image that made each,
        purged or not). The inverted index is rebuilt from the images' words; the filter
        starts at "no loop" as at any start; the earlier images are hypotheses at once.
        ``stored``: the :attr:`loader` gives every one of these images (they came from its
        map), and an image without keypoints here is one left there (only its words given)."""
        if stored and self.loader is None:
            raise ValueError("restore(stored=True) needs a loader")
        if len(self._features):
            raise ValueError("restore() needs a detector that has seen no image")
        n_words = len(word_descriptors)
        seen = np.zeros(n_words, np.int64)
        for t, f in enumerate(images):
            w = f.words.astype(np.int64)
            if len(w) and w.max() >= n_words:
                raise ValueError(f"stored image {t} has word {int(w.max())}, beyond the {n_words} stored words")
            seen[np.unique(w)] += 1
            self.memory.add(t, w, t)
            self._features.append(None if stored and not len(f) else without_words(f))
        self._in_store = bytearray((b"\x01" if stored else b"\x00") * len(images))
        for t in range(len(images) if stored else 0):
            self._release(t)
        self._pose_buf = np.full((len(self._features), 3), np.nan)  # no pose stored for them
        self._var_buf = np.full((len(self._features), 3), np.nan)
        self._poses, self._poses_var = self._pose_buf, self._var_buf
        self.vocabulary.restore(word_descriptors, word_born, word_purged, seen, len(images))
        if self.vocabulary.lends:
            for t, f in enumerate(images):
                if self._features[t] is not None and len(f.words):
                    self._features[t] = self._keep(t, self._founders_as_stored(t, f, word_descriptors))
        if not self.params.memory.bounded:
            self.index.drop_postings(np.flatnonzero(np.asarray(word_purged, bool)))

    @staticmethod
    def _founders_as_stored(t: int, f: CompactFeatures, word_descriptors: np.ndarray) -> CompactFeatures:
        """``f`` with the word ids of keypoints whose descriptor is not their word's
        descriptor as stored set apart (-1, so :meth:`_keep` lends nothing it could not
        give back as it was); ``f`` itself when all agree."""
        w = f.words.astype(np.int64)
        d = np.asarray(f.descriptors)
        if d.dtype != np.uint8 or d.ndim != 2 or d.shape[1] != word_descriptors.shape[1]:
            return replace(f, words=np.full(len(w), -1, np.int64))
        differ = np.any(d != np.asarray(word_descriptors)[w], axis=1)
        if not differ.any():
            return f
        return replace(f, words=np.where(differ, -1, w))

    def _append_pose(self, pose: np.ndarray, var: np.ndarray) -> None:
        """The next image's pose and variances ``(3,)`` each (NaN: unknown)."""
        n = len(self._poses)
        if n == len(self._pose_buf):  # a thirty-second and one row more (48 bytes a row: no 16-row first block)
            cap = n + n // 32 + 1
            self._pose_buf = np.concatenate([self._pose_buf, np.full((cap - n, 3), np.nan)])
            self._var_buf = np.concatenate([self._var_buf, np.full((cap - n, 3), np.nan)])
        self._pose_buf[n] = pose
        self._var_buf[n] = var
        self._poses, self._poses_var = self._pose_buf[:n + 1], self._var_buf[:n + 1]

    def forget_poses(self) -> None:
        """Odometry lost its continuity (the robot was carried, a kidnapping): the poses of
        the images so far are not comparable with the ones to come, so they count as
        unknown for :class:`OdometryParams` (appearance alone decides about them)."""
        self._poses[:] = np.nan
        self._poses_var[:] = np.nan

    def _verify(self, candidate: int, feats: Features, hyp_ids: np.ndarray,
                odo: np.ndarray | None, t: int, defer_accept: bool = False, max_checks: int | None = None
                ) -> tuple[PendingVerification, tuple[int, Verification, bool] | PendingVerification]:
        """Verify ``candidate`` and, if it fails, its most probable neighbours that odometry
        agrees with (within ``filter.neighbours`` images; up to ``verify_tries`` images in
        all; ``odo``: the hypotheses' odometry factors, None without odometry): ``(image,
        its verification, whether it is a loop)``: the first accepted (and passing
        :attr:`accept`), else the candidate's (``accepted`` True there when only
        :attr:`accept` refused it), after the job that ran them (its ``checks``). With ``defer_accept`` (and an :attr:`accept` test) the
        first view whose check passes is not put to the test: the rest of the verification
        is returned instead (:class:`PendingVerification`, finished by :meth:`resume`); so is
        the rest when ``max_checks`` epipolar checks ran and views are left (None: no bound)."""
        p = self.params
        order = [candidate]
        o = p.odometry
        if p.verify_tries > 1 and o.verify_place:
            # The candidate's place: the hypotheses whose pose agrees with the candidate's
            # (other laps' views of the same spot), most probable first.
            post = self._posterior[1:]
            if len(post) == len(hyp_ids) and np.isfinite(self._poses[candidate]).all():
                place = np.array([o.place_sigma_m ** 2] * 2 + [o.place_sigma_yaw_rad ** 2])
                agree = pose_agreement(self._poses[hyp_ids], self._poses_var[hyp_ids],
                                       int(np.searchsorted(hyp_ids, candidate)), place, o.variance_scale)
                near = np.flatnonzero((agree >= o.agree_factor) & (hyp_ids != candidate) & (post > 0.0))
                order += hyp_ids[near[np.argsort(-post[near], kind="stable")]][:p.verify_tries - 1].tolist()
        elif p.verify_tries > 1 and odo is not None:
            # The candidate's neighbours (the same place) that odometry agrees with, most
            # probable first; never without odometry (on the office route, appearance alone
            # let false positives through this way).
            post = self._posterior[1:]
            near = np.flatnonzero((np.abs(hyp_ids - candidate) <= p.filter.neighbours) & (hyp_ids != candidate)
                                  & (post > 0.0) & (odo >= p.odometry.agree_factor))
            order += hyp_ids[near[np.argsort(-post[near], kind="stable")]][:p.verify_tries - 1].tolist()
        agreed = frozenset(int(h) for h, f in zip(hyp_ids.tolist(), odo.tolist()) if f >= o.agree_factor) \
            if odo is not None else frozenset()
        job = PendingVerification(t, int(candidate), feats, [int(j) for j in order], agreed)
        return job, self._advance(job, defer_accept, max_checks)

    def _advance(self, job: PendingVerification, defer_accept: bool, max_checks: int | None = None
                 ) -> tuple[int, Verification, bool] | PendingVerification:
        """Go on with ``job``: the awaiting view's :attr:`accept` test, then the views not yet
        verified and, with :attr:`DetectorParams.fallbacks_last`, the fallbacks due after them
        (at most ``max_checks`` epipolar checks, None: all), as :meth:`_verify` describes."""
        p = self.params
        o = p.odometry
        if job.view is not None and job.verification is not None:
            j, v = job.view, job.verification
            job.view, job.verification = None, None
            if self.accept is None or self.accept(j, v):
                return j, v, True
        checks = 0
        while job.next < len(job.order) or job.due:
            if max_checks is not None and checks >= max_checks:
                return job  # the budget spent: the views from job.next on (and the fallbacks due) are left
            room = p.verify_fallbacks is None or job.fallbacks < p.verify_fallbacks
            if job.next >= len(job.order):  # every view checked near its level motion: the fallbacks due
                if not room:
                    job.due.clear()  # the bound on the image's work
                    break
                at, j, due = job.due.pop(0)
                v = fallback_verification(due)
                job.failed[at] = v
            else:
                j = job.order[job.next]
                job.next += 1
                vp = p.verify
                if not room:
                    vp = replace(vp, fallback_inliers=None)  # the bound on the image's work
                elif p.fallbacks_last:
                    vp = replace(vp, defer_fallback=True)
                if j in job.agreed:
                    if o.agree_min_inliers is not None:
                        vp = replace(vp, min_inliers=o.agree_min_inliers)
                    if o.agree_min_support_area is not None:
                        vp = replace(vp, min_support_area=o.agree_min_support_area)
                try:
                    old = self.features_of(j)
                except LookupError:
                    self.read_back_failed += 1
                    continue
                v = verify_pair(old, job.feats, vp, self.camera_matrix)
                if isinstance(v, DueFallback):
                    job.due.append((len(job.failed), j, v))
                    v = v.checked()
                job.failed.append(v)
            checks += 1
            job.checks += 1
            job.fallbacks += v.fallback
            if v.accepted:
                if self.accept is None:
                    return j, v, True
                if defer_accept:
                    job.view, job.verification = j, v
                    return job
                if self.accept(j, v):
                    return j, v, True
        if not job.failed:  # not one of them could be read back (counted): as if nothing matched
            return job.candidate, Verification(False, TOO_FEW_MATCHES, 0, 0), False
        return job.candidate, job.failed[0], False

    def resume(self, job: PendingVerification, max_checks: int | None = None, defer_accept: bool = False
               ) -> tuple[DetectionStatus, int, Verification] | PendingVerification:
        """Go on with a verification left with ``ACCEPT_PENDING`` or ``VERIFY_PENDING``
        (:class:`PendingVerification`): the awaiting view's :attr:`accept` test, and, when it
        fails (or none awaits), the views after it as :meth:`process_features` would have
        tried them. Returns ``(LOOP, the loop's past image, its verification)`` or
        ``(NO_GEOMETRIC_CONSISTENCY, the candidate, the check kept for it)``; with a bounded
        working memory the loop's places are linked now. :attr:`accept` runs for image
        ``job.image_id``, which may no longer be the newest. ``max_checks``: at most this
        many epipolar checks in this call (None: no bound); ``defer_accept``: a view whose
        check passes is left awaiting its test. Either stops the call with ``job`` itself
        returned, to be resumed again (the same answers as one call: the views, their order
        and the tests are the job's, whatever ran between)."""
        if job.finished:
            raise ValueError("resume: this verification has no view awaiting its accept test and none left to check")
        out = self._advance(job, defer_accept, max_checks)
        if isinstance(out, PendingVerification):
            return out
        j, v, ok = out
        if ok and self.params.memory.bounded:
            self.memory.link(job.image_id, int(j))
        return (LOOP if ok else NO_GEOMETRIC_CONSISTENCY), int(j), v

    def memory_bytes(self) -> dict[str, int]:
        """Bytes the detector holds, by part: ``images`` (word ids, keypoints, descriptors
        of every past image in memory, those read back lately included, and the per-image
        list, flags, poses, posterior and hypothesis ids), ``index`` (the inverted index and the working memory's
        per-place state), ``vocabulary`` (the word search, as usearch reports it, reserved
        capacity included)."""
        kept = [f for f in self._features if f is not None] + list(self._read_back.values())
        return {"images": sum(_held_bytes(f) for f in kept) + self._bookkeeping_bytes(),
                "index": self.index.memory_bytes() + self.memory.memory_bytes(),
                "vocabulary": self.vocabulary.memory_bytes()}

    def _bookkeeping_bytes(self) -> int:
        """Bytes of the per-image list, flags, poses, posterior, hypothesis ids and the latest image's word ids."""
        return (sys.getsizeof(self._features) + len(self._in_store) + self._pose_buf.nbytes + self._var_buf.nbytes
                + self._posterior.nbytes + self._hyp_ids.nbytes + self._latest_words.nbytes)

    def process(self, image: np.ndarray, pose: np.ndarray | None = None,
                pose_cov: np.ndarray | None = None, defer_accept: bool = False,
                max_checks: int | None = None) -> Detection:
        """Run one image (``(H, W)`` gray or ``(H, W, 3)`` BGR uint8) through the detector;
        ``pose``, ``pose_cov``, ``defer_accept``, ``max_checks``: see :meth:`process_features`."""
        t0 = self._timer()
        feats = self._extract(image)
        return self.process_features(feats, self._timer() - t0, pose, pose_cov, defer_accept, max_checks)

    def process_features(self, feats: Features, features_s: float = 0.0, pose: np.ndarray | None = None,
                         pose_cov: np.ndarray | None = None, defer_accept: bool = False,
                         max_checks: int | None = None) -> Detection:
        """Run one image given its already extracted features (``features_s``: the time
        that took, for the record). ``pose (3,)``: the robot's odometry pose when the image
        was taken (x_m, y_m, yaw_rad; the fused odometry the daemon has, never a ground
        truth), ``pose_cov (3, 3)`` its covariance; used by :class:`OdometryParams`, kept
        with the image either way (None: unknown). ``defer_accept``: a view whose epipolar
        check passes is not put to the :attr:`accept` test here; the image's status is then
        ``ACCEPT_PENDING`` and :meth:`resume` finishes its verification (the caller chooses
        when: the daemon's stage spreads the test over its keyframes). ``max_checks``: at
        most this many epipolar checks for the image here (None: every view it tries); with
        views left the status is ``VERIFY_PENDING`` and :meth:`resume` goes on with them."""
        p = self.params
        clock = self._timer
        t = len(self._features)
        times = {"features": features_s}

        t0 = clock()
        words, new_words = self.vocabulary.add(feats.descriptors)
        made_at = self.vocabulary.take_new_at()  # this image's founding keypoints (kept by the image it lends)
        gone = self.vocabulary.last_purged
        if len(gone) and not p.memory.bounded:
            self.index.drop_postings(gone)  # no query can find them
        if len(gone) and self.vocabulary.lends:
            self._give_back(gone, self.vocabulary.last_purged_descriptors)
        t1 = clock()
        times["words"] = t1 - t0

        bounded = p.memory.bounded
        scores, virtual = self.index.vote(words)
        if not bounded:  # the paper's detector: slots are images 0 .. t - 1
            n_hyp = max(0, t - p.recent_excluded + 1)
            hyp_ids = np.arange(n_hyp, dtype=np.int64)
            hyp_scores = np.concatenate([[virtual], scores[:n_hyp]])
        else:
            slot_ids = self.index.image_ids
            live = slot_ids >= 0
            scores_t = np.zeros(t, np.float64)
            scores_t[slot_ids[live]] = scores[live]
            scores = scores_t
            wm = self.memory.ids()
            hyp_ids = wm[wm <= t - p.recent_excluded]
            hyp_scores = np.concatenate([[virtual], scores[hyp_ids]])
        n_hyp = len(hyp_ids)
        like = adjust_likelihood(hyp_scores, p.likelihood)
        pose_now, var_now = _pose_row(pose, pose_cov)
        odo = None
        if p.odometry.use and n_hyp and np.isfinite(pose_now).all():
            odo = odometry_factor(pose_now, var_now, self._poses[hyp_ids], self._poses_var[hyp_ids], p.odometry)
            like[1:] *= odo
        t2 = clock()
        times["likelihood"] = t2 - t1

        best = None
        if p.decision == "score":  # no filter: the posterior shown is the normalised likelihood
            candidate, prob = _best_normalised(scores, n_hyp, virtual, t, p, odo)
            self._posterior = like / like.sum()
        elif not bounded:
            if p.odometry.metric_neighbours and np.isfinite(pose_now).all():
                prior = predict_metric(self._posterior, n_hyp, self._poses, self._poses_var, p)
            else:
                prior = predict(self._posterior, n_hyp, p.filter)
            self._posterior = update(prior, like)
            if p.odometry.merge_places and np.isfinite(pose_now).all():
                candidate, prob = _merged_candidate(self._posterior, hyp_ids, self._poses, self._poses_var, p)
            else:
                candidate, prob = select_candidate(self._posterior, p.filter)
        else:
            prior = predict_ids(self._posterior, self._hyp_ids, hyp_ids, p.filter)
            self._posterior = update(prior, like)
            candidate, prob, best = select_candidate_ids(self._posterior, hyp_ids, p.filter)
        self._hyp_ids = hyp_ids
        t3 = clock()
        times["filter"] = t3 - t2

        # I_t joins the inverted index after its own vote (its words are part of Z_t+1);
        # that bookkeeping counts as word search.
        # The image lends its founding descriptors at once (the word search holds them from
        # now on); its word ids stay beside it until the next image (features_of gives them),
        # then live on in the index (and a map file) only.
        self.memory.add(t, words, t)
        latest = compact(feats, words)
        self._features.append(self._keep(t, latest, made_at))
        w = latest.words  # uint16 while the word ids fit (the first 65,536 words)
        self._latest_words = w.astype(np.uint16) if len(w) and int(w.max()) <= 0xFFFF else w
        self._in_store.append(0)
        if t:
            self._release(t - self.resident)
        self._append_pose(pose_now, var_now)
        t3b = clock()
        times["words"] += t3b - t3
        t3 = t3b

        if candidate is None:
            self._run, self._last_candidate = 0, None
        else:
            near = (self._last_candidate is not None
                    and abs(int(candidate) - self._last_candidate) <= p.consistency_gap)
            self._run = self._run + 1 if near else 1
            self._last_candidate = int(candidate)
        verification = None
        pending = None
        checks = 0
        if n_hyp == 0:
            status = NO_HYPOTHESES
        elif candidate is None:
            status = LOW_POSTERIOR
        elif self._run < p.consistency:
            status = NOT_CONSISTENT_YET
        else:
            job, out = self._verify(candidate, feats, hyp_ids, odo, t, defer_accept, max_checks)
            checks = job.checks
            if isinstance(out, PendingVerification):
                pending, verification = out, out.verification
                status = ACCEPT_PENDING if out.view is not None else VERIFY_PENDING
            else:
                candidate, verification, ok = out
                status = LOOP if ok else NO_GEOMETRIC_CONSISTENCY
        t4 = clock()
        times["verify"] = t4 - t3

        retrieved: list[int] = []
        transferred: list[int] = []
        if bounded:
            if status == LOOP and candidate is not None:  # a loop always has its candidate
                self.memory.link(t, int(candidate))
            if best is not None and prob >= p.memory.retrieve_threshold:
                k = p.filter.neighbours
                self.memory.touch(hyp_ids[np.abs(hyp_ids - best) <= k], t)
                retrieved = self.memory.retrieve_around(best, t)
            over = 0.0
            if p.memory.time_budget_s is not None:
                over = (times["likelihood"] + times["filter"]) / p.memory.time_budget_s
            transferred = self.memory.enforce_bound(t, over)
        t5 = clock()
        times["memory"] = t5 - t4
        times["total"] = features_s + (t5 - t0)
        return Detection(
            image_id=t, status=status, loop_id=candidate if status == LOOP else None,
            candidate_id=candidate, candidate_probability=prob, scores=scores,
            virtual_score=virtual, likelihood=like, posterior=self._posterior.copy(),
            verification=verification, n_features=len(feats), new_words=new_words,
            vocabulary_size=len(self.vocabulary), times_s=times, hypothesis_ids=hyp_ids,
            working_memory=len(self.memory), retrieved=tuple(retrieved),
            transferred=tuple(transferred), pending=pending, checks=checks)


def _held_bytes(f: CompactFeatures | LentFeatures) -> int:
    """Bytes an image's features hold in memory: a lent record with its object and its
    buffer's header (Python's own figures: one per image, about 180 bytes), else the arrays."""
    if isinstance(f, LentFeatures):
        return sys.getsizeof(f) + sys.getsizeof(f.data)
    return f.nbytes


def _pose_row(pose: np.ndarray | None, pose_cov: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(3,)`` pose and ``(3,)`` variances (NaN when unknown) of one image."""
    if pose is None:
        return np.full(3, np.nan), np.full(3, np.nan)
    xy = np.asarray(pose, np.float64).reshape(3)
    var = np.zeros(3) if pose_cov is None else np.diag(np.asarray(pose_cov, np.float64).reshape(3, 3)).copy()
    return xy, var


def _merged_candidate(posterior: np.ndarray, hyp_ids: np.ndarray, poses: np.ndarray, poses_var: np.ndarray,
                      p: DetectorParams, top: int = 16) -> tuple[int | None, float]:
    """The candidate among places merged by metric pose (:attr:`OdometryParams.merge_places`):
    ``(image or None, probability)`` from ``posterior (1 + n,)`` over the hypotheses
    ``hyp_ids (n,)``, with every image's ``poses (t, 3)`` and ``poses_var (t, 3)``. Only the
    ``top`` most probable images found places (the rest hold too little mass to win)."""
    img = np.asarray(posterior, np.float64)[1:]
    if not len(img):
        return None, 0.0
    o = p.odometry
    seeds = np.argsort(-img, kind="stable")[:top]
    seeds = seeds[img[seeds] > 0.0]
    if not len(seeds):
        return None, 0.0
    hp, hv = poses[hyp_ids], poses_var[hyp_ids]
    place = np.array([o.place_sigma_m ** 2] * 2 + [o.place_sigma_yaw_rad ** 2])
    best_sum, best_img = -1.0, int(seeds[0])
    for s_ in seeds.tolist():
        d = hp - hp[s_][None, :]
        d[:, 2] = (d[:, 2] + np.pi) % (2.0 * np.pi) - np.pi
        d2 = (d * d / (o.variance_scale * np.abs(hv - hv[s_][None, :]) + place[None, :])).sum(axis=1)
        same = np.isfinite(d2) & (np.exp(-0.5 * np.where(np.isfinite(d2), d2, np.inf)) >= o.agree_factor)
        same |= np.abs(hyp_ids - hyp_ids[s_]) <= p.filter.neighbours
        total = float(img[same].sum())
        if total > best_sum:
            members = np.flatnonzero(same)
            best_sum, best_img = total, int(members[np.argmax(img[members])])
    prob = best_sum if p.filter.rule == "neighbourhood" else 1.0 - float(posterior[0])
    if prob <= p.filter.loop_threshold:
        return None, prob
    return int(hyp_ids[best_img]), prob


def _best_normalised(scores: np.ndarray, n_hyp: int, virtual: float, t: int,
                     p: DetectorParams, weights: np.ndarray | None = None) -> tuple[int | None, float]:
    """The score decision (:attr:`DetectorParams.decision`): ``(candidate or None,
    normalised score)`` over the hypotheses 0 .. n_hyp - 1 (their scores multiplied by
    ``weights (n_hyp,)``, the odometry factors, when given)."""
    if n_hyp == 0:
        return None, 0.0
    s = scores[:n_hyp] if weights is None else scores[:n_hyp] * weights
    best = int(np.argmax(s))
    if not s[best] > 0.0:
        return None, 0.0
    ref = virtual if p.score_normalisation == "virtual" else (float(scores[t - 1]) if t >= 1 else 0.0)
    if p.islands:
        return _best_island(s, ref, p)
    ratio = float(s[best] / ref) if ref > 0.0 else float("inf")
    return (best if ratio > p.score_threshold else None), ratio


def _best_island(s: np.ndarray, ref: float, p: DetectorParams) -> tuple[int | None, float]:
    """DLoopDetector's islands (:attr:`DetectorParams.islands`) over the scores ``s (n,)``
    normalised by ``ref``: ``(best image of the best island or None, the island's summed
    normalised score)``."""
    ns = s / ref if ref > 0.0 else np.where(s > 0.0, np.inf, 0.0)
    above = np.flatnonzero(ns > p.score_threshold)
    if not len(above):
        return None, float(ns.max())
    starts = np.concatenate([[0], np.flatnonzero(np.diff(above) > max(1, p.consistency_gap)) + 1])
    sums = np.add.reduceat(ns[above], starts)
    k = int(np.argmax(sums))
    members = above[starts[k]:(starts[k + 1] if k + 1 < len(starts) else len(above))]
    return int(members[np.argmax(ns[members])]), float(sums[k])


def method_params(method: str, **overrides: Unpack[DetectorOverrides]) -> DetectorParams:
    """The detector a method name selects (``[forward_detector] method``,
    ``robotd eval forward --method``), with ``overrides`` replacing fields of the result.

    - ``"paper"``: paper 000 as written: SIFT, the paper's likelihood, the 0.8 threshold on
      one neighbourhood's posterior, every candidate verified (the reference).
    - ``"default"``: binary ORB features (OpenCV) in an incremental Hamming vocabulary whose
      words that never recur are purged, and the levers that the ablation of
      ``bench/bench_forward_ablation.py`` kept (``docs/forward.md``): the total loop
      probability above 0.3, every candidate verified (k = 1; k = 2 and 0.5 each lost
      recall on both development sequences), and the keyframe's odometry pose, when one
      is given, as a second likelihood (``OdometryParams(use=True)``) with no support test
      for a candidate it agrees with (``agree_min_support_area = 0``) and, when the
      candidate fails, up to two of its time neighbours that odometry agrees with verified
      (``verify_tries = 3``): with the daemon's fused pose (wheel + gyro + floor visual
      odometry) on the office route they raised recall at 100 % precision from 0.534 to
      0.818 with no false positive; without a pose (the real corridor, ``robotd eval
      forward`` without ``--odometry``) the detector is the one without odometry. The
      other metric levers (:class:`OdometryParams`) stay selectable. Its verification
      searches a level camera's motion first (``VerifyParams(model="planar")``; the
      paper's general search stays selectable as ``model="general"``), with its work per
      image bounded by rule (:func:`bounded_verification`: the essential matrix near the
      level motion searched by OpenCV's USAC, the general search after a failed one in a
      10 px band around the level motion and for one view per image, once every view was checked near
      its level motion: ``fallbacks_last``); the verification
      without the bound stays selectable (:func:`unbounded_verification`). Measured
      (``docs/forward.md``, "Time and memory per image"): with the bound the p99 per image
      is within 40 ms of CPU in the bench (the office route's median is not shown within
      15 ms), and the recall targets on both development sequences and the forward demo's
      targets on its seeds 0-4 hold.
    """
    from robotd.forward.features import FeatureParams
    from robotd.forward.filter import FilterParams
    from robotd.forward.vocabulary import VocabularyParams

    if method == "paper":
        params = DetectorParams()
    elif method == "default":
        params = DetectorParams(features=FeatureParams(kind="orb", max_features=DEFAULT_ORB_FEATURES),
                                vocabulary=VocabularyParams(purge_after=DEFAULT_PURGE_AFTER),
                                filter=FilterParams(rule=DEFAULT_RULE, loop_threshold=DEFAULT_THRESHOLD),
                                consistency=DEFAULT_CONSISTENCY, verify_tries=DEFAULT_VERIFY_TRIES,
                                odometry=OdometryParams(use=True, agree_min_support_area=0.0),
                                verify=VerifyParams(model=DEFAULT_VERIFY_MODEL, guided_estimator=DEFAULT_GUIDED_ESTIMATOR,
                                                    fallback_band_px=DEFAULT_FALLBACK_BAND_PX,
                                                    fallback_screen=DEFAULT_FALLBACK_SCREEN),
                                verify_fallbacks=DEFAULT_VERIFY_FALLBACKS, fallbacks_last=DEFAULT_FALLBACKS_LAST)
    else:
        raise ValueError(f"forward detector method must be one of {', '.join(METHODS)}, got {method!r}")
    return replace(params, **overrides) if overrides else params


def daemon_params(params: DetectorParams) -> DetectorParams:
    """The daemon's forward detector (``robotd run``, ``robotd demo --forward``): ``params``
    (the ``"default"`` method's) with the levers that rest on what only the daemon has
    behind the detector. The keyframe's pose from the fused odometry (wheels, gyro, visual
    odometry) is a second likelihood (:class:`OdometryParams`); a candidate it agrees with
    is verified without the support test (odometry and appearance agreeing replace it; the
    default method has both since the ablation with the fused pose) and, when it fails,
    up to two of its neighbours that odometry also agrees with are tried;
    every consistent candidate is verified (k = 1); the total loop probability above 0.5
    (the daemon's forward loops were measured with it, ``docs/forward.md``; the bench's
    0.3 was not run in the daemon). Behind the detector a loop must still
    be a level camera's motion (:mod:`robotd.app.stages.forward_loops`) and pass the pose
    graph's gate against the graph's prediction. The office route's ablation with the
    fused pose (no gate) is in ``docs/forward.md``."""
    return replace(params, odometry=replace(params.odometry, use=True, agree_min_support_area=0.0),
                   verify_tries=max(params.verify_tries, 3), consistency=1,
                   filter=replace(params.filter, loop_threshold=0.5))


#: The default detector's settings, chosen by the ablation (docs/forward.md): each lever was
#: kept only when it helped on both development sequences (rtabmap_samples and the virtual
#: office route), never on one alone.
DEFAULT_ORB_FEATURES = 300
DEFAULT_PURGE_AFTER = 50
DEFAULT_RULE = "total"
DEFAULT_THRESHOLD = 0.3
DEFAULT_CONSISTENCY = 1
DEFAULT_VERIFY_TRIES = 3
DEFAULT_VERIFY_MODEL = "planar"
DEFAULT_GUIDED_ESTIMATOR = "usac"
DEFAULT_FALLBACK_BAND_PX = 10.0
#: No screen before the band fallback's RANSAC: USAC's (``VerifyParams.fallback_screen``)
#: refuses fallbacks RANSAC accepts on both development sequences
#: (docs/forward.md, "Tried and not taken").
DEFAULT_FALLBACK_SCREEN: str | None = None
DEFAULT_VERIFY_FALLBACKS = 1
#: An image's fallbacks after every view's check near its level motion (docs/forward.md,
#: "The verification"): a later view that passes near its level motion is found without
#: the fallback of an earlier one.
DEFAULT_FALLBACKS_LAST = True


def bounded_verification(params: DetectorParams) -> DetectorParams:
    """``params`` with the planar verification's work per image bounded by rule (the
    ``"default"`` method's): the essential matrix near the level motion searched by
    OpenCV's USAC, the general search after a failed one drawing its samples within 10 px
    of the level motion, and run for one view per image at most, after every view's check near
    its level motion (``docs/forward.md``, "Time and memory per image", "The verification")."""
    return replace(params, verify=replace(params.verify, guided_estimator="usac", fallback_band_px=10.0),
                   verify_fallbacks=1, fallbacks_last=True)


def unbounded_verification(params: DetectorParams) -> DetectorParams:
    """``params`` with the planar verification's work per image not bounded (the default
    before the bound): RANSAC near the level motion, the general search over all the
    matches after a failed one, for every view that fails, right after its check."""
    return replace(params, verify=replace(params.verify, guided_estimator=None, fallback_band_px=None),
                   verify_fallbacks=None, fallbacks_last=False)
