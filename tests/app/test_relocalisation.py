"""Relocalisation in the pipeline (pose graph + map writer): a restart on a stored map is
"not localised" until two floor loops agree, then joins the map frame; a kidnapping
(wheel drop) breaks the odometry chain, makes the daemon "LOST", and relocalises the same
way against the run's own earlier keyframes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from robotd.app.pipeline import Pipeline
from robotd.app.stages.map_writer import MapWriterStage
from robotd.app.stages.pose_graph import PoseGraphStage
from robotd.base.geometry import between, compose, wrap_angle
from robotd.base.messages import ForwardLoop, Frame, Keyframe, LoopCandidate, PoseStamped, WheelDrop
from robotd.graph.incremental import IncrementalGraph
from robotd.io.store import MapStore

LOOP_INFO = np.diag([1 / 0.003**2, 1 / 0.003**2, 1 / 0.003**2])
DRIFT = np.array([0.0, 0.0, 0.004])  # rad of odometry heading error per 0.25 m step


def _square_laps(laps: int, start: int = 0) -> np.ndarray:
    """True keyframe poses on a 1 m square (0.25 m steps, a 90 deg turn at each corner; a
    lap is 20 steps), beginning at step ``start`` of the lap."""
    steps = [np.array([0.25, 0.0, 0.0])] * 4 + [np.array([0.0, 0.0, math.pi / 2])]
    pose = np.zeros(3)
    for k in range(start):
        pose = compose(pose, steps[k % 5])
    out = [pose]
    for k in range(start, start + 20 * laps):
        out.append(compose(out[-1], steps[k % 5]))
    return np.array(out)


def _pipeline(store: MapStore, run: int) -> tuple[Pipeline, PoseGraphStage]:
    p = Pipeline()
    graph = p.add(PoseGraphStage(IncrementalGraph(), store))
    p.add(MapWriterStage(store, run, image_width_px=0, takes=Keyframe))
    return p, graph


class _Odometry:
    """Publishes keyframes along a true path with odometry that starts at its own origin
    and drifts in heading; remembers the stored ids."""

    def __init__(self, p: Pipeline, store: MapStore, run: int) -> None:
        self.p, self.store, self.run = p, store, run
        self.odo: np.ndarray | None = None
        self.prev_truth: np.ndarray | None = None
        self.cov = np.zeros((3, 3))
        self.ids: list[int] = []
        self.truth: list[np.ndarray] = []
        self.lifted = False  # since the previous keyframe (what the keyframe stage tells the writer)

    def keyframe(self, truth: np.ndarray, stamp_s: float) -> int:
        if self.odo is None:
            self.odo = np.zeros(3)
        elif self.prev_truth is not None:
            self.odo = compose(self.odo, between(self.prev_truth, truth) + DRIFT)
            self.cov = self.cov + np.diag([1e-6, 1e-6, 2e-5])
        self.prev_truth = truth
        stamp = int(stamp_s * 1e9)
        self.p.publish(Keyframe(Frame(stamp, "floor", np.zeros((4, 4), np.uint8), len(self.ids)),
                                PoseStamped(stamp, *self.odo, self.cov.copy()), carried=self.lifted))
        self.lifted = False
        kid = max(k.id for k in self.store.keyframes(self.run))
        self.ids.append(kid)
        self.truth.append(truth)
        return kid

    def carried(self) -> None:
        """The robot was lifted: the wheels stop, the odometry holds its pose."""
        self.prev_truth = None
        self.lifted = True


def _loop(p: Pipeline, old_id: int, old_truth: np.ndarray, new_id: int, new_truth: np.ndarray,
          rng: np.random.Generator, offset: np.ndarray | None = None) -> None:
    meas = between(old_truth, new_truth) + rng.normal(0.0, 0.002, 3)
    if offset is not None:
        meas = meas + offset
    p.publish(LoopCandidate(old_id, new_id, 200.0, meas, LOOP_INFO))


def _first_run(store: MapStore, rng: np.random.Generator) -> tuple[list[int], np.ndarray]:
    """A first run round the square twice, closed by loops: it starts the map."""
    run = store.begin_run("")
    p, graph = _pipeline(store, run)
    assert graph.status_fragment() == ""
    drive = _Odometry(p, store, run)
    truth = _square_laps(2)
    for k, t in enumerate(truth):
        drive.keyframe(t, k)
    for a in (0, 5, 10, 15, 20):
        _loop(p, drive.ids[a], truth[a], drive.ids[a + 20], truth[a + 20], rng)
    p.finish()
    store.end_run(run)
    return drive.ids, truth


def _error_m(store: MapStore, ids: list[int], truth: list[np.ndarray]) -> float:
    opt = store.optimized_poses()
    return max(float(np.hypot(*(opt[k][:2] - t[:2]))) for k, t in zip(ids, truth))


def test_a_restart_relocalises_after_two_agreeing_loops_and_joins_the_map(tmp_path: Path):
    rng = np.random.default_rng(11)
    with MapStore.open(tmp_path / "map.sqlite") as store:
        old_ids, old_truth = _first_run(store, rng)
        assert store.map_frame_runs() == {1}
        assert _error_m(store, old_ids, old_truth) < 0.05
        map_before = store.optimized_poses()
        run = store.begin_run("")
        p, graph = _pipeline(store, run)
        drive = _Odometry(p, store, run)
        truth = _square_laps(1, start=7)  # restarted at another corner of the map, heading elsewhere
        for k in range(3):
            drive.keyframe(truth[k], 100 + k)
        assert graph.status_fragment() == "not localised in the stored map"
        # A look-alike first (the floor of keyframe 13 seen 0.3 m off), then a true loop: they disagree.
        _loop(p, old_ids[13], old_truth[13], drive.ids[2], truth[2], rng, offset=np.array([0.3, 0.0, 0.4]))
        for k in range(3, 6):
            drive.keyframe(truth[k], 100 + k)
        _loop(p, old_ids[12], old_truth[12], drive.ids[5], truth[5], rng)
        assert graph.status_fragment() == "not localised in the stored map"
        assert p.counters()["localised"] == 0
        for k in range(6, 9):
            drive.keyframe(truth[k], 100 + k)
        _loop(p, old_ids[15], old_truth[15], drive.ids[8], truth[8], rng)  # 0.75 m further: agrees
        c = p.counters()
        assert (c["localised"], c["relocalisations"]) == (1, 1)
        assert graph.status_fragment() == "relocalised against run 1 after 8.0 s and 1.5 m (floor camera)"
        # From now on the gate judges as usual: a true loop passes, a look-alike does not.
        for k in range(9, 21):
            drive.keyframe(truth[k], 100 + k)
        fates = {(r.query_id, r.candidate_id): (r.fate, r.detail) for r in store.loop_candidates()}
        assert fates[(drive.ids[2], old_ids[13])][0] == "failed_gate"
        # Held until then, the look-alike meets the gate once the run is in the map frame.
        assert fates[(drive.ids[2], old_ids[13])][1].startswith("chi2 ")
        assert fates[(drive.ids[5], old_ids[12])][0] == "accepted"
        assert fates[(drive.ids[8], old_ids[15])][0] == "accepted"
        _loop(p, old_ids[2], old_truth[2], drive.ids[15], truth[15], rng)
        _loop(p, old_ids[5], old_truth[5], drive.ids[18], truth[18], rng, offset=np.array([0.35, 0.0, 0.0]))
        p.finish()
        c = p.counters()
        assert (c["loops_accepted"], c["loops_failed_gate"]) == (3, 2)
        assert store.map_frame_runs() == {1, 2}
        # The restarted run's keyframes are in the map frame (the first run's), near the truth.
        assert _error_m(store, drive.ids, drive.truth) < 0.05
        # ... and the first run's map poses were not moved.
        after = store.optimized_poses()
        assert all(np.array_equal(after[k], map_before[k]) for k in old_ids)


def test_a_single_look_alike_after_a_restart_leaves_the_run_unlocalised(tmp_path: Path):
    rng = np.random.default_rng(12)
    with MapStore.open(tmp_path / "map.sqlite") as store:
        old_ids, old_truth = _first_run(store, rng)
        run = store.begin_run("")
        p, graph = _pipeline(store, run)
        drive = _Odometry(p, store, run)
        truth = _square_laps(1, start=3)
        for k in range(12):
            drive.keyframe(truth[k], 100 + k)
        _loop(p, old_ids[9], old_truth[9], drive.ids[4], truth[4], rng, offset=np.array([0.0, 0.4, -0.5]))
        p.finish()
        c = p.counters()
        assert (c["localised"], c["relocalisations"], c["reloc_candidates_refused"]) == (0, 0, 1)
        assert graph.status_fragment() == "not localised in the stored map"
        [fate] = [r for r in store.loop_candidates() if r.query_id in drive.ids]
        assert (fate.fate, fate.detail) == ("failed_gate", "relocalisation: no agreeing candidate before the run ended")
        assert store.map_frame_runs() == {1}
        # Not in the map frame: no optimised poses for this run.
        assert not set(store.optimized_poses()) & set(drive.ids)
        assert store.links("loop") and all(lk.to_id not in drive.ids for lk in store.links("loop"))


def test_a_kidnapping_breaks_the_chain_and_relocalises_against_the_run_itself(tmp_path: Path):
    rng = np.random.default_rng(13)
    with MapStore.open(tmp_path / "map.sqlite") as store:
        run = store.begin_run("")
        p, graph = _pipeline(store, run)
        drive = _Odometry(p, store, run)
        lap = _square_laps(2)
        for k in range(21):  # a lap and a step
            drive.keyframe(lap[k], k)
        before = drive.ids[-1]
        p.publish(WheelDrop(int(20.4e9), True, left=True, right=True))
        assert graph.status_fragment() == "LOST (lifted)"
        p.publish(WheelDrop(int(24e9), False))
        assert graph.status_fragment() == "LOST (relocalising)"
        drive.carried()
        # Put down at step 7 of the lap (1.25 m and a quarter turn from where it was lifted).
        after = _square_laps(1, start=7)
        new_ids = [drive.keyframe(t, 25 + k) for k, t in enumerate(after[:10])]
        c = p.counters()
        assert c["odometry_breaks"] == 1 and c["lifts"] == 1
        assert not any(lk.from_id == before and lk.to_id == new_ids[0] for lk in store.links("odometry"))
        # A candidate of the lost segment is not judged by the gate against the old frame.
        _loop(p, drive.ids[8], lap[8], new_ids[1], after[1], rng)
        assert c["loops_accepted"] == 0 and graph.status_fragment() == "LOST (relocalising)"
        _loop(p, drive.ids[11], lap[11], new_ids[4], after[4], rng)
        c = p.counters()
        assert (c["relocalisations"], c["localised"], c["loops_accepted"]) == (1, 1, 2)
        assert graph.status_fragment() == "relocalised against run 1 after 5.0 s and 0.8 m (floor camera)"
        p.finish()
        opt = store.optimized_poses()
        # The map itself is off where the robot is put down: keyframes 8 and 11 of a lap
        # without loops carry 8 to 11 steps of 0.004 rad of heading drift (1.8 to 2.5 deg).
        map_yaw_error = [abs(wrap_angle(opt[drive.ids[k]][2] - lap[k][2])) for k in (8, 11)]
        assert max(map_yaw_error) > math.radians(1.5)
        for n, (k, t) in enumerate(zip(new_ids, after[:10])):
            assert np.hypot(*(opt[k][:2] - t[:2])) < 0.05
            if n <= 4:  # between the two loops; past them the segment's own drift adds up again
                assert abs(wrap_angle(opt[k][2] - t[2])) < max(map_yaw_error) + math.radians(0.5)
        # The odometry alone (its frame is the truth's at the start) went on from where the
        # robot was lifted: more than a metre off.
        odo = store.keyframe(new_ids[0])
        assert np.hypot(odo.x_m - after[0][0], odo.y_m - after[0][1]) > 1.0


def _forward_loop(p: Pipeline, old_id: int, old_truth: np.ndarray, new_id: int, new_truth: np.ndarray,
                  rng: np.random.Generator, sigma_yaw_rad: float | None = None) -> None:
    """A verified forward loop (the camera at the robot's origin, the stage's default mount):
    the heading change and the bearing from the truth with noise, no range; ``sigma_yaw_rad``:
    on a ridge no heading settled (its half-width)."""
    rel = between(old_truth, new_truth)
    p.publish(ForwardLoop(old_id, new_id, 0.9, float(rel[2] + rng.normal(0.0, math.radians(0.5))),
                          float(math.atan2(rel[1], rel[0]) + rng.normal(0.0, math.radians(1.0))), 60,
                          sigma_yaw_rad=sigma_yaw_rad))


def test_a_kidnapping_relocalises_from_three_forward_loops_without_the_floor_camera(tmp_path: Path):
    from robotd.evaluation.observations import RunObservations
    from robotd.graph.gate import GROUP_MEMBER

    rng = np.random.default_rng(17)
    with MapStore.open(tmp_path / "map.sqlite") as store:
        run = store.begin_run("")
        p, graph = _pipeline(store, run)
        obs = p.add(RunObservations())  # what the demo's summary counts its accepted forward loops from
        drive = _Odometry(p, store, run)
        lap = _square_laps(2)
        for k in range(21):
            drive.keyframe(lap[k], k)
        p.publish(WheelDrop(int(20.4e9), True, left=True, right=True))
        p.publish(WheelDrop(int(24e9), False))
        drive.carried()
        after = _square_laps(1, start=7)
        new_ids = [drive.keyframe(t, 25 + k) for k, t in enumerate(after[:12])]
        # One forward loop places the robot on a ray only: it waits for a second one.
        _forward_loop(p, drive.ids[5], lap[5], new_ids[1], after[1], rng)
        c = p.counters()
        assert (c["relocalisations"], c["forward_loops_accepted"]) == (0, 0)
        assert graph.status_fragment() == "LOST (relocalising)"
        # After 0.75 m and a turn, a second one sees another keyframe across the first ray:
        # two bearings always cross, so two forward loops alone cannot check each other.
        _forward_loop(p, drive.ids[10], lap[10], new_ids[5], after[5], rng)
        assert p.counters()["relocalisations"] == 0
        # A third, further on, over-determines the position.
        _forward_loop(p, drive.ids[14], lap[14], new_ids[9], after[9], rng)
        c = p.counters()
        # The group enters the graph as one edge (its fit), none of the three as a loop of its own.
        assert (c["relocalisations"], c["localised"], c["forward_loops_accepted"], c["loops_accepted"]) == (1, 1, 0, 0)
        assert (c["reloc_group_edges"], c["forward_loops_grouped"], c["forward_loops_failed_gate"]) == (1, 3, 0)
        assert [(lk.from_id, lk.to_id) for lk in store.links("loop")] == [(drive.ids[5], new_ids[1])]
        members = {(drive.ids[5], new_ids[1]), (drive.ids[10], new_ids[5]), (drive.ids[14], new_ids[9])}
        assert set(obs.forward_fates) == members
        assert all(f == "grouped" for f in obs.forward_fates.values())
        assert all(obs.forward_fate_details[m].startswith(GROUP_MEMBER) for m in members)
        assert graph.status_fragment().startswith("relocalised against run 1 after ")
        assert graph.status_fragment().endswith(" (forward camera)")
        assert graph.relocalised_at[-1]["cameras"] == "forward"
        p.finish()
        # The map records the members so too.
        stored = {(r.candidate_id, r.query_id): r.fate for r in store.loop_candidates()}
        assert stored == dict.fromkeys(members, "grouped")
        assert sorted(r.query_id for r in store.loop_candidates("grouped")) == sorted(q for _o, q in members)
        opt = store.optimized_poses()
        err = [float(np.hypot(*(opt[k][:2] - t[:2]))) for k, t in zip(new_ids[:6], after[:6])]
        assert max(err) < 0.1, err
        # The odometry alone went on from where the robot was lifted: more than a metre off.
        odo = store.keyframe(new_ids[0])
        assert np.hypot(odo.x_m - after[0][0], odo.y_m - after[0][1]) > 1.0


def test_forward_loops_on_unsettled_ridges_relocalise_but_the_gate_takes_none_after(tmp_path: Path):
    """A loop on a heading-bearing ridge no heading settled (its heading as uncertain as the
    ridge is wide) is a relocalisation candidate like any other; once relocalised, the gate
    refuses such a loop (the stage settles the next view of the place at the heading the
    relocalising loops give) and takes a settled one."""
    rng = np.random.default_rng(17)
    with MapStore.open(tmp_path / "map.sqlite") as store:
        run = store.begin_run("")
        p, graph = _pipeline(store, run)
        drive = _Odometry(p, store, run)
        lap = _square_laps(2)
        for k in range(21):
            drive.keyframe(lap[k], k)
        p.publish(WheelDrop(int(20.4e9), True, left=True, right=True))
        p.publish(WheelDrop(int(24e9), False))
        drive.carried()
        after = _square_laps(1, start=7)
        new_ids = [drive.keyframe(t, 25 + k) for k, t in enumerate(after[:14])]
        ridge = math.radians(1.0)
        # The second query 0.25 m from the first: not independent of it, held beside the group.
        for old, new in ((5, 1), (6, 2), (10, 5), (14, 9)):
            _forward_loop(p, drive.ids[old], lap[old], new_ids[new], after[new], rng, sigma_yaw_rad=ridge)
        c = p.counters()
        # Relocalised by three (one edge, none of them accepted as a loop); the one held beside
        # them is refused, not gated into the graph.
        assert (c["relocalisations"], c["forward_loops_accepted"], c["forward_loops_failed_gate"]) == (1, 0, 1)
        assert graph.status_fragment().endswith(" (forward camera)")
        _forward_loop(p, drive.ids[15], lap[15], new_ids[10], after[10], rng, sigma_yaw_rad=ridge)
        c = p.counters()
        assert (c["forward_loops_accepted"], c["forward_loops_failed_gate"]) == (0, 2)
        _forward_loop(p, drive.ids[16], lap[16], new_ids[11], after[11], rng)
        assert p.counters()["forward_loops_accepted"] == 1
        p.finish()


def test_a_restart_relocalises_from_a_forward_and_a_floor_loop_that_agree(tmp_path: Path):
    rng = np.random.default_rng(19)
    with MapStore.open(tmp_path / "map.sqlite") as store:
        old_ids, old_truth = _first_run(store, rng)
        run = store.begin_run("")
        p, graph = _pipeline(store, run)
        drive = _Odometry(p, store, run)
        truth = _square_laps(1, start=7)
        for k in range(3):
            drive.keyframe(truth[k], 100 + k)
        _forward_loop(p, old_ids[5], old_truth[5], drive.ids[2], truth[2], rng)
        assert graph.status_fragment() == "not localised in the stored map"
        for k in range(3, 6):
            drive.keyframe(truth[k], 100 + k)
        _loop(p, old_ids[12], old_truth[12], drive.ids[5], truth[5], rng)  # 0.5 m further on: agrees
        c = p.counters()
        assert (c["localised"], c["relocalisations"], c["forward_loops_accepted"], c["loops_accepted"]) == (1, 1, 1, 1)
        assert graph.status_fragment().endswith(" (floor and forward cameras)")
        p.finish()
        assert _error_m(store, drive.ids[:6], drive.truth[:6]) < 0.05


def test_the_status_line_says_where_the_robot_stands_with_the_map(tmp_path: Path):
    from robotd.app.daemon import Daemon
    from robotd.app.notify import Notifier
    from robotd.base.clock import ManualClock

    rng = np.random.default_rng(14)
    with MapStore.open(tmp_path / "map.sqlite") as store:
        old_ids, old_truth = _first_run(store, rng)
        run = store.begin_run("")
        p, _graph = _pipeline(store, run)
        d = Daemon(ManualClock(0), p, {}, Notifier(), wall_clock=ManualClock(0), driver_stats=lambda: {})
        assert d.status_text(1.0).endswith("unsynced 0")  # nothing known yet
        drive = _Odometry(p, store, run)
        truth = _square_laps(1, start=7)
        for k in range(9):
            drive.keyframe(truth[k], 100 + k)
        assert d.status_text(1.0).endswith("unsynced 0, not localised in the stored map")
        _loop(p, old_ids[12], old_truth[12], drive.ids[5], truth[5], rng)
        _loop(p, old_ids[15], old_truth[15], drive.ids[8], truth[8], rng)
        assert d.status_text(1.0).endswith("unsynced 0, relocalised against run 1 after 8.0 s and 1.5 m (floor camera)")
        p.publish(WheelDrop(int(109e9), True, left=True, right=True))
        assert d.status_text(1.0).endswith("unsynced 0, LOST (lifted)")
