"""A backend module for tests/drivers/test_base.py: importing it is observable."""

from __future__ import annotations

from typing import Any

from drivers.base import Driver


class _Named(Driver):
    def _read_internal(self, timeout_s: float) -> None:
        return None


def open_fake(section: Any, clock: Any) -> Driver:
    """A driver named after ``section`` (a string in the test)."""
    return _Named(section)
