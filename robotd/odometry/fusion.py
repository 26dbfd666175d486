"""The odometry filter over the daemon's message stream.

:class:`OdometryFilter` runs the EKF functions of :mod:`robotd.odometry.ekf` over the message stream the daemon sees:
:class:`~robotd.base.messages.WheelTicks` and :class:`~robotd.base.messages.YawRate` in stamp order,
with a wheel-only :class:`~robotd.odometry.kinematics.WheelOdometry` alongside for
comparison and the last couple of seconds of fused poses, so a camera frame gets the pose
at its own timestamp (paper 003, Sec. IV-C pairs floor images with this odometry). The
pose history and the keyframe edges are :mod:`robotd.odometry.history`'s; the journal that
lets a late visual odometry step be applied at its own time is :mod:`robotd.odometry.journal`'s.
Messages that cannot be used are values, not exceptions: ``on_wheels`` and
``on_yaw_rate`` return False and count why in :class:`FilterCounters`.

Standstill is where the bias is learnt, so it is detected with care: an interval counts
as still only when no tick moved in it *and* in the interval before (a decelerating wheel
can go ~30 ms without a tick while the base still creeps). Gyro readings wait for the
wheel message that covers their stamp (at most one packet, 20 ms) so the filter knows
whether they were taken at rest; each reading at rest is paired with a zero-velocity
update at its own time, unless it disagrees with the bias estimate by more than
``still_gate_sigma`` (the base was still turning). Without the pairing the white angular
acceleration lets ``w`` wander between the 50 Hz wheel updates and a 2 s standstill
teaches the filter almost nothing about the bias.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from robotd.base.geometry import between, between_error_covariance, compose_with_covariance, rot2
from robotd.base.messages import PoseStamped, WheelTicks, YawRate
from robotd.odometry.ekf import (
    IB,
    IV,
    IW,
    STATE_SIZE,
    EkfParams,
    EkfState,
    advance_pose,
    initial_state,
    predict_rates,
    predict_with_jacobian,
    update_gyro_with_gain,
    update_wheels_with_gain,
)
from robotd.odometry.kinematics import (
    DiffDriveParams,
    WheelOdometry,
    integrate_pose,
    unwrap_ticks_delta,
    wheel_increment,
)
from robotd.odometry.history import EdgeBiasTerms, PoseHistory
from robotd.odometry.increments import combine_edges, edge_disagreement
from robotd.odometry.journal import Journal, Snapshot
from robotd.odometry.packet import (
    PACKET_SIZE,
    Rounding,
    close_packet,
    open_packet,
    packet_gyro,
    packet_gyro_mean,
    packet_predict,
    packet_wheels,
    rounding_variances,
)
from robotd.odometry.relative import (
    PoseClone,
    clone_after_predict,
    clone_pose,
    shift_measurement,
    update_relative_pose,
)

__all__ = ["LIVE_POSES", "FilterCounters", "OdometryFilter"]

#: :attr:`OdometryFilter.live_pose`'s values.
LIVE_POSES = ("fused", "combined_edges")

_log = logging.getLogger(__name__)
_EYE = np.eye(STATE_SIZE)
_EYE.setflags(write=False)  # the error map of no step, shared: maps are replaced, never changed in place
_EYE8 = np.eye(STATE_SIZE + 2)
_EYE8.setflags(write=False)


#: The source of the Kobuki driver's raw-gyro reading: the mean of the packet's samples.
PACKET_MEAN_SOURCE = "raw_gyro"
#: How far from the packet's middle such a reading may be stamped and still be its mean.
_MEAN_STAMP_TOLERANCE_NS = 2_000_000


def _packet_mean_reading(buf: collections.deque[YawRate], start_ns: int, end_ns: int) -> bool:
    """Whether the gyro readings buffered for the packet ``(start_ns, end_ns]`` are one
    reading of the packet's mean rate: one reading in it, from the Kobuki driver's raw gyro
    (:data:`PACKET_MEAN_SOURCE`: the mean of the samples since the previous packet, stamped
    in the middle of that interval), stamped in the packet's middle (a packet after a lost
    one is longer than the samples' interval; a source of point samples has several)."""
    if not buf or buf[0].stamp_ns > end_ns or (len(buf) > 1 and buf[1].stamp_ns <= end_ns):
        return False
    g = buf[0]
    mid = (start_ns + end_ns) // 2
    return (g.source == PACKET_MEAN_SOURCE and g.stamp_ns > start_ns
            and abs(g.stamp_ns - mid) <= _MEAN_STAMP_TOLERANCE_NS)


def _pad8(step: np.ndarray) -> np.ndarray:
    """A six-entry step's error map ``(6, 6)`` on the error ``[state, rounding]`` (the
    rounding of the count unchanged by it): ``(8, 8)``."""
    out = np.eye(STATE_SIZE + 2)
    out[:STATE_SIZE, :STATE_SIZE] = step
    return out


@dataclass
class FilterCounters:
    """What the filter did with its input.

    ``wheel_msgs``/``yaw_msgs``: messages used. ``out_of_order``: dropped because older
    than what was already processed (beyond ``late_tolerance_ns``). ``duplicates``:
    dropped because their stream already had a message with that stamp. ``late``: used
    at the filter's current time although slightly older. ``gaps``: wheel intervals
    longer than ``max_gap_s``. ``resets``: gaps so long the tick counters may have
    wrapped ambiguously; the wheel reference was restarted without motion.
    ``still_updates``: wheel intervals taken as standstill (zero-velocity updates).
    ``still_rejected``: gyro readings at standstill that disagreed with it (gate).
    Visual odometry (:meth:`OdometryFilter.on_visual_odometry`): ``vo_fused`` used,
    ``vo_missing`` keyframes without a measurement, ``vo_no_clone`` measurements whose
    previous keyframe is not the filter's last, ``vo_no_pose`` keyframes outside the
    pose history, ``vo_rejected`` measurements that failed the chi-square gate.
    """

    wheel_msgs: int = 0
    yaw_msgs: int = 0
    still_updates: int = 0
    still_rejected: int = 0
    out_of_order: int = 0
    duplicates: int = 0
    late: int = 0
    gaps: int = 0
    resets: int = 0
    vo_fused: int = 0
    vo_missing: int = 0
    vo_no_clone: int = 0
    vo_no_pose: int = 0
    vo_rejected: int = 0


@dataclass
class OdometryFilter:
    """Wheel + gyro EKF over a message stream, with a wheel-only twin and a pose history.

    ``drive``: the base geometry. ``params``: the EKF noise model. ``initial_pose``: the
    pose at the first message (the start defines the odometry frame). ``history_s``: how
    far back :meth:`pose_at` can look. ``max_gap_s``: a longer wheel interval is a gap.
    ``late_tolerance_ns``: a message at most this much older than the filter's time is
    still used, at the filter's time (a driver may emit a packet's gyro samples after its
    wheel ticks); older ones are dropped. ``max_wheel_speed_mps``: bounds how far a wheel
    can turn in a gap before the 16-bit counters become ambiguous. ``max_gyro_wait_s``:
    how long gyro readings wait for a wheel message before they are applied anyway.
    ``still_gate_sigma``: at rest, a gyro reading further than this many sigma from the
    bias estimate is not paired with a zero-velocity update. ``vo_gate_nis``: a visual
    odometry measurement whose normalised innovation squared exceeds this (chi-square, 3
    degrees of freedom; 16.27 = 99.9 %) is rejected. ``vo_twin``: visual odometry will be
    fused (:meth:`on_visual_odometry`); a twin filter then sees only the wheels and the gyro
    and gives :meth:`keyframe_edge` its edges, so that the pose graph gets the wheel + gyro
    motion and the visual step as independent measurements of the same edge
    (:func:`robotd.odometry.increments.combine_edges`) instead of a fused estimate whose
    cross-covariances a late relative update makes hard to carry. The filter then also
    keeps a journal of its messages over the history, so that a visual step is applied at
    its keyframe's time however late it comes (see :meth:`on_visual_odometry`).
    ``gyro_scale``: the gyro's calibrated scale (measured over true yaw rate; ``robotd
    calibrate odometry``), by which every reading is divided; 1 uncalibrated.
    ``initial_bias``: the gyro bias's prior ``(mean, sigma)`` in rad/s of the scaled
    readings (default: 0 and ``params.initial_gyro_bias_sigma_radps``).
    ``vo_rate_only`` (default False): with ``vo_twin``, the fused filter's pose gets no
    process noise of its own (:attr:`robotd.odometry.ekf.EkfParams.rate_only_process`),
    so that a visual step's heading reaches the gyro bias instead of being taken for
    unmodelled turning; the twin, whose edges the pose graph and its gate use, keeps
    ``params`` as given. It helped while the visual steps were fitted on the descriptor's
    coordinate grid; on the detector's positions (steps several times more precise) the
    filter whose pose keeps its own process noise is the better one, and a filter whose
    pose follows its rates alone refuses some of those steps (docs/odometry.md, "The
    visual steps on the detected positions").
    ``pose_after_rates`` (default False): a filter whose pose follows its rates
    (``rate_only_process``, which ``vo_twin`` with ``vo_rate_only`` sets) moves its pose
    over each interval between two readings by the trapezoid rule: the first half with the
    rates before the reading, the second half with the rates the reading left
    (:func:`robotd.odometry.ekf.advance_pose`, :func:`robotd.odometry.ekf.predict_rates`).
    Moved by the rates before the reading alone, the pose lagged the truth by about 5 ms
    of yaw rate while the base turned (the Kobuki's readings: the raw gyro's mean stamped
    in the middle of its packet, the ticks at its end); on the office route (seed 0, no
    visual odometry) the heading change over a keyframe interval was then 0.72 mrad RMS
    off the truth, and 0.26 mrad with the trapezoid. The twin (``rate_only_process``
    off) is unchanged.
    ``vo_angular_accel_noise_radps2_per_sqrt_hz`` (default None: the params'): with
    ``vo_twin`` and ``vo_rate_only``, the fused filter's white angular acceleration. The
    configuration's 0.3 is also the twin's pose noise (its edges, the graph's gate); in a
    filter whose pose follows its rates it only says how far the yaw rate may wander
    between two readings, and with 0.3 the fused filter's heading change over a keyframe
    interval claimed 0.83 mrad (1-sigma) where it was 0.21 mrad off the truth (office,
    seeds 0-1, the daemon's visual steps: NEES of the heading component 0.06 against 1),
    so the visual steps' heading, 0.47 mrad off per step, outweighed the gyro's and the
    fused heading followed their random walk. With 0.1 that NEES is 0.33 and no step is
    refused; with 0.05 it is 0.6 but the lateral component becomes overconfident (5-6
    steps of 760 refused by the gate), with 0.03 24 are.
    Neither is the daemon's default: with both (0.1) the fused APE at the keyframes over
    seeds 0-4 is 0.0545 m on average against 0.0607 m without them, but the demo's end
    error (seed 0) is 0.045 m against 0.038 m, and the fused filter beats the graph's
    combined edges on 2 seeds of 5 instead of 3 (``bench/bench_odometry_fused.py``).
    ``twin_params``: with ``vo_twin``, the twin's noise model in place of ``params`` (the
    calibration's gyro noise goes to the graph's edges only, and with ``[odometry] noise_model =
    "calibration"`` its whole sensor-level noise model: :func:`robotd.app.assemble.build_odometry`).
    ``vo_bias_update`` (default True): False makes a visual step a relative-pose update
    that leaves the gyro bias alone (its gain row zeroed, a Schmidt "consider" bias:
    :func:`robotd.odometry.relative.update_relative_pose`), so that the bias is learnt from
    the wheels and the standstills only and the fused heading no longer follows the visual
    steps' heading random walk through it. On the office route (seeds 0-4, the daemon's
    visual steps, ``bench/bench_odometry_fused.py --variants designs``) it is no better
    than the default: fused end error and APE better than the nominal model's on 1 seed
    of 5, no worse than the combined edges on 3 (as the default), mean keyframe ATE 0.0609
    against 0.0611 m.
    ``live_pose`` (default ``"fused"``): ``"combined_edges"`` (with ``vo_twin``) makes
    :meth:`pose` the graph's combined edges chained without loops from the first
    keyframe's fused pose (at each keyframe the twin's edge over the interval and the
    visual step, combined when they agree within ``vo_gate_nis``, as the visual odometry
    stage makes the graph's edge) followed by the twin's motion since the last keyframe
    (:meth:`chain_pose` is the chain's end). The twin keeps a second edge history for it,
    since :meth:`keyframe_edge` is the pipeline's. :meth:`pose_at` stays the fused
    filter's. Same bench: at the keyframes it is the combined edges by construction; end
    error and APE better than the nominal model's on seeds 1, 2 and 4, the best mean of
    the designs measured; but on seed 0, the demo's, it ends 0.113 m off against the
    default's 0.043 m, so it is not the default.
    """

    drive: DiffDriveParams = field(default_factory=DiffDriveParams)
    params: EkfParams = field(default_factory=EkfParams)
    initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    history_s: float = 2.0
    max_gap_s: float = 0.25
    late_tolerance_ns: int = 20_000_000
    max_wheel_speed_mps: float = 0.7
    max_gyro_wait_s: float = 0.1
    still_gate_sigma: float = 3.0
    vo_gate_nis: float = 16.27
    vo_twin: bool = False
    gyro_scale: float = 1.0
    initial_bias: tuple[float, float] | None = None
    vo_rate_only: bool = False
    pose_after_rates: bool = False
    vo_angular_accel_noise_radps2_per_sqrt_hz: float | None = None
    twin_params: EkfParams | None = None
    vo_bias_update: bool = True
    live_pose: str = "fused"

    def __post_init__(self) -> None:
        if self.live_pose not in LIVE_POSES:
            raise ValueError(f"live_pose must be one of {', '.join(LIVE_POSES)}, got {self.live_pose!r}")
        self.counters = FilterCounters()
        self._twin = dataclasses.replace(self, vo_twin=False, twin_params=None, params=(
            self.params if self.twin_params is None else self.twin_params)) if self.vo_twin else None
        # live_pose = "combined_edges": the twin's edges (a history of their own, beside the
        # one keyframe_edge gives the pipeline), the chain and the twin's pose at its end.
        self._edge_history: PoseHistory | None = None
        self._chain: tuple[int, np.ndarray, np.ndarray, np.ndarray] | None = None
        if self._twin is not None and self.live_pose == "combined_edges":
            self._twin._edge_history = PoseHistory(int(self.history_s * 1e9), self._twin.params.edge_floor_m)
        if self.vo_twin and self.vo_rate_only:
            self.params = dataclasses.replace(self.params, rate_only_process=True)
            q = self.vo_angular_accel_noise_radps2_per_sqrt_hz
            if q is not None:
                self.params = dataclasses.replace(self.params, angular_accel_noise_density_radps2_per_sqrt_hz=q)
        # The pose's move over the interval since the rates' prediction, made by _settle.
        self._deferred = self.pose_after_rates and self.params.rate_only_process
        self._pending_ns = 0
        self._state: EkfState | None = None
        self._wheel = WheelOdometry(self.drive, self.initial_pose)
        self._dead_reckons = True  # this filter advances _wheel (the twin shares its owner's)
        if self._twin is not None:  # one wheel-only odometry, the owner's: the twin's would be the same
            self._twin._wheel, self._twin._dead_reckons = self._wheel, False
        self._wheel_ref: WheelTicks | None = None
        self._last_yaw_ns: int | None = None
        self._gyro_buf: collections.deque[YawRate] = collections.deque()
        self._was_still = False
        self._clone: PoseClone | None = None  # the pose at the last keyframe (relative.py)
        self._max_gyro_wait_ns = int(self.max_gyro_wait_s * 1e9)
        self._map = _EYE  # the error's linear map since the last record
        self._history = PoseHistory(int(self.history_s * 1e9), self.params.edge_floor_m)  # pose_at, keyframe_edge
        # With visual odometry fused: each wheel or gyro message with the filter after it.
        self._journal: Journal | None = Journal() if self.vo_twin else None
        # wheel_increments: the wheel readings as integrated measurements (packet.py), in a
        # filter without the journal (whose snapshots hold the six-entry state between steps)
        # and without the trapezoid's deferred move.
        self._increments = self.params.wheel_increments and self._journal is None and not self._deferred
        # wheel_rounding: the last count's roundings carried from packet to packet, and the
        # error map since the last record of the eight-entry error [state, rounding] (the
        # six-entry steps' maps, self._map, join it at the record).
        self._rounding: Rounding | None = None
        self._xmap = _EYE8
        if self._increments and self.params.wheel_rounding:
            self._rounding = Rounding(rounding_variances(self.drive.metres_per_tick_left,
                                                         self.drive.metres_per_tick_right,
                                                         self.drive.wheel_base_m))
        self._replaying = False
        # A wheel turning at max speed covers half the counter range in this time.
        half_range_m = 32767 * self.drive.metres_per_tick
        self._max_unwrap_ns = int(half_range_m / self.max_wheel_speed_mps * 1e9)

    # ---- input --------------------------------------------------------------------------

    def on_wheels(self, msg: WheelTicks) -> bool:
        """Use one encoder reading; False (and counted) when it was dropped.

        Gyro readings buffered up to this stamp are applied first, in stamp order; when no
        tick moved over this interval and the one before, the base was standing still and
        each of them is paired with a zero-velocity update (this calibrates the bias).
        """
        if self._twin is not None:
            self._twin.on_wheels(msg)
        return self._journalled(msg, self._on_wheels(msg))

    def _on_wheels(self, msg: WheelTicks) -> bool:
        t = int(msg.stamp_ns)
        ref = self._wheel_ref
        if ref is not None:
            if t == ref.stamp_ns:
                self.counters.duplicates += 1
                return False
            if t < ref.stamp_ns:
                self.counters.out_of_order += 1
                return False
        if not self._admit(t):
            return False
        self.counters.wheel_msgs += 1
        self._wheel_ref = msg
        if ref is None:
            if self._dead_reckons and not self._replaying:
                self._wheel.advance(msg)
            self._flush_gyro(t, stationary=False)
            self._advance_to(t)
            self._record()
            return True

        dt_ns = t - ref.stamp_ns
        if dt_ns > self._max_unwrap_ns:
            self.counters.gaps += 1
            self.counters.resets += 1
            if not self._replaying:
                _log.warning("wheel gap of %.1f s: tick counters may have wrapped; restarting "
                             "the wheel reference", dt_ns * 1e-9)
                if self._dead_reckons:
                    self._wheel.rebase(msg)
            self._flush_gyro(t, stationary=False)
            self._advance_to(t)
            self._record()
            return True

        dl = unwrap_ticks_delta(ref.left_ticks, msg.left_ticks)
        dr = unwrap_ticks_delta(ref.right_ticks, msg.right_ticks)
        if self._dead_reckons and not self._replaying:
            self._wheel.advance(msg)
        ds, dyaw = wheel_increment(dl, dr, self.drive)
        dt = dt_ns * 1e-9
        v, w = ds / dt, dyaw / dt
        # At rest: no tick over this interval and the one before (a decelerating wheel
        # can go ~30 ms without a tick while the base still creeps).
        still_now = dl == 0 and dr == 0
        stationary = still_now and self._was_still
        self._was_still = still_now
        if dt_ns > self.max_gap_s * 1e9:
            self.counters.gaps += 1
            state = self._state
            no_gyro = not self._gyro_buf or self._gyro_buf[0].stamp_ns > t
            if state is not None and state.stamp_ns <= ref.stamp_ns and no_gyro:
                # Nothing arrived during the gap: the constant-rate prediction knows
                # nothing of what happened, the ticks do. Move the mean along the wheel
                # arc and keep the predicted (grown) covariance.
                pred, jac = predict_with_jacobian(state, t, self.params)
                mean = pred.mean.copy()
                mean[:3] = integrate_pose(state.mean[:3], ds, dyaw)
                mean[IV], mean[IW] = v, w
                self._state = EkfState(t, mean, pred.cov)
                self._step_map(jac)
                self._new_count()
        state = self._state
        if (self._increments and not stationary and dt_ns <= self.max_gap_s * 1e9 and self._clone is None
                and state is not None and state.stamp_ns == ref.stamp_ns):
            self._packet(t, ds, dyaw, dt, msg)
            self._record()
            return True
        self._flush_gyro(t, stationary)
        self.counters.still_updates += int(stationary)
        self._advance_to(t)
        self._apply_wheels(v, w, stationary, msg, dt)
        if not still_now:
            self._new_count()
        self._record()
        return True

    def on_yaw_rate(self, msg: YawRate) -> bool:
        """Take one gyro reading; False (and counted) when it was dropped.

        Readings wait (at most ``max_gyro_wait_s``) for the wheel message that covers
        their stamp, which tells whether the base was standing still.
        """
        if self._twin is not None:
            self._twin.on_yaw_rate(msg)
        return self._journalled(msg, self._on_yaw_rate(msg))

    def _on_yaw_rate(self, msg: YawRate) -> bool:
        t = int(msg.stamp_ns)
        if self._last_yaw_ns is not None:
            if t == self._last_yaw_ns:
                self.counters.duplicates += 1
                return False
            if t < self._last_yaw_ns:
                self.counters.out_of_order += 1
                return False
        if not self._admit(t):
            return False
        self._last_yaw_ns = t
        self.counters.yaw_msgs += 1
        self._gyro_buf.append(msg)
        if t - self._gyro_buf[0].stamp_ns > self._max_gyro_wait_ns:
            # No wheel message for a while: use what we have without the standstill test.
            self._flush_gyro(t, stationary=False)
        return True

    def _flush_gyro(self, t: int, stationary: bool) -> None:
        """Apply the buffered gyro readings stamped at or before ``t``."""
        buf = self._gyro_buf
        while buf and buf[0].stamp_ns <= t:
            msg = buf.popleft()
            ts = int(msg.stamp_ns)
            if self._state is None:
                self._state = initial_state(ts, self.params, self.initial_pose, self.initial_bias)
            self._advance_to(ts)
            rate = float(msg.yaw_rate_radps) / self.gyro_scale
            at_rest = stationary and self._still_gate(rate)
            if at_rest:
                self._apply_wheels(0.0, 0.0, True)
            var = msg.yaw_rate_var_rad2ps2
            var = None if var is None else var / self.gyro_scale ** 2
            up = update_gyro_with_gain(self._state, rate, self.params, at_rest, var)
            self._state = up.state
            self._step_map(up.error_map)
            self._record()

    def _packet(self, t: int, ds: float, dyaw: float, dt: float, msg: WheelTicks) -> None:
        """``wheel_increments``: the packet from the last wheel reading to ``t`` as one
        augmented state (:mod:`robotd.odometry.packet`): the gyro readings up to ``t``, then
        the ticks' distance ``ds`` and heading change ``dyaw`` over ``dt`` seconds; the pose
        moves by them, and the error map of the whole packet joins the filter's."""
        assert self._state is not None
        r = self._rounding
        if r is not None:  # the six-entry steps since the last record first
            self._clone_follows_map()
            r.cross = self._map @ r.cross
            self._xmap = _pad8(self._map) @ self._xmap
            self._map = _EYE
        p = open_packet(self._state, r)
        buf = self._gyro_buf
        mean = _packet_mean_reading(buf, p.stamp_ns, t)
        while buf and buf[0].stamp_ns <= t:
            g = buf.popleft()
            var = g.yaw_rate_var_rad2ps2
            var = None if var is None else var / self.gyro_scale ** 2
            if mean:  # the packet's mean rate: an integrated measurement at its end
                packet_predict(p, t, self.params)
                packet_gyro_mean(p, float(g.yaw_rate_radps) / self.gyro_scale, dt, self.params, var)
                continue
            packet_predict(p, int(g.stamp_ns), self.params)
            packet_gyro(p, float(g.yaw_rate_radps) / self.gyro_scale, self.params, var)
        packet_predict(p, t, self.params)
        packet_wheels(p, ds, dyaw, dt, self.params, msg.speed_var_m2ps2, msg.yaw_rate_var_rad2ps2)
        self._state, step = close_packet(p, r)
        if r is None:
            self._map = step @ self._map
        else:
            self._xmap = step @ self._xmap

    def _new_count(self) -> None:
        """``wheel_rounding``: the ticks moved outside a packet (a rate update, a gap): the
        new count's roundings are fresh, independent of the state (what the old ones did is
        in that update's white noise)."""
        r = self._rounding
        if r is None:
            return
        self._clone_follows_map()
        r.cross = self._map @ r.cross
        xmap = _pad8(self._map) @ self._xmap
        xmap[PACKET_SIZE - 2:, :] = 0.0
        self._xmap, self._map = xmap, _EYE
        r.reset()

    def _apply_wheels(self, v: float, w: float, stationary: bool, msg: WheelTicks | None = None,
                      dt_s: float | None = None) -> None:
        """The wheel update, carrying a pose clone's cross-covariance along (``msg``: the
        reading, whose stated variances replace the noise model's when it has them;
        ``dt_s``: its interval, for the wheels' continuous slip)."""
        prior = self._state
        assert prior is not None
        var_v, var_w = (None, None) if msg is None else (msg.speed_var_m2ps2, msg.yaw_rate_var_rad2ps2)
        up = update_wheels_with_gain(prior, v, w, self.params, stationary, var_v, var_w, dt_s)
        self._state = up.state
        self._step_map(up.error_map)

    def _still_gate(self, rate_radps: float) -> bool:
        """True when the gyro agrees with a base at rest (within ``still_gate_sigma``).

        Ticks stop about 30 ms before a decelerating turn does (the last tick is 85 um of
        rim), so a reading can come from a base that still turns a little: pinning its
        yaw rate to zero then would push the error into the bias estimate.
        """
        s = self._state
        assert s is not None
        p = self.params
        var = s.cov[IB, IB] + p.gyro_noise_radps ** 2 + p.stationary_noise_radps ** 2
        resid = rate_radps - s.mean[IB]
        if resid * resid <= self.still_gate_sigma ** 2 * var:
            return True
        self.counters.still_rejected += 1
        return False

    def _admit(self, t: int) -> bool:
        """False (counted) when ``t`` is too far behind the filter's time."""
        if self._state is None:
            self._state = initial_state(t, self.params, self.initial_pose, self.initial_bias)
            return True
        if t >= self._state.stamp_ns:
            return True
        if self._state.stamp_ns - t <= self.late_tolerance_ns:
            self.counters.late += 1
            return True
        self.counters.out_of_order += 1
        return False

    def _advance_to(self, t: int) -> None:
        assert self._state is not None
        if t > self._state.stamp_ns and self._deferred:
            self._settle()  # a move still pending goes with the rates it had
            dt_ns = t - self._state.stamp_ns
            # The first half of the interval with the rates before the readings at t, the
            # second (_settle) with the rates after them: the trapezoid rule.
            self._move_pose(dt_ns // 2)
            self._pending_ns = dt_ns - dt_ns // 2
            self._state = predict_rates(self._state, t, self.params)  # Jacobian: identity
        elif t > self._state.stamp_ns:
            self._state, jac = predict_with_jacobian(self._state, t, self.params)
            self._step_map(jac)

    def _step_map(self, step: np.ndarray) -> None:
        """One filter step's error map ``step (6, 6)`` joins the map since the last record
        (a pose clone's cross-covariance follows the whole map at :meth:`_record`)."""
        self._map = step if self._map is _EYE else step @ self._map

    def on_visual_odometry(self, stamp_ns: int, prev_stamp_ns: int | None, delta: np.ndarray | None,
                           covariance: np.ndarray | None) -> bool:
        """Fuse the motion between the keyframes at ``prev_stamp_ns`` and ``stamp_ns``.

        ``delta (3,)``: the pose at ``stamp_ns`` in the robot frame of the pose at
        ``prev_stamp_ns`` (``dx_m, dy_m, dyaw_rad``, floor visual odometry, paper 003 Sec.
        IV-D); ``covariance (3, 3)``. Call it for every keyframe, in order, once the filter
        has reached its stamp; ``delta=None`` (the step failed) leaves the wheel + gyro
        estimate alone. Either way the pose at ``stamp_ns`` becomes the clone the next
        measurement refers to (stochastic cloning, :mod:`robotd.odometry.relative`).
        Returns True when fused; otherwise False and counted (:class:`FilterCounters`).

        The pipeline gets to a keyframe's step when the filter is already past its frame:
        on the office demo 53 ms at the median, 227 ms at p90, up to half a second. With
        ``vo_twin`` the filter goes back to its state after the first message that reached
        ``stamp_ns`` (journalled over the history), applies the step there and runs the
        wheel and gyro messages since once more. The result is the same, to the bit, as if
        the step had come at once, so the fused pose does not depend on the pipeline's
        timing. Without the journal (or beyond it) the step goes to the current state, its
        motion since the frame taken as exact (``shift_measurement``): on the office demo
        the chi-square gate then refused about a quarter of the steps (424 and 435 of 1770
        in two runs) and three runs ended 0.06 to 0.21 m from the truth.
        """
        at = self._rewind(stamp_ns)
        fused = self._visual_update(stamp_ns, prev_stamp_ns, delta, covariance)
        if at is not None:
            journal = self._journal
            assert journal is not None
            journal.amend(at, self._snapshot())  # a later rewind keeps the step
            tail = journal.tail(at)
            self._replaying = True
            try:
                for msg in tail:
                    self._journalled(msg, self._on_wheels(msg) if isinstance(msg, WheelTicks)
                                     else self._on_yaw_rate(msg))
            finally:
                self._replaying = False
        if self._twin is not None and self._twin._edge_history is not None:
            self._chain_edge(stamp_ns, prev_stamp_ns, delta, covariance)
        return fused

    def _chain_edge(self, stamp_ns: int, prev_stamp_ns: int | None, delta: np.ndarray | None,
                    covariance: np.ndarray | None) -> None:
        """``live_pose = "combined_edges"``: the chain moved to the keyframe at ``stamp_ns``
        by the graph's combined edge (the twin's edge and the visual step, combined when they
        agree within ``vo_gate_nis``, as the visual odometry stage makes it)."""
        twin = self._twin
        assert twin is not None and twin._edge_history is not None
        edge = twin._edge_history.keyframe_edge(stamp_ns)
        tp = twin.pose_at(stamp_ns)
        if tp is None:
            self._chain = None
            return
        at_kf = np.array([tp.x_m, tp.y_m, tp.yaw_rad])
        chain = self._chain
        if chain is None:  # the first keyframe: the chain starts at the fused pose there
            kp = self.pose_at(stamp_ns)
            if kp is None:
                return
            self._chain = (stamp_ns, np.array([kp.x_m, kp.y_m, kp.yaw_rad]), kp.covariance.copy(), at_kf)
            return
        step = None
        if (delta is not None and covariance is not None and prev_stamp_ns == chain[0]
                and np.all(np.isfinite(delta))):
            step = (np.asarray(delta, float), between_error_covariance(np.asarray(delta, float), covariance))
        if edge is None:
            edge = step
        elif step is not None and edge_disagreement(edge, step) <= self.vo_gate_nis:
            edge = combine_edges(edge, step)
        if edge is None:  # nothing measured the interval: the twin's motion over it
            edge = (between(chain[3], at_kf), np.zeros((3, 3)))
        pose, cov = _compose_with_covariance(chain[1], chain[2], edge[0], _start_frame(edge[0], edge[1]))
        self._chain = (stamp_ns, pose, cov, at_kf)

    def _combined_pose(self) -> PoseStamped | None:
        """The chain's pose at its keyframe followed by the twin's motion since (with the
        twin's covariance growth since then), or None before the chain's first keyframe."""
        chain, twin = self._chain, self._twin
        if chain is None or twin is None or twin.state is None:
            return None
        now = twin.state
        kf = twin.pose_at(chain[0])
        motion = between(chain[3], now.mean[:3])
        grown = np.zeros((3, 3))
        if kf is not None:
            r = np.eye(3)
            r[:2, :2] = rot2(float(chain[3][2])).T
            d = r @ (now.cov[:3, :3] - kf.covariance) @ r.T
            w, v = np.linalg.eigh(0.5 * (d + d.T))
            grown = (v * np.clip(w, 0.0, None)) @ v.T
        pose, cov = _compose_with_covariance(chain[1], chain[2], motion, grown)
        return PoseStamped(now.stamp_ns, float(pose[0]), float(pose[1]), float(pose[2]), cov)

    def _visual_update(self, stamp_ns: int, prev_stamp_ns: int | None, delta: np.ndarray | None,
                       covariance: np.ndarray | None) -> bool:
        s = self._state
        kf = self.pose_at(stamp_ns) if s is not None else None
        if s is None or kf is None:
            self.counters.vo_no_pose += 1
            self._clone = None
            return False
        offset = between(np.array([kf.x_m, kf.y_m, kf.yaw_rad]), s.mean[:3])
        fused = False
        c = self._clone_now()
        if delta is None or covariance is None or not np.all(np.isfinite(delta)):
            self.counters.vo_missing += 1
        elif c is None or c.keyframe_stamp_ns != prev_stamp_ns:
            self.counters.vo_no_clone += 1
        else:
            z, r = shift_measurement(delta, covariance, c.offset, offset)
            mean, cov, nis = update_relative_pose(s.mean, s.cov, c, z, r, () if self.vo_bias_update else (IB,))
            if nis > self.vo_gate_nis:
                self.counters.vo_rejected += 1
            else:
                self._state = EkfState(s.stamp_ns, mean, cov)
                self._record()
                self.counters.vo_fused += 1
                self._history.mark_fused()
                fused = True
        now = self._state  # s, or s with the step fused
        assert now is not None
        self._clone = clone_pose(now.mean, now.cov, stamp_ns, offset)
        return fused

    def _journalled(self, msg: WheelTicks | YawRate, used: bool) -> bool:
        """Journal ``msg`` with the filter after it (with ``vo_twin``); returns ``used``."""
        if self._pending_ns:  # every path that advances records; kept safe all the same
            self._record()
        if self._journal is not None:
            self._journal.append(msg, self._snapshot(), self._history.oldest_stamp_ns())
        return used

    def _snapshot(self) -> Snapshot:
        return Snapshot(self._state, self._wheel_ref, self._last_yaw_ns, tuple(self._gyro_buf),
                        self._was_still, self._clone, self._map, self._history.save(),
                        vars(self.counters).copy())

    def _rewind(self, stamp_ns: int) -> int | None:
        """Go back to the journalled state after the first message that brought the filter
        to ``stamp_ns``; its index in the journal, or None (no journal, not reached yet, or
        gone from the history: the step then goes to the current state)."""
        journal = self._journal
        if not journal:
            return None
        at = journal.rewind_point(stamp_ns)
        if at is None:
            return None
        snap = journal.snapshot(at)
        if not self._history.can_restore(snap.history):  # its records are gone: cannot go back
            return None
        self._state, self._wheel_ref, self._last_yaw_ns = snap.state, snap.wheel_ref, snap.last_yaw_ns
        self._gyro_buf = collections.deque(snap.gyro_buf)
        self._was_still, self._clone, self._map = snap.was_still, snap.clone, snap.map
        self.counters = FilterCounters(**snap.counters)
        self._history.restore(snap.history)
        return at

    def keyframe_edge(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The odometry edge from the previous keyframe to the keyframe at ``stamp_ns``:
        ``(delta (3,), covariance (3, 3))`` with the covariance of a pose clone taken after
        the fact (:meth:`robotd.odometry.history.PoseHistory.keyframe_edge`, which says why).
        Call it once per keyframe, in order; None at the first keyframe or when ``stamp_ns``
        is outside the history.

        With visual odometry fused the edge is the wheel + gyro twin's (``vo_twin``). A
        filter fusing it without the twin returns None for an edge with a fused update in
        it.
        """
        if self._twin is not None:
            return self._twin.keyframe_edge(stamp_ns)
        return self._history.keyframe_edge(stamp_ns)

    def keyframe_edge_terms(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray, EdgeBiasTerms] | None:
        """:meth:`keyframe_edge` with what the edge shares with the gyro bias
        (:meth:`robotd.odometry.history.PoseHistory.keyframe_edge_terms`; call one or the
        other once per keyframe)."""
        if self._twin is not None:
            return self._twin.keyframe_edge_terms(stamp_ns)
        return self._history.keyframe_edge_terms(stamp_ns)

    def _settle(self) -> None:
        """Move the pose over the interval of the last :func:`predict_rates` with the rates
        as the readings at its end left them (``pose_after_rates``)."""
        if self._pending_ns:
            self._move_pose(self._pending_ns)
            self._pending_ns = 0

    def _move_pose(self, dt_ns: int) -> None:
        """The pose along the state's rates over ``dt_ns`` (:func:`robotd.odometry.ekf.advance_pose`)."""
        assert self._state is not None
        self._state, jac = advance_pose(self._state, dt_ns * 1e-9)
        self._step_map(jac)

    def _clone_now(self) -> PoseClone | None:
        """The pose clone with its cross-covariance as of the current state (it follows the
        map at records, :meth:`_clone_follows_map`; every message ends with one)."""
        c = self._clone
        return c if c is None or self._map is _EYE else clone_after_predict(c, self._map)

    def _clone_follows_map(self) -> None:
        """The pose clone's cross-covariance carried through the map since the last record
        (the clone lags the state by that map until a record, :meth:`_step_map`)."""
        if self._clone is not None and self._map is not _EYE:
            self._clone = clone_after_predict(self._clone, self._map)

    def _record(self) -> None:
        self._settle()
        s = self._state
        assert s is not None
        self._clone_follows_map()
        step, self._map = self._map, _EYE
        r = self._rounding
        ext_cov = None
        if r is not None:  # the history keeps the eight-entry error [state, rounding]
            r.cross = step @ r.cross
            step, self._xmap = _pad8(step) @ self._xmap, _EYE8
            ext_cov = np.block([[s.cov, r.cross], [r.cross.T, r.cov]])
        self._history.record(s, step, ext_cov)
        if self._edge_history is not None:
            self._edge_history.record(s, step, ext_cov)

    # ---- output -------------------------------------------------------------------------

    @property
    def wheel_gyro(self) -> OdometryFilter:
        """The filter of the wheels and the gyro alone: the twin when visual odometry is
        fused (``vo_twin``), else this one. The daemon chooses and poses keyframes on it, so
        that the map does not depend on when a visual step reached the fused filter (live,
        that is whenever the pipeline got to the keyframe; a replay must give the same map)."""
        return self if self._twin is None else self._twin

    @property
    def state(self) -> EkfState | None:
        """The full EKF state (None before the first message)."""
        return self._state

    def latest_stamp_ns(self) -> int | None:
        """The filter's time: the newest stamp it has processed (None before any)."""
        return None if self._state is None else self._state.stamp_ns

    def settled_stamp_ns(self) -> int | None:
        """The newest stamp up to which :meth:`pose_at` is final (None before two poses;
        :meth:`robotd.odometry.history.PoseHistory.settled_stamp_ns`)."""
        return self._history.settled_stamp_ns()

    def pose(self) -> PoseStamped:
        """The fused pose and its 3x3 covariance (the initial pose before any message)."""
        if self._state is None:
            return initial_state(0, self.params, self.initial_pose, self.initial_bias).pose()
        if self.live_pose == "combined_edges":
            combined = self._combined_pose()
            if combined is not None:
                return combined
        return self._state.pose()

    def chain_pose(self) -> PoseStamped | None:
        """``live_pose = "combined_edges"``: the chain's pose at its last keyframe (the
        graph's combined edges chained without loops, from the first keyframe's fused pose),
        or None (another live pose, or before the first keyframe)."""
        c = self._chain
        return None if c is None else PoseStamped(c[0], float(c[1][0]), float(c[1][1]), float(c[1][2]), c[2].copy())

    def wheel_pose(self) -> PoseStamped:
        """The wheel-only dead-reckoned pose, for comparison."""
        return self._wheel.pose()

    def pose_at(self, stamp_ns: int) -> PoseStamped | None:
        """The fused pose at ``stamp_ns``, interpolated between the two recorded poses around
        it; None when ``stamp_ns`` is newer than the filter's time or older than the history
        (:meth:`robotd.odometry.history.PoseHistory.pose_at`)."""
        return self._history.pose_at(stamp_ns)


def _start_frame(delta: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """An edge's covariance as the pose graph measures its error (in the frame of its end,
    :func:`robotd.base.geometry.between_error_covariance`) back to errors added in the
    frame of its start."""
    j = np.eye(3)
    j[:2, :2] = rot2(float(delta[2]))
    return j @ np.asarray(cov, float) @ j.T


def _compose_with_covariance(a: np.ndarray, cov_a: np.ndarray, b: np.ndarray,
                             cov_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`robotd.base.geometry.compose_with_covariance`, the covariance kept symmetric."""
    pose, cov = compose_with_covariance(a, cov_a, b, cov_b)
    return pose, 0.5 * (cov + cov.T)
