"""SIGKILL at random moments while ``robotd replay`` writes a map, several times into one
map: the map stays whole and keeps every keyframe the daemon acknowledged, and the next
start reports the killed run. ``bench/bench_sigkill.py --kills 100``
runs many more rounds."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from bench.bench_sigkill import check_map, kill_rounds, make_recording


@pytest.mark.slow
def test_sigkill_during_map_writes_loses_no_acknowledged_keyframe(tmp_path: Path) -> None:
    rec = tmp_path / "drive.mcap"
    make_recording(rec, duration_s=20.0, seed=1)
    report = kill_rounds(rec, tmp_path / "map.sqlite", 5, seed=1, max_delay_s=4.0, work=tmp_path / "work")
    # A round may end before its kill comes (then it ended cleanly); on a loaded machine
    # all five are killed, a fast one may finish the 20 s drive in a few seconds.
    assert report.kills >= 1
    assert report.integrity_failures == 0, [r.integrity for r in report.rounds]
    assert report.acked_lost == 0, [(r.acked, r.in_map) for r in report.rounds]
    # The kills landed while keyframes were being written: acknowledged ones were at stake.
    assert report.acked_total > 0
    assert report.unreported_unfinished == 0
    assert all(r.previous_reported_unfinished for r, prev in zip(report.rounds[1:], report.rounds)
               if prev.killed)
    if report.rounds[-1].killed:
        assert report.last_found_unfinished is True


def test_the_map_check_finds_a_damaged_map(tmp_path: Path) -> None:
    """The harness's check can fail: a map with a page overwritten is not "ok"."""
    from robotd.io.store import MapStore
    import numpy as np

    path = tmp_path / "m.sqlite"
    with MapStore.open(path) as store:
        run = store.begin_run("")
        for i in range(40):
            store.add_keyframe(run, i, (0.01 * i, 0.0, 0.0), np.eye(3), np.zeros((60, 80), np.uint8),
                               descriptor=b"x" * 400, descriptor_mode=1)
        store.end_run(run)
    assert check_map(path) == ("ok", 40, run)
    with sqlite3.connect(path) as raw:
        raw.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    raw.close()
    wal = Path(str(path) + "-wal")
    assert not wal.exists() or wal.stat().st_size == 0  # everything is in the main file
    data = bytearray(path.read_bytes())
    page = int.from_bytes(data[16:18], "big")
    for start in range(page, len(data), page):  # every b-tree page header but the first page's
        data[start:start + 12] = b"\xa5" * 12
    path.write_bytes(bytes(data))
    integrity, _, _ = check_map(path)
    assert integrity != "ok"
