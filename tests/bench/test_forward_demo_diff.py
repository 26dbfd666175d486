"""``bench/forward_demo_diff.py``: two demo runs' forward answers compared; the claim that a
cut keeps every answer rests on it naming every difference."""

from __future__ import annotations

import json
from pathlib import Path

from bench.forward_demo_diff import differences


def _run(tmp: Path, name: str, *, accepted: int = 1, bearing: float = 12.5, fate: str = "accepted",
         pose_x: float = 1.0, loops: int = 1) -> Path:
    d = tmp / name
    d.mkdir()
    loop = {"from": 3, "to": 90, "inliers": 41, "fate": fate, "bearing_deg": bearing, "sigma_yaw_deg": None,
            "right": True}
    summary = {"forward_detector": {"images": 100, "verified_loops": 1, "accepted": accepted,
                                    "cpu_ms_per_image_p99": 40.0 + len(name), "loops": [loop] * loops}}
    (d / "summary.json").write_text(json.dumps(summary))
    (d / "corrected.tum").write_text(f"# t x y z qx qy qz qw\n0.0 {pose_x} 0 0 0 0 0 1\n1.0 2.0 0 0 0 0 0 1\n")
    return d


def test_the_same_answers_differ_nowhere_whatever_the_times(tmp_path):
    assert differences(_run(tmp_path, "a"), _run(tmp_path, "bb")) == []  # the p99s differ: times are left out


def test_every_changed_answer_is_named(tmp_path):
    a = _run(tmp_path, "a")
    assert differences(a, _run(tmp_path, "b", accepted=0)) == ["accepted: 1 != 0"]
    assert differences(a, _run(tmp_path, "c", fate="refused_by_gate")) == \
        ["loop 0 (3 -> 90).fate: 'accepted' != 'refused_by_gate'"]
    assert differences(a, _run(tmp_path, "d", bearing=12.5 + 1e-12)) == \
        ["loop 0 (3 -> 90).bearing_deg: 12.5 != 12.500000000001"]
    assert differences(a, _run(tmp_path, "e", bearing=12.5 + 1e-12), tol=1e-9) == []
    assert differences(a, _run(tmp_path, "f", pose_x=1.0 + 1e-9)) == ["corrected.tum row 0: differs by 1e-09"]
    assert differences(a, _run(tmp_path, "g", loops=2)) == ["loops: 1 != 2"]


def test_by_pair_matches_the_loops_by_their_keyframes_not_their_order(tmp_path):
    def run(name: str, loops: list[tuple[int, int, float]]) -> Path:
        d = tmp_path / name
        d.mkdir()
        rows = [{"from": f, "to": t, "inliers": 30, "fate": "accepted", "bearing_deg": b} for f, t, b in loops]
        (d / "summary.json").write_text(json.dumps({"forward_detector": {"loops": rows}}))
        return d

    a = run("a", [(3, 90, 1.0), (5, 95, 2.0)])
    swapped = run("b", [(5, 95, 2.0), (3, 90, 1.0)])
    assert differences(a, swapped) != []  # in order, every field of both rows differs
    assert differences(a, swapped, by_pair=True) == []
    moved = run("c", [(5, 95, 2.5), (4, 91, 1.0)])
    assert differences(a, moved, by_pair=True) == [
        "loop 3 -> 90: in the first run only", "loop 4 -> 91: in the second run only",
        "loop 0 (5 -> 95).bearing_deg: 2.0 != 2.5"]
