"""Drives recorded for the tests (the session's shared one: :func:`tests.conftest.recorded_square`)."""

from __future__ import annotations

import stat
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class RecordedDrive:
    """A demo drive recorded once for the whole session (read-only: copy what you change).

    ``recording``: the MCAP (PNG frames, lossless); ``live``: the demo's output folder
    (``map.sqlite``, the TUM files, ``summary.json``); ``summary``: the demo's summary (as
    read back from ``summary.json``); ``duration_s``: the robot time driven.
    """

    recording: Path
    live: Path
    summary: dict
    duration_s: float


def record_square(folder: Path, duration_s: float) -> None:
    """Drive the square route (seed 5) for ``duration_s`` with ``run_demo``, recorded
    lossless into ``folder/run.mcap``, its output in ``folder/live``; then make it all
    read-only and mark it ``done``."""
    from robotd.app.demo import run_demo
    from robotd.base.config import Config, replace

    run_demo(replace(Config(), "recording", image_format="png"), out=folder / "live",
             route="square", duration_s=duration_s, seed=5, plot=False, record=folder / "run.mcap")
    for p in folder.rglob("*"):  # (for a user other than root, a test writing into it fails)
        if p.is_file():
            p.chmod(stat.S_IRUSR | stat.S_IRGRP | stat.S_IROTH)
    (folder / "done").touch()
