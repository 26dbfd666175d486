"""``bench/common.py``: the commit and the machine a benchmark's JSON records."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from bench.common import git_commit, machine_info


def test_an_exported_tree_records_the_commit_it_is_told(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path.parent))  # no repository above tmp_path
    monkeypatch.delenv("ROBOTD_GIT_COMMIT", raising=False)
    assert git_commit(tmp_path) is None
    monkeypatch.setenv("ROBOTD_GIT_COMMIT", "0123abc")
    assert git_commit(tmp_path) == "0123abc"


def test_a_work_tree_records_its_own_head_not_the_variable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROBOTD_GIT_COMMIT", "0123abc")
    env = {"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t",
           "PATH": "/usr/bin:/bin"}
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True, env=env)
    subprocess.run(["git", "commit", "-q", "--allow-empty", "-m", "x"], cwd=tmp_path, check=True, env=env)
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=tmp_path, check=True, capture_output=True,
                          text=True, env=env).stdout.strip()
    assert git_commit(tmp_path) == head


def test_the_machine_record_names_the_cpu_model_the_kernel_reports() -> None:
    try:
        lines = Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        pytest.skip("no /proc/cpuinfo")
    names = [ln.partition(":")[2].strip() for ln in lines
             if ln.partition(":")[0].strip() in ("model name", "Model") and ln.partition(":")[2].strip()]
    if not names:
        pytest.skip("/proc/cpuinfo names no model")
    assert machine_info()["cpu_model"] == names[0]
