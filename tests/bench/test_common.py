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


def test_a_repeated_map_grows_through_sizes_with_the_descriptors_in_order(tmp_path: Path) -> None:
    from bench.common import grow_repeated_map
    from robotd.io.store import MapStore

    blobs = [bytes([i]) * 8 for i in range(3)]
    ids: list[int] = []
    assert len(grow_repeated_map(tmp_path / "m.sqlite", blobs, 4, 4, ids)) == 4
    assert grow_repeated_map(tmp_path / "m.sqlite", blobs, 4, 7, ids) is ids and len(ids) == 7
    assert len(set(ids)) == 7
    with MapStore.open(tmp_path / "m.sqlite", create=False, read_only=True) as store:
        got = {r.id: (r.descriptor, r.descriptor_mode) for r in store.keyframes()}
    assert [got[i] for i in ids] == [(blobs[i % 3], 4) for i in range(7)]
