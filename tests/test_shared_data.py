"""Published-result tests skip where ../shared/data is absent, but fail in CI."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.shared_data import SHARED_DATA, require


def test_a_missing_file_fails_in_ci_and_skips_elsewhere(monkeypatch: pytest.MonkeyPatch,
                                                        tmp_path: Path):
    missing = tmp_path / "absent.g2o"
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="a graph not found at .*absent.g2o"):
        require(missing, "a graph")
    monkeypatch.setenv("CI", "")
    with pytest.raises(pytest.skip.Exception, match="a graph not found"):
        require(missing, "a graph")
    assert require(tmp_path, "a folder") == tmp_path


def test_the_shared_data_is_where_the_tests_look():
    assert require(SHARED_DATA / "README.md", "the data's README").is_file()
