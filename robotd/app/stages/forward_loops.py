"""The forward camera's loop detector as a pipeline stage (paper 000).

Forward frames are buffered; when a floor keyframe is stored and the robot has moved
``distance_m`` or turned ``rotation_rad`` since the last forward keyframe, the buffered
forward frame nearest the keyframe's stamp (within ``sync_tolerance_s``) becomes a forward
keyframe under the floor keyframe's id: the pose graph's vertices stay the floor keyframes,
and a forward loop is an edge between two of them. The image runs through
:class:`robotd.forward.ForwardDetector` (incremental vocabulary, Bayes filter, epipolar
verification); a verified loop whose motion is planar is published as a
:class:`~robotd.base.messages.ForwardLoop`, which the pose graph gates and adds
(:mod:`robotd.app.stages.pose_graph`).

With a map store the forward memory is durable: each forward image is
written to the map (its word ids, compact keypoints and descriptors, the words it made and
the words purged after it) in one transaction, and a new stage on the same map takes up
the earlier runs' memory, so the detector goes on finding loops against them after a
restart. A write that fails is logged and counted (``forward_store_errors``); detection
goes on.

A loop is published only when its motion is a level camera's: the out-of-plane part of the
refined two-view motion must be within its own covariance, the inliers' noise scaled by the
measured factor :data:`robotd.forward.planar.INLIER_NOISE_FACTOR`
(:func:`robotd.forward.planar.planarity_bound`), and under ``max_tilt_rad``. At short
baselines the five-point motion sometimes comes out with its bearing 10-130 deg wrong and
the heading about right; it then leans out of the floor plane by more than the inliers
allow, though often by less than a fixed tilt limit (the daemon's wrong forward loops were
of this kind; rendered at the frames' own times, so not the frame's offset from its
keyframe). Such a motion is refitted with the motion kept in the floor plane
(:func:`robotd.forward.planefit.fit_planar`, heading change and bearing only) from the two
images' matches, its heading scanned around both the verified motion's heading and the
heading of the level motion the verification's search found first, the fit with more
inliers kept (``scan_centre="both"``, the default: a five-point motion found near the
level motion can be tens of degrees off the truth, beyond the scan's +-8 deg, while the
level motion is near it; on the office route's five seeds this accepted no fewer loops on
any seed than the verified heading's scan, 4 more in all, none wrong); ``"verified"`` (the
rule before) or ``"level"`` scan around one of them; the refit is the loop's motion when it
keeps at least the verification's ``min_inliers`` and half of its inliers.

A motion that passes the test is fitted in the floor plane too, and the planar fit is the
loop's motion when it explains more of the two images' matches than the verified motion
brought into the plane (its heading change and bearing,
:func:`robotd.forward.planefit.planar_inliers`), under the same conditions. For a camera
moving along its optical axis the general fit trades a heading change against a bearing
and a little tilt: loops 0.3-0.65 m apart came out with the bearing 10-13 deg off and the
heading 1.3-2.7 deg, leaning 2-7 deg (inside the planarity test), while the true planar
motion fitted their inliers to 0.5-0.7 px and the verified one, brought into the plane, to
9-26 px. The test runs inside the detector's verification
(its ``accept`` hook), so a candidate refused there lets the detector verify the next view
it may try (``DetectorParams.verify_tries``). Refusals are counted (``forward_not_planar``,
one per refused view) and, when no view was a loop, published as a ``failed_gate`` fate
(``forward: motion ... out of the floor plane``); refits are counted
(``forward_planar_refits``).

The detector runs in the pipeline's thread, once per forward keyframe (every half metre by
default, about one image per 1.5 s at the demo's speed): a SIFT image costs tens of
milliseconds, which the source queues absorb.

**One verification's work per forward keyframe** (``defer_accept``, on by default). The
costliest forward keyframes were those that verified a loop on a heading-bearing ridge: the
detector's features, words and epipolar check, and then, inside the same call, the level
test below (the planar scan, the ridge's fixed-heading fits, the heading graph's solve).
Most forward keyframes verify nothing. So the detector stops an image at its first view
whose epipolar check passes (:meth:`robotd.forward.ForwardDetector.process` with
``defer_accept``) and the level test of that view waits in a queue for the next forward
keyframe that verifies nothing (no epipolar check of its own), which finishes the oldest
waiting image's verification after its own detector call (:meth:`~robotd.forward.ForwardDetector.resume`:
the test and, when refused, the views after it, as the detector would have tried them).
Every piece of the test reads the waiting image's own context (its frame's offset, pose,
keyframe and the heading graph's links when it was stored), and nothing the detector does
for the images between depends on a verification's outcome, so the loop is the one the test
at once would have found; it is published with the keyframe that ran its test (one or more
forward keyframes later: the gate sees it that much later). The work is counted on the
keyframe that does it: its CPU per forward keyframe includes the finished verification
(part ``deferred``). At most ``max_deferred`` images wait; a verifying image that finds the
queue full is tested in its own keyframe (``forward_deferred_inline``); those still waiting
at the end of the input are finished then, their CPU the last forward keyframe's
(``forward_deferred_at_end``); ``forward_deferred_wait_max``: the most forward keyframes
one waited. A view of another odometry chain than the image's (across a kidnapping or a
restart: the loop may relocalise the robot) never waits: its test runs in its own keyframe
(``forward_deferred_across``), so the deferral does not delay a relocalisation.

**A budget of checks** (``check_budget``, ``[forward_detector] checks_per_keyframe``). The
queue of level tests alone left the costliest keyframes to the images verified in their own
keyframe: on the office route's revisits every forward keyframe verifies, the queue fills,
and an image that finds it full runs its views' epipolar checks (several views, each an
essential matrix, a homography and a pose) and its test in its own keyframe. With a budget
the image's verification itself is split: each forward keyframe runs at most
``check_budget`` epipolar checks (a view's check near its level motion and, with the detector's
``fallbacks_last``, its fallback run after the image's other views one each), a level test counting
:data:`TEST_CHECKS`, on the waiting
verifications first, the oldest first, and on its own image's only when none waits
(:meth:`robotd.forward.ForwardDetector.process` ``max_checks``, then
:meth:`~robotd.forward.ForwardDetector.resume` with the budget left, call after call); what
the budget leaves waits for the next forward keyframes. The count is of checks, not of
time, so the same input gives the same schedule and the same loops whatever the load: each
piece of the verification reads its image's own job (its features, its views in order, the
checks so far) and context, never the images run since. At most ``max_deferred`` images
wait after a keyframe; more finish the oldest at once, over the budget
(``forward_deferred_forced``); those still waiting at the end of the input run then; a
verification with a view of another odometry chain runs whole in its own keyframe
(``forward_deferred_across``). ``forward_checks_max`` is the most checks (tests included) one
forward keyframe ran, ``forward_checks_over_budget`` the keyframes over the budget
(forced or across).

The forward frame is up to ``sync_tolerance_s`` off its keyframe's stamp (33 ms at the
demo's 15 frames a second: 1 cm and 1 deg at its speeds), while the loop is an edge
between the two keyframes. The stage keeps the last seconds of the wheel odometry
(:class:`~robotd.base.messages.OdometryUpdate`, the wheel-only pose: no visual step moves it)
and takes the robot's motion from each keyframe's stamp to its frame's (interpolated, or
extrapolated at the last speed for a frame newer than the odometry; none without odometry).
A loop's motion, measured between the two frames, is carried to the two keyframes through
these offsets before it is published: the heading change exactly, the bearing at the
measured range on the floor or else at the range the keyframes' poses predict (same
odometry chain); with neither, the bearing is left as measured. Images taken up from the
map by a later run have no offset (zero).

For a camera moving along its optical axis towards a far wall, a small turn and a small
sideways shift move the points alike: the planar motion keeps nearly as many matches at
every heading change over a few degrees, its bearing moving 4-10 deg per degree of heading,
and the fit's best count picks a place on that ridge by the inliers' noise (the daemon's
last wrong forward loops: the heading 1.4 deg and the bearing 12-15 deg off, 0.2-0.3 m
apart). The images cannot settle such a loop; the pose graph knows the two keyframes'
relative heading far better than the edge's heading sigma (its floor loops tie them). So
when the headings whose count in the planar fit's inlier profile (:attr:`robotd.forward.planefit.PlanarFit.scan_inliers`)
stays within one counting sigma (``sqrt`` of the best count) of its best span a half-width
wider than the edge's heading sigma (:class:`RidgeParams`, :func:`ridge_headings`: every such
heading, not only the contiguous run around the best; over the 171 verified loops of five
demo runs the truth lay within one counting sigma of the best in 134 of the 161 right ones,
inside the run around the best in 122),
the stage takes the relative heading the graph predicts (:class:`HeadingGraph`: the yaw
part of the odometry and floor loop :class:`~robotd.base.messages.Link` messages, solved
exactly; the odometry's poses where the graph has not linked the two) and, if it lies on
the ridge (within three of its sigmas of one of its headings), publishes the ridge's motion at that heading (the
planar fit with the heading held, :func:`robotd.forward.planefit.fit_planar` ``fix_yaw``),
its bearing's sigma the fixed-heading fit's and the graph heading's sigma times the ridge's
slope; off the ridge, the view is refused (``forward_ridge_refused``, a log line) and the
detector may verify the next. Without any prior heading the loop keeps its motion, its
bearing's sigma spans the ridge and its heading's sigma takes the ridge's half-width beside
the edge's (``ForwardLoop.sigma_yaw_rad``, ``forward_ridge_unsettled``): such a loop is a
relocalisation candidate, never an edge the gate takes (:mod:`robotd.graph.gate`).

Across a kidnapping or a restart, with the floor camera off, no odometry or floor loop ties
the two odometry chains' headings, so every ridge loop between them was unsettled and
published at the point the inliers' noise picked, with the edge's 1 deg heading sigma: the
relocalisation's fit and the gate after it held a heading the images never fixed (the
forward-only kidnappings' wrong loops, ``docs/forward.md``). The pose graph's links of the
forward loops that join two chains therefore go into the heading graph (:meth:`ForwardLoopStage.on_link`),
except those the stage settled at the heading graph's own heading (their heading is that
prior's, not a measurement): once the forward camera has relocalised the robot, its next
ridge loops across the carry are settled at the heading the relocalising loops give.

**The same input gives the same loops, whatever the machine's load.** The daemon's sources
are read by their own threads, so how the forward frames interleave with the wheel
odometry and the stored keyframes (with the links the pose graph publishes beside them)
changes with the load; the demo once accepted 31 forward loops on a seed under load where
it had accepted 27 quiet. The stage took a keyframe's image when its frame happened to
arrive: the heading graph had the links that had come by then, the frame's offset was
interpolated or extrapolated as far as the odometry had got, a due keyframe still waiting
for its frame was dropped when the next due one came, and the loop reached the pose graph's
gate with the graph as far as it had got. Now every stored keyframe is queued and decided in
order (whether it is due, once the ones before it are); a due one runs when a frame at or
after its stamp has come (the nearest frame is then known) and the wheel odometry has passed
that frame; the heading graph answers from the links it had when the keyframe was stored
(``HeadingGraph.relative(..., upto)``); and what the image publishes (its loop, or the fate
of a view out of the floor plane) is held until the first stored keyframe at or after its
stamp plus ``publish_delay_s`` (1 s), so the gate always sees the graph at the same place in
the keyframes' stream. Two cases remain order-dependent, and are counted instead: a frame
later than the delay (``forward_late``: its loop is the same but reaches the graph later)
and a frame pushed out of the 16-frame buffer by frames running ahead of the keyframes
(``forward_frames_evicted``). The loops of the last ``publish_delay_s`` of a run go out at
the end of the input (:meth:`ForwardLoopStage.finish`), after the pose graph's last solve.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from robotd.app import gcwatch
from robotd.app.pipeline import Publisher
from robotd.base.config import ForwardDetectorConfig
from robotd.base.errors import ConfigError, MapStoreError
from robotd.base.geometry import between, compose, inverse, wrap_angle
from robotd.base.messages import CandidateFate, ForwardLoop, Frame, KeyframeStored, Link, LoopFate, OdometryUpdate
from robotd.forward import LOOP, ForwardDetector
from robotd.forward.detector import ACCEPT_PENDING, VERIFY_PENDING, PendingVerification
from robotd.forward.features import CompactFeatures
from robotd.forward.planar import INLIER_NOISE_FACTOR, planar_motion, planarity_bound
from robotd.forward.planefit import (SCAN_STEP_RAD, PlanarFit, fit_planar_fixed, fit_planar_scans, planar_inliers,
                                    ridge_span)
from robotd.forward.verify import VerifyParams, floor_range, match_features, matched_points

log = logging.getLogger(__name__)

# The stage's parts timed per forward keyframe (ForwardLoopStage.part_cpu_ms).
PARTS = ("match", "scan", "level", "ridge", "graph", "readback", "store", "gc", "deferred", "stage")

#: What a level test (the planar scan, the ridge's fits, the heading graph's solve) counts
#: for in a forward keyframe's budget of epipolar checks (ForwardLoopStage ``check_budget``).
TEST_CHECKS = 1

#: Where the planar refit's heading scan is centred (ForwardLoopStage ``scan_centre``): the
#: verified motion's heading, the level motion's the verification's search found first, or
#: both (two scans, the fit with more inliers kept; the verified one's on a tie).
SCAN_CENTRES = ("verified", "level", "both")


@dataclass(frozen=True)
class _Unsettled:
    """A ridge no prior heading settled (:meth:`ForwardLoopStage._settle`): the bearing's
    sigma over the whole ridge and the heading's, its half-width (rad)."""

    sigma_bearing_rad: float
    sigma_yaw_rad: float


@dataclass
class _Pending:
    """What the level test (:meth:`ForwardLoopStage._level`) found for the view of one past
    image from the image being run, read when that view is the detector's loop: the loop's
    motion in the floor plane with its inlier pixels (old, new) when refitted or settled on
    a ridge (None: the verified motion's); the bearing's sigma of a ridge loop (replaces its
    fit's); the heading's sigma of a ridge no prior heading settled (its half-width); and
    whether it was taken at the prior heading (settled on a ridge: its link does not go
    back into the heading graph)."""

    fit: tuple[PlanarFit, np.ndarray, np.ndarray] | None = None
    sigma_bearing_rad: float | None = None
    sigma_yaw_rad: float | None = None
    at_prior: bool = False


@dataclass
class _Decision:
    """A forward image whose verification is being decided: its detector image, keyframe,
    the context :meth:`ForwardLoopStage._level` reads (``ForwardLoopStage._current``), the
    filter's probability, and, while its level test waits (``defer_accept``), the rest of
    its verification and the forward keyframe it was queued at."""

    image: int
    keyframe_id: int
    current: tuple[np.ndarray, np.ndarray, float | None, int, int, int]
    probability: float
    pending: PendingVerification | None = None
    queued_at: int = 0
    last_refused: tuple[int, float, float] | None = None  # its last view out of the plane so far


@dataclass(frozen=True)
class RidgeParams:
    """When a loop's planar fit lies on a heading-bearing ridge, and how the odometry's
    heading settles it (module notes).

    Fields:
        edge_sigma_yaw_rad: the heading sigma the pose graph gives a forward loop edge
            (``[forward_detector] sigma_yaw_deg``): a ridge whose half-width exceeds it
            claims a heading the images do not fix, so the edge would be overconfident.
        count_sigmas: the ridge is the headings whose best motion keeps at least the best
            count less this many times ``sqrt(best count)``: an inlier count is a count,
            its one-sigma noise about its square root; counts closer than that are not
            told apart by the images.
        prior_gate_sigmas: the odometry's relative heading lies on the ridge when within
            this many of its sigmas of the ridge's ends (3: the 99.7 % point of a normal).
        slope_step_rad: the heading step either side of the prior at which the ridge's
            motion is fitted again to measure how fast its bearing moves with the heading
            (well inside a ridge wider than ``edge_sigma_yaw_rad``, well above the inlier
            noise's effect on a fixed-heading fit).
        span: which headings the ridge is (:func:`ridge_headings`): ``"within"`` (default)
            every scanned heading whose count is within the margin of the best, wherever it
            lies (the ridge spans them, and the graph's heading must be near one of them);
            ``"run"`` only the contiguous run of them around the best
            (:func:`robotd.forward.planefit.ridge_span`, the rule before), which leaves out a
            heading the counts cannot tell from the best when a dip lies between them.
        narrow: a loop whose ridge is no wider than ``edge_sigma_yaw_rad``: ``"keep"``
            (default) keeps the fit's heading, left to the pose graph's gate; ``"graph"``
            takes it, as a ridge loop, at the graph's heading when the graph knows the
            heading better than the edge claims (``prior_gate_sigmas`` of its sigmas within
            ``edge_sigma_yaw_rad``) and within ``prior_gate_sigmas`` edge sigmas of the
            fit's (what the gate would let through anyway); measured, not the default.
    """

    edge_sigma_yaw_rad: float = math.radians(ForwardDetectorConfig.sigma_yaw_deg)
    count_sigmas: float = 1.0
    prior_gate_sigmas: float = 3.0
    slope_step_rad: float = math.radians(0.5)
    span: str = "within"
    narrow: str = "keep"


def ridge_headings(fit: PlanarFit, margin: float, span: str = "within") -> tuple[float, float, np.ndarray]:
    """The ridge of ``fit``'s inlier profile over the heading (:attr:`PlanarFit.scan_inliers`):
    ``(lowest, highest, headings)`` in radians, ``headings`` the scanned ones whose best
    translation direction keeps at least the scan's maximum less ``margin`` matches (with
    ``span="run"`` only the contiguous run of them around the best heading,
    :func:`robotd.forward.planefit.ridge_span`). Without a scan, the fit's own heading."""
    n, yaws = np.asarray(fit.scan_inliers), np.asarray(fit.scan_yaw_rad)
    if len(n) == 0:
        return fit.dyaw_rad, fit.dyaw_rad, np.array([fit.dyaw_rad])
    if span == "run":
        lo, hi = ridge_span(fit, margin)
        return lo, hi, yaws[(yaws >= lo) & (yaws <= hi)]
    on = yaws[n >= n.max() - margin]
    return float(on.min()), float(on.max()), on


def tree_yaws(fi: np.ndarray, ti: np.ndarray, d: np.ndarray, order: np.ndarray, pred: np.ndarray,
              nn: int) -> np.ndarray:
    """The yaws ``(nn,)`` (radians) of ``nn`` nodes along a spanning tree, the tree's root at
    0: ``y[u] = y[pred[u]] + step(pred[u], u)`` in ``order`` (parents first, as
    :func:`scipy.sparse.csgraph.breadth_first_order` gives it; nodes not in it stay 0).
    The step from ``p`` to ``u`` is that of the first of the links ``fi -> ti (M,)`` (yaw
    change ``d (M,)``) between them, ``d`` from ``p`` to ``u`` or ``-d`` from ``u`` to ``p``.
    Found by sorting the links' keys, without a Python object per link: the links are
    thousands, and every tuple a dictionary of them made was a container the garbage
    collector then counted (and paid for at a full collection)."""
    m = len(fi)
    src, dst, val = np.empty(2 * m, np.int64), np.empty(2 * m, np.int64), np.empty(2 * m, np.float64)
    src[0::2], src[1::2] = fi, ti  # each link both ways, the forward one first (as found first)
    dst[0::2], dst[1::2] = ti, fi
    val[0::2], val[1::2] = d, -np.asarray(d, np.float64)
    keys, first = np.unique(src * nn + dst, return_index=True)  # the first occurrence of each pair
    child = np.asarray(order[1:], np.int64)
    parent = np.asarray(pred, np.int64)[child]
    steps = val[first[np.searchsorted(keys, parent * nn + child)]]
    y = [0.0] * nn
    for u, p, s in zip(child.tolist(), parent.tolist(), steps.tolist()):
        y[u] = y[p] + s
    return np.array(y, np.float64)


#: What :meth:`HeadingGraph._links` gives: nodes, link ends (indexes), yaw changes, weights, a's and b's indexes.
_Links = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, int]


class HeadingGraph:
    """The pose graph's headings alone: the keyframes' yaw tied by the yaw part of its edges
    (the odometry's and the floor loops' :class:`~robotd.base.messages.Link` messages; a
    relative pose's yaw is the difference of the two yaws, so this part of the graph is
    linear and solves exactly). It gives the relative heading of two keyframes and its
    1-sigma as the graph knows it (:meth:`relative`). The forward loops' own edges are left
    out (the heading is asked to judge one of them), but for those that join two odometry
    chains with a measured heading (:meth:`ForwardLoopStage.on_link`).

    Bounded: only the links among the ``window`` keyframes before the newer of the two are
    solved, and links entirely older than the newest keyframe's window are forgotten (the
    links are kept in arrays, 24 bytes each). A loop to a keyframe further back gets no
    graph heading (the stage then takes the odometry's). ``window`` (2,000 keyframes, about
    1 km at the demo's spacing) is larger than any run of the demo, whose figures it does
    not change; at 10,000 keyframes it keeps the time per call and the memory flat.

    ``ordering``: SuperLU's column ordering of the solve (``splu``'s ``permc_spec``):
    ``"MMD_AT_PLUS_A"`` (default: the system is symmetric, and its factorisation takes
    about half the time of ``"COLAMD"``'s, the ordering before, on the demo's graphs; the
    headings agree to 1e-15 rad). SciPy's sparse modules are imported when the graph is made
    (at the stage's start), not at the first loop on a ridge, which paid for the import."""

    def __init__(self, window: int = 2000, ordering: str = "MMD_AT_PLUS_A") -> None:
        import scipy.sparse.csgraph
        import scipy.sparse.linalg  # noqa: F401  (imported here, not at a keyframe: see above)

        self.window = int(window)
        self.ordering = ordering
        self._f = np.zeros(0, np.int64)  # the links' from and to keyframes, yaw change (rad), variance (rad^2)
        self._t = np.zeros(0, np.int64)
        self._d = np.zeros(0, np.float64)
        self._v = np.zeros(0, np.float64)
        self._n = 0  # links held (the arrays' first _n entries)
        self._dropped = 0  # links forgotten from the front: link number k is at k - _dropped
        self._newest = -1  # the newest keyframe id seen
        # keyframe -> (odometry yaw_rad, its variance): joins keyframes the links have not reached yet
        self._odom: dict[int, tuple[float, float]] = {}
        # the last solve (_again): its key, nodes, yaws, component, free numbering, factorisation, a's and b's indexes
        self._key: tuple[int, int, int, int] | None = None
        self._nodes = np.zeros(0, np.int64)
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, Any, int, int] | None = None

    def __len__(self) -> int:
        """The links received so far (forgotten ones included): a count for ``upto``."""
        return self._dropped + self._n

    def add_link(self, link: Link, across_chains: bool = False) -> None:
        """Hold one link's yaw part. A forward loop's only with ``across_chains`` (the
        stage's rule, :meth:`ForwardLoopStage.on_link`)."""
        if link.kind == "loop" and link.source == "forward" and not across_chains:
            return
        info = np.asarray(link.information, np.float64)
        try:
            var = float(np.linalg.inv(info)[2, 2])
        except np.linalg.LinAlgError:
            return
        if not (math.isfinite(var) and var > 0.0):
            return
        if self._n == len(self._f):
            cap = max(64, 2 * self._n)
            self._f, self._t = np.resize(self._f, cap), np.resize(self._t, cap)
            self._d, self._v = np.resize(self._d, cap), np.resize(self._v, cap)
        n = self._n
        self._f[n], self._t[n], self._d[n], self._v[n] = link.from_id, link.to_id, float(link.delta_xyyaw[2]), var
        self._n += 1
        self._forget(max(link.from_id, link.to_id))

    def add_keyframe(self, keyframe_id: int, yaw_rad: float, yaw_var_rad2: float) -> None:
        self._odom[keyframe_id] = (yaw_rad, yaw_var_rad2)
        self._forget(keyframe_id)

    def _forget(self, newest: int) -> None:
        """Drop the leading links (and odometry poses) wholly older than ``newest``'s window."""
        if newest <= self._newest:
            return
        self._newest = newest
        horizon = newest - 2 * self.window  # twice: a keyframe up to a window old may still be asked about
        if horizon <= 0:
            return
        n = self._n
        old = np.maximum(self._f[:n], self._t[:n]) < horizon
        k = int(np.argmin(old)) if not old.all() else n  # the leading run of old links
        if k >= 1024 or k == n and n:
            for a in (self._f, self._t, self._d, self._v):
                a[: n - k] = a[k:n].copy()
            self._n -= k
            self._dropped += k
        if len(self._odom) > 4 * self.window:
            for key in [key for key in self._odom if key < horizon]:
                del self._odom[key]

    def relative(self, a: int, b: int, upto: int | None = None) -> tuple[float, float] | None:
        """``(yaw_b - yaw_a, 1-sigma)`` in radians by the graph's yaw edges (a keyframe not
        yet linked is joined to the newest linked one older than it by the odometry's
        poses); None when the two are not connected within the window. ``upto``: only the
        first this many links received (those the graph had when keyframe ``b`` was stored:
        the answer then does not depend on how far the pipeline has gone since)."""
        n_eff = self._n if upto is None else max(0, min(self._n, upto - self._dropped))
        key = (b, self._dropped, n_eff, len(self._odom))
        hit, again = self._again(key, a)
        if hit:
            return again
        self._last = None
        links = self._links(a, b, upto)
        if links is None:
            return None
        nodes, fi, ti, d, w, ia, ib = links
        self._key = key
        import scipy.sparse as sp
        from scipy.sparse.csgraph import breadth_first_order

        nn = len(nodes)
        # The links both ways as one symmetric adjacency (sorted, duplicates summed: the
        # structure of adj + adj.T, so the search below visits the nodes in the same order).
        both_f, both_t = np.concatenate([fi, ti]), np.concatenate([ti, fi])
        sym = sp.csr_matrix((np.ones(len(both_f)), (both_f, both_t)), shape=(nn, nn))
        sym.sum_duplicates()
        # The yaws by a spanning tree from a (the linearisation point), then the weighted
        # least squares of the wrapped residuals with node a held at 0. The tree reaches
        # a's connected component, no further: b outside it has no graph heading.
        order, pred = breadth_first_order(sym, ia, directed=False, return_predecessors=True)
        keep = np.zeros(nn, bool)
        keep[order] = True
        if not keep[ib]:
            return None
        self._nodes = nodes
        y0 = tree_yaws(fi, ti, d, order, pred, nn)
        ok = keep[fi] & keep[ti]
        fi, ti, d, w = fi[ok], ti[ok], d[ok], w[ok]
        r = np.remainder(d - (y0[ti] - y0[fi]) + math.pi, math.tau) - math.pi
        wr = w * r
        # The gradient summed link by link, the to-ends first, then the from-ends (the
        # order of two np.add.at calls: the same sums).
        g = np.bincount(np.concatenate([ti, fi]), np.concatenate([wr, -wr]), nn)
        return self._step(fi, ti, w, g, y0, keep, ia, ib)

    def _links(self, a: int, b: int, upto: int | None) -> _Links | None:
        """The yaw links :meth:`relative` solves over: ``(nodes, fi, ti, d, w, ia, ib)``,
        the links' ends as indexes into the sorted ``nodes``, their yaw changes and weights,
        and a's and b's indexes (None when either is not in the window's links)."""
        n = self._n if upto is None else max(0, min(self._n, upto - self._dropped))
        lo = max(a, b) - self.window
        f, t, d, v = self._f[:n], self._t[:n], self._d[:n], self._v[:n]
        inside = (f >= lo) & (t >= lo)
        f, t, d, v = f[inside], t[inside], d[inside], v[inside]
        linked = np.unique(np.concatenate([f, t]))
        extra: list[tuple[int, int, float, float]] = []
        for k in (a, b):
            at = int(np.searchsorted(linked, k))
            if k >= lo and k in self._odom and not (at < len(linked) and int(linked[at]) == k):
                # the newest linked keyframe older than k with an odometry pose: searched from
                # the newest down (the first found), not every linked keyframe tested
                m = next((i for i in reversed(linked[:at].tolist()) if i in self._odom), None)
                if m is not None:
                    (ya, va), (yb, vb) = self._odom[m], self._odom[k]
                    extra.append((m, k, float(wrap_angle(yb - ya)), max(vb - va, 1e-8)))
        if extra:
            ex = np.array(extra, np.float64)
            f = np.concatenate([f, ex[:, 0].astype(np.int64)])
            t = np.concatenate([t, ex[:, 1].astype(np.int64)])
            d, v = np.concatenate([d, ex[:, 2]]), np.concatenate([v, ex[:, 3]])
        nodes = np.unique(np.concatenate([f, t]))
        if a == b or len(nodes) == 0:
            return None
        ia, ib = int(np.searchsorted(nodes, a)), int(np.searchsorted(nodes, b))
        if ia >= len(nodes) or ib >= len(nodes) or nodes[ia] != a or nodes[ib] != b:
            return None
        return nodes, np.searchsorted(nodes, f), np.searchsorted(nodes, t), d, 1.0 / v, ia, ib

    def _step(self, fi: np.ndarray, ti: np.ndarray, w: np.ndarray, g: np.ndarray, y0: np.ndarray,
              keep: np.ndarray, ia: int, ib: int) -> tuple[float, float]:
        """The Gauss-Newton step from the tree's yaws ``y0`` with gradient ``g`` (node ``ia``
        held, the nodes outside ``keep`` left out): b's yaw and its 1-sigma."""
        import scipy.sparse as sp
        from scipy.sparse.linalg import splu

        nn = len(y0)
        free = np.flatnonzero(keep & (np.arange(nn) != ia))
        # The normal matrix over the free nodes only, built in their numbering (the
        # entries in the order the whole matrix had them: the same sums).
        pos = np.full(nn, -1, np.int64)
        pos[free] = np.arange(len(free))
        rows, cols = pos[np.concatenate([fi, ti, fi, ti])], pos[np.concatenate([fi, ti, ti, fi])]
        inner = (rows >= 0) & (cols >= 0)
        h = sp.csc_matrix((np.concatenate([w, w, -w, -w])[inner], (rows[inner], cols[inner])),
                          shape=(len(free), len(free)))
        lu = splu(h, permc_spec=self.ordering)
        dy = np.zeros(nn)
        dy[free] = lu.solve(g[free])
        e = np.zeros(len(free))
        jb = int(np.flatnonzero(free == ib)[0])
        e[jb] = 1.0
        var = float(lu.solve(e)[jb])
        self._last = (self._nodes, y0 + dy, keep, pos, lu, ia, ib)
        return float(wrap_angle(y0[ib] + dy[ib])), math.sqrt(max(var, 0.0))

    def _again(self, key: tuple[int, int, int, int], a: int) -> tuple[bool, tuple[float, float] | None]:
        """The answer for ``a`` from the last solve when it was for the same newer keyframe
        with the same links (``key``: the stage asks once per view of one forward keyframe,
        all against that keyframe, with the links it had when stored) and ``a`` is one of its
        nodes: the solution is the same least squares (a node the last pair joined by the
        odometry is a leaf, which moves no other node), so its yaws give ``a``'s heading and
        the factorisation its sigma, by one more back-substitution instead of a new solve
        (the same figures up to rounding): ``(True, answer)``; ``(False, None)`` when there is
        no such solve."""
        last = self._last
        if last is None or key != self._key:
            return False, None
        nodes, y, keep, pos, lu, ia0, ib = last
        ia = int(np.searchsorted(nodes, a))
        if ia >= len(nodes) or int(nodes[ia]) != a:
            return False, None
        if not keep[ia]:
            return True, None
        e = np.zeros(lu.shape[0])
        if ia != ia0:
            e[pos[ia]] = -1.0
        e[pos[ib]] += 1.0
        var = float(e @ lu.solve(e))
        return True, (float(wrap_angle(y[ib] - y[ia])), math.sqrt(max(var, 0.0)))


class ForwardLoopStage(Publisher):
    """Forward keyframes through the detector; verified planar loops out (module notes)."""

    name = "forward"
    produces = (ForwardLoop, CandidateFate)
    optional_inputs = (OdometryUpdate, Link)  # without them the frames' offsets are zero, the ridges unsettled

    def __init__(self, detector: ForwardDetector, *, distance_m: float = 0.5,
                 rotation_rad: float = math.radians(20.0), sync_tolerance_s: float = 0.04,
                 max_tilt_rad: float = math.radians(10.0), camera: str = "forward",
                 store: Any = None, planarity_bound: float = planarity_bound(), planar_refit: bool = True,
                 mount: np.ndarray | None = None, ridge: RidgeParams | None = None,
                 publish_delay_s: float = 1.0, scan_centre: str = "both", defer_accept: bool = True,
                 max_deferred: int = 4, check_budget: int | None = None) -> None:
        if scan_centre not in SCAN_CENTRES:
            raise ConfigError(f"forward stage: scan_centre must be one of {', '.join(SCAN_CENTRES)}, "
                              f"not {scan_centre!r}")
        if max_deferred < 1:
            raise ConfigError(f"forward stage: max_deferred must be >= 1, not {max_deferred}")
        if check_budget is not None and check_budget < TEST_CHECKS:
            raise ConfigError(f"forward stage: check_budget must be >= {TEST_CHECKS} (one level test), "
                              f"not {check_budget}")
        self.scan_centre = scan_centre
        # The level test of a verified view waits for a forward keyframe that verifies
        # nothing (module notes, "One verification's work per keyframe"): the queue, its bound.
        self.defer_accept = defer_accept
        self.max_deferred = int(max_deferred)
        self._deferred: deque[_Decision] = deque()
        self.deferred = 0  # images whose level test waited for a later keyframe
        self.deferred_inline = 0  # images tested in their own keyframe because the queue was full
        self.deferred_across = 0  # images tested at once: their view in another odometry chain
        self.deferred_at_end = 0  # images whose test ran at the end of the input
        self.deferred_wait_max = 0  # the most forward keyframes an image's test waited
        # The verification's work per forward keyframe in epipolar checks, a level test counting
        # TEST_CHECKS (module notes, "A budget of checks"); None: the queue of level tests alone.
        self.check_budget = check_budget
        self.deferred_forced = 0  # waiting verifications finished over the budget: the queue over its bound
        self.checks_max = 0  # the most checks (a level test TEST_CHECKS) one forward keyframe ran
        self.checks_over = 0  # forward keyframes whose checks went over the budget (forced, across, the end)
        self._image: int | None = None  # the detector image being decided (for _scan)
        self.tests = 0  # level tests run (views whose epipolar check passed)
        self.detector = detector
        self.ridge = RidgeParams() if ridge is None else ridge
        self.ridge_settled = 0  # loops on a ridge, settled at the graph's heading (module notes)
        self.ridge_refused = 0  # loops on a ridge the graph's heading lies off
        self.ridge_unsettled = 0  # loops on a ridge without a graph or odometry heading: the bearing's sigma the ridge's
        self.narrow_settled = 0  # of the settled, loops with no ridge taken at the graph's heading (RidgeParams.narrow)
        # Per detector image: the keyframe pose's heading variance (rad^2), None when not known.
        self._yaw_vars: list[float | None] = []
        # The image being run: (offset, keyframe pose, its heading variance, chain, keyframe id,
        # the heading graph's links when the keyframe was stored), for _level.
        self._current: tuple[np.ndarray, np.ndarray, float | None, int, int, int] | None = None
        # past image -> what _level found for its view of the image being run (_Pending)
        self._pending: dict[int, _Pending] = {}
        # loops (old keyframe, new keyframe) published at the prior heading: their heading is
        # the heading graph's own, so their links do not go back into it
        self._prior_loops: set[tuple[int, int]] = set()
        # keyframe of a detector image -> its odometry chain (-1: an image taken up from the map)
        self._chain_of: dict[int, int] = {}
        self.headings = HeadingGraph()  # the graph's headings, for a ridge loop's prior
        self.mount = np.zeros(3) if mount is None else np.asarray(mount, np.float64).reshape(3)
        # The wheel odometry's last seconds, (stamp_ns, (x_m, y_m, yaw_rad)), for the frames' offsets.
        self._odom: deque[tuple[int, np.ndarray]] = deque(maxlen=512)
        # Per detector image: the camera's motion from its keyframe's stamp to its frame's
        # (camera frame, x forward, y left: (x_m, y_m, yaw_rad)), the keyframe's pose, and the
        # odometry chain it belongs to (a lift starts a new one).
        self._offsets: list[np.ndarray] = []
        self._poses: list[np.ndarray | None] = []
        self._chains: list[int] = []
        self._chain = 0
        self.frame_offset_ms_max = 0.0  # the largest |frame stamp - keyframe stamp| of a forward keyframe
        self.no_offset = 0  # forward keyframes whose frame had no odometry around it
        self.planar_refit = planar_refit
        self.refits = 0
        self.level_refits = 0  # of them, motions that passed the planarity test (module notes)
        self._last_refused: tuple[int, float, float] | None = None  # (past image, tilt, chi2)
        # A candidate whose motion is not a level camera's is not a loop: the detector then
        # verifies the next view it may try (DetectorParams.verify_tries).
        detector.accept = self._level
        self.store = store
        self.store_errors = 0
        self.read_errors = 0  # reads of a past image's stored features that failed (logged once per image)
        self._unreadable: set[int] = set()
        self.restored = 0
        if store is not None:  # the past images' features stay in the map, read back when verified
            detector.loader = self._load
        self.distance_m = distance_m
        self.rotation_rad = rotation_rad
        self.sync_tolerance_ns = int(sync_tolerance_s * 1e9)
        self.max_tilt_rad = max_tilt_rad
        self.planarity_bound = planarity_bound
        self.camera = camera
        self._frames: deque[Frame] = deque(maxlen=16)
        self._keyframe_ids: list[int] = []  # detector image id -> floor keyframe id
        self._last_pose: np.ndarray | None = None
        # Stored keyframes not yet decided, in order: (keyframe, pose, chain, the heading graph's
        # links when it was stored); None marks a lift (forget the poses). A due one waits for
        # its frame and the odometry past it (module notes).
        self._due_kfs: deque[tuple[Any, np.ndarray, int, int] | None] = deque()
        # What each forward keyframe publishes, held until the stream passes its stamp plus
        # publish_delay_s (module notes): (release stamp_ns, messages).
        self.publish_delay_ns = int(publish_delay_s * 1e9)
        self._outbox: deque[tuple[int, list[Any]]] = deque()
        self._released_ns = -1  # the newest stored keyframe's stamp the held messages were released at
        self._out: list[Any] | None = None  # the messages of the image being run
        self.late = 0  # forward keyframes whose messages came after their release point (order-dependent)
        self.evicted = 0  # forward keyframes whose nearest frame had been pushed out of the buffer
        self._evicted_ns: int | None = None
        self.frames = 0
        self.images = 0
        self.unsynced = 0
        self.loops = 0
        self.not_planar = 0
        self.rejected_geometry = 0
        self.total_ms: list[float] = []  # the detector's time per forward keyframe (wall clock)
        self.cpu_ms: list[float] = []  # the same, in the pipeline thread's CPU time
        self.verify_ms: list[float] = []  # its verification part (wall clock)
        self.features_ms: list[float] = []  # its feature extraction (OpenCV's ORB, wall clock): the baseline
        # The stage's parts per forward keyframe in the pipeline thread's CPU time (ms): the
        # planar refit's matches and heading scan, the level test against the verified motion,
        # the ridge's fits, the graph's heading, the read-back of evicted images, the map write,
        # Python's garbage collections run in this thread meanwhile (with a
        # robotd.app.gcwatch installed; they are inside the other parts), and the whole
        # keyframe (detector and stage).
        self.part_cpu_ms: dict[str, list[float]] = {k: [] for k in PARTS}
        self._part: dict[str, float] = {}
        if store is not None:
            self._restore()

    def _restore(self) -> None:
        """Take up the forward memory stored in the map by earlier runs."""
        images, words = self.store.forward_memory(features_from=self._features_from())
        if not images and not words:
            return
        kind = self.detector.params.features.kind
        kinds = {i[2] for i in images} | {w[1] for w in words}
        if kinds != {kind}:
            log.warning("the map's forward memory holds %s features, the detector uses %s: the "
                        "earlier runs' forward images are not used and this run's are not stored",
                        "/".join(sorted(kinds)), kind)
            self.store = None
            return
        binary = self.detector.params.features.binary
        dim = self.detector.params.features.descriptor_size
        dtype = np.uint8 if binary else np.float32
        feats = []
        for n, (image_id, kf_id, _, size, w, kq, desc) in enumerate(images):
            if image_id != n:
                log.warning("the map's forward images are not numbered 0, 1, ...: not used, and this run's "
                            "are not stored")
                self.store = None
                return
            d = np.frombuffer(desc, dtype).reshape(-1, dim)  # (0, dim) for one left in the map
            feats.append(CompactFeatures(w, kq, d, size))
            self._keyframe_ids.append(kf_id)
            self._offsets.append(np.zeros(3))
            self._poses.append(None)
            self._yaw_vars.append(None)
            self._chains.append(-1)
            self._chain_of[int(kf_id)] = -1
        word_desc = np.zeros((len(words), dim), dtype)  # purged words' descriptors are not kept
        for n, w in enumerate(words):
            if not w[4]:
                word_desc[n] = np.frombuffer(w[2], dtype)
        self.detector.restore(feats, word_desc, np.array([w[3] for w in words], np.int64),
                              np.array([w[4] for w in words], bool), stored=True)
        self.restored = len(feats)
        log.info("forward memory taken up from the map: %d images, %d words (%d purged)", len(feats),
                 len(words), self.detector.vocabulary.purged)

    def _store_image(self, keyframe_id: int) -> None:
        """Write the image just processed, with the words it made and those purged."""
        t = len(self.detector) - 1
        f = self.detector.features_of(t)
        voc = self.detector.vocabulary
        ids, descs = voc.last_new
        try:
            self.store.add_forward_image(
                t, keyframe_id, self.detector.params.features.kind, f.image_size_px, f.words, f.keypoints_q,
                f.descriptors, new_words=[(int(i), d.tobytes()) for i, d in zip(ids, descs)],
                purged=[int(i) for i in voc.last_purged])
        except (ValueError, MapStoreError) as exc:
            self.store_errors += 1
            log.warning("forward image %d (keyframe %d) not stored: %s", t, keyframe_id, exc)
            return
        self.detector.mark_stored(t)

    def _features_from(self) -> int:
        """The first stored image whose features a restart reads into memory (the
        detector's ``resident`` newest; the older ones are read back when verified)."""
        rows = self.store.forward_image_count()
        return max(0, rows - self.detector.resident)

    def _load(self, image_id: int) -> CompactFeatures:
        """The detector's loader: a past image's features read back from the map (a read
        that fails is logged and counted, and that image is not verified)."""
        t0 = time.thread_time()
        try:
            return self._read_back(image_id)
        finally:
            self._add_cpu("readback", t0)

    def _read_back(self, image_id: int) -> CompactFeatures:
        try:
            row = self.store.forward_image(image_id) if self.store is not None else None
        except MapStoreError as exc:
            row, why = None, str(exc)
        else:
            why = "not in the map"
        if row is not None and row[0] == self.detector.params.features.kind:
            kind, size, kq, desc = row
            fp = self.detector.params.features
            dtype = np.uint8 if fp.binary else np.float32
            try:
                d = np.frombuffer(desc, dtype).reshape(-1, fp.descriptor_size)
            except ValueError as exc:
                why = str(exc)
            else:
                if len(d) == len(kq):
                    return CompactFeatures(np.zeros(0, np.uint32), kq, d, size)
                why = f"{len(kq)} keypoints but {len(d)} descriptors"
        self.read_errors += 1
        (log.debug if image_id in self._unreadable else log.warning)(
            "forward image %d: its stored features could not be read back (%s): not verified", image_id, why)
        self._unreadable.add(image_id)
        raise LookupError(image_id)

    def subscriptions(self) -> Mapping[type, Any]:
        return {Frame: self.on_frame, KeyframeStored: self.on_keyframe, OdometryUpdate: self.on_odometry,
                Link: self.on_link}

    def on_link(self, link: Link) -> None:
        """A pose graph link into the heading graph (:class:`HeadingGraph`). A forward loop's
        goes in when it joins two odometry chains (a kidnapping or a restart apart: without
        the floor camera nothing else ties their headings, and a ridge loop between them
        could not be settled) and its heading was measured, not taken at the heading
        graph's own prior (module notes)."""
        across = False
        if link.kind == "loop" and link.source == "forward":
            a, b = self._chain_of.get(int(link.from_id)), self._chain_of.get(int(link.to_id))
            across = (a is not None and b is not None and a != b
                      and (int(link.from_id), int(link.to_id)) not in self._prior_loops)
        self.headings.add_link(link, across_chains=across)

    def on_odometry(self, msg: OdometryUpdate) -> None:
        w = msg.wheel
        if self._odom and w.stamp_ns <= self._odom[-1][0]:
            if w.stamp_ns < self._odom[-1][0]:  # time went back (a new run's clock): start again
                self._odom.clear()
            else:
                return
        self._odom.append((w.stamp_ns, np.array([w.x_m, w.y_m, w.yaw_rad])))
        if self._due_kfs:
            self._drain()

    def _odom_at(self, stamp_ns: int) -> np.ndarray | None:
        """The wheel odometry's pose at ``stamp_ns``: interpolated between its two samples
        around it, or extrapolated at the last two samples' speed up to 0.1 s past the newest;
        None without odometry there."""
        od = self._odom
        if len(od) < 2 or stamp_ns < od[0][0] or stamp_ns > od[-1][0] + 100_000_000:
            return None
        k = len(od) - 1
        while k > 1 and od[k - 1][0] > stamp_ns:
            k -= 1
        (t0, p0), (t1, p1) = od[k - 1], od[k]
        q = (stamp_ns - t0) / max(t1 - t0, 1)
        d = p1 - p0
        d[2] = wrap_angle(d[2])
        return p0 + q * d

    def _frame_offset(self, kf_stamp_ns: int, frame_stamp_ns: int) -> np.ndarray | None:
        """The camera's motion ``(3,)`` from the keyframe's stamp to the frame's, in the
        camera's planar frame at the keyframe (module notes); None without odometry."""
        a, b = self._odom_at(kf_stamp_ns), self._odom_at(frame_stamp_ns)
        if a is None or b is None:
            return None
        return compose(compose(inverse(self.mount), between(a, b)), self.mount)

    def on_frame(self, frame: Frame) -> None:
        if frame.camera != self.camera:
            return
        self.frames += 1
        if len(self._frames) == self._frames.maxlen:  # the newest frame pushed out, for _take_frame
            self._evicted_ns = self._frames[0].stamp_ns
        self._frames.append(frame)
        if self._due_kfs:
            self._drain()

    def _drain(self, force: bool = False) -> None:
        """Run the due keyframes, oldest first, whose frame is decided (a frame at or after
        the keyframe's stamp has come) and whose frame the wheel odometry has reached (so
        the frame's offset is interpolated, not extrapolated); with ``force`` (the end of
        the input) all of them. What they publish does not depend on when this runs
        (module notes)."""
        while self._due_kfs:
            head = self._due_kfs[0]
            if head is None:  # a lift: odometry cannot relate the images before it to those after
                self._due_kfs.popleft()
                self.detector.forget_poses()
                continue
            kf, pose = head[0], head[1]
            if not self._due(pose):
                self._due_kfs.popleft()
                continue
            if not force:
                if not self._frames or self._frames[-1].stamp_ns < kf.stamp_ns:
                    return
                frame = min(self._frames, key=lambda f: abs(f.stamp_ns - kf.stamp_ns))
                if self._odom and self._odom[-1][0] < max(frame.stamp_ns, kf.stamp_ns):
                    return
            self._due_kfs.popleft()
            self._take(*head)

    def _due(self, pose: np.ndarray) -> bool:
        if self._last_pose is None:
            return True
        d = pose - self._last_pose
        turn = abs(math.remainder(float(d[2]), math.tau))
        return bool(math.hypot(d[0], d[1]) >= self.distance_m or turn >= self.rotation_rad)

    def on_keyframe(self, msg: KeyframeStored) -> None:
        kf = msg.keyframe
        cov = np.asarray(kf.pose.covariance, np.float64)
        self.headings.add_keyframe(kf.keyframe_id, float(kf.pose_xyyaw[2]),
                                   float(cov[2, 2]) if cov.shape == (3, 3) else 0.0)
        if kf.carried:  # odometry cannot relate the images before the lift to the ones after
            self._due_kfs.append(None)
            self._chain += 1
        pose = np.array(kf.pose_xyyaw, dtype=np.float64)
        # Whether it is due is decided in the keyframes' order, once the ones before it are.
        self._due_kfs.append((kf, pose, self._chain, len(self.headings)))
        self._drain()
        self._release(kf.stamp_ns)

    def _release(self, stamp_ns: int) -> None:
        """Publish the held messages due by the stored keyframe of ``stamp_ns``."""
        self._released_ns = max(self._released_ns, stamp_ns)
        while self._outbox and self._outbox[0][0] <= self._released_ns:
            for m in self._outbox.popleft()[1]:
                self._publish(m)

    def finish(self) -> int:
        """End of the input: the keyframes still waiting for their frame run with what came,
        and every held message is published."""
        self._drain(force=True)
        self._flush_deferred()
        n = len(self._outbox)
        self._release(2**62)
        if self.cpu_ms:
            c = self.counters()
            log.info("forward keyframes' CPU time: median %.2f ms, p99 %.2f ms; parts (p99 / total ms): %s; "
                     "the three costliest keyframes: %s", c["forward_cpu_ms_median"], c["forward_cpu_ms_p99"],
                     ", ".join(f"{k} {c[f'forward_{k}_cpu_ms_p99']} / {c[f'forward_{k}_cpu_ms_total']}"
                               for k in PARTS if f"forward_{k}_cpu_ms_p99" in c),
                     c.get("forward_cpu_top_keyframes"))
        return n

    def _take(self, kf: Any, pose: np.ndarray, chain: int, links: int) -> None:
        """Run the forward frame nearest ``kf``'s stamp through the detector, if near enough;
        what it publishes is held until the stream passes ``kf``'s stamp plus the delay."""
        self._out = []
        self._part = {}
        n_images = self.images
        watch = gcwatch.installed()
        gc0 = watch.thread_cpu_ms() if watch is not None else 0.0
        cpu0 = time.thread_time()
        try:
            self._take_frame(kf, pose, chain, links)
        finally:
            out, self._out = self._out, None
            if self.images > n_images:  # a forward keyframe was run: its parts
                self._add_cpu("stage", cpu0)
                if watch is not None:  # the collections run in this thread meanwhile
                    self._part["gc"] = watch.thread_cpu_ms() - gc0
                for part in PARTS:
                    self.part_cpu_ms[part].append(self._part.get(part, 0.0))
        if not out:
            return
        release = kf.stamp_ns + self.publish_delay_ns
        if release <= self._released_ns:  # its slot has passed: published now, counted
            self.late += 1
            for m in out:
                self._publish(m)
        else:
            self._outbox.append((release, out))

    def _add_cpu(self, part: str, since: float) -> None:
        """Add the thread's CPU time since ``since`` (``time.thread_time``) to ``part`` of
        the keyframe being run."""
        self._part[part] = self._part.get(part, 0.0) + (time.thread_time() - since) * 1e3

    def _emit(self, msg: Any) -> None:
        if self._out is not None:
            self._out.append(msg)
        else:
            self._publish(msg)

    def _take_frame(self, kf: Any, pose: np.ndarray, chain: int, links: int) -> None:
        if not self._frames:
            self.unsynced += 1
            return
        frame = min(self._frames, key=lambda f: abs(f.stamp_ns - kf.stamp_ns))
        if self._evicted_ns is not None and abs(self._evicted_ns - kf.stamp_ns) < abs(frame.stamp_ns - kf.stamp_ns):
            self.evicted += 1  # the frames ran ahead of the keyframes by more than the buffer holds
        if abs(frame.stamp_ns - kf.stamp_ns) > self.sync_tolerance_ns:
            self.unsynced += 1
            return
        self._last_pose = pose
        self._last_refused = None
        offset = self._frame_offset(kf.stamp_ns, frame.stamp_ns)
        cov = np.asarray(kf.pose.covariance, np.float64)
        yaw_var = float(cov[2, 2]) if cov.shape == (3, 3) and math.isfinite(float(cov[2, 2])) else None
        current = (np.zeros(3) if offset is None else offset, pose, yaw_var, chain, kf.keyframe_id, links)
        t = len(self._offsets)  # this image's number in the detector
        self._current, self._image = current, t
        if self.check_budget is not None:
            self._take_budgeted(kf, frame, pose, chain, current, t, offset, yaw_var)
            return
        defer = self.defer_accept and len(self._deferred) < self.max_deferred
        tests = self.tests
        cpu0 = time.thread_time()
        det = self.detector.process(frame.image, pose, kf.pose.covariance,
                                    defer_accept=defer)  # the keyframe's odometry pose
        cpu_ms = (time.thread_time() - cpu0) * 1e3
        self._current, self._image = None, None
        self._record_image(kf, frame, pose, chain, offset, yaw_var)
        self.deferred_inline += bool(self.defer_accept and not defer and self.tests > tests)
        decision = _Decision(t, kf.keyframe_id, current, det.candidate_probability)
        across = False
        if det.status == ACCEPT_PENDING:
            decision.pending, decision.queued_at = det.pending, self.images
            view = det.pending.view if det.pending is not None else None
            across = view is not None and self._chains[int(view)] != chain
            if not across:
                self._deferred.append(decision)
                self.deferred += 1
        else:
            self._decide(decision, det.status, det.loop_id, det.verification)
        # A view of another odometry chain (across a kidnapping or a restart) may relocalise
        # the robot: its level test runs now. Otherwise a keyframe that verified nothing
        # finishes the oldest waiting verification (its level test, and the views after it
        # when refused). Either way its CPU is this keyframe's.
        resumed_s = 0.0
        if across or (det.verification is None and self._deferred):
            t0, w0 = time.thread_time(), time.perf_counter()
            if across:
                self.deferred_across += 1
                self._resume(decision)
            else:
                self._resume(self._deferred.popleft())
            resumed = (time.thread_time() - t0) * 1e3
            cpu_ms += resumed
            resumed_s = time.perf_counter() - w0
            self._part["deferred"] = self._part.get("deferred", 0.0) + resumed
        self._finish_image(kf, det, cpu_ms, resumed_s)

    def _record_image(self, kf: Any, frame: Frame, pose: np.ndarray, chain: int,
                      offset: np.ndarray | None, yaw_var: float | None) -> None:
        """Keep what later keyframes read of the image just given to the detector: its
        keyframe, offset, pose, heading variance and odometry chain."""
        self._keyframe_ids.append(kf.keyframe_id)
        if offset is None:
            self.no_offset += 1
        self._offsets.append(np.zeros(3) if offset is None else offset)
        self._poses.append(pose)
        self._yaw_vars.append(yaw_var)
        self._chains.append(chain)
        self._chain_of[int(kf.keyframe_id)] = chain
        self.frame_offset_ms_max = max(self.frame_offset_ms_max, abs(frame.stamp_ns - kf.stamp_ns) / 1e6)

    def _finish_image(self, kf: Any, det: Any, cpu_ms: float, resumed_s: float) -> None:
        """The keyframe's CPU and times (with the waiting work it ran, ``resumed_s`` of wall
        time), and the image stored."""
        self.cpu_ms.append(cpu_ms)
        if self.store is not None:
            t0 = time.thread_time()
            self._store_image(kf.keyframe_id)
            self._add_cpu("store", t0)
        self.images += 1
        self.total_ms.append((det.times_s["total"] + resumed_s) * 1e3)
        self.verify_ms.append((det.times_s.get("verify", 0.0) + resumed_s) * 1e3)
        self.features_ms.append(det.times_s.get("features", 0.0) * 1e3)

    def _take_budgeted(self, kf: Any, frame: Frame, pose: np.ndarray, chain: int,
                       current: tuple[np.ndarray, np.ndarray, float | None, int, int, int], t: int,
                       offset: np.ndarray | None, yaw_var: float | None) -> None:
        """:meth:`_take_frame` with a budget of epipolar checks per forward keyframe (module
        notes, "A budget of checks"): the waiting verifications go first, oldest first, then
        the image's own; what the budget leaves waits, the queue bounded by ``max_deferred``."""
        budget = self.check_budget
        assert budget is not None
        cpu0 = time.thread_time()
        # The image's own checks only when nothing older waits (the oldest first).
        own = 0 if self._deferred else budget
        det = self.detector.process(frame.image, pose, kf.pose.covariance, defer_accept=True, max_checks=own)
        cpu_ms = (time.thread_time() - cpu0) * 1e3
        self._current, self._image = None, None
        self._record_image(kf, frame, pose, chain, offset, yaw_var)
        decision = _Decision(t, kf.keyframe_id, current, det.candidate_probability)
        spent = det.checks
        t0, w0 = time.thread_time(), time.perf_counter()
        if det.status in (ACCEPT_PENDING, VERIFY_PENDING) and det.pending is not None:
            decision.pending, decision.queued_at = det.pending, self.images
            if any(self._chains[int(j)] != chain for j in det.pending.order):
                # A view of another odometry chain may relocalise the robot: the image's whole
                # verification now, over the budget (counted).
                self.deferred_across += 1
                spent += self._run_job(decision, None)
            else:
                self._deferred.append(decision)
        else:
            self._decide(decision, det.status, det.loop_id, det.verification)
        # The budget left goes to the waiting verifications, the oldest first: a level test
        # needs TEST_CHECKS of it, a view's epipolar check one.
        while self._deferred and spent < budget:
            d = self._deferred[0]
            assert d.pending is not None
            if d.pending.view is not None and budget - spent < TEST_CHECKS:
                break
            spent += self._run_job(d, budget - spent)
            if d.pending is None:
                self._deferred.popleft()
            elif d.pending.view is None:
                break  # stopped by the budget
        # Over the bound: the oldest finished now, over the budget (counted).
        while len(self._deferred) > self.max_deferred:
            self.deferred_forced += 1
            spent += self._run_job(self._deferred.popleft(), None)
        self.deferred += decision.pending is not None  # its verification goes on in a later keyframe
        resumed = (time.thread_time() - t0) * 1e3
        resumed_s = time.perf_counter() - w0
        cpu_ms += resumed
        self._part["deferred"] = self._part.get("deferred", 0.0) + resumed
        self.checks_max = max(self.checks_max, spent)
        self.checks_over += spent > budget
        self._finish_image(kf, det, cpu_ms, resumed_s)

    def _run_job(self, d: _Decision, max_checks: int | None) -> int:
        """Go on with waiting verification ``d`` (:meth:`ForwardDetector.resume`): its awaiting
        level test, then its views' checks, at most ``max_checks`` of budget (None: to the end);
        what it decides is published with the keyframe being run. Returns the budget it spent
        (a level test :data:`TEST_CHECKS`, a check one); ``d.pending`` is None once decided."""
        job = d.pending
        assert job is not None
        if d.queued_at != self.images:
            self.deferred_wait_max = max(self.deferred_wait_max, self.images - d.queued_at)
        tests, checks = self.tests, job.checks
        self._pending.clear()
        self._last_refused = d.last_refused
        self._current, self._image = d.current, d.image
        try:
            limit = None if max_checks is None else max_checks - (TEST_CHECKS if job.view is not None else 0)
            out = self.detector.resume(job, max_checks=limit, defer_accept=max_checks is not None)
        finally:
            self._current, self._image = None, None
        spent = (self.tests - tests) * TEST_CHECKS + job.checks - checks
        if out is job or isinstance(out, PendingVerification):  # stopped by the budget, or at a view awaiting its test
            d.last_refused, self._last_refused = self._last_refused, None
            return spent
        status, j, v = out
        d.pending = None
        self._decide(d, status, j if status == LOOP else None, v)
        return spent

    def _resume(self, d: _Decision) -> None:
        """Finish a waiting verification (:meth:`ForwardDetector.resume`) and publish what it
        decided with the keyframe being run."""
        self._run_job(d, None)

    def _flush_deferred(self) -> None:
        """The end of the input: every waiting verification finished, its CPU the last
        forward keyframe's, what it decides held for the final release."""
        if not self._deferred:
            return
        self.deferred_at_end += len(self._deferred)
        self._out, self._part = [], {}
        cpu0 = time.thread_time()
        try:
            while self._deferred:
                self._resume(self._deferred.popleft())
        finally:
            ms = (time.thread_time() - cpu0) * 1e3
            out, self._out = self._out, None
        if self.cpu_ms:
            self.cpu_ms[-1] += ms
            for part, extra in {**self._part, "deferred": ms, "stage": ms}.items():
                if part in self.part_cpu_ms and self.part_cpu_ms[part]:
                    self.part_cpu_ms[part][-1] += extra
        if out:
            self._outbox.append((2**62, out))

    def _decide(self, d: _Decision, status: Any, loop_id: int | None, verification: Any) -> None:
        """What image ``d``'s verification decided, published: its loop, or the fate of a
        view the level test found out of the floor plane."""
        if status != LOOP or verification is None or loop_id is None:
            self._pending.clear()
            if verification is not None and not verification.accepted:
                self.rejected_geometry += 1
            elif verification is not None and self._last_refused is not None:
                j, tilt, chi2 = self._last_refused
                self._emit(CandidateFate(d.keyframe_id, self._keyframe_ids[j], d.probability,
                                            LoopFate.FAILED_GATE,
                                            f"forward: motion {math.degrees(tilt):.1f} deg out of the floor plane "
                                            f"(planarity chi2 {chi2:.0f}, bound {self.planarity_bound:.0f})"))
            self._last_refused = None
            return
        v = verification
        if v.rotation is None or v.translation_dir is None:
            raise AssertionError("an accepted forward loop's verification has no relative pose")
        old = self._keyframe_ids[loop_id]
        pending = self._pending.pop(loop_id, None) or _Pending()
        self._pending.clear()
        refit, ridge_sigma, ridge_yaw = pending.fit, pending.sigma_bearing_rad, pending.sigma_yaw_rad
        if pending.at_prior:
            self._prior_loops.add((int(old), int(d.keyframe_id)))
        # The general fit's bearing sigma is the inliers' own noise; scaled as the planarity
        # test and the planar fit scale it (robotd.forward.planar.INLIER_NOISE_FACTOR).
        range_m, sigma_b = v.range_m, v.sigma_bearing_rad * INLIER_NOISE_FACTOR
        fit = None
        if refit is not None:  # refitted in the floor plane (robotd.forward.planefit)
            fit, p_old, p_new = refit
            k = self.detector.camera_matrix
            assert k is not None  # _refit fits nothing without it
            dyaw, bearing, sigma_b = fit.dyaw_rad, fit.bearing_rad, fit.sigma_bearing_rad
            if ridge_sigma is not None:
                sigma_b = ridge_sigma
            range_m = floor_range(p_old, p_new, fit.rotation, fit.translation_dir, k,
                                  self.detector.params.verify)[0]
        else:
            dyaw, bearing, _ = planar_motion(v.rotation, v.translation_dir)
            if ridge_sigma is not None:
                sigma_b = ridge_sigma
        dyaw, bearing, range_m = self._to_keyframes(loop_id, d.image, dyaw, bearing, range_m)
        self.loops += 1
        log.debug("forward loop: keyframe %d sees keyframe %d (p %.2f, %d inliers%s)", d.keyframe_id, old,
                  d.probability, v.n_inliers, ", refitted in the plane" if fit is not None else "")
        self._emit(ForwardLoop(old, d.keyframe_id, d.probability, dyaw, bearing, v.n_inliers,
                                  range_m=range_m, sigma_bearing_rad=sigma_b if np.isfinite(sigma_b) else None,
                                  sigma_yaw_rad=ridge_yaw))

    def _to_keyframes(self, i_old: int, i_new: int, dyaw: float, bearing: float,
                      range_m: float | None) -> tuple[float, float, float | None]:
        """The loop's ``(dyaw_rad, bearing_rad, range_m)`` measured between the frames of
        detector images ``i_old`` and ``i_new``, carried to their keyframes (module notes)."""
        e_old, e_new = self._offsets[i_old], self._offsets[i_new]
        dyaw_kf = float(wrap_angle(dyaw + e_old[2] - e_new[2]))
        r = range_m
        p_old, p_new = self._poses[i_old], self._poses[i_new]
        if r is None and p_old is not None and p_new is not None and self._chains[i_old] == self._chains[i_new]:
            cam_kf = compose(compose(inverse(self.mount), between(p_old, p_new)), self.mount)
            pred = compose(compose(inverse(e_old), cam_kf), e_new)  # between the frames
            r = float(math.hypot(pred[0], pred[1]))
        if r is None or not (math.isfinite(r) and r > 0.0):
            return dyaw_kf, bearing, range_m
        cam_fr = np.array([r * math.cos(bearing), r * math.sin(bearing), dyaw])
        cam = compose(compose(e_old, cam_fr), inverse(e_new))
        return (dyaw_kf, float(math.atan2(cam[1], cam[0])),
                None if range_m is None else max(float(math.hypot(cam[0], cam[1])), 1e-3))

    def _planar(self, v: Any) -> tuple[bool, float]:
        """Whether a verification's motion is a level camera's (module notes), and its tilt."""
        _, _, tilt = planar_motion(v.rotation, v.translation_dir)
        # (A planarity not computed, NaN, leaves the tilt limit alone to judge.)
        return not (tilt > self.max_tilt_rad or v.planarity_chi2 > self.planarity_bound), tilt

    def _level(self, image_id: int, v: Any) -> bool:
        """The detector's acceptance test (:class:`~robotd.forward.ForwardDetector` ``accept``):
        the verified motion of the current image against past image ``image_id`` is a level
        camera's, as verified or refitted in the floor plane (:func:`robotd.forward.planefit.fit_planar`:
        its inliers at least the verification's minimum and half of its inliers); and when
        the planar fit lies on a heading-bearing ridge, the graph's heading lies on it
        (:meth:`_settle`)."""
        self.tests += 1
        ok, tilt = self._planar(v)
        scan = self._scan(image_id, v) if self.planar_refit else None
        refit = None if scan is None else self._choose(scan, v, level=ok)
        if not ok and refit is None:
            self.not_planar += 1
            self._last_refused = (image_id, tilt, v.planarity_chi2)
            return False
        if scan is not None:
            t0 = time.thread_time()
            settled = self._settle(image_id, scan)
            self._add_cpu("ridge", t0)
            if settled is False:
                return False
            if isinstance(settled, tuple):
                rec = self._pending.setdefault(image_id, _Pending())
                rec.fit, rec.sigma_bearing_rad, rec.at_prior = settled[0], settled[1], True
            elif isinstance(settled, _Unsettled):  # the motion as chosen, its sigmas the ridge's
                rec = self._pending.setdefault(image_id, _Pending())
                rec.sigma_bearing_rad, rec.sigma_yaw_rad = settled.sigma_bearing_rad, settled.sigma_yaw_rad
        if refit is not None:
            self.refits += 1
            self.level_refits += ok
            rec = self._pending.setdefault(image_id, _Pending())
            if rec.fit is None:  # the ridge's fit, when settled there, stays the loop's motion
                rec.fit = refit
        return True

    def _scan(self, image_id: int, v: Any) -> tuple[PlanarFit, np.ndarray, np.ndarray] | None:
        """The motion of the current image against past image ``image_id`` fitted in the
        floor plane from all their matches (:func:`robotd.forward.planefit.fit_planar`, the
        heading searched around the verified motion's, the level motion's or both,
        :attr:`scan_centre`; the verified motion's without a level motion), with the matched
        pixels (old, new); None without a camera matrix or enough matches."""
        det = self.detector
        k = det.camera_matrix
        if k is None:
            return None
        t0 = time.thread_time()
        new_id = len(det) - 1 if self._image is None else self._image
        old, new = det.features_of(image_id), det.features_of(new_id)
        index = getattr(v, "match_index", None)
        if index is not None:  # the verification's matches (the same), not matched again
            p_old, p_new = matched_points(old, new, index)
        else:
            p_old, p_new = match_features(old, new, det.params.verify.ratio)
        self._add_cpu("match", t0)
        t0 = time.thread_time()
        verified, _, _ = planar_motion(v.rotation, v.translation_dir)
        level = float(getattr(v, "level_yaw_rad", math.nan)) if self.scan_centre != "verified" else math.nan
        if not math.isfinite(level) or (self.scan_centre == "both" and
                                        round(level / SCAN_STEP_RAD) == round(verified / SCAN_STEP_RAD)):
            centres = [verified]  # one scan: the two would scan the same lattice points
        else:
            centres = [level] if self.scan_centre == "level" else [verified, level]
        fit = None  # the better-supported scan, the first's on a tie
        # The scans share their common lattice headings (fit_planar_scans: each fit as
        # fit_planar gives it around its centre).
        for f in fit_planar_scans(p_old, p_new, k, centres, threshold_px=det.params.verify.ransac_threshold_px):
            if f is not None and (fit is None or f.n_inliers > fit.n_inliers):
                fit = f
        self._add_cpu("scan", t0)
        return None if fit is None else (fit, p_old, p_new)

    def _choose(self, scan: tuple[PlanarFit, np.ndarray, np.ndarray], v: Any,
                level: bool = False) -> tuple[PlanarFit, np.ndarray, np.ndarray] | None:
        """The planar fit ``scan`` as the loop's motion, with its inlier pixels (old, new);
        None when it keeps fewer than the verification's ``min_inliers`` or half of its
        inliers, or, with ``level`` (the verified motion passed the planarity test), no more
        of the matches than the verified motion brought into the plane."""
        fit, p_old, p_new = scan
        vp: VerifyParams = self.detector.params.verify
        k = self.detector.camera_matrix
        if k is None or fit.n_inliers < max(vp.min_inliers, 0.5 * v.n_inliers):
            return None
        if level:
            t0 = time.thread_time()
            dyaw, bearing, _ = planar_motion(v.rotation, v.translation_dir)
            n_level = int(planar_inliers(p_old, p_new, k, dyaw, bearing, threshold_px=vp.ransac_threshold_px).sum())
            self._add_cpu("level", t0)
            if fit.n_inliers <= n_level:
                return None
        return fit, p_old[fit.inliers], p_new[fit.inliers]

    def _prior_yaw(self, image_id: int) -> tuple[float, float] | None:
        """The camera's heading change from past image ``image_id``'s frame to the current
        image's that the pose graph predicts (:class:`HeadingGraph`: its odometry and floor
        loop edges) or else the odometry (the keyframes' poses on one chain), carried to the
        frames by their offsets, and its 1-sigma (the graph's; the odometry's: the growth of
        its heading variance between the two keyframes); None with neither."""
        cur = self._current
        if cur is None or image_id >= len(self._poses):
            return None
        e_new, pose_new, var_new, chain, kf_new, links = cur
        e_old = self._offsets[image_id]
        t0 = time.thread_time()
        graph = self.headings.relative(self._keyframe_ids[image_id], kf_new, upto=links)
        self._add_cpu("graph", t0)
        if graph is not None:
            return float(wrap_angle(graph[0] - e_old[2] + e_new[2])), graph[1]
        pose_old = self._poses[image_id]
        if pose_old is None or self._chains[image_id] != chain:
            return None
        yaw_kf = float(between(pose_old, pose_new)[2])  # the mount's yaw cancels
        yaw_fr = float(wrap_angle(yaw_kf - e_old[2] + e_new[2]))
        var_old = self._yaw_vars[image_id]
        sigma = math.sqrt(max(var_new - var_old, 0.0)) if var_new is not None and var_old is not None else 0.0
        return yaw_fr, sigma

    def _settle(self, image_id: int, scan: tuple[PlanarFit, np.ndarray, np.ndarray]
                ) -> tuple[tuple[PlanarFit, np.ndarray, np.ndarray], float] | _Unsettled | bool | None:
        """A planar fit on a heading-bearing ridge (module notes, :class:`RidgeParams`):
        None when ``scan``'s inlier profile is no ridge (half-width within the edge's heading
        sigma); else, with the graph's heading (:meth:`_prior_yaw`) on the ridge, the ridge's motion at that
        heading with its inlier pixels and the bearing's sigma along the ridge; False (the
        loop refused) with it off the ridge; without a graph or odometry heading, the bearing's
        sigma over the whole ridge and the heading's, its half-width (:class:`_Unsettled`)."""
        fit, p_old, p_new = scan
        rp = self.ridge
        k = self.detector.camera_matrix
        if k is None or len(fit.scan_inliers) == 0:
            return None
        lo, hi, on = ridge_headings(fit, rp.count_sigmas * math.sqrt(float(fit.scan_inliers.max())), rp.span)
        narrow = 0.5 * (hi - lo) <= rp.edge_sigma_yaw_rad
        if narrow and rp.narrow != "graph":
            return None
        vp: VerifyParams = self.detector.params.verify
        thr = vp.ransac_threshold_px

        prior = self._prior_yaw(image_id)
        if narrow:  # RidgeParams.narrow == "graph"
            if prior is None or rp.prior_gate_sigmas * prior[1] >= rp.edge_sigma_yaw_rad or \
                    abs(math.remainder(prior[0] - fit.dyaw_rad, math.tau)) > rp.prior_gate_sigmas * rp.edge_sigma_yaw_rad:
                return None
            lo = hi = prior[0]
            on = np.array([prior[0]])
        if prior is None:
            ends = fit_planar_fixed(p_old, p_new, k, [lo, hi], [False, False], threshold_px=thr)
            if ends[0] is None or ends[1] is None:
                return None
            spread = 0.5 * abs(math.remainder(ends[1].bearing_rad - ends[0].bearing_rad, math.tau))
            self.ridge_unsettled += 1
            sigma_b = math.hypot(fit.sigma_bearing_rad, spread) if math.isfinite(fit.sigma_bearing_rad) else spread
            # the heading anywhere on the ridge: its half-width, beside the bearing's spread
            return _Unsettled(float(sigma_b), 0.5 * float(hi - lo))
        yaw_p, sigma_p = prior
        gate = rp.prior_gate_sigmas * sigma_p
        old_kf = self._keyframe_ids[image_id]
        if rp.span == "run":
            off = not lo - gate <= yaw_p <= hi + gate
        else:  # near one of the headings the counts cannot tell from the best (within half a scan step)
            step = float(np.median(np.diff(fit.scan_yaw_rad))) if len(fit.scan_yaw_rad) > 1 else 0.0
            off = not bool(np.any(np.abs(on - yaw_p) <= gate + 0.5 * step + 1e-12))
        if off:
            self.ridge_refused += 1
            log.info("forward loop to keyframe %d refused: its motion lies on a heading-bearing ridge "
                     "(%.1f to %.1f deg) and the graph's heading change %.1f deg (sigma %.2f) lies off it",
                     old_kf, math.degrees(lo), math.degrees(hi), math.degrees(yaw_p), math.degrees(sigma_p))
            return False
        yaw = min(max(yaw_p, lo), hi)
        # the fit there and, 0.5 deg either side, the two whose bearings give the ridge's slope (below)
        best, *side = fit_planar_fixed(p_old, p_new, k, [yaw, yaw - rp.slope_step_rad, yaw + rp.slope_step_rad],
                                       [True, False, False], threshold_px=thr)
        if best is None or best.n_inliers < vp.min_inliers:
            self.ridge_refused += 1
            log.info("forward loop to keyframe %d refused: on a heading-bearing ridge, too few matches at the "
                     "graph's heading change %.1f deg", old_kf, math.degrees(yaw_p))
            return False
        # How fast the ridge's bearing moves with the heading, there: the prior's heading
        # sigma becomes the bearing's along the ridge.
        slope = 0.0
        if side[0] is not None and side[1] is not None:
            slope = math.remainder(side[1].bearing_rad - side[0].bearing_rad, math.tau) / (2 * rp.slope_step_rad)
        sig_fixed = best.sigma_bearing_rad if math.isfinite(best.sigma_bearing_rad) else 0.0
        sigma_b = float(math.hypot(sig_fixed, slope * sigma_p))
        self.ridge_settled += 1
        self.narrow_settled += narrow
        log.info("forward loop to keyframe %d on a heading-bearing ridge (%.1f to %.1f deg, fit %.1f deg bearing "
                 "%.1f): taken at the graph's heading change %.1f deg (sigma %.2f): bearing %.1f deg, "
                 "%.1f deg of bearing per deg of heading", old_kf, math.degrees(lo), math.degrees(hi),
                 math.degrees(fit.dyaw_rad), math.degrees(fit.bearing_rad), math.degrees(yaw_p),
                 math.degrees(sigma_p), math.degrees(best.bearing_rad), slope)
        return (best, p_old[best.inliers], p_new[best.inliers]), sigma_b

    def counters(self) -> dict[str, Any]:
        total = np.asarray(self.total_ms) if self.total_ms else np.zeros(1)
        cpu = np.asarray(self.cpu_ms) if self.cpu_ms else np.zeros(1)
        verify = np.asarray(self.verify_ms) if self.verify_ms else np.zeros(1)
        feat = np.asarray(self.features_ms) if self.features_ms else np.zeros(1)
        return {"forward_frames": self.frames, "forward_images": self.images,
                "forward_unsynced": self.unsynced, "forward_loops": self.loops,
                "forward_late": self.late, "forward_frames_evicted": self.evicted,
                "forward_frames_without_odometry": self.no_offset,
                "forward_frame_offset_ms_max": round(self.frame_offset_ms_max, 1),
                "forward_not_planar": self.not_planar, "forward_planar_refits": self.refits,
                "forward_level_refits": self.level_refits,
                "forward_ridge_settled": self.ridge_settled, "forward_ridge_refused": self.ridge_refused,
                "forward_ridge_unsettled": self.ridge_unsettled, "forward_narrow_settled": self.narrow_settled,
                "forward_failed_verification": self.rejected_geometry,
                "forward_deferred": self.deferred, "forward_deferred_inline": self.deferred_inline,
                "forward_deferred_across": self.deferred_across,
                "forward_deferred_at_end": self.deferred_at_end, "forward_deferred_waiting": len(self._deferred),
                "forward_deferred_wait_max": self.deferred_wait_max,
                "forward_deferred_forced": self.deferred_forced,
                "forward_checks_max": self.checks_max, "forward_checks_over_budget": self.checks_over,
                "forward_vocabulary": len(self.detector.vocabulary),
                "forward_restored_images": self.restored, "forward_store_errors": self.store_errors,
                "forward_ms_median": round(float(np.median(total)), 2),
                "forward_ms_p99": round(float(np.percentile(total, 99)), 2),
                "forward_cpu_ms_median": round(float(np.median(cpu)), 2),
                "forward_cpu_ms_p99": round(float(np.percentile(cpu, 99)), 2),
                "forward_verify_ms_median": round(float(np.median(verify)), 2),
                "forward_verify_ms_p99": round(float(np.percentile(verify, 99)), 2),
                "forward_verify_ms_total": round(float(np.sum(verify)), 1),
                "forward_features_ms_median": round(float(np.median(feat)), 2),
                "forward_ms_total": round(float(np.sum(total)), 1),
                **self._part_counters(cpu)}

    def _part_counters(self, cpu: np.ndarray) -> dict[str, Any]:
        """The stage's parts in CPU time (:attr:`part_cpu_ms`): each one's p99 and total over
        the run, and the parts of the three keyframes that cost the detector the most CPU
        (those that make its p99), in ms."""
        out: dict[str, Any] = {}
        parts = {k: np.asarray(v) for k, v in self.part_cpu_ms.items() if len(v) == len(self.cpu_ms) and len(v)}
        for k, a in parts.items():
            out[f"forward_{k}_cpu_ms_p99"] = round(float(np.percentile(a, 99)), 2)
            out[f"forward_{k}_cpu_ms_total"] = round(float(np.sum(a)), 1)
        if parts:
            top = np.argsort(-cpu)[:3] if len(self.cpu_ms) else np.zeros(0, np.int64)
            out["forward_cpu_top_keyframes"] = [
                {"cpu_ms": round(float(cpu[i]), 1), "verify_ms": round(float(self.verify_ms[i]), 1),
                 **{k: round(float(a[i]), 1) for k, a in parts.items()}} for i in top]
        return out
