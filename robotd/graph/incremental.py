"""Live pose graph: one iSAM2 update per keyframe (Kaess et al., IJRR 2012), a loop edge
under the batch solver's robust kernel (DCS when the full solve is GNC), and a full batch
re-solve on demand.

Kept in step with the full solve: :meth:`IncrementalGraph.resolve` restarts iSAM2 from the
batch result, and when that was a GNC solve, without the loop edges GNC rejected (weight
below one half), so that iSAM2's later updates build on the same inliers instead of
letting a rejected loop pull again through its kernel. The rejected loops stay in
:attr:`IncrementalGraph.graph`: the next full solve judges them again, with everything
learnt since."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import gtsam
import numpy as np

from robotd.base.errors import GraphError
from robotd.base.geometry import compose
from robotd.graph.batch import BatchParams, BatchResult, optimize_batch
from robotd.graph.factors import anchor_factor, between_factor, factor_graph, from_values, to_values
from robotd.graph.model import Edge, PoseGraph


@dataclass(frozen=True, slots=True)
class IncrementalParams:
    """Parameters of :class:`IncrementalGraph`.

    relinearize_threshold: iSAM2 relinearises a variable whose update exceeds this
        (m and rad), default 0.01.
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
    """

    relinearize_threshold: float = 0.01
    relinearize_skip: int = 1
    loop_updates: int = 5
    batch: BatchParams = field(default_factory=BatchParams)
    loop_spacing: int = 10
    loops_per_keyframe: int = 2
    factorization: str = "QR"

    def __post_init__(self) -> None:
        if self.factorization not in ("QR", "CHOLESKY"):
            raise ValueError(f"factorization must be 'QR' or 'CHOLESKY', not {self.factorization!r}")


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
        self._isam = self._new_isam()
        self._version = 0  # bumped by every change of the estimate
        self._cached: tuple[int, np.ndarray, np.ndarray] | None = None

    def _update(self, factors: gtsam.NonlinearFactorGraph | None = None,
                values: gtsam.Values | None = None) -> None:
        """One iSAM2 step with the new ``factors`` and ``values`` (none: one more relinearisation)."""
        if factors is None or values is None:
            self._isam.update()
        else:
            self._isam.update(factors, values)
        self._version += 1

    def _new_isam(self) -> gtsam.ISAM2:
        p = gtsam.ISAM2Params()
        p.setRelinearizeThreshold(self.params.relinearize_threshold)
        p.relinearizeSkip = self.params.relinearize_skip
        p.setFactorization(self.params.factorization)
        return gtsam.ISAM2(p)

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
                     information: np.ndarray) -> np.ndarray:
        """Add a keyframe with its odometry edge from ``from_id`` (delta ``(dx_m, dy_m,
        dyaw_rad)`` in ``from_id``'s frame, ``(3, 3)`` information); one iSAM2 update.
        Returns the new keyframe's estimated pose ``(3,)``."""
        if from_id not in self.graph:
            raise GraphError(f"odometry edge to keyframe {keyframe_id} from unknown keyframe {from_id}")
        guess = compose(self.pose(from_id), np.asarray(delta, dtype=float))
        self.graph.add_pose(keyframe_id, guess)
        edge = self.graph.add_edge(from_id, keyframe_id, delta, information, "odometry")
        fg = gtsam.NonlinearFactorGraph()
        fg.add(between_factor(edge))
        self._update(fg, to_values(np.array([keyframe_id]), guess[None]))
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
        ``loops_per_keyframe`` loops in already. Loops come best first (the detector's
        order), so a keyframe's first loops enter. GraphError for a bad edge either way.
        Returns whether it entered."""
        edge = self.graph.check_edge(from_id, to_id, delta, information, "loop")
        if not self._admit_loop(edge.from_id, edge.to_id):
            self.held_loops += 1
            self._newest_held = edge
            return False
        self._newest_held = None
        self.graph.add_edges([edge])
        fg = gtsam.NonlinearFactorGraph()
        fg.add(between_factor(edge, self._kernel))
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
        two marginals (0.1-0.7 ms on the office demo's graphs)."""
        pa = self._isam.calculateEstimatePose2(int(from_id))
        pb = self._isam.calculateEstimatePose2(int(to_id))
        predicted = pa.between(pb)
        d = [float(v) for v in delta]
        e = gtsam.Pose2.Logmap(predicted.between(gtsam.Pose2(d[0], d[1], d[2])))
        ad = predicted.inverse().AdjointMap()
        if joint and int(from_id) != int(to_id):
            keys = gtsam.KeyVector([int(from_id), int(to_id)])
            j = np.asarray(self._isam.jointMarginalCovariance(keys).fullMatrix(), dtype=float)
            a = np.hstack([-ad, np.eye(3)])
            cov = a @ j @ a.T + np.linalg.inv(information)
        else:
            cov = (ad @ self._isam.marginalCovariance(int(from_id)) @ ad.T
                   + self._isam.marginalCovariance(int(to_id)) + np.linalg.inv(information))
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
        isam = self._new_isam()
        isam.update(factor_graph(self.graph, self._kernel, skip=self.rejected_loops), to_values(ids, est))
        for _ in range(self.params.loop_updates):
            isam.update()
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
        edges = self.graph.edges
        return {"edges": len(edges), "loops": sum(1 for e in edges if e.kind == "loop"),
                "held_loops": self.held_loops,
                "factors": int(self._isam.getFactorsUnsafe().nrFactors()), "cliques": int(self._isam.size()),
                "tree_nnz": int(self._isam.treeNnz()),
                "cached_marginals": int(self._isam.numCachedSeparatorMarginals())}

    def pose(self, keyframe_id: int) -> np.ndarray:
        """The current estimate of one keyframe, ``(3,)`` (m, m, rad)."""
        p = self._isam.calculateEstimatePose2(int(keyframe_id))
        return np.array([p.x(), p.y(), p.theta()])

    def marginal_covariance(self, keyframe_id: int) -> np.ndarray:
        """iSAM2's marginal covariance of one keyframe, ``(3, 3)``, in the pose's own tangent
        space (x, y along its axes in m^2, yaw in rad^2; :func:`robotd.graph.covariance.tangent_to_world`
        moves it to the map's axes)."""
        return np.asarray(self._isam.marginalCovariance(int(keyframe_id)), dtype=float)

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """Every keyframe's current estimate: ``(ids (N,), poses (N, 3))`` (copies; computed
        once per change of the graph, which the mapped-ground test asks for at every
        keyframe)."""
        c = self._cached
        if c is None or c[0] != self._version:
            ids = self.graph.ids
            c = self._cached = (self._version, ids, from_values(self._isam.calculateEstimate(), ids))
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
        loops = [n for n, e in enumerate(self.graph.edges) if e.kind == "loop"]
        b = self.params.batch
        rejected = ({n for n, w in zip(loops, result.loop_weights) if w < 0.5}
                    if b.robust and b.kernel == "gnc" else set())
        before = self.estimate()
        self._isam = self._new_isam()
        self._version += 1
        try:
            self._isam.update(factor_graph(self.graph, self._kernel, skip=rejected),
                              to_values(result.ids, result.poses))
        except RuntimeError:
            self._isam = self._new_isam()
            self._isam.update(factor_graph(self.graph, self._kernel, skip=self.rejected_loops),
                              to_values(*before))
            raise
        self.rejected_loops = rejected
        return result
