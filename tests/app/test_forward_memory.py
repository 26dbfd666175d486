"""The forward memory in the map: each forward image is written as it is
processed; a new stage on the same map takes the earlier run's memory up and closes a loop
against it."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from robotd.app.stages.forward_loops import ForwardLoopStage
from robotd.app.pipeline import Pipeline
from robotd.base.messages import ForwardLoop, Frame, KeyframeStored, PoseStamped, StoredKeyframe
from robotd.forward import ForwardDetector, method_params
from robotd.forward.detector import _held_bytes
from robotd.forward.features import FeatureExtractor, compact
from robotd.forward.verify import ACCEPTED, Verification
from robotd.io.store import MapStore


def _places(n: int) -> list[np.ndarray]:
    """``n`` distinct textured 320x240 views (ORB finds a few hundred corners in each)."""
    rng = np.random.default_rng(5)
    out = []
    for _ in range(n):
        img = cv2.resize(rng.integers(0, 256, (30, 40), dtype=np.uint8), (320, 240), interpolation=cv2.INTER_NEAREST)
        out.append(cv2.GaussianBlur(img, (0, 0), 1.0))
    return out


def _run(store: MapStore, run: int, views: list[np.ndarray], t0_ms: int, monkeypatch,
         resident: int = 1024) -> tuple[ForwardLoopStage, list]:
    import robotd.forward.detector as det_mod

    # Decisions only: the geometry of these flat views is not what this test is about.
    monkeypatch.setattr(det_mod, "verify_pair", lambda old, new, p, k: Verification(
        True, ACCEPTED, 100, 100, np.eye(3), np.array([0.0, 0.0, -1.0])))
    params = replace(method_params("default"), recent_excluded=2, decision="score", consistency=1,
                     score_threshold=20.0)  # an identical view stands far out; different ones reach 3
    stage = ForwardLoopStage(ForwardDetector(params, resident=resident), distance_m=0.5, store=store)
    got: list = []
    p = Pipeline()
    p.add(stage)
    p.add(type("Sink", (), {"name": "sink", "subscriptions": lambda self: {ForwardLoop: got.append}})())
    for k, img in enumerate(views):
        t_ms = t0_ms + 1000 * k
        kid = store.add_keyframe(run, t_ms * 10**6, (float(k), 0.0, 0.0), np.eye(3) * 1e-4, None)
        p.publish(Frame(t_ms * 10**6, "forward", img))
        kf = StoredKeyframe(Frame(t_ms * 10**6, "floor", np.zeros((4, 4), np.uint8)),
                            PoseStamped(t_ms * 10**6, float(k), 0.0, 0.0), keyframe_id=kid, run_id=run)
        p.publish(KeyframeStored(kf))
    p.finish()  # the end of the input: the loops held for the delay go out
    return stage, got


def test_a_restarted_stage_closes_a_loop_against_the_earlier_run(tmp_path: Path, monkeypatch):
    places = _places(6)
    path = tmp_path / "map.sqlite"
    with MapStore.open(path) as store:
        run1 = store.begin_run("a = 1\n", started_ns=0)
        first, got1 = _run(store, run1, places, 0, monkeypatch)
        assert first.images == 6 and first.store_errors == 0 and got1 == []
        stored_words = len(first.detector.vocabulary)
        kf_first = first._keyframe_ids[3]
    with MapStore.open(path) as store:  # a new daemon on the same map
        images, words = store.forward_memory()
        assert len(images) == 6 and len(words) == stored_words
        run2 = store.begin_run("a = 1\n", started_ns=0)
        # Place 3 (place 0 would tie with the virtual image, its words being the oldest).
        second, got2 = _run(store, run2, [places[3]], 100_000, monkeypatch)
        assert second.restored == 6 and len(second.detector) == 7
        assert [(m.from_id, m.to_id) for m in got2] == [(kf_first, second._keyframe_ids[6])]
        assert len(store.forward_memory()[0]) == 7  # this run's image is stored too
        # A stage without the map starts empty and finds nothing.
    with MapStore.open(tmp_path / "other.sqlite") as other:
        run = other.begin_run("a = 1\n", started_ns=0)
        fresh, got3 = _run(other, run, [places[3]], 0, monkeypatch)
        assert fresh.restored == 0 and got3 == []



def _resident(stage: ForwardLoopStage) -> list[int]:
    """The images whose features the stage's detector holds in memory (not read back)."""
    return [t for t, f in enumerate(stage.detector._features) if f is not None]


def _extracted(stage: ForwardLoopStage, img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An image's features as the detector keeps them: keypoints in 1/16 px, descriptors."""
    f = compact(FeatureExtractor(stage.detector.params.features)(img), np.zeros(0))
    return f.keypoints_q, f.descriptors


def test_past_images_features_stay_in_the_map_and_come_back_identical(tmp_path: Path, monkeypatch):
    places = _places(6)
    with MapStore.open(tmp_path / "map.sqlite") as store:
        run = store.begin_run("a = 1\n", started_ns=0)
        stage, _ = _run(store, run, places, 0, monkeypatch, resident=2)
        det = stage.detector
        assert det.loader is not None and _resident(stage) == [4, 5]
        # the two resident images (5 keeps its descriptors whole, 4 lends those that made
        # words to the word search) and the per-image bookkeeping, nothing of 0-3
        held = sum(_held_bytes(det._features[t]) for t in (4, 5))
        assert held < det.features_of(4).nbytes + det.features_of(5).nbytes
        assert det.memory_bytes()["images"] == held + det._bookkeeping_bytes()
        for t in (0, 3):  # read back from the map: what the detector had
            kq, desc = _extracted(stage, places[t])
            back = det.features_of(t)
            np.testing.assert_array_equal(back.keypoints_q, kq)
            np.testing.assert_array_equal(back.descriptors, desc)
            assert back.image_size_px == (320, 240)
        assert det.read_back == 2 and stage.read_errors == 0
        # A revisit of place 1 (out of memory) is verified against its features from the map.
        seen: list = []
        import robotd.forward.detector as det_mod
        monkeypatch.setattr(det_mod, "verify_pair", lambda old, new, p, k: (seen.append(old), Verification(
            True, ACCEPTED, 100, 100, np.eye(3), np.array([0.0, 0.0, -1.0])))[1])
        assert det.process(places[1]).loop_id == 1
        np.testing.assert_array_equal(seen[0].descriptors, _extracted(stage, places[1])[1])
        assert det.read_back == 3


def test_a_restarted_stage_reads_only_the_newest_images_features(tmp_path: Path, monkeypatch):
    places = _places(6)
    path = tmp_path / "map.sqlite"
    with MapStore.open(path) as store:
        run1 = store.begin_run("a = 1\n", started_ns=0)
        first, _ = _run(store, run1, places, 0, monkeypatch)
        kf_first = first._keyframe_ids[1]
        full_images, full_words = store.forward_memory()
        images, words = store.forward_memory(features_from=4)
        assert words == full_words  # the founders' descriptors, read image by image
        assert [len(i[5]) for i in images[:4]] == [0] * 4 and [i[6] for i in images[:4]] == [b""] * 4
        for a, b in zip(images, full_images):
            assert a[:4] == b[:4]
            np.testing.assert_array_equal(a[4], b[4])  # every image's words
        for a, b in zip(images[4:], full_images[4:]):
            np.testing.assert_array_equal(a[5], b[5])
            assert a[6] == b[6]
    with MapStore.open(path) as store:
        run2 = store.begin_run("a = 1\n", started_ns=0)
        second, got = _run(store, run2, [places[1]], 100_000, monkeypatch, resident=2)
        assert second.restored == 6
        assert _resident(second) == [5, 6]  # the newest stored image and this run's
        assert [(m.from_id, m.to_id) for m in got] == [(kf_first, second._keyframe_ids[6])]
        assert second.detector.read_back == 1 and second.read_errors == 0


def test_a_damaged_stored_image_is_counted_and_not_verified(tmp_path: Path, monkeypatch, caplog):
    places = _places(6)
    with MapStore.open(tmp_path / "map.sqlite") as store:
        run = store.begin_run("a = 1\n", started_ns=0)
        stage, _ = _run(store, run, places, 0, monkeypatch, resident=2)
        store._conn.execute("UPDATE forward_images SET descriptors = X'0102' WHERE image_id = 1")
        store._conn.commit()
        d = stage.detector.process(places[1])
    assert d.loop_id is None and d.verification is not None and not d.verification.accepted
    assert stage.read_errors == 1 and stage.detector.read_back_failed == 1
    assert "forward image 1: its stored features could not be read back" in caplog.text
