"""The data flow between the stages: typed, checked at assembly, and drawn in the docs from
the registrations."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robotd.app.assemble import build_pipeline, data_flow_diagram
from robotd.app.pipeline import Pipeline
from robotd.app.stages.keyframes import KeyframeStage
from robotd.app.stages.map_writer import MapWriterStage
from robotd.app.stages.visual_odometry import VisualOdometryStage
from robotd.base.clock import ManualClock
from robotd.base.config import Config, replace
from robotd.base.messages import (
    DescribedKeyframe,
    Frame,
    Keyframe,
    KeyframeStored,
    MeasuredKeyframe,
    PoseStamped,
)
from robotd.io.store import MapStore

REPO = Path(__file__).resolve().parents[2]


def test_the_docs_show_the_data_flow_of_the_registered_stages():
    import sys

    sys.path.insert(0, str(REPO / "tools"))
    try:
        import dataflow_doc
    finally:
        sys.path.pop(0)
    page = (REPO / "docs" / "concepts.md").read_text()
    diagram = data_flow_diagram()
    assert dataflow_doc.render(page, diagram) == page, "run tools/dataflow_doc.py"
    # What the diagram must say, whatever its layout: the keyframe's way through the stages.
    for edge in ("keyframes -->|Keyframe| floor", "floor -->|DescribedKeyframe| visual_odometry",
                 "visual_odometry -->|MeasuredKeyframe| map", "odometry -.->|KeyframeOdometry| keyframes"):
        assert edge in diagram


class _NoVo:
    params = None


def test_a_stage_reading_what_no_stage_produces_is_refused(tmp_path: Path):
    with MapStore.open(tmp_path / "map.sqlite") as store:
        run = store.begin_run("")
        p = Pipeline()
        p.add(KeyframeStage(None, ManualClock(), distance_m=0.1, rotation_rad=0.1, max_sync_wait_s=0.5,
                            lossless=True))
        p.add(MapWriterStage(store, run, image_width_px=0, takes=MeasuredKeyframe))  # no VO stage
        assert p.missing_inputs() == {"map": [MeasuredKeyframe]}
        with pytest.raises(ValueError, match="stage 'map' reads MeasuredKeyframe, which nothing produces"):
            p.check()
        # Visual odometry taking described keyframes with no floor detector to describe them.
        p.add(VisualOdometryStage(_NoVo(), "fused", takes=DescribedKeyframe))  # type: ignore[arg-type]
        assert p.missing_inputs() == {"visual_odometry": [DescribedKeyframe]}
        with pytest.raises(ValueError, match="reads stage 'graph', which is not registered"):
            Pipeline().add(MapWriterStage(store, run, image_width_px=0), reads={"graph": "KeyframeChain"})


@pytest.mark.parametrize("floor, vo, takes", [(True, True, MeasuredKeyframe), (True, False, DescribedKeyframe),
                                              (False, True, MeasuredKeyframe), (False, False, Keyframe)])
def test_the_map_writer_takes_the_last_keyframe_type_of_the_assembled_stages(tmp_path: Path, floor: bool,
                                                                              vo: bool, takes: type):
    cfg = replace(Config(), "base", driver="kobuki")
    cfg = replace(cfg, "calibration", path=str(tmp_path / "none.yml"))
    cfg = replace(cfg, "visual_odometry", enabled=vo)
    with MapStore.open(tmp_path / "map.sqlite") as store:
        p = build_pipeline(cfg, ManualClock(), store, store.begin_run(""), lossless=True, floor_detector=floor)
        assert p.stage("map").takes is takes
        assert p.missing_inputs() == {}


def test_a_stored_keyframe_is_a_new_message_and_its_inputs_stay_as_they_were(tmp_path: Path):
    """The map writer publishes a StoredKeyframe with the map's id; the keyframe it was
    given is frozen and unchanged (no stage fills in another's message)."""
    got: list = []
    with MapStore.open(tmp_path / "map.sqlite") as store:
        run = store.begin_run("")
        p = Pipeline()
        p.add(MapWriterStage(store, run, image_width_px=0, takes=Keyframe))
        p.add(type("Sink", (), {"name": "sink", "subscriptions": lambda self: {KeyframeStored: got.append}})())
        kf = Keyframe(Frame(5, "floor", np.zeros((4, 4), np.uint8)), PoseStamped(5, 1.0, 2.0, 0.5, np.eye(3)))
        p.publish(kf)
        [stored] = [m.keyframe for m in got]
        assert stored is not kf and stored.keyframe_id == next(iter(store.keyframes())).id and stored.run_id == run
        assert stored.frame is kf.frame and stored.descriptor is None and stored.visual_pose is None
        with pytest.raises(AttributeError):
            kf.odometry_edge = None  # type: ignore[misc]


def test_the_pose_graph_registered_after_the_floor_stage_is_refused(tmp_path: Path):
    """Both subscribe to KeyframeStored: the graph must hold the keyframe before the floor
    stage publishes its loop candidates, the one order the types do not give."""
    from robotd.app.stages.floor import FloorDetectorStage
    from robotd.app.stages.pose_graph import PoseGraphStage
    from robotd.floor.detector import FloorDetectorParams, FloorLoopDetector
    from robotd.graph.incremental import IncrementalGraph

    with MapStore.open(tmp_path / "map.sqlite") as store:
        p = Pipeline()
        p.add(FloorDetectorStage(FloorLoopDetector.from_store(store, FloorDetectorParams(descriptor_mode=2))))
        p.add(PoseGraphStage(IncrementalGraph(), store))
        assert p.misordered() == [("graph", "floor")]
        with pytest.raises(ValueError, match="stage 'graph' must be registered before 'floor'"):
            p.check()
