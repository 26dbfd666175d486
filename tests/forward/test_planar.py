"""A verified forward loop as a planar edge (robotd.forward.planar)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.base.geometry import between, compose, inverse
from robotd.forward.planar import PlanarLoopParams, loop_edge, planar_motion

# Planar frame (x forward, y left, z up) -> OpenCV camera axes (x right, y down, z forward).
_CAM_FROM_PLANAR = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def _opencv_motion(rel: np.ndarray, pitch_rad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t_dir)`` as cv2.recoverPose reports them for a new camera at planar pose ``rel``
    (x, y, yaw) in the old camera's planar frame, optionally pitched up by ``pitch_rad``."""
    c, s = math.cos(rel[2]), math.sin(rel[2])
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])   # new planar axes in old planar
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    ry = np.array([[cp, 0.0, -sp], [0.0, 1.0, 0.0], [sp, 0.0, cp]])  # nose up about the planar y axis
    # new camera axes in the old camera frame
    r_old_new = _CAM_FROM_PLANAR @ rz @ ry @ _CAM_FROM_PLANAR.T
    centre = _CAM_FROM_PLANAR @ np.array([rel[0], rel[1], 0.0])
    r = r_old_new.T                  # X_new = R X_old + t
    t = -r @ centre
    return r, t / np.linalg.norm(t)


@pytest.mark.parametrize("rel", [(2.0, 0.0, 0.0), (1.0, 1.0, math.radians(30)),
                                 (-0.5, -2.0, math.radians(-100)), (0.3, 0.1, math.radians(170))])
def test_planar_motion_recovers_heading_change_and_bearing(rel):
    rel = np.array(rel)
    dyaw, bearing, tilt = planar_motion(*_opencv_motion(rel))
    assert dyaw == pytest.approx(rel[2], abs=1e-9)
    assert bearing == pytest.approx(math.atan2(rel[1], rel[0]), abs=1e-9)
    assert tilt == pytest.approx(0.0, abs=1e-9)


def test_planar_motion_reports_a_tilted_motion():
    _, _, tilt = planar_motion(*_opencv_motion(np.array([1.0, 0.5, 0.3]), pitch_rad=math.radians(15)))
    assert tilt == pytest.approx(math.radians(15), abs=1e-6)


def _measure(predicted_base: np.ndarray, true_base: np.ndarray, mount: np.ndarray):
    """The camera-frame dyaw and bearing of the *true* motion, as a perfect verification gives."""
    cam = compose(compose(inverse(mount), true_base), mount)
    return cam[2], math.atan2(cam[1], cam[0])


@pytest.mark.parametrize("mount", [np.zeros(3), np.array([0.1, 0.0, 0.0]), np.array([0.2, -0.05, 0.3])])
def test_a_right_prediction_and_a_perfect_measurement_give_the_predicted_edge(mount):
    true = np.array([1.5, -0.7, math.radians(120)])
    dyaw, bearing = _measure(true, true, mount)
    delta, info = loop_edge(true, dyaw, bearing, mount)
    np.testing.assert_allclose(delta, true, atol=1e-9)
    assert np.all(np.linalg.eigvalsh(info) > 0)


def test_the_edge_keeps_the_measured_bearing_and_takes_only_the_range_from_the_prediction():
    mount = np.array([0.1, 0.0, 0.0])
    true = np.array([2.0, 1.0, math.radians(45)])
    # The prediction is 30 % too long in range but right in direction and heading.
    cam_true = compose(compose(inverse(mount), true), mount)
    cam_pred = cam_true.copy()
    cam_pred[:2] *= 1.3
    predicted = compose(compose(mount, cam_pred), inverse(mount))
    dyaw, bearing = _measure(predicted, true, mount)
    delta, info = loop_edge(predicted, dyaw, bearing, mount)
    np.testing.assert_allclose(delta, predicted, atol=1e-9)  # the same direction: nothing to correct
    # The range error costs almost nothing; a bearing error of 10 deg costs a lot.
    e_range = np.array([*(cam_true[:2] - cam_pred[:2]), 0.0])  # the range difference, camera frame
    e_range = np.array([*np.array([[math.cos(delta[2]), math.sin(delta[2])],
                                   [-math.sin(delta[2]), math.cos(delta[2])]]) @ e_range[:2], 0.0])
    assert e_range @ info @ e_range < 0.5
    wrong = loop_edge(predicted, dyaw, bearing + math.radians(10), mount)[0]
    e_wrong = between(delta, wrong)
    assert e_wrong @ info @ e_wrong > 16.27  # the gate's 99.9 % point


def test_heading_information_follows_sigma_yaw():
    true = np.array([1.0, 0.0, 0.2])
    dyaw, bearing = _measure(true, true, np.zeros(3))
    _, info_tight = loop_edge(true, dyaw, bearing, params=PlanarLoopParams(sigma_yaw_rad=math.radians(0.5)))
    _, info_loose = loop_edge(true, dyaw, bearing, params=PlanarLoopParams(sigma_yaw_rad=math.radians(2.0)))
    cov_tight, cov_loose = np.linalg.inv(info_tight), np.linalg.inv(info_loose)
    assert math.sqrt(cov_tight[2, 2]) == pytest.approx(math.radians(0.5), rel=1e-3)
    assert math.sqrt(cov_loose[2, 2]) == pytest.approx(math.radians(2.0), rel=1e-3)


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="sigma_bearing_rad"):
        PlanarLoopParams(sigma_bearing_rad=0.0)


def test_verified_rendered_views_give_the_true_planar_motion():
    """Two frames of the virtual forward camera, verified by the five-point method: the heading
    change and bearing match the true camera poses."""
    from robotd.forward import extract_features, verify_pair
    from sim.cameras.forward import (
        ForwardCameraModel,
        ForwardRenderer,
        ForwardRenderParams,
    )
    from sim.world.rooms import world_for_route

    model = ForwardCameraModel()
    renderer = ForwardRenderer(world_for_route("office", 0), model, ForwardRenderParams(),
                               np.random.default_rng(0))
    k = np.array([[model.intrinsics.fx_px, 0, model.intrinsics.cx_px],
                  [0, model.intrinsics.fy_px, model.intrinsics.cy_px], [0, 0, 1.0]])
    mount = np.array([model.x_m, model.y_m, model.yaw_rad])
    a = np.array([2.0, 0.0, 0.0])
    checked = 0
    for b in (np.array([2.6, 0.15, math.radians(8)]), np.array([3.0, -0.2, math.radians(-12)])):
        v = verify_pair(extract_features(renderer.render(a)), extract_features(renderer.render(b)),
                        camera_matrix=k)
        assert v.accepted, v.reason
        dyaw, bearing, tilt = planar_motion(v.rotation, v.translation_dir)
        cam = between(compose(a, mount), compose(b, mount))
        assert math.degrees(abs(dyaw - cam[2])) < 1.0
        assert math.degrees(abs(bearing - math.atan2(cam[1], cam[0]))) < 3.0
        assert math.degrees(tilt) < 3.0
        checked += 1
    assert checked == 2


def test_a_measured_range_replaces_the_predicted_one_and_is_weighed():
    """With ``range_m`` (measured on the floor) the edge's length is the measurement, not
    the prediction's, and its range is far better constrained than a predicted one's."""
    true = np.array([2.0, 0.0, 0.0])
    d_pred, i_pred = loop_edge(true, 0.0, 0.0)
    d_meas, i_meas = loop_edge(true, 0.0, 0.0, range_m=0.4)
    assert d_pred[0] == pytest.approx(2.0) and d_meas[0] == pytest.approx(0.4)
    # Information along x (the range) at a 2 m range: 1 / (2 m * 1.0)^2 predicted, about
    # 1 / (0.4 m * 0.5)^2 measured.
    assert i_meas[0, 0] > 20 * i_pred[0, 0]
    with pytest.raises(ValueError):
        loop_edge(true, 0.0, 0.0, range_m=-1.0)


# --- the bearing's uncertainty from the inliers (robotd.forward.planar.refine_motion) -------

def _synthetic_pair(rel: np.ndarray, noise_px: float, rng: np.random.Generator, n: int = 120):
    """Noisy pixels ``(N, 2), (N, 2)`` of points 1.5-8 m ahead seen from the old camera and
    from a new one at planar pose ``rel``, with ``(R, t_dir)`` the truth, and the camera matrix."""
    k = np.array([[525.0, 0.0, 320.0], [0.0, 525.0, 240.0], [0.0, 0.0, 1.0]])
    r, t = _opencv_motion(rel)
    centre = -r.T @ t  # unit-length new camera centre in the old frame; scale it to the range
    s = math.hypot(rel[0], rel[1])
    z = rng.uniform(1.5, 8.0, n)
    pts = np.column_stack([rng.uniform(-0.45, 0.45, n) * z, rng.uniform(-0.35, 0.35, n) * z, z])
    new = (pts - s * centre) @ r.T
    keep = new[:, 2] > 0.5
    pts, new = pts[keep], new[keep]
    p_old = (pts / pts[:, 2:]) @ k.T
    p_new = (new / new[:, 2:]) @ k.T
    p_old = p_old[:, :2] + rng.normal(0.0, noise_px, (len(pts), 2))
    p_new = p_new[:, :2] + rng.normal(0.0, noise_px, (len(pts), 2))
    in_view = (p_new[:, 0] > 0) & (p_new[:, 0] < 640) & (p_new[:, 1] > 0) & (p_new[:, 1] < 480)
    return p_old[in_view], p_new[in_view], r, t, k


@pytest.mark.parametrize("baseline_m", [0.25, 1.0])
def test_the_claimed_bearing_sigma_is_the_spread_of_the_bearing_over_noisy_images(baseline_m):
    """Monte Carlo against the Cramer-Rao covariance: the refined bearing's spread over many
    noisy draws of one scene matches the sigma each draw claims, at a short and a long
    baseline, and the noise is recovered from the residuals."""
    from robotd.forward.planar import refine_motion

    rel = np.array([baseline_m * math.cos(0.6), baseline_m * math.sin(0.6), math.radians(5.0)])
    t_bearing = math.atan2(rel[1], rel[0])
    rng = np.random.default_rng(7)
    errors, sigmas, noises = [], [], []
    for _ in range(150):
        p_old, p_new, r, t, k = _synthetic_pair(rel, 0.5, rng)
        # Start off the truth, as a five-point sample would.
        r0 = r @ np.array([[1.0, -0.002, 0.004], [0.002, 1.0, 0.0], [-0.004, 0.0, 1.0]])
        t0 = t + rng.normal(0.0, 0.03, 3)
        r_ref, t_ref, sig_b, sig_y, noise = refine_motion(p_old, p_new, r0, t0 / np.linalg.norm(t0), k)
        _, bearing, _ = planar_motion(r_ref, t_ref)
        errors.append(math.remainder(bearing - t_bearing, math.tau))
        sigmas.append(sig_b)
        noises.append(noise)
    spread = float(np.sqrt(np.mean(np.square(errors))))
    claimed = float(np.sqrt(np.mean(np.square(sigmas))))
    assert 0.75 < spread / claimed < 1.33
    assert float(np.median(noises)) == pytest.approx(0.5, rel=0.1)


def test_the_bearing_sigma_grows_as_the_baseline_shrinks():
    """One scene seen from new cameras ever closer to the old one: the parallax shrinks with
    the baseline, and the claimed bearing sigma grows about inversely with it."""
    from robotd.forward.planar import refine_motion

    sig = {}
    for b in (0.1, 0.2, 0.4, 0.8):
        rel = np.array([b * math.cos(1.0), b * math.sin(1.0), 0.0])
        p_old, p_new, r, t, k = _synthetic_pair(rel, 0.5, np.random.default_rng(3), n=300)
        sig[b] = refine_motion(p_old, p_new, r, t, k)[2]
    for b in (0.1, 0.2, 0.4):
        assert 1.7 < sig[b] / sig[2 * b] < 2.4  # measured 2.0-2.2
    assert math.degrees(sig[0.1]) > 0.5 > math.degrees(sig[0.8])


def test_a_measured_bearing_sigma_loosens_the_edge_across_the_baseline():
    true = np.array([0.25, 0.0, 0.0])
    dyaw, bearing = 0.0, 0.0
    _, info_default = loop_edge(true, dyaw, bearing, range_m=0.25)
    _, info_loose = loop_edge(true, dyaw, bearing, range_m=0.25, sigma_bearing_rad=math.radians(10.0))
    # Across the baseline (y) the edge now allows about 0.25 m * 10 deg, plus the 3 cm floor.
    sig_y_default = math.sqrt(np.linalg.inv(info_default)[1, 1])
    sig_y_loose = math.sqrt(np.linalg.inv(info_loose)[1, 1])
    expect = math.hypot(0.03, 0.25 * math.hypot(math.radians(2.0), math.radians(10.0)))
    assert sig_y_loose == pytest.approx(expect, rel=0.05)
    assert sig_y_default == pytest.approx(math.hypot(0.03, 0.25 * math.radians(2.0)), rel=0.05)
    with pytest.raises(ValueError, match="sigma_bearing_rad"):
        loop_edge(true, dyaw, bearing, sigma_bearing_rad=math.nan)


def test_batched_rotations_and_essentials_equal_the_one_at_a_time_ones() -> None:
    """fit_motion builds its perturbed motions in one pass (_rotvec_matrices, _skews): each
    row must equal the single-vector Rodrigues and [t]x R it replaced, the zero vector
    included (identity), and the cross product the helper computes must be numpy's."""
    from robotd.forward.planar import _cross, _essential, _rotvec_matrices, _rotvec_matrix, _skews

    rng = np.random.default_rng(3)
    w = np.vstack([rng.normal(size=(6, 3)) * 0.7, np.zeros((1, 3)), np.eye(3) * 1e-6])
    batch = _rotvec_matrices(w)
    for i in range(len(w)):
        np.testing.assert_allclose(batch[i], _rotvec_matrix(w[i]), rtol=0, atol=1e-14)
    r = _rotvec_matrix(np.array([0.1, -0.3, 0.2]))
    t = rng.normal(size=(len(w), 3))
    es = _skews(t) @ (batch @ r)
    for i in range(len(w)):
        np.testing.assert_allclose(es[i], _essential(batch[i] @ r, t[i]), rtol=0, atol=1e-12)
    a, b = rng.normal(size=3), rng.normal(size=3)
    np.testing.assert_allclose(_cross(a, b), np.cross(a, b), rtol=0, atol=1e-15)


# --- fit_motion in fewer calls, against the code before it (a reference kept here) ---------

def _fit_motion_reference(p_old_px, p_new_px, rotation, translation_dir, camera_matrix, iterations=5):
    """:func:`robotd.forward.planar.fit_motion` as it was before its constant perturbations
    were made once, the sigma part's angles computed once per pose and the condition number
    tested without the SVD where it is clear: the reference it must equal to the bit."""
    from robotd.base.geometry import wrap_angle
    from robotd.forward.planar import (MotionFit, _cross, _rotvec_matrices, _rotvec_matrix, _sampson_px_many,
                                       _skews, out_of_plane)

    p_old = np.asarray(p_old_px, np.float64).reshape(-1, 2)
    p_new = np.asarray(p_new_px, np.float64).reshape(-1, 2)
    r0 = np.asarray(rotation, np.float64).reshape(3, 3)
    t0 = np.asarray(translation_dir, np.float64).reshape(3)
    t0 = t0 / max(float(np.linalg.norm(t0)), 1e-15)
    n = len(p_old)
    if n < 6:
        return MotionFit(r0, t0)
    k = np.asarray(camera_matrix, np.float64)
    kinv = np.linalg.inv(k)
    focal = 0.5 * (k[0, 0] + k[1, 1])
    x_old = np.hstack([p_old, np.ones((n, 1))]) @ kinv.T
    x_new = np.hstack([p_new, np.ones((n, 1))]) @ kinv.T

    def linearise(r, t):
        a = np.eye(3)[int(np.argmin(np.abs(t)))]
        e1 = _cross(t, a)
        e1 /= math.sqrt(float(e1 @ e1))
        e2 = _cross(t, e1)

        def pose(theta):
            tt = t + theta[3] * e1 + theta[4] * e2
            return _rotvec_matrix(theta[:3]) @ r, tt / math.sqrt(float(tt @ tt))

        h = 1e-6
        steps = np.vstack([np.eye(5) * h, -np.eye(5) * h, np.zeros((1, 5))])
        tt = t + steps[:, 3:4] * e1 + steps[:, 4:5] * e2
        tt /= np.sqrt(np.einsum("ij,ij->i", tt, tt))[:, None]
        es = _skews(tt) @ (_rotvec_matrices(steps[:, :3]) @ r)
        s = _sampson_px_many(x_old, x_new, es, focal)
        jac = ((s[:5] - s[5:10]) / (2 * h)).T
        return s[10], jac, pose

    r, t = r0, t0
    res, jac, pose = linearise(r, t)
    cost = float(res @ res)
    for _ in range(iterations):
        jtj = jac.T @ jac
        if not np.all(np.isfinite(jtj)) or np.linalg.cond(jtj) > 1e14:
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
    if not np.all(np.isfinite(jtj)) or np.linalg.cond(jtj) > 1e14:
        return MotionFit(r, t, noise_px=noise)
    cov = noise**2 * np.linalg.inv(jtj)
    grad = np.zeros((2, 5))
    g_out = np.zeros((3, 5))
    h = 1e-6
    plus, minus = [pose(d) for d in np.eye(5) * h], [pose(d) for d in np.eye(5) * -h]
    for j in range(5):
        yp, bp, _ = planar_motion(*plus[j])
        ym, bm, _ = planar_motion(*minus[j])
        grad[:, j] = (wrap_angle(bp - bm) / (2 * h), wrap_angle(yp - ym) / (2 * h))
        g_out[:, j] = (out_of_plane(*plus[j]) - out_of_plane(*minus[j])) / (2 * h)
    var = np.einsum("ij,jk,ik->i", grad, cov, grad)
    c_out = g_out @ cov @ g_out.T
    e_out = out_of_plane(r, t)
    try:
        chi2 = float(e_out @ np.linalg.solve(c_out, e_out))
    except np.linalg.LinAlgError:
        chi2 = math.nan
    return MotionFit(r, t, math.sqrt(max(float(var[0]), 0.0)), math.sqrt(max(float(var[1]), 0.0)), noise,
                     chi2 if math.isfinite(chi2) and chi2 >= 0.0 else math.nan)


def _motion_bytes(f) -> list[bytes]:
    return [np.asarray(getattr(f, name), np.float64).tobytes() for name in
            ("rotation", "translation_dir", "sigma_bearing_rad", "sigma_yaw_rad", "noise_px", "planarity_chi2")]


@pytest.mark.parametrize("seed", range(4))
def test_fit_motion_is_the_reference_s_to_the_bit(seed):
    """The refinement in fewer calls gives the reference's motion, sigmas, noise and
    planarity to the bit: level and tilted motions, short and long baselines, few and many
    points, clean and noisy, with outliers, started off the truth, and degenerate sets
    (pure rotation, every point one match: the condition number's SVD path)."""
    from robotd.forward.planar import fit_motion

    rng = np.random.default_rng(seed)
    cases = 0
    for _ in range(30):
        rel = np.array([rng.uniform(-1.5, 1.5), rng.uniform(-1.0, 1.0), rng.uniform(-0.6, 0.6)])
        if rng.random() < 0.15:
            rel[:2] = 0.0  # a pure turn: the translation's direction is not fixed
        noise = float(rng.choice([0.0, 0.3, 1.0, 3.0]))
        n = int(rng.choice([8, 20, 60, 150]))
        p_old, p_new, r, t, k = _synthetic_pair(rel if rel[:2].any() else rel + [1e-9, 0, 0], noise, rng, n)
        if rng.random() < 0.3:  # outliers
            m = max(1, len(p_new) // 5)
            p_new[:m] = rng.uniform([0, 0], [640, 480], (m, 2))
        if rng.random() < 0.1:  # every point the same match: a singular normal matrix
            p_old[:] = p_old[0]
            p_new[:] = p_new[0]
        tilt = _rotvec_matrix_of(rng.normal(size=3) * float(rng.choice([0.0, 0.02, 0.2])))
        t0 = t + rng.normal(size=3) * 0.05
        a, b = fit_motion(p_old, p_new, tilt @ r, t0, k), _fit_motion_reference(p_old, p_new, tilt @ r, t0, k)
        assert _motion_bytes(a) == _motion_bytes(b)
        cases += math.isfinite(b.sigma_bearing_rad)
    assert cases >= 10  # most cases reach the sigma part


def _rotvec_matrix_of(w):
    from robotd.forward.planar import _rotvec_matrix

    return _rotvec_matrix(np.asarray(w, np.float64))


def test_the_condition_test_without_the_svd_decides_as_the_svd():
    """fit_motion's condition test (the SVD only where the eigenvalues leave it open) says
    what ``np.linalg.cond(m) > 1e14`` says, on normal matrices from well to badly
    conditioned and singular."""
    from robotd.forward.planar import _COND_LIMIT, _ill_conditioned

    rng = np.random.default_rng(7)
    seen = set()
    for scale in (0.0, 1e-3, 1e-6, 1e-7, 1e-8, 1e-9, 1e-12):
        for _ in range(40):
            jac = rng.normal(size=(30, 5))
            jac[:, 4] = jac[:, 3] + scale * rng.normal(size=30)  # two columns alike, to the scale
            m = jac.T @ jac
            expected = bool(np.linalg.cond(m) > _COND_LIMIT)
            assert _ill_conditioned(m) == expected
            seen.add(expected)
    assert seen == {True, False}
