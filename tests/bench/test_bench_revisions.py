"""``bench/bench_revisions.py``: its measures of the live fused pose, its verdict per seed, its
refusals, and the replay part's reading of a revision's ``robotd replay``."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.bench_revisions import DESCRIBE_CHILD, REPO, fused_errors, graph_errors, replay_once, verdict
from robotd.base.geometry import compose
from robotd.io.trajectory import write_tum


def test_the_fused_pose_drifting_by_a_turn_shows_in_the_end_error_and_the_anchored_not_the_aligned(tmp_path: Path):
    t_ns = np.arange(0, 101) * 100_000_000
    truth = np.column_stack([np.linspace(0.0, 20.0, 101), np.zeros(101), np.zeros(101)])
    write_tum(tmp_path / "groundtruth.tum", t_ns, truth)
    turn = math.radians(0.1)
    # the track heads 0.1 deg off while its heading reads straight (a drift the anchoring
    # keeps), from its own origin (the demo anchors it at the truth's first pose)
    drifted = truth.copy()
    drifted[:, 0], drifted[:, 1] = truth[:, 0] * math.cos(turn), truth[:, 0] * math.sin(turn)
    fused = compose(np.array([3.0, -1.0, 0.4]), drifted)
    write_tum(tmp_path / "fused.tum", t_ns, fused)
    e = fused_errors(tmp_path)
    assert e["poses"] == 101
    assert abs(e["end_m"] - 20.0 * turn) < 1e-5  # 20 m out at 0.1 deg: 34.9 mm
    assert e["ape_anchored_m"] > 0.015
    assert e["ate_aligned_m"] < 1e-5


def row(end: float, ate: float, lc: float | None = 0.002, refused: int = 0) -> dict:
    return {"fused": {"end_m": end, "ape_anchored_m": ate, "ate_aligned_m": ate},
            "loop_corrected": {"ape_anchored_m": lc, "ate_aligned_m": None}, "loops_refused": refused}


def test_the_verdict_asks_strictly_lower_fused_figures_and_no_refused_loop():
    v = verdict(row(0.2, 0.07), row(0.04, 0.02))
    assert v == {"fused_end": True, "fused_ape_anchored": True, "fused_ate_aligned": True,
                 "loop_corrected_ape": True, "no_loop_refused": True}
    v = verdict(row(0.15, 0.05), row(0.15, 0.06, lc=0.003, refused=2))
    assert not v["fused_end"] and not v["fused_ate_aligned"]
    assert not v["loop_corrected_ape"] and not v["no_loop_refused"]


def test_an_older_revisions_graph_figures_are_read_under_their_old_name():
    assert graph_errors({"ate_rmse_m": 0.15}) == {"ape_anchored_m": 0.15, "ate_aligned_m": None}
    assert graph_errors({"ape_origin_rmse_m": 0.1, "ate_aligned_rmse_m": 0.05}) == {
        "ape_anchored_m": 0.1, "ate_aligned_m": 0.05}


@pytest.mark.parametrize("args, message", [
    (["--before", "no-such-revision-here"], "unknown revision 'no-such-revision-here'"),
    ([], "--before REV is needed"),
    (["replay", "--before", "HEAD", "--pairs", "0"], "--pairs must be at least 1"),
    (["describe", "--before", "HEAD", "--frames", "0"], "--frames must be at least 1"),
    (["--page-from", "x.json"], "--page-from needs --markdown"),
])
def test_refusals_are_one_line_and_write_nothing(tmp_path: Path, args: list[str], message: str):
    done = subprocess.run([sys.executable, str(REPO / "bench" / "bench_revisions.py"), *args,
                           "--work", str(tmp_path / "work"), "--out", str(tmp_path / "out.json")],
                          capture_output=True, text=True, cwd=REPO)
    assert done.returncode != 0
    assert message in done.stderr
    assert "Traceback" not in done.stderr
    assert not (tmp_path / "out.json").exists()


def fake_tree(root: Path, last_line: str, code: int = 0) -> Path:
    """A tree whose ``robotd.app.cli`` prints ``last_line`` and exits with ``code``."""
    app = root / "robotd" / "app"
    app.mkdir(parents=True)
    for d in (root / "robotd", app):
        (d / "__init__.py").write_text("")
    (app / "cli.py").write_text(f"import sys\nprint('replaying')\nprint({last_line!r})\nsys.exit({code})\n")
    return root


def test_a_replay_reads_the_keyframes_from_the_revisions_last_line(tmp_path: Path):
    tree = fake_tree(tmp_path / "tree", "replayed x.mcap: 60.0 s of recording in 6.6 s; 3001 odometry samples, "
                                        "1800 frames (0 without odometry), 181 keyframes -> m.sqlite")
    r = replay_once(tree, tmp_path / "x.mcap", tmp_path, None)
    assert r["keyframes"] == 181
    assert r["cpu_s"] >= 0.0 and r["wall_s"] > 0.0


def test_a_replay_that_fails_is_an_error_that_names_its_command(tmp_path: Path):
    tree = fake_tree(tmp_path / "tree", "robotd replay: no such file", code=2)
    with pytest.raises(RuntimeError, match="exit 2"):
        replay_once(tree, tmp_path / "x.mcap", tmp_path, None)


def test_the_describe_child_times_every_frame_with_the_trees_own_extract(tmp_path: Path):
    floor = tmp_path / "tree" / "robotd" / "floor"
    floor.mkdir(parents=True)
    for d in (floor.parent, floor):
        (d / "__init__.py").write_text("")
    # an extract that counts its calls (5 warm-up frames, then every frame timed)
    (floor / "descriptor.py").write_text(
        f"calls = []\ndef extract(image, mode):\n    calls.append(mode)\n"
        f"    open({str(tmp_path / 'calls')!r}, 'a').write(f'{{image.shape}} {{mode}}\\n')\n")
    np.save(tmp_path / "frames.npy", np.zeros((7, 4, 6), np.uint8))
    done = subprocess.run([sys.executable, "-c", DESCRIBE_CHILD, str(tmp_path / "frames.npy"), "4"],
                          capture_output=True, text=True, cwd=tmp_path / "tree",
                          env={"PYTHONPATH": str(tmp_path / "tree")})
    assert done.returncode == 0, done.stderr
    r = json.loads(done.stdout.strip().splitlines()[-1])
    assert r["frames"] == 7 and r["median_ms"] >= 0.0 and r["p90_ms"] >= r["median_ms"]
    assert (tmp_path / "calls").read_text().splitlines() == ["(4, 6) 4"] * 12


def test_a_revisions_snapshot_is_its_tree_exported_whole_and_kept(tmp_path: Path):
    from bench.bench_revisions import snapshot

    tree, commit = snapshot("HEAD", tmp_path)
    assert len(commit) == 40 and tree == tmp_path / f"tree-{commit[:12]}"
    assert (tree / "robotd" / "floor" / "descriptor.py").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == [tree.name]  # nothing half-made beside it
    (tree / "marker").write_text("kept")
    assert snapshot("HEAD", tmp_path) == (tree, commit) and (tree / "marker").is_file()
