"""The odometry filter's pose history and keyframe edge recorder (no I/O).

:class:`PoseHistory` keeps the last couple of seconds of the filter's recorded states, so a
camera frame gets the pose at its own timestamp (:meth:`PoseHistory.pose_at`; paper 003,
Sec. IV-C pairs floor images with this odometry), and turns them into the odometry edge
between consecutive keyframes with the covariance of a pose clone taken after the fact
(:meth:`PoseHistory.keyframe_edge`). :class:`robotd.odometry.fusion.OdometryFilter` owns
one and records into it after every step; its late-measurement journal
(:mod:`robotd.odometry.journal`) saves and restores it (:meth:`PoseHistory.save`).
"""

from __future__ import annotations

import bisect
import math
from typing import NamedTuple

import numpy as np

from robotd.base.geometry import between, between_error_covariance, inverse, rot2, wrap_angle
from robotd.base.messages import PoseStamped
from robotd.odometry.ekf import IB, STATE_SIZE, EkfState
from robotd.odometry.increments import floor_covariance
from robotd.odometry.relative import (
    PoseClone,
    relative_pose_covariance,
    relative_pose_jacobians,
    shift_jacobian,
)

__all__ = ["EdgeBiasTerms", "HistoryMark", "PoseHistory"]


class EdgeBiasTerms(NamedTuple):
    """What a keyframe edge shares with the gyro bias (:meth:`PoseHistory.keyframe_edge_terms`),
    for a pose graph that keeps the bias as a variable (:mod:`robotd.graph.bias`).

    The edge's error ``eps`` (the pose graph's, in the frame of its end, as its covariance)
    and the filter's bias error ``db = b_hat - b`` at the edge's start are jointly Gaussian
    in the filter; conditioned on ``db``, ``eps ~ N(jac_bias * db, cov_given_bias)``.

    Fields:
        cov_given_bias: ``(3, 3)`` the edge's covariance given the bias at its start
            (``C - g g^T / P``, ``g = Cov(eps, db)``), floored as the edge's own.
        jac_bias: ``(3,)`` ``g / P``: the edge's error per rad/s of bias error at its start
            (m and rad per rad/s).
        bias_radps: the filter's bias estimate ``b_hat`` at the edge's start, rad/s.
        bias_var: its variance ``P``, (rad/s)^2.
        bias_end_radps: the estimate at the edge's end, rad/s.
        bias_end_var: its variance, (rad/s)^2.
        bias_cov: the covariance of the bias errors at the start and the end, (rad/s)^2
            (the filter's: the two are one random walk seen through the same readings).
        scale_gain: ``(3, 3)`` how much of the wheel + gyro edge's own error the edge
            carries (the edge moves by ``scale_gain e`` for an error ``e`` of the twin's
            edge): None for the twin's edge itself (the identity); an edge combined with a
            visual step carries ``K`` (:func:`robotd.odometry.increments.combine_bias_terms`).
            A pose graph with scale variables gives the edge ``scale_gain`` times the
            twin's scale Jacobian.
    """

    cov_given_bias: np.ndarray
    jac_bias: np.ndarray
    bias_radps: float
    bias_var: float
    bias_end_radps: float
    bias_end_var: float
    bias_cov: float
    scale_gain: np.ndarray | None = None


_TWO_PI = 2.0 * math.pi


class HistoryMark(NamedTuple):
    """What a rewind needs to put the history back as it was (:meth:`PoseHistory.save`):
    the records appended so far, the last one's entries (which a later step may amend),
    and the edge recorder's state."""

    n_rec: int
    last_rec: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None
    kf: tuple[int | None, bool, np.ndarray, tuple[int, np.ndarray, np.ndarray] | None]


class PoseHistory:
    """The recorded states of the last ``history_ns`` (at least; pruned to it when twice as
    long), each with its mean and covariance and the linear map of the error since the
    previous record, and the state the last keyframe's edge ends at. ``edge_floor_m``: the
    floor on the 1-sigma of an edge's position (:func:`robotd.odometry.increments.floor_covariance`)."""

    def __init__(self, history_ns: int, edge_floor_m: float = 1e-4) -> None:
        self._history_ns = history_ns
        self._edge_floor_m = edge_floor_m  # floor_covariance's min_sigma_m for the edges
        self._hist_t: list[int] = []
        self._hist_pose: list[np.ndarray] = []
        self._hist_cov: list[np.ndarray] = []
        # For keyframe_edge: each recorded state's mean and covariance, and the linear map
        # of the error since the previous recorded state (the first one's: since _anchor).
        self._hist_mean6: list[np.ndarray] = []
        self._hist_cov6: list[np.ndarray] = []
        self._hist_map: list[np.ndarray] = []
        self._kf_t: int | None = None  # the recorded state the last keyframe's edge ends at
        # A fused visual-odometry update since the last keyframe's edge: keyframe_edge then
        # leaves the next edge to the fallback (see there).
        self._vo_fused_since_keyframe = False
        self._kf_offset = np.zeros(3)
        self._anchor: tuple[int, np.ndarray, np.ndarray] | None = None  # it, once out of the history
        self._n_rec = 0  # records appended, and dropped from the front, since the start
        self._n_pruned = 0

    def oldest_stamp_ns(self) -> int:
        """The oldest recorded stamp (0 before any)."""
        return self._hist_t[0] if self._hist_t else 0

    def newest_pose(self) -> np.ndarray | None:
        return self._hist_pose[-1] if self._hist_pose else None

    def mark_fused(self) -> None:
        """A visual odometry update was fused since the last keyframe (no twin: see
        :meth:`keyframe_edge`)."""
        self._vo_fused_since_keyframe = True

    def save(self) -> HistoryMark:
        """A mark to :meth:`restore` the history to (the journal's snapshots)."""
        last = None
        if self._hist_t:
            last = (self._hist_pose[-1], self._hist_cov[-1], self._hist_mean6[-1],
                    self._hist_cov6[-1], self._hist_map[-1])
        return HistoryMark(self._n_rec, last,
                           (self._kf_t, self._vo_fused_since_keyframe, self._kf_offset, self._anchor))

    def can_restore(self, mark: HistoryMark) -> bool:
        """Whether the records of ``mark`` are still here (not pruned)."""
        return mark.n_rec - self._n_pruned >= 2 and mark.last_rec is not None

    def restore(self, mark: HistoryMark) -> None:
        """Back to ``mark`` (:meth:`can_restore` must hold): later records are dropped."""
        keep = mark.n_rec - self._n_pruned
        assert mark.last_rec is not None
        self._kf_t, self._vo_fused_since_keyframe, self._kf_offset, self._anchor = mark.kf
        for lst in (self._hist_t, self._hist_pose, self._hist_cov, self._hist_mean6,
                    self._hist_cov6, self._hist_map):
            del lst[keep:]
        (self._hist_pose[-1], self._hist_cov[-1], self._hist_mean6[-1], self._hist_cov6[-1],
         self._hist_map[-1]) = mark.last_rec
        self._n_rec = mark.n_rec

    def record(self, state: EkfState, step: np.ndarray, ext_cov: np.ndarray | None = None) -> None:
        """Record ``state`` (its stamp's pose, or the newest record amended when the stamp is
        the same); ``step``: the linear map of the error since the previous record.
        ``ext_cov``: the covariance of a longer error whose first six entries are the
        state's (``wheel_rounding``: ``[state, rounding]``, ``(8, 8)``), ``step`` then that
        error's map; every record of a history has the same length."""
        s = state
        t = s.stamp_ns
        pose, cov = s.mean[:3], s.cov[:3, :3]  # views: a state's arrays are read-only, never changed
        full_cov = s.cov if ext_cov is None else ext_cov
        if self._hist_t and self._hist_t[-1] == t:
            self._hist_pose[-1], self._hist_cov[-1] = pose, cov
            self._hist_mean6[-1], self._hist_cov6[-1] = s.mean, full_cov  # not changed in place
            self._hist_map[-1] = step @ self._hist_map[-1]
            return
        self._n_rec += 1
        self._hist_t.append(t)
        self._hist_pose.append(pose)
        self._hist_cov.append(cov)
        self._hist_mean6.append(s.mean)
        self._hist_cov6.append(full_cov)
        self._hist_map.append(step)
        if len(self._hist_t) > 64 and t - self._hist_t[0] > 2 * self._history_ns:
            cut = bisect.bisect_left(self._hist_t, t - self._history_ns)
            cut = min(cut, len(self._hist_t) - 2)
            self._prune(cut)

    def _prune(self, cut: int) -> None:
        """Forget the recorded states before index ``cut``. The last keyframe's state, if
        among them, becomes the anchor, and the maps of the forgotten states after it fold
        into the first kept one (whose map is then relative to the anchor)."""
        ts = self._hist_t
        if self._kf_t is not None and self._anchor is None and self._kf_t < ts[cut]:
            i = bisect.bisect_left(ts, self._kf_t)
            if i < len(ts) and ts[i] == self._kf_t:
                self._anchor = (self._kf_t, self._hist_mean6[i], self._hist_cov6[i])
                first = i + 1
            else:  # not recorded (cannot happen): no edge from it
                self._kf_t = None
                first = cut
        else:
            first = 0
        if self._anchor is not None:
            folded = self._hist_map[cut]
            for m in reversed(self._hist_map[first:cut]):
                folded = folded @ m
            self._hist_map[cut] = folded
        self._n_pruned += cut
        del (ts[:cut], self._hist_pose[:cut], self._hist_cov[:cut], self._hist_mean6[:cut],
             self._hist_cov6[:cut], self._hist_map[:cut])

    def keyframe_edge(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The odometry edge from the previous keyframe to the keyframe at ``stamp_ns``:
        ``(delta (3,), covariance (3, 3))``, the pose at ``stamp_ns`` in the frame of the
        previous keyframe's pose (``dx_m, dy_m, dyaw_rad``), the covariance that of the
        error as the pose graph measures it (in the frame of the edge's end,
        :func:`robotd.base.geometry.between_error_covariance`).

        Call it once per keyframe, in order, with ``stamp_ns`` at most the filter's time
        and inside the history (as :meth:`pose_at`); None at the first keyframe or when
        ``stamp_ns`` is outside the history.

        Why not the difference of the two absolute covariances: the increment's error is
        correlated with the pose at the first keyframe through the speed, yaw-rate and
        gyro-bias states (a bias error turned the heading before it and keeps turning it
        after), and late in a run the two covariances are large numbers whose small
        difference that formula takes. On the 110 m office route over planks it gave edges
        whose smallest eigenvalue had to be raised to the 0.1 mm floor while their error in
        that direction was millimetres (NEES 7.3, 75 % of it from 1 % of the edges, at turns
        on the spot and stops). Here the cross-covariance of the two poses is the first
        state's covariance carried through the linear map of every filter step between the
        two recorded states at the keyframes' stamps (the stochastic cloning of
        :mod:`robotd.odometry.relative`, done after the fact: the pipeline learns that a
        frame is a keyframe when the filter may be a second past it, and a clone taken then
        gives the covariance of another interval than the edge's). It is exact for the
        filter as run; floored as the old edges were
        (:func:`robotd.odometry.increments.floor_covariance`).

        A filter that fused visual odometry since the previous keyframe
        (:meth:`mark_fused`; without the wheel + gyro twin, ``vo_twin``) returns None for an edge with a fused update in
        it: its error map would need the clone's share of each update, and on the office
        route the edges made without that term made iSAM2's system indeterminate after
        about 400 keyframes.
        """
        got = self.keyframe_edge_terms(stamp_ns)
        return None if got is None else (got[0], got[1])

    def keyframe_edge_terms(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray, EdgeBiasTerms] | None:
        """:meth:`keyframe_edge` (call one or the other once per keyframe) with the edge's
        :class:`EdgeBiasTerms`: ``(delta (3,), covariance (3, 3), terms)``, from the same
        joint covariance of the two keyframes' states (the bias's rows of the first
        state's covariance carried through the same error maps)."""
        ts = self._hist_t
        kf = self.pose_at(stamp_ns)
        if kf is None:
            self._kf_t, self._anchor = None, None
            return None
        j = min(bisect.bisect_left(ts, stamp_ns), len(ts) - 1)  # the state at or after it
        offset = between(np.array([kf.x_m, kf.y_m, kf.yaw_rad]), self._hist_pose[j])
        edge: tuple[np.ndarray, np.ndarray, EdgeBiasTerms] | None = None
        if self._kf_t is not None:
            if self._anchor is not None:
                _t, mean_a, cov_a = self._anchor
                first = 0
            else:
                i = bisect.bisect_left(ts, self._kf_t)
                mean_a, cov_a = self._hist_mean6[i], self._hist_cov6[i]
                first = i + 1
            step = np.eye(cov_a.shape[0])
            for m in self._hist_map[first:j + 1]:
                step = m @ step
            # Cov(state at j, state at the previous keyframe), over the longer error when
            # the records carry one (its entries past the state's are marginalised here)
            cross = (step @ cov_a)[:STATE_SIZE, :STATE_SIZE]
            cov_a = cov_a[:STATE_SIZE, :STATE_SIZE]
            clone = PoseClone(self._kf_t, mean_a[:3], cov_a[:3, :3], cross[:, :3], self._kf_offset)
            # The Jacobians of the motion and of the shift serve the covariance and the bias
            # terms alike: computed once.
            jac = relative_pose_jacobians(mean_a[:3], self._hist_pose[j])
            h, cov_h = relative_pose_covariance(self._hist_pose[j], self._hist_cov[j], clone, jac)
            # From the recorded states back to the keyframes' stamps (offsets taken as exact;
            # shift_measurement's arithmetic).
            delta, j_shift = shift_jacobian(h, inverse(self._kf_offset), inverse(offset))
            cov = between_error_covariance(delta, j_shift @ cov_h @ j_shift.T)
            edge = (delta, floor_covariance(cov, min_sigma_m=self._edge_floor_m),
                    self._bias_terms(mean_a, cov_a, cross, j, delta, cov, jac, j_shift))
        if self._vo_fused_since_keyframe:  # no twin: see the docstring
            edge = None
        self._vo_fused_since_keyframe = False
        self._kf_t, self._kf_offset, self._anchor = ts[j], offset, None
        return edge

    def _bias_terms(self, mean_a: np.ndarray, cov_a: np.ndarray, cross: np.ndarray, j: int,
                    delta: np.ndarray, cov: np.ndarray,
                    jac: tuple[np.ndarray, np.ndarray, np.ndarray], j_shift: np.ndarray) -> EdgeBiasTerms:
        """The edge's :class:`EdgeBiasTerms`: ``cross (6, 6)`` the covariance of the state
        recorded at ``j`` with the previous keyframe's (``mean_a``, ``cov_a``), ``delta`` and
        ``cov`` the edge and its covariance in the frame of its end (unfloored); ``jac`` the
        motion's :func:`~robotd.odometry.relative.relative_pose_jacobians`, ``j_shift`` the
        shift's Jacobian (:func:`~robotd.odometry.relative.shift_jacobian`)."""
        _h, j_pose, j_clone = jac
        g = j_pose @ cross[:3, IB] + j_clone @ cov_a[:3, IB]  # Cov(h, bias at the start)
        g = j_shift @ g
        g[:2] = rot2(float(delta[2])).T @ g[:2]  # as between_error_covariance
        p = float(cov_a[IB, IB])
        cond = floor_covariance(cov - np.outer(g, g) / p, min_sigma_m=self._edge_floor_m)
        end_cov = self._hist_cov6[j]
        return EdgeBiasTerms(cond, g / p, float(mean_a[IB]), p, float(self._hist_mean6[j][IB]),
                             float(end_cov[IB, IB]), float(cross[IB, IB]))

    def settled_stamp_ns(self) -> int | None:
        """The newest stamp up to which :meth:`pose_at` is final (None before two poses).

        The newest recorded pose can still change: a gyro reading of its own stamp, or a
        late one, is applied to it when the next wheel message arrives. Every pose before it
        is fixed, so a frame stamped up to here gets the same pose whatever arrives later
        (a replay then reproduces the live keyframes exactly).
        """
        return self._hist_t[-2] if len(self._hist_t) >= 2 else None

    def pose_at(self, stamp_ns: int) -> PoseStamped | None:
        """The fused pose at ``stamp_ns``, interpolated between the two recorded poses around it.

        Position and covariance are interpolated linearly, yaw along the shorter arc.
        None when ``stamp_ns`` is newer than the filter's time or older than the history.
        """
        ts = self._hist_t
        if not ts or stamp_ns > ts[-1] or stamp_ns < ts[0]:
            return None
        i = bisect.bisect_left(ts, stamp_ns)
        if ts[i] == stamp_ns:
            p, c = self._hist_pose[i], self._hist_cov[i]
            return PoseStamped(int(stamp_ns), float(p[0]), float(p[1]), float(p[2]), c.copy())
        t0, t1 = ts[i - 1], ts[i]
        f = (stamp_ns - t0) / (t1 - t0)
        x, y, yaw = _interpolate_pair(float(t1 - t0), self._hist_pose[i - 1], self._hist_pose[i],
                                      float(stamp_ns - t0))
        cov = (1.0 - f) * self._hist_cov[i - 1] + f * self._hist_cov[i]
        return PoseStamped(int(stamp_ns), x, y, yaw, cov)


def _interpolate_pair(dt: float, p0: np.ndarray, p1: np.ndarray, q: float) -> tuple[float, float, float]:
    """:func:`robotd.base.geometry.interpolate_poses` of the two poses ``p0`` at 0 and ``p1``
    at ``dt`` (> 0) at ``0 < q < dt``, in floats and by the same arithmetic, so the same
    numbers (``np.unwrap`` of the yaw pair, ``np.interp``'s ``slope * (q - 0) + y0``): it
    runs for every camera frame, where the array version cost ten times as much."""
    x0, y0, a0 = float(p0[0]), float(p0[1]), float(p0[2])
    x1, y1, a1 = float(p1[0]), float(p1[1]), float(p1[2])
    dd = a1 - a0
    if not abs(dd) < math.pi:  # np.unwrap: take the shorter arc
        ddmod = (dd + math.pi) % _TWO_PI - math.pi
        if ddmod == -math.pi and dd > 0:
            ddmod = math.pi
        a1 = a1 + (ddmod - dd)
    return ((x1 - x0) / dt * q + x0, (y1 - y0) / dt * q + y0, wrap_angle((a1 - a0) / dt * q + a0))
