"""Odometry increments between keyframes, as pose-graph edges with their information.

A pose graph chains consecutive keyframes with the odometry's relative transform
``d = x_a^-1 (+) x_b`` (the pose of keyframe b in the frame of keyframe a) and its
uncertainty. The filter gives the *absolute* pose covariances ``P_a`` and ``P_b``. Writing
``x_b = x_a (+) d`` and linearising,

    P_b = J_a P_a J_a^T + J_d S J_d^T,   J_a = d x_b / d x_a,  J_d = d x_b / d d,

so the increment's covariance is ``S = J_d^-1 (P_b - J_a P_a J_a^T) J_d^-T``. This holds
when the increment is independent of the pose at a, which a filter's motion increments
are up to the slowly varying gyro bias (it correlates consecutive increments a little).
``P_b - J_a P_a J_a^T`` can then lose definiteness by rounding or by that correlation, so
the result is symmetrised and its eigenvalues are raised to a floor (``min_sigma_m``,
``min_sigma_rad``). The information is ``S^-1``.

The daemon does not link keyframes this way any more: late in a run the two absolute
covariances are large, the speed, yaw-rate and bias states correlate the increment with
the pose at a, and at turns on the spot and stops the difference lost definiteness by
millimetres, so the floor stood in for an unknown error (NEES 7.3 where 3 is expected on
the 110 m office route). The map's edges come from the filter's pose clone
(:meth:`robotd.odometry.fusion.OdometryFilter.keyframe_edge`); this remains the fallback
for a keyframe the filter has no clone for, and :func:`floor_covariance` is shared.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from robotd.base.geometry import (
    between,
    between_error_covariance,
    compose,
    information_from_covariance,
    se2_exp,
    se2_log,
    wrap_angle,
)

if TYPE_CHECKING:
    from robotd.odometry.history import EdgeBiasTerms


def increment_covariance(pose_a: np.ndarray, cov_a: np.ndarray, pose_b: np.ndarray,
                         cov_b: np.ndarray, *, min_sigma_m: float = 1e-4,
                         min_sigma_rad: float = 1e-4) -> np.ndarray:
    """Covariance ``(3, 3)`` of ``between(pose_a, pose_b)`` over ``(dx_m, dy_m, dyaw_rad)``.

    ``pose_*``: ``(3,)`` x_m, y_m, yaw_rad; ``cov_*``: their ``(3, 3)`` filter covariances.
    See the module notes for the derivation and the eigenvalue floor.
    """
    xa, ya, tha = (float(v) for v in pose_a)
    xb, yb = float(pose_b[0]), float(pose_b[1])
    j_a = np.array([[1.0, 0.0, -(yb - ya)],
                    [0.0, 1.0, xb - xa],
                    [0.0, 0.0, 1.0]])
    c, s = math.cos(tha), math.sin(tha)
    j_d_inv = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # inverse of the rotation
    grown = np.asarray(cov_b, float) - j_a @ np.asarray(cov_a, float) @ j_a.T
    cov = j_d_inv @ grown @ j_d_inv.T
    return floor_covariance(cov, min_sigma_m=min_sigma_m, min_sigma_rad=min_sigma_rad)


def floor_covariance(cov: np.ndarray, *, min_sigma_m: float = 1e-4,
                     min_sigma_rad: float = 1e-4) -> np.ndarray:
    """``cov (3, 3)`` over ``(dx_m, dy_m, dyaw_rad)``, symmetrised, with each eigenvalue
    raised to the floor of its axis mix (``min_sigma_m`` for x and y, ``min_sigma_rad``
    for yaw). An edge no better known than that keeps the pose graph well conditioned: a
    straight drive's lateral offset and heading change are nearly the same error in the
    filter (sigma of their difference ~10 um over 5 cm), which iSAM2 cannot factor beside
    loop edges of 0.1 mm."""
    cov = np.asarray(cov, float)
    cov = 0.5 * (cov + cov.T)
    floor = np.diag([min_sigma_m ** 2, min_sigma_m ** 2, min_sigma_rad ** 2])
    w, v = np.linalg.eigh(cov)
    floor_w = np.einsum("ij,jk,ki->i", v.T, floor, v)
    return (v * np.maximum(w, floor_w)) @ v.T


def odometry_edge(pose_a: np.ndarray, cov_a: np.ndarray, pose_b: np.ndarray,
                  cov_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The edge from keyframe a to b: ``(delta (3,), information (3, 3))``, the information
    of the error as the pose graph measures it (:func:`robotd.base.geometry.between_error_covariance`)."""
    delta = between(np.asarray(pose_a, float), np.asarray(pose_b, float))
    cov = between_error_covariance(delta, increment_covariance(pose_a, cov_a, pose_b, cov_b))
    return delta, information_from_covariance(cov)


def combine_edges(a: tuple[np.ndarray, np.ndarray],
                  b: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Two independent measurements of the same edge, ``(delta (3,), covariance (3, 3))``
    each with its covariance as the pose graph measures the error
    (:func:`robotd.base.geometry.between_error_covariance`), as one: the pose that
    minimises both factors' errors ``log(z^-1 (+) x)`` weighted by their information (a few
    Gauss-Newton steps from ``a``), with the inverse of the summed information at it, as
    the graph would have it from the two factors.
    """
    za, zb = np.asarray(a[0], float), np.asarray(b[0], float)
    infos = [information_from_covariance(a[1]), information_from_covariance(b[1])]
    x = za.copy()
    for _ in range(_COMBINE_STEPS):
        hess, grad = np.zeros((3, 3)), np.zeros(3)
        for z, info in zip((za, zb), infos):
            r, jac = _error_and_jacobian(z, x)
            hess += jac.T @ info @ jac
            grad += jac.T @ info @ r
        step = -np.linalg.solve(hess, grad)
        x = compose(x, se2_exp(step))
        if np.abs(step).max() < 1e-12:
            break
    hess = np.zeros((3, 3))
    for z, info in zip((za, zb), infos):
        jac = _error_and_jacobian(z, x)[1]
        hess += jac.T @ info @ jac
    cov = np.linalg.inv(hess)
    return x, 0.5 * (cov + cov.T)


_COMBINE_STEPS = 5


def combine_bias_terms(a_cov: np.ndarray, combined_cov: np.ndarray, terms: EdgeBiasTerms,
                       scale_share: np.ndarray | None = None) -> EdgeBiasTerms:
    """The bias terms of an edge combined from the wheel + gyro edge (covariance ``a_cov``
    ``(3, 3)``, its terms ``terms``) and an independent measurement that does not see the
    gyro bias (a visual step) by :func:`combine_edges` (covariance ``combined_cov``).

    To first order the combined edge moves by ``K = C_c I_a`` per unit of the wheel + gyro
    edge's error (``I_a`` its information), so its error per rad/s of bias error is
    ``K J`` and its covariance given the bias ``C_c - P (K J)(K J)^T``: what is left of the
    combined covariance once the bias's share is taken out (``K C_given K^T`` plus the
    other measurement's share, never below zero). The bias's own figures (estimate,
    variance, chain step) are the filter's, unchanged. The twin's scale errors reach the
    combined edge through the same ``K`` (``scale_gain``). ``scale_share``: ``(3, 3)`` the
    twin's edge's covariance from a pose graph's scale variable (``J_s Sigma_s J_s^T``),
    already in ``a_cov`` (the combination weighed the twin by its marginal over the scale,
    as over the bias); its share ``K S K^T`` is taken out of the combined covariance too."""
    k = np.asarray(combined_cov, float) @ information_from_covariance(np.asarray(a_cov, float))
    jac = k @ np.asarray(terms.jac_bias, float)
    cond = np.asarray(combined_cov, float) - terms.bias_var * np.outer(jac, jac)
    if scale_share is not None:
        cond = cond - k @ np.asarray(scale_share, float) @ k.T
    gain = k if terms.scale_gain is None else k @ np.asarray(terms.scale_gain, float)
    return terms._replace(cov_given_bias=floor_covariance(0.5 * (cond + cond.T)), jac_bias=jac, scale_gain=gain)


def edge_disagreement(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    """Mahalanobis distance squared between two independent measurements of one edge
    (as :func:`combine_edges` takes them): ``e^T (A + B)^-1 e`` with ``e = log(a^-1 (+) b)``;
    chi-square with 3 degrees of freedom when both are right."""
    e = se2_log(between(np.asarray(a[0], float), np.asarray(b[0], float)))
    s = np.asarray(a[1], float) + np.asarray(b[1], float)
    return float(e @ np.linalg.solve(s, e))


_EPS = 1e-7  # the central differences' step (the perturbations below are precomputed for it)


def _error_and_jacobian(z: np.ndarray, x: np.ndarray, eps: float = _EPS) -> tuple[np.ndarray, np.ndarray]:
    """``log(z^-1 (+) x)`` and its Jacobian ``(3, 3)`` in a right perturbation of ``x``
    (central differences: the error's own Jacobian is near the identity).

    The same arithmetic as :func:`robotd.base.geometry.between`, ``compose``, ``se2_exp``
    and ``se2_log``, on Python floats: the seven errors are one pose each, and NumPy's cost
    per call on three numbers was most of the visual odometry stage's time. What the seven
    share is computed once: the cosines and sines of ``z^-1``'s and ``x``'s headings, and
    the six perturbations ``exp(+-eps e_k)`` (constants at the default ``eps``)."""
    zt = (float(z[0]), float(z[1]), float(z[2]))
    xt = (float(x[0]), float(x[1]), float(x[2]))
    # z^-1 once (geometry.inverse)
    c, s = math.cos(zt[2]), math.sin(zt[2])
    zi = (-c * zt[0] - s * zt[1], s * zt[0] - c * zt[1], wrap_angle(-zt[2]))
    cz, sz = math.cos(zi[2]), math.sin(zi[2])
    cx, sx = math.cos(xt[2]), math.sin(xt[2])
    r = _log(_compose_cs(zi, cz, sz, xt))
    jac = np.empty((3, 3))
    for k, (step_plus, step_minus) in enumerate(_PERTURBATIONS if eps == _EPS else _perturbations(eps)):
        plus = _log(_compose_cs(zi, cz, sz, _compose_cs(xt, cx, sx, step_plus)))
        minus = _log(_compose_cs(zi, cz, sz, _compose_cs(xt, cx, sx, step_minus)))
        jac[0, k] = (plus[0] - minus[0]) / (2 * eps)
        jac[1, k] = (plus[1] - minus[1]) / (2 * eps)
        jac[2, k] = (plus[2] - minus[2]) / (2 * eps)
    return np.array(r), jac


_Pose = tuple[float, float, float]
_TWO_PI = 2.0 * math.pi  # robotd.base.geometry's


def _exp(u: float, v: float, w: float) -> _Pose:
    """:func:`robotd.base.geometry.se2_exp` on floats."""
    if abs(w) < 1e-9:
        a, b = 1.0 - w * w / 6.0, w / 2.0
    else:
        a, b = math.sin(w) / w, (1.0 - math.cos(w)) / w
    return (a * u - b * v, b * u + a * v, wrap_angle(w))


def _log(pose: _Pose) -> _Pose:
    """:func:`robotd.base.geometry.se2_log` on floats."""
    x, y, w = pose[0], pose[1], (pose[2] + math.pi) % _TWO_PI - math.pi  # wrap_angle's arithmetic
    if abs(w) < 1e-9:
        a, b = 1.0 - w * w / 6.0, w / 2.0
    else:
        a, b = math.sin(w) / w, (1.0 - math.cos(w)) / w
    det = a * a + b * b
    return ((a * x + b * y) / det, (-b * x + a * y) / det, w)


def _compose_cs(a: _Pose, c: float, s: float, b: _Pose) -> _Pose:
    """:func:`robotd.base.geometry.compose` of one pose each, on floats, with ``c, s`` the
    cosine and sine of ``a``'s heading (computed once by the caller), the heading wrapped
    by :func:`robotd.base.geometry.wrap_angle`'s arithmetic written out (no call)."""
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1],
            (a[2] + b[2] + math.pi) % _TWO_PI - math.pi)  # wrap_angle's arithmetic


def _perturbations(eps: float) -> tuple[tuple[_Pose, _Pose], ...]:
    """``(exp(eps e_k), exp(-eps e_k))`` for k = 0, 1, 2 (:func:`_error_and_jacobian`)."""
    out = []
    for k in range(3):
        d = [0.0, 0.0, 0.0]
        d[k] = eps
        plus = _exp(d[0], d[1], d[2])
        d[k] = -eps
        out.append((plus, _exp(d[0], d[1], d[2])))
    return tuple(out)


_PERTURBATIONS = _perturbations(_EPS)
