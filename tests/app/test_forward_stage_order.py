"""The forward stage decides the same whatever the order its inputs arrive in.

The daemon's sources are read by their own threads: how the forward camera's frames
interleave with the wheel odometry and the stored keyframes (and the links the pose graph
publishes with them) depends on the machine's load. The forward demo once gave other loops
under load for that reason: the stage ran a keyframe's image when its frame happened to
arrive, with the heading graph and the odometry as far as they had got by then, and the
loop reached the pose graph's gate at that moment. Here the same streams are delivered in
several orders, frames early, late and jittered, and what the detector is given and what
the stage publishes, and where in the keyframes' stream, must not change
(robotd.app.stages.forward_loops, module notes)."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from robotd.app.pipeline import Pipeline
from robotd.app.stages.forward_loops import ForwardLoopStage
from robotd.base.geometry import between
from robotd.base.messages import (CandidateFate, ForwardLoop, Frame, KeyframeStored, Link, OdometryUpdate,
                                  PoseStamped, StoredKeyframe)
from robotd.forward import LOOP, LOW_POSTERIOR
from robotd.forward.verify import ACCEPTED, Verification

V_MPS, W_RADPS = 0.3, 0.05
RUN_S = 24.0


def _pose(t_s: float) -> np.ndarray:
    return np.array([V_MPS * t_s, 0.02 * math.sin(t_s), W_RADPS * t_s])


class _Recorder:
    """Stands in for ForwardDetector: records what each image came with (its frame, the
    keyframe's pose, the frame's offset and the graph's heading to image 0 as the stage
    gives them) and calls every fourth image from the fourth a loop with image 0."""

    def __init__(self) -> None:
        self.stage: ForwardLoopStage | None = None
        self.inputs: list[tuple[Any, ...]] = []
        self.vocabulary: list[int] = []
        c, s = math.cos(0.1), math.sin(0.1)
        self.v = Verification(True, ACCEPTED, 80, 60, np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]),
                              np.array([0.2, 0.0, -1.0]) / math.hypot(0.2, 1.0))

    def forget_poses(self) -> None:
        self.inputs.append(("forget",))

    def __len__(self) -> int:
        return len(self.inputs)

    def process(self, image: np.ndarray, pose: np.ndarray | None = None, pose_cov: Any = None,
                defer_accept: bool = False) -> object:
        st = self.stage
        assert st is not None and st._current is not None
        k = len(self.inputs)
        prior = st._prior_yaw(0) if st._poses else None
        self.inputs.append((int(image[0, 0]), tuple(np.round(pose, 9)), tuple(np.round(st._current[0], 9)),
                            None if prior is None else tuple(np.round(prior, 9))))
        loop = k >= 4 and k % 4 == 0
        return SimpleNamespace(status=LOOP if loop else LOW_POSTERIOR, loop_id=0 if loop else None,
                               verification=self.v if loop else None, candidate_probability=0.9,
                               times_s={"total": 0.01})


def _streams() -> tuple[list[tuple[int, Any]], list[tuple[int, Any]], list[tuple[int, Any]]]:
    """``(odometry, keyframe stream, forward frames)``, each ``(stamp_ns, message)`` in order.
    The keyframe stream is what the pipeline makes of the floor camera: per keyframe its
    odometry link, the keyframe, and now and then a floor loop to an older one."""
    odo = []
    for t in np.arange(0.0, RUN_S, 0.02):
        p = _pose(float(t))
        ps = PoseStamped(int(round(t * 1e9)), *map(float, p))
        odo.append((ps.stamp_ns, OdometryUpdate(ps, ps)))
    kfs: list[tuple[int, Any]] = []
    info = np.diag([1e4, 1e4, 1e5])
    t_kf = np.arange(0.1, RUN_S - 1.0, 0.3)
    for k, t in enumerate(t_kf):
        stamp = int(round(t * 1e9))
        p = _pose(float(t))
        if k:
            delta = between(_pose(float(t_kf[k - 1])), p)
            kfs.append((stamp, Link("odometry", k - 1, k, delta, info)))
        kf = StoredKeyframe(Frame(stamp, "floor", np.zeros((2, 2), np.uint8)),
                            PoseStamped(stamp, *map(float, p), np.diag([1e-4, 1e-4, 1e-4 * (1 + k)])),
                            keyframe_id=k, run_id=1)
        kfs.append((stamp, KeyframeStored(kf)))
        if k >= 10 and k % 5 == 0:  # a floor loop, published after the keyframe, as the pose graph does
            j = k - 9
            kfs.append((stamp, Link("loop", j, k, between(_pose(float(t_kf[j])), p) + [0.0, 0.0, 0.003],
                                    np.diag([1e4, 1e4, 1e6]))))
    frames = [(int(round(t * 1e9)), Frame(int(round(t * 1e9)), "forward",
                                          np.full((2, 2), n % 256, np.uint8), n))
              for n, t in enumerate(np.arange(0.0, RUN_S, 1.0 / 15.0))]
    return odo, kfs, frames


def _deliver(rng: np.random.Generator | None, odo_lag: float, kf_lag: float, frame_lag: float) -> list[Any]:
    """The three streams merged by delivery time: each message ``lag`` s after its stamp
    (with ``rng``, a random lag up to that, never overtaking its own stream's previous one),
    a keyframe never before the odometry past its stamp (the keyframe stage waits for it)."""
    odo, kfs, frames = _streams()

    def times(stream: list[tuple[int, Any]], lag: float) -> list[float]:
        out, last = [], -1.0
        for stamp, _ in stream:
            d = stamp / 1e9 + (lag if rng is None else float(rng.uniform(0.0, lag)))
            last = max(last, d)
            out.append(last)
        return out

    t_odo, t_fr = times(odo, odo_lag), times(frames, frame_lag)
    t_kf = times(kfs, kf_lag)
    stamps = np.array([s for s, _ in odo])
    for i, (stamp, _) in enumerate(kfs):  # after the odometry sample past the keyframe's stamp
        j = min(int(np.searchsorted(stamps, stamp + 20_000_000)), len(stamps) - 1)
        t_kf[i] = max(t_kf[i], t_odo[j] + 1e-6, t_kf[i - 1] if i else 0.0)
    events = ([(t, 0, i, m) for i, ((_, m), t) in enumerate(zip(odo, t_odo))]
              + [(t, 1, i, m) for i, ((_, m), t) in enumerate(zip(kfs, t_kf))]
              + [(t, 2, i, m) for i, ((_, m), t) in enumerate(zip(frames, t_fr))])
    events.sort(key=lambda e: (e[0], e[1], e[2]))
    return [e[3] for e in events]


def _run(messages: list[Any]) -> tuple[list[Any], list[Any], ForwardLoopStage]:
    det = _Recorder()
    stage = ForwardLoopStage(det, distance_m=0.25, sync_tolerance_s=0.04, planar_refit=False)  # type: ignore[arg-type]
    det.stage = stage
    log: list[Any] = []
    p = Pipeline()
    p.add(stage)
    p.add(SimpleNamespace(name="sink", subscriptions=lambda: {
        KeyframeStored: lambda m: log.append(("keyframe", m.keyframe.keyframe_id)),
        ForwardLoop: lambda m: log.append(("loop", m.from_id, m.to_id, round(m.dyaw_rad, 9),
                                           round(m.bearing_rad, 9))),
        CandidateFate: lambda m: log.append(("fate", m.query_id, m.candidate_id))}))
    for m in messages:
        p.publish(m)
    p.finish()
    return det.inputs, log, stage


def test_the_same_streams_in_any_order_give_the_same_loops_at_the_same_place():
    ref_inputs, ref_log, ref = _run(_deliver(None, 0.0, 0.03, 0.0))  # frames ahead of the keyframes
    assert ref.images >= 20 and ref.loops >= 5 and ref.unsynced == 0
    # The graph's heading was asked with the floor loops in (the test can tell them apart).
    assert sum(1 for i in ref_inputs if i[-1] is not None) >= 20
    loops = [e for e in ref_log if e[0] == "loop"]
    assert len(loops) == ref.loops
    orders = {
        "frames late": _deliver(None, 0.0, 0.03, 0.6),
        "odometry far ahead, frames late": _deliver(None, 0.0, 0.5, 0.9),
        "jittered": _deliver(np.random.default_rng(1), 0.3, 0.4, 0.9),
        "jittered again": _deliver(np.random.default_rng(2), 0.05, 0.6, 0.95),
    }
    for name, msgs in orders.items():
        inputs, log, stage = _run(msgs)
        assert inputs == ref_inputs, name
        assert log == ref_log, name
        assert stage.late == 0 and stage.evicted == 0, name


def test_a_frame_later_than_the_delay_is_counted_and_its_loop_keeps_its_content():
    """Beyond the delay the order shows: the loop goes out late (counted), but what the
    detector was given and the loop itself are the same."""
    ref_inputs, ref_log, _ = _run(_deliver(None, 0.0, 0.03, 0.0))
    inputs, log, stage = _run(_deliver(None, 0.0, 0.03, 1.5))
    assert inputs == ref_inputs
    assert stage.late > 0
    assert [e for e in log if e[0] == "loop"] == [e for e in ref_log if e[0] == "loop"]
    assert log != ref_log  # published at other places in the keyframes' stream


@pytest.mark.parametrize("upto", [None, 3])
def test_the_heading_graph_answers_from_the_links_it_had(upto):
    """``HeadingGraph.relative(..., upto=n)`` uses the first ``n`` links only: a floor loop
    that came later does not move the answer."""
    from robotd.app.stages.forward_loops import HeadingGraph

    g = HeadingGraph()
    info = np.diag([1e4, 1e4, 1e4])  # 0.01 rad each
    for k in range(3):
        g.add_link(Link("odometry", k, k + 1, np.array([0.1, 0.0, 0.1]), info))
    g.add_link(Link("loop", 0, 3, np.array([0.3, 0.0, 0.0]), np.diag([1e4, 1e4, 1e8])))  # says 0, firmly
    yaw, sigma = g.relative(0, 3, upto=upto)
    if upto == 3:
        assert yaw == pytest.approx(0.3) and sigma == pytest.approx(math.sqrt(3) * 0.01)
    else:
        assert abs(yaw) < 1e-3 and sigma < 1e-3
