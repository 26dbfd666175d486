"""SE(2) maths: the one place that owns planar rotations and rigid transforms.

Poses are ``(x_m, y_m, yaw_rad)`` in REP-103 conventions (x forward, y left, yaw
counter-clockwise). Arrays of poses are ``(N, 3) float64``.
"""

from __future__ import annotations

import math
from typing import overload

import numpy as np


_TWO_PI = 2.0 * math.pi


@overload
def wrap_angle(a_rad: float) -> float: ...
@overload
def wrap_angle(a_rad: np.ndarray) -> np.ndarray: ...
def wrap_angle(a_rad: float | np.ndarray) -> float | np.ndarray:
    """Wrap an angle or an array of angles (radians) to ``[-pi, pi)``.

    The one angle wrap of robotd. A scalar (Python or NumPy) gives a Python ``float``
    through plain float arithmetic (no array is built: the EKF calls this once per
    message); an array gives an array of the same shape and dtype.
    """
    if isinstance(a_rad, np.ndarray):
        return (a_rad + math.pi) % _TWO_PI - math.pi
    return (float(a_rad) + math.pi) % _TWO_PI - math.pi


def interpolate_poses(track_stamps_ns: np.ndarray, track_poses: np.ndarray,
                      query_stamps_ns: np.ndarray) -> np.ndarray:
    """Poses of a track at query stamps: ``(N,)`` int ns, ``(N, 3)``, ``(M,)`` int ns -> ``(M, 3)``.

    Between the two track poses around a query, x and y are interpolated linearly and the
    yaw linearly along the shorter arc between them (the track's yaw is unwrapped first,
    so a turn through +-pi goes the short way round); the yaw returned is wrapped to
    ``[-pi, pi)``. A query at a track stamp gives that pose. Queries before the first
    stamp or after the last are clamped: they get the first or the last pose (no
    extrapolation). ``track_stamps_ns`` must be non-decreasing and non-empty; stamps are
    taken relative to the first one before any float arithmetic, so epoch nanoseconds
    keep their resolution.
    """
    t = np.asarray(track_stamps_ns).reshape(-1)
    p = np.asarray(track_poses, dtype=np.float64).reshape(-1, 3)
    if len(t) == 0 or len(t) != len(p):
        raise ValueError(f"need as many track stamps as poses (at least one), got {len(t)} and {len(p)}")
    if np.any(np.diff(t) < 0):
        raise ValueError("track stamps must be non-decreasing")
    q = np.asarray(query_stamps_ns).reshape(-1)
    t0 = t[0]
    tr = (t - t0).astype(np.float64)
    qr = (q - t0).astype(np.float64)
    yaw = np.unwrap(p[:, 2])
    return np.column_stack([np.interp(qr, tr, p[:, 0]), np.interp(qr, tr, p[:, 1]),
                            wrap_angle(np.interp(qr, tr, yaw))])


def rot2(yaw_rad: float) -> np.ndarray:
    """The 2x2 rotation matrix of ``yaw_rad``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s], [s, c]])


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a (+) b``: pose ``b`` expressed in frame ``a``, returned in ``a``'s parent frame.

    Works on single poses ``(3,)`` and on stacks ``(N, 3)`` (broadcast).
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    yaw = wrap_angle(a[..., 2] + b[..., 2])
    return np.stack([x, y, yaw], axis=-1)


def inverse(a: np.ndarray) -> np.ndarray:
    """The inverse transform of pose ``a`` (``(3,)`` or ``(N, 3)``)."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a^-1 (+) b``: pose ``b`` expressed in the frame of pose ``a``."""
    return compose(inverse(a), b)


def between_floats(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """``between(a, b)`` of two single ``(3,)`` poses as three floats, bit for bit.

    :func:`between` builds and stacks numpy arrays for one pose (about 0.1 ms on a slow
    core; the keyframe stage asks once per floor frame, 30 a second);
    here the same operations in the same order run on floats: the sines and cosines from
    numpy's ``sin``/``cos`` (as ``between`` takes them; the C library's may differ in the
    last bit), the products and sums in IEEE double either way.
    """
    ax, ay, ayaw = float(a[0]), float(a[1]), float(a[2])
    c, s = float(np.cos(ayaw)), float(np.sin(ayaw))
    ix, iy, iyaw = -c * ax - s * ay, s * ax - c * ay, wrap_angle(-ayaw)  # inverse(a)
    c, s = float(np.cos(iyaw)), float(np.sin(iyaw))
    bx, by, byaw = float(b[0]), float(b[1]), float(b[2])
    return ix + c * bx - s * by, iy + s * bx + c * by, wrap_angle(iyaw + byaw)  # compose(inverse(a), b)


def transform_points(pose: np.ndarray, points_xy: np.ndarray) -> np.ndarray:
    """Map ``(N, 2)`` points from the frame of ``pose`` into its parent frame."""
    pose = np.asarray(pose, dtype=float)
    pts = np.asarray(points_xy, dtype=float)
    return pts @ rot2(float(pose[2])).T + pose[:2]


def yaw_to_quaternion(yaw_rad: float) -> tuple[float, float, float, float]:
    """Quaternion ``(qx, qy, qz, qw)`` of a rotation by ``yaw_rad`` about z."""
    return (0.0, 0.0, math.sin(yaw_rad / 2.0), math.cos(yaw_rad / 2.0))


def quaternion_from_rotation(rot: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion ``(qx, qy, qz, qw)`` of a ``(3, 3)`` rotation matrix, ``qw >= 0``.

    Shepperd's method: the largest of the four squared components is taken from the
    trace or a diagonal element, the others from off-diagonal sums, so it stays accurate
    for every rotation (a trace near -1 included).
    """
    r = np.asarray(rot, dtype=np.float64)
    if r.shape != (3, 3):
        raise ValueError(f"rotation must be (3, 3), got {r.shape}")
    t = float(np.trace(r))
    cands = (t, r[0, 0], r[1, 1], r[2, 2])
    k = int(np.argmax(cands))
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + t, 0.0))
        q = ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 0.0))
        q = (0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s)
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 - r[0, 0] + r[1, 1] - r[2, 2], 0.0))
        q = ((r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s)
    else:
        s = 2.0 * math.sqrt(max(1.0 - r[0, 0] - r[1, 1] + r[2, 2], 0.0))
        q = ((r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s)
    n = math.sqrt(sum(c * c for c in q))
    sign = -1.0 if q[3] < 0.0 else 1.0
    return tuple(float(sign * c / n) for c in q)  # type: ignore[return-value]


def quaternion_to_yaw(qx: float, qy: float, qz: float, qw: float) -> float:
    """Yaw (rad) of a quaternion, assuming a rotation about z (roll = pitch = 0)."""
    return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def rigid_fit_2d(src_xy: np.ndarray, dst_xy: np.ndarray) -> np.ndarray:
    """The rigid transform ``(x_m, y_m, yaw_rad)`` that best maps ``src`` onto ``dst``.

    Least squares over ``(N, 2)`` point pairs (N >= 2): centroids, then the rotation that
    maximises the cross-covariance's trace (Kabsch, as paper 003 Sec. IV-D does for visual
    odometry), which in 2-D is ``atan2`` of its antisymmetric and symmetric parts, with no
    SVD. ``dst ~ R(yaw) src + t``; a reflection is never returned.
    """
    a = np.asarray(src_xy, dtype=float).reshape(-1, 2)
    b = np.asarray(dst_xy, dtype=float).reshape(-1, 2)
    if len(a) < 2 or a.shape != b.shape:
        raise ValueError("rigid_fit_2d needs at least two point pairs of equal shape")
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    h = (a - ca).T @ (b - cb)
    yaw = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([cb[0] - (c * ca[0] - s * ca[1]), cb[1] - (s * ca[0] + c * ca[1]), yaw])


def rigid_fit_2d_covariance(src_xy: np.ndarray, dst_xy: np.ndarray, pose: np.ndarray,
                            min_sigma_m: float = 0.0) -> tuple[np.ndarray, float]:
    """Covariance ``(3, 3)`` of :func:`rigid_fit_2d`'s ``pose`` from its residuals, and the
    residual sigma (metres per coordinate).

    Model: ``dst_i = R(yaw) src_i + t + e_i`` with ``e_i`` white, isotropic, ``sigma`` per
    coordinate. ``sigma^2`` is estimated as ``sum |r_i|^2 / (2N - 3)`` (3 parameters
    fitted), raised to ``min_sigma_m^2`` (a perfect fit on a few points is not proof of
    perfection). The covariance is the Gauss-Newton one, ``sigma^2 (sum J_i^T J_i)^-1``
    with ``J_i = [I_2 | perp(R src_i)]``, so the coupling of yaw with a translation far
    from the points' centroid is kept. ``(N, 2)`` metres in, N >= 2 (N = 2 has no
    residual degree of freedom: only ``min_sigma_m`` then). Points bunched together
    determine the yaw poorly; the yaw's information is floored at that of points 1 mm
    from the fitted centre, so the matrix stays invertible (the caller checks the spread).
    """
    a = np.asarray(src_xy, dtype=float).reshape(-1, 2)
    b = np.asarray(dst_xy, dtype=float).reshape(-1, 2)
    n = len(a)
    resid = transform_points(pose, a) - b
    dof = 2 * n - 3
    sigma2 = float(np.sum(resid * resid)) / dof if dof > 0 else 0.0
    sigma2 = max(sigma2, min_sigma_m * min_sigma_m)
    ra = a @ rot2(float(pose[2])).T
    perp = np.column_stack([-ra[:, 1], ra[:, 0]])  # d(R src)/d(yaw)
    jtj = np.zeros((3, 3))
    jtj[0, 0] = jtj[1, 1] = n
    jtj[:2, 2] = jtj[2, :2] = perp.sum(axis=0)
    centred = perp - perp.mean(axis=0)
    jtj[2, 2] = float(np.sum(perp * perp)) + max(0.0, n * 1e-6 - float(np.sum(centred * centred)))
    cov = sigma2 * np.linalg.inv(jtj)
    return 0.5 * (cov + cov.T), math.sqrt(sigma2)


def rigid_from_two_pairs(src_i: np.ndarray, src_j: np.ndarray, dst_i: np.ndarray,
                         dst_j: np.ndarray) -> np.ndarray:
    """Rigid transforms ``(K, 3)`` (x_m, y_m, yaw_rad) from ``K`` minimal samples.

    Each sample is two point pairs, ``(K, 2)`` arrays: the yaw turns the segment
    ``src_i -> src_j`` onto ``dst_i -> dst_j``, the translation maps the segment's midpoint
    onto the other's (``dst ~ R src + t``, as :func:`rigid_fit_2d`). Used for RANSAC
    hypotheses; the scale of the two segments is not checked here.
    """
    va, vb = src_j - src_i, dst_j - dst_i
    yaw = wrap_angle(np.arctan2(vb[:, 1], vb[:, 0]) - np.arctan2(va[:, 1], va[:, 0]))
    c, s = np.cos(yaw), np.sin(yaw)
    ma, mb = 0.5 * (src_i + src_j), 0.5 * (dst_i + dst_j)
    return np.column_stack([mb[:, 0] - (c * ma[:, 0] - s * ma[:, 1]),
                            mb[:, 1] - (s * ma[:, 0] + c * ma[:, 1]), yaw])


def compose_jacobians(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(3, 3)`` Jacobians of :func:`compose` ``a (+) b`` with respect to ``a`` and ``b``."""
    c, s = math.cos(float(a[2])), math.sin(float(a[2]))
    bx, by = float(b[0]), float(b[1])
    j_a = np.array([[1.0, 0.0, -s * bx - c * by], [0.0, 1.0, c * bx - s * by], [0.0, 0.0, 1.0]])
    j_b = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return j_a, j_b


def compose_with_covariance(a: np.ndarray, cov_a: np.ndarray, b: np.ndarray,
                            cov_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``a (+) b`` ``(3,)`` and its covariance ``(3, 3)`` to first order
    (:func:`compose_jacobians`), ``a`` and ``b`` independent, ``cov_b`` of errors added in
    the frame of ``a``."""
    j_a, j_b = compose_jacobians(a, b)
    return compose(a, b), j_a @ cov_a @ j_a.T + j_b @ cov_b @ j_b.T


def se2_exp(xi: np.ndarray) -> np.ndarray:
    """The pose ``(x_m, y_m, yaw_rad)`` of the tangent vector ``xi = (u, v, w)`` of SE(2)
    (GTSAM's ``Pose2.Expmap``: translation ``V(w) (u, v)``)."""
    u, v, w = (float(c) for c in xi)
    if abs(w) < 1e-9:
        a, b = 1.0 - w * w / 6.0, w / 2.0
    else:
        a, b = math.sin(w) / w, (1.0 - math.cos(w)) / w
    return np.array([a * u - b * v, b * u + a * v, wrap_angle(w)])


def se2_log(pose: np.ndarray) -> np.ndarray:
    """The tangent vector ``(u, v, w)`` of a pose, the inverse of :func:`se2_exp`
    (GTSAM's ``Pose2.Logmap``)."""
    x, y, w = float(pose[0]), float(pose[1]), float(wrap_angle(float(pose[2])))
    if abs(w) < 1e-9:
        a, b = 1.0 - w * w / 6.0, w / 2.0
    else:
        a, b = math.sin(w) / w, (1.0 - math.cos(w)) / w
    det = a * a + b * b
    return np.array([(a * x + b * y) / det, (-b * x + a * y) / det, w])


def between_error_covariance(delta: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """A relative pose's covariance as the pose graph measures its error.

    ``delta (3,)`` = ``a^-1 (+) b`` was estimated with errors ``(dx_m, dy_m, dyaw_rad)``
    added in frame ``a`` (covariance ``cov (3, 3)``: a rigid fit's, the odometry filter's).
    GTSAM's ``BetweenFactor<Pose2>`` and g2o's ``EDGE_SE2`` measure an edge's error as
    ``log(delta^-1 (+) a^-1 (+) b)``, in the frame of ``delta``'s end: to first order the
    translation error turned by ``-dyaw``, so ``J cov J^T`` with ``J = diag(R(dyaw)^T, 1)``.
    Without it a loop closed in the opposite direction has its x and y variances and its
    yaw-translation coupling applied 180 deg turned.
    """
    j = np.eye(3)
    j[:2, :2] = rot2(float(np.asarray(delta, float)[2])).T
    out = j @ np.asarray(cov, float) @ j.T
    return 0.5 * (out + out.T)


def information_from_covariance(cov: np.ndarray) -> np.ndarray:
    """The symmetric information matrix ``(3, 3)`` of a pose covariance (its inverse,
    symmetrised against rounding)."""
    info = np.linalg.inv(np.asarray(cov, dtype=float))
    return 0.5 * (info + info.T)
