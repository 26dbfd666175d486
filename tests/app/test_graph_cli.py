"""``robotd graph optimize`` and ``robotd graph export`` end to end on small files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from robotd.app.cli import main
from robotd.io.g2o import read_g2o
from robotd.io.store import MapStore
from robotd.io.trajectory import read_tum

# An octagon inscribed in a circle of radius 3 m, starting at the origin heading +x.
CENTRE = (3 * math.sin(math.pi / 8), 3 * math.cos(math.pi / 8))
RING = "".join(
    f"EDGE_SE2 {k} {(k + 1) % 8} {2 * 3 * math.sin(math.pi / 8):.9f} 0 {math.pi / 4:.9f} "
    f"100 0 0 100 0 1000\n" for k in range(8))


def test_optimize_prints_the_objectives_and_writes_the_result(tmp_path: Path, capsys):
    src = tmp_path / "ring.g2o"
    src.write_text("# an octagon, 7 odometry edges and a closing loop\n" + RING)
    out = tmp_path / "out.g2o"
    assert main(["graph", "optimize", str(src), "--out", str(out), "--isotropic"]) == 0
    text = capsys.readouterr().out
    assert "8 poses, 8 edges (1 loops)" in text
    final = float(text.split("final objective")[1].split()[0])
    assert final < 1e-12
    assert "iterations" in text and "time" in text
    g = read_g2o(out)
    assert np.allclose(np.linalg.norm(g.poses()[:, :2] - CENTRE, axis=1), 3.0, atol=1e-6)


def test_optimize_refuses_to_overwrite_and_reports_bad_lines(tmp_path: Path, capsys):
    src = tmp_path / "bad.g2o"
    src.write_text("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    out = tmp_path / "out.g2o"
    assert main(["graph", "optimize", str(src), "--out", str(out)]) == 2
    assert f"robotd: error: {src}:2: edge 0 -> 1 refers to vertex 1" in capsys.readouterr().err
    out.write_text("keep me")
    assert main(["graph", "optimize", str(src), "--out", str(out)]) == 2
    assert "exists (use --force" in capsys.readouterr().err
    assert out.read_text() == "keep me"


def test_export_writes_g2o_and_both_trajectories(tmp_path: Path, capsys):
    path = tmp_path / "map.sqlite"
    step = math.pi / 4
    chord = 2 * 3 * math.sin(step / 2)
    info = np.diag([100.0, 100.0, 1000.0])
    with MapStore.open(path) as store:
        run = store.begin_run("", started_ns=0, epoch_unix_ns=0)
        ids = []
        pose = np.zeros(3)
        for k in range(8):
            ids.append(store.add_keyframe(run, 1_000_000_000 * (k + 1), pose, np.eye(3) * 1e-4, None))
            drift = (chord * 1.05, 0.0, step * 1.02)  # odometry poses drift
            c, s = math.cos(pose[2]), math.sin(pose[2])
            pose = pose + (c * drift[0], s * drift[0], drift[2])
        for a, b in zip(ids, ids[1:]):
            store.add_link("odometry", a, b, (chord, 0.0, step), info)
        store.add_link("loop", ids[-1], ids[0], (chord, 0.0, step), info)
    out = tmp_path / "export"
    assert main(["graph", "export", str(path), "--out", str(out)]) == 0
    assert "8 keyframes, 7 odometry and 1 loop links" in capsys.readouterr().out
    g = read_g2o(out / "graph.g2o")
    assert len(g) == 8 and len(g.edges) == 8
    stamps, odo = read_tum(out / "odometry.tum")
    _, opt = read_tum(out / "optimized.tum")
    assert list(stamps) == [1_000_000_000 * (k + 1) for k in range(8)]
    assert np.allclose(odo[:, :2], g.poses()[:, :2], atol=1e-6)
    assert np.allclose(np.linalg.norm(opt[:, :2] - CENTRE, axis=1), 3.0, atol=1e-5)
    assert main(["graph", "export", str(path), "--out", str(out)]) == 2
    assert main(["graph", "export", str(path), "--out", str(out), "--force"]) == 0


def test_export_of_a_missing_map_is_a_clear_error(tmp_path: Path, capsys):
    assert main(["graph", "export", str(tmp_path / "none.sqlite"), "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_optimize_robust_chooses_gnc_or_dcs_and_both_reject_a_wrong_loop(tmp_path: Path, capsys):
    # The octagon twice round (the second lap's vertices 8..15 tied to the first's by true
    # loops) and one wrong loop between opposite corners.
    side = 2 * 3 * math.sin(math.pi / 8)
    lines = [f"EDGE_SE2 {k} {k + 1} {side:.9f} 0 {math.pi / 4:.9f} 100 0 0 100 0 1000\n" for k in range(15)]
    lines += [f"EDGE_SE2 {k} {k + 8} 0 0 0 100 0 0 100 0 1000\n" for k in range(8)]
    lines.append("EDGE_SE2 2 13 1.5 -0.5 0.3 100 0 0 100 0 1000\n")  # wrong
    src = tmp_path / "laps.g2o"
    src.write_text("".join(lines))
    for robust in ("gnc", "dcs"):
        out = tmp_path / f"{robust}.g2o"
        assert main(["graph", "optimize", str(src), "--out", str(out), "--robust", robust]) == 0
        text = capsys.readouterr().out
        assert f"robust kernel {robust} (" in text
        assert ("of which GNC" in text) == (robust == "gnc")
        assert "loops down-weighted by the optimiser: 1 of 9" in text
        r = np.linalg.norm(read_g2o(out).poses()[:, :2] - CENTRE, axis=1)
        assert np.allclose(r, 3.0, atol=1e-3)  # (GNC against DCS, exactly: tests/graph/test_batch.py)
