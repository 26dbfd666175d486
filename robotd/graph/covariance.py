"""The uncertainty of the loop-corrected pose: a keyframe's marginal covariance from the
pose graph, carried forward by the odometry since that keyframe (no I/O).

What ``robotd/pose`` (``geometry_msgs/PoseWithCovarianceStamped``, map frame) publishes:
the robot's pose in the map is the newest corrected keyframe's pose composed with the
odometry increment since it, ``T_map_now = T_map_k * (T_odom_k^-1 * T_odom_now)``, and its
covariance is, to first order,

    C_now = J_k C_k J_k^T + R C_inc R^T

- ``C_k``: the keyframe's marginal covariance in the graph (iSAM2's, Kaess et al. 2012:
  :meth:`robotd.graph.incremental.IncrementalGraph.marginal_covariance`), moved from the
  pose's own tangent space (GTSAM's ``Pose2`` convention: x, y along the keyframe's axes,
  then yaw) to the map frame's axes by the keyframe's rotation;
- ``J_k``: the Jacobian of the composition with respect to the keyframe pose (map axes);
- ``C_inc``: what the odometry added between the keyframe and now, in the odometry frame's
  axes: the fused covariance now minus the keyframe's carried along,
  ``Sigma_now - J Sigma_k J^T`` (exact for dead reckoning, whose covariance grows as
  ``J Sigma J^T + Q``; with the filter's velocity states and visual updates an
  approximation), symmetrised and its negative eigenvalues (rounding) set to zero;
- ``R``: the rotation of ``odom`` in ``map`` (the yaw of ``map -> odom``).

Without loops the keyframe's marginal grows along the chain; a loop to an older, better
known keyframe shrinks it, and the published covariance with it.
"""

from __future__ import annotations

import numpy as np

from robotd.base.geometry import compose, inverse


def _rotation3(yaw_rad: float) -> np.ndarray:
    """``(3, 3)``: rotate ``(x, y)`` by ``yaw_rad``, keep the yaw."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _compose_jacobian(first_xyyaw: np.ndarray, result_xyyaw: np.ndarray) -> np.ndarray:
    """``(3, 3)`` Jacobian of ``first * delta`` with respect to ``first``, both in world axes
    (the translation swings with the first pose's yaw about its position)."""
    return np.array([[1.0, 0.0, -(result_xyyaw[1] - first_xyyaw[1])],
                     [0.0, 1.0, result_xyyaw[0] - first_xyyaw[0]],
                     [0.0, 0.0, 1.0]])


def tangent_to_world(pose_xyyaw: np.ndarray, cov_tangent: np.ndarray) -> np.ndarray:
    """``(3, 3)`` covariance in world axes of a pose whose ``(3, 3)`` covariance is given in
    its own tangent space (GTSAM's ``Pose2`` marginals: x, y along the pose's axes, yaw)."""
    r = _rotation3(float(pose_xyyaw[2]))
    out: np.ndarray = r @ np.asarray(cov_tangent, float) @ r.T
    sym: np.ndarray = 0.5 * (out + out.T)
    return sym


def odometry_increment_covariance(odom_k_xyyaw: np.ndarray, cov_k: np.ndarray,
                                  odom_now_xyyaw: np.ndarray, cov_now: np.ndarray) -> np.ndarray:
    """``(3, 3)`` covariance the odometry added from keyframe pose ``odom_k`` (covariance
    ``cov_k``) to ``odom_now`` (``cov_now``), all in the odometry frame's axes:
    ``cov_now - J cov_k J^T``, symmetrised, negative eigenvalues set to zero."""
    j = _compose_jacobian(np.asarray(odom_k_xyyaw, float), np.asarray(odom_now_xyyaw, float))
    inc = np.asarray(cov_now, float) - j @ np.asarray(cov_k, float) @ j.T
    inc = 0.5 * (inc + inc.T)
    w, v = np.linalg.eigh(inc)
    psd: np.ndarray = (v * np.clip(w, 0.0, None)) @ v.T
    return psd


def corrected_pose(map_k_xyyaw: np.ndarray, map_k_cov_world: np.ndarray, odom_k_xyyaw: np.ndarray,
                   odom_k_cov: np.ndarray, odom_now_xyyaw: np.ndarray,
                   odom_now_cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The robot's pose in the map and its covariance (see the module notes).

    ``map_k_xyyaw`` ``(3,)`` and ``map_k_cov_world`` ``(3, 3)``: the keyframe in the graph
    (map axes: :func:`tangent_to_world` of its marginal); ``odom_k_xyyaw``/``odom_k_cov``:
    the fused odometry at the keyframe's stamp; ``odom_now_xyyaw``/``odom_now_cov``: the
    fused odometry now. Metres and radians. Returns ``(pose (3,), covariance (3, 3))``.
    """
    map_k = np.asarray(map_k_xyyaw, float)
    odom_k = np.asarray(odom_k_xyyaw, float)
    delta = compose(inverse(odom_k), np.asarray(odom_now_xyyaw, float))
    now = compose(map_k, delta)
    j = _compose_jacobian(map_k, now)
    r = _rotation3(float(map_k[2] - odom_k[2]))
    inc = odometry_increment_covariance(odom_k, odom_k_cov, odom_now_xyyaw, odom_now_cov)
    cov: np.ndarray = j @ np.asarray(map_k_cov_world, float) @ j.T + r @ inc @ r.T
    return now, 0.5 * (cov + cov.T)
