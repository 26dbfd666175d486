"""Python's garbage collections are timed and counted (robotd.app.gcwatch), and the forward
stage takes those run in its thread during a forward keyframe as its ``gc`` part."""

from __future__ import annotations

import gc
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from robotd.app import gcwatch
from robotd.app.gcwatch import GcWatch
from tests.app.test_forward_stage_order import _deliver, _Recorder, _run


def _garbage(n: int) -> None:
    for _ in range(n):  # cycles: only the collector frees them
        a: list[Any] = []
        a.append(a)


def test_it_times_each_collection_by_generation_and_thread_and_uninstalls():
    w = GcWatch().install()
    try:
        assert gcwatch.installed() is w
        before = list(w.collections)
        _garbage(2000)
        gc.collect(2)
        gc.collect(1)
        assert w.collections[2] == before[2] + 1 and w.collections[1] >= before[1] + 1
        assert w.ms_total[2] > 0.0 and w.ms_max[2] <= w.ms_total[2]
        assert any(e[2] == 2 and e[1] == threading.current_thread().name for e in w.events)
        assert 0.0 < w.cpu_ms_total[2] <= w.thread_cpu_ms() + 1e-9
        other: list[float] = []
        t = threading.Thread(target=lambda: other.append(w.thread_cpu_ms()))
        t.start()
        t.join()
        assert other == [0.0]  # that thread ran none
        c = w.counters()
        assert c["gc_collections_gen2"] == w.collections[2] and c["gc_frozen_objects"] == gc.get_freeze_count()
    finally:
        w.uninstall()
    assert gcwatch.installed() is None and w._callback not in gc.callbacks
    n = w.collections[2]
    gc.collect(2)
    assert w.collections[2] == n


def test_deferred_full_collections_run_only_in_poll_after_ten_of_generation_1_and_finish_restores():
    before = gc.get_threshold()
    w = GcWatch().install()
    try:
        w.defer_full()
        assert gc.get_threshold()[:2] == before[:2] and gc.get_threshold()[2] > 1_000_000
        gc.collect(2)  # the count of generation-1 collections since the last full one starts at 0
        full = w.collections[2]
        for _ in range(gcwatch.FULL_AFTER - 1):
            gc.collect(1)
            assert w.poll() == 0
        assert w.collections[2] == full and w.deferred_full == 0  # nine: not yet due
        # the automatic rule would have run one by now; allocations alone run none
        _garbage(20 * before[0] * before[1])
        assert w.collections[2] == full
        gc.collect(1)
        assert gc.get_count()[2] >= gcwatch.FULL_AFTER
        assert w.poll() == 0 and w.collections[2] == full + 1 and w.deferred_full == 1
        assert gc.get_count()[2] == 0 and w.poll() == 0 and w.deferred_full == 1
        assert w.counters()["gc_deferred_full"] == 1
        w.finish()
        assert gc.get_threshold() == before
        w.finish()  # twice: nothing more to restore
        assert gc.get_threshold() == before
    finally:
        w.uninstall()
        gc.set_threshold(*before)


def test_without_deferral_poll_runs_nothing():
    w = GcWatch()
    for _ in range(gcwatch.FULL_AFTER + 1):
        gc.collect(1)
    assert w.poll() == 0 and w.deferred_full == 0 and w.collections == [0, 0, 0]


class _Collecting(_Recorder):
    """The stage-order test's stand-in detector, collecting the youngest generation on every third image."""

    def process(self, image: np.ndarray, pose: np.ndarray | None = None, pose_cov: Any = None,
                defer_accept: bool = False) -> object:
        if len(self.inputs) % 3 == 0:
            _garbage(200)
            gc.collect(0)
        return super().process(image, pose, pose_cov)


def test_the_forward_stage_counts_the_collections_in_its_keyframes(monkeypatch):
    import tests.app.test_forward_stage_order as order

    monkeypatch.setattr(order, "_Recorder", _Collecting)
    msgs = _deliver(None, 0.0, 0.03, 0.0)
    _, _, without = _run(msgs)
    assert without.part_cpu_ms["gc"] == [0.0] * without.images  # no watch installed: nothing counted
    w = GcWatch().install()
    try:
        _, _, stage = _run(msgs)
    finally:
        w.uninstall()
    got = np.array(stage.part_cpu_ms["gc"])
    assert len(got) == stage.images >= 20
    assert (got[0::3] > 0.0).all()
    assert stage.counters()["forward_gc_cpu_ms_total"] >= float(got[0::3].sum()) - 0.1


@pytest.mark.parametrize("freeze", [True, False])
def test_the_daemon_freezes_its_start_up_and_defers_full_collections_for_the_run_and_undoes_both_at_the_end(tmp_path: Path, freeze: bool):
    thresholds = gc.get_threshold()
    from robotd.app.assemble import assemble_daemon
    from robotd.app.notify import Notifier
    from robotd.base.clock import ManualClock
    from robotd.base.configfile import load_config
    from robotd.io.calibfile import CalibrationFile, LoopThresholds, write_calibration
    from robotd.io.store import MapStore

    write_calibration(tmp_path / "calibration.yml",
                      CalibrationFile(loop=LoopThresholds(thresholds=(None, None, None, 40.0, None, None))))
    path = tmp_path / "robotd.toml"
    path.write_text(f'[base]\nport = "/dev/kobuki"\n[calibration]\npath = "{tmp_path / "calibration.yml"}"\n'
                    f'[map]\npath = "{tmp_path / "map.sqlite"}"\n[daemon]\ngc_freeze = {str(freeze).lower()}\n'
                    f'gc_full_between_messages = {str(freeze).lower()}\n')
    cfg = load_config(path)
    assert gc.get_freeze_count() == 0
    store = MapStore.open(cfg.map.path)
    try:
        daemon = assemble_daemon(cfg, ManualClock(0), {}, store, Notifier(), lossless=True)
        frozen = gc.get_freeze_count()
        c = daemon.pipeline.counters()
        assert (frozen > 1000) == freeze and c["gc_frozen_at_start"] >= frozen  # (a few freed since)
        assert gcwatch.installed() is not None and "gc_collections_gen2" in c
        assert (gc.get_threshold()[2] > thresholds[2]) == freeze  # the full collections deferred with it
        daemon.start()
        daemon.shutdown()
        assert gc.get_freeze_count() == 0 and gc.get_threshold() == thresholds
    finally:
        store.close()
        gc.unfreeze()
        gc.set_threshold(*thresholds)
        w = gcwatch.installed()
        if w is not None:
            w.uninstall()
