"""The layer contracts of DESIGN.md hold, and breaking one fails the check."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LINT = Path(sys.executable).with_name("lint-imports")


def _lint(root: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(LINT), "--no-cache", "--config", str(root / "pyproject.toml")],
                          cwd=root, capture_output=True, text=True, timeout=120)


def _copy(tmp: Path) -> Path:
    root = tmp / "repo"
    for name in ("robotd", "drivers", "sim", "calibration"):
        shutil.copytree(REPO / name, root / name, ignore=shutil.ignore_patterns("__pycache__", "*.npz"))
    shutil.copy(REPO / "pyproject.toml", root / "pyproject.toml")
    return root


def test_the_tree_keeps_every_contract():
    r = _lint(REPO)
    assert r.returncode == 0, r.stdout[-3000:]
    assert "BROKEN" not in r.stdout and r.stdout.count("KEPT") == 5


def test_a_driver_importing_the_app_breaks_the_build(tmp_path: Path):
    root = _copy(tmp_path)
    camera = root / "drivers" / "camera.py"
    camera.write_text(camera.read_text() + "\nfrom robotd.app import daemon  # wrong on purpose\n")
    r = _lint(root)
    assert r.returncode == 1
    assert "drivers know only the base layer BROKEN" in r.stdout
    assert "drivers.camera -> robotd.app.daemon" in r.stdout


def test_the_base_layer_importing_an_algorithm_breaks_the_build(tmp_path: Path):
    root = _copy(tmp_path)
    geometry = root / "robotd" / "base" / "geometry.py"
    geometry.write_text(geometry.read_text() + "\n\ndef _late():\n    import robotd.floor.match  # noqa\n")
    r = _lint(root)
    assert r.returncode == 1
    assert "robotd layers: app > io > evaluation > algorithms (independent) > base BROKEN" in r.stdout
