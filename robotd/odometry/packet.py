"""The wheel reading as an integrated measurement: the pose advanced by the distance and the
heading change the ticks measured over their packet (``wheel_increments`` in
:class:`robotd.odometry.ekf.EkfParams`).

The ticks count how far each wheel turned between two readings, 20 ms apart: the integral
of the base's speed and yaw rate over the packet, not their value at its end. The rate
update of :func:`robotd.odometry.ekf.update_wheels` takes them for the rates at the end; the
pose was moved over the packet with the speed the filter had before the reading, and the
update moves it back only along the pose's correlation with the speed, part of the way to
where the ticks put it. So the pose trails the truth where the speed changes (on the office
route, with the calibration's noise model, by about 7 ms times the change of speed: 3 mm
across a stop from 0.4 m/s).

Here the filter's state over one packet is augmented with the distance ``D`` and the heading
change ``Th`` driven since the packet's start (the pose held at the start, the stochastic
clone of that pose written in the packet's own coordinates)::

    [x_m, y_m, yaw_rad, v_mps, w_radps, gyro_bias_radps, D_m, Th_rad]

Over the packet ``D`` and ``Th`` integrate ``v`` and ``w`` (the white accelerations' exact
discretisation for the pairs ``(D, v)`` and ``(Th, w)``), the gyro readings update ``w`` and
the bias as before, and the wheel reading measures ``(D, Th)`` directly, its noise the rate
noise times the packet's length. At the reading the packet closes: the pose moves along the
arc of ``(D, Th)`` from the packet's start (:func:`close_packet`) and the state is back to
six entries. The error at the packet's end is a linear map of the error at its start plus
noise drawn inside the packet, so the keyframe edges' error maps
(:class:`robotd.odometry.history.PoseHistory`) stay exact when the filter records at the
wheel readings only.
"""

from __future__ import annotations

import math

import numpy as np

from robotd.odometry.ekf import (
    IB,
    IV,
    IW,
    IX,
    IY,
    IYAW,
    STATE_SIZE,
    EkfParams,
    EkfState,
    _arc,
    gyro_noise_var,
    slip_variances,
    speed_changing,
    turning,
    wheel_noise,
)
from robotd.base.geometry import wrap_angle

__all__ = ["ID", "ITH", "PACKET_SIZE", "ROUNDING_SIZE", "Packet", "Rounding", "close_packet",
           "open_packet", "packet_gyro", "packet_gyro_mean", "packet_predict", "packet_wheels",
           "rounding_variances"]

PACKET_SIZE = STATE_SIZE + 2
ID, ITH = STATE_SIZE, STATE_SIZE + 1
# wheel_rounding: the roundings of the distance and the heading change at the packet's
# start (carried from the packet before) and at its end (drawn fresh inside it).
ROUNDING_SIZE = PACKET_SIZE + 4
IDO, ITO, IDN, ITN = PACKET_SIZE, PACKET_SIZE + 1, PACKET_SIZE + 2, PACKET_SIZE + 3


def _gyro_row(n: int) -> np.ndarray:
    h = np.zeros((1, n))
    h[0, IW] = h[0, IB] = 1.0
    return h


def _inc_rows(n: int) -> np.ndarray:
    h = np.zeros((2, n))
    h[0, ID] = h[1, ITH] = 1.0
    if n == ROUNDING_SIZE:  # counted = true - rounding at the end + rounding at the start
        h[0, IDO], h[0, IDN] = 1.0, -1.0
        h[1, ITO], h[1, ITN] = 1.0, -1.0
    return h


_H_GYRO = {n: _gyro_row(n) for n in (PACKET_SIZE, ROUNDING_SIZE)}
_H_INC = {n: _inc_rows(n) for n in (PACKET_SIZE, ROUNDING_SIZE)}
_EYE = {n: np.eye(n) for n in (PACKET_SIZE, ROUNDING_SIZE)}


def rounding_variances(metres_per_tick_left: float, metres_per_tick_right: float,
                       wheel_base_m: float) -> np.ndarray:
    """``(2,)`` the variances of one count's rounding carried into the distance (m^2) and the
    heading change (rad^2): each wheel's count is its travel rounded to a tick, the residual
    uniform over the tick (variance ``tick^2 / 12``), the two wheels' independent; the
    distance takes their mean, the heading change their difference over the wheel base."""
    vl, vr = metres_per_tick_left ** 2 / 12.0, metres_per_tick_right ** 2 / 12.0
    return np.array([(vl + vr) / 4.0, (vl + vr) / wheel_base_m ** 2])


class Rounding:
    """``wheel_rounding``: the roundings of the distance and the heading change the last
    count left (the filter's estimate, carried from packet to packet): ``mean (2,)``, m and
    rad, ``cov (2, 2)``, ``cross (6, 2)`` the covariance of the six-entry state's error with
    theirs, and ``fresh (2,)`` the variances of a new count's (:func:`rounding_variances`)."""

    __slots__ = ("cov", "cross", "fresh", "mean")

    def __init__(self, fresh: np.ndarray) -> None:
        self.fresh = fresh
        self.reset()

    def reset(self) -> None:
        """A count whose rounding nothing else has seen: zero mean, fresh variance, no
        correlation with the state."""
        self.mean = np.zeros(2)
        self.cov = np.diag(self.fresh)
        self.cross = np.zeros((STATE_SIZE, 2))


class Packet:
    """The augmented state over one open packet: ``stamp_ns``, ``mean (8,)``, ``cov (8, 8)``
    and ``error_map (8, 6)``, the linear map from the error of the six-entry state the
    packet opened on to the augmented state's error (noise drawn inside the packet aside)."""

    __slots__ = ("cov", "error_map", "mean", "stamp_ns")

    def __init__(self, stamp_ns: int, mean: np.ndarray, cov: np.ndarray, error_map: np.ndarray) -> None:
        self.stamp_ns = int(stamp_ns)
        self.mean = mean
        self.cov = cov
        self.error_map = error_map


def open_packet(state: EkfState, rounding: Rounding | None = None) -> Packet:
    """The packet that starts at ``state``: ``D`` and ``Th`` zero and exactly known. With
    ``rounding`` (``wheel_rounding``) the last count's roundings join it, and the roundings
    of the count that will close it (fresh, independent of all before); its error map then
    starts from the eight-entry error ``[state, rounding]``."""
    if rounding is None:
        mean = np.zeros(PACKET_SIZE)
        mean[:STATE_SIZE] = state.mean
        cov = np.zeros((PACKET_SIZE, PACKET_SIZE))
        cov[:STATE_SIZE, :STATE_SIZE] = state.cov
        return Packet(state.stamp_ns, mean, cov, _EYE[PACKET_SIZE][:, :STATE_SIZE].copy())
    n = ROUNDING_SIZE
    mean = np.zeros(n)
    mean[:STATE_SIZE] = state.mean
    mean[IDO:ITO + 1] = rounding.mean
    cov = np.zeros((n, n))
    cov[:STATE_SIZE, :STATE_SIZE] = state.cov
    cov[:STATE_SIZE, IDO:ITO + 1] = rounding.cross
    cov[IDO:ITO + 1, :STATE_SIZE] = rounding.cross.T
    cov[IDO:ITO + 1, IDO:ITO + 1] = rounding.cov
    cov[IDN, IDN], cov[ITN, ITN] = rounding.fresh
    emap = np.zeros((n, PACKET_SIZE))
    emap[:STATE_SIZE, :STATE_SIZE] = np.eye(STATE_SIZE)
    emap[IDO, STATE_SIZE] = emap[ITO, STATE_SIZE + 1] = 1.0
    return Packet(state.stamp_ns, mean, cov, emap)


def packet_predict(p: Packet, t_ns: int, params: EkfParams) -> None:
    """Move ``p`` to ``t_ns`` (not before its stamp: a late reading is taken at the packet's
    time): ``D += v dt``, ``Th += w dt``, the rates' and the bias's process noise, the pose
    held at the packet's start."""
    dt_ns = int(t_ns) - p.stamp_ns
    if dt_ns <= 0:
        return
    dt = dt_ns * 1e-9
    n = p.mean.shape[0]
    jac = _EYE[n].copy()
    jac[ID, IV] = dt
    jac[ITH, IW] = dt
    m = p.mean
    m[ID] += m[IV] * dt
    m[ITH] += m[IW] * dt
    ql = params.accel_noise_density_mps2_per_sqrt_hz ** 2
    qa = params.angular_accel_noise_density_radps2_per_sqrt_hz ** 2
    d2, d3 = dt * dt / 2.0, dt ** 3 / 3.0
    if params.rate_only_process:
        d2 = d3 = 0.0
    q = np.zeros((n, n))
    q[ID, ID], q[ID, IV], q[IV, ID], q[IV, IV] = ql * d3, ql * d2, ql * d2, ql * dt
    q[ITH, ITH], q[ITH, IW], q[IW, ITH], q[IW, IW] = qa * d3, qa * d2, qa * d2, qa * dt
    q[IB, IB] = params.gyro_bias_walk_radps_per_sqrt_s ** 2 * dt
    cov = jac @ p.cov @ jac.T + q
    p.cov = 0.5 * (cov + cov.T)
    p.error_map = jac @ p.error_map
    p.stamp_ns = int(t_ns)


#: The rows a Schmidt update may hold (:func:`_update`): the pose at the packet's start, its position.
_POSE, _POSITION = slice(IX, IYAW + 1), slice(IX, IY + 1)


def _update(p: Packet, innovation: np.ndarray, h: np.ndarray, r: np.ndarray,
            hold: slice | None = None) -> None:
    """The Joseph-form update of ``p`` (the optimal gain: the base is moving); ``hold``:
    these rows of the gain zeroed, a Schmidt ("consider") update that leaves them where
    they are (the Joseph form keeps the covariance exact for it): :data:`_POSE` the pose at
    the packet's start, :data:`_POSITION` its position alone (the heading takes its gain)."""
    ph = p.cov @ h.T
    s = h @ ph + r
    gain = np.linalg.solve(s, ph.T).T
    if hold is not None:
        gain[hold] = 0.0
    p.mean = p.mean + gain @ innovation
    a = _EYE[p.mean.shape[0]] - gain @ h
    cov = a @ p.cov @ a.T + gain @ r @ gain.T
    p.cov = 0.5 * (cov + cov.T)
    p.error_map = a @ p.error_map


def packet_gyro(p: Packet, w_radps: float, params: EkfParams, yaw_rate_var_rad2ps2: float | None = None) -> None:
    """A gyro reading inside the packet: ``h = w + bias`` (:func:`robotd.odometry.ekf.update_gyro`)."""
    innovation = np.array([w_radps - p.mean[IW] - p.mean[IB]])
    _update(p, innovation, _H_GYRO[p.mean.shape[0]], gyro_noise_var(params, yaw_rate_var_rad2ps2))


def packet_gyro_mean(p: Packet, w_radps: float, dt_s: float, params: EkfParams,
                     yaw_rate_var_rad2ps2: float | None = None) -> None:
    """The packet's one gyro reading when it is the mean rate over the packet (``p`` at its
    end, ``dt_s`` long): ``h = Th / dt + bias``, an integrated measurement of the heading
    change, as the ticks' reading is of the distance. Its noise is the reading's
    (:func:`robotd.odometry.ekf.gyro_noise_var`).

    Why: :func:`packet_gyro` takes a reading for the rate at its stamp, and the packet's
    heading change integrates the rate before it up to the stamp and the one after. The
    Kobuki's raw-gyro reading is the mean of the samples since the previous packet (stamped
    in the middle of that interval): its rate times the packet's length is the heading
    change, up to the reading's noise. Taken at its stamp, half the packet got the previous
    packet's rate, and the white angular acceleration's ``dt^3 / 3`` term stood for that
    half; on a straight it made a keyframe edge's heading variance about twice what the
    heading's error was.

    The reading corrects the heading change, the rates, the bias and the heading the packet
    opened on (its error is the packets before's yaw rate), not the position there (a
    Schmidt update of those rows). That position correlates with the bias by the lever arm
    of the drive since the last stop, and through a yaw-rate ramp (a turn's start or end,
    which the white angular acceleration does not expect) each reading corrects the bias a
    little, always the same way: with the optimal gain the position then moved sideways
    while the base turned on the spot (1.3 mm over the first 11 deg of the demo's turn at
    184 s on seed 0, where its keyframe edge claimed 0.17 mm, NEES 91)."""
    n = p.mean.shape[0]
    h = np.zeros((1, n))
    h[0, ITH] = 1.0 / dt_s
    h[0, IB] = 1.0
    innovation = np.array([w_radps - float(h[0] @ p.mean)])
    _update(p, innovation, h, gyro_noise_var(params, yaw_rate_var_rad2ps2), hold=_POSITION)


def packet_wheels(p: Packet, ds_m: float, dyaw_rad: float, dt_s: float, params: EkfParams,
                  speed_var_m2ps2: float | None = None, yaw_rate_var_rad2ps2: float | None = None) -> None:
    """The wheel reading of the packet (``p`` at its end): the distance ``ds_m`` and heading
    change ``dyaw_rad`` over ``dt_s`` measure ``(D, Th)``, with the rate noise of
    :func:`robotd.odometry.ekf.wheel_noise` at the mean rates over ``dt_s`` (its continuous
    slip included) times ``dt_s`` (and the slip
    test's widening, :func:`robotd.odometry.ekf.slip_variances`, on the yaw rate's
    disagreement over the packet).

    With the roundings in the packet (:func:`open_packet` with a :class:`Rounding`) the
    ticks measure ``D`` and ``Th`` plus the start's rounding minus the end's, and the white
    noise keeps only what exceeds the two roundings' variance (``2 fresh``): the rate noise
    of the calibration's model is the ticks' own, which the roundings now carry.

    The heading change corrects ``Th``, the rates and the bias, not the pose held at the
    packet's start (a Schmidt update of that row, as the filter's at rest; the distance's
    row keeps the optimal gain, which moves the pose along its correlation with the speed).
    The optimal gain would move that pose along its correlation with the yaw rate and the
    bias, which spans the run (a bias error since the last stop has turned the heading,
    and the heading the position, by metres of lever arm), by the wheels' heading change:
    a reading whose modelled yaw-rate noise (``wheel_w_noise_*``, 0.3 rad/s at 0.5 m/s) is
    a bound for the wheels' systematic errors, not their white noise (a few tenths of a
    milliradian per packet: the ticks' quantisation and slip). Each reading then added
    ``K R K^T`` of 0.1-0.35 mm to the pose (the more the later in a run), which the
    keyframe edges claimed as motion noise while the true corrections were a twentieth of
    it."""
    v, w = ds_m / dt_s, dyaw_rad / dt_s
    sv, sw = wheel_noise(v, w, params, False, speed_var_m2ps2, yaw_rate_var_rad2ps2, dt_s)
    n = p.mean.shape[0]
    h = _H_INC[n]
    predicted = h @ p.mean
    innovation = np.array([ds_m - predicted[0], dyaw_rad - predicted[1]])
    var_v, var_w = sv * sv, sw * sw
    dt2 = dt_s * dt_s
    if n == ROUNDING_SIZE and speed_var_m2ps2 is None and yaw_rate_var_rad2ps2 is None:
        fresh_d, fresh_t = p.cov[IDN, IDN], p.cov[ITN, ITN]
        var_v = max(var_v - 2.0 * fresh_d / dt2, 0.0)
        var_w = max(var_w - 2.0 * fresh_t / dt2, 0.0)
    if params.slip_gate_sigma > 0.0 and speed_var_m2ps2 is None:
        yaw_var = float(p.cov[ITH, ITH]) / dt2
        speed_var = float(h[0] @ p.cov @ h[0]) / dt2 + var_v  # the distance's innovation, in speed
        add_v, add_w = slip_variances(float(innovation[1]) / dt_s, yaw_var, params, dt_s, turning(w, params),
                                      speed_changing(float(innovation[0]) / dt_s, speed_var, params))
        var_v += add_v
        var_w += add_w
    # the two rows one after the other (their noises are independent: the same update as
    # both at once), the heading change's with the pose held
    _update(p, innovation[:1], h[:1], np.array([[var_v * dt2]]))
    _update(p, np.array([dyaw_rad - h[1] @ p.mean]), h[1:], np.array([[var_w * dt2]]), hold=_POSE)


def close_packet(p: Packet, rounding: Rounding | None = None) -> tuple[EkfState, np.ndarray]:
    """The six-entry state at the packet's end (the pose moved along the arc of ``(D, Th)``
    from the packet's start) and the ``(6, 6)`` linear map of the error from the state the
    packet opened on to it. With the roundings in the packet, ``rounding`` (the one it
    opened with) becomes the closing count's, and the map is ``(8, 8)``, of the error
    ``[state, rounding]`` from the packet's start to its end."""
    m = p.mean
    base = np.array([m[IX], m[IY], m[IYAW], m[ID], m[ITH], m[IB]])
    moved, jac, _c, _s = _arc(base, 1.0)  # dt = 1: "v" is D, "w" is Th
    n = p.mean.shape[0]
    out = STATE_SIZE if n == PACKET_SIZE else PACKET_SIZE
    g = np.zeros((out, n))
    g[:3, :3] = jac[:3, :3]
    g[:3, ID] = jac[:3, IV]
    g[:3, ITH] = jac[:3, IW]
    g[IV, IV] = g[IW, IW] = g[IB, IB] = 1.0
    if n == ROUNDING_SIZE:
        g[STATE_SIZE, IDN] = g[STATE_SIZE + 1, ITN] = 1.0
    mean = np.array([moved[IX], moved[IY], wrap_angle(float(moved[IYAW])), m[IV], m[IW], m[IB]])
    cov = g @ p.cov @ g.T
    cov = 0.5 * (cov + cov.T)
    if not (np.all(np.isfinite(mean)) and math.isfinite(float(cov.trace()))):
        raise FloatingPointError("the packet's state is not finite")
    if n == ROUNDING_SIZE:
        if rounding is None:
            raise ValueError("a packet with the roundings closes into a Rounding")
        rounding.mean = np.array([m[IDN], m[ITN]])
        rounding.cov = cov[STATE_SIZE:, STATE_SIZE:].copy()
        rounding.cross = cov[:STATE_SIZE, STATE_SIZE:].copy()
        cov = cov[:STATE_SIZE, :STATE_SIZE].copy()
    return EkfState._own(p.stamp_ns, mean, cov), g @ p.error_map
