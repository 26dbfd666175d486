"""The configuration reference in docs/ is generated from the config's own definitions."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from robotd.app.cli import config_reference
from robotd.base.config import Config, live_keys
from robotd.base.configfile import RENAMED, unit_of

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
            assert cells[2] == unit_of(f) and cells[5] == ("yes" if (section.name, f.name) in live_keys() else ""), row
    assert "| `path` | string |  | `\"/var/lib/robotd/map.sqlite\"` | not empty | yes |" not in text
    assert "| `path` | string |  | `\"/var/lib/robotd/map.sqlite\"` | not empty |  |" in text
    assert ("| `accel_noise_density_mps2_per_sqrt_hz` | number | m/s^2/sqrt(Hz) | `0.5` | 1e-06 to 100 |  |"
            in text)
    assert "| `distance_m` | number | m | `0.15` | 0.001 to 100 | yes |" in text
    for (old_sec, old_key), (new_sec, new_key) in RENAMED.items():
        assert f"| `[{old_sec}] {old_key}` | `[{new_sec}] {new_key}` |" in text


def test_the_docs_name_no_old_key():
    """After a rename the pages say the new name (the renamed table of the reference and
    CHANGELOG.md excepted)."""
    root = DOC.parents[1]
    pages = [p for p in (root / "docs").rglob("*.md") if p != DOC] + [
        root / "README.md", root / "systemd" / "README.md", root / "systemd" / "robotd.toml"]
    for page in pages:
        text = page.read_text()
        for old_sec, old_key in RENAMED:
            assert f"[{old_sec}] {old_key}" not in text, (page, old_sec, old_key)
            assert f"[{old_sec}]` `{old_key}`" not in text, (page, old_sec, old_key)
