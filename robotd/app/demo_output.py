"""The demo's output folder made safe to write: made and checked writable, and an earlier
demo's map in it replaced while anything else is refused and left as it is."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from robotd.base.errors import ConfigError, MapStoreError
from robotd.io.mapfile import read_meta

log = logging.getLogger(__name__)

DEMO_MAP_META = "demo"
"""The ``meta`` key that marks a map written by the demo, which the next demo into the
same folder may replace; any other file at ``OUT/map.sqlite`` is left alone."""


def prepare_output_folder(out: Path) -> None:
    """Make ``out`` (and its parents); ConfigError, naming it, when it is a file, cannot be
    made, or cannot be written."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output folder {out} exists and is not a folder (choose another --out)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create the output folder {out}: {exc.strerror or exc}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise ConfigError(f"output folder {out} is not writable (read-only file system or "
                          "permissions; choose another --out)")


def clear_previous_map(map_path: Path) -> None:
    """Remove an earlier demo's map at ``map_path`` (with its ``-wal``/``-shm``); refuse,
    leaving it untouched, anything else there: a foreign or damaged file, a robotd map not
    written by the demo (:data:`DEMO_MAP_META`)."""
    sidecars = [Path(str(map_path) + suffix) for suffix in ("-wal", "-shm")]
    if not map_path.exists():
        if any(p.exists() for p in sidecars):
            raise MapStoreError(f"{sidecars[0].name} or {sidecars[1].name} without their map is in "
                                f"{map_path.parent}; left as it is: move it away or choose another --out")
        return
    try:
        is_demo_map = map_path.is_file() and DEMO_MAP_META in read_meta(map_path)
    except MapStoreError as exc:
        raise MapStoreError(f"{map_path} is in the way and is not a demo map ({exc}); left as it "
                            "is: move it away or choose another --out") from None
    if not is_demo_map:
        raise MapStoreError(f"{map_path} is in the way: a robotd map without the demo's mark (not "
                            "written by the demo, or by a demo older than the mark); left as it "
                            "is: move it away or choose another --out")
    log.info("replacing the previous demo map %s", map_path)
    for stale in (map_path, *sidecars):
        stale.unlink(missing_ok=True)
