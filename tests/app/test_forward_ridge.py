"""A forward loop whose planar fit lies on a heading-bearing ridge (the camera moving along
its optical axis towards a wall: a small turn and a small sideways shift move the points
alike) is settled by the odometry's heading change, or refused when that lies off the
ridge (robotd.app.stages.forward_loops, RidgeParams)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.app.stages.forward_loops import ForwardLoopStage, HeadingGraph, ridge_headings
from robotd.base.messages import Link
from robotd.forward import ForwardDetector, method_params
from robotd.forward.features import Features
from robotd.forward.planefit import fit_planar, planar_pose, ridge_span
from robotd.forward.verify import ACCEPTED, Verification
from tests.forward.test_planefit import K, _views


def _wall(seed: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of 60 points on a wall 2.8-3.2 m ahead (and 20 outliers), seen before and
    after the camera moved 0.3 m straight ahead without turning (truth: heading 0, bearing 0)."""
    rng = np.random.default_rng(seed)
    x = np.column_stack([rng.uniform(-1.5, 1.5, 60), rng.uniform(-1, 0.6, 60), rng.uniform(2.8, 3.2, 60)])
    xn = x - np.array([0.0, 0.0, 0.3])
    po, pn = x @ K.T, xn @ K.T
    po, pn = po[:, :2] / po[:, 2:], pn[:, :2] / pn[:, 2:]
    pn = pn + rng.normal(0.0, 0.5, pn.shape)
    pn[:20] = rng.uniform(0, 600, (20, 2))
    return po, pn


def _stage(po: np.ndarray, pn: np.ndarray, prior_yaw_deg: float | None, sigma_deg: float = 0.1) -> ForwardLoopStage:
    """A stage whose detector holds the two views, as if the current image were being run:
    the odometry says the heading changed by ``prior_yaw_deg`` (1-sigma ``sigma_deg``
    between the two keyframes); None: the two keyframes are not on one odometry chain."""
    rng = np.random.default_rng(1)
    desc = rng.integers(0, 256, (len(po), 32), dtype=np.uint8)
    det = ForwardDetector(method_params("default"), camera_matrix=K)
    det.process_features(Features(po.astype(np.float32), desc, (640, 480)))
    det.process_features(Features(pn.astype(np.float32), desc, (640, 480)))
    stage = ForwardLoopStage(det)
    # The old image's keyframe as _take records it; the current one as _take holds it.
    stage._keyframe_ids.append(7)
    stage._offsets.append(np.zeros(3))
    stage._poses.append(np.array([1.0, 2.0, 0.3]))
    stage._yaw_vars.append(math.radians(0.5) ** 2)
    stage._chains.append(0)
    yaw = 0.3 + math.radians(prior_yaw_deg or 0.0)
    new_pose = np.array([1.0 + 0.3 * math.cos(yaw), 2.0 + 0.3 * math.sin(yaw), yaw])
    var_new = math.radians(0.5) ** 2 + math.radians(sigma_deg) ** 2
    stage._current = (np.zeros(3), new_pose, var_new, 0 if prior_yaw_deg is not None else 1, 8, len(stage.headings))
    return stage


def _verification(yaw_rad: float, bearing_rad: float) -> Verification:
    r, _ = planar_pose(yaw_rad, 0.0)
    centre = np.array([-math.sin(bearing_rad), 0.0, math.cos(bearing_rad)])
    return Verification(True, ACCEPTED, 40, 40, r, -r @ centre, planarity_chi2=2.0)


def test_the_wall_is_a_ridge_and_the_best_count_picks_the_wrong_place_on_it():
    """The synthetic case itself: the most matches lie at a heading 0.7 deg and a bearing
    6.7 deg off, and the whole ridge keeps nearly as many (the images cannot settle it)."""
    po, pn = _wall()
    fit = fit_planar(po, pn, K, math.radians(1.5))
    assert fit is not None
    assert abs(math.degrees(fit.bearing_rad)) > 5.0  # the wrong choice
    lo, hi = ridge_span(fit, math.sqrt(float(fit.scan_inliers.max())))
    assert math.degrees(hi - lo) > 3.0 and lo < 0.0 < hi
    # Held at the true heading, the same matches give the true bearing.
    at = fit_planar(po, pn, K, 0.0, fix_yaw=True)
    assert at is not None and at.dyaw_rad == 0.0 and at.sigma_yaw_rad == 0.0
    assert math.degrees(at.bearing_rad) == pytest.approx(0.0, abs=1.5)
    assert at.n_inliers >= fit.scan_inliers.max() - math.sqrt(float(fit.scan_inliers.max()))


def test_a_clear_motion_has_no_ridge():
    po, pn = _views(10, 30, 0.5)
    fit = fit_planar(po, pn, K, math.radians(11.0))
    lo, hi = ridge_span(fit, math.sqrt(float(fit.scan_inliers.max())))
    assert math.degrees(hi - lo) < 1.0


def _ridge_sigmas(stage: ForwardLoopStage) -> dict[int, float]:
    """The pending views' ridge bearing sigmas (those the level test set)."""
    return {i: r.sigma_bearing_rad for i, r in stage._pending.items() if r.sigma_bearing_rad is not None}


def test_a_ridge_loop_takes_the_odometry_heading_and_the_bearing_it_implies():
    po, pn = _wall()
    fit = fit_planar(po, pn, K, math.radians(1.5))
    stage = _stage(po, pn, prior_yaw_deg=0.0)
    assert stage._level(0, _verification(fit.dyaw_rad, fit.bearing_rad))
    best, p_old, p_new = stage._pending[0].fit
    assert math.degrees(best.dyaw_rad) == pytest.approx(0.0, abs=1e-9)
    assert math.degrees(best.bearing_rad) == pytest.approx(0.0, abs=1.5)  # the fit alone: 6.7 deg off
    assert len(p_old) == len(p_new) == best.n_inliers
    assert stage.ridge_settled == 1 and stage.ridge_refused == 0
    # The bearing's sigma along the ridge: about 10 deg of bearing per degree of heading
    # (3 m / 0.3 m) times the odometry's 0.1 deg, with the fixed-heading fit's own.
    sigma = math.degrees(stage._pending[0].sigma_bearing_rad)
    assert 0.7 < sigma < 3.0
    assert stage.counters()["forward_ridge_settled"] == 1


def test_a_ridge_loop_the_odometry_heading_lies_off_is_refused():
    po, pn = _wall()
    fit = fit_planar(po, pn, K, math.radians(1.5))
    stage = _stage(po, pn, prior_yaw_deg=6.0)
    assert not stage._level(0, _verification(fit.dyaw_rad, fit.bearing_rad))
    assert stage.ridge_refused == 1 and stage.ridge_settled == 0 and 0 not in stage._pending
    # An odometry heading that uncertain reaches the ridge: settled at the ridge's end.
    loose = _stage(po, pn, prior_yaw_deg=6.0, sigma_deg=2.0)
    assert loose._level(0, _verification(fit.dyaw_rad, fit.bearing_rad))
    scan = fit_planar(po, pn, K, fit.dyaw_rad)  # the stage scans around the verification's heading
    lo, hi = ridge_span(scan, math.sqrt(float(scan.scan_inliers.max())))
    assert loose._pending[0].fit[0].dyaw_rad == pytest.approx(hi)
    assert loose._pending[0].sigma_bearing_rad > stage.ridge.edge_sigma_yaw_rad * 5


def test_a_ridge_loop_without_an_odometry_heading_carries_the_whole_ridge_in_its_bearing_sigma():
    po, pn = _wall()
    fit = fit_planar(po, pn, K, math.radians(1.5))
    stage = _stage(po, pn, prior_yaw_deg=None)
    assert stage._level(0, _verification(fit.dyaw_rad, fit.bearing_rad))
    assert stage.ridge_unsettled == 1 and stage.ridge_settled == 0
    assert math.degrees(stage._pending[0].sigma_bearing_rad) > 10.0  # the ridge spans +-1.8 deg at ~10 deg per deg


def test_a_clear_loop_ignores_the_odometry_heading():
    """No ridge: the images fix the heading, the odometry's (here 6 deg off) is not used."""
    po, pn = _views(10, 30, 0.5)
    stage = _stage(po, pn, prior_yaw_deg=16.0)
    assert stage._level(0, _verification(math.radians(10), math.radians(30)))
    assert stage.ridge_settled == stage.ridge_refused == stage.ridge_unsettled == 0 and not _ridge_sigmas(stage)


def test_the_ridge_test_takes_the_edge_heading_sigma_from_the_config():
    from robotd.app.assemble import build_forward_stage
    from robotd.base.config import Config, replace

    cfg = Config()
    assert build_forward_stage(cfg).ridge.edge_sigma_yaw_rad == pytest.approx(math.radians(1.0))
    wide = replace(cfg, "forward_detector", sigma_yaw_deg=2.5)
    assert build_forward_stage(wide).ridge.edge_sigma_yaw_rad == pytest.approx(math.radians(2.5))


def _link(kind: str, a: int, b: int, dyaw_deg: float, sigma_deg: float, source: str = "floor") -> Link:
    info = np.diag([1e4, 1e4, 1.0 / math.radians(sigma_deg) ** 2])
    return Link(kind, a, b, np.array([0.1, 0.0, math.radians(dyaw_deg)]), info, source=source)


def test_the_heading_graph_knows_a_relative_heading_better_than_the_odometry():
    """Odometry edges 0->1->...->10 each 1 deg off (sigma 1 deg), a floor loop 0->10 saying
    the truth (0 deg, sigma 0.1 deg): the graph puts 10 relative to 0 at about 0 deg, and 5
    too (the loop spreads the drift along the chain), with the sigmas of the weighted mean."""
    g = HeadingGraph()
    for k in range(10):
        g.add_link(_link("odometry", k, k + 1, 1.0, 1.0))
    g.add_link(_link("loop", 0, 10, 0.0, 0.1))
    g.add_link(_link("loop", 0, 10, 40.0, 0.01, source="forward"))  # forward loops: left out
    yaw, sigma = g.relative(0, 10)
    assert math.degrees(yaw) == pytest.approx(10.0 * 0.01 / 10.01, abs=1e-4)  # nearly the loop's 0
    assert math.degrees(sigma) == pytest.approx(1.0 / math.sqrt(1.0 / 10.0 + 1.0 / 0.01), rel=1e-3)
    yaw5, sigma5 = g.relative(0, 5)
    assert math.degrees(yaw5) == pytest.approx(5.0 - 5.0 * 10.0 / 10.01, abs=0.01)
    assert math.degrees(sigma5) < math.sqrt(5.0)  # the loop tightens the middle too
    # A keyframe the links have not reached yet joins the newest linked one by the odometry.
    g.add_keyframe(10, 0.2, math.radians(3.0) ** 2)
    g.add_keyframe(11, 0.2 + math.radians(2.0), math.radians(3.0) ** 2 + math.radians(0.5) ** 2)
    yaw11, sigma11 = g.relative(0, 11)
    assert math.degrees(yaw11) == pytest.approx(math.degrees(yaw) + 2.0, abs=1e-6)
    assert math.degrees(sigma11) == pytest.approx(math.hypot(math.degrees(sigma), 0.5), rel=1e-3)
    assert g.relative(0, 99) is None  # not connected


def test_the_ridge_is_every_heading_the_counts_cannot_tell_from_the_best_not_only_the_run_around_it():
    """A profile like the demo's loop 736 -> 162 of seed 2: a plateau of 28 matches from -3
    to +0.4 deg, a dip of 24, and a peak of 32 at +1.5 deg. The plateau is within one counting
    sigma (sqrt(32) = 5.7) of the peak, so the images cannot tell it from the peak; the run
    around the peak alone is 0.6 deg wide and would call the heading fixed."""
    from types import SimpleNamespace

    from robotd.app.stages.forward_loops import ridge_headings

    deg = np.arange(-4.0, 4.01, 0.2)
    n = np.where(deg < -3.05, 20, np.where(deg < 0.45, 28, np.where(deg < 1.05, 24, np.where(deg < 1.75, 32, 22))))
    n[np.isclose(deg, 1.2)] = 29
    fit = SimpleNamespace(scan_inliers=n, scan_yaw_rad=np.radians(deg), dyaw_rad=math.radians(1.4))
    margin = math.sqrt(32.0)
    lo, hi, on = ridge_headings(fit, margin)
    assert math.degrees(lo) == pytest.approx(-3.0) and math.degrees(hi) == pytest.approx(1.6)
    assert not np.any(np.isclose(np.degrees(on), 0.8))  # the dip is not on it
    lo_r, hi_r, _ = ridge_headings(fit, margin, span="run")
    assert math.degrees(lo_r) == pytest.approx(1.2) and math.degrees(hi_r) == pytest.approx(1.6)


@pytest.mark.parametrize("prior_deg, settled", [(10.5, True), (16.0, False)])
def test_narrow_graph_takes_a_clear_loop_at_a_graph_heading_known_better_than_the_edge_claims(prior_deg, settled):
    """``RidgeParams(narrow="graph")`` (not the default): a loop without a ridge is taken at
    the graph's heading when that heading's 3 sigmas (0.3 deg here) are within the edge's
    heading sigma (1 deg) and it is within 3 edge sigmas of the fit's; else it is kept as
    fitted, for the pose graph's gate."""
    from robotd.app.stages.forward_loops import RidgeParams

    po, pn = _views(10, 30, 0.5)
    stage = _stage(po, pn, prior_yaw_deg=prior_deg)
    stage.ridge = RidgeParams(narrow="graph")
    assert stage._level(0, _verification(math.radians(10), math.radians(30)))
    assert stage.ridge_settled == stage.narrow_settled == int(settled) and stage.ridge_refused == 0
    if settled:
        assert math.degrees(stage._pending[0].fit[0].dyaw_rad) == pytest.approx(prior_deg, abs=0.05)
    else:
        assert not _ridge_sigmas(stage)


def test_a_ridge_loop_without_an_odometry_heading_carries_the_whole_ridge_in_its_heading_sigma_too():
    """Unsettled, the loop's heading is anywhere on the ridge as much as its bearing: the
    edge's heading sigma takes the ridge's half-width (the relocalisation's fit and the gate
    otherwise held a heading the images never fixed to the edge's 1 deg)."""
    from robotd.forward.planar import loop_edge

    po, pn = _wall()
    fit = fit_planar(po, pn, K, math.radians(1.5))
    stage = _stage(po, pn, prior_yaw_deg=None)
    assert stage._level(0, _verification(fit.dyaw_rad, fit.bearing_rad))
    scan = fit_planar(po, pn, K, fit.dyaw_rad)
    lo, hi, _on = ridge_headings(scan, math.sqrt(float(scan.scan_inliers.max())))
    assert stage._pending[0].sigma_yaw_rad == pytest.approx(0.5 * (hi - lo))
    assert math.degrees(stage._pending[0].sigma_yaw_rad) > 1.5  # the ridge spans about +-1.8 deg
    _d, info = loop_edge(np.array([0.3, 0.0, 0.0]), 0.0, 0.0, sigma_bearing_rad=stage._pending[0].sigma_bearing_rad,
                         sigma_yaw_rad=stage._pending[0].sigma_yaw_rad)
    _d, info_fixed = loop_edge(np.array([0.3, 0.0, 0.0]), 0.0, 0.0, sigma_bearing_rad=stage._pending[0].sigma_bearing_rad)
    assert math.sqrt(np.linalg.inv(info)[2, 2]) == pytest.approx(
        math.hypot(math.sqrt(np.linalg.inv(info_fixed)[2, 2]), stage._pending[0].sigma_yaw_rad), rel=1e-3)
    # Settled by a prior heading, the loop's heading is that prior's: no ridge-wide sigma.
    settled = _stage(po, pn, prior_yaw_deg=0.0)
    assert settled._level(0, _verification(fit.dyaw_rad, fit.bearing_rad)) and settled._pending[0].sigma_yaw_rad is None
    assert settled._pending[0].at_prior


def _links_now(stage: ForwardLoopStage) -> None:
    """The current keyframe stored after the links the heading graph holds now."""
    cur = stage._current
    assert cur is not None
    stage._current = (*cur[:5], len(stage.headings))


def test_forward_loops_that_relocalised_the_robot_settle_a_ridge_loop_across_the_carry():
    """Across a kidnapping without the floor camera nothing but forward loops ties the two
    odometry chains' headings: their links (a measured heading) go into the heading graph,
    so a later ridge loop across the carry is settled at the heading they give, not left at
    the count's best (here 0.7 deg and 6.7 deg of bearing off)."""
    po, pn = _wall()
    fit = fit_planar(po, pn, K, math.radians(1.5))
    stage = _stage(po, pn, prior_yaw_deg=None)
    stage._chain_of.update({7: 0, 8: 1})  # the old image's keyframe on chain 0, the current one's on 1
    stage.on_link(_link("loop", 7, 8, 0.0, 0.3, source="forward"))
    _links_now(stage)
    assert stage.headings.relative(7, 8) is not None
    assert stage._level(0, _verification(fit.dyaw_rad, fit.bearing_rad))
    assert stage.ridge_settled == 1 and stage.ridge_unsettled == 0
    assert math.degrees(stage._pending[0].fit[0].bearing_rad) == pytest.approx(0.0, abs=1.5)


def test_a_forward_link_on_one_chain_or_taken_at_the_prior_stays_out_of_the_heading_graph():
    po, pn = _wall()
    # One chain: the forward loop's heading is what the graph is asked to judge.
    same = _stage(po, pn, prior_yaw_deg=None)
    same._chain_of.update({7: 0, 8: 0})
    same.on_link(_link("loop", 7, 8, 0.0, 0.3, source="forward"))
    assert len(same.headings) == 0
    # Across chains, but published at the heading graph's own heading: an echo, not a measurement.
    echo = _stage(po, pn, prior_yaw_deg=None)
    echo._chain_of.update({7: 0, 8: 1})
    echo._prior_loops.add((7, 8))
    echo.on_link(_link("loop", 7, 8, 0.0, 0.3, source="forward"))
    assert len(echo.headings) == 0
    # A keyframe the stage has no image of (its chain unknown): left out.
    unknown = _stage(po, pn, prior_yaw_deg=None)
    unknown.on_link(_link("loop", 3, 8, 0.0, 0.3, source="forward"))
    assert len(unknown.headings) == 0
    # Odometry and floor loop links go in as before.
    unknown.on_link(_link("odometry", 7, 8, 0.0, 0.3))
    assert len(unknown.headings) == 1
