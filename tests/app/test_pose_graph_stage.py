"""The pose graph stage's full solve hands the memory it freed back to the system."""

from __future__ import annotations

from typing import Any

import numpy as np

from robotd.app.stages import pose_graph
from robotd.graph.incremental import IncrementalGraph


class _Store:
    def __init__(self) -> None:
        self.saved: list[tuple[list[int], Any]] = []

    def put_optimized_poses(self, ids: list[int], poses: Any) -> None:
        self.saved.append((ids, poses))

    def add_map_frame_run(self, run_id: int) -> None:
        pass


def test_a_full_solve_trims_the_heap_after_it(monkeypatch):
    calls: list[int] = []
    monkeypatch.setattr(pose_graph, "_MALLOC_TRIM", lambda pad: calls.append(pad) or 1)
    graph = IncrementalGraph()
    stage = pose_graph.PoseGraphStage(graph, _Store())  # type: ignore[arg-type]
    graph.add_first(0)
    graph.add_keyframe(1, 0, (1.0, 0.0, 0.0), np.eye(3) * 100)
    assert calls == []
    stage.solve_and_save()
    assert calls == [0] and stage.solves == 1
    monkeypatch.setattr(pose_graph, "_MALLOC_TRIM", None)  # not glibc: nothing to call
    stage.solve_and_save()
    assert stage.solves == 2
