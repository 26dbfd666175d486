"""A short soak (slow): three laps of the recorded figure eight through one daemon, by
``bench/bench_soak.py`` itself (the full soak is 100,000 frames; see the bench)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_three_laps_lose_nothing_find_loops_and_keep_the_descriptor_bound(tmp_path: Path) -> None:
    out = tmp_path / "soak.json"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_soak.py"), "--laps", "3",
                        "--work", str(tmp_path), "--out", str(out)],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=1800)
    assert r.returncode == 0, r.stderr[-3000:]
    s = json.loads(out.read_text())
    laps = s["laps_table"]
    assert s["laps"] == 3 and [row["lap"] for row in laps] == [0, 1, 2]
    # Nothing lost: every frame handed out went through the pipeline and got its pose.
    assert s["frames_handed_out"] == 3 * s["frames_per_lap"] == s["frames_processed"]
    assert [row["frames"] for row in laps] == [s["frames_per_lap"]] * 3
    assert s["frames_unsynced"] == 0 and sum(s["queue_drops"].values()) == 0
    # Laps 2 and 3 drive over lap 1's floor again: the daemon localises there
    # ([pose_graph] localise_mapped, on in the soak) and the map stops growing: almost no
    # keyframe is stored (the seam and the odd failed match may add a few), nearly every
    # keyframe taken is matched against the map instead, and the robot re-localises.
    first = laps[0]["keyframes_total"]
    added = [laps[k]["keyframes_total"] - laps[k - 1]["keyframes_total"] for k in (1, 2)]
    assert first > 100 and max(added) <= 0.1 * first, (first, added)
    not_stored = [laps[k]["keyframes_not_stored"] - laps[k - 1]["keyframes_not_stored"] for k in (1, 2)]
    assert min(not_stored) >= 0.8 * first, (first, not_stored)
    assert laps[2]["localise_matches"] > laps[1]["localise_matches"] > laps[0]["localise_matches"]
    # With keyframes every 0.2 m and max_unlocalised_m = 1.0, fewer than one accepted match
    # in five keyframes would make the daemon store keyframes again.
    assert s["relocalisations"] == laps[2]["localise_matches"] >= 0.2 * sum(not_stored)
    m = s["map"]
    assert m["keyframes"] == s["keyframes_stored"] == laps[2]["keyframes_total"]
    assert s["keyframes"] == s["keyframes_stored"] + s["keyframes_not_stored"]  # every one taken
    assert 0 < m["descriptor_bytes_max"] <= m["descriptor_bound_bytes"] == 4096
    # Memory: what the process holds (after malloc_trim) may not grow from lap 2 to lap 3
    # by more than a few MB: a leak of one 640 x 480 frame per keyframe taken (307 kB
    # each, about 137 a lap) would add 40 MB.
    growth_mb = laps[2]["rss_trimmed_mb"] - laps[1]["rss_trimmed_mb"]
    assert growth_mb < 10, growth_mb
