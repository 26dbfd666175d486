"""The real data in ``../shared/data`` that tests compare with published results.

Outside the project's workspace the folder may be absent and those tests skip; in CI
(``CI=true``) a missing file is a failure, so a published-result check never passes by
skipping.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def in_ci() -> bool:
    """True when run by CI (``CI=true``, as .ci/run's caller sets it)."""
    return os.environ.get("CI", "").lower() in ("true", "1", "yes")


def require(path: Path, what: str) -> Path:
    """``path`` when it is there; otherwise a skip, or in CI a failure, naming ``what``."""
    if path.exists():
        return path
    message = f"{what} not found at {path} (../shared/data is absent)"
    if in_ci():
        pytest.fail(message, pytrace=False)
    pytest.skip(message)
