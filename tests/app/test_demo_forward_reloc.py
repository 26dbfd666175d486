"""`robotd demo --forward --kidnap` with the floor detector off: the forward camera alone
relocalises the kidnapped robot (three verified forward loops to stored places that agree,
after odometry has moved the robot: two bearings always cross, so two cannot check each
other), and says so."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest


@pytest.mark.slow
def test_the_forward_camera_relocalises_a_kidnapped_robot_without_the_floor_detector(tmp_path: Path):
    cfg = tmp_path / "nofloor.toml"
    cfg.write_text("[floor_detector]\nenabled = false\n")
    out = tmp_path / "out"
    # The office route: lifted at 120 s, put down where the route was at 60 s (2.6 m away),
    # a corridor it drove before.
    r = subprocess.run([sys.executable, "-m", "robotd.app.cli", "--log-level", "info", "demo", "--route", "office",
                        "--forward", "--config", str(cfg), "--kidnap", "120", "--kidnap-to", "60",
                        "--duration", "150", "--no-plot", "--out", str(out)],
                       capture_output=True, text=True, timeout=3600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "lifted (wheel drop): lost" in r.stderr
    assert "relocalised against run 1 after" in r.stderr and "(forward camera)" in r.stderr
    s = json.loads((out / "summary.json").read_text())
    assert "floor_detector" not in s or not s["floor_detector"]
    rl = s["relocalisation"]
    assert (rl["lifts_detected"], rl["odometry_breaks"], rl["relocalisations"]) == (1, 1, 1)
    assert rl["relocalised"] and rl["cameras"] == "forward" and rl["agreeing_candidates"] >= 3
    # Measured (bench/bench_forward_kidnap.py, seed 0): 5.3 s and 2.67 m after being put down,
    # 0.03 m and 0.5 deg off (the odometry alone is off by the whole carry, 2.6 m).
    assert rl["after_s"] < 25.0 and rl["after_m_true"] < 10.0
    assert rl["position_error_m"] < 0.4 and rl["heading_error_deg"] < 5.0
    fw = s["forward_detector"]
    # The relocalising group entered the graph as one edge: its members are no accepted loops
    # and none refused by the gate, but ``grouped``, counted so.
    members = [x for x in fw["loops"] if x["fate_detail"].startswith("relocalisation: a member of the relocalising")]
    assert len(members) == rl["agreeing_candidates"] and all(x["fate"] == "grouped" for x in members)
    assert [x for x in fw["loops"] if x["fate"] == "grouped"] == members
    assert fw["grouped"] == len(members)
    assert f"{len(members)} in through their relocalising group's one edge" in r.stdout
    from robotd.io.store import MapStore

    with MapStore.open(out / "map.sqlite", read_only=True) as store:
        assert len(store.loop_candidates("grouped")) == len(members)
    # Every accepted forward loop right by the demo's judge (measured: 22 of 22): across the
    # carry a ridge loop is settled at the relocalising loops' heading or not taken at all.
    assert fw["accepted_right"] == fw["accepted"]
    assert "by the forward camera" in r.stdout
