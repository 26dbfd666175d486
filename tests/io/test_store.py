"""Tests of robotd.io.store: round trips through the file, refusal of bad files without
touching them, migrations, and survival of a SIGKILL in the middle of writing."""

from __future__ import annotations

import hashlib
import os
import signal
import sqlite3
import struct
import subprocess
import sys
import textwrap
import threading
import time
from dataclasses import FrozenInstanceError
from pathlib import Path

import numpy as np
import pytest

from robotd.io import mapconnection
from robotd.io import store as store_module
from robotd.base.errors import MapStoreError
from robotd.io.store import (
    LOOP_CANDIDATE_FATES,
    SCHEMA_VERSION,
    KeyframeRecord,
    LoopCandidateRecord,
    MapStore,
)


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _cov(seed: int) -> np.ndarray:
    """A non-symmetric 3x3 matrix with distinct entries: catches transposes and reorderings."""
    return np.arange(9, dtype=np.float64).reshape(3, 3) * 0.125 + seed + 1e-9 * seed


def _make_map(path: Path, n_keyframes: int = 3) -> list[int]:
    rng = np.random.default_rng(1)
    with MapStore.open(path, image_codec="png") as store:
        run = store.begin_run("[robot]\nname = 'x'\n", started_ns=1_000)
        ids = [
            store.add_keyframe(
                run,
                stamp_ns=2_000 + i,
                pose_xyyaw=(float(i), -float(i), 0.1 * i),
                covariance=_cov(i),
                image=rng.integers(0, 256, size=(24, 32), dtype=np.uint8),
            )
            for i in range(n_keyframes)
        ]
        store.end_run(run, ended_ns=3_000)
    return ids


def test_round_trip_of_every_field_through_the_file(tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    rng = np.random.default_rng(7)
    image = rng.integers(0, 256, size=(48, 64), dtype=np.uint8)
    descriptor = bytes(rng.integers(0, 256, size=300, dtype=np.uint8))
    with MapStore.open(path, image_codec="png") as store:
        run = store.begin_run("a = 1\n", started_ns=123, notes="bench run", robotd_version="9.9")
        kf1 = store.add_keyframe(run, 1_000_000_001, (1.5, -2.25, 3.0), _cov(1), image,
                                 descriptor, 3)
        kf2 = store.add_keyframe(run, 1_000_000_002, (0.0, 0.5, -1.0), _cov(2), None)
        store.set_descriptor(kf2, b"\x00\x01\xff", 6)
        odo = store.add_link("odometry", kf1, kf2, (0.25, -0.5, 0.125), _cov(3))
        loop = store.add_link("loop", kf2, kf1, (-0.25, 0.5, -0.125), _cov(4))
        store.put_calibration("floor_camera", "fx = 1\n", created_ns=10)
        store.put_calibration("floor_camera", "fx = 2\n", created_ns=20)
        store.set_meta("map_name", "kitchen")
        store.end_run(run, ended_ns=456)

    with MapStore.open(path, create=False) as store:
        assert store.schema_version == SCHEMA_VERSION
        (r,) = store.runs()
        assert (r.id, r.started_ns, r.ended_ns, r.config, r.robotd_version, r.notes) == (
            run, 123, 456, "a = 1\n", "9.9", "bench run")
        a, b = store.keyframes()
        assert (a.id, a.run_id, a.stamp_ns, a.x_m, a.y_m, a.yaw_rad) == (
            kf1, run, 1_000_000_001, 1.5, -2.25, 3.0)
        np.testing.assert_array_equal(a.covariance, _cov(1))
        assert (a.image_width, a.image_height) == (64, 48)
        assert (a.descriptor, a.descriptor_mode) == (descriptor, 3)
        np.testing.assert_array_equal(store.keyframe_image(kf1), image)
        assert (b.id, b.x_m, b.y_m, b.yaw_rad) == (kf2, 0.0, 0.5, -1.0)
        assert (b.image_width, b.image_height) == (None, None)
        assert store.keyframe_image(kf2) is None
        assert (b.descriptor, b.descriptor_mode) == (b"\x00\x01\xff", 6)
        assert store.keyframe(kf2).descriptor == b"\x00\x01\xff"
        l1, l2 = store.links()
        assert (l1.id, l1.kind, l1.from_id, l1.to_id, l1.dx_m, l1.dy_m, l1.dyaw_rad) == (
            odo, "odometry", kf1, kf2, 0.25, -0.5, 0.125)
        np.testing.assert_array_equal(l1.information, _cov(3))
        assert (l2.id, l2.kind, l2.from_id, l2.to_id) == (loop, "loop", kf2, kf1)
        np.testing.assert_array_equal(l2.information, _cov(4))
        assert [link.id for link in store.links("loop")] == [loop]
        assert store.get_calibration("floor_camera") == "fx = 2\n"
        assert store.get_calibration("forward_camera") is None
        assert store.get_meta("map_name") == "kitchen"
        assert store.count_keyframes() == 2
        assert not a.covariance.flags.writeable

    # The documented on-disk format: 9 little-endian float64, row-major.
    with sqlite3.connect(path) as raw:
        blob = raw.execute("SELECT covariance FROM keyframes WHERE id = ?", (kf1,)).fetchone()[0]
    assert struct.unpack("<9d", blob) == tuple(_cov(1).ravel())


def test_jpeg_images_are_jpeg_and_close_to_the_original(tmp_path: Path) -> None:
    yy, xx = np.mgrid[0:60, 0:80]
    image = (xx * 2 + yy).astype(np.uint8)  # smooth: JPEG's error stays small
    with MapStore.open(tmp_path / "map.sqlite", jpeg_quality=95) as store:
        run = store.begin_run("", 0)
        kf = store.add_keyframe(run, 0, (0, 0, 0), np.eye(3), image)
        decoded = store.keyframe_image(kf)
    with sqlite3.connect(tmp_path / "map.sqlite") as raw:
        blob = raw.execute("SELECT image FROM keyframes").fetchone()[0]
    assert blob[:2] == b"\xff\xd8"  # JPEG start-of-image marker
    assert decoded.shape == (60, 80) and decoded.dtype == np.uint8
    assert np.abs(decoded.astype(int) - image.astype(int)).mean() < 2.0


def test_file_is_in_wal_mode(tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    _make_map(path)
    with sqlite3.connect(path) as raw:
        assert raw.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_reopen_continues_the_same_map(tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    first_ids = _make_map(path, n_keyframes=3)
    assert first_ids == [1, 2, 3]
    with MapStore.open(path) as store:
        run2 = store.begin_run("second", started_ns=5_000)
        new_id = store.add_keyframe(run2, 6_000, (9, 9, 0), np.eye(3), None)
        assert new_id == 4
        assert store.count_keyframes() == 4
        assert store.count_keyframes(run2) == 1
        assert [r.id for r in store.runs()] == [1, run2]
        assert [k.id for k in store.keyframes(run_id=1)] == [1, 2, 3]
        assert [k.x_m for k in store.keyframes()] == [0.0, 1.0, 2.0, 9.0]


def test_keyframe_descriptor_reads_the_descriptor_columns_alone(tmp_path: Path) -> None:
    """The floor index's read back: the stored bytes and mode, as the full record has them."""
    path = tmp_path / "map.sqlite"
    ids = _make_map(path)
    with MapStore.open(path) as store:
        store.set_descriptor(ids[1], b"\x00\x01\xff", 6)
    with MapStore.open(path, read_only=True) as store:
        assert store.keyframe_descriptor(ids[1]) == (b"\x00\x01\xff", 6)
        rec = store.keyframe(ids[1])
        assert (rec.descriptor, rec.descriptor_mode) == store.keyframe_descriptor(ids[1])
        assert store.keyframe_descriptor(ids[0]) == (None, None)
        with pytest.raises(KeyError, match="no keyframe 999"):
            store.keyframe_descriptor(999)


def test_keyframe_iteration_crosses_page_boundaries(tmp_path: Path) -> None:
    n = 2 * store_module._PAGE_ROWS + 3
    with MapStore.open(tmp_path / "map.sqlite") as store:
        runs = [store.begin_run("a", 0), store.begin_run("b", 1)]
        for i in range(n):
            store.add_keyframe(runs[i % 2], i, (i, 0, 0), np.eye(3), None)
        assert [k.stamp_ns for k in store.keyframes()] == list(range(n))
        assert [k.stamp_ns for k in store.keyframes(runs[1])] == list(range(1, n, 2))


@pytest.mark.parametrize(
    "damage",
    [
        pytest.param(lambda data: os.urandom(len(data)), id="random-bytes"),
        pytest.param(lambda data: b"hello" * 3, id="tiny-text-file"),
    ],
)
def test_a_file_that_is_not_sqlite_is_refused_and_untouched(tmp_path: Path, damage) -> None:
    path = tmp_path / "map.sqlite"
    path.write_bytes(damage(b"x" * 8192))
    before, listing = _digest(path), sorted(os.listdir(tmp_path))
    with pytest.raises(MapStoreError, match="is not an SQLite database") as info:
        MapStore.open(path)
    assert str(path) in str(info.value)
    assert _digest(path) == before
    assert sorted(os.listdir(tmp_path)) == listing


def _truncate(data: bytes) -> bytes:
    return data[: len(data) // 2]


def _smash_a_page(data: bytes) -> bytes:
    page = 4096
    assert len(data) >= 6 * page
    damaged = bytearray(data)
    damaged[4 * page : 5 * page] = np.random.default_rng(3).bytes(page)
    return bytes(damaged)


@pytest.mark.parametrize("damage", [_truncate, _smash_a_page])
def test_a_damaged_map_is_refused_and_untouched(tmp_path: Path, damage) -> None:
    path = tmp_path / "map.sqlite"
    _make_map(path, n_keyframes=20)  # several pages of PNG noise
    path.write_bytes(damage(path.read_bytes()))
    before, listing = _digest(path), sorted(os.listdir(tmp_path))
    with pytest.raises(MapStoreError, match="damaged") as info:
        MapStore.open(path)
    assert str(path) in str(info.value)
    assert _digest(path) == before
    assert sorted(os.listdir(tmp_path)) == listing


def test_a_newer_schema_is_refused_and_untouched(tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    _make_map(path)
    with sqlite3.connect(path) as raw:
        raw.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'",
                    (str(SCHEMA_VERSION + 1),))
    raw.close()
    before = _digest(path)
    with pytest.raises(MapStoreError, match=f"schema version {SCHEMA_VERSION + 1}, newer"):
        MapStore.open(path)
    assert _digest(path) == before


def test_another_sqlite_database_is_refused_and_untouched(tmp_path: Path) -> None:
    path = tmp_path / "other.db"
    with sqlite3.connect(path) as raw:
        raw.execute("CREATE TABLE photos (id INTEGER)")
    raw.close()
    before = _digest(path)
    with pytest.raises(MapStoreError, match="not a robotd map"):
        MapStore.open(path)
    assert _digest(path) == before


def test_missing_file_without_create(tmp_path: Path) -> None:
    path = tmp_path / "nope.sqlite"
    with pytest.raises(MapStoreError, match="does not exist"):
        MapStore.open(path, create=False)
    assert not path.exists()
    with pytest.raises(MapStoreError, match="directory .* does not exist"):
        MapStore.open(tmp_path / "no_dir" / "map.sqlite")


def _add_cameras_column(conn: sqlite3.Connection) -> None:
    conn.execute("ALTER TABLE keyframes ADD COLUMN camera TEXT NOT NULL DEFAULT 'floor'")


def _broken_migration(conn: sqlite3.Connection) -> None:
    conn.execute("ALTER TABLE keyframes ADD COLUMN camera TEXT")
    raise RuntimeError("simulated failure half-way through a migration")


def _columns(path: Path) -> list[str]:
    with sqlite3.connect(path) as raw:
        cols = [row[1] for row in raw.execute("PRAGMA table_info(keyframes)")]
    raw.close()
    return cols


def test_an_older_schema_is_migrated_keeping_the_data(tmp_path, monkeypatch) -> None:
    path = tmp_path / "map.sqlite"
    _make_map(path, n_keyframes=2)
    monkeypatch.setattr(
        mapconnection, "MIGRATIONS", {**mapconnection.MIGRATIONS, SCHEMA_VERSION + 1: _add_cameras_column}
    )
    with MapStore.open(path) as store:
        assert store.schema_version == SCHEMA_VERSION + 1
        assert [k.x_m for k in store.keyframes()] == [0.0, 1.0]
    assert "camera" in _columns(path)


def test_a_failing_migration_leaves_the_old_version(tmp_path, monkeypatch) -> None:
    path = tmp_path / "map.sqlite"
    _make_map(path, n_keyframes=2)
    monkeypatch.setattr(
        mapconnection, "MIGRATIONS", {**mapconnection.MIGRATIONS, SCHEMA_VERSION + 1: _broken_migration}
    )
    with pytest.raises(RuntimeError, match="simulated failure"):
        MapStore.open(path)
    monkeypatch.undo()
    assert "camera" not in _columns(path)
    with MapStore.open(path) as store:
        assert store.schema_version == SCHEMA_VERSION
        assert store.count_keyframes() == 2


def test_bad_arguments_are_rejected(tmp_path: Path) -> None:
    with MapStore.open(tmp_path / "map.sqlite") as store:
        run = store.begin_run("", 0)
        kf = store.add_keyframe(run, 0, (0, 0, 0), np.eye(3), None)
        with pytest.raises(ValueError, match="FOREIGN KEY"):
            store.add_keyframe(run + 1, 0, (0, 0, 0), np.eye(3), None)
        with pytest.raises(ValueError, match="FOREIGN KEY"):
            store.add_link("loop", kf, kf + 1, (0, 0, 0), np.eye(3))
        with pytest.raises(ValueError, match="link kind"):
            store.add_link("gps", kf, kf, (0, 0, 0), np.eye(3))
        with pytest.raises(ValueError, match=r"shape \(3, 3\)"):
            store.add_keyframe(run, 0, (0, 0, 0), np.eye(2), None)
        with pytest.raises(ValueError, match="finite"):
            store.add_keyframe(run, 0, (0, float("nan"), 0), np.eye(3), None)
        with pytest.raises(ValueError, match="together"):
            store.add_keyframe(run, 0, (0, 0, 0), np.eye(3), None, descriptor=b"x")
        with pytest.raises(ValueError, match="grey"):
            store.add_keyframe(run, 0, (0, 0, 0), np.eye(3), np.zeros((4, 4, 3), np.uint8))
        with pytest.raises(KeyError):
            store.end_run(run + 5, 1)
        with pytest.raises(KeyError):
            store.set_descriptor(kf + 5, b"x", 1)
        with pytest.raises(KeyError):
            store.keyframe_image(kf + 5)
        with pytest.raises(ValueError, match="reserved|managed"):
            store.set_meta("schema_version", "7")
        # None of the refused writes left a row behind.
        assert store.count_keyframes() == 1
        assert store.links() == []


def test_close_twice_and_use_after_close(tmp_path: Path) -> None:
    store = MapStore.open(tmp_path / "map.sqlite")
    store.close()
    store.close()
    assert store.closed
    with pytest.raises(MapStoreError, match="closed"):
        store.count_keyframes()


def test_the_store_refuses_use_from_another_thread(tmp_path: Path) -> None:
    errors: list[BaseException] = []
    with MapStore.open(tmp_path / "map.sqlite") as store:
        def use() -> None:
            try:
                store.count_keyframes()
            except BaseException as exc:  # noqa: BLE001 - recorded for the assertion
                errors.append(exc)

        thread = threading.Thread(target=use)
        thread.start()
        thread.join()
    assert len(errors) == 1
    assert isinstance(errors[0], sqlite3.ProgrammingError)
    assert "thread" in str(errors[0])


_WRITER = textwrap.dedent(
    """
    import sys
    import numpy as np
    from robotd.io.store import MapStore

    store = MapStore.open(sys.argv[1])
    run = store.begin_run("crash test", 0)
    image = np.random.default_rng(0).integers(0, 256, size=(120, 160), dtype=np.uint8)
    for i in range(1_000_000):
        kf = store.add_keyframe(run, i, (float(i), 0.0, 0.0), np.eye(3), image)
        print(kf, flush=True)  # reported only after add_keyframe's COMMIT returned
    """
)


def test_sigkill_while_writing_loses_nothing_reported_committed(tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    with (tmp_path / "stderr.txt").open("w") as stderr:
        proc = subprocess.Popen(
            [sys.executable, "-c", _WRITER, str(path)],
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
        )
        guard = threading.Timer(60.0, proc.kill)  # only if the child hangs; not a sleep
        guard.start()
        try:
            reported: list[int] = []
            assert proc.stdout is not None
            for line in proc.stdout:
                reported.append(int(line))
                if len(reported) == 300:  # past the first WAL checkpoint (~4 MB)
                    os.kill(proc.pid, signal.SIGKILL)
                    break
            # Ids the child printed between our read and the kill were committed too.
            reported += [int(line) for line in proc.stdout.read().split()]
            proc.wait()
        finally:
            guard.cancel()
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL, (tmp_path / "stderr.txt").read_text()
    assert reported == list(range(1, len(reported) + 1))

    with MapStore.open(path, create=False) as store:  # runs quick_check
        stored = list(store.keyframes())
        ids = [k.id for k in stored]
        assert set(reported) <= set(ids)
        # At most one keyframe committed whose id the child had not printed yet.
        assert ids == list(range(1, len(ids) + 1))
        assert len(ids) - len(reported) in (0, 1)
        assert all(isinstance(k, KeyframeRecord) and k.x_m == k.id - 1 for k in stored)
        image = store.keyframe_image(reported[-1])
        assert image is not None and image.shape == (120, 160)
    with sqlite3.connect(path) as raw:
        assert raw.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
    raw.close()


def test_times_not_given_come_from_the_injected_clock(tmp_path: Path) -> None:
    from robotd.base.clock import ManualClock

    path = tmp_path / "map.sqlite"
    clock = ManualClock(5 * 10**9)
    with MapStore.open(path, clock=clock) as store:
        run = store.begin_run("cfg")
        clock.advance_ns(7)
        store.put_calibration("floor_camera", "fx = 1\n")
        clock.advance_ns(3)
        store.end_run(run)
        (record,) = store.runs()
    assert (record.started_ns, record.ended_ns) == (5 * 10**9, 5 * 10**9 + 10)
    with sqlite3.connect(path) as raw:
        assert raw.execute("SELECT created_ns FROM calibration").fetchone() == (5 * 10**9 + 7,)
    raw.close()


V1_MAP = Path(__file__).parent / "data" / "map_v1.sqlite"
"""A version-1 map written by the store as it was before version 2 (commit ecb9c76):
two runs of three keyframes (mode-1 descriptors, 160 px images), a loop link, one
calibration document."""


def test_a_version_1_map_written_by_the_old_code_is_migrated(tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    path.write_bytes(V1_MAP.read_bytes())
    with sqlite3.connect(path) as raw:
        before_kf = raw.execute("SELECT * FROM keyframes ORDER BY id").fetchall()
        before_links = raw.execute("SELECT * FROM links").fetchall()
        assert raw.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone() == ("1",)
    raw.close()
    with MapStore.open(path) as store:
        assert store.schema_version == SCHEMA_VERSION == 6
        assert store.forward_memory() == ([], [])
        assert store.optimized_poses() == {}
        assert store.loop_candidates() == []
        runs = store.runs()
        assert [r.id for r in runs] == [1, 2]
        assert all(r.epoch_unix_ns is None for r in runs)  # unknown for old runs
        assert [r.ended_ns for r in runs] == [4_000_000_000] * 2
        kfs = list(store.keyframes())
        assert [k.run_id for k in kfs] == [1, 1, 1, 2, 2, 2]
        assert [k.x_m for k in kfs] == pytest.approx([0.0, 0.05, 0.1] * 2)
        assert all(k.descriptor_mode == 1 and len(k.descriptor) <= 512 for k in kfs)
        assert store.keyframe_image(kfs[4].id).shape == (120, 160)
        assert store.get_calibration("loop_thresholds") == "mode1 = 20.0\n"
        new_run = store.begin_run("", 0)
        assert store.runs()[-1].epoch_unix_ns is not None
        assert new_run == 3
    with sqlite3.connect(path) as raw:
        # Every old row is still there, unchanged.
        assert raw.execute("SELECT * FROM keyframes ORDER BY id").fetchall() == before_kf
        assert raw.execute("SELECT * FROM links").fetchall() == before_links
        indexes = {r[0] for r in raw.execute("SELECT name FROM sqlite_master WHERE type='index'")}
        assert "keyframes_by_run_stamp" in indexes
        assert "loop_candidates_by_query" in indexes
        tables = {r[0] for r in raw.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        assert {"optimized_poses", "loop_candidates"} <= tables
        assert raw.execute("SELECT count(*) FROM optimized_poses").fetchone() == (0,)
        assert raw.execute("SELECT count(*) FROM loop_candidates").fetchone() == (0,)
    raw.close()


def _all_rows(path: Path) -> dict[str, list[tuple]]:
    """Every row of every table of the file (sqlite_sequence included), by table name."""
    with sqlite3.connect(path) as raw:
        names = [r[0] for r in raw.execute("SELECT name FROM sqlite_master WHERE type='table'")]
        rows = {n: raw.execute(f'SELECT * FROM "{n}" ORDER BY 1').fetchall() for n in names}
    raw.close()
    return rows


def test_a_version_2_map_written_by_the_current_code_is_migrated(tmp_path, monkeypatch) -> None:
    path = tmp_path / "map.sqlite"
    migrations = mapconnection.MIGRATIONS
    monkeypatch.setattr(mapconnection, "MIGRATIONS", {1: migrations[1], 2: migrations[2]})
    with MapStore.open(path, image_codec="png") as store:
        assert store.schema_version == 2
        run = store.begin_run("a = 1\n", started_ns=10, notes="v2", epoch_unix_ns=1_700_000_000)
        image = np.random.default_rng(2).integers(0, 256, size=(24, 32), dtype=np.uint8)
        kfs = [store.add_keyframe(run, 100 + i, (i, 2 * i, 0.1), _cov(i), image, b"d", 2)
               for i in range(3)]
        store.add_link("odometry", kfs[0], kfs[1], (1, 2, 0), _cov(5))
        store.add_link("loop", kfs[2], kfs[0], (-2, -4, 0), _cov(6))
        store.put_calibration("floor_camera", "fx = 1\n", created_ns=5)
        store.set_meta("map_name", "hall")
        store.end_run(run, ended_ns=200)
    before = _all_rows(path)
    assert "optimized_poses" not in before and "loop_candidates" not in before
    monkeypatch.undo()

    with MapStore.open(path) as store:
        assert store.schema_version == SCHEMA_VERSION == 6
        assert store.forward_memory() == ([], [])
        assert store.optimized_poses() == {} and store.loop_candidates() == []
        np.testing.assert_array_equal(store.keyframe_image(kfs[1]), image)
        (r,) = store.runs()
        assert (r.epoch_unix_ns, r.ended_ns, r.notes) == (1_700_000_000, 200, "v2")
    after = _all_rows(path)
    assert after.pop("optimized_poses") == [] and after.pop("loop_candidates") == []
    assert after.pop("forward_images") == [] and after.pop("forward_words") == []
    # Every old row is still there, unchanged; only the schema version moved on.
    meta_before, meta_after = before.pop("meta"), after.pop("meta")
    assert after == before
    assert dict(meta_after) == {**dict(meta_before), "schema_version": "6"}

    with MapStore.open(path) as store:  # and the new tables take rows
        store.put_optimized_poses(kfs, np.zeros((3, 3)), solved_unix_ns=1)
        store.add_loop_candidates([(kfs[2], kfs[0], 0.5, "accepted", "")])
        assert len(store.optimized_poses()) == 3 and len(store.loop_candidates()) == 1


def test_optimized_poses_round_trip_and_the_newest_solution_replaces_the_old(
    tmp_path: Path,
) -> None:
    path = tmp_path / "map.sqlite"
    a, b, c = _make_map(path, n_keyframes=3)
    with MapStore.open(path) as store:
        assert store.optimized_poses() == {} and store.optimized_pose(a) is None
        store.put_optimized_poses([a, b], np.array([[1.0, 2.0, 0.5], [-1.5, 0.25, -3.0]]),
                                  solved_unix_ns=1_000)
        store.put_optimized_poses((b, c), [[7.0, 8.0, 0.125], [0.0, -0.5, 3.0]],
                                  solved_unix_ns=2_000)
        t0 = time.time_ns()
        store.put_optimized_poses([], np.empty((0, 3)))  # nothing to write: no error
    with MapStore.open(path, create=False) as store:
        poses = store.optimized_poses()
        assert sorted(poses) == [a, b, c]
        np.testing.assert_array_equal(poses[a], [1.0, 2.0, 0.5])
        np.testing.assert_array_equal(poses[b], [7.0, 8.0, 0.125])  # replaced
        np.testing.assert_array_equal(poses[c], [0.0, -0.5, 3.0])
        assert poses[a].shape == (3,) and poses[a].dtype == np.float64
        np.testing.assert_array_equal(store.optimized_pose(b), [7.0, 8.0, 0.125])
        assert store.optimized_pose(c + 1) is None
        store.put_optimized_poses([a], np.array([[0.0, 0.0, 0.0]]))  # default: wall clock now
        t1 = time.time_ns()
    with sqlite3.connect(path) as raw:
        stamps = dict(raw.execute("SELECT keyframe_id, solved_unix_ns FROM optimized_poses"))
        assert raw.execute("SELECT count(*) FROM optimized_poses").fetchone() == (3,)
    raw.close()
    assert stamps[b] == stamps[c] == 2_000
    assert t0 <= stamps[a] <= t1


def test_loop_candidates_round_trip_with_every_fate(tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    a, b, c = _make_map(path, n_keyframes=3)
    rows = [(c, a, 0.25 * i, fate, f"chi2={i}.5") for i, fate in enumerate(LOOP_CANDIDATE_FATES)]
    with MapStore.open(path) as store:
        store.add_loop_candidates(rows)
        store.add_loop_candidates([(b, a, 3.0, "accepted", "")])
        store.add_loop_candidates([])
    with MapStore.open(path, create=False) as store:
        records = store.loop_candidates()
        assert all(isinstance(r, LoopCandidateRecord) for r in records)
        assert [(r.query_id, r.candidate_id, r.score, r.fate, r.detail) for r in records] == [
            *rows, (b, a, 3.0, "accepted", "")]
        assert [r.id for r in records] == list(range(1, len(rows) + 2))
        assert [r.query_id for r in store.loop_candidates("accepted")] == [c, b]
        assert [r.detail for r in store.loop_candidates("failed_gate")] == ["chi2=2.5"]
        assert [r.detail for r in store.loop_candidates("grouped")] == ["chi2=5.5"]
        with pytest.raises(FrozenInstanceError):
            records[0].fate = "accepted"  # type: ignore[misc]
        with pytest.raises(ValueError, match="accepted"):
            store.loop_candidates("rejected")
    assert set(LOOP_CANDIDATE_FATES) == {
        "accepted", "below_threshold", "failed_gate", "no_transform", "down_weighted", "grouped"}
    assert {"LOOP_CANDIDATE_FATES", "LoopCandidateRecord"} <= set(store_module.__all__)
    # The table itself refuses any other fate (its CHECK and the constant agree).
    with sqlite3.connect(path) as raw, pytest.raises(sqlite3.IntegrityError, match="CHECK"):
        raw.execute("INSERT INTO loop_candidates(query_id, candidate_id, score, fate)"
                    " VALUES (?, ?, 0.0, 'maybe')", (a, b))
    raw.close()


def test_bad_pose_graph_writes_are_refused_and_write_nothing(tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    a, b = _make_map(path, n_keyframes=2)
    good = np.array([[1.0, 2.0, 0.5], [3.0, 4.0, -0.5]])
    with MapStore.open(path) as store:
        with pytest.raises(KeyError, match=f"no keyframe {b + 7}"):
            store.put_optimized_poses([a, b, b + 7], np.vstack([good, good[:1]]))
        with pytest.raises(ValueError, match=r"shape \(2, 3\)"):
            store.put_optimized_poses([a, b], good[:1])
        with pytest.raises(ValueError, match=r"shape \(2, 3\)"):
            store.put_optimized_poses([a, b], good[:, :2])
        with pytest.raises(ValueError, match="finite"):
            store.put_optimized_poses([a, b], np.array([[1.0, 2.0, 0.5], [np.inf, 0, 0]]))
        with pytest.raises(ValueError, match="distinct"):
            store.put_optimized_poses([a, a], good)
        assert store.optimized_poses() == {}

        with pytest.raises(ValueError, match="accepted.*below_threshold.*down_weighted"):
            store.add_loop_candidates([(b, a, 1.0, "accepted", ""), (b, a, 1.0, "maybe", "")])
        with pytest.raises(ValueError, match="finite"):
            store.add_loop_candidates([(b, a, float("nan"), "accepted", "")])
        with pytest.raises(ValueError, match="FOREIGN KEY"):
            store.add_loop_candidates([(b, a, 1.0, "accepted", ""), (b, b + 9, 1.0, "accepted", "")])
        with pytest.raises(ValueError):
            store.add_loop_candidates([(b, a, 1.0, "accepted")])  # type: ignore[list-item]
        assert store.loop_candidates() == []
    with sqlite3.connect(path) as raw:
        assert raw.execute("SELECT count(*) FROM optimized_poses").fetchone() == (0,)
        assert raw.execute("SELECT count(*) FROM loop_candidates").fetchone() == (0,)
    raw.close()


def test_a_file_claiming_a_version_without_its_tables_is_refused_and_untouched(tmp_path: Path) -> None:
    """A crafted file holding only meta(schema_version=1) used to be switched to WAL mode
    (its header rewritten) before the migration to version 2 failed on it."""
    path = tmp_path / "map.sqlite"
    with sqlite3.connect(path) as raw:
        raw.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL) WITHOUT ROWID")
        raw.execute("INSERT INTO meta VALUES ('schema_version', '1')")
    raw.close()
    before = _digest(path)
    with pytest.raises(MapStoreError, match=r"claims schema version 1 but lacks calibration, "
                                            r"keyframes, links, runs: not a robotd map"):
        MapStore.open(path)
    assert _digest(path) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.sqlite"]


def test_a_map_missing_a_column_of_its_version_is_refused_and_untouched(tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    _make_map(path)
    with sqlite3.connect(path) as raw:
        raw.execute("PRAGMA journal_mode=DELETE")
        raw.execute("ALTER TABLE loop_candidates DROP COLUMN detail")
    raw.close()
    before = _digest(path)
    with pytest.raises(MapStoreError, match=r"lacks loop_candidates\.detail"):
        MapStore.open(path)
    assert _digest(path) == before


@pytest.fixture
def read_only_folder(tmp_path: Path):
    """A folder nothing can be written into: permissions for a normal user, a read-only
    bind mount for root (skipped where it cannot be made)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    if os.geteuid() != 0:
        def make_read_only() -> None:
            folder.chmod(0o555)
        yield folder, make_read_only
        folder.chmod(0o755)
        return
    mounted = []

    def make_read_only() -> None:
        for cmd in (["mount", "--bind", str(folder), str(folder)],
                    ["mount", "-o", "remount,bind,ro", str(folder)]):
            if subprocess.run(cmd, capture_output=True, check=False).returncode != 0:
                pytest.skip("root without a read-only bind mount")
            mounted.append(cmd)
    yield folder, make_read_only
    if mounted:
        subprocess.run(["umount", str(folder)], check=True)


def test_a_healthy_map_in_a_read_only_folder(read_only_folder) -> None:
    """It used to be called damaged (SQLite could not make its -shm), and on a read-only
    mount the clean-up of that check ended in a traceback (EROFS from unlink)."""
    folder, make_read_only = read_only_folder
    path = folder / "map.sqlite"
    ids = _make_map(path)
    make_read_only()
    before = _digest(path)
    with pytest.raises(MapStoreError) as refused:
        MapStore.open(path)
    assert str(refused.value) == (f"map file {path}: its folder {folder} is read-only (the map "
                                  "writes its -wal and -shm files beside it)")
    with MapStore.open(path, create=False, read_only=True) as store:  # reading needs no writing
        assert [k.id for k in store.keyframes()] == ids
        assert store.keyframe_image(ids[1]).shape == (24, 32)
        with pytest.raises(MapStoreError, match="write failed"):
            store.begin_run("")
    with pytest.raises(MapStoreError, match=f"cannot create map file {folder / 'new.sqlite'}: "
                                            f"its folder {folder} is read-only"):
        MapStore.open(folder / "new.sqlite")
    assert _digest(path) == before
    assert sorted(p.name for p in folder.iterdir()) == ["map.sqlite"]


def test_a_read_only_open_neither_creates_nor_migrates(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "map.sqlite"
    with pytest.raises(MapStoreError, match="does not exist"):
        MapStore.open(path, read_only=True)
    assert not path.exists()
    _make_map(path)
    monkeypatch.setattr(
        mapconnection, "MIGRATIONS", {**mapconnection.MIGRATIONS, SCHEMA_VERSION + 1: _add_cameras_column}
    )
    before = _digest(path)
    with pytest.raises(MapStoreError, match=f"schema version {SCHEMA_VERSION}; open it once for "
                                            "writing"):
        MapStore.open(path, read_only=True)
    assert _digest(path) == before


def test_runs_that_never_ended_are_marked_once_keeping_their_keyframes(tmp_path: Path) -> None:
    path = tmp_path / "map.sqlite"
    with MapStore.open(path) as store:
        killed = store.begin_run("a", started_ns=100)
        ids = [store.add_keyframe(killed, stamp_ns=200 + i, pose_xyyaw=(i, 0, 0), covariance=_cov(i),
                                  image=None) for i in range(3)]
        empty = store.begin_run("b", started_ns=50, notes="bench drive")
        found = store.mark_unfinished_runs()
        assert [(run.id, run.ended_ns, n) for run, n in found] == [(killed, None, 3), (empty, None, 0)]
        runs = {r.id: r for r in store.runs()}
        assert runs[killed].ended_ns == 202 and runs[empty].ended_ns == 50
        assert runs[killed].notes.startswith("did not end cleanly: no end was recorded")
        assert runs[empty].notes.startswith("bench drive\ndid not end cleanly")
        assert not runs[killed].ended_cleanly and not runs[empty].ended_cleanly
        assert [k.id for k in store.keyframes(killed)] == ids
        assert store.mark_unfinished_runs() == []  # said once
        clean = store.begin_run("c", started_ns=1)
        store.end_run(clean, ended_ns=2)
        assert store.runs()[-1].ended_cleanly



def test_a_version_3_map_gains_the_forward_memory_and_keeps_its_rows(tmp_path, monkeypatch) -> None:
    """Version-3 maps are upgraded: the forward tables appear, empty; every earlier row
    is as it was."""
    path = tmp_path / "map.sqlite"
    migrations = mapconnection.MIGRATIONS
    monkeypatch.setattr(mapconnection, "MIGRATIONS", {v: migrations[v] for v in (1, 2, 3)})
    with MapStore.open(path) as store:
        assert store.schema_version == 3
        run = store.begin_run("a = 1\n", started_ns=10)
        kfs = [store.add_keyframe(run, 100 + i, (i, 0.0, 0.0), _cov(i), None) for i in range(2)]
        store.add_link("odometry", kfs[0], kfs[1], (1, 0, 0), _cov(3))
        store.put_optimized_poses([kfs[0]], np.zeros((1, 3)), solved_unix_ns=7)
    before = _all_rows(path)
    monkeypatch.undo()
    with MapStore.open(path) as store:
        assert store.schema_version == SCHEMA_VERSION
        assert store.forward_memory() == ([], [])
    after = _all_rows(path)
    assert {k: v for k, v in after.items() if k != "meta"} == {
        **{k: v for k, v in before.items() if k != "meta"}, "forward_images": [], "forward_words": []}


def test_the_forward_memory_round_trips_one_image_per_transaction(tmp_path) -> None:
    path = tmp_path / "map.sqlite"
    rng = np.random.default_rng(3)
    with MapStore.open(path) as store:
        run = store.begin_run("a = 1\n", started_ns=10)
        kfs = [store.add_keyframe(run, 100 + i, (i, 0.0, 0.0), _cov(i), None) for i in range(2)]
        desc = rng.integers(0, 256, (5, 32), dtype=np.uint8)
        kps = rng.integers(0, 10_000, (5, 2)).astype(np.uint16)
        store.add_forward_image(0, kfs[0], "orb", (640, 480), np.arange(5, dtype=np.uint32), kps, desc,
                                new_words=[(i, desc[i].tobytes()) for i in range(5)])
        store.add_forward_image(1, kfs[1], "orb", (640, 480), np.array([0, 1, 5], np.uint32), kps[:3], desc[:3],
                                new_words=[(5, desc[0].tobytes())], purged=[3, 4])
        with pytest.raises(ValueError):  # an unknown keyframe: nothing of the image is kept
            store.add_forward_image(2, 999, "orb", (640, 480), np.array([6], np.uint32), kps[:1], desc[:1],
                                    new_words=[(6, desc[0].tobytes())])
    with MapStore.open(path) as store:
        images, words = store.forward_memory()
    assert [(i[0], i[1], i[2], i[3]) for i in images] == [(0, kfs[0], "orb", (640, 480)), (1, kfs[1], "orb", (640, 480))]
    np.testing.assert_array_equal(images[1][4], [0, 1, 5])
    np.testing.assert_array_equal(images[0][5], kps)
    assert np.frombuffer(images[0][6], np.uint8).reshape(-1, 32).tolist() == desc.tolist()
    assert [(w[0], w[3], w[4]) for w in words] == [(0, 0, False), (1, 0, False), (2, 0, False), (3, 0, True),
                                                   (4, 0, True), (5, 1, False)]
    assert words[2][2] == desc[2].tobytes() and words[3][2] == b"" and words[4][2] == b""  # purged: dropped


def test_forward_word_ids_are_stored_deflated_when_shorter_and_raw_rows_still_read(tmp_path) -> None:
    """An image's word ids go into the map deflated by byte significance when that is
    shorter (300 ids below 2^17: well under the 1200 raw bytes); rows written raw (as
    every earlier map has them) read back the same; a damaged value is one clear error."""
    import sqlite3

    from robotd.base.errors import MapStoreError
    from robotd.io.store import pack_word_ids, unpack_word_ids

    rng = np.random.default_rng(4)
    ids = rng.integers(0, 1 << 17, 300).astype(np.uint32)
    blob = pack_word_ids(ids)
    assert len(blob) < 0.8 * 4 * len(ids)
    np.testing.assert_array_equal(unpack_word_ids(blob, len(ids)), ids)
    few = np.array([7], np.uint32)  # deflating one id does not pay: raw bytes
    assert pack_word_ids(few) == few.astype("<u4").tobytes()
    np.testing.assert_array_equal(unpack_word_ids(pack_word_ids(few), 1), few)
    with pytest.raises(ValueError):
        unpack_word_ids(blob, len(ids) + 1)  # the keypoints say another count
    path = tmp_path / "map.sqlite"
    kps = rng.integers(0, 10_000, (300, 2)).astype(np.uint16)
    desc = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    with MapStore.open(path) as store:
        run = store.begin_run("a = 1\n", started_ns=10)
        kfs = [store.add_keyframe(run, 100 + i, (i, 0.0, 0.0), _cov(i), None) for i in range(2)]
        store.add_forward_image(0, kfs[0], "orb", (640, 480), ids, kps, desc)
        store.add_forward_image(1, kfs[1], "orb", (640, 480), ids[::-1].copy(), kps, desc)
    with sqlite3.connect(path) as conn:  # image 1 as an earlier map wrote it: raw uint32
        conn.execute("UPDATE forward_images SET words = ? WHERE image_id = 1", (ids[::-1].astype("<u4").tobytes(),))
    with MapStore.open(path) as store:
        images, _ = store.forward_memory()
    np.testing.assert_array_equal(images[0][4], ids)
    np.testing.assert_array_equal(images[1][4], ids[::-1])
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE forward_images SET words = ? WHERE image_id = 0", (b"not deflated",))
    with MapStore.open(path) as store, pytest.raises(MapStoreError, match="forward image 0"):
        store.forward_memory()


def test_a_new_words_descriptor_is_taken_from_its_founder_in_the_image_row(tmp_path) -> None:
    """A word whose descriptor is its founder's (the image's first feature with it) is
    written without one and read back with the founder's; one that is not keeps its own;
    a word row left without a descriptor and without a feature to take it from is one
    clear error, not a wrong descriptor."""
    import sqlite3

    from robotd.base.errors import MapStoreError

    rng = np.random.default_rng(6)
    desc = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    kps = rng.integers(0, 10_000, (4, 2)).astype(np.uint16)
    path = tmp_path / "map.sqlite"
    with MapStore.open(path) as store:
        run = store.begin_run("a = 1\n", started_ns=10)
        kf = store.add_keyframe(run, 100, (0.0, 0.0, 0.0), _cov(0), None)
        # features 1 and 3 share word 8 (founded by feature 1); word 9 is not any feature's descriptor
        store.add_forward_image(0, kf, "orb", (640, 480), np.array([7, 8, 2, 8], np.uint32), kps, desc,
                                new_words=[(7, desc[0].tobytes()), (8, desc[1].tobytes()), (9, desc[3].tobytes())])
    with sqlite3.connect(path) as conn:
        stored = dict(conn.execute("SELECT id, descriptor FROM forward_words").fetchall())
    assert stored[7] == b"" and stored[8] == b"" and stored[9] == desc[3].tobytes()
    with MapStore.open(path) as store:
        _, words = store.forward_memory()
    assert [(w[0], w[2]) for w in words] == [(7, desc[0].tobytes()), (8, desc[1].tobytes()), (9, desc[3].tobytes())]
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE forward_words SET born_image = 5 WHERE id = 8")
    with MapStore.open(path) as store, pytest.raises(MapStoreError, match="forward word 8"):
        store.forward_memory()


def test_a_version_4_map_with_forward_rows_is_marked_version_5_and_reads_as_before(tmp_path, monkeypatch) -> None:
    """Version 5 changed no table, only what the forward rows may hold (deflated word ids, a
    word without its own descriptor), which a version-4 reader would misread: the upgrade
    moves the version number and nothing else, and the rows a version-4 store wrote (raw
    ids, every descriptor written) read back the same; a version-4 build refuses a
    version-5 file (the newer-schema test above)."""
    import sqlite3

    path = tmp_path / "map.sqlite"
    migrations = mapconnection.MIGRATIONS
    monkeypatch.setattr(mapconnection, "MIGRATIONS", {v: migrations[v] for v in (1, 2, 3, 4)})
    rng = np.random.default_rng(8)
    desc = rng.integers(0, 256, (3, 32), dtype=np.uint8)
    kps = rng.integers(0, 10_000, (3, 2)).astype(np.uint16)
    with MapStore.open(path) as store:
        assert store.schema_version == 4
        run = store.begin_run("a = 1\n", started_ns=10)
        kf = store.add_keyframe(run, 100, (0.0, 0.0, 0.0), _cov(0), None)
    with sqlite3.connect(path) as conn:  # the rows as a version-4 store wrote them
        conn.execute("INSERT INTO forward_images VALUES (0, ?, 'orb', 640, 480, ?, ?, ?)",
                     (kf, np.array([4, 5, 4], "<u4").tobytes(), kps.astype("<u2").tobytes(), desc.tobytes()))
        conn.executemany("INSERT INTO forward_words (id, kind, descriptor, born_image) VALUES (?, 'orb', ?, 0)",
                         [(4, desc[0].tobytes()), (5, desc[1].tobytes())])
    conn.close()
    before = _all_rows(path)
    monkeypatch.setattr(mapconnection, "MIGRATIONS", {v: migrations[v] for v in (1, 2, 3, 4, 5)})
    with MapStore.open(path) as store:
        assert store.schema_version == 5
        images, words = store.forward_memory()
    np.testing.assert_array_equal(images[0][4], [4, 5, 4])
    assert [(w[0], w[2]) for w in words] == [(4, desc[0].tobytes()), (5, desc[1].tobytes())]
    after = _all_rows(path)
    meta_before, meta_after = before.pop("meta"), after.pop("meta")
    assert after == before
    assert dict(meta_after) == {**dict(meta_before), "schema_version": "5"}


def _version_5_map_with_fates(path: Path, monkeypatch) -> tuple[list[int], list[tuple]]:
    """A map written by the store at version 5 (the migrations up to it), with loop
    candidates as a version-5 daemon recorded them; the newest row deleted, so the table's
    AUTOINCREMENT counter is above its largest id. Returns the keyframe ids and the rows
    left ``(id, query, candidate, score, fate, detail)``."""
    from robotd.graph.gate import GROUP_MEMBER

    migrations = mapconnection.MIGRATIONS
    monkeypatch.setattr(mapconnection, "MIGRATIONS", {v: migrations[v] for v in (1, 2, 3, 4, 5)})
    member = f"forward: {GROUP_MEMBER} (2->7): 3 candidates agree"
    with MapStore.open(path) as store:
        assert store.schema_version == 5
        run = store.begin_run("a = 1\n", started_ns=10)
        kfs = [store.add_keyframe(run, 100 + i, (i, 0.0, 0.0), _cov(i), None) for i in range(4)]
        store.add_link("odometry", kfs[0], kfs[1], (1, 0, 0), _cov(3))
        store.put_optimized_poses(kfs[:2], np.zeros((2, 3)), solved_unix_ns=7)
        store.add_loop_candidates([
            (kfs[3], kfs[0], 0.9, "failed_gate", member),
            (kfs[3], kfs[1], 0.8, "failed_gate", "forward: chi2 30.1 > 13.82"),
            (kfs[2], kfs[0], 0.7, "failed_gate", "relocalisation: no agreeing candidate before the run ended"),
            (kfs[3], kfs[2], 0.95, "failed_gate", member),
            (kfs[2], kfs[1], 31.0, "accepted", "chi2 0.40"),
            (kfs[3], kfs[0], 12.0, "below_threshold", f"score 12.0; {member}"),  # the text, not at the start
            (kfs[2], kfs[0], 0.6, "down_weighted", "weight 0.100"),
        ])
    monkeypatch.undo()
    with sqlite3.connect(path) as raw:
        raw.execute("DELETE FROM loop_candidates WHERE id = 7")
        with pytest.raises(sqlite3.IntegrityError, match="CHECK"):  # what version 5 cannot hold
            raw.execute("INSERT INTO loop_candidates(query_id, candidate_id, score, fate) VALUES (?, ?, 0, 'grouped')",
                        (kfs[3], kfs[0]))
        rows = raw.execute("SELECT * FROM loop_candidates ORDER BY id").fetchall()
    raw.close()
    return kfs, rows


def test_a_version_5_map_gains_the_grouped_fate_and_its_members_rows_are_relabelled(tmp_path, monkeypatch) -> None:
    """Version 6 rebuilds ``loop_candidates`` with ``grouped`` in its CHECK: every row keeps
    its id, keyframes, score and detail; a relocalising group's member (``failed_gate``
    with the gate's member text at the start of its detail) becomes ``grouped``, every other
    row keeps its fate; the index is back, the id counter goes on where it was (an id is
    never reused), every other table is as it was; the CHECK takes ``grouped`` and still
    refuses any other text."""
    path = tmp_path / "map.sqlite"
    kfs, rows = _version_5_map_with_fates(path, monkeypatch)
    before = _all_rows(path)
    assert ("loop_candidates", 7) in before["sqlite_sequence"]
    with MapStore.open(path) as store:
        assert store.schema_version == SCHEMA_VERSION == 6
        records = store.loop_candidates()
        assert [(r.id, r.query_id, r.candidate_id, r.score, r.detail) for r in records] == [
            (i, q, c, sc, d) for i, q, c, sc, _f, d in rows]
        assert [r.fate for r in records] == ["grouped", "failed_gate", "failed_gate", "grouped", "accepted",
                                             "below_threshold"]
        assert [r.id for r in store.loop_candidates("grouped")] == [1, 4]
        store.add_loop_candidates([(kfs[3], kfs[1], 0.5, "grouped", "forward: new")])
        assert store.loop_candidates()[-1].id == 8  # not 7: that id was used
    after = _all_rows(path)
    relabelled = [(i, q, c, sc, "grouped" if i in (1, 4) else f, d) for i, q, c, sc, f, d in rows]
    assert after.pop("loop_candidates") == [*relabelled, (8, kfs[3], kfs[1], 0.5, "grouped", "forward: new")]
    before.pop("loop_candidates")
    seq_before, seq_after = dict(before.pop("sqlite_sequence")), dict(after.pop("sqlite_sequence"))
    assert seq_after == {**seq_before, "loop_candidates": 8}
    meta_before, meta_after = before.pop("meta"), after.pop("meta")
    assert after == before
    assert dict(meta_after) == {**dict(meta_before), "schema_version": "6"}
    with sqlite3.connect(path) as raw:
        assert raw.execute("SELECT name FROM sqlite_master WHERE tbl_name = 'loop_candidates' AND type = 'index'"
                           ).fetchall() == [("loop_candidates_by_query",)]
        assert raw.execute("EXPLAIN QUERY PLAN SELECT * FROM loop_candidates WHERE query_id = 1"
                           ).fetchall()[0][3].endswith("USING INDEX loop_candidates_by_query (query_id=?)")
        assert raw.execute("PRAGMA foreign_key_check").fetchall() == []
        assert raw.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
        raw.execute("INSERT INTO loop_candidates(query_id, candidate_id, score, fate) VALUES (?, ?, 0, 'grouped')",
                    (kfs[2], kfs[0]))
        for junk in ("maybe", "Grouped", "group", ""):
            with pytest.raises(sqlite3.IntegrityError, match="CHECK"):
                raw.execute("INSERT INTO loop_candidates(query_id, candidate_id, score, fate) VALUES (?, ?, 0, ?)",
                            (kfs[2], kfs[0], junk))
    raw.close()


def test_a_version_5_robotd_refuses_a_version_6_map_untouched(tmp_path, monkeypatch) -> None:
    """The robotd before version 6 (its migrations end at 5) meets a version-6 map: its
    clear error, the file not modified."""
    path = tmp_path / "map.sqlite"
    _make_map(path)
    before = _digest(path)
    migrations = mapconnection.MIGRATIONS
    monkeypatch.setattr(mapconnection, "MIGRATIONS", {v: migrations[v] for v in (1, 2, 3, 4, 5)})
    for read_only in (False, True):
        with pytest.raises(MapStoreError, match="has schema version 6, newer than the 5 this robotd .* understands; "
                                                "upgrade robotd"):
            MapStore.open(path, read_only=read_only)
    assert _digest(path) == before


_KILLED_IN_MIGRATION = textwrap.dedent(
    """
    import os, signal, sys
    from robotd.io import mapconnection
    from robotd.io.store import MapStore

    step = mapconnection.MIGRATIONS[6]

    def step_then_power_cut(conn):
        step(conn)  # the whole rebuild done, not committed
        print("rebuilt", flush=True)
        os.kill(os.getpid(), signal.SIGKILL)

    mapconnection.MIGRATIONS = {**mapconnection.MIGRATIONS, 6: step_then_power_cut}
    MapStore.open(sys.argv[1])
    """
)


def test_a_kill_during_the_migration_to_version_6_loses_nothing(tmp_path, monkeypatch) -> None:
    """Killed after the table was rebuilt and before the migration committed: the file is
    the version-5 map it was, row for row, and the next open migrates it."""
    path = tmp_path / "map.sqlite"
    _kfs, rows = _version_5_map_with_fates(path, monkeypatch)
    before = _all_rows(path)
    proc = subprocess.run([sys.executable, "-c", _KILLED_IN_MIGRATION, str(path)], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL and proc.stdout == "rebuilt\n", proc.stderr
    assert _all_rows(path) == before  # version 5, every row as it was
    with sqlite3.connect(path) as raw:
        assert raw.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
        assert raw.execute("SELECT name FROM sqlite_master WHERE name LIKE 'loop_candidates%'").fetchall() == [
            ("loop_candidates",), ("loop_candidates_by_query",)]
    raw.close()
    with MapStore.open(path) as store:
        assert store.schema_version == 6
        assert [r.id for r in store.loop_candidates("grouped")] == [1, 4]
        assert len(store.loop_candidates()) == len(rows)


@pytest.mark.parametrize("schema_less", ["empty file", "database without tables"])
def test_a_reader_meeting_a_map_being_created_says_so(tmp_path: Path, schema_less: str) -> None:
    """Between a writer's lock and its schema the file is empty or has no tables: a reader
    then says the map is being created (by whom), not that it is empty or old; once that
    writer is gone the old messages come back."""
    from robotd.io.maplock import hold_map_lock, lock_path

    m = tmp_path / "m.sqlite"
    if schema_less == "empty file":
        m.write_bytes(b"")
        after = "is empty"
    else:
        conn = sqlite3.connect(m)
        conn.execute("PRAGMA user_version = 0")
        conn.execute("CREATE TABLE t (x)")  # a real SQLite file, none of the map's tables
        conn.execute("DROP TABLE t")
        conn.commit()
        conn.close()
        after = "has schema version 0"
    before = m.read_bytes()
    with hold_map_lock(m):
        with pytest.raises(MapStoreError, match=rf"being created by another process \(pid {os.getpid()}"):
            MapStore.open(m, create=False, read_only=True)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    lock_path(m).write_text(f"pid {dead.stdout.strip()}: robotd run\n")  # left by a killed writer
    with pytest.raises(MapStoreError, match=after):
        MapStore.open(m, create=False, read_only=True)
    assert m.read_bytes() == before
