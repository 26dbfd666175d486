"""The forward stage's budget: one verification's work per forward keyframe.

A forward keyframe whose image verified a view leaves that view's level test (the planar
scan, the ridge's fits, the heading graph's solve: the stage's ``accept`` hook) to the next
forward keyframe that verifies nothing; the queue of waiting tests is bounded (a full queue
runs the new image's test in its own keyframe, counted) and emptied at the end of the input.
The loop is the waiting image's (its keyframe, its context for the hook), published with
the keyframe that ran its test (robotd.app.stages.forward_loops, module notes)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

import tests.app.test_forward_stage_order as order
from robotd.app.pipeline import Pipeline
from robotd.app.stages.forward_loops import ForwardLoopStage
from robotd.base.errors import ConfigError
from robotd.base.messages import ForwardLoop, KeyframeStored
from robotd.forward import LOOP, LOW_POSTERIOR, NO_GEOMETRIC_CONSISTENCY
from robotd.forward.detector import ACCEPT_PENDING, VERIFY_PENDING
from robotd.forward.verify import NO_GEOMETRIC_CONSISTENCY as NOT_CONSISTENT, Verification


class _Deferring(order._Recorder):
    """A stand-in detector: the images in ``verifying`` verify a view of image 0 (left to
    :meth:`resume` when the stage defers, tested at once otherwise), the others nothing.
    It records which forward keyframe ran each image's test, and the context the stage gave
    its hook then."""

    def __init__(self, verifying: set[int]) -> None:
        super().__init__()
        self.verifying = verifying
        self.tested: list[tuple[int, int, int | None, int]] = []  # (image, keyframe running it, stage's image, its kf)
        self.inline: list[int] = []

    def process(self, image: np.ndarray, pose: np.ndarray | None = None, pose_cov: Any = None,
                defer_accept: bool = False) -> object:
        k = len(self.inputs)
        self.inputs.append(k)
        out = dict(loop_id=None, verification=None, candidate_probability=0.9, times_s={"total": 0.01}, pending=None)
        if k not in self.verifying:
            return SimpleNamespace(status=LOW_POSTERIOR, **out)
        if defer_accept:
            return SimpleNamespace(**{**out, "status": ACCEPT_PENDING, "verification": self.v,
                                      "pending": SimpleNamespace(image_id=k, view=0, checks=0, order=[0])})
        self.inline.append(k)
        self._test(k)
        return SimpleNamespace(**{**out, "status": LOOP, "loop_id": 0, "verification": self.v})

    def _test(self, k: int) -> None:
        st = self.stage
        assert st is not None and st._current is not None
        self.tested.append((k, len(self.inputs) - 1, st._image, st._current[4]))
        assert self.accept(0, self.v)  # the stage's hook (set on the detector by the stage), a level motion

    def resume(self, job: Any, max_checks: int | None = None, defer_accept: bool = False) -> tuple[Any, int, Any]:
        self._test(job.image_id)
        return LOOP, 0, self.v


class _FromTheMap(_Deferring):
    """Image 0 stands for an image taken up from the map (the stage's chain -1, as a
    restarted daemon's are): every view of it lies in another odometry chain."""

    def process(self, image: np.ndarray, pose: np.ndarray | None = None, pose_cov: Any = None,
                defer_accept: bool = False) -> object:
        if len(self.inputs) == 1:
            assert self.stage is not None
            self.stage._chains[0] = -1
        return super().process(image, pose, pose_cov, defer_accept)


def _run(verifying: set[int], kind: type[_Deferring] = _Deferring,
         **kw: Any) -> tuple[_Deferring, ForwardLoopStage, list[Any]]:
    det = kind(verifying)
    stage, log = _drive(det, **kw)
    return det, stage, log


def _drive(det: Any, **kw: Any) -> tuple[ForwardLoopStage, list[Any]]:
    """The office sequence through a stage over ``det``: the stage and what it published."""
    stage = ForwardLoopStage(det, distance_m=0.25, sync_tolerance_s=0.04, planar_refit=False, **kw)
    det.stage = stage
    log: list[Any] = []
    p = Pipeline()
    p.add(stage)
    p.add(SimpleNamespace(name="sink", subscriptions=lambda: {
        KeyframeStored: lambda m: log.append(("keyframe", m.keyframe.keyframe_id)),
        ForwardLoop: lambda m: log.append(("loop", m.from_id, m.to_id))}))
    for m in order._deliver(None, 0.0, 0.03, 0.0):
        p.publish(m)
    p.finish()
    return stage, log


def test_a_verifying_keyframe_leaves_its_level_test_to_the_next_keyframe_that_verifies_nothing():
    last = len(_run(set())[0].inputs) - 1
    det, stage, log = _run({4, 5, 6, 8, last})
    kf = stage._keyframe_ids
    # image: the forward keyframe that ran its test. 7, 9, 10 verify nothing: one test each, oldest first;
    # the last image's waits for the end of the input.
    ran = {k: at for k, at, _, _ in det.tested}
    assert ran == {4: 7, 5: 9, 6: 10, 8: 11, last: last}
    # The hook saw the waiting image's context, not the newest image's.
    assert all(img == k and kf_id == kf[k] for k, _, img, kf_id in det.tested)
    # At most one test per keyframe, never in one that verified its own view.
    at = [a for k, a, _, _ in det.tested if k != last]
    assert len(at) == len(set(at)) and not set(at) & {4, 5, 6, 8}
    assert det.inline == []
    c = stage.counters()
    assert (c["forward_deferred"], c["forward_deferred_inline"], c["forward_deferred_at_end"]) == (5, 0, 1)
    assert c["forward_deferred_wait_max"] == 4 and c["forward_deferred_waiting"] == 0  # image 6, run at 10
    # Each loop is its own image's keyframe's, published after the keyframe that ran its test.
    loops = [e for e in log if e[0] == "loop"]
    assert [e[2] for e in loops] == [kf[k] for k in (4, 5, 6, 8, last)]
    for k in (4, 5, 6, 8):
        assert log.index(("loop", kf[0], kf[k])) > log.index(("keyframe", kf[ran[k]]))
    assert len(stage.cpu_ms) == stage.images and all(len(v) == stage.images for v in stage.part_cpu_ms.values())


def test_a_full_queue_runs_the_new_images_test_in_its_own_keyframe_and_counts_it():
    det, stage, log = _run({4, 5, 6, 7, 9}, max_deferred=2)
    ran = {k: at for k, at, _, _ in det.tested}
    # 4 and 5 wait; 6 and 7 find the queue full and are tested at once; 8 runs 4's, 9 waits, 10 runs 5's.
    assert det.inline == [6, 7]
    assert ran == {4: 8, 5: 10, 6: 6, 7: 7, 9: 11}
    c = stage.counters()
    assert (c["forward_deferred"], c["forward_deferred_inline"], c["forward_deferred_at_end"]) == (3, 2, 0)
    assert stage.tests == 5
    assert len([e for e in log if e[0] == "loop"]) == 5


def test_without_deferral_every_test_runs_in_its_own_keyframe():
    det, stage, _ = _run({4, 5, 8}, defer_accept=False)
    assert det.inline == [4, 5, 8] and [(k, at) for k, at, _, _ in det.tested] == [(4, 4), (5, 5), (8, 8)]
    assert stage.counters()["forward_deferred"] == 0 and stage.counters()["forward_deferred_inline"] == 0


def test_the_queue_bound_must_be_positive():
    with pytest.raises(ConfigError, match="max_deferred"):
        ForwardLoopStage(order._Recorder(), max_deferred=0)  # type: ignore[arg-type]


def test_the_config_sets_the_queue_of_waiting_tests_or_turns_the_deferral_off():
    """``[forward_detector] max_deferred_tests`` reaches the stage: 0 runs every image's
    verification in its own keyframe, N > 0 lets N wait; ``checks_per_keyframe`` is the
    stage's budget of checks (0: none, the queue of level tests alone)."""
    from robotd.app.assemble import build_forward_stage
    from robotd.base.config import Config, replace

    def shape(cfg: Config) -> tuple[bool, int, int | None]:
        st = build_forward_stage(cfg)
        return st.defer_accept, st.max_deferred, st.check_budget

    on = replace(Config(), "forward_detector", enabled=True)
    assert shape(on) == (True, 4, None)
    assert shape(replace(on, "forward_detector", max_deferred_tests=7)) == (True, 7, None)
    budget = replace(on, "forward_detector", checks_per_keyframe=1, max_deferred_tests=16)
    assert shape(budget) == (True, 16, 1)
    assert shape(replace(budget, "forward_detector", checks_per_keyframe=3)) == (True, 16, 3)
    off = replace(budget, "forward_detector", max_deferred_tests=0)
    assert shape(off)[0] is False and shape(off)[2] is None


def test_a_view_in_another_odometry_chain_is_tested_at_once():
    """A loop to an image of another chain (the map's, or before a kidnapping) may relocalise
    the robot: it never waits, and still counts its CPU on its own keyframe."""
    det, stage, log = _run({4, 5, 8}, kind=_FromTheMap)
    assert [(k, at) for k, at, _, _ in det.tested] == [(4, 4), (5, 5), (8, 8)]
    assert det.inline == []  # each was stopped for the deferral, then resumed in its own keyframe
    c = stage.counters()
    assert (c["forward_deferred_across"], c["forward_deferred"], c["forward_deferred_at_end"]) == (3, 0, 0)
    assert len([e for e in log if e[0] == "loop"]) == 3
    assert len(stage.cpu_ms) == stage.images and all(len(v) == stage.images for v in stage.part_cpu_ms.values())


_FAILED = Verification(False, NOT_CONSISTENT, 40, 0)


class _Planned(order._Recorder):
    """A stand-in detector whose images verify by plan: ``plan[image]`` lists its views in
    the order the detector tries them, each ``(past image, its check passes, its level test
    passes)``. It follows the detector's rules for ``defer_accept`` and ``max_checks`` (stop at
    a view whose check passes, or after the budget, and go on in :meth:`resume`), and records
    each check and test with the forward keyframe that ran it and the context the stage gave."""

    def __init__(self, plan: dict[int, list[tuple[int, bool, bool]]]) -> None:
        super().__init__()
        self.plan = plan
        self.work: list[tuple[str, int, int, int | None, int]] = []  # (kind, image, keyframe running, stage's image, its kf)

    def process(self, image: np.ndarray, pose: np.ndarray | None = None, pose_cov: Any = None,
                defer_accept: bool = False, max_checks: int | None = None) -> object:
        k = len(self.inputs)
        self.inputs.append(k)
        out = dict(loop_id=None, verification=None, candidate_probability=0.9, times_s={"total": 0.01},
                   pending=None, checks=0)
        if k not in self.plan:
            return SimpleNamespace(status=LOW_POSTERIOR, **out)
        job = SimpleNamespace(image_id=k, order=[j for j, _, _ in self.plan[k]], next=0, view=None, checks=0)
        return self._answer(job, self._advance(job, defer_accept, max_checks), out)

    def _answer(self, job: Any, res: Any, out: dict[str, Any]) -> object:
        out["checks"] = job.checks
        if res is job:
            status = ACCEPT_PENDING if job.view is not None else VERIFY_PENDING
            return SimpleNamespace(**{**out, "status": status, "pending": job,
                                      "verification": self.v if job.view is not None else None})
        status, j = res
        return SimpleNamespace(**{**out, "status": status, "loop_id": j if status == LOOP else None,
                                  "verification": self.v if status == LOOP else _FAILED})

    def _advance(self, job: Any, defer: bool, max_checks: int | None) -> Any:
        res: Any = None
        if job.view is not None:  # the awaiting view's test (not one of max_checks)
            j, ok = self._test(job, job.view)
            job.view = None
            res = (LOOP, j) if ok else None
        checks = 0
        while res is None and job.next < len(job.order):
            if max_checks is not None and checks >= max_checks:
                return job
            i = job.next
            job.next += 1
            job.checks += 1
            checks += 1
            self._log("check", job)
            if self.plan[job.image_id][i][1]:
                if defer:
                    job.view = i
                    return job
                j, ok = self._test(job, i)
                res = (LOOP, j) if ok else None
        return res if res is not None else (NO_GEOMETRIC_CONSISTENCY, job.order[0])

    def _log(self, kind: str, job: Any) -> None:
        st = self.stage
        assert st is not None and st._current is not None
        self.work.append((kind, job.image_id, len(self.inputs) - 1, st._image, st._current[4]))

    def _test(self, job: Any, i: int) -> tuple[int, bool]:
        self._log("test", job)
        j, _, passes = self.plan[job.image_id][i]
        assert self.accept(j, self.v)  # the stage's hook (a level motion) with the image's context
        return j, passes

    def resume(self, job: Any, max_checks: int | None = None, defer_accept: bool = False) -> Any:
        res = self._advance(job, defer_accept, max_checks)
        if res is job:
            return job
        status, j = res
        return status, j, self.v if status == LOOP else _FAILED


def _run_planned(plan: dict[int, list[tuple[int, bool, bool]]], kind: type[_Planned] = _Planned,
                 **kw: Any) -> tuple[_Planned, ForwardLoopStage, list[Any]]:
    det = kind(plan)
    stage, log = _drive(det, **kw)
    return det, stage, log


#: Images' views (past image, check passes, level test passes), in the detector's order: a
#: run of verifying keyframes with several checks each, refused tests, a view that fails all.
PLAN = {4: [(0, False, False), (1, True, True)],
        5: [(0, True, False), (1, True, True), (2, True, True)],
        6: [(1, True, True)],
        7: [(0, False, False), (1, False, False), (2, False, False)],
        8: [(2, True, False), (1, False, False)],
        9: [(0, True, True)],
        12: [(3, False, False), (2, True, True)]}


def test_a_check_budget_spreads_each_images_verification_over_keyframes_with_the_loops_of_the_verification_at_once():
    at_once, st_once, log_once = _run_planned(PLAN, defer_accept=False)
    det, stage, log = _run_planned(PLAN, check_budget=1, max_deferred=8)
    last = len(det.inputs) - 1
    # The same checks and tests of each image, in its order, and the same loops.
    def by_image(work: list[Any]) -> dict[int, list[str]]:
        out: dict[int, list[str]] = {}
        for kind, img, _, _, _ in work:
            out.setdefault(img, []).append(kind)
        return out
    assert by_image(det.work) == by_image(at_once.work)
    assert sorted(e for e in log if e[0] == "loop") == sorted(e for e in log_once if e[0] == "loop")
    assert len([e for e in log if e[0] == "loop"]) == 5  # 4, 5, 6, 9, 12 (7 and 8 fail)
    # At once the images ran up to four checks and tests in their keyframe; split, at most one
    # per keyframe (the budget), the end of the input apart.
    per_kf = np.bincount([at for _, _, at, _, _ in det.work if at != last], minlength=last)
    assert per_kf.max() == 1 and np.bincount([at for _, _, at, _, _ in at_once.work]).max() == 4
    c = stage.counters()
    assert c["forward_checks_max"] == 1 and c["forward_checks_over_budget"] == 0
    assert c["forward_deferred_forced"] == 0 and c["forward_deferred_waiting"] == 0
    # The oldest first: the images' work runs in image order; each with its own image's context.
    imgs = [img for _, img, _, _, _ in det.work]
    assert imgs == sorted(imgs)
    kf = stage._keyframe_ids
    assert all(img == i and kf_id == kf[i] for _, i, _, img, kf_id in det.work)
    # A loop is its own image's, published after the keyframe that ran its last test.
    done = {i: at for _, i, at, _, _ in det.work}
    loops = [e for e in log if e[0] == "loop"]
    assert sorted(kf.index(e[2]) for e in loops) == [4, 5, 6, 9, 12]
    for e in loops:
        at = done[kf.index(e[2])]
        assert at == last or log.index(e) > log.index(("keyframe", kf[at]))
    assert c["forward_deferred"] == 7 and c["forward_deferred_wait_max"] > 5


def test_a_verification_queue_over_its_bound_finishes_the_oldest_over_the_budget_and_counts_it():
    plan = {k: [(0, True, True)] for k in (4, 5, 6)}
    det, stage, log = _run_planned(plan, check_budget=1, max_deferred=1)
    ran = [(kind, img, at) for kind, img, at, _, _ in det.work]
    # 4's check in its keyframe, its test in 5's; 6 finds 4 done and 5 checked: 5's test
    # is forced in 6's keyframe (the queue of one would hold two), 6's check and test follow.
    assert ran == [("check", 4, 4), ("test", 4, 5), ("check", 5, 6), ("test", 5, 6), ("check", 6, 7), ("test", 6, 8)]
    c = stage.counters()
    assert (c["forward_deferred_forced"], c["forward_checks_over_budget"], c["forward_checks_max"]) == (1, 1, 2)
    assert len([e for e in log if e[0] == "loop"]) == 3


def test_a_check_budget_never_delays_a_view_of_another_odometry_chain():
    class _MapPlanned(_Planned):
        def process(self, image: np.ndarray, pose: np.ndarray | None = None, pose_cov: Any = None,
                    defer_accept: bool = False, max_checks: int | None = None) -> object:
            if len(self.inputs) == 1:
                assert self.stage is not None
                self.stage._chains[0] = -1  # image 0 as taken up from the map
            return super().process(image, pose, pose_cov, defer_accept, max_checks)

    plan = {4: [(1, True, True)], 5: [(1, False, False), (0, True, True)], 6: [(1, True, True)]}
    det, stage, _ = _run_planned(plan, _MapPlanned, check_budget=1)
    ran = [(kind, img, at) for kind, img, at, _, _ in det.work]
    # 5 may see image 0 (another chain): its whole verification in its own keyframe, over the
    # budget, while 4's test waits a keyframe more.
    assert ran == [("check", 4, 4), ("check", 5, 5), ("check", 5, 5), ("test", 5, 5), ("test", 4, 6),
                   ("check", 6, 7), ("test", 6, 8)]
    c = stage.counters()
    assert c["forward_deferred_across"] == 1 and c["forward_checks_over_budget"] == 1


def test_the_check_budget_must_hold_a_level_test():
    with pytest.raises(ConfigError, match="check_budget"):
        ForwardLoopStage(order._Recorder(), check_budget=0)  # type: ignore[arg-type]
