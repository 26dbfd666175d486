from __future__ import annotations

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "posegraphs"


@pytest.fixture
def posegraph_file():
    """Path of a shared benchmark graph, or a skip when ../shared is absent."""
    def get(name: str) -> Path:
        path = SHARED / name
        if not path.is_file():
            pytest.skip(f"shared benchmark graph {path} is absent (../shared/data not checked out)")
        return path
    return get
