"""The two-view motion of a level camera, fitted with the motion kept in the floor plane.

The epipolar verification (:mod:`robotd.forward.verify`) fits the general five-degree-of-
freedom motion (rotation, translation direction). On a robot the forward camera only turns
about its vertical axis and moves in the floor plane, so the motion has two degrees of
freedom: the heading change ``dyaw`` and the bearing of the translation. When the views
are close, or their inliers crowd on one wall, the general fit often leans out of the
plane and its bearing is off by tens of degrees while the heading is right; the daemon then
refuses the loop as not planar (:mod:`robotd.app.stages.forward_loops`). Fitting the two
planar parameters instead is the model the robot's motion has: it cannot lean, and with
three fewer unknowns the same inliers fix the bearing better. (Not in paper 000.)

For a fixed heading change ``yaw`` (rotation ``R`` about the camera's y axis, OpenCV axes:
x right, y down, z forward) the epipolar constraint ``x_new . (t x R x_old) = 0`` with
``t = (sin psi, 0, cos psi)`` is one linear equation in ``(sin psi, cos psi)`` per match:
each match votes for a translation direction ``psi`` (modulo pi). :func:`fit_planar` scans
the heading over a window around a first guess, takes the directions most matches vote for
at each heading, counts the matches within ``threshold_px`` (Sampson distance) of each
(heading, direction) and keeps the best; the sign of the translation is the one that puts
the matched points in front of both cameras. The uncertainty of the heading change and of
the bearing comes from the inliers' epipolar errors (Gauss-Newton covariance at the
optimum, scaled by :data:`robotd.forward.planar.INLIER_NOISE_FACTOR` as the general fit's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from robotd.forward.planar import INLIER_NOISE_FACTOR, normalised_points

__all__ = ["SCAN_STEP_RAD", "PlanarFit", "PlanarSearch", "fit_planar", "fit_planar_fixed", "fit_planar_scans", "front_mask", "planar_inliers", "planar_pose",
           "ransac_planar", "ridge_span"]


@dataclass(frozen=True, eq=False)
class PlanarFit:
    """A planar two-view motion (:func:`fit_planar`).

    ``dyaw_rad``: the camera's heading change (positive: turned left); ``bearing_rad``: the
    direction of the new camera centre in the old camera's planar frame (x along the
    optical axis, y to the left), as :func:`robotd.forward.planar.planar_motion` gives them;
    ``rotation (3, 3)``, ``translation_dir (3,)`` the same motion as
    :class:`robotd.forward.verify.Verification` holds it; ``inliers (N,) bool`` the matches
    within the threshold; ``sigma_yaw_rad``, ``sigma_bearing_rad`` their 1-sigma (``inf``
    when the inliers do not fix them: too few, or no parallax; ``sigma_yaw_rad`` 0 when the
    heading was held fixed). ``scan_yaw_rad (H,)``, ``scan_inliers (H,)``: the headings the
    fit scanned and the most matches a translation direction keeps at each (the inlier
    count's profile over the heading, :func:`ridge_span`).
    """

    dyaw_rad: float
    bearing_rad: float
    rotation: np.ndarray
    translation_dir: np.ndarray
    inliers: np.ndarray
    sigma_yaw_rad: float = math.inf
    sigma_bearing_rad: float = math.inf
    scan_yaw_rad: np.ndarray = field(default_factory=lambda: np.zeros(0))
    scan_inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def planar_pose(yaw_rad: float, psi_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """``(rotation (3, 3), translation_dir (3,))`` of the heading change ``yaw_rad`` and the
    translation direction ``t = (sin psi, 0, cos psi)`` (OpenCV camera axes)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    # A left turn (positive yaw in the floor frame) turns the optical axis towards -x.
    r = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return r, np.array([math.sin(psi_rad), 0.0, math.cos(psi_rad)])


def _sampson(x_old: np.ndarray, x_new: np.ndarray, r: np.ndarray, t: np.ndarray, focal: float) -> np.ndarray:
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    e = tx @ r
    ex1 = x_old @ e.T
    etx2 = x_new @ e
    num = np.einsum("ij,ij->i", x_new, ex1)
    den = np.sqrt(ex1[:, 0] ** 2 + ex1[:, 1] ** 2 + etx2[:, 0] ** 2 + etx2[:, 1] ** 2)
    out: np.ndarray = focal * num / np.maximum(den, 1e-15)
    return out


def _linear_terms(x_old: np.ndarray, x_new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The matches' factors of the Sampson distance of a planar pose (:func:`_scores`,
    :func:`_sampson_linear`): ``(4, N)`` of the numerator, linear in the pose's
    ``v = (cos psi, sin psi, cos(psi - yaw), sin(psi - yaw))``, and ``(6, N)`` of the
    denominator squared, linear in ``v``'s six products (:func:`_pose_terms`)."""
    x1, y1, z1 = x_old[:, 0], x_old[:, 1], x_old[:, 2]
    x2, y2, z2 = x_new[:, 0], x_new[:, 1], x_new[:, 2]
    n = len(x_old)
    # num = -cos psi (x2 y1) + sin psi (z2 y1) + cos(psi - yaw) (y2 x1) - sin(psi - yaw) (y2 z1)
    a = np.empty((4, n))
    np.multiply(x2, y1, out=a[0])
    np.negative(a[0], out=a[0])
    np.multiply(z2, y1, out=a[1])
    np.multiply(y2, x1, out=a[2])
    np.multiply(y2, z1, out=a[3])
    np.negative(a[3], out=a[3])
    # den^2 = |E x_old|_01^2 + |E^T x_new|_01^2 = (cos psi y1)^2 + (cos(psi - yaw) x1 - sin(psi - yaw) z1)^2
    #         + (cos(psi - yaw) y2)^2 + (sin psi z2 - cos psi x2)^2, multiplied out
    b = np.empty((6, n))
    b[0] = y1 * y1 + x2 * x2
    np.multiply(z2, z2, out=b[1])
    b[2] = -2.0 * x2 * z2
    b[3] = x1 * x1 + y2 * y2
    b[4] = -2.0 * x1 * z1
    np.multiply(z1, z1, out=b[5])
    return a, b


def _pose_terms(yaws: np.ndarray, psis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The poses' ``v (M, 4)`` and its products ``(M, 6)`` (:func:`_linear_terms`)."""
    cp, sp_ = np.cos(psis), np.sin(psis)
    cd, sd = np.cos(psis - yaws), np.sin(psis - yaws)
    v = np.stack([cp, sp_, cd, sd], axis=1)
    w = np.stack([cp * cp, sp_ * sp_, cp * sp_, cd * cd, cd * sd, sd * sd], axis=1)
    return v, w


def _sampson_linear(a: np.ndarray, b: np.ndarray, thetas: list[tuple[float, float]], focal: float) -> np.ndarray:
    """``(P, N)``: row ``k`` the Sampson distance (signed, as :func:`_sampson`'s) of the
    planar pose ``thetas[k] = (yaw, psi)`` for the matches of :func:`_linear_terms`'s
    ``a, b``: two matrix products (the few poses' terms by ``math``). The same distances
    as :func:`_sampson`'s up to rounding (:func:`_refine`)."""
    v, w = [], []
    for yaw, psi in thetas:
        cp, sp_, cd, sd = math.cos(psi), math.sin(psi), math.cos(psi - yaw), math.sin(psi - yaw)
        v.append((cp, sp_, cd, sd))
        w.append((cp * cp, sp_ * sp_, cp * sp_, cd * cd, cd * sd, sd * sd))
    den = np.array(w) @ b
    np.maximum(den, 0.0, out=den)
    np.sqrt(den, out=den)
    np.maximum(den, 1e-15, out=den)
    out: np.ndarray = np.array(v) @ a
    out *= focal
    out /= den
    return out


#: :func:`_refine` stops once a Gauss-Newton step moves neither parameter by more than this
#: (rad): the steps then shrink by orders of magnitude each, far below the fit's sigmas.
_STEP_TOL_RAD = 1e-9


_SCORE_BLOCK = 256  # candidates scored at once by _scores


def _scores(terms: tuple[np.ndarray, np.ndarray], yaws: np.ndarray, psis: np.ndarray, focal: float,
            threshold_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Each planar pose ``(yaws[m], psis[m])``'s inliers (matches within ``threshold_px``,
    Sampson distance) and cost (minus the sum of the distances squared, each capped at the
    threshold): ``(M,) int``, ``(M,)``.

    With ``v = (cos psi, sin psi, cos(psi - yaw), sin(psi - yaw))`` the Sampson numerator
    ``x_new . E x_old`` is linear in ``v`` and its denominator squared quadratic
    (:func:`_linear_terms`), so the squared distances of every pose and match are two
    matrix products, ``(M, 4) @ (4, N)`` and ``(M, 6) @ (6, N)``, and a few element-wise
    passes, where the essential matrices' entries written out took about twenty-five. The
    same distances as :func:`_sampson`'s up to rounding (the sums in another order): a
    count differs only for a match within rounding of the threshold."""
    a, b = terms  # (_linear_terms of the matches)
    v, w = _pose_terms(yaws, psis)
    thr2 = threshold_px * threshold_px
    f2 = focal * focal
    inl_n = np.zeros(len(psis), np.int64)
    cost = np.zeros(len(psis))
    for at in range(0, len(psis), _SCORE_BLOCK):
        sl = slice(at, at + _SCORE_BLOCK)
        q = v[sl] @ a
        q *= q
        q *= f2
        q /= np.maximum(w[sl] @ b, 1e-30)  # the distances squared, (block, N)
        inl_n[sl] = np.count_nonzero(q < thr2, axis=1)
        np.minimum(q, thr2, out=q)
        cost[sl] = -q.sum(axis=1)
    return inl_n, cost


def _bearing(yaw: float, psi: float) -> float:
    r, t = planar_pose(yaw, psi)
    centre = -r.T @ t
    return math.atan2(-centre[0], centre[2])


#: :func:`fit_planar`'s heading step (rad): its scanned headings lie on this lattice.
SCAN_STEP_RAD = math.radians(0.2)


def fit_planar(p_old_px: np.ndarray, p_new_px: np.ndarray, camera_matrix: np.ndarray, yaw_guess_rad: float,
               *, threshold_px: float = 1.0, window_rad: float = math.radians(8.0),
               step_rad: float = SCAN_STEP_RAD, fix_yaw: bool = False, sigmas: bool = True) -> PlanarFit | None:
    """The planar motion (module notes) of matched pixels ``p_old_px, p_new_px (N, 2)``
    (``camera_matrix (3, 3)`` shared), the heading change searched within ``window_rad``
    of ``yaw_guess_rad`` in steps of ``step_rad``; None with fewer than 5 matches. With
    ``fix_yaw`` the heading change is held at ``yaw_guess_rad`` (``window_rad`` unused) and
    only the translation direction is fitted: the motion on a heading-bearing ridge at a
    heading known from elsewhere (:func:`ridge_span`); its ``sigma_bearing_rad`` is then the
    bearing's given the heading. Without ``sigmas`` the sigmas are not computed (left
    ``inf``; the motion and its inliers are the same): for a caller that reads the motion
    alone."""
    if fix_yaw:
        return _fit_planar(p_old_px, p_new_px, camera_matrix, [yaw_guess_rad], threshold_px, 0, step_rad, True,
                           sigmas)[0]
    n_steps = int(round(window_rad / step_rad))
    return _fit_planar(p_old_px, p_new_px, camera_matrix, [yaw_guess_rad], threshold_px, n_steps, step_rad,
                       sigmas=sigmas)[0]


def fit_planar_scans(p_old_px: np.ndarray, p_new_px: np.ndarray, camera_matrix: np.ndarray,
                     yaw_guesses_rad: list[float], *, threshold_px: float = 1.0,
                     window_rad: float = math.radians(8.0), step_rad: float = SCAN_STEP_RAD) -> list[PlanarFit | None]:
    """:func:`fit_planar` of the same matches around each of ``yaw_guesses_rad``: the same
    fits, but a heading on the lattice that two windows share is scored once (the scans
    lie on one lattice, and a heading's candidates and counts are the matches' alone), and
    a best candidate two windows share is refined once."""
    n_steps = int(round(window_rad / step_rad))
    return _fit_planar(p_old_px, p_new_px, camera_matrix, list(yaw_guesses_rad), threshold_px, n_steps, step_rad)


def fit_planar_fixed(p_old_px: np.ndarray, p_new_px: np.ndarray, camera_matrix: np.ndarray, yaws_rad: list[float],
                     sigmas: list[bool], *, threshold_px: float = 1.0) -> list[PlanarFit | None]:
    """:func:`fit_planar` with ``fix_yaw`` of the same matches at each of ``yaws_rad`` (with
    its sigmas where ``sigmas`` says): the matches are normalised once and every heading's
    candidates scored together (the ridge's fit and its two side fits)."""
    return _fit_planar(p_old_px, p_new_px, camera_matrix, list(yaws_rad), threshold_px, 0, SCAN_STEP_RAD, True,
                       list(sigmas))


def _fit_planar(p_old_px: np.ndarray, p_new_px: np.ndarray, camera_matrix: np.ndarray, guesses: list[float],
                threshold_px: float, n_steps: int, step_rad: float, fix_yaw: bool = False,
                sigmas: bool | list[bool] = True) -> list[PlanarFit | None]:
    """:func:`fit_planar` (``fix_yaw``: each guess's heading held, ``n_steps`` 0),
    :func:`fit_planar_scans` and :func:`fit_planar_fixed`: one fit per guess, each scanning
    ``n_steps`` lattice headings either side of it; ``sigmas`` one for all or one per guess."""
    each = list(sigmas) if isinstance(sigmas, list) else [sigmas] * len(guesses)
    p_old = np.asarray(p_old_px, np.float64).reshape(-1, 2)
    p_new = np.asarray(p_new_px, np.float64).reshape(-1, 2)
    n = len(p_old)
    if n < 5:
        return [None] * len(guesses)
    k = np.asarray(camera_matrix, np.float64)
    kinv = np.linalg.inv(k)
    focal = 0.5 * (k[0, 0] + k[1, 1])
    x_old = np.hstack([p_old, np.ones((n, 1))]) @ kinv.T
    x_new = np.hstack([p_new, np.ones((n, 1))]) @ kinv.T
    bins = 360  # half-degree bins over psi modulo pi
    # Every heading of the scan at once: each match's translation direction per heading,
    # a histogram per heading, its two fullest bins, three directions per bin.
    # The scanned headings lie on one lattice of step_rad (the guess rounded to it), so the
    # inlier profile is the matches' alone, not where the guess fell within a step. The
    # windows of several guesses share the headings they both scan (those equal to the
    # bit: a window's headings are its rounded guess plus multiples of the step, as one
    # window's always were, so each fit is the one its window alone gives).
    if fix_yaw:
        wanted = [np.array([float(g)]) for g in guesses]
    else:
        steps = np.arange(-n_steps, n_steps + 1) * step_rad
        wanted = [round(g / step_rad) * step_rad + steps for g in guesses]
    yaws = np.unique(np.concatenate(wanted))
    rows = [np.searchsorted(yaws, w) for w in wanted]
    c, s_ = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    x1, y1, z1 = x_old[:, 0], x_old[:, 1], x_old[:, 2]
    x2, y2, z2 = x_new[:, 0], x_new[:, 1], x_new[:, 2]
    # u = (R x_old) x x_new with R x_old = (c x1 + s z1, y1, -s x1 + c z1), written out (its
    # first and last components are the ones the direction needs).
    u0 = y1 * z2 - (-s_ * x1 + c * z1) * y2
    u2 = (c * x1 + s_ * z1) * y2 - y1 * x2
    # u . t = 0 with t = (sin psi, 0, cos psi): psi = atan2(-u_z, u_x) modulo pi.
    psis = np.mod(np.arctan2(-u2, u0), math.pi)
    idx = (psis / math.pi * bins).astype(np.int64) % bins + bins * np.arange(len(yaws))[:, None]
    hist = np.bincount(idx.ravel(), minlength=bins * len(yaws)).reshape(len(yaws), bins)
    hist = _with_neighbours(hist)
    top = np.argsort(-hist, axis=1)[:, :2]
    cands = ((top + 0.5) * math.pi / bins)[..., None] + np.array([-0.5, 0.0, 0.5]) * math.pi / bins  # (yaws, 2, 3)
    cand_yaw = np.broadcast_to(yaws[:, None, None], cands.shape).ravel()
    cand_psi = cands.ravel()
    # Each candidate's inliers and cost, a block of candidates at a time (the block's
    # distances stay in the cache; each row's figures are those of the whole at once).
    terms = _linear_terms(x_old, x_new)
    inl_n, cost = _scores(terms, cand_yaw, cand_psi, focal, threshold_px)
    per = cands.shape[1] * cands.shape[2]  # candidates per heading
    fits: list[PlanarFit | None] = []
    refined: dict[tuple[int, bool], PlanarFit] = {}  # a best candidate's refinement, for a window sharing it
    for r, sg in zip(rows, each):
        ci = (r[:, None] * per + np.arange(per)).ravel()  # this window's candidates, in scan order
        w_n, w_cost = inl_n[ci], cost[ci]
        # The most inliers, then the least cost; the first in scan order among equals.
        best_i = int(ci[np.flatnonzero(w_n == w_n.max())[np.argmax(w_cost[w_n == w_n.max()])]])
        w_yaws, scan_n = yaws[r], w_n.reshape(len(r), -1).max(axis=1)
        if (best_i, sg) not in refined:
            refined[best_i, sg] = _refine(x_old, x_new, focal, float(cand_yaw[best_i]), float(cand_psi[best_i]),
                                          threshold_px, fix_yaw, w_yaws, scan_n, sg, terms)
            fits.append(refined[best_i, sg])
        else:
            fits.append(replace(refined[best_i, sg], scan_yaw_rad=w_yaws, scan_inliers=scan_n))
    return fits




def _with_neighbours(hist: np.ndarray) -> np.ndarray:
    """Each bin of the rows of ``hist (H, B)`` int plus its two neighbours, cyclically:
    ``hist + np.roll(hist, 1, axis=1) + np.roll(hist, -1, axis=1)`` (integer sums, so the
    same counts) from one padded copy instead of two rolled ones."""
    wrapped = np.concatenate([hist[:, -1:], hist, hist[:, :1]], axis=1)
    out: np.ndarray = wrapped[:, 1:-1] + wrapped[:, :-2] + wrapped[:, 2:]
    return out


#: :func:`_refine`'s limit on the condition number of its normal matrix.
_COND_LIMIT = 1e12


def _cond(m: np.ndarray) -> float:
    """``np.linalg.cond(m)`` of a finite ``(1, 1)`` or ``(2, 2)`` matrix as far as a
    comparison with :data:`_COND_LIMIT` can tell: the same number, or one on the same side
    of the limit. A nonzero 1 x 1 matrix's condition number is 1 (its one singular value
    over itself, as the SVD gives it). A 2 x 2 one's is ``s_max^2 / |det|`` with ``s_max^2``
    from the Frobenius norm and the determinant; its rounding error is a few ulps of the
    condition number (the determinant's cancellation), so an estimate below a tenth of the
    limit puts the SVD's below it too; otherwise the SVD's own figure is returned. (The SVD
    took about a fifth of a refinement's time, once per Gauss-Newton step.)"""
    if m.shape == (1, 1) and m[0, 0] != 0.0:
        return 1.0
    if m.shape == (2, 2):
        a, b, c, d = float(m[0, 0]), float(m[0, 1]), float(m[1, 0]), float(m[1, 1])
        fro = a * a + b * b + c * c + d * d
        det = abs(a * d - b * c)
        if det > 0.0 and math.isfinite(fro):
            s2 = 0.5 * (fro + math.sqrt(max(fro * fro - 4.0 * det * det, 0.0)))  # s_max^2
            if s2 / det < 0.1 * _COND_LIMIT:
                return s2 / det
    return float(np.linalg.cond(m))


def _refine(x_old: np.ndarray, x_new: np.ndarray, focal: float, yaw: float, psi: float, threshold_px: float,
            fix_yaw: bool, yaws: np.ndarray, scan_n: np.ndarray, sigmas: bool = True,
            terms: tuple[np.ndarray, np.ndarray] | None = None) -> PlanarFit:
    """The planar motion ``(yaw, psi)`` refined by Gauss-Newton on the Sampson distances of
    the normalised matches ``x_old, x_new (N, 3)`` within ``threshold_px`` of it, the
    translation's sign chosen by the points in front of both cameras, and its sigmas
    (with ``sigmas``; else left ``inf``) (:func:`fit_planar`, :func:`ransac_planar`).

    The residuals at a point and at its central-difference neighbours are two matrix
    products from the matches' terms (:func:`_linear_terms`, ``terms`` when the caller has
    them), those around a trial step computed with the trial itself (used when the step is
    taken, which is the rule); the steps stop when both parameters move by at most
    :data:`_STEP_TOL_RAD` (or after five). The sign of the translation from one
    triangulation (:func:`front_masks`)."""
    a_all, b_all = _linear_terms(x_old, x_new) if terms is None else terms
    inl = np.abs(_sampson_linear(a_all, b_all, [(yaw, psi)], focal)[0]) < threshold_px
    a_in, b_in = a_all[:, inl], b_all[:, inl]  # the inliers' columns, taken once per inlier set
    h = 1e-6
    n_free = 1 if fix_yaw else 2  # the parameters fitted: psi alone or (yaw, psi)

    def around(y: float, p: float) -> tuple[np.ndarray, np.ndarray]:
        """The residuals at ``(y, p)`` and the central-difference Jacobian there ``(n_free, N)``."""
        pts = [(y, p), (y, p + h), (y, p - h)] if fix_yaw else [(y, p), (y + h, p), (y - h, p), (y, p + h), (y, p - h)]
        s = _sampson_linear(a_in, b_in, pts, focal)
        jt = (s[1::2] - s[2::2]) / (2 * h)
        return s[0], jt

    if inl.sum() >= 3:
        r0, jt = around(yaw, psi)
        for _ in range(5):
            jtj = jt @ jt.T
            if not np.all(np.isfinite(jtj)) or _cond(jtj) > _COND_LIMIT:
                break
            g = jt @ r0
            if fix_yaw:  # a scalar: LAPACK's solve of a 1 x 1 system is this division
                dy, dp = 0.0, -(float(g[0]) / float(jtj[0, 0]))
            else:
                dy, dp = (float(x) for x in -np.linalg.solve(jtj, g))
            trial, jt_trial = around(yaw + dy, psi + dp)
            if not float(trial @ trial) < float(r0 @ r0):
                break
            yaw, psi, r0, jt = yaw + dy, psi + dp, trial, jt_trial
            if abs(dy) <= _STEP_TOL_RAD and abs(dp) <= _STEP_TOL_RAD:
                break
    r, t = planar_pose(yaw, psi)
    inl = np.abs(_sampson_linear(a_all, b_all, [(yaw, psi)], focal)[0]) < threshold_px
    xo_in, xn_in = x_old[inl], x_new[inl]
    a_in, b_in = a_all[:, inl], b_all[:, inl]
    # The sign of the translation: the points in front of both cameras (the opposite
    # translation's are those behind both).
    front, back = front_masks(xo_in, xn_in, r, t)
    if int(np.count_nonzero(back)) > int(np.count_nonzero(front)):
        psi += math.pi
        r, t = planar_pose(yaw, psi)
    m = int(inl.sum())
    sig_y = sig_b = math.inf
    if sigmas and m > n_free:
        s = _sampson_linear(a_in, b_in, [(yaw, psi), (yaw + h, psi), (yaw - h, psi), (yaw, psi + h), (yaw, psi - h)],
                            focal)
        rr = s[0]
        noise = math.sqrt(float(rr @ rr) / (m - n_free)) * INLIER_NOISE_FACTOR
        jt = (s[1::2] - s[2::2]) / (2 * h)
        jtj = jt @ jt.T
        cov: np.ndarray | None = None
        if fix_yaw:  # the heading known: psi's variance alone, the heading's none
            if math.isfinite(float(jtj[1, 1])) and jtj[1, 1] > 0:
                cov = noise ** 2 * np.diag([0.0, 1.0 / jtj[1, 1]])
        elif np.all(np.isfinite(jtj)) and _cond(jtj) < _COND_LIMIT:
            cov = noise ** 2 * np.linalg.inv(jtj)
        if cov is not None:
            g = np.array([[1.0, 0.0],
                          [(_bearing(yaw + h, psi) - _bearing(yaw - h, psi)) / (2 * h),
                           math.remainder(_bearing(yaw, psi + h) - _bearing(yaw, psi - h), math.tau) / (2 * h)]])
            var = np.einsum("ij,jk,ik->i", g, cov, g)
            sig_y, sig_b = math.sqrt(max(float(var[0]), 0.0)), math.sqrt(max(float(var[1]), 0.0))
    return PlanarFit(yaw, _bearing(yaw, psi), r, t, inl, sig_y, sig_b, yaws, scan_n)


def _two_point_motions(a: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """The planar motions through the match pairs ``(i[s], j[s])``: ``(2 S, 4)`` vectors
    ``v = (cos psi, sin psi, cos(psi - yaw), sin(psi - yaw))`` up to scale (rows of NaN
    where a pair fixes none), from the epipolar rows ``a (N, 4)`` (:func:`ransac_planar`)."""
    pair = np.stack([a[i], a[j]], axis=1)                      # (S, 2, 4)
    null = np.linalg.svd(pair)[2][:, 2:, :]                    # (S, 2, 4): the null space
    n1, n2 = null[:, 0], null[:, 1]
    q = np.array([1.0, 1.0, -1.0, -1.0])  # |(v0, v1)| = |(v2, v3)|: both halves unit vectors
    q11, q12, q22 = (n1 * q * n1).sum(1), (n1 * q * n2).sum(1), (n2 * q * n2).sum(1)
    disc = q12 * q12 - q11 * q22
    root = np.sqrt(np.maximum(disc, 0.0))
    by_a = np.abs(q11) >= np.abs(q22)
    # q11 al^2 + 2 q12 al be + q22 be^2 = 0, solved for the better-conditioned ratio
    al = np.where(by_a, np.stack([-q12 + root, -q12 - root]), q22[None])
    be = np.where(by_a, q11[None], np.stack([-q12 + root, -q12 - root]))
    v = al[..., None] * n1[None] + be[..., None] * n2[None]   # (2, S, 4)
    v = v.reshape(-1, 4)
    bad = np.repeat((disc < 0.0)[None], 2, 0).ravel() | (np.hypot(v[:, 0], v[:, 1]) < 1e-12)
    v[bad] = np.nan
    return v


def _inlier_counts(a: np.ndarray, b: np.ndarray, v: np.ndarray, threshold: float) -> np.ndarray:
    """``(M,)`` matches within ``threshold`` (Sampson distance, normalised units) of each of
    the planar motions ``v (M, 4)`` of :func:`_two_point_motions` (any scale): the squared
    distance is ``(a . v)^2 / (w(v) . b)`` with ``w(v)`` the six products of ``v`` below and
    ``b (N, 6)`` from the matches (:func:`_sampson_terms`), so the test is two matrix
    products."""
    num = v @ a.T
    w = np.stack([v[:, 0] ** 2, v[:, 1] ** 2, v[:, 0] * v[:, 1], v[:, 2] ** 2, v[:, 2] * v[:, 3], v[:, 3] ** 2], axis=1)
    out: np.ndarray = (num * num < threshold * threshold * (w @ b.T)).sum(axis=1)
    return out


def _sampson_terms(x_old: np.ndarray, x_new: np.ndarray) -> np.ndarray:
    """``(N, 6)``: the Sampson denominator's terms of each match (:func:`_inlier_counts`):
    ``|E x|^2`` and ``|E^T x'|^2``'s first two components, expanded in ``v``."""
    x1, y1, x2, y2 = x_old[:, 0], x_old[:, 1], x_new[:, 0], x_new[:, 1]
    one = np.ones(len(x_old))
    return np.stack([y1 * y1 + x2 * x2, one, -2.0 * x2, x1 * x1 + y2 * y2, -2.0 * x1, one], axis=1)


def front_masks(x_old: np.ndarray, x_new: np.ndarray, r: np.ndarray, t: np.ndarray,
                max_depth: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
    """:func:`front_mask` of the motion ``r, t`` and of ``r, -t`` at once: the second's depths
    are the first's negated, exactly (the camera centre enters the triangulation linearly)."""
    za, zb, ok, lim = _depths(x_old, x_new, r, t, max_depth)
    front: np.ndarray = ok & (za > 0) & (zb > 0) & (za < lim) & (zb < lim)
    back: np.ndarray = ok & (za < 0) & (zb < 0) & (-za < lim) & (-zb < lim)
    return front, back


def _depths(x_old: np.ndarray, x_new: np.ndarray, r: np.ndarray, t: np.ndarray,
            max_depth: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """:func:`front_mask`'s depths in the old and the new camera, where they are defined, and
    the depth limit."""
    d1 = x_old
    d2 = x_new @ r
    c2 = -r.T @ t
    a11 = np.einsum("ij,ij->i", d1, d1)
    a12 = -np.einsum("ij,ij->i", d1, d2)
    a22 = np.einsum("ij,ij->i", d2, d2)
    b1 = d1 @ c2
    b2 = -(d2 @ c2)
    det = a11 * a22 - a12 * a12
    ok = np.abs(det) > 1e-12
    det = np.where(ok, det, 1.0)
    za = (a22 * b1 - a12 * b2) / det   # depth in the old camera (x_old's z is 1)
    zb = (a11 * b2 - a12 * b1) / det   # depth in the new camera
    lim = max_depth * math.sqrt(float(t @ t))
    return za, zb, ok, lim


def front_mask(x_old: np.ndarray, x_new: np.ndarray, r: np.ndarray, t: np.ndarray,
               max_depth: float = math.inf) -> np.ndarray:
    """``(N,) bool``: the normalised matches ``x_old, x_new (N, 3)`` whose triangulated point
    is in front of both cameras of the motion ``r, t`` (midpoint method) and nearer than
    ``max_depth`` times the baseline ``|t|`` to both (``cv2.recoverPose``'s ``distanceThresh``,
    50 by default there: a point further away has no parallax to show the motion)."""
    za, zb, ok, lim = _depths(x_old, x_new, r, t, max_depth)
    out: np.ndarray = ok & (za > 0) & (zb > 0) & (za < lim) & (zb < lim)
    return out


@dataclass(frozen=True)
class PlanarSearch:
    """What :func:`ransac_planar` did: ``samples`` drawn (pairs of matches), ``hypotheses``
    scored against every match, ``best_inliers`` of the best hypothesis before refinement,
    and that hypothesis, ``yaw_rad`` and ``psi_rad`` as :func:`planar_pose` takes them (0
    when there was none)."""

    samples: int
    hypotheses: int
    best_inliers: int
    yaw_rad: float = 0.0
    psi_rad: float = 0.0

    def inliers(self, p_old_px: np.ndarray, p_new_px: np.ndarray, camera_matrix: np.ndarray,
                threshold_px: float, normalised: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """``(N,) bool``: the matched pixels within ``threshold_px`` (Sampson distance) of the
        best hypothesis (``normalised``: the pixels already through ``K^-1``,
        :func:`robotd.forward.planar.normalised_points`)."""
        k = np.asarray(camera_matrix, np.float64)
        x_old, x_new = normalised_points(p_old_px, p_new_px, k) if normalised is None else normalised
        r, t = planar_pose(self.yaw_rad, self.psi_rad)
        out: np.ndarray = np.abs(_sampson(x_old, x_new, r, t, 0.5 * (k[0, 0] + k[1, 1]))) < threshold_px
        return out


def ransac_planar(p_old_px: np.ndarray, p_new_px: np.ndarray, camera_matrix: np.ndarray, *,
                  threshold_px: float = 1.0, min_inliers: int = 20, confidence: float = 0.999,
                  max_samples: int = 500, batch: int = 64, seed: int = 0, refine: bool = True,
                  normalised: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[PlanarFit | None, PlanarSearch]:
    """The planar motion of the matched pixels ``p_old_px, p_new_px (N, 2)`` found without
    a first guess: RANSAC over pairs of matches (the two-point solver of a level camera's
    motion; not in paper 000).

    With ``v = (cos psi, sin psi, cos(psi - yaw), sin(psi - yaw))`` the epipolar constraint
    of the motion of :func:`planar_pose` is linear, ``a_i . v = 0`` with
    ``a_i = (-x'_i y_i, y_i, y'_i x_i, -y'_i)`` (normalised coordinates, ``'`` the new
    image). Two matches leave a two-dimensional null space; the two halves of ``v`` being
    unit vectors of equal length gives a quadratic in it, so each pair of matches gives at
    most two motions. All hypotheses of a batch of ``batch`` samples are scored against
    every match at once (Sampson distance within ``threshold_px``); sampling stops when
    a consensus as large as the best found, and at least ``min_inliers``, would have been
    drawn with ``confidence`` (the adaptive RANSAC bound with a sample of two), and after
    at most ``max_samples`` samples: the work per verification is at most ``2 max_samples``
    hypotheses times N matches (the stated cap, no timer). The best hypothesis is refined
    on its inliers as :func:`fit_planar` refines its own (Gauss-Newton, the translation's
    sign from the points in front of both cameras, sigmas scaled by
    :data:`robotd.forward.planar.INLIER_NOISE_FACTOR`); its ``inliers`` are then those
    within the threshold *and* in front of both cameras.
    ``(None, search)`` with fewer than 5 matches, or without ``refine`` (the search's
    size alone: a screen). Samples from ``numpy``'s generator seeded with ``seed``
    (reproducible). ``normalised``: the pixels already through ``K^-1``
    (:func:`robotd.forward.planar.normalised_points`), not computed again."""
    n = len(p_old_px)
    if n < 5:
        return None, PlanarSearch(0, 0, 0)
    k = np.asarray(camera_matrix, np.float64)
    focal = 0.5 * (k[0, 0] + k[1, 1])
    x_old, x_new = normalised_points(p_old_px, p_new_px, k) if normalised is None else normalised
    a = np.stack([-x_new[:, 0] * x_old[:, 1], x_old[:, 1], x_new[:, 1] * x_old[:, 0], -x_new[:, 1]], axis=1)
    terms = _sampson_terms(x_old, x_new)
    thr = threshold_px / focal
    rng = np.random.default_rng(seed)
    log_miss = math.log(1.0 - confidence)

    def needed(count: int) -> int:
        w = min(1.0, max(count, min_inliers) / n)
        miss = 1.0 - w * w
        return 1 if miss <= 0.0 else int(math.ceil(log_miss / math.log(miss)))

    drawn = hyps = 0
    best_n, best_v = -1, np.full(4, np.nan)
    while drawn < min(max_samples, needed(best_n)):
        m = min(batch, max_samples - drawn)
        i = rng.integers(0, n, m)
        j = (i + 1 + rng.integers(0, n - 1, m)) % n
        v = _two_point_motions(a, i, j)
        v = v[np.all(np.isfinite(v), axis=1)]
        drawn += m
        if not len(v):
            continue
        hyps += len(v)
        counts = _inlier_counts(a, terms, v, thr)
        top = int(np.argmax(counts))
        if counts[top] > best_n:
            best_n, best_v = int(counts[top]), v[top]
    if best_n < 0:
        return None, PlanarSearch(drawn, hyps, 0)
    psi = math.atan2(best_v[1], best_v[0])
    yaw = math.remainder(psi - math.atan2(best_v[3], best_v[2]), math.tau)
    search = PlanarSearch(drawn, hyps, best_n, yaw, psi)
    if not refine:
        return None, search
    fit = _refine(x_old, x_new, focal, yaw, psi, threshold_px, False, np.zeros(0), np.zeros(0, np.int64))
    front = fit.inliers & front_mask(x_old, x_new, fit.rotation, fit.translation_dir)
    return PlanarFit(fit.dyaw_rad, fit.bearing_rad, fit.rotation, fit.translation_dir, front,
                     fit.sigma_yaw_rad, fit.sigma_bearing_rad), search


def ridge_span(fit: PlanarFit, margin: float) -> tuple[float, float]:
    """``(lowest, highest)`` heading change (rad) of the ridge around ``fit``'s best heading:
    the contiguous run of scanned headings whose best translation direction keeps at least
    ``fit``'s scan maximum less ``margin`` matches (:attr:`PlanarFit.scan_inliers`). Along
    such a ridge the images cannot tell the headings apart, and each heading has its own
    bearing (for a camera moving along its optical axis, a small turn and a small sideways
    shift move the far points alike). ``(dyaw_rad, dyaw_rad)`` without a scan."""
    n, yaws = fit.scan_inliers, fit.scan_yaw_rad
    if len(n) == 0:
        return fit.dyaw_rad, fit.dyaw_rad
    on = n >= n.max() - margin
    i = int(np.argmin(np.abs(yaws - fit.dyaw_rad)))
    if not on[i]:  # the refined heading between scan steps: start from the best scan step
        i = int(np.argmax(n))
    lo = hi = i
    while lo > 0 and on[lo - 1]:
        lo -= 1
    while hi < len(n) - 1 and on[hi + 1]:
        hi += 1
    return float(yaws[lo]), float(yaws[hi])


def planar_inliers(p_old_px: np.ndarray, p_new_px: np.ndarray, camera_matrix: np.ndarray, dyaw_rad: float,
                   bearing_rad: float, *, threshold_px: float = 1.0) -> np.ndarray:
    """``(N,) bool``: the matched pixels ``p_old_px, p_new_px (N, 2)`` within ``threshold_px``
    (Sampson distance) of the planar motion with heading change ``dyaw_rad`` and bearing
    ``bearing_rad`` (as :class:`PlanarFit` holds them), ``camera_matrix (3, 3)`` shared."""
    p_old = np.asarray(p_old_px, np.float64).reshape(-1, 2)
    p_new = np.asarray(p_new_px, np.float64).reshape(-1, 2)
    if not len(p_old):
        return np.zeros(0, bool)
    k = np.asarray(camera_matrix, np.float64)
    kinv = np.linalg.inv(k)
    x_old = np.hstack([p_old, np.ones((len(p_old), 1))]) @ kinv.T
    x_new = np.hstack([p_new, np.ones((len(p_new), 1))]) @ kinv.T
    r, _ = planar_pose(dyaw_rad, 0.0)
    centre = np.array([-math.sin(bearing_rad), 0.0, math.cos(bearing_rad)])  # the new camera, old frame
    out: np.ndarray = np.abs(_sampson(x_old, x_new, r, -r @ centre, 0.5 * (k[0, 0] + k[1, 1]))) < threshold_px
    return out
