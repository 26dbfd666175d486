"""A verified forward-camera loop as a planar pose-graph edge.

Epipolar verification (:mod:`robotd.forward.verify`) gives the rotation between the two
camera views and the *direction* of the translation; the distance between them is not
observable from two images. On a robot moving on a floor the camera's motion is planar, so
the measurement reduces to two numbers in the old camera's planar frame (x along the optical
axis, y to the left):

* ``dyaw``, the heading change of the camera, and
* ``bearing``, the direction in which the new camera centre lies.

The pose graph's edges are full SE(2) relative poses with a 3x3 information matrix. The
metric scale is therefore taken from the graph's own prediction of the relative pose (from
odometry and earlier loops): the range is the predicted one, and its uncertainty is made so
large (``sigma_log_range``: a factor e^1 either way by default) that the edge constrains
almost only the bearing and the heading change. That keeps one edge type for the solvers,
the gate, the map file and g2o export; the cost is that the range component of the edge
repeats the prediction and adds no information (its weight is about 1 / e^2 of the range
squared per edge, far below odometry's), and that the chi-square gate's three degrees of
freedom have in effect two.

When the verification measured the range on the floor (``range_m``,
:func:`robotd.forward.verify.floor_range`: the camera's known height fixes the scale), the
edge takes that range with ``sigma_log_range_measured`` instead: the edge then constrains
all three components, and the gate refuses a loop whose measured range contradicts the
graph's prediction (the wrong loops of an aliased floor and ceiling, 0.1-0.5 m measured
where the places are 2.5 m apart).

The camera sits at ``mount = (x_m, y_m, yaw_rad)`` in the robot frame; the robot-frame edge is
``mount * camera_edge * mount^-1``. Its covariance is propagated to the GTSAM ``Between``
error coordinates (translation in the *to* frame, as in :mod:`robotd.graph.model`) through a
numerical Jacobian, so any mount and heading change are handled the same way.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from robotd.base.config import ForwardDetectorConfig
from robotd.base.geometry import compose, inverse, wrap_angle

__all__ = ["MotionFit", "PlanarLoopParams", "fit_motion", "loop_edge", "normalised_points", "out_of_plane",
           "planar_motion", "planarity_bound", "refine_motion"]


@dataclass(frozen=True)
class PlanarLoopParams:
    """1-sigma uncertainties of a forward loop edge.

    Fields:
        sigma_bearing_rad: direction of the translation (the five-point solution on a level
            camera; 2 deg, chosen when it also had to cover a frame taken up to 40 ms from
            its keyframe at 0.5 rad/s; the daemon's forward stage now carries each loop from
            its frames to its keyframes through the odometry, and keeps this floor).
        sigma_yaw_rad: heading change.
        sigma_log_range: the range is the prediction's, uncertain by this much in log units.
        sigma_log_range_measured: a range measured on the floor, uncertain by this much in
            log units (0.5: within a factor 1.65; measured on true loops of the virtual
            office route, up to a factor 1.7 from the truth, from 2-12 floor points).
        sigma_translation_m: isotropic translation noise added in the camera frame, for
            views taken close together where the bearing means little.
        max_tilt_rad: the camera motion must be planar: a rotation axis or a translation
            direction more than this out of the floor plane is not a level robot's motion,
            and :func:`planar_motion` reports it.
    """

    sigma_bearing_rad: float = math.radians(ForwardDetectorConfig.sigma_bearing_deg)
    sigma_yaw_rad: float = math.radians(ForwardDetectorConfig.sigma_yaw_deg)
    sigma_log_range: float = 1.0
    sigma_log_range_measured: float = 0.5
    sigma_translation_m: float = 0.03
    max_tilt_rad: float = math.radians(10.0)

    @classmethod
    def from_config(cls, section: ForwardDetectorConfig) -> PlanarLoopParams:
        """The loop noise of a ``[forward_detector]`` table (whose defaults these are)."""
        return cls(sigma_bearing_rad=math.radians(section.sigma_bearing_deg),
                   sigma_yaw_rad=math.radians(section.sigma_yaw_deg))

    def __post_init__(self) -> None:
        for name in ("sigma_bearing_rad", "sigma_yaw_rad", "sigma_log_range", "sigma_log_range_measured",
                     "sigma_translation_m",
                     "max_tilt_rad"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be positive and finite, got {v}")


def planar_motion(rotation: np.ndarray, translation_dir: np.ndarray) -> tuple[float, float, float]:
    """``(dyaw_rad, bearing_rad, tilt_rad)`` of the new camera in the old camera's planar frame.

    ``rotation (3, 3)`` and ``translation_dir (3,)`` as :class:`robotd.forward.verify.Verification`
    gives them (OpenCV axes: x right, y down, z forward; a point X_old in the old camera frame
    is ``rotation @ X_old + s * translation_dir`` in the new one). ``tilt_rad`` is how far the
    motion leaves the floor plane: the larger of the new optical axis' elevation, the roll
    of its x axis and the translation's elevation; a level camera on a floor gives about 0.
    """
    r = np.asarray(rotation, np.float64).reshape(3, 3)
    t = np.asarray(translation_dir, np.float64).reshape(3)
    centre = -r.T @ t               # new camera centre in the old camera frame (times s)
    forward = r.T @ np.array([0.0, 0.0, 1.0])   # new optical axis in the old frame
    right = r.T @ np.array([1.0, 0.0, 0.0])
    dyaw = math.atan2(-forward[0], forward[2])   # planar frame: x = camera z, y = -camera x
    bearing = math.atan2(-centre[0], centre[2])
    norm = max(float(np.linalg.norm(centre)), 1e-12)
    tilt = max(abs(math.asin(max(-1.0, min(1.0, forward[1])))),
               abs(math.asin(max(-1.0, min(1.0, right[1])))),
               abs(math.asin(max(-1.0, min(1.0, centre[1] / norm)))))
    return dyaw, bearing, tilt


INLIER_NOISE_FACTOR = 3.4
"""How many times the inliers' own epipolar residual understates the error of the two-view
motion (dimensionless). The keypoints' errors are not independent (the same texture, the
same blur, sub-pixel bias of one detector), so ``noise_px^2 (J^T J)^-1`` is too confident by
a factor the residuals cannot show. Measured on 116 verified revisit pairs of the virtual
office route 0.2-0.6 m apart (two worlds, seeds 0 and 1; every true motion there is planar,
so :attr:`MotionFit.planarity_chi2` would be chi-square with 3 degrees of freedom, median
2.37, were the noise model honest): median 27.7, a factor sqrt(27.7 / 2.37) = 3.4 in the
noise. The same factor as the docs' 2-5 between the bearing's claimed sigma and its true
error on rendered pairs."""

PLANARITY_CHI2_3DOF_999 = 16.27  # chi-square, 3 degrees of freedom, 99.9 %


def planarity_bound(noise_factor: float = INLIER_NOISE_FACTOR) -> float:
    """The largest :attr:`MotionFit.planarity_chi2` of a level camera's motion, at 99.9 %
    under the inliers' noise scaled by ``noise_factor`` (dimensionless)."""
    return PLANARITY_CHI2_3DOF_999 * noise_factor ** 2


def _base_edge(params: np.ndarray, mount: np.ndarray) -> np.ndarray:
    """Robot-frame edge from ``(bearing, dyaw, log_range, nx, ny)`` in the camera frame."""
    bearing, dyaw, log_range, nx, ny = params
    s = math.exp(log_range)
    cam = np.array([s * math.cos(bearing) + nx, s * math.sin(bearing) + ny, dyaw])
    return compose(compose(mount, cam), inverse(mount))


def _between_error(nominal: np.ndarray, other: np.ndarray) -> np.ndarray:
    """GTSAM's ``Between`` error coordinates of ``other`` against ``nominal`` (first order):
    the translation difference in ``nominal``'s frame, the wrapped heading difference."""
    c, s = math.cos(nominal[2]), math.sin(nominal[2])
    d = other[:2] - nominal[:2]
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], float(wrap_angle(other[2] - nominal[2]))])


def loop_edge(predicted: np.ndarray, dyaw_rad: float, bearing_rad: float,
              mount: np.ndarray | None = None, params: PlanarLoopParams | None = None,
              range_m: float | None = None,
              sigma_bearing_rad: float | None = None,
              sigma_yaw_rad: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The robot-frame loop edge ``(delta (3,), information (3, 3))`` of a forward loop.

    ``predicted (3,)``: the graph's current relative pose of the two keyframes (robot
    frame, to in from), which gives the range unless ``range_m`` (the distance between the
    camera centres measured on the floor, metres) is given; ``dyaw_rad``, ``bearing_rad`` from
    :func:`planar_motion`; ``mount (3,)``: the forward camera in the robot frame (default:
    at the robot's origin, looking forward); ``params``: the noise (default
    :class:`PlanarLoopParams`); ``sigma_bearing_rad``: how well the verification's inliers
    fixed the bearing (:func:`refine_motion`), added in quadrature to
    ``params.sigma_bearing_rad`` (a floor for what the inliers do not show);
    ``sigma_yaw_rad``: how far the images are from fixing the heading change (a ridge no
    prior heading settled), added in quadrature to ``params.sigma_yaw_rad``.
    """
    mount = np.zeros(3) if mount is None else np.asarray(mount, np.float64).reshape(3)
    params = PlanarLoopParams() if params is None else params
    predicted = np.asarray(predicted, np.float64).reshape(3)
    pred_cam = compose(compose(inverse(mount), predicted), mount)
    if range_m is not None and not (math.isfinite(range_m) and range_m > 0.0):
        raise ValueError(f"range_m must be positive and finite, got {range_m}")
    measured = range_m is not None
    if range_m is None:
        range_m = float(math.hypot(pred_cam[0], pred_cam[1]))
    range_m = max(float(range_m), 1e-3)
    x0 = np.array([bearing_rad, dyaw_rad, math.log(range_m), 0.0, 0.0])
    delta = _base_edge(x0, mount)
    sig_range = params.sigma_log_range_measured if measured else params.sigma_log_range
    if sigma_bearing_rad is not None and not (math.isfinite(sigma_bearing_rad) and sigma_bearing_rad >= 0.0):
        raise ValueError(f"sigma_bearing_rad must be non-negative and finite, got {sigma_bearing_rad}")
    sig_bearing = params.sigma_bearing_rad if sigma_bearing_rad is None else math.hypot(params.sigma_bearing_rad,
                                                                                         sigma_bearing_rad)
    if sigma_yaw_rad is not None and not (math.isfinite(sigma_yaw_rad) and sigma_yaw_rad >= 0.0):
        raise ValueError(f"sigma_yaw_rad must be non-negative and finite, got {sigma_yaw_rad}")
    sig_yaw = params.sigma_yaw_rad if sigma_yaw_rad is None else math.hypot(params.sigma_yaw_rad, sigma_yaw_rad)
    sig = np.array([sig_bearing, sig_yaw, sig_range,
                    params.sigma_translation_m, params.sigma_translation_m])
    jac = np.zeros((3, 5))
    for k in range(5):  # central differences, steps well inside each parameter's sigma
        h = 1e-6 * max(1.0, abs(x0[k]))
        xp, xm = x0.copy(), x0.copy()
        xp[k] += h
        xm[k] -= h
        jac[:, k] = (_between_error(delta, _base_edge(xp, mount))
                     - _between_error(delta, _base_edge(xm, mount))) / (2.0 * h)
    cov = jac @ np.diag(sig**2) @ jac.T
    info = np.linalg.inv(cov)
    return delta, 0.5 * (info + info.T)


def _rotvec_matrix(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w (3,)`` (Rodrigues)."""
    a = math.sqrt(float(w @ w))
    if a < 1e-15:
        return np.eye(3)
    k = w / a
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    out: np.ndarray = np.eye(3) + math.sin(a) * kx + (1.0 - math.cos(a)) * (kx @ kx)
    return out


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` of two ``(3,)`` vectors (``np.cross`` costs tens of microseconds a call)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _skews(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``(M, 3, 3)`` of the vectors ``v (M, 3)``."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def _rotvec_matrices(w: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(M, 3, 3)`` of the rotation vectors ``w (M, 3)`` (Rodrigues, as
    :func:`_rotvec_matrix` row by row, in one pass)."""
    a = np.sqrt(np.einsum("ij,ij->i", w, w))
    small = a < 1e-15
    kx = _skews(w / np.where(small, 1.0, a)[:, None])
    out: np.ndarray = (np.eye(3) + np.sin(a)[:, None, None] * kx
                       + (1.0 - np.cos(a))[:, None, None] * (kx @ kx))
    out[small] = np.eye(3)
    return out


def _essential(rotation: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``E = [t]x R`` (3, 3)."""
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    out: np.ndarray = tx @ rotation
    return out


def _sampson_px_many(x_old: np.ndarray, x_new: np.ndarray, es: np.ndarray, focal_px: float) -> np.ndarray:
    """Sampson distances ``(M, N)`` in pixels of normalised homogeneous points ``(N, 3)``
    to each of the essential matrices ``es (M, 3, 3)``."""
    ex1 = es @ x_old.T                             # E x_old, (M, 3, N)
    etx2 = es.transpose(0, 2, 1) @ x_new.T         # E^T x_new
    num = (ex1 * x_new.T).sum(axis=1)
    den = np.sqrt(ex1[:, 0]**2 + ex1[:, 1]**2 + etx2[:, 0]**2 + etx2[:, 1]**2)
    out: np.ndarray = focal_px * num / np.maximum(den, 1e-15)
    return out


#: :func:`fit_motion`'s central-difference step on each of its five parameters.
_STEP = 1e-6

#: The ten perturbations of :func:`fit_motion`'s parameters (plus, then minus) and the
#: unperturbed one, as rows ``(11, 5)``; and the rotations of their first three.
_STEPS = np.vstack([np.eye(5) * _STEP, -np.eye(5) * _STEP, np.zeros((1, 5))])
_STEP_ROTATIONS = _rotvec_matrices(_STEPS[:, :3])
#: The same rotations one by one as :func:`_rotvec_matrix` gives them (the ten perturbed
#: poses of the sigmas).
_STEP_ROTATION_LIST = [_rotvec_matrix(d[:3]) for d in _STEPS[:10]]


#: :func:`fit_motion`'s limit on the condition number of its normal matrix.
_COND_LIMIT = 1e14


def _ill_conditioned(m: np.ndarray) -> bool:
    """``np.linalg.cond(m) > _COND_LIMIT`` for a finite symmetric positive semi-definite
    ``m (5, 5)`` (``J^T J``), without the SVD where the answer is clear. The symmetric
    eigenvalues' ratio is the same condition number up to a rounding error of about
    ``1e-15`` of the largest eigenvalue in the smallest (and the matrix's asymmetry from
    rounding, as small); where that ratio is below a hundredth of the limit, the smallest
    eigenvalue is fixed to a thousandth and the SVD's figure is below the limit too;
    otherwise the SVD's figure decides. (The SVD took about a sixth of the refinement's
    time, once per Gauss-Newton step.)"""
    w = np.linalg.eigvalsh(m)
    if w[0] > 0.0 and w[-1] < 0.01 * _COND_LIMIT * w[0]:
        return False
    return bool(np.linalg.cond(m) > _COND_LIMIT)


def _planar_angles(rotation: np.ndarray, translation_dir: np.ndarray) -> tuple[float, float, float, float, float]:
    """``(bearing_rad, dyaw_rad)`` of :func:`planar_motion` and the three sines of
    :func:`out_of_plane` of one motion, computed once for both (the same arithmetic)."""
    centre = -rotation.T @ translation_dir
    forward, right = rotation[2], rotation[0]   # r.T times the unit z and x axes
    norm = max(float(np.linalg.norm(centre)), 1e-12)
    return (math.atan2(-centre[0], centre[2]), math.atan2(-forward[0], forward[2]),
            float(forward[1]), float(right[1]), float(centre[1] / norm))


@dataclass(frozen=True, eq=False)
class MotionFit:
    """The two-view motion refined on the inliers (:func:`fit_motion`).

    ``rotation (3, 3)``, ``translation_dir (3,)`` as :class:`robotd.forward.verify.Verification`;
    ``sigma_bearing_rad``, ``sigma_yaw_rad``: 1-sigma of :func:`planar_motion`'s bearing and
    heading change from the inliers; ``noise_px``: the inliers' epipolar residual (pixels);
    ``planarity_chi2``: the motion's out-of-plane part (the new optical axis' elevation, the
    roll of its x axis, the translation's elevation: :func:`out_of_plane`) against its own
    covariance, ``e^T C^-1 e`` (dimensionless, 3 degrees of freedom; NaN when not
    computed: too few inliers or a degenerate geometry). A level robot's camera moves in the floor plane: under the inliers' noise
    model this is chi-square with 3 degrees of freedom.
    """

    rotation: np.ndarray
    translation_dir: np.ndarray
    sigma_bearing_rad: float = math.inf
    sigma_yaw_rad: float = math.inf
    noise_px: float = math.nan
    planarity_chi2: float = math.nan


def out_of_plane(rotation: np.ndarray, translation_dir: np.ndarray) -> np.ndarray:
    """``(3,)`` sines of the motion's out-of-plane angles (OpenCV axes, y down): the new
    optical axis' elevation, the roll of its x axis and the translation's elevation, all in
    the old camera's frame; zero for a level camera moving on a floor (:func:`planar_motion`'s
    ``tilt`` is the largest of them, as an angle)."""
    r = np.asarray(rotation, np.float64).reshape(3, 3)
    t = np.asarray(translation_dir, np.float64).reshape(3)
    centre = -r.T @ t
    return np.array([(r.T @ np.array([0.0, 0.0, 1.0]))[1], (r.T @ np.array([1.0, 0.0, 0.0]))[1],
                     centre[1] / max(float(np.linalg.norm(centre)), 1e-12)])


def normalised_points(p_old_px: np.ndarray, p_new_px: np.ndarray,
                      camera_matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The matched pixels ``p_old_px, p_new_px (N, 2)`` through ``K^-1``: ``(N, 3), (N, 3)``
    homogeneous normalised coordinates, the rows the verification's steps compute from
    them (each row the same whichever rows are taken with it)."""
    kinv = np.linalg.inv(np.asarray(camera_matrix, np.float64))
    p_old = np.asarray(p_old_px, np.float64).reshape(-1, 2)
    p_new = np.asarray(p_new_px, np.float64).reshape(-1, 2)
    x_old: np.ndarray = np.hstack([p_old, np.ones((len(p_old), 1))]) @ kinv.T
    x_new: np.ndarray = np.hstack([p_new, np.ones((len(p_new), 1))]) @ kinv.T
    return x_old, x_new


def refine_motion(p_old_px: np.ndarray, p_new_px: np.ndarray, rotation: np.ndarray,
                  translation_dir: np.ndarray, camera_matrix: np.ndarray,
                  iterations: int = 5) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """:func:`fit_motion` as a tuple ``(rotation, translation_dir, sigma_bearing_rad,
    sigma_yaw_rad, noise_px)``."""
    f = fit_motion(p_old_px, p_new_px, rotation, translation_dir, camera_matrix, iterations)
    return f.rotation, f.translation_dir, f.sigma_bearing_rad, f.sigma_yaw_rad, f.noise_px


def fit_motion(p_old_px: np.ndarray, p_new_px: np.ndarray, rotation: np.ndarray,
               translation_dir: np.ndarray, camera_matrix: np.ndarray, iterations: int = 5,
               normalised: tuple[np.ndarray, np.ndarray] | None = None) -> MotionFit:
    """The two-view motion refined on all the inliers, and how well they fix it (not in
    paper 000).

    Returns a :class:`MotionFit`. RANSAC's essential matrix comes from one minimal sample of five points;
    here its five degrees of freedom (the rotation, the translation's direction on the unit
    sphere) are refined by Gauss-Newton on every inlier's epipolar error (Sampson distance,
    pixels), and their covariance is ``noise_px^2 (J^T J)^-1`` at the optimum, with
    ``noise_px`` the inliers' own residual (``sqrt(sum r^2 / (N - 5))``). It is propagated
    to the bearing and the heading change of :func:`planar_motion`. This is what makes the
    bearing honest at short baselines: a point at depth Z moves by about ``f * b / Z``
    pixels of parallax for a baseline b, so the translation's direction is fixed to about
    ``noise / parallax / sqrt(N)``; with the rotation free too, a lateral shift and a turn
    explain the far points alike (the rotation-translation ambiguity of a narrow field of
    view). Both grow as the baseline shrinks; nothing here is tuned. The same covariance,
    propagated to the out-of-plane angles, gives ``planarity_chi2``.

    ``p_old_px, p_new_px (N, 2)``: the inliers, pixels; ``rotation (3, 3)``,
    ``translation_dir (3,)`` as :class:`robotd.forward.verify.Verification`;
    ``camera_matrix (3, 3)``. With fewer than six inliers or a degenerate geometry the
    motion is returned as given and the sigmas are ``inf``. ``normalised``: the same pixels
    already through ``K^-1`` (:func:`normalised_points`), so a caller that has them does
    not compute them again (the same rows).
    """
    p_old = np.asarray(p_old_px, np.float64).reshape(-1, 2)
    p_new = np.asarray(p_new_px, np.float64).reshape(-1, 2)
    r0 = np.asarray(rotation, np.float64).reshape(3, 3)
    t0 = np.asarray(translation_dir, np.float64).reshape(3)
    t0 = t0 / max(float(np.linalg.norm(t0)), 1e-15)
    n = len(p_old)
    if n < 6:
        return MotionFit(r0, t0)
    k = np.asarray(camera_matrix, np.float64)
    focal = 0.5 * (k[0, 0] + k[1, 1])
    if normalised is None:
        x_old, x_new = normalised_points(p_old, p_new, k)
    else:
        x_old, x_new = normalised

    def linearise(r: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                        Callable[..., tuple[np.ndarray, np.ndarray]]]:
        # Two unit vectors orthogonal to t: the translation's tangent plane on the sphere.
        a = np.eye(3)[int(np.argmin(np.abs(t)))]
        e1 = _cross(t, a)
        e1 /= math.sqrt(float(e1 @ e1))
        e2 = _cross(t, e1)

        def pose(theta: np.ndarray, rotation: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
            # rotation: _rotvec_matrix(theta[:3]) when the caller has it already
            tt = t + theta[3] * e1 + theta[4] * e2
            rot = _rotvec_matrix(theta[:3]) if rotation is None else rotation
            return rot @ r, tt / math.sqrt(float(tt @ tt))

        # Central differences: the ten perturbed motions and the current one (rows of
        # ``_STEPS``), built and their Sampson distances computed in one pass each.
        tt = t + _STEPS[:, 3:4] * e1 + _STEPS[:, 4:5] * e2
        tt /= np.sqrt(np.einsum("ij,ij->i", tt, tt))[:, None]
        es = _skews(tt) @ (_STEP_ROTATIONS @ r)
        s = _sampson_px_many(x_old, x_new, es, focal)             # (11, N)
        jac = ((s[:5] - s[5:10]) / (2 * _STEP)).T
        return s[10], jac, pose

    r, t = r0, t0
    res, jac, pose = linearise(r, t)
    cost = float(res @ res)
    for _ in range(iterations):
        jtj = jac.T @ jac
        if not np.all(np.isfinite(jtj)) or _ill_conditioned(jtj):
            return MotionFit(r0, t0, noise_px=math.sqrt(cost / (n - 5)))
        step = -np.linalg.solve(jtj, jac.T @ res)
        r_new, t_new = pose(step)
        res_new, jac_new, pose_new = linearise(r_new, t_new)
        cost_new = float(res_new @ res_new)
        if not cost_new < cost:
            break
        converged = cost - cost_new < 1e-6 * cost
        r, t, res, jac, pose, cost = r_new, t_new, res_new, jac_new, pose_new, cost_new
        if converged:
            break
    noise = math.sqrt(cost / (n - 5))
    jtj = jac.T @ jac
    if not np.all(np.isfinite(jtj)) or _ill_conditioned(jtj):
        return MotionFit(r, t, noise_px=noise)
    cov = noise**2 * np.linalg.inv(jtj)
    # The bearing, heading change and out-of-plane sines of the ten perturbed motions
    # (rows of ``_STEPS``, plus then minus), each as planar_motion and out_of_plane give them.
    h = _STEP
    angles = np.array([_planar_angles(*pose(d, rot)) for d, rot in zip(_STEPS[:10], _STEP_ROTATION_LIST)])  # (10, 5)
    diff = (angles[:5] - angles[5:]).T                                   # (5, 5)
    grad = np.array([[wrap_angle(float(d)) / (2 * h) for d in diff[0]],
                     [wrap_angle(float(d)) / (2 * h) for d in diff[1]]])
    g_out = diff[2:] / (2 * h)
    var = np.einsum("ij,jk,ik->i", grad, cov, grad)
    c_out = g_out @ cov @ g_out.T
    e_out = np.array(_planar_angles(r, t)[2:])
    try:
        chi2 = float(e_out @ np.linalg.solve(c_out, e_out))
    except np.linalg.LinAlgError:
        chi2 = math.nan
    return MotionFit(r, t, math.sqrt(max(float(var[0]), 0.0)), math.sqrt(max(float(var[1]), 0.0)), noise,
                     chi2 if math.isfinite(chi2) and chi2 >= 0.0 else math.nan)
