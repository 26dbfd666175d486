"""The configuration reference in docs/ is generated from the config's own definitions."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from robotd.app.cli import config_reference
from robotd.app.reload import LIVE_KEYS
from robotd.base.config import Config

DOC = Path(__file__).resolve().parents[2] / "docs" / "configuration.md"


def test_the_docs_page_is_the_generated_reference():
    assert DOC.read_text() == config_reference(), (
        "docs/configuration.md is out of date: robotd config reference > docs/configuration.md")


def test_every_key_is_listed_once_with_its_default_and_liveness():
    text = config_reference()
    for section in dataclasses.fields(Config):
        assert text.count(f"## [{section.name}]\n") == 1
        part = text.split(f"## [{section.name}]\n")[1].split("\n## [")[0]
        for f in dataclasses.fields(section.default_factory):  # type: ignore[misc]
            (row,) = [line for line in part.splitlines() if line.startswith(f"| `{f.name}` |")]
            cells = [c.strip() for c in row.split("|")[1:-1]]
            assert cells[4] == ("yes" if (section.name, f.name) in LIVE_KEYS else ""), row
    assert "| `path` | string | `\"/var/lib/robotd/map.sqlite\"` | not empty |" in text
