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
    wheel_noise,
)
from robotd.base.geometry import wrap_angle

__all__ = ["ID", "ITH", "PACKET_SIZE", "Packet", "close_packet", "open_packet", "packet_gyro",
           "packet_predict", "packet_wheels"]

PACKET_SIZE = STATE_SIZE + 2
ID, ITH = STATE_SIZE, STATE_SIZE + 1
_EYE8 = np.eye(PACKET_SIZE)
_H_GYRO8 = np.zeros((1, PACKET_SIZE))
_H_GYRO8[0, IW] = 1.0
_H_GYRO8[0, IB] = 1.0
_H_INC = np.zeros((2, PACKET_SIZE))
_H_INC[0, ID] = 1.0
_H_INC[1, ITH] = 1.0


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


def open_packet(state: EkfState) -> Packet:
    """The packet that starts at ``state``: ``D`` and ``Th`` zero and exactly known."""
    mean = np.zeros(PACKET_SIZE)
    mean[:STATE_SIZE] = state.mean
    cov = np.zeros((PACKET_SIZE, PACKET_SIZE))
    cov[:STATE_SIZE, :STATE_SIZE] = state.cov
    return Packet(state.stamp_ns, mean, cov, _EYE8[:, :STATE_SIZE].copy())


def packet_predict(p: Packet, t_ns: int, params: EkfParams) -> None:
    """Move ``p`` to ``t_ns`` (not before its stamp: a late reading is taken at the packet's
    time): ``D += v dt``, ``Th += w dt``, the rates' and the bias's process noise, the pose
    held at the packet's start."""
    dt_ns = int(t_ns) - p.stamp_ns
    if dt_ns <= 0:
        return
    dt = dt_ns * 1e-9
    jac = _EYE8.copy()
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
    q = np.zeros((PACKET_SIZE, PACKET_SIZE))
    q[ID, ID], q[ID, IV], q[IV, ID], q[IV, IV] = ql * d3, ql * d2, ql * d2, ql * dt
    q[ITH, ITH], q[ITH, IW], q[IW, ITH], q[IW, IW] = qa * d3, qa * d2, qa * d2, qa * dt
    q[IB, IB] = params.gyro_bias_walk_radps_per_sqrt_s ** 2 * dt
    cov = jac @ p.cov @ jac.T + q
    p.cov = 0.5 * (cov + cov.T)
    p.error_map = jac @ p.error_map
    p.stamp_ns = int(t_ns)


def _update(p: Packet, innovation: np.ndarray, h: np.ndarray, r: np.ndarray) -> None:
    """The Joseph-form update of ``p`` (the optimal gain: the base is moving)."""
    ph = p.cov @ h.T
    s = h @ ph + r
    gain = np.linalg.solve(s, ph.T).T
    p.mean = p.mean + gain @ innovation
    a = _EYE8 - gain @ h
    cov = a @ p.cov @ a.T + gain @ r @ gain.T
    p.cov = 0.5 * (cov + cov.T)
    p.error_map = a @ p.error_map


def packet_gyro(p: Packet, w_radps: float, params: EkfParams, yaw_rate_var_rad2ps2: float | None = None) -> None:
    """A gyro reading inside the packet: ``h = w + bias`` (:func:`robotd.odometry.ekf.update_gyro`)."""
    innovation = np.array([w_radps - p.mean[IW] - p.mean[IB]])
    _update(p, innovation, _H_GYRO8, gyro_noise_var(params, yaw_rate_var_rad2ps2))


def packet_wheels(p: Packet, ds_m: float, dyaw_rad: float, dt_s: float, params: EkfParams,
                  speed_var_m2ps2: float | None = None, yaw_rate_var_rad2ps2: float | None = None) -> None:
    """The wheel reading of the packet (``p`` at its end): the distance ``ds_m`` and heading
    change ``dyaw_rad`` over ``dt_s`` measure ``(D, Th)``, with the rate noise of
    :func:`robotd.odometry.ekf.wheel_noise` at the mean rates times ``dt_s`` (and the slip
    test's widening, :func:`robotd.odometry.ekf.slip_variances`, on the yaw rate's
    disagreement over the packet)."""
    v, w = ds_m / dt_s, dyaw_rad / dt_s
    sv, sw = wheel_noise(v, w, params, False, speed_var_m2ps2, yaw_rate_var_rad2ps2)
    innovation = np.array([ds_m - p.mean[ID], dyaw_rad - p.mean[ITH]])
    var_v, var_w = sv * sv, sw * sw
    if params.slip_gate_sigma > 0.0 and speed_var_m2ps2 is None:
        add_v, add_w = slip_variances(float(innovation[1]) / dt_s, float(p.cov[ITH, ITH]) / dt_s ** 2, params)
        var_v += add_v
        var_w += add_w
    dt2 = dt_s * dt_s
    _update(p, innovation, _H_INC, np.array([[var_v * dt2, 0.0], [0.0, var_w * dt2]]))


def close_packet(p: Packet) -> tuple[EkfState, np.ndarray]:
    """The six-entry state at the packet's end (the pose moved along the arc of ``(D, Th)``
    from the packet's start) and the ``(6, 6)`` linear map of the error from the state the
    packet opened on to it."""
    m = p.mean
    base = np.array([m[IX], m[IY], m[IYAW], m[ID], m[ITH], m[IB]])
    moved, jac, _c, _s = _arc(base, 1.0)  # dt = 1: "v" is D, "w" is Th
    g = np.zeros((STATE_SIZE, PACKET_SIZE))
    g[:3, :3] = jac[:3, :3]
    g[:3, ID] = jac[:3, IV]
    g[:3, ITH] = jac[:3, IW]
    g[IV, IV] = g[IW, IW] = g[IB, IB] = 1.0
    mean = np.array([moved[IX], moved[IY], wrap_angle(float(moved[IYAW])), m[IV], m[IW], m[IB]])
    cov = g @ p.cov @ g.T
    cov = 0.5 * (cov + cov.T)
    if not (np.all(np.isfinite(mean)) and math.isfinite(float(cov.trace()))):
        raise FloatingPointError("the packet's state is not finite")
    return EkfState._own(p.stamp_ns, mean, cov), g @ p.error_map
