from __future__ import annotations

from pathlib import Path

import pytest

from tests.shared_data import require

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "posegraphs"


@pytest.fixture
def posegraph_file():
    """Path of a shared benchmark graph, or a skip when ../shared is absent."""
    def get(name: str) -> Path:
        return require(SHARED / name, "shared benchmark graph")
    return get
