"""A relative-pose measurement between a past keyframe and now, fused into the wheel + gyro
EKF by stochastic cloning (Roumeliotis and Burdick 2002).

Floor visual odometry (paper 003, Sec. IV-D) measures ``z = x_{k-1}^-1 (+) x_k``: the pose
of keyframe ``k`` in the frame of keyframe ``k-1``, with covariance ``R``. The filter's
state :data:`robotd.odometry.ekf.STATE_SIZE` holds only the current pose, so the pose at
keyframe ``k-1`` is kept as a *clone*: when a keyframe is taken, its pose ``c`` (3) is
copied with its covariance and with the cross-covariance ``X = Cov(state, c)`` (6 x 3).
Until the next keyframe, every filter step carries ``X`` along:

- a prediction ``state' = f(state)`` with Jacobian ``F``: ``X' = F X``;
- a wheel or gyro update with gain ``K`` and measurement matrix ``H``: ``X' = (I - K H) X``.

The clone itself is not refined by those updates (a Schmidt-style "consider" clone: rates
say almost nothing about a past pose), which keeps the joint covariance exact for the
estimator actually run. At keyframe ``k`` the measurement ``h(state, c) = c^-1 (+) pose``
is applied to the joint ``(state, c)`` by an ordinary EKF update (Joseph form), then the
clone is replaced by one of the new keyframe.

Why not the simpler alternative, treating the previous keyframe pose as known and
inflating ``R`` by its covariance ``P_{k-1}``: the current pose and the pose at ``k-1``
share all the error accumulated before ``k-1``, so that treatment counts ``P_{k-1}`` twice.
The gain on a yaw drift becomes ``(P_{k-1} + q) / (2 P_{k-1} + q + r)`` instead of the right
``q / (q + r)`` (``q``: the yaw variance added since ``k-1``, ``r``: the measurement's),
about 1/2 however good the measurement is, and the covariance shrinks every keyframe
though the absolute heading is no better known: an overconfident filter. The clone costs a
6 x 3 matrix and a 3 x 3 product per filter step.

Everything here is a pure function of its inputs; :class:`~robotd.odometry.fusion.OdometryFilter`
keeps the clone and calls them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from robotd.base.geometry import (
    between,
    compose,
    compose_jacobians,
    inverse,
    wrap_angle,
)
from robotd.odometry.ekf import rate_gain

__all__ = ["PoseClone", "clone_after_predict", "clone_after_update", "clone_pose",
           "relative_pose_covariance", "relative_pose_jacobians",
           "shift_jacobian", "shift_measurement", "update_relative_pose"]

_IYAW = 2


@dataclass(frozen=True, eq=False)
class PoseClone:
    """The filter's pose at the last keyframe, kept for the next relative measurement.

    Fields:
        keyframe_stamp_ns: stamp of the keyframe (camera frame) the clone stands for.
        pose: ``(3,)`` the filter's ``(x_m, y_m, yaw_rad)`` when the clone was taken.
        cov: ``(3, 3)`` its covariance.
        cross: ``(n, 3)`` covariance of the filter's current state with ``pose``.
        offset: ``(3,)`` ``pose`` in the frame of the filter's pose at ``keyframe_stamp_ns``
            (the filter is usually a few ms past the frame when it learns of it).
    """

    keyframe_stamp_ns: int
    pose: np.ndarray
    cov: np.ndarray
    cross: np.ndarray
    offset: np.ndarray


def clone_pose(mean: np.ndarray, cov: np.ndarray, keyframe_stamp_ns: int,
               offset: np.ndarray | None = None) -> PoseClone:
    """Clone the pose (the first three entries) of a state ``mean (n,)``, ``cov (n, n)``."""
    mean = np.asarray(mean, float)
    cov = np.asarray(cov, float)
    off = np.zeros(3) if offset is None else np.asarray(offset, float).reshape(3)
    return PoseClone(int(keyframe_stamp_ns), mean[:3].copy(), cov[:3, :3].copy(), cov[:, :3].copy(), off)


def clone_after_predict(clone: PoseClone, jac: np.ndarray) -> PoseClone:
    """The clone after a prediction with state Jacobian ``jac (n, n)``: ``X' = F X``."""
    return PoseClone(clone.keyframe_stamp_ns, clone.pose, clone.cov, jac @ clone.cross, clone.offset)


def clone_after_update(clone: PoseClone, prior_cov: np.ndarray | None, h: np.ndarray, r: np.ndarray,
                       smooth_pose: bool = False, *, gain: np.ndarray | None = None) -> PoseClone:
    """The clone after a measurement update of the state alone: ``X' = (I - K H) X`` with
    ``K = P H^T (H P H^T + R)^-1`` from the state's covariance ``P`` before the update (its
    pose rows zeroed with ``smooth_pose``, as the filter's rate updates do); ``gain``: that
    ``K`` when the caller has it (then ``prior_cov`` is not read)."""
    if gain is None:
        assert prior_cov is not None
        gain = rate_gain(prior_cov, h, r, smooth_pose)
    cross = clone.cross - gain @ (h @ clone.cross)
    return PoseClone(clone.keyframe_stamp_ns, clone.pose, clone.cov, cross, clone.offset)


def relative_pose_jacobians(clone_xyyaw: np.ndarray, pose_xyyaw: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``h = clone^-1 (+) pose`` ``(3,)`` and its ``(3, 3)`` Jacobians with respect to the
    current pose and to the clone."""
    h = between(clone_xyyaw, pose_xyyaw)
    c, s = math.cos(float(clone_xyyaw[2])), math.sin(float(clone_xyyaw[2]))
    rt = np.array([[c, s], [-s, c]])
    j_pose = np.eye(3)
    j_pose[:2, :2] = rt
    j_clone = -np.eye(3)
    j_clone[:2, :2] = -rt
    j_clone[0, 2], j_clone[1, 2] = h[1], -h[0]  # d(R^T (p - c)) / d(clone yaw)
    return h, j_pose, j_clone


def relative_pose_covariance(pose_xyyaw: np.ndarray, pose_cov: np.ndarray, clone: PoseClone,
                             jacobians: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                             ) -> tuple[np.ndarray, np.ndarray]:
    """The filter's motion since the clone, ``h = clone^-1 (+) pose`` ``(3,)``, and its
    covariance ``(3, 3)`` from the joint covariance of ``(pose, clone)``: ``pose_cov``, the
    clone's own and their cross-covariance (the first three rows of ``clone.cross``),
    ``J_p P J_p^T + J_c P_c J_c^T + J_p X J_c^T + (J_p X J_c^T)^T``. Everything the pose
    and the clone share (the error accumulated before the clone, the gyro bias's part in
    both) cancels here, which the difference of two absolute covariances cannot do.
    ``jacobians``: :func:`relative_pose_jacobians` of ``(clone.pose, pose_xyyaw)`` when the
    caller has them already (the same numbers)."""
    h, j_pose, j_clone = (relative_pose_jacobians(clone.pose, np.asarray(pose_xyyaw, float))
                          if jacobians is None else jacobians)
    cross = j_pose @ clone.cross[:3] @ j_clone.T
    cov = j_pose @ np.asarray(pose_cov, float) @ j_pose.T + j_clone @ clone.cov @ j_clone.T + cross + cross.T
    return h, 0.5 * (cov + cov.T)


def shift_measurement(z: np.ndarray, r: np.ndarray, offset_prev: np.ndarray,
                      offset_now: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A measurement between two keyframe stamps moved to the filter times of the clones:
    ``offset_prev^-1 (+) z (+) offset_now``, its covariance ``J R J^T`` (the offsets, a
    few ms of the filter's own motion, are taken as exact)."""
    shifted, j = shift_jacobian(z, offset_prev, offset_now)
    return shifted, j @ np.asarray(r, float) @ j.T


def shift_jacobian(z: np.ndarray, offset_prev: np.ndarray, offset_now: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``offset_prev^-1 (+) z (+) offset_now`` ``(3,)`` and its ``(3, 3)`` Jacobian with
    respect to ``z`` (:func:`shift_measurement` carries a covariance through it; the
    keyframe edge's bias terms, a cross-covariance)."""
    z = np.asarray(z, float)
    inv_prev = inverse(np.asarray(offset_prev, float))
    w = compose(z, offset_now)
    j_z, _ = compose_jacobians(z, offset_now)
    _, j_w = compose_jacobians(inv_prev, w)
    return compose(inv_prev, w), j_w @ j_z


def update_relative_pose(mean: np.ndarray, cov: np.ndarray, clone: PoseClone, z: np.ndarray,
                         r: np.ndarray, consider: tuple[int, ...] = ()) -> tuple[np.ndarray, np.ndarray, float]:
    """EKF update of the joint ``(state, clone)`` with ``z = clone^-1 (+) pose``, ``(3,)``,
    covariance ``r (3, 3)``.

    ``mean (n,)``, ``cov (n, n)``: the state (pose first). ``consider``: indices of state
    entries the measurement does not update (their gain rows zeroed, a Schmidt "consider"
    update; the Joseph form keeps the covariance right for that gain). Returns the updated
    state's mean and covariance and the normalised innovation squared (chi-square, 3
    degrees of freedom) for gating by the caller.
    """
    mean = np.asarray(mean, float)
    n = len(mean)
    pj, hm, h = _joint(mean, cov, clone)
    innovation = np.asarray(z, float) - h
    innovation[_IYAW] = wrap_angle(float(innovation[_IYAW]))
    phT = pj @ hm.T
    s = hm @ phT + r
    nis = float(innovation @ np.linalg.solve(s, innovation))
    gain = np.linalg.solve(s, phT.T).T
    if consider:
        gain[list(consider)] = 0.0
    a = np.eye(n + 3) - gain @ hm
    joint = a @ pj @ a.T + gain @ r @ gain.T
    new_mean = mean + (gain @ innovation)[:n]
    new_mean[_IYAW] = wrap_angle(float(new_mean[_IYAW]))
    new_cov = joint[:n, :n]
    return new_mean, 0.5 * (new_cov + new_cov.T), nis


def _joint(mean: np.ndarray, cov: np.ndarray, clone: PoseClone) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The joint ``(state, clone)`` covariance ``(n + 3, n + 3)``, the Jacobian ``(3, n + 3)``
    of ``clone^-1 (+) pose`` in it, and that predicted relative pose ``(3,)``."""
    n = len(mean)
    pj = np.zeros((n + 3, n + 3))
    pj[:n, :n] = cov
    pj[:n, n:] = clone.cross
    pj[n:, :n] = clone.cross.T
    pj[n:, n:] = clone.cov
    h, j_pose, j_clone = relative_pose_jacobians(clone.pose, mean[:3])
    hm = np.zeros((3, n + 3))
    hm[:, :3] = j_pose
    hm[:, n:] = j_clone
    return pj, hm, h
