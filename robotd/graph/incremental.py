"""Live pose graph: one iSAM2 update per keyframe (Kaess et al., IJRR 2012), a loop edge
under the batch solver's robust kernel (DCS when the full solve is GNC), and a full batch
re-solve on demand.

Kept in step with the full solve: :meth:`IncrementalGraph.resolve` restarts iSAM2 from the
batch result, and when that was a GNC solve, without the loop edges GNC rejected (weight
below one half), so that iSAM2's later updates build on the same inliers instead of
letting a rejected loop pull again through its kernel. The rejected loops stay in
:attr:`IncrementalGraph.graph`: the next full solve judges them again, with everything
learnt since.

Should iSAM2 give up (GTSAM raises an indeterminate system for an ill-conditioned
update, e.g. under Cholesky over a long chain without loops), the graph is not lost:
:meth:`IncrementalGraph._recover` re-solves the whole graph it keeps (every keyframe and
every loop in it, :func:`optimize_batch`), rebuilds iSAM2 from that solution by QR,
logs it and counts it (:attr:`IncrementalGraph.isam_failures`), and the update goes on.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
from collections.abc import Iterable, Sequence
from typing import Any
from dataclasses import dataclass, field

import gtsam
import numpy as np

from robotd.base.errors import GraphError
from robotd.base.geometry import between, compose, inverse
from robotd.graph.batch import BatchParams, BatchResult, optimize_batch
from robotd.graph.bias import BiasEdge, WindowChain, bias_edge, scale_key, scale_prior_factor, span_factors
from robotd.graph.factors import anchor_factor, between_factor, factor_graph, from_values, to_values
from robotd.graph.model import Edge, PoseGraph, make_edge

log = logging.getLogger(__name__)


#: What :attr:`IncrementalParams.odometry_model` takes.
ODOMETRY_MODELS = ("independent", "bias_window", "bias_scale_window")

#: The segment number of the run's scale variable (:func:`robotd.graph.bias.scale_key`):
#: one for the whole graph, the base's scale errors being the same before and after a carry.
SCALE_SEGMENT = 0


@dataclass(frozen=True, slots=True)
class IncrementalParams:
    """Parameters of :class:`IncrementalGraph`.

    relinearize_threshold: iSAM2 relinearises a variable whose update exceeds this
        (m and rad), default 1e-4. A pose linearised 1 mrad away from its estimate puts a
        loop closed metres away millimetres off, more than the floor's edges now measure:
        at 1e-3 and 1e-2 the gate refused true loops across a relocalised segment's
        re-driven ground (docs/odometry.md, Known limits).
    relinearize_skip: check for relinearisation every this many updates, default 1.
    loop_updates: extra iSAM2 iterations after a loop edge (it moves many poses), default 5 (2 left 0.2 m errors on a 24-pose ring).
    batch: parameters of :meth:`IncrementalGraph.resolve` and of the loop edges' kernel
        (iSAM2 itself always uses each edge's full information).
    loop_spacing: loop edges enter the graph from one keyframe in this many (by id),
        spread in time by as much (0: every loop enters); see
        :meth:`IncrementalGraph.add_loop`. Default 10 (1.5 m of driving at 15 cm).
    loops_per_keyframe: at most this many loop edges per keyframe (by its newer end) enter
        the graph (0: no limit), default 2.
    factorization: iSAM2's ``"QR"`` (default) or ``"CHOLESKY"``. Over a long drive with no
        loop the newest pose's marginal information is the small difference of large
        edge informations; Cholesky squares that condition number and GTSAM raises an
        indeterminate system after a few thousand keyframes (a 4762-keyframe chain of the
        office drive's own edges), where QR goes on.
    fold: after a full solve (:meth:`IncrementalGraph.resolve`), iSAM2 is rebuilt with
        only the keyframes it needs as variables: the anchors, both ends of every loop in
        it, the newest ``fold`` keyframes and one in ``fold`` along each odometry chain;
        the others are folded into their chain's odometry (one edge between the kept
        keyframes, its delta and covariance composed from the edges between them) and
        follow the kept keyframe before them (see :meth:`IncrementalGraph.pose`). Each
        variable costs iSAM2 about 4-6 KB; the full solve and the map keep every keyframe.
        1: every keyframe stays a variable. Default 10.
    loops_per_place: at most this many loops in iSAM2 end at each older place: a loop is
        left out (as by ``loop_spacing``) when that many loops already in iSAM2 have their
        older end within ``loop_spacing`` ids of its own. Over ground driven lap after lap
        each lap then ties to a pass not yet tied there (the previous one) instead of
        every pass to every earlier one, which fills iSAM2's Bayes tree in (its memory
        grows with the square of the passes): on 4,000 keyframes of repeated office laps
        the graph alone held 18.7 MB instead of 29.7 (``bench/bench_graph_memory.py``);
        the demo's loops and errors as without it. Default 1; 0: no such limit.
    tie_to: which earlier pass a later pass's loops in iSAM2 tie it to. ``"previous"``
        (default): as ``loops_per_place`` admits them, the pass before (passes chained
        place by place: a lattice of laps x places, whose Bayes tree's separators hold a
        pose of every pass, so each lap costs more than the one before). ``"first"``: a
        loop enters only when its older end is on a first pass, not within
        ``loop_spacing`` ids of the newer end of a loop in iSAM2 (``loops_per_place`` is
        then not applied): every pass ties to the ground as first mapped, a star rather
        than a lattice. Measured (``bench/bench_graph_memory.py``, 10,000 keyframes of
        synthetic office laps with noisy odometry, the graph alone): 97.1 MB against 52.5
        with ``"previous"`` (iSAM2's incremental ordering still fills the tree in), the
        last full solve 1.9 mm APE RMS from the truth against 2.7; so not the default.
    odometry_model: ``"independent"`` (default): every odometry edge its own factor with
        its covariance. ``"bias_window"``: an edge given with the filter's bias terms
        (:meth:`IncrementalGraph.add_keyframe`'s ``bias``) shares the gyro bias with its
        neighbours: ``window_edges`` consecutive ones become one
        :func:`robotd.graph.bias.bias_window_factor` with a bias variable at the window's
        start, the windows chained; the full solve is refined with them and the fold keeps
        them (docs/concepts.md, "The bias windows in the daemon"). ``"bias_scale_window"``:
        the same windows, and every one of them (and every fold span) also shares one
        variable of the base's relative scale errors, the wheels' distance and the gyro's
        rate (:func:`robotd.graph.bias.scale_jacobian`), with the prior ``scale_sigmas``:
        a wheel scale a few tenths of a percent off its calibration is then estimated by
        the loops instead of stretching every edge that lacks a visual step.
    window_edges: the edges of a bias window, default 10.
    scale_sigmas: ``(wheel, gyro)`` 1-sigma relative scale errors of the prior on the scale
        variable (``"bias_scale_window"``), default 0.3 % and 0.02 %.
    """

    relinearize_threshold: float = 1e-4
    relinearize_skip: int = 1
    loop_updates: int = 5
    batch: BatchParams = field(default_factory=BatchParams)
    loop_spacing: int = 10
    loops_per_keyframe: int = 2
    factorization: str = "QR"
    fold: int = 10
    loops_per_place: int = 1
    tie_to: str = "previous"
    odometry_model: str = "independent"
    window_edges: int = 10
    scale_sigmas: tuple[float, float] = (0.003, 0.0002)

    def __post_init__(self) -> None:
        if self.factorization not in ("QR", "CHOLESKY"):
            raise ValueError(f"factorization must be 'QR' or 'CHOLESKY', not {self.factorization!r}")
        if self.fold < 1:
            raise ValueError(f"fold must be >= 1, got {self.fold}")
        if self.loops_per_place < 0:
            raise ValueError(f"loops_per_place must be >= 0, got {self.loops_per_place}")
        if self.tie_to not in ("previous", "first"):
            raise ValueError(f"tie_to must be 'previous' or 'first', not {self.tie_to!r}")
        if self.odometry_model not in ODOMETRY_MODELS:
            raise ValueError(f"odometry_model must be one of {', '.join(ODOMETRY_MODELS)}, not {self.odometry_model!r}")
        if self.window_edges < 1:
            raise ValueError(f"window_edges must be >= 1, got {self.window_edges}")
        if len(self.scale_sigmas) != 2 or not all(s > 0 for s in self.scale_sigmas):
            raise ValueError(f"scale_sigmas must be two positive sigmas, got {self.scale_sigmas}")

    @property
    def bias_terms(self) -> bool:
        """Whether the model takes the edges' bias terms (a bias window model)."""
        return self.odometry_model != "independent"

    @property
    def scale_segment(self) -> int | None:
        """The scale variable's segment with ``"bias_scale_window"``, else None."""
        return SCALE_SEGMENT if self.odometry_model == "bias_scale_window" else None


class IncrementalGraph:
    """A pose graph that grows one keyframe at a time.

    The first keyframe is fixed at the pose it is given; every later one comes with an
    odometry edge from an existing keyframe, and its initial guess is that keyframe's
    current estimate composed with the edge. :attr:`graph` keeps the odometry guesses, so
    :meth:`resolve` can start LAGO from scratch.
    """

    def __init__(self, params: IncrementalParams = IncrementalParams()) -> None:
        self.params = params
        self.graph = PoseGraph()
        b = params.batch
        self._kernel = b.loop_kernel()
        self.rejected_loops: set[int] = set()  # edge indices the last GNC solve left out
        self.held_loops = 0  # loop edges left out (add_loop)
        self._newest_held: Edge | None = None  # the last loop left out, if none entered since
        self._in_isam: list[tuple[int, int]] = []  # (newer, older) ends of the newest keyframe's loops in iSAM2
        self._older_ends: list[int] = []  # sorted older ends of the loops admitted (loops_per_place)
        self._newer_ends: list[int] = []  # sorted newer ends of the loops admitted (tie_to "first")
        self.factorization = params.factorization  # iSAM2's; QR after a failure under Cholesky
        self.isam_failures = 0  # iSAM2 updates that raised, each recovered (_recover)
        self._isam = self._new_isam()
        self._version = 0  # bumped by every change of the estimate
        self._cached: tuple[int, np.ndarray, np.ndarray] | None = None
        # odometry_model "bias_window": the edges' bias terms by edge index, the live windows
        self._bias: dict[int, BiasEdge] = {}
        self._windows = WindowChain(params.window_edges, segment=params.scale_segment)
        self._scale_in = False  # the scale variable is in iSAM2 (odometry_model "bias_scale_window")
        self._scale_value = np.zeros(2)  # its estimate at the last full solve
        self.bias_windows = 0  # windows closed by add_keyframe
        self._clear_fold()

    def _clear_fold(self) -> None:
        """No keyframe folded: every keyframe of :attr:`graph` is an iSAM2 variable."""
        # Folded keyframes (sorted ids), each: the kept keyframe it follows, its pose in that
        # keyframe's frame (from the full solve) and the covariance of that relative pose
        # (the chain's odometry composed, in the folded keyframe's own tangent space).
        self._fold_ids = np.zeros(0, np.int64)
        self._fold_anchor = np.zeros(0, np.int64)
        self._fold_rel = np.zeros((0, 3))
        self._fold_cov = np.zeros((0, 3, 3))

    def _folded(self, keyframe_id: int) -> int | None:
        """The row of a folded keyframe in the fold arrays, None for an iSAM2 variable."""
        ids = self._fold_ids
        i = int(np.searchsorted(ids, keyframe_id))
        return i if i < len(ids) and int(ids[i]) == int(keyframe_id) else None

    def _reexpress(self, from_id: int, to_id: int, delta: np.ndarray, information: np.ndarray
                   ) -> tuple[int, int, np.ndarray, np.ndarray] | None:
        """An edge between keyframes, either folded, as the edge between the iSAM2 variables
        they follow (``a (+) r`` for a folded end: ``r`` composed into the delta, its
        covariance added through the adjoint); None when both follow the same variable."""
        d = np.asarray(delta, float)
        i, j = self._folded(from_id), self._folded(to_id)
        if i is None and j is None:
            return from_id, to_id, d, np.asarray(information, float)
        cov = np.linalg.inv(information)
        if i is not None:  # from = a (+) r: a -> to is r (+) d
            ad = gtsam.Pose2(*d).inverse().AdjointMap()
            cov = ad @ self._fold_cov[i] @ ad.T + cov
            d = compose(self._fold_rel[i], d)
            from_id = int(self._fold_anchor[i])
        if j is not None:  # to = b (+) s: from -> b is d (+) s^-1
            s = self._fold_rel[j]
            ad = gtsam.Pose2(*s).AdjointMap()
            cov = ad @ (cov + self._fold_cov[j]) @ ad.T
            d = compose(d, inverse(s))
            to_id = int(self._fold_anchor[j])
        if from_id == to_id:
            return None
        info = np.linalg.inv(cov)
        return from_id, to_id, d, (info + info.T) / 2

    def _update(self, factors: gtsam.NonlinearFactorGraph | None = None,
                values: gtsam.Values | None = None, remove: list[int] | None = None) -> gtsam.ISAM2Result | None:
        """One iSAM2 step with the new ``factors`` and ``values`` (none: one more
        relinearisation), the factors of indices ``remove`` taken out. The factors' edges
        are already in :attr:`graph`: should iSAM2 raise, :meth:`_recover` rebuilds it from
        the whole graph, these included, and None is returned."""
        try:
            if factors is None or values is None:
                res = self._isam.update()
            elif remove:
                res = self._isam.update(factors, values, remove)
            else:
                res = self._isam.update(factors, values)
        except RuntimeError as exc:  # GTSAM's IndeterminantLinearSystemException, among others
            self._recover(exc)
            return None
        self._version += 1
        return res

    def _recover(self, exc: Exception) -> None:
        """iSAM2 raised: re-solve the whole graph (every keyframe, every loop it holds; the
        robust batch solve from scratch, or the odometry poses should that fail too),
        rebuild iSAM2 from that solution with every keyframe a variable (nothing folded
        until the next :meth:`resolve`), by QR from now on, and count and log it. The
        graph loses nothing. GraphError if iSAM2 cannot be rebuilt even so."""
        self.isam_failures += 1
        detail = next((line for line in str(exc).splitlines() if line.strip()), type(exc).__name__).strip()
        rejected = self.rejected_loops
        try:
            result = optimize_batch(self.graph, self.params.batch)
            ids, poses, how = result.ids, result.poses, "a full solve"
            b = self.params.batch
            if b.robust and b.kernel == "gnc":
                loops = np.flatnonzero(self.graph.is_loop).tolist()
                rejected = {n for n, w in zip(loops, result.loop_weights) if w < 0.5}
        except RuntimeError:
            ids, poses, how = self.graph.ids, self.graph.poses(), "the odometry poses (the full solve failed too)"
        was = self.factorization
        self.factorization = "QR"
        self._clear_fold()
        self._isam = self._new_isam()
        try:
            self._isam.update(*self._whole_graph(rejected, ids, poses))
        except RuntimeError as again:
            raise GraphError(f"iSAM2 failed ({detail}) and could not be rebuilt from the graph: "
                             f"{str(again).strip().splitlines()[0] if str(again).strip() else again}") from again
        self.rejected_loops = rejected
        self._version += 1
        log.warning("pose graph: iSAM2 failed at %d keyframes (%s); rebuilt from %s%s (%d failure%s so far)",
                    len(self.graph), detail, how, ", QR from now on" if was != "QR" else "",
                    self.isam_failures, "" if self.isam_failures == 1 else "s")

    def _new_isam(self) -> gtsam.ISAM2:
        p = gtsam.ISAM2Params()
        p.setRelinearizeThreshold(self.params.relinearize_threshold)
        p.relinearizeSkip = self.params.relinearize_skip
        p.setFactorization(self.factorization)
        self._scale_in = False
        return gtsam.ISAM2(p)

    def _add_scale(self, fg: gtsam.NonlinearFactorGraph, values: gtsam.Values, whole: bool = False) -> None:
        """With ``"bias_scale_window"``: the scale variable (at the last full solve's
        estimate, zero before one) and its prior into ``fg`` and ``values``: for a whole
        graph (``whole``) always, for an update unless iSAM2 has it already."""
        seg = self.params.scale_segment
        if seg is None or (self._scale_in and not whole) or values.exists(scale_key(seg)):
            return
        fg.add(scale_prior_factor(seg, self.params.scale_sigmas))
        values.insert(scale_key(seg), self._scale_value.copy())
        self._scale_in = True

    def scale_estimate(self) -> np.ndarray | None:
        """iSAM2's estimate of the base's relative scale errors ``(wheel, gyro)`` (the
        calibration's distance and gyro rate are too large by these fractions), None without
        the scale variable (or before the first window)."""
        seg = self.params.scale_segment
        if seg is None or not self._scale_in:
            return None
        return np.asarray(self._isam.calculateEstimateVector(scale_key(seg)), float)

    def add_first(self, keyframe_id: int, pose: Iterable[float] = (0.0, 0.0, 0.0)) -> None:
        """Start the graph with keyframe ``keyframe_id`` fixed at ``pose`` (m, m, rad)."""
        if len(self.graph):
            raise GraphError("add_first on a graph that already has keyframes")
        self.graph.add_pose(keyframe_id, pose)
        self.graph.fix(keyframe_id)
        fg = gtsam.NonlinearFactorGraph()
        fg.add(anchor_factor(keyframe_id, self.graph.pose(keyframe_id)))
        self._update(fg, to_values(np.array([keyframe_id]), self.graph.pose(keyframe_id)[None]))

    def add_keyframe(self, keyframe_id: int, from_id: int, delta: Iterable[float],
                     information: np.ndarray, bias: Sequence[Any] | None = None) -> np.ndarray:
        """Add a keyframe with its odometry edge from ``from_id`` (delta ``(dx_m, dy_m,
        dyaw_rad)`` in ``from_id``'s frame, ``(3, 3)`` information, the edge's marginal);
        one iSAM2 update. ``bias``: the edge's bias terms
        (:class:`robotd.odometry.history.EdgeBiasTerms`), used with ``odometry_model``
        ``"bias_window"`` (:class:`robotd.graph.bias.WindowChain`). Returns the new
        keyframe's estimated pose ``(3,)``."""
        if from_id not in self.graph:
            raise GraphError(f"odometry edge to keyframe {keyframe_id} from unknown keyframe {from_id}")
        guess = compose(self.pose(from_id), np.asarray(delta, dtype=float))
        index = self.graph.edge_count
        self.graph.add_pose(keyframe_id, guess)
        edge = self.graph.add_edge(from_id, keyframe_id, delta, information, "odometry")
        fg = gtsam.NonlinearFactorGraph()
        live = self._reexpress(edge.from_id, edge.to_id, edge.delta, edge.information)
        assert live is not None  # the new keyframe is not folded
        values = to_values(np.array([keyframe_id]), guess[None])
        windows = self._windows
        be = None
        if bias is not None and self.params.bias_terms:
            be = bias_edge(edge.from_id, edge.to_id, edge.delta, bias)
            self._bias[index] = be
        if be is None or live[0] != edge.from_id or not windows.continues(be):
            windows.reset()
        closed = None if be is None or live[0] != edge.from_id else windows.offer(be)
        if closed is not None:
            fg, bias_values, remove = closed
            values.insert(bias_values)
            self._add_scale(fg, values)
            self.bias_windows += 1
            self._update(fg, values, remove)
        else:
            fg.add(between_factor(edge if live[0] == edge.from_id else make_edge(*live, "odometry")))
            res = self._update(fg, values)
            if res is not None and windows.open and windows.open[-1][0] is be:  # (None: rebuilt whole)
                windows.placed(int(res.getNewFactorsIndices()[0]))
        return self.pose(keyframe_id)

    def add_loop(self, from_id: int, to_id: int, delta: Iterable[float],
                 information: np.ndarray) -> bool:
        """Add a loop edge to :attr:`graph` and, under the robust kernel, to iSAM2, unless
        iSAM2 holds loops enough near it: every later pass over the same ground loops to
        every earlier one, and all those edges in iSAM2 fill its Bayes tree in (its memory
        and each update's time grow with the passes). Such an edge is left out (of the
        graph, iSAM2 and the full solve of :meth:`resolve`; the map stores it, and
        :attr:`held_loops` counts it) when the last loop to enter came from a keyframe
        less than ``loop_spacing`` ids before its newer end, or from that same keyframe
        but with an older end less than ``loop_spacing`` ids from its own (one
        keyframe's loops are spread in time), or when its newer end has
        ``loops_per_keyframe`` loops in already, or its older end's place has
        ``loops_per_place`` (an older end within ``loop_spacing`` ids of its own). Loops come best first (the detector's
        order), so a keyframe's first loops enter. GraphError for a bad edge either way.
        Returns whether it entered."""
        edge = self.graph.check_edge(from_id, to_id, delta, information, "loop")
        if not self._admit_loop(edge.from_id, edge.to_id):
            self.held_loops += 1
            self._newest_held = edge
            return False
        self._newest_held = None
        self.graph.add_edges([edge])
        live = self._reexpress(edge.from_id, edge.to_id, edge.delta, edge.information)
        if live is None:  # both ends follow one iSAM2 variable: the full solve has it
            return True
        fg = gtsam.NonlinearFactorGraph()
        fg.add(between_factor(edge if live[:2] == (edge.from_id, edge.to_id) else make_edge(*live, "loop"),
                              self._kernel))
        self._update(fg, gtsam.Values())
        for _ in range(self.params.loop_updates):
            self._update()
        return True

    def _admit_loop(self, a: int, b: int) -> bool:
        """Whether a loop between keyframes ``a`` and ``b`` enters iSAM2 (see
        :meth:`add_loop`); records it if so."""
        newer, older = max(a, b), min(a, b)
        s, cap = self.params.loop_spacing, self.params.loops_per_keyframe
        last = self._in_isam[-1][0] if self._in_isam else None
        if last is not None and newer != last:
            if s and abs(newer - last) < s:
                return False
            self._in_isam = []  # a new keyframe's loops
        if cap and len(self._in_isam) >= cap:
            return False
        if s and any(abs(o - older) < s for _n, o in self._in_isam):
            return False
        if self.params.tie_to == "first":
            ne, w = self._newer_ends, max(s, 1)
            if bisect.bisect_left(ne, older + w) - bisect.bisect_right(ne, older - w) > 0:
                return False  # the older end was itself tied back: not a first pass
            bisect.insort(ne, newer)
        elif self.params.loops_per_place:
            ends = self._older_ends
            near = bisect.bisect_left(ends, older + max(s, 1)) - bisect.bisect_right(ends, older - max(s, 1))
            if near >= self.params.loops_per_place:
                return False
            bisect.insort(ends, older)
        self._in_isam.append((newer, older))
        return True

    def loop_chi2(self, from_id: int, to_id: int, delta: Iterable[float],
                  information: np.ndarray, *, joint: bool = False) -> float:
        """Mahalanobis distance squared of a measured loop ``from_id -> to_id`` against the
        graph's prediction, dimensionless: the innovation ``e = log(predicted^-1 measured)``
        with covariance ``Ad P_from Ad^T + P_to + information^-1`` (the two marginals from
        iSAM2, their correlation left out: ``S`` is then larger, the test more lenient).

        ``joint``: with the two poses' correlation, from iSAM2's joint marginal ``[[P_from,
        C], [C^T, P_to]]``: ``S = A J A^T + information^-1`` with ``A = [-Ad, I]``, the
        covariance of the relative pose itself. Where the two poses share most of their
        uncertainty (a relocalised segment and the keyframes it was placed by: each pose's
        own marginal then carries the whole map's drift from the first keyframe, the
        relative pose little of it) the marginals alone overstate ``S`` many times, and a
        look-alike a few centimetres off passes. It costs one Bayes-tree query more than the
        two marginals (0.1-0.7 ms on the office demo's graphs). With either keyframe folded
        (:attr:`IncrementalParams.fold`) the two marginals are used, as without ``joint``.
        Should iSAM2 raise on the marginals, it is rebuilt (:meth:`_recover`) and asked again."""
        try:
            return self._loop_chi2(from_id, to_id, delta, information, joint)
        except RuntimeError as exc:
            self._recover(exc)
            return self._loop_chi2(from_id, to_id, delta, information, joint)

    def _loop_chi2(self, from_id: int, to_id: int, delta: Iterable[float], information: np.ndarray,
                   joint: bool) -> float:
        pa, pb = self._pose2(from_id), self._pose2(to_id)
        predicted = pa.between(pb)
        d = [float(v) for v in delta]
        e = gtsam.Pose2.Logmap(predicted.between(gtsam.Pose2(d[0], d[1], d[2])))
        ad = predicted.inverse().AdjointMap()
        folded = self._folded(from_id) is not None or self._folded(to_id) is not None
        if joint and int(from_id) != int(to_id) and not folded:
            keys = gtsam.KeyVector([int(from_id), int(to_id)])
            j = np.asarray(self._isam.jointMarginalCovariance(keys).fullMatrix(), dtype=float)
            a = np.hstack([-ad, np.eye(3)])
            cov = a @ j @ a.T + np.linalg.inv(information)
        else:
            cov = (ad @ self.marginal_covariance(from_id) @ ad.T
                   + self.marginal_covariance(to_id) + np.linalg.inv(information))
        return float(e @ np.linalg.solve(cov, e))

    def add_segment(self, keyframe_id: int, pose: Iterable[float]) -> None:
        """Start a new trajectory segment at ``keyframe_id`` without an odometry edge (the
        chain was broken: the robot was carried). iSAM2 holds it at ``pose`` (its own frame)
        until :meth:`attach` ties the segment to the rest; in a full solve the segment, a
        component without a fixed vertex, is anchored at its smallest id, this one."""
        if keyframe_id in self.graph:
            raise GraphError(f"keyframe {keyframe_id} is already in the graph")
        self.graph.add_pose(keyframe_id, pose)
        fg = gtsam.NonlinearFactorGraph()
        fg.add(anchor_factor(keyframe_id, self.graph.pose(keyframe_id)))
        self._update(fg, to_values(np.array([keyframe_id]), self.graph.pose(keyframe_id)[None]))

    def add_fixed(self, keyframe_id: int, pose: Iterable[float]) -> None:
        """Add a keyframe held at ``pose`` (an earlier run's optimised pose in the map frame),
        with no edge yet; loops to it are added with :meth:`add_loop` or :meth:`attach`."""
        if keyframe_id in self.graph:
            raise GraphError(f"keyframe {keyframe_id} is already in the graph")
        self.graph.add_pose(keyframe_id, pose)
        self.graph.fix(keyframe_id)
        fg = gtsam.NonlinearFactorGraph()
        fg.add(anchor_factor(keyframe_id, self.graph.pose(keyframe_id)))
        self._update(fg, to_values(np.array([keyframe_id]), self.graph.pose(keyframe_id)[None]))

    def attach(self, segment_ids: Iterable[int], transform: Iterable[float],
               loops: Iterable[tuple[int, int, np.ndarray, np.ndarray]]) -> None:
        """Relocalise a segment: move its keyframes (``segment_ids``) by ``transform`` (their
        own frame in the graph's frame, ``(3,)``), let go of their anchors, add ``loops``
        (``(from_id, to_id, delta (3,), information (3, 3))``, under the robust kernel) that
        tie them to the rest, and rebuild iSAM2 from the whole graph at the moved estimate."""
        t = np.asarray(transform, dtype=float).reshape(3)
        moved = {int(k) for k in segment_ids}
        ids, est = self.estimate()
        for n, kid in enumerate(ids):
            if int(kid) in moved:
                est[n] = compose(t, est[n])
                self.graph.set_pose(int(kid), compose(t, self.graph.pose(int(kid))))
                self.graph.unfix(int(kid))
        for from_id, to_id, delta, info in loops:
            self.graph.add_edge(from_id, to_id, delta, info, "loop")
        self._clear_fold()  # every keyframe a variable again, until the next full solve
        isam = self._new_isam()
        try:
            isam.update(*self._whole_graph(self.rejected_loops, ids, est))
            for _ in range(self.params.loop_updates):
                isam.update()
        except RuntimeError as exc:  # as for any update: the whole graph re-solved (_recover)
            self._isam = isam
            self._recover(exc)
            return
        self._isam = isam
        self._version += 1

    def stats(self) -> dict[str, int]:
        """The graph's size, for the memory benchmark: its edges (``edges``, ``loops``), the
        loops :meth:`add_loop` left out (``held_loops``), the factors iSAM2 holds
        (``factors``), its Bayes tree's cliques (``cliques``), the non-zero entries of the
        tree's conditionals (``tree_nnz``, 8 bytes each; each clique also caches a dense
        factor on its separator, not counted here, which is what grows when loops between
        many passes fill the tree in) and the separator marginals it keeps cached from
        :meth:`marginal_covariance` (``cached_marginals``)."""
        return {"edges": self.graph.edge_count, "loops": self.graph.loop_count,
                "held_loops": self.held_loops,
                "factors": int(self._isam.getFactorsUnsafe().nrFactors()), "cliques": int(self._isam.size()),
                "tree_nnz": int(self._isam.treeNnz()),
                "cached_marginals": int(self._isam.numCachedSeparatorMarginals()),
                "folded": len(self._fold_ids)}

    def _pose2(self, keyframe_id: int) -> gtsam.Pose2:
        i = self._folded(keyframe_id)
        if i is None:
            return self._isam.calculateEstimatePose2(int(keyframe_id))
        return self._isam.calculateEstimatePose2(int(self._fold_anchor[i])).compose(gtsam.Pose2(*self._fold_rel[i]))

    def pose(self, keyframe_id: int) -> np.ndarray:
        """The current estimate of one keyframe, ``(3,)`` (m, m, rad): iSAM2's, or for a
        folded keyframe (:attr:`IncrementalParams.fold`) the kept keyframe's before it on
        its chain composed with its pose relative to that one at the last full solve."""
        p = self._pose2(keyframe_id)
        return np.array([p.x(), p.y(), p.theta()])

    def marginal_covariance(self, keyframe_id: int) -> np.ndarray:
        """iSAM2's marginal covariance of one keyframe, ``(3, 3)``, in the pose's own tangent
        space (x, y along its axes in m^2, yaw in rad^2; :func:`robotd.graph.covariance.tangent_to_world`
        moves it to the map's axes). A folded keyframe's: the kept keyframe's it follows,
        moved through the relative pose's adjoint, plus the chain's odometry covariance
        from it (larger than the full graph's, which also holds it from the next one)."""
        i = self._folded(keyframe_id)
        if i is None:
            return np.asarray(self._isam.marginalCovariance(int(keyframe_id)), dtype=float)
        ad = gtsam.Pose2(*self._fold_rel[i]).inverse().AdjointMap()
        return np.asarray(ad @ self._isam.marginalCovariance(int(self._fold_anchor[i])) @ ad.T + self._fold_cov[i])

    def joint_marginal_covariance(self, a: int, b: int) -> np.ndarray:
        """iSAM2's joint marginal covariance ``(6, 6)`` of two keyframes that are variables
        (not folded), each in its own tangent space as :meth:`marginal_covariance`."""
        keys = gtsam.KeyVector([int(a), int(b)])
        return np.asarray(self._isam.jointMarginalCovariance(keys).fullMatrix(), dtype=float)

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """Every keyframe's current estimate: ``(ids (N,), poses (N, 3))`` (copies; computed
        once per change of the graph, which the mapped-ground test asks for at every
        keyframe)."""
        c = self._cached
        if c is None or c[0] != self._version:
            ids = self.graph.ids
            values = self._isam.calculateEstimate()
            folded = np.isin(ids, self._fold_ids)
            poses = np.empty((len(ids), 3))
            poses[~folded] = from_values(values, ids[~folded])
            if folded.any():  # ids[folded] is _fold_ids: both sorted, the same keyframes
                poses[folded] = compose(from_values(values, self._fold_anchor), self._fold_rel)
            c = self._cached = (self._version, ids, poses)
        return c[1].copy(), c[2].copy()

    def resolve(self) -> BatchResult:
        """Full robust batch re-solve (:func:`optimize_batch` from scratch), then restart
        iSAM2 from its result so that later updates build on it (without the loops a GNC
        solve rejected). If the last loop offered to :meth:`add_loop` was left out, it
        joins the graph first: the keyframes since the last loop in would otherwise keep
        their odometry poses in the solve (at the end of a run, in the map).

        The old iSAM2 is let go before the new one is built: built beside it, the new
        tree's allocations interleave with the old one's, whose freed pages then stay
        resident (a 3000-keyframe chain held 9.8 MB more after a re-solve so, 4.5 MB
        more this way). Should the new one fail, iSAM2 is rebuilt at the estimate before
        the solve, as it was, and the error raised."""
        if self._newest_held is not None:  # the newest keyframes' loop, lest they end on odometry alone
            self.graph.add_edges([self._newest_held])
            self._in_isam = [(max(self._newest_held.from_id, self._newest_held.to_id),
                              min(self._newest_held.from_id, self._newest_held.to_id))]
            self._newest_held = None
            self.held_loops -= 1
        result = optimize_batch(self.graph, self.params.batch)
        loops = np.flatnonzero(self.graph.is_loop).tolist()
        b = self.params.batch
        rejected = ({n for n, w in zip(loops, result.loop_weights) if w < 0.5}
                    if b.robust and b.kernel == "gnc" else set())
        if self._bias:  # odometry_model "bias_window": the same loops, the odometry as bias windows
            fg, values = self._whole_graph(rejected, result.ids, result.poses)
            refined = gtsam.LevenbergMarquardtOptimizer(fg, values).optimize()
            result = dataclasses.replace(result, poses=from_values(refined, result.ids))
            seg = self.params.scale_segment
            if seg is not None and refined.exists(scale_key(seg)):
                self._scale_value = np.asarray(refined.atVector(scale_key(seg)), float)
        before = self.estimate()
        self._isam = self._new_isam()
        self._version += 1
        try:
            self._isam.update(*self._folded_graph(result.ids, result.poses, rejected))
        except RuntimeError:
            self._clear_fold()
            self._isam = self._new_isam()
            self._isam.update(*self._whole_graph(self.rejected_loops, *before))
            raise
        self.rejected_loops = rejected
        return result

    def _folded_graph(self, ids: np.ndarray, poses: np.ndarray, skip: set[int]
                      ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """iSAM2's factors and values after a full solve at ``poses`` (aligned with the
        sorted ``ids``), the loops ``skip`` (edge indices) left out, the keyframes folded
        as :attr:`IncrementalParams.fold` says; sets the fold arrays. Every keyframe stays
        a variable (nothing folded) with ``fold`` 1 or when an odometry edge does not run
        from an older keyframe to a newer one with one edge into each."""
        self._clear_fold()
        fold = self.params.fold
        src, dst, delta, info = self.graph.edge_arrays()
        is_loop = self.graph.is_loop
        odo = np.flatnonzero(~is_loop)
        chain = (fold > 1 and bool(np.all(src[odo] < dst[odo]))
                 and len(np.unique(dst[odo])) == len(odo))
        if not chain:
            return self._whole_graph(skip, ids, poses)
        loops = [n for n in np.flatnonzero(is_loop).tolist() if n not in skip]
        anchors = self.graph.anchors()
        kept = set(anchors) | set(src[loops].tolist()) | set(dst[loops].tolist()) | set(ids[-fold:].tolist())
        into = dict(zip(dst[odo].tolist(), odo.tolist()))
        row = {k: n for n, k in enumerate(ids.tolist())}
        # per keyframe, while walking the chains: the kept keyframe it follows, the odometry
        # from it composed, that composition's covariance, how many edges it spans, and
        # their bias terms (None: one has none)
        state: dict[int, tuple[int, np.ndarray, np.ndarray, int, list[BiasEdge] | None]] = {}
        span_into: dict[int, list[BiasEdge]] = {}  # odometry_model "bias_window": a kept span by its end
        bias_values = gtsam.Values()
        fg = gtsam.NonlinearFactorGraph()
        f_ids: list[int] = []
        f_anchor: list[int] = []
        f_cov: list[np.ndarray] = []
        zero = np.zeros(3)
        for k in ids.tolist():
            n = into.get(k)
            if n is None:  # a chain starts here: kept
                kept.add(k)
                state[k] = (k, zero, np.zeros((3, 3)), 0, [])
                continue
            a, r, c, count, span = state[int(src[n])]
            d = delta[n]
            ad = gtsam.Pose2(*d).inverse().AdjointMap()
            r2, c2 = compose(r, d), ad @ c @ ad.T + np.linalg.inv(info[n])
            be = self._bias.get(n)
            span2 = None if span is None or be is None else span + [be]
            if k in kept or count + 1 >= fold:
                kept.add(k)
                if span2:  # the span's factor given the bias at its start (robotd.graph.bias.span_edge)
                    fg.push_back(span_factors(span2, span_into.get(a), bias_values, self.params.scale_segment))
                    span_into[k] = span2
                else:
                    i2 = np.linalg.inv(c2)
                    fg.add(between_factor(make_edge(a, k, r2, (i2 + i2.T) / 2, "odometry")))
                state[k] = (k, zero, np.zeros((3, 3)), 0, [])
            else:
                state[k] = (a, r2, c2, count + 1, span2)
                f_ids.append(k)
                f_anchor.append(a)
                f_cov.append(c2)
        for n in loops:
            fg.add(between_factor(make_edge(int(src[n]), int(dst[n]), delta[n], info[n], "loop"), self._kernel))
        for kid in anchors:
            fg.add(anchor_factor(kid, self.graph.pose(kid)))
        held = np.array(sorted(kept), np.int64)
        self._fold_ids = np.array(f_ids, np.int64)
        self._fold_anchor = np.array(f_anchor, np.int64)
        if f_ids:
            self._fold_rel = between(poses[[row[a] for a in f_anchor]], poses[[row[k] for k in f_ids]])
            self._fold_cov = np.array(f_cov)
        self._windows.reset()
        self._windows.previous = span_into.get(int(ids[-1]))  # the live windows chain on from the newest
        values = to_values(held, poses[[row[k] for k in held.tolist()]])
        values.insert(bias_values)
        if span_into:
            self._add_scale(fg, values, whole=True)
        return fg, values

    def _whole_graph(self, skip: set[int], ids: np.ndarray, poses: np.ndarray
                     ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """Every edge but ``skip`` (indices) and the anchors as iSAM2's factors, every
        keyframe a variable, at ``poses`` (aligned with ``ids``); with bias terms
        (``odometry_model`` ``"bias_window"``) the odometry in closed windows and the open
        one's edges independent, as :meth:`add_keyframe` would have left them (the live
        windows set to go on from there)."""
        self._windows.reset()
        if not self._bias:
            return factor_graph(self.graph, self._kernel, skip=skip), to_values(ids, poses)
        values = to_values(ids, poses)
        items: list[gtsam.NonlinearFactor | None] = []
        windows = WindowChain(self.params.window_edges, segment=self.params.scale_segment)
        for n, e in enumerate(self.graph.edges):
            if n in skip:
                continue
            be = self._bias.get(n)
            if e.kind == "loop" or be is None:
                if e.kind != "loop":
                    windows.reset()
                items.append(between_factor(e, self._kernel if e.kind == "loop" else None))
                continue
            if not windows.continues(be):
                windows.reset()
            closed = windows.offer(be)
            if closed is None:
                items.append(between_factor(e))
                windows.placed(len(items) - 1)
                continue
            wfg, bias_values, remove = closed
            for r in remove:
                items[r] = None
            items.extend(wfg.at(i) for i in range(wfg.size()))
            values.insert(bias_values)
        for kid in self.graph.anchors():
            items.append(anchor_factor(kid, self.graph.pose(kid)))
        fg = gtsam.NonlinearFactorGraph()
        slot: dict[int, int] = {}
        for i, f in enumerate(items):
            if f is not None:
                slot[i] = fg.size()
                fg.add(f)
        if any(f is not None and f.size() > 2 for f in items):  # a window: the scale variable too
            self._add_scale(fg, values, whole=True)
        windows.open = [(e, slot[i]) for e, i in windows.open]
        self._windows = windows
        return fg, values
