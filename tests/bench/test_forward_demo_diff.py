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
