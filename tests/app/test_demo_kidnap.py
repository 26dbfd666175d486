"""`robotd demo --kidnap`: the virtual robot is lifted, carried blind and put down elsewhere;
the daemon notices the wheel drop, breaks its odometry chain and relocalises."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from robotd.io.store import MapStore


@pytest.mark.slow
def test_a_kidnapped_demo_relocalises_with_a_small_pose_error(tmp_path: Path):
    # The square route: lifted at 20 s, put down 5 s later where the route was at 4 s (1.2 m
    # away, facing another way), then 9 s of driving over floor it saw in its first lap.
    r = subprocess.run([sys.executable, "-m", "robotd.app.cli", "--log-level", "info", "demo", "--route", "square",
                        "--kidnap", "20", "--kidnap-to", "4", "--duration", "34", "--no-plot",
                        "--out", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "lifted (wheel drop): lost" in r.stderr
    assert "relocalised against run 1 after" in r.stderr
    s = json.loads((tmp_path / "summary.json").read_text())
    rl = s["relocalisation"]
    assert (rl["lifts_detected"], rl["odometry_breaks"], rl["relocalisations"]) == (1, 1, 1)
    assert rl["carried_m"] > 1.0
    assert rl["relocalised"] and rl["against_run"] == 1
    assert rl["after_s"] < 8.0 and rl["after_m_true"] < 2.0
    # The pose right after relocalisation, against the truth (the odometry alone is off by
    # the whole carry, more than a metre).
    assert rl["position_error_m"] < 0.05 and rl["heading_error_deg"] < 1.0
    assert "relocalised against run 1" in r.stdout
    with MapStore.open(tmp_path / "map.sqlite", create=False) as store:
        kfs = [k.id for k in store.keyframes()]
        odo = {(lk.from_id, lk.to_id) for lk in store.links("odometry")}
        # One keyframe (the first after the carry) has no odometry link into it.
        assert sum((a, b) not in odo for a, b in zip(kfs, kfs[1:])) == 1
        assert store.map_frame_runs() == {1}
        # Every keyframe, before and after the carry, has a pose in the map frame.
        assert set(store.optimized_poses()) == set(kfs)
