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


@pytest.mark.parametrize(("args", "message"), [
    (("--kidnap-to", "3"), "--kidnap-to needs --kidnap"),
    (("--kidnap", "900"), "a kidnapping at 900.0 s to 450.0 s (carried 5.0 s) does not fit a motion of 56.6 s"),
    (("--kidnap", "5", "--base", "can"), "a kidnapping needs the Kobuki base (the wheel-drop bits of its sensor data)"),
])
def test_a_kidnapping_that_cannot_be_is_one_line(tmp_path: Path, capsys, args: tuple[str, ...], message: str):
    from robotd.app.cli import main

    code = main(["demo", "--route", "square", "--no-plot", "--out", str(tmp_path / "out"), *args])
    assert (code, capsys.readouterr().err) == (2, f"robotd: error: {message}\n")
